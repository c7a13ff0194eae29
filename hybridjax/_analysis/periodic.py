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

The orbit is a function of the system's parameters `args`, differentiable by the implicit
function theorem on the fixed point: x*(a) = P(x*(a), a) gives

    (I - D_x P) dx* = D_a P da,

and every other output q(x, a) (the period, DP, the base point, the monodromy matrix) moves by
D_x q dx* + D_a q da. The Newton iterations are not differentiated. The Jacobians D_x q, D_a q
are taken by forward mode through `simulate` (DP's derivative is a second derivative through
the events, exact to the tolerance: `event_point`), and contracted with the tangents as plain
arrays, so that reverse mode (`jax.grad`) transposes the contraction alone.
"""

import dataclasses
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Complex, Float

from .._analysis.saltation import variational_jacobian
from .._definition.system import HybridSystem, Transition
from .._solve.simulate import simulate

sg = jax.lax.stop_gradient


class PeriodicOrbit(NamedTuple):
    """A hybrid periodic orbit through the reset image of `transition`: JAX arrays,
    differentiable with respect to `args` (the saltation check excepted)."""

    state: Float[Array, " n"]  # x* just after the transition (the section point)
    mode: int  # the mode x* lives in (the transition's target)
    period: Float[Array, ""]
    residual: Float[Array, ""]  # |P(x*) - x*| (no derivative)
    poincare_jacobian: Float[Array, "n n"]  # DP(x*)
    base_time: Float[Array, ""]  # time after the section of the base point of the monodromy matrices
    base_state: Float[Array, " n"]
    monodromy_ad: Float[Array, "n n"]
    monodromy_saltation: Float[Array, "n n"] | None  # None where the call is traced
    multipliers_ad: Complex[Array, " n"]  # eigenvalues of monodromy_ad, largest modulus first
    multipliers_saltation: Complex[Array, " n"] | None


def _sorted_eigs(m):
    e = jnp.linalg.eigvals(m)
    return e[jnp.argsort(-jnp.abs(e))]


class _ReturnProblem(eqx.Module):
    """Everything the return map depends on besides the state. Module-level functions of it are
    compiled once per configuration (`_orbit_compiled`) and reused by later calls, so a second
    orbit of the same problem (another slope given as an array) compiles nothing; its arrays are
    inputs, the rest is the cache key. `args` holds the parameters' leaves that are not
    differentiated (the inexact arrays are passed separately: `at`)."""

    system: HybridSystem
    args: Any
    ctrl: diffrax.AbstractStepSizeController
    mode: int = eqx.field(static=True)  # static: Python indices into the system's tuples
    transition: int = eqx.field(static=True)
    t_max: Any
    max_epochs: int = eqx.field(static=True)
    rtol: float

    def at(self, diff_args) -> "_ReturnProblem":
        """The problem with the parameters' inexact arrays `diff_args` put back."""
        return dataclasses.replace(self, args=eqx.combine(diff_args, self.args))

    def run(self, x, t1):
        return simulate(self.system, x, self.mode, 0.0, t1, self.args, stepsize_controller=self.ctrl,
                        max_epochs=self.max_epochs, adjoint=diffrax.ForwardMode())

    def first_return(self, x):
        sol = self.run(x, self.t_max)
        hit = sol.transitions == self.transition
        i = jnp.argmax(hit)
        n = self.system.modes[self.mode].dim
        return sol.states_after[i, :n], sol.event_times[i], jnp.any(hit), sol.event_times[0]


def _residual(x, problem: _ReturnProblem):
    return problem.first_return(x)[0] - x


def _fixed_point(problem: _ReturnProblem, x_guess):
    """x* with P(x*) = x*: optimistix's Newton method (DP by forward mode through `simulate`),
    without derivatives (those come from the implicit function theorem, `_orbit`)."""
    dynamic, static = eqx.partition(problem, eqx.is_array)
    problem, x_guess = eqx.combine(sg(dynamic), static), sg(x_guess)
    solver = optx.Newton(rtol=problem.rtol, atol=problem.rtol)
    return sg(optx.root_find(_residual, solver, x_guess, args=problem, throw=False).value)


