"""Multiple shooting over the epochs of an execution with a given event sequence.

The unknowns are the parameters theta, the state z_i at the start of each epoch after the first,
and each epoch's duration T_i. Epoch i flows in the source mode of the i-th transition from
z_i (z_0 = x0(theta)) for T_i, reaching x_i^-; the residuals are

- the guard condition g_i(t_{i+1}, x_i^-) = 0 (the epoch ends on its transition's guard),
- continuity R_i(t_{i+1}, x_i^-) - z_{i+1} = 0 (the next epoch starts at the reset image),
- the user's residuals r(theta, times, states_before) (targets, boundary conditions),

solved together as one nonlinear least-squares problem with optimistix. Each epoch is a smooth
flow, so nothing in the residual is piecewise: the event sequence is fixed by construction (A. M.
Johnson, "Hybrid Dynamical Systems", section 3.6, for the execution this describes).

Two things keep the solver to executions. Each duration is T_i = tau_i softplus(u_i) / ln 2 > 0
in an unconstrained u_i (tau_i the guessed duration), and the guard residual of such an epoch is
deflated, g_i (1 + tau_i^2 / T_i^2), so that an epoch starting on its own guard (a ball just after
its bounce) cannot meet it as T_i -> 0 (P. E. Farrell, A. Birkisson, S. W. Funke, "Deflation
techniques for finding distinct solutions of nonlinear partial differential equations", SIAM J.
Sci. Comput. 37(4), 2015: their operator 1 / |T|^p + sigma with p = 2 and sigma = 1 / tau_i^2,
scaled by tau_i^2, deflating the spurious root T_i = 0). An epoch whose guessed duration is 0 is
held at zero length: the engine's start rule (execution rule 3) fires its transition at once.
A solution is then checked against a forward `simulate` from the found parameters (same
transitions, same event times), and a failed round restarts from that forward execution.
"""

from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, PyTree

from .._core.names import one_of
from .._definition.system import HybridSystem
from .._solution.solution import Solution
from .._solve.simulate import simulate


def rk4_flow(flow: Callable, t_a, t_b, x, substeps: int):
    """x(t_b) for dx/dt = flow(t, x) from x(t_a) = x, by `substeps` classical RK4 steps
    (t_b < t_a integrates backward). Smooth in (t_a, t_b, x): a flow map to differentiate."""
    h = (t_b - t_a) / substeps

    def step(x, i):
        t = t_a + i * h
        k1 = flow(t, x)
        k2 = flow(t + h / 2, x + h / 2 * k1)
        k3 = flow(t + h / 2, x + h / 2 * k2)
        k4 = flow(t + h, x + h * k3)
        return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4), None

    return jax.lax.scan(step, x, jnp.arange(substeps))[0]


class EpochGuess(eqx.Module):
    """Starting states z_1 .. z_{k-1} (each in its epoch's mode dimension, padded to the largest)
    and durations T_0 .. T_{k-1} >= 0 of k epochs. `multiple_shooting` holds an epoch guessed at
    duration 0 at zero length (one whose transition the simulation fires at its start)."""

    states: Float[Array, "k_minus_1 n"]
    durations: Float[Array, " k"]

    @classmethod
    def from_solution(cls, sol: Solution, k: int) -> "EpochGuess":
        """The first k epochs of an execution (its post-event states and event times); an epoch
        the execution left at once has duration 0."""
        times = jnp.concatenate([jnp.reshape(sol.t0, (1,)), sol.event_times[:k]])
        return cls(sol.states_after[: k - 1], jnp.diff(times))


