"""Hybrid iLQR: iterative LQR through events, with saltation matrices.

N. J. Kong, G. Council, A. M. Johnson, "iLQR for piecewise-smooth hybrid dynamical systems",
IEEE CDC 2021 (arXiv:2103.14584). Controls u_0 .. u_{N-1} are held constant on the intervals of
a time grid t_0 < ... < t_N; the discrete dynamics x_{k+1} = f_k(x_k, u_k) is one hybrid
execution over [t_k, t_{k+1}] (`simulate`, the control in `args`). Where an event falls inside
an interval, its linearisation is the chain

    A_k = Phi_2 Xi Phi_1,   B_k = Phi_2 Xi B_1 + B_2,

Phi_i, B_i the flow's state-transition and control sensitivities before and after the event
and Xi the saltation matrix (A. M. Johnson, "Hybrid Dynamical Systems", section 3.6). The
backward pass is the LQR Riccati recursion on (A_k, B_k); the forward pass rolls the hybrid
system out under u = u_k + alpha d_k + K_k (x - xbar_k). Where the new rollout has taken one
event more or fewer than the nominal one by t_k, xbar_k and K_k come from the *reference
extension*: the nominal trajectory continued past its event in the old mode's flow (the new
rollout is late) or the post-event trajectory integrated back before it (the new rollout is
early), with the gain of the last knot before, or the first knot after, that event.
"""

from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._analysis.saltation import saltation_matrix
from .._core.checks import check_int
from .._core.names import bounds_of, one_of
from .._definition.system import HybridSystem
from .._optimise.multiple_shooting import rk4_flow
from .._solve.simulator import Simulator, simulator_of


