"""Saltation matrices and the variational (state-transition matrix) solver.

References: N. J. Kong, J. J. Payne, J. Zhu, A. M. Johnson, "Saltation matrices: the essential
tool for linearizing hybrid dynamical systems", Proc. IEEE, 2024; N. J. Kong, J. J. Payne,
G. Council, A. M. Johnson, "The Salted Kalman Filter: Kalman filtering on hybrid dynamical
systems", Automatica 131, 2021. For a transition (I, J) at (t, x) with guard g, reset R and flows F_I, F_J,

    Xi = D_x R + (F_J(t, R(t, x)) - D_x R F_I(t, x) - D_t R) D_x g / (D_t g + D_x g F_I(t, x)).

A chain of transitions at one instant (a reset into another guard, giving zero-length epochs)
acts as one transition whose reset is the composition R = R_m o ... o R_1 and whose guard is
the first one's: the later transitions' times *are* the first one's, so they contribute no
timing term of their own (their guards may be constant, where the plain formula is 0/0).
"""

from collections.abc import Sequence
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._definition.system import HybridSystem, Transition


def _chain(system: HybridSystem, transition) -> list[int]:
    if isinstance(transition, (Transition, int, np.integer)):
        return [system.transition_index(transition)]
    ks = [system.transition_index(tr) for tr in transition]
    if not ks:
        raise ValueError("saltation_matrix: empty chain of transitions.")
    for a, b in zip(ks, ks[1:], strict=False):
        if system.targets[a] != system.sources[b]:
            raise ValueError(
                f"saltation_matrix: transition {b} ({system.transitions[b].label}) does not "
                f"leave the mode that transition {a} ({system.transitions[a].label}) enters."
            )
    return ks


def _composite_reset(system: HybridSystem, ks: list[int], args):
    def reset(t, x):
        for k in ks:
            x = jnp.asarray(system.transitions[k].reset(t, x, args))
        return x

    return reset


def saltation_matrix(
    system: HybridSystem,
    transition: Transition | int | Sequence[Transition | int],
    t: Float[ArrayLike, ""],
    x: Float[ArrayLike, " n_I"],
    args: Any = None,
    *,
    timing: bool = True,
) -> Float[Array, "n_J n_I"]:
    r"""The saltation matrix of `transition` at the pre-event state `x` (mode I's dimension).

    Xi = D_x R + (F_J(t, R(t, x)) - D_x R F_I(t, x) - D_t R) D_x g / (D_t g + D_x g F_I(t, x)),
    an n_J x n_I matrix, by AD of the user's functions. `transition` is a `Transition` of
    `system`, its index, or a sequence of them fired at the same instant (R is then the
    composition and g the first guard). With `timing=False` only D_x R is returned: the
    Jacobian of a transition fired at a time that does not depend on the state (one fired at
    the start of an epoch, e.g. at t0).

    !!! Example

        Bouncing ball, pre-impact velocity v < 0: Xi = [[-e, 0], [-(1 + e) g / v, -e]].
    """
    ks = _chain(system, transition)
    x = jnp.asarray(x)
    x = x.astype(jnp.result_type(x.dtype, jnp.float32))
    t = jnp.asarray(t, x.dtype)
    first, last = ks[0], ks[-1]
    mode_i = system.modes[system.sources[first]]
    mode_j = system.modes[system.targets[last]]
    if x.shape != (mode_i.dim,):
        raise ValueError(
            f"saltation_matrix: x has shape {x.shape}; transition "
            f"{system.transitions[first].label} leaves mode '{mode_i.name}' of dim {mode_i.dim}."
        )
    reset = _composite_reset(system, ks, args)
    DxR = jax.jacfwd(reset, argnums=1)(t, x)
    if not timing:
        return DxR
    DtR = jax.jacfwd(reset, argnums=0)(t, x)
    guard = system.transitions[first].guard
    Dtg, Dxg = jax.grad(lambda tt, xx: jnp.asarray(guard(tt, xx, args)), argnums=(0, 1))(t, x)
    F_i = mode_i.flow(t, x, args)
    F_j = mode_j.flow(t, reset(t, x), args)
    gdot = Dtg + Dxg @ F_i
    return DxR + jnp.outer(F_j - DxR @ F_i - DtR, Dxg) / gdot


class VariationalJacobian(NamedTuple):
    """Jacobians of one execution with respect to its initial state, by variational equations.

    - `final_state`: d x(t1) / d x0, n_final x n_0.
    - `states_before`, `states_after`: d x(t_i^-) / d x0 and d x(t_i^+) / d x0 per event,
      including the dependence through the event time.
    - `event_times`: d t_i / d x0 per event (n_0,).
    """

    final_state: np.ndarray
    states_before: list
    states_after: list
    event_times: list