def _quantities(problem: _ReturnProblem, x):
    """At a section point x: P(x), DP(x), the return time (period), the base point (halfway
    through the first epoch, not on an event, so that the time-T flow is smooth there), its time,
    and the monodromy matrix, the Jacobian of the time-T flow at the base point. Also whether the
    transition fired again (1.0 or 0.0), and the execution along the orbit from the base point."""

    def P_aux(x):
        P, *aux = problem.first_return(x)
        return P, (P, *aux)

    DP, (P, period, hit, first_event) = jax.jacfwd(P_aux, has_aux=True)(x)
    base_time = 0.5 * first_event
    base = problem.run(x, base_time).final_state
    def flow_T(y):
        sol = problem.run(y, period)
        return sol.final_state, sol

    M, orbit_sol = jax.jacfwd(flow_T, has_aux=True)(base)
    q = dict(P=P, DP=DP, period=period, base_time=base_time, base=base, M=M)
    return q, hit.astype(x.dtype), orbit_sol


# The non-array parts of the execution along the orbit, from `_orbit`'s trace to `_orbit_compiled`.
_SOLUTION_PARTS: list = []


@eqx.filter_custom_jvp
def _orbit(diff_args, x_guess, problem: _ReturnProblem):
    """(x*, the quantities at x*, whether the transition fired again, the arrays of the execution
    along the orbit) for the parameters' inexact arrays `diff_args`; derivatives by `_orbit_jvp`
    (none for the execution)."""
    pr = problem.at(diff_args)
    x_star = _fixed_point(pr, x_guess)
    q, hit, orbit_sol = _quantities(pr, x_star)
    arrays, static = eqx.partition(orbit_sol, eqx.is_array)
    _SOLUTION_PARTS.append(static)
    return x_star, q, hit, arrays


@_orbit.def_jvp
def _orbit_jvp(primals, tangents):
    r"""The implicit function theorem on x* = P(x*, a): (I - D_x P) dx* = D_a P da, and
    dq = D_x q dx* + D_a q da, with the Jacobians of the quantities in (x, a) by forward mode
    (one `jax.jacfwd` over the stacked state and raveled parameters)."""
    diff_args, x_guess, problem = primals
    d_args = tangents[0]
    x_star, q, hit, sol_arrays = _orbit(diff_args, x_guess, problem)
    flat, unravel = ravel_pytree(diff_args)
    if d_args is None:
        d_flat = jnp.zeros_like(flat)
    else:
        d_args = jax.tree_util.tree_map(lambda t, a: jnp.zeros_like(a) if t is None else t, d_args, diff_args,
                                        is_leaf=lambda t: t is None)
        d_flat = ravel_pytree(d_args)[0]
    n = x_star.shape[0]

    def quantities_of(z):
        return _quantities(problem.at(unravel(z[n:])), z[:n])[0]

    J = jax.jacfwd(quantities_of)(jnp.concatenate([x_star, flat.astype(x_star.dtype)]))
    d_flat = d_flat.astype(x_star.dtype)
    I_n = jnp.eye(n, dtype=x_star.dtype)
    dx = jnp.linalg.solve(I_n - q["DP"], J["P"][:, n:] @ d_flat)
    dq = {key: J[key][..., :n] @ dx + J[key][..., n:] @ d_flat for key in q}
    no_tangent = jax.tree_util.tree_map(lambda _: None, sol_arrays)
    return (x_star, q, hit, sol_arrays), (dx, dq, jnp.zeros_like(hit), no_tangent)


@eqx.filter_jit
def _orbit_compiled(diff_args, x_guess, problem: _ReturnProblem):
    """`_orbit`, compiled once per configuration, with the execution along the orbit made whole
    again: its non-array parts, which a custom JVP cannot return, are left by `_orbit` (traced
    at once by the call below) in `_SOLUTION_PARTS`."""
    _SOLUTION_PARTS.clear()
    x_star, q, hit, sol_arrays = _orbit(diff_args, x_guess, problem)
    return x_star, q, hit, eqx.combine(sol_arrays, _SOLUTION_PARTS.pop())