class HybridILQR(eqx.Module):
    r"""A tracking problem for `hybrid_ilqr` (`hj.HybridLQRProblem` is another name for it): minimise

    $J = \sum_{k<N} \tfrac12 (x_k - r_k)^T Q (x_k - r_k) + \tfrac12 u_k^T R u_k
    + \tfrac12 (x_N - r_N)^T Q_f (x_N - r_N)$

    over controls $u_k$ held constant on $[t_k, t_{k+1})$ of the grid `ts`, subject to the hybrid
    dynamics from `x0` in `mode0`.

    **Arguments:**

    - `system`: a `HybridSystem` whose modes all have the same dimension n, and whose guards and
      resets do not read the control (flows do).
    - `control_args`: `control_args(u) -> args` for a control value u of shape (m,); the
      system's functions read u from these `args`.
    - `x0`, `mode0`: the initial state and mode.
    - `ts` (N + 1,): the time grid.
    - `reference` (N + 1, n): the states r_k to track; `Q`, `R`, `Qf`: the weights.
    - `bounds`: optional `(lower, upper)` control bounds (scalars or (m,) arrays, None for no
      bound on that side); the rollout clips the controls to them.
    - `simulator`: an `hj.Simulator`, how each interval's execution is computed. Its
      `max_epochs` is the most events one interval may hold (it also sizes the linearisation's
      chain of flow segments). Default: `hj.Simulator(stepsize_controller=diffrax.PIDController(
      rtol=1e-10, atol=1e-10), max_epochs=2)`.
    - `substeps`: RK4 steps per flow segment for the linearisations and the reference
      extensions. These segments are iLQR's own fixed-step discretisation, differentiated by
      AD, not executions: the simulator does not compute them.

    **Keyword shorthands** (pass a name or its shorthands, not both: a `ValueError` names both;
    an unknown keyword is a `TypeError` naming it):

    - `lower`, `upper`: `bounds=(lower, upper)`.
    - `max_epochs` (2; `max_events` is the same option), `stepsize_controller` (the
      PIDController above) and `simulate`'s other keywords: `simulator=hj.Simulator(...)` with
      these settings.

    !!! Example

        ```python
        problem = hj.HybridILQR(ball, lambda u: {"g": 9.8, "e": 0.8, "u": u[0]},
                                      x0, "flight", ts, reference, Q, R, Qf, bounds=(-5.0, 5.0))
        result = hj.hybrid_ilqr(problem, jnp.zeros((len(ts) - 1, 1)), iterations=20)
        ```
    """

    system: HybridSystem
    control_args: Callable
    x0: Float[Array, " n"]
    mode0: int = eqx.field(static=True)
    ts: Float[Array, " N+1"]
    reference: Float[Array, "N+1 n"]
    Q: Float[Array, "n n"]
    R: Float[Array, "m m"]
    Qf: Float[Array, "n n"]
    bounds: tuple[Any, Any]
    simulator: Simulator
    substeps: int = eqx.field(static=True)  # static: the RK4 scan's length

    def __init__(
        self,
        system: HybridSystem,
        control_args: Callable,
        x0: Float[ArrayLike, " n"],
        mode0: str | int,
        ts: Float[ArrayLike, " N+1"],
        reference: Float[ArrayLike, "N+1 n"],
        Q: Float[ArrayLike, "n n"],
        R: Float[ArrayLike, "m m"],
        Qf: Float[ArrayLike, "n n"],
        *,
        bounds: tuple[Any, Any] | None = None,
        simulator: Simulator | None = None,
        substeps: int = 8,
        **shorthands,
    ):
        dims = {m.dim for m in system.modes}
        if len(dims) != 1:
            raise ValueError("HybridILQR: every mode needs the same state dimension, got "
                             f"{sorted(dims)}.")
        n = dims.pop()
        ts = jnp.asarray(ts, float)
        reference = jnp.asarray(reference, float)
        if ts.ndim != 1 or ts.shape[0] < 2 or not bool(jnp.all(jnp.diff(ts) > 0)):
            raise ValueError("HybridILQR: ts must be an increasing 1-D grid of at least 2 times.")
        if reference.shape != (ts.shape[0], n):
            raise ValueError(f"HybridILQR: reference has shape {reference.shape}, expected "
                             f"{(ts.shape[0], n)} (one state per grid time).")
        check_int("HybridILQR", "substeps", substeps, 1)
        bounds = bounds_of("HybridILQR", bounds, shorthands)
        max_events = shorthands.pop("max_events", None)  # max_epochs under its other name
        if max_events is not None:
            if simulator is not None:
                raise ValueError("HybridILQR: simulator=hj.Simulator(...) holds the run's settings: "
                                 "pass max_events there (as max_epochs), not beside it.")
            shorthands["max_epochs"] = one_of("HybridILQR", max_epochs=shorthands.get("max_epochs"),
                                              max_events=max_events, default=None)
        simulator = simulator_of("HybridILQR", simulator, shorthands, defaults={
            "stepsize_controller": diffrax.PIDController(rtol=1e-10, atol=1e-10), "max_epochs": 2})
        self.system, self.control_args = system, control_args
        self.x0, self.mode0 = jnp.asarray(x0, float), system.mode_index(mode0)
        self.ts, self.reference = ts, reference
        self.Q, self.R, self.Qf = (jnp.atleast_2d(jnp.asarray(w, float)) for w in (Q, R, Qf))
        self.bounds, self.simulator, self.substeps = bounds, simulator, substeps

    # The bounds' sides and the simulator's settings, readable under their shorthands' names.
    @property
    def lower(self) -> Any:
        return self.bounds[0]

    @property
    def upper(self) -> Any:
        return self.bounds[1]

    @property
    def max_epochs(self) -> int:
        """The most events one interval may hold (the simulator's `max_epochs`)."""
        return self.simulator.options.max_epochs

    @property
    def max_events(self) -> int:
        """`max_epochs` under its other name."""
        return self.max_epochs

    @property
    def stepsize_controller(self) -> diffrax.AbstractStepSizeController | None:
        return self.simulator.stepsize_controller

    # ------------------------------------------------------------------ pieces

    def interval(self, x, mode, u, t_a, t_b):
        """One interval of the discrete dynamics: the hybrid execution over [t_a, t_b]."""
        return self.simulator(self.system, x, mode, t_a, t_b, self.control_args(u))

    def clip(self, u):
        """`u` clipped to `bounds` (unchanged without bounds)."""
        if self.lower is None and self.upper is None:
            return u
        return jnp.clip(u, self.lower, self.upper)

    def flow(self, mode, t, x, u):
        args = self.control_args(u)
        return jax.lax.switch(mode, [lambda t, x, m=m: jnp.asarray(m.flow(t, x, args), x.dtype)
                                     for m in self.system.modes], t, x)

    def segment(self, mode, t_a, t_b, x, u):
        """The flow of `mode` from (t_a, x) to t_b (t_b < t_a integrates backward), by RK4."""
        return rk4_flow(lambda t, x: self.flow(mode, t, x, u), t_a, t_b, x, self.substeps)

    def saltation(self, transition, t, x, u):
        args = self.control_args(u)
        return jax.lax.switch(transition, [lambda t, x, k=k: saltation_matrix(self.system, k, t, x, args)
                                           for k in range(self.system.num_transitions)], t, x)

    def cost(self, xs, us):
        dx = xs - self.reference
        run = 0.5 * jnp.einsum("ki,ij,kj->", dx[:-1], self.Q, dx[:-1]) + 0.5 * jnp.einsum(
            "ki,ij,kj->", us, self.R, us)
        return run + 0.5 * dx[-1] @ self.Qf @ dx[-1]