class MultipleShooting(eqx.Module):
    r"""A multiple-shooting problem over the k epochs ended by `transitions` (in order).

    **Arguments:**

    - `system`: the `HybridSystem`; `transitions`: the event sequence, transition indices or
      `Transition`s, each leaving the mode the previous one enters.
    - `x0`: the initial state, a value or a function of the parameters; `t0`: the start time.
    - `args`: a value or a function of the parameters.
    - `residual`: `residual(params, times, states_before) -> array`, the targets: `times` (k,) are
      the event times and `states_before` (k, n) the states just before each event.
    - `substeps`: RK4 steps per epoch.

    !!! Example

        ```python
        problem = hj.MultipleShooting(ball, (0, 0, 0), x0=launch, args=args,
                                      residual=lambda v, ts, xs: xs[-1, :1] - 4.0)   # 3rd impact at x = 4
        result = hj.multiple_shooting(problem, v_guess, hj.EpochGuess.from_solution(sol, 3))
        result.success, result.reason   # checked against a forward simulate from result.params
        ```
    """

    system: HybridSystem
    transitions: tuple[int, ...] = eqx.field(static=True)
    x0: Any
    residual: Callable
    t0: Any = 0.0
    args: Any = None
    substeps: int = eqx.field(static=True, default=32)

    def __init__(self, system, transitions, x0, residual, *, t0=0.0, args=None, substeps=32):
        ks = tuple(system.transition_index(tr) for tr in transitions)
        if not ks:
            raise ValueError("MultipleShooting: give at least one transition.")
        for a, b in zip(ks, ks[1:], strict=False):
            if system.targets[a] != system.sources[b]:
                raise ValueError(
                    f"MultipleShooting: transition {b} ({system.transitions[b].label}) does not leave the "
                    f"mode that transition {a} ({system.transitions[a].label}) enters.")
        self.system, self.transitions, self.x0, self.residual = system, ks, x0, residual
        self.t0, self.args, self.substeps = t0, args, substeps

    def flow_epochs(self, params, states, durations):
        """Event times (k,), pre-event states (k, n), guard values g_i(t_{i+1}, x_i^-) (k,)
        and continuity defects (one block per epoch after the first, concatenated) of the
        epochs from the starting states z_1 .. z_{k-1} and the durations."""
        args = self.args(params) if callable(self.args) else self.args
        x = self.x0(params) if callable(self.x0) else jnp.asarray(self.x0)
        t = jnp.asarray(self.t0, durations.dtype)
        times, befores, guards, continuity = [], [], [], []
        for i, k in enumerate(self.transitions):
            mode = self.system.modes[self.system.sources[k]]
            tr = self.system.transitions[k]
            if i > 0:
                x = states[i - 1, : mode.dim]
            t_end = t + durations[i]
            x_end = rk4_flow(lambda s, y, f=mode.flow: f(s, y, args), t, t_end, x, self.substeps)
            guards.append(jnp.reshape(tr.guard(t_end, x_end, args), ()))
            if i + 1 < len(self.transitions):
                nxt = self.system.modes[self.system.targets[k]].dim
                continuity.append(tr.reset(t_end, x_end, args) - states[i, :nxt])
            times.append(t_end)
            befores.append(jnp.pad(x_end, (0, self.system.max_dim - mode.dim)))
            t = t_end
        cont = jnp.concatenate(continuity) if continuity else jnp.zeros((0,), durations.dtype)
        return jnp.stack(times), jnp.stack(befores), jnp.stack(guards), cont

    def epochs(self, params, guess: EpochGuess):
        """Event times and pre-event states of the epochs, and the guard and continuity defects
        (each epoch's guard value followed by its continuity defect)."""
        times, befores, guards, cont = self.flow_epochs(params, guess.states, guess.durations)
        defects, j = [], 0
        for i, k in enumerate(self.transitions):
            defects.append(guards[i : i + 1])
            if i + 1 < len(self.transitions):
                nxt = self.system.modes[self.system.targets[k]].dim
                defects.append(cont[j : j + nxt])
                j += nxt
        return times, befores, jnp.concatenate(defects)

    def residuals(self, unknowns, _=None):
        """The guard and continuity defects and the targets at `unknowns = (params, guess)`."""
        params, guess = unknowns
        times, befores, defects = self.epochs(params, guess)
        return jnp.concatenate([defects, jnp.ravel(self.residual(params, times, befores))])

    @property
    def mode0(self) -> int:
        """The mode of the first epoch: the source of the first transition."""
        return self.system.sources[self.transitions[0]]