def _saltation_monodromy(orbit_sol):
    """The monodromy matrix by saltation composition along the orbit from the base point
    (`variational_jacobian`, an independent check of the AD one), or None where the values are
    traced (it needs concrete event times)."""
    arrays, static = eqx.partition(orbit_sol, eqx.is_array)
    arrays = sg(arrays)
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(arrays)):
        return None
    return variational_jacobian(eqx.combine(arrays, static)).final_state


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

    A JAX function of `args`: usable inside `jax.jit`, and differentiable (`jax.grad`,
    `jax.jvp`, `jax.jacfwd`) with respect to `args`' floating-point arrays by the implicit
    function theorem on the fixed point, (I - DP) dx* = D_a P da, without differentiating the
    Newton iterations; the period, DP, the base point, `monodromy_ad` and `multipliers_ad` follow
    (DP's derivative is a second derivative through the events). `monodromy_saltation` and
    `multipliers_saltation` are an independent check without derivatives, None where the call is
    traced (inside `jax.jit` or a transformation). A transition that does not fire again within
    `t_max` from the converged state is an error (`eqx.error_if`). The eigenvalues use
    `jnp.linalg.eigvals`, whose derivative needs distinct eigenvalues.

    !!! Example

        ```python
        wheel = hj.examples.rimless_wheel()
        orbit = hj.periodic_orbit(wheel, 0, jnp.array([0.05, 0.4]), {"alpha": 0.3, "gamma": 0.08})
        orbit.multipliers_ad   # [1, cos(2 alpha)^2]

        def multiplier(alpha):  # d/d alpha: -2 sin(4 alpha)
            orbit = hj.periodic_orbit(wheel, 0, jnp.array([-0.22, 0.4]), {"alpha": alpha, "gamma": 0.08})
            return jnp.trace(orbit.poincare_jacobian)
        jax.grad(multiplier)(0.3)
        ```
    """
    if not (isinstance(max_epochs, int) and not isinstance(max_epochs, bool) and max_epochs >= 1):
        raise ValueError(f"periodic_orbit: max_epochs must be an int >= 1, got {max_epochs!r}.")
    if not (isinstance(rtol, (int, float)) and rtol > 0):
        raise ValueError(f"periodic_orbit: rtol must be a number > 0, got {rtol!r}.")
    k = system.transition_index(transition)
    mode = system.targets[k]
    x_guess = jnp.asarray(x_guess)
    dtype = jnp.result_type(x_guess.dtype, jnp.float32)
    x_guess = x_guess.astype(dtype)
    ctrl = stepsize_controller or diffrax.PIDController(rtol=1e-12, atol=1e-12)
    diff_args, rest = eqx.partition(args, eqx.is_inexact_array)
    problem = _ReturnProblem(system, rest, ctrl, mode=mode, transition=k, t_max=t_max, max_epochs=max_epochs,
                             rtol=float(rtol))

    x_star, q, hit, orbit_sol = _orbit_compiled(diff_args, x_guess, problem)
    x_star = eqx.error_if(
        x_star, hit == 0,
        f"periodic_orbit: transition {system.transitions[k].label} did not fire again within t_max={t_max} "
        "from the converged state.")
    M_salt = _saltation_monodromy(orbit_sol)
    return PeriodicOrbit(
        state=x_star,
        mode=mode,
        period=q["period"],
        residual=sg(jnp.max(jnp.abs(q["P"] - x_star))),
        poincare_jacobian=q["DP"],
        base_time=q["base_time"],
        base_state=q["base"],
        monodromy_ad=q["M"],
        monodromy_saltation=M_salt,
        multipliers_ad=_sorted_eigs(q["M"]),
        multipliers_saltation=None if M_salt is None else _sorted_eigs(M_salt),
    )