class _Rollout(eqx.Module):
    xs: Array  # (N+1, n) states at the grid times
    modes: Array  # (N+1,)
    us: Array  # (N, m) controls applied
    counts: Array  # (N+1,) events taken by t_k
    event_times: Array  # (N, E)
    transitions: Array  # (N, E)
    before: Array  # (N, E, n)
    after: Array  # (N, E, n)
    event_modes: Array  # (N, E + 1) mode of each epoch of each interval
    num_events: Array  # (N,)
    status: Array  # (N,)
    cost: Array


def _record(problem, sol):
    return (sol.final_state, sol.final_mode, sol.num_events, sol.event_times, sol.transitions,
            sol.states_before, sol.states_after, sol.epoch_modes, sol.status_code)


def _rollout(problem: HybridILQR, policy) -> _Rollout:
    """Roll the hybrid system out on the grid, u_k = policy(k, x_k, events so far)."""

    def step(carry, k):
        x, mode, count = carry
        u = problem.clip(policy(k, x, count))
        fx, fm, ne, et, tr, sb, sa, em, st = _record(
            problem, problem.interval(x, mode, u, problem.ts[k], problem.ts[k + 1]))
        return (fx, fm, count + ne), (x, mode, count, u, et, tr, sb, sa, em, ne, st)

    (xN, mN, cN), (xs, modes, counts, us, et, tr, sb, sa, em, ne, st) = jax.lax.scan(
        step, (problem.x0, jnp.asarray(problem.mode0), jnp.asarray(0)), jnp.arange(problem.ts.shape[0] - 1))
    xs = jnp.concatenate([xs, xN[None]])
    return _Rollout(xs, jnp.append(modes, mN), us, jnp.append(counts, cN), et, tr, sb, sa, em, ne, st,
                    problem.cost(xs, us))


def _linearise_interval(problem: HybridILQR, roll: _Rollout, k):
    """(A_k, B_k): flow segments by AD of RK4, joined at each event by its saltation matrix."""
    n, m = problem.x0.shape[0], roll.us.shape[1]
    u, t_a, t_b = roll.us[k], problem.ts[k], problem.ts[k + 1]
    A, B = jnp.eye(n), jnp.zeros((n, m))
    x, t = roll.xs[k], t_a
    for e in range(problem.max_epochs + 1):
        has_event = e < roll.num_events[k]
        active = e <= roll.num_events[k]
        t_end = jnp.where(has_event, roll.event_times[k, e] if e < problem.max_epochs else t_b, t_b)
        t_end = jnp.where(active, t_end, t)
        mode = jnp.maximum(roll.event_modes[k, e], 0)
        Phi, Bu = jax.jacfwd(lambda x, u: problem.segment(mode, t, t_end, x, u), argnums=(0, 1))(x, u)
        A, B = Phi @ A, Phi @ B + Bu
        if e < problem.max_epochs:
            tr = jnp.maximum(roll.transitions[k, e], 0)
            xb = jnp.where(has_event, roll.before[k, e], x)
            Xi = problem.saltation(tr, t_end, xb, u)
            A, B = jnp.where(has_event, Xi @ A, A), jnp.where(has_event, Xi @ B, B)
            x = jnp.where(has_event, roll.after[k, e], x)
            t = t_end
    return A, B


def linearise(problem: HybridILQR, rollout: "_Rollout"):
    """(A_k, B_k) for every interval of a rollout (vmapped over k)."""
    N = problem.ts.shape[0] - 1
    return jax.vmap(lambda k: _linearise_interval(problem, rollout, k))(jnp.arange(N))