@eqx.filter_jit
def _epoch_stm(system: HybridSystem, mode: int, args, t0, t1, x0, solver, controller):
    """x(t1) and Phi(t1, t0) for mode's flow: dPhi/dt = D_x F Phi, Phi(t0) = I (diffrax).

    Compiled once per (system, mode, args' non-array values, solver, controller) and reused:
    t0 and t1 are passed as arrays, so each epoch and each later call runs the same program
    (built inside each call, the solve was traced and compiled anew for every epoch)."""
    flow = system.modes[mode].flow

    def vf(t, y, a):
        x, phi = y
        return flow(t, x, a), jax.jacfwd(lambda xx: flow(t, xx, a))(x) @ phi

    y0 = (x0, jnp.eye(x0.shape[0], dtype=x0.dtype))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vf), solver, t0, t1, None, y0, args=args,
        stepsize_controller=controller, max_steps=100_000,
    )
    return sol.ys[0][-1], sol.ys[1][-1]


def variational_jacobian(
    sol,
    *,
    solver: diffrax.AbstractSolver | None = None,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
) -> VariationalJacobian:
    r"""Jacobian of one execution's final and event states w.r.t. x0, without AD through the loop.

    Each epoch's state-transition matrix Phi_i solves dPhi/dt = D_x F_I(t, x) Phi with diffrax
    (from the solution's own event times and post-event states), and the epochs are joined by
    saltation matrices: J = Phi_n Xi_{n-1} ... Xi_1 Phi_1. Events at one instant form one
    chain (see `saltation_matrix`); transitions fired at the start of an epoch that began at
    t0 have no timing term. An independent check of `jax.jacfwd(simulate)`.
    """
    sol._check_single("variational_jacobian")
    system = sol.system
    args = sol.args
    solver = diffrax.Tsit5() if solver is None else solver
    dtype = sol.final_state.dtype
    if stepsize_controller is None:
        tol = 1e-11 if dtype == jnp.float64 else 1e-6
        stepsize_controller = diffrax.PIDController(rtol=tol, atol=tol)
    n_events = int(sol.num_events)
    times = np.asarray(sol.event_times)[:n_events]
    trans = [int(k) for k in np.asarray(sol.transitions)[:n_events]]
    if any(k >= system.num_transitions for k in trans):
        raise NotImplementedError(
            "variational_jacobian: the execution passes a Zeno completion, whose limit point "
            "has no saltation matrix; linearise the execution before the completion."
        )
    modes = [int(m) for m in np.asarray(sol.epoch_modes)[: n_events + 1]]
    t_start = float(sol.t0)
    mode = modes[0]
    x = jnp.asarray(sol.x0)[: system.modes[mode].dim]
    J = jnp.eye(x.shape[0], dtype=dtype)
    before, after, dts = [], [], []
    i = 0
    while True:
        t_end = float(times[i]) if i < n_events else float(sol.final_time)
        crossed = t_end > t_start
        if crossed:
            x, phi = _epoch_stm(system, mode, args, jnp.asarray(t_start, dtype), jnp.asarray(t_end, dtype),
                                x, solver, stepsize_controller)
            J = phi @ J
        if i >= n_events:
            break
        # the chain of transitions fired at this instant: this one and the zero-length epochs after it
        j = i
        while j + 1 < n_events and times[j + 1] == times[i]:
            j += 1
        chain = trans[i : j + 1]
        t_ev = jnp.asarray(t_end, dtype)
        guard = system.transitions[chain[0]].guard
        if crossed:
            Dtg, Dxg = jax.grad(lambda tt, xx: jnp.asarray(guard(tt, xx, args)), argnums=(0, 1))(t_ev, x)
            gdot = Dtg + Dxg @ system.modes[mode].flow(t_ev, x, args)
            dt = -(Dxg @ J) / gdot
        else:
            dt = jnp.zeros((J.shape[1],), dtype)
        x_before_jac = J + jnp.outer(system.modes[mode].flow(t_ev, x, args), dt)
        # Along the chain: after transition m, d x+ / d x0 = Xi_{1..m} J + F_{J_m}(x+) dt.
        for m in range(len(chain)):
            before.append(np.asarray(x_before_jac))
            dts.append(np.asarray(dt))
            x_m = _composite_reset(system, chain[: m + 1], args)(t_ev, x)
            Xi_m = saltation_matrix(system, chain[: m + 1], t_ev, x, args, timing=crossed)
            F_m = system.modes[system.targets[chain[m]]].flow(t_ev, x_m, args)
            x_before_jac = Xi_m @ J + jnp.outer(F_m, dt)
            after.append(np.asarray(x_before_jac))
        x_next = x_m
        J = Xi_m @ J
        x = x_next
        mode = modes[j + 1]
        t_start = t_end
        i = j + 1
    return VariationalJacobian(np.asarray(J), before, after, dts)
