"""Hybrid periodic orbits: fixed points of a Poincare return map, and their Floquet multipliers.

The section is the image of one transition's reset: P(x) is the post-reset state at the next
firing of that transition, starting from x just after it. A fixed point x* = P(x*) is found
with optimistix (Newton). Two independent linearisations of the orbit (period T):

- by AD: the Jacobian of the time-T hybrid flow from a base point inside the first epoch;
- by saltation composition: Phi_k Xi_{k-1} ... Xi_1 Phi_1 along the same orbit
  (`variational_jacobian`).

Both are the monodromy matrix at the base point; its eigenvalues (Floquet multipliers) include
1 (the flow direction, since Xi F_I = F_J) and the multipliers of the return map. The return
map's own Jacobian DP (eigenvalues 0 along the flow, and the same nontrivial multipliers) is
returned too. Reference: S. A. Burden, S. Revzen, S. S. Sastry, "Model reduction near periodic
orbits of hybrid dynamical systems", IEEE TAC 60(10), 2015.
"""

from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import ArrayLike, Float

from ._saltation import variational_jacobian
from ._simulate import simulate
from ._system import HybridSystem, Transition


class PeriodicOrbit(NamedTuple):
    """A hybrid periodic orbit through the reset image of `transition`."""

    state: np.ndarray  # x* just after the transition (the section point)
    mode: int  # the mode x* lives in (the transition's target)
    period: float
    residual: float  # |P(x*) - x*|
    poincare_jacobian: np.ndarray  # DP(x*)
    base_time: float  # time after the section of the base point of the monodromy matrices
    base_state: np.ndarray
    monodromy_ad: np.ndarray
    monodromy_saltation: np.ndarray
    multipliers_ad: np.ndarray
    multipliers_saltation: np.ndarray


def _sorted_eigs(m: np.ndarray) -> np.ndarray:
    e = np.linalg.eigvals(m)
    return e[np.argsort(-np.abs(e))]


def periodic_orbit(
    system: HybridSystem,
    transition: Transition | int,
    x_guess: Float[ArrayLike, " n"],
    args: Any = None,
    *,
    t_max: float = 100.0,
    max_epochs: int = 16,
    rtol: float = 1e-10,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
) -> PeriodicOrbit:
    r"""Find x* with P(x*) = x*, P the return map to the reset image of `transition`.

    `x_guess` is a post-reset state in the transition's target mode. Newton's method
    (optimistix) on P(x) - x, with DP by forward-mode AD through `simulate`. Then the
    monodromy matrix by AD and by saltation composition, and their eigenvalues.

    !!! Example

        ```python
        wheel = hj.examples.rimless_wheel()
        orbit = hj.periodic_orbit(wheel, 0, jnp.array([0.05, 0.4]), {"alpha": 0.3, "gamma": 0.08})
        orbit.multipliers_ad   # [1, cos(2 alpha)^2]
        ```
    """
    k = system.transition_index(transition)
    mode = system.targets[k]
    x_guess = jnp.asarray(x_guess)
    dtype = jnp.result_type(x_guess.dtype, jnp.float32)
    x_guess = x_guess.astype(dtype)
    ctrl = stepsize_controller or diffrax.PIDController(rtol=1e-12, atol=1e-12)
    fwd = diffrax.ForwardMode()

    def first_return(x):
        sol = simulate(system, x, mode, 0.0, t_max, args, stepsize_controller=ctrl,
                       max_epochs=max_epochs, adjoint=fwd)
        hit = sol.transitions == k
        i = jnp.argmax(hit)
        n = system.modes[mode].dim
        return sol.states_after[i, :n], sol.event_times[i], jnp.any(hit), sol.event_times[0]

    def residual(x, _):
        return first_return(x)[0] - x

    found = optx.root_find(residual, optx.Newton(rtol=rtol, atol=rtol), x_guess, throw=False)
    x_star = found.value

    # Two compiled functions (eager calls of `simulate` would dispatch op by op and compile
    # once per call site): the return map with its Jacobian, then the monodromy matrix.
    @eqx.filter_jit
    def return_map(x):
        def P_aux(x):
            P, *aux = first_return(x)
            return P, (P, *aux)

        return jax.jacfwd(P_aux, has_aux=True)(x)

    DP, (P, period, hit, first_event) = return_map(x_star)
    if not bool(hit):
        raise RuntimeError(
            f"periodic_orbit: transition {system.transitions[k].label} did not fire again "
            f"within t_max={t_max} from the converged state {np.asarray(x_star)}."
        )

    @eqx.filter_jit
    def monodromy(x_star, base_time, period):
        # Base point inside the first epoch (not on an event), so the time-T flow is smooth there.
        base = simulate(system, x_star, mode, 0.0, base_time, args, stepsize_controller=ctrl,
                        max_epochs=max_epochs).final_state

        def flow_T(x):
            sol = simulate(system, x, mode, 0.0, period, args, stepsize_controller=ctrl,
                           max_epochs=max_epochs, adjoint=fwd)
            return sol.final_state, sol

        M_ad, orbit_sol = jax.jacfwd(flow_T, has_aux=True)(base)
        return base, M_ad, orbit_sol

    base_time = 0.5 * first_event
    base, M_ad, orbit_sol = monodromy(x_star, base_time, period)
    period, base_time, M_ad = float(period), float(base_time), np.asarray(M_ad)
    M_salt = variational_jacobian(orbit_sol).final_state
    return PeriodicOrbit(
        state=np.asarray(x_star),
        mode=mode,
        period=period,
        residual=float(jnp.max(jnp.abs(P - x_star))),
        poincare_jacobian=np.asarray(DP),
        base_time=base_time,
        base_state=np.asarray(base),
        monodromy_ad=M_ad,
        monodromy_saltation=M_salt,
        multipliers_ad=_sorted_eigs(M_ad),
        multipliers_saltation=_sorted_eigs(M_salt),
    )