def _backward(problem: HybridILQR, roll: _Rollout, A, B, mu):
    """The Riccati recursion of iLQR: feedforward d_k and gains K_k, and the expected decrease."""
    dx = roll.xs - problem.reference
    Vx, Vxx = problem.Qf @ dx[-1], problem.Qf
    m = B.shape[-1]

    def step(carry, inp):
        Vx, Vxx = carry
        A_k, B_k, dx_k, u_k = inp
        Qx = problem.Q @ dx_k + A_k.T @ Vx
        Qu = problem.R @ u_k + B_k.T @ Vx
        Qxx = problem.Q + A_k.T @ Vxx @ A_k
        Quu = problem.R + B_k.T @ Vxx @ B_k + mu * jnp.eye(m)
        Qux = B_k.T @ Vxx @ A_k
        d = -jnp.linalg.solve(Quu, Qu)
        K = -jnp.linalg.solve(Quu, Qux)
        Vx = Qx + K.T @ Quu @ d + K.T @ Qu + Qux.T @ d
        Vxx = Qxx + K.T @ Quu @ K + K.T @ Qux + Qux.T @ K
        return (Vx, 0.5 * (Vxx + Vxx.T)), (d, K, d @ Qu)

    _, (d, K, dV) = jax.lax.scan(step, (Vx, Vxx), (A, B, dx[:-1], roll.us), reverse=True)
    return d, K, jnp.sum(dV)


def _extensions(problem: HybridILQR, roll: _Rollout, K):
    """For each knot t_k, the nominal trajectory extended across its nearest events:
    `late` (continued past the last event before t_k in its pre-event mode, for a rollout that
    has not taken it yet) and `early` (the state after the next event integrated back to t_k in
    the post-event mode, for a rollout that has taken it already), with their gains."""
    N, E = roll.event_times.shape
    times = roll.event_times.reshape(-1)
    valid = (jnp.arange(E)[None, :] < roll.num_events[:, None]).reshape(-1)
    times = jnp.where(valid, times, jnp.inf)
    before, after = roll.before.reshape(N * E, -1), roll.after.reshape(N * E, -1)
    mode_before = roll.event_modes[:, :-1].reshape(-1)
    mode_after = roll.event_modes[:, 1:].reshape(-1)
    interval = jnp.repeat(jnp.arange(N), E)
    us = roll.us

    def at(k):
        t_k = problem.ts[k]
        # last event at or before t_k, next event after it (indices into the flat event list)
        last = jnp.argmax(jnp.where(times <= t_k, times, -jnp.inf))
        has_last = jnp.any(times <= t_k)
        nxt = jnp.argmin(jnp.where(times > t_k, times, jnp.inf))
        has_next = jnp.any((times > t_k) & jnp.isfinite(times))
        u_last = us[interval[last]]
        late = problem.segment(jnp.maximum(mode_before[last], 0), jnp.where(has_last, times[last], t_k), t_k,
                               before[last], u_last)
        u_next = us[interval[nxt]]
        early = problem.segment(jnp.maximum(mode_after[nxt], 0), jnp.where(has_next, times[nxt], t_k), t_k,
                                after[nxt], u_next)
        K_late = jnp.where(has_last, K[interval[last]], 0.0)
        after_knot = jnp.minimum(interval[nxt] + 1, N - 1)
        K_early = jnp.where(has_next & (interval[nxt] + 1 < N), K[after_knot], 0.0)
        return late, K_late, early, K_early

    return jax.vmap(at)(jnp.arange(N))


def _policy(problem, nominal: _Rollout, d, K, ext, alpha):
    late, K_late, early, K_early = ext

    def policy(k, x, count):
        nom = nominal.counts[k]
        same, is_late, is_early = count == nom, count == nom - 1, count == nom + 1
        xbar = jnp.where(same, nominal.xs[k], jnp.where(is_late, late[k], jnp.where(is_early, early[k],
                                                                                   nominal.xs[k])))
        gain = jnp.where(same, K[k], jnp.where(is_late, K_late[k], jnp.where(is_early, K_early[k], 0.0)))
        return nominal.us[k] + alpha * d[k] + gain @ (x - xbar)

    return policy


@eqx.filter_jit
def _initial(problem: HybridILQR, us):
    return _rollout(problem, lambda k, x, count: us[k])


@eqx.filter_jit
def _iteration(problem: HybridILQR, nominal: _Rollout, mu, alphas):
    A, B = linearise(problem, nominal)
    d, K, dV = _backward(problem, nominal, A, B, mu)
    ext = _extensions(problem, nominal, K)
    trials = jax.vmap(lambda a: _rollout(problem, _policy(problem, nominal, d, K, ext, a)))(alphas)
    costs = jnp.where(jnp.all(trials.status == 0, axis=1) & jnp.isfinite(trials.cost), trials.cost, jnp.inf)
    best = jnp.argmin(costs)
    return jax.tree_util.tree_map(lambda a: a[best], trials), costs[best], dV