class MultipleShootingStatus(eqx.Enumeration):
    """Whether `multiple_shooting` found an execution, and if not, why not (the first reason in
    this order, from the bottom up: a failed solve is reported before a large residual, which is
    reported before a disagreement with the forward `simulate`).
    `hj.MultipleShootingStatus[result.status]` (or `result.reason`) is the message."""

    SUCCESSFUL = ("The residuals vanish and a forward `simulate` from the found parameters takes the "
                  "same transitions at the same event times.")
    SOLVER_FAILED = "The least-squares solver did not converge (`result` says how)."
    RESIDUAL_TOO_LARGE = ("The largest residual exceeds `check.residual_tol`: no execution with this "
                          "event sequence meets the targets near the solver's stopping point.")
    FEWER_EVENTS = ("A forward `simulate` from the found parameters takes fewer transitions than the "
                    "event sequence by the last event time (`execution.status` says why it stopped).")
    OTHER_TRANSITIONS = ("A forward `simulate` from the found parameters takes other transitions than "
                         "the event sequence (an epoch crosses another guard, or its own, earlier).")
    EVENT_TIMES_DIFFER = ("A forward `simulate` from the found parameters takes the same transitions at "
                          "event times more than `check.time_atol + check.time_rtol (t_k - t0)` apart.")


