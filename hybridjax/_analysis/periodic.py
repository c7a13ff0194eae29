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

from .._analysis.saltation import variational_jacobian
from .._definition.system import HybridSystem, Transition
from .._solve.simulate import simulate


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


class _ReturnProblem(eqx.Module):
    """Everything the return map depends on besides the state. Module-level functions of it
    (`_residual`, `_return_map`, `_monodromy`) are compiled once per configuration and reused
    by later calls, so a second orbit of the same problem (another slope given as an array)
    compiles nothing; its arrays are inputs, the rest is the cache key."""

    system: HybridSystem
    args: Any
    ctrl: diffrax.AbstractStepSizeController
    mode: int = eqx.field(static=True)
    transition: int = eqx.field(static=True)
    t_max: Any
    max_epochs: int

    def run(self, x, t1, adjoint=diffrax.ForwardMode()):
        return simulate(self.system, x, self.mode, 0.0, t1, self.args, stepsize_controller=self.ctrl,
                        max_epochs=self.max_epochs, adjoint=adjoint)

    def first_return(self, x):
        sol = self.run(x, self.t_max)
        hit = sol.transitions == self.transition
        i = jnp.argmax(hit)
        n = self.system.modes[self.mode].dim
        return sol.states_after[i, :n], sol.event_times[i], jnp.any(hit), sol.event_times[0]


def _residual(x, problem: _ReturnProblem):
    return problem.first_return(x)[0] - x


@eqx.filter_jit
def _return_map(problem: _ReturnProblem, x):
    """P(x) and DP(x) (forward mode), with the return time, whether the transition fired again
    and the first event time."""

    def P_aux(x):
        P, *aux = problem.first_return(x)
        return P, (P, *aux)

    return jax.jacfwd(P_aux, has_aux=True)(x)


@eqx.filter_jit
def _monodromy(problem: _ReturnProblem, x_star, base_time, period):
    # Base point inside the first epoch (not on an event), so the time-T flow is smooth there.
    base = problem.run(x_star, base_time, diffrax.RecursiveCheckpointAdjoint()).final_state

    def flow_T(x):
        sol = problem.run(x, period)
        return sol.final_state, sol

    M_ad, orbit_sol = jax.jacfwd(flow_T, has_aux=True)(base)
    return base, M_ad, orbit_sol


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
    problem = _ReturnProblem(system, args, ctrl, mode=mode, transition=k, t_max=t_max,
                             max_epochs=max_epochs)

    found = optx.root_find(_residual, optx.Newton(rtol=rtol, atol=rtol), x_guess, args=problem,
                           throw=False)
    x_star = found.value

    DP, (P, period, hit, first_event) = _return_map(problem, x_star)
    if not bool(hit):
        raise RuntimeError(
            f"periodic_orbit: transition {system.transitions[k].label} did not fire again "
            f"within t_max={t_max} from the converged state {np.asarray(x_star)}."
        )

    base_time = 0.5 * first_event
    base, M_ad, orbit_sol = _monodromy(problem, x_star, base_time, period)
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