# The problem under the name it had first: `hj.HybridLQRProblem(...)` builds a `HybridILQR`.
HybridLQRProblem = HybridILQR


class HybridILQRResult(eqx.Module):
    """What `hybrid_ilqr` returns.

    - `controls` (N, m), `states` (N + 1, n), `modes` (N + 1,): the last iterate on the grid;
      `cost` its cost.
    - `costs` (iterations + 1,): the cost of each iterate (iterate 0: the initial controls).
    - `event_times`, `transitions` (iterations + 1, N, max_epochs): each iterate's events per
      interval (`inf`, -1 where none); `num_events` (iterations + 1,) their count.
    - `sequence_changed` (iterations + 1,): whether an iterate's event sequence (the intervals
      its events fall in, and the transitions) differs from the previous iterate's.
    - `gains` (N, m, n): the feedback gains K_k of the last backward pass.
    """

    controls: Float[Array, "N m"]
    states: Float[Array, "N+1 n"]
    modes: Int[Array, " N+1"]
    cost: Float[Array, ""]
    costs: Float[Array, " iterations"]
    event_times: Float[Array, "iterations N events"]
    transitions: Int[Array, "iterations N events"]
    num_events: Int[Array, " iterations"]
    sequence_changed: Bool[Array, " iterations"]
    gains: Float[Array, "N m n"]


def hybrid_ilqr(
    problem: HybridILQR,
    controls: Float[ArrayLike, "N m"],
    *,
    iterations: int = 20,
    mu: float = 1e-6,
    alphas: Float[ArrayLike, " trials"] = (1.0, 0.5, 0.25, 0.1, 0.03, 0.01),
    tol: float = 1e-12,
) -> HybridILQRResult:
    r"""Minimise `problem`'s cost by hybrid iLQR from the initial `controls` (N, m).

    Each iteration linearises the nominal rollout (saltation matrices at its events), runs the
    Riccati backward pass with regularisation `mu` on $Q_{uu}$, and rolls out the new policy
    $u = u_k + \alpha d_k + K_k (x - \bar x_k)$ for every step length $\alpha$ in `alphas` (in
    parallel), keeping the cheapest; $\bar x_k$, $K_k$ come from the reference extension where
    the rollout's events run ahead of or behind the nominal's. It stops after `iterations`, or
    when no step length lowers the cost by more than `tol` (relative) after raising `mu` tenfold
    five times.
    """
    us = jnp.asarray(controls, float)
    N = problem.ts.shape[0] - 1
    if us.ndim != 2 or us.shape[0] != N:
        raise ValueError(f"hybrid_ilqr: controls must have shape (N, m) = ({N}, m), got {us.shape}.")
    alphas = jnp.asarray(alphas, float)
    nominal = _initial(problem, us)
    history = [nominal]
    gains = jnp.zeros((N, us.shape[1], problem.x0.shape[0]))
    mu_k = mu
    for _ in range(iterations):
        for _ in range(6):
            trial, cost, _ = _iteration(problem, nominal, jnp.asarray(mu_k), alphas)
            if float(cost) < float(nominal.cost) * (1 - tol):
                break
            mu_k *= 10.0
        else:
            break
        mu_k = max(mu, mu_k / 10.0)
        nominal = trial
        history.append(nominal)
    A, B = linearise(problem, nominal)
    _, gains, _ = _backward(problem, nominal, A, B, jnp.asarray(mu_k))

    def signature(r):
        return (np.asarray(r.num_events), np.asarray(r.transitions))

    changed = [False] + [
        not all(np.array_equal(a, b) for a, b in zip(signature(r0), signature(r1), strict=True))
        for r0, r1 in zip(history, history[1:], strict=False)
    ]
    return HybridILQRResult(
        controls=nominal.us, states=nominal.xs, modes=nominal.modes, cost=nominal.cost,
        costs=jnp.stack([r.cost for r in history]),
        event_times=jnp.stack([r.event_times for r in history]),
        transitions=jnp.stack([r.transitions for r in history]),
        num_events=jnp.stack([r.counts[-1] for r in history]),
        sequence_changed=jnp.asarray(changed), gains=gains,
    )