class MultipleShootingCheck(eqx.Module):
    r"""How `multiple_shooting` checks a solution: the largest residual is at most
    `residual_tol`, and a forward `simulate` from the found parameters (with `solver`,
    `stepsize_controller` and `max_steps`) takes the event sequence's k transitions, in order,
    at event times within `time_atol + time_rtol (t_k - t0)` of the epochs'.

    The tolerances allow for the RK4 flow of the epochs (`MultipleShooting.substeps`) and the
    simulation's own: a flow that RK4 integrates exactly (polynomial of degree <= 4 in t)
    agrees to rounding and the simulation's tolerance.
    """

    residual_tol: float = 1e-8
    time_rtol: float = 1e-6
    time_atol: float = 1e-9
    solver: diffrax.AbstractSolver = diffrax.Tsit5()
    stepsize_controller: diffrax.AbstractStepSizeController = diffrax.PIDController(rtol=1e-10, atol=1e-10)
    max_steps: int = eqx.field(static=True, default=4096)

    def __check_init__(self):
        for name in ("residual_tol", "time_rtol", "time_atol"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not value >= 0:
                raise ValueError(f"MultipleShootingCheck: {name} must be a number >= 0, got {value!r}.")
        if not isinstance(self.solver, diffrax.AbstractSolver):
            raise TypeError(f"MultipleShootingCheck: solver must be a diffrax solver, got {self.solver!r}.")
        if not isinstance(self.stepsize_controller, diffrax.AbstractStepSizeController):
            raise TypeError("MultipleShootingCheck: stepsize_controller must be a diffrax step-size "
                            f"controller, got {self.stepsize_controller!r}.")
        if isinstance(self.max_steps, bool) or not isinstance(self.max_steps, int) or self.max_steps < 1:
            raise ValueError(f"MultipleShootingCheck: max_steps must be an int >= 1, got {self.max_steps!r}.")


class MultipleShootingResult(eqx.Module):
    """What `multiple_shooting` returns: the parameters, the epochs (`EpochGuess` at the solution,
    every duration > 0 except those held at zero length), the event times and pre-event states
    of the epochs, the largest residual, optimistix's result and step count, the check's
    `status` (a `MultipleShootingStatus`), the forward `simulate` it compared with
    (`execution`, a `Solution` padded to k + 1 events), and how many restarts it took.
    `steps` counts the solver's steps over all rounds.

    `success` is `status == MultipleShootingStatus.SUCCESSFUL`; `reason` the status's message.
    """

    params: PyTree
    epochs: EpochGuess
    event_times: Float[Array, " k"]
    states_before: Float[Array, "k n"]
    max_residual: Float[Array, ""]
    result: optx.RESULTS
    steps: Array
    status: MultipleShootingStatus
    execution: Solution
    restarts: Array

    @property
    def success(self) -> Bool[Array, ""]:
        return self.status == MultipleShootingStatus.SUCCESSFUL

    @property
    def reason(self) -> str:
        return MultipleShootingStatus[self.status]


def multiple_shooting(
    problem: MultipleShooting,
    params0: PyTree,
    guess: EpochGuess,
    *,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    iterations: int | None = None,
    check: MultipleShootingCheck | None = None,
    restarts: int = 3,
    max_steps: int | None = None,
) -> MultipleShootingResult:
    r"""Solve `problem` from `params0` and the epoch `guess` by nonlinear least squares:
    minimise $\tfrac12 \|r\|^2$ over $(\theta, z, u)$, $r$ the deflated guard, continuity and
    target residuals. Each duration is $T_i = \tau_i\,\mathrm{softplus}(u_i) / \ln 2 > 0$
    ($\tau_i$ the guessed duration, $u_i = 0$ at the guess), and each guard residual is
    $g_i\,(1 + \tau_i^2 / T_i^2)$: the roots of $g_i$ at $T_i > 0$, and none as $T_i \to 0$ for an
    epoch that starts on its guard and leaves it ($\dot g_i \neq 0$), where $g_i \approx \dot g_i T_i$.

    `guess.durations` must be known (not traced) and $\ge 0$: an epoch guessed at 0 (as
    `EpochGuess.from_solution` gives where the simulation fired a transition at the start of an
    epoch, execution rule 3) is held at zero length, its guard left to the check.

    The result's `status` is `SUCCESSFUL` only if the solver converged, the largest residual is
    within `check.residual_tol`, and a forward `simulate` from the found parameters takes the
    same k transitions at the same event times (`MultipleShootingCheck`); otherwise it says why
    not. A round that fails while that forward execution takes the k transitions (later or
    earlier than the epochs) is restarted from it: its epochs (`EpochGuess.from_solution`) and
    the round's parameters, up to `restarts` times (`result.restarts` counts them).

    `solver` defaults to `optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)`, with `iterations`
    steps a round (default 256; `max_steps`, optimistix's name, is a shorthand). A problem
    whose targets fix every unknown has residual 0 at its solution.
    """
    iterations = one_of("multiple_shooting", iterations=iterations, max_steps=max_steps, default=256)
    solver = solver or optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
    check = MultipleShootingCheck() if check is None else check
    if not isinstance(check, MultipleShootingCheck):
        raise TypeError("multiple_shooting: check must be a MultipleShootingCheck, "
                        f"got {type(check).__name__}.")
    if isinstance(restarts, bool) or not isinstance(restarts, int) or restarts < 0:
        raise ValueError(f"multiple_shooting: restarts must be an int >= 0, got {restarts!r}.")
    k = len(problem.transitions)
    zero = _zero_length(guess, k)
    params = jax.tree_util.tree_map(lambda p: jnp.asarray(p, jnp.result_type(p, float)), params0)
    steps = 0
    for restart in range(restarts + 1):
        result = _solve(problem, params, guess, solver, iterations, zero, check)
        steps = steps + result.steps
        ex = result.execution
        if bool(result.success) or restart == restarts or int(ex.num_events) < k or not np.array_equal(
                np.asarray(ex.transitions[:k]), problem.transitions):
            break
        params, guess = result.params, EpochGuess.from_solution(ex, k)
        zero = _zero_length(guess, k)
    return eqx.tree_at(lambda r: (r.steps, r.restarts), result, (steps, jnp.asarray(restart)))


def _zero_length(guess, k) -> tuple[bool, ...]:
    """Which epochs `guess` holds at zero length (duration 0), checking its durations."""
    try:
        durations = np.asarray(guess.durations, dtype=float)
    except jax.errors.TracerArrayConversionError:
        raise TypeError("multiple_shooting: guess.durations must be known values (not traced inside "
                        "jax.jit or jax.vmap): the epochs guessed at 0 are held at zero length.") from None
    if durations.shape != (k,):
        raise ValueError(f"multiple_shooting: guess.durations must have shape ({k},) for {k} transitions, "
                         f"got {durations.shape}.")
    if not np.all(np.isfinite(durations)) or np.any(durations < 0):
        raise ValueError(f"multiple_shooting: guess.durations must be finite and >= 0, got {durations} "
                         "(inf or nan where the solution the guess came from has fewer than k events).")
    return tuple(bool(d == 0) for d in durations)


def _durations(u, tau, zero):
    """T = tau softplus(u) / ln 2 (T = tau at u = 0), and 0 for the epochs held at zero length."""
    return jnp.where(jnp.asarray(zero), 0.0, tau * jax.nn.softplus(u) / jnp.log(2.0))


def _flowing(zero):
    return np.flatnonzero(~np.asarray(zero, dtype=bool))


@eqx.filter_jit
def _solve(problem, params0, guess, solver, iterations, zero, check):
    tau = jnp.where(jnp.asarray(zero), 1.0, guess.durations)
    flowing = _flowing(zero)

    def parts(params, states, T):
        times, befores, guards, cont = problem.flow_epochs(params, states, T)
        targets = jnp.ravel(problem.residual(params, times, befores))
        return times, befores, guards[flowing], cont, targets

    def deflated(unknowns, _):
        params, states, u = unknowns
        T = _durations(u, tau, zero)
        _, _, guards, cont, targets = parts(params, states, T)
        return jnp.concatenate([guards * (1 + (tau[flowing] / T[flowing]) ** 2), cont, targets])

    y0 = (params0, guess.states, jnp.zeros_like(guess.durations))
    sol = optx.least_squares(deflated, solver, y0, max_steps=iterations, throw=False)
    params, states, u = sol.value
    epochs = EpochGuess(states, _durations(u, tau, zero))
    times, befores, guards, cont, targets = parts(params, states, epochs.durations)
    max_residual = jnp.max(jnp.abs(jnp.concatenate([guards, cont, targets])), initial=0.0)
    horizon = jnp.maximum(times[-1] - problem.t0, jnp.sum(guess.durations))
    status, execution = _check(problem, params, times, horizon, max_residual, sol.result, check)
    return MultipleShootingResult(params, epochs, times, befores, max_residual, sol.result,
                                  sol.stats["num_steps"], status, execution, jnp.asarray(0))


def _check(problem, params, times, horizon, max_residual, result, check):
    """The status of a solution (`MultipleShootingStatus`) and the forward `simulate` from its
    parameters, run to `horizon` (the longer of t_k - t0 and the guessed epochs' total) past
    the last event time t_k, and at least the time tolerance past it, for at most k + 1
    events: long enough to see events that come later than the epochs', from which
    `multiple_shooting` restarts."""
    S = MultipleShootingStatus
    k = len(problem.transitions)
    args = problem.args(params) if callable(problem.args) else problem.args
    x0 = problem.x0(params) if callable(problem.x0) else jnp.asarray(problem.x0)
    t0 = jnp.asarray(problem.t0, times.dtype)
    tol = check.time_atol + check.time_rtol * jnp.abs(times[-1] - t0)
    finite = jnp.all(jnp.isfinite(times)) & jnp.isfinite(max_residual)
    t1 = jnp.where(finite, times[-1] + horizon + 2 * tol, t0)
    execution = simulate(problem.system, x0, problem.mode0, t0, t1, args, solver=check.solver,
                         stepsize_controller=check.stepsize_controller, max_epochs=k + 1,
                         max_steps=check.max_steps, zeno=False)
    same_transitions = jnp.all(execution.transitions[:k] == jnp.asarray(problem.transitions))
    same_times = jnp.all(jnp.abs(execution.event_times[:k] - times) <= tol)
    status = S.where(same_times, S.SUCCESSFUL, S.EVENT_TIMES_DIFFER)
    status = S.where(same_transitions, status, S.OTHER_TRANSITIONS)
    status = S.where(execution.num_events >= k, status, S.FEWER_EVENTS)
    status = S.where(finite & (max_residual <= check.residual_tol), status, S.RESIDUAL_TOO_LARGE)
    status = S.where(result == optx.RESULTS.successful, status, S.SOLVER_FAILED)
    return status, execution
