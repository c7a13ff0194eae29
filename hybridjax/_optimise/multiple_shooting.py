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
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float, PyTree

from .._definition.system import HybridSystem
from .._solution.solution import Solution


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
    and durations T_0 .. T_{k-1} of k epochs."""

    states: Float[Array, "k_minus_1 n"]
    durations: Float[Array, " k"]

    @classmethod
    def from_solution(cls, sol: Solution, k: int) -> "EpochGuess":
        """The first k epochs of an execution (its post-event states and event times)."""
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

    def epochs(self, params, guess: EpochGuess):
        """Event times and pre-event states of the epochs, and the guard and continuity defects."""
        args = self.args(params) if callable(self.args) else self.args
        x = self.x0(params) if callable(self.x0) else jnp.asarray(self.x0)
        t = jnp.asarray(self.t0, guess.durations.dtype)
        times, befores, defects = [], [], []
        for i, k in enumerate(self.transitions):
            mode = self.system.modes[self.system.sources[k]]
            tr = self.system.transitions[k]
            if i > 0:
                x = guess.states[i - 1, : mode.dim]
            t_end = t + guess.durations[i]
            x_end = rk4_flow(lambda s, y, f=mode.flow: f(s, y, args), t, t_end, x, self.substeps)
            defects.append(jnp.reshape(tr.guard(t_end, x_end, args), (1,)))
            if i + 1 < len(self.transitions):
                nxt = self.system.modes[self.system.targets[k]].dim
                defects.append(tr.reset(t_end, x_end, args) - guess.states[i, :nxt])
            times.append(t_end)
            befores.append(jnp.pad(x_end, (0, self.system.max_dim - mode.dim)))
            t = t_end
        return jnp.stack(times), jnp.stack(befores), jnp.concatenate(defects)

    def residuals(self, unknowns, _=None):
        params, guess = unknowns
        times, befores, defects = self.epochs(params, guess)
        return jnp.concatenate([defects, jnp.ravel(self.residual(params, times, befores))])


class MultipleShootingResult(eqx.Module):
    """What `multiple_shooting` returns: the parameters, the epochs (`EpochGuess` at the solution),
    the event times and pre-event states, the largest residual and optimistix's result."""

    params: PyTree
    epochs: EpochGuess
    event_times: Float[Array, " k"]
    states_before: Float[Array, "k n"]
    max_residual: Float[Array, ""]
    result: optx.RESULTS
    steps: Array


def multiple_shooting(
    problem: MultipleShooting,
    params0: PyTree,
    guess: EpochGuess,
    *,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 256,
) -> MultipleShootingResult:
    r"""Solve `problem` from `params0` and the epoch `guess` by nonlinear least squares:
    minimise $\tfrac12 \|r\|^2$ over (theta, z, T), r the guard, continuity and target residuals.

    `solver` defaults to `optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)`. A problem whose
    targets fix every unknown has residual 0 at its solution (a root of the residuals).
    """
    solver = solver or optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
    params0 = jax.tree_util.tree_map(lambda p: jnp.asarray(p, jnp.result_type(p, float)), params0)
    return _solve(problem, params0, guess, solver, max_steps)


@eqx.filter_jit
def _solve(problem, params0, guess, solver, max_steps):
    sol = optx.least_squares(problem.residuals, solver, (params0, guess), max_steps=max_steps, throw=False)
    params, epochs = sol.value
    times, befores, _ = problem.epochs(params, epochs)
    return MultipleShootingResult(params, epochs, times, befores,
                                  jnp.max(jnp.abs(problem.residuals(sol.value))), sol.result,
                                  sol.stats["num_steps"])
