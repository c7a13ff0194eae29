"""A point search: find (t, x) with equalities = 0 and inequalities >= 0, by sampling and then
local optimisation.

Many questions about a hybrid system's sets are of this form: does a guard meet a domain
(A. M. Johnson, "Hybrid Dynamical Systems", eq. (3)), do two guards of one mode meet (eq. (6)),
is there a point of a domain's boundary, where the flow leaves, that no guard covers (eq. (7))?
`find_point` answers each with a witness: the samples are scored by their constraint violation,
the best few are refined by a trust-region (dogleg) least-squares solve (optimistix) of the
violated constraints, and the best point found is returned.

A search finds points; it does not prove that none exist. `found=False` means that no sample,
and no local refinement of the best samples, reached the tolerance: the set may still be
non-empty (small, or far from every sample).
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, PRNGKeyArray

from .._core import small_linalg as small_linalg
from .._core.names import bounds_of, one_of


class SearchOptions(eqx.Module):
    r"""How the point searches of `check_properties` and `contact_system` refine their samples,
    as `find_point`'s keywords of the same names: the `num_starts` samples of least violation
    $v$ are refined by a dogleg trust-region least-squares solve of at most `iterations` steps
    each, and a point counts as found where $v \le$ `tol`.

    **Fields:** `num_starts` (default 8), `iterations` (64), `tol` (1e-14, for float64).

    ```python
    report = hj.check_properties(system, args, bounds=bounds,
                                 search=hj.SearchOptions(num_starts=16, iterations=128))
    ```
    """

    num_starts: int = eqx.field(static=True, default=8)  # static: how many starts (a shape)
    iterations: int = eqx.field(static=True, default=64)  # static: a loop bound
    tol: float = 1e-14

    def __check_init__(self):
        for name in ("num_starts", "iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"SearchOptions: {name} must be an int >= 1, got {value!r}.")
        tol = self.tol
        if isinstance(tol, bool) or not isinstance(tol, (int, float, np.floating)) or not tol >= 0:
            raise ValueError(f"SearchOptions: tol must be a number >= 0, got {self.tol!r}.")


# The keyword shorthands of `search=` (with `max_steps`, optimistix's name of `iterations`).
SEARCH_SHORTHANDS = ("num_starts", "iterations", "max_steps", "tol")


def search_options(owner: str, search: SearchOptions | None, shorthands: dict[str, Any]) -> SearchOptions:
    """The `SearchOptions` of a call: `search` itself, or built from the keyword shorthands
    `num_starts`, `iterations` (or `max_steps`), `tol`, taken out of `shorthands` (None counts
    as not given). A shorthand beside `search`, or `iterations` beside `max_steps`, is a
    `ValueError` naming both."""
    given = {name: shorthands.pop(name) for name in SEARCH_SHORTHANDS if name in shorthands}
    given = {name: value for name, value in given.items() if value is not None}
    iterations = one_of(owner, iterations=given.pop("iterations", None),
                        max_steps=given.pop("max_steps", None), default=None)
    if iterations is not None:
        given["iterations"] = iterations
    if search is None:
        return SearchOptions(**given)
    if not isinstance(search, SearchOptions):
        raise TypeError(f"{owner}: search must be an hj.SearchOptions, got {type(search).__name__}.")
    if given:
        raise ValueError(f"{owner}: search and {' and '.join(sorted(given))} are the same option (fields of "
                         "hj.SearchOptions); pass one of them.")
    return search


class Witness(eqx.Module):
    """The result of `find_point`: the best point found and whether it satisfies the constraints.

    - `found`: `violation <= tol`.
    - `t`, `x`: the point.
    - `violation`: $\\sum_i e_i(t, x)^2 + \\sum_j \\min(c_j(t, x), 0)^2$ for the equalities $e$
      and inequalities $c$ (and the time bounds, where `t` was optimised).
    """

    found: Bool[Array, ""]
    t: Float[Array, ""]
    x: Float[Array, " n"]
    violation: Float[Array, ""]


def _values(fn, t, x, args, dtype) -> Array:
    if fn is None:
        return jnp.zeros((0,), dtype)
    return jnp.reshape(jnp.asarray(fn(t, x, args), dtype), (-1,))


def _joint(equalities, inequalities) -> Callable:
    """(t, x, args) -> (equalities, inequalities) as two 1-D arrays (empty for `None`)."""

    def constraints(t, x, args):
        return _values(equalities, t, x, args, x.dtype), _values(inequalities, t, x, args, x.dtype)

    return constraints


def _residuals(constraints, t_bounds, t, x, args) -> Array:
    """The violated parts of every constraint, one vector: their squared sum is the violation."""
    eq, ineq = constraints(t, x, args)
    parts = [eq.astype(x.dtype), jnp.minimum(ineq, 0.0).astype(x.dtype)]
    if t_bounds is not None:
        lo, hi = t_bounds
        parts.append(jnp.minimum(jnp.stack([t - lo, hi - t]).astype(x.dtype), 0.0))
    return jnp.concatenate(parts)


def _time_of(s, lo, hi):
    """t = (lo + hi) / 2 + (hi - lo) / 2 sin(s): the time searched, kept in [lo, hi] by a smooth
    map (a penalty on t outside the bounds has its minimiser outside them; a reflection at the
    bounds puts a kink where the minimiser often is, at a bound, and Gauss-Newton steps
    oscillate about it)."""
    return 0.5 * (lo + hi) + 0.5 * (hi - lo) * jnp.sin(s)


def _angle_of(t, lo, hi):
    """The s with `_time_of(s, lo, hi) = t`, for t in [lo, hi] at least 0.5 % of the window from
    its ends: a start at an end would sit where d t / d s = 0, and its t would never move."""
    w = hi - lo
    return jnp.arcsin(jnp.clip((2 * t - lo - hi) / jnp.where(w > 0, w, 1.0), -0.99, 0.99))


class _DampedLeastSquares(lx.AbstractLinearSolver):
    """The least-squares step of the search: `_small_linalg.least_squares` (damped normal
    equations, close to the least-norm solution where the Jacobian is rank-deficient) of the
    Jacobian's matrix, whose non-finite entries `_with_jacobian` has already set to 0.

    Written as array operations rather than LAPACK's SVD, whose custom call can wait forever on
    the thread pool when other such calls run at once (see `_small_linalg`). Only `compute` is
    used by optimistix's least-squares solvers (the search is not differentiated through).
    """

    def init(self, operator, options):
        del options
        return operator.as_matrix()

    def compute(self, state, vector, options):
        del options
        return small_linalg.least_squares(state, vector), lx.RESULTS.successful, {}

    def transpose(self, state, options):
        return state.T, options

    def conj(self, state, options):
        return state, options

    def assume_full_rank(self):
        return False


def _finite(r: Array) -> Array:
    """Residuals with every non-finite entry replaced by a large finite one (still violated):
    the least-squares step stays finite, and the point is scored by `_violation`, where it is
    infinite."""
    # A fourth root of the largest float: the squared sum of many such entries stays finite.
    return jnp.where(jnp.isfinite(r), r, jnp.asarray(jnp.finfo(r.dtype).max ** 0.25, r.dtype))


def _with_jacobian(residuals: Callable[[Array], Array]) -> Callable[[Array, Any], Array]:
    r"""`residuals` as optimistix calls it, `(y, args) -> r(y)`, differentiated through its
    Jacobian matrix $J = \partial r / \partial y$ with the non-finite entries set to 0:
    $\dot r = J \dot y$.

    The least-squares solver linearises `r` at every iterate and carries the linearisation
    between iterations. A linearisation of `r` itself keeps every intermediate value of `r`
    (a contact system's kinematics and solves: thousands of arrays, each selected per lane
    under `jax.vmap`); this one keeps the (m, n) matrix alone: a program about half the size,
    traced and compiled in under half the time. A constraint can have a non-finite derivative
    at an iterate (a contact system's equations where its constraints are dependent): with
    those entries 0, every use of the Jacobian by the descent (its Gauss-Newton and Cauchy
    steps, `_DampedLeastSquares`) leaves that direction out."""

    @jax.custom_jvp
    def r(y):
        return residuals(y)

    @r.defjvp
    def r_jvp(primals, tangents):
        (y,), (y_dot,) = primals, tangents
        jac, value = jax.jacfwd(lambda z: (lambda v: (v, v))(residuals(z)), has_aux=True)(y)
        jac = jnp.where(jnp.isfinite(jac), jac, 0.0)
        return value, jac @ y_dot

    return lambda y, _: r(y)


def constraint_violation(
    equalities: Callable | None,
    inequalities: Callable | None,
    t: Float[Array, ""],
    x: Float[Array, " n"],
    args: Any = None,
) -> Float[Array, ""]:
    """$\\sum_i e_i(t, x)^2 + \\sum_j \\min(c_j(t, x), 0)^2$; infinite where a value is not finite.

    `equalities(t, x, args)` and `inequalities(t, x, args)` return 1-D arrays (or scalars),
    wanted `== 0` and `>= 0`; either may be `None`.
    """
    return _violation(_joint(equalities, inequalities), None, t, x, args)


def _violation(constraints, t_bounds, t, x, args):
    """The squared norm of `_residuals`; infinite where a value is not finite."""
    v = jnp.sum(_residuals(constraints, t_bounds, t, x, args) ** 2)
    return jnp.where(jnp.isfinite(v), v, jnp.inf)


def find_point(
    equalities: Callable | None,
    inequalities: Callable | None,
    ts: Float[Array, " N"],
    xs: Float[Array, "N n"],
    args: Any = None,
    *,
    t_bounds: tuple[Any, Any] | None = None,
    tol: float = 1e-10,
    num_starts: int = 8,
    iterations: int | None = None,
    max_steps: int | None = None,
) -> Witness:
    """A point (t, x) with `equalities == 0` and `inequalities >= 0`, searched from samples.

    Every sample (ts[i], xs[i]) is scored by its violation
    $v(t, x) = \\sum_i e_i(t, x)^2 + \\sum_j \\min(c_j(t, x), 0)^2$; the `num_starts` best are
    refined by a dogleg trust-region solve of the residual vector $(e, \\min(c, 0))$ (optimistix,
    at most `iterations` steps each, default 64); the point of least violation among the starts and
    their refinements is returned, `found` when $v \\le$ `tol`.

    **Arguments:**

    - `equalities`, `inequalities`: `(t, x, args) -> 1-D array` (or a scalar), wanted `== 0`
      and `>= 0`; either may be `None`, not both. Strict inequalities are the caller's to
      write with a margin (`c - margin >= 0`).
    - `ts` (N,), `xs` (N, n): the samples (`box_samples` draws them in a box).
    - `args`: passed to the constraint functions.
    - `t_bounds`: `None` keeps each start's t fixed; `(lo, hi)` optimises t too, within
      [lo, hi] (the samples' `ts` should lie in it).
    - `tol`: the violation accepted as zero.
    - `num_starts`: how many of the best samples are refined.
    - `iterations`: the most steps of each refinement (`max_steps`, optimistix's name, is a
      shorthand).

    Jittable and vmappable (e.g. over many pairs of sets at once, with the constraint
    functions selecting the pair from `args`).

    A search finds points; it does not prove that none exist: `found=False` says only that no
    sample and no refinement reached `tol`.

    !!! Example

        ```python
        circle = lambda t, x, args: jnp.array([x[0] ** 2 + x[1] ** 2 - 1.0])
        half_plane = lambda t, x, args: jnp.array([x[0] - 0.5])
        xs = hj.box_samples(jax.random.key(0), (-2.0 * jnp.ones(2), 2.0 * jnp.ones(2)), 64)
        w = hj.find_point(circle, half_plane, jnp.zeros(64), xs)
        w.found, w.x  # True, a point of the unit circle with x[0] >= 0.5
        ```
    """
    if equalities is None and inequalities is None:
        raise ValueError("find_point needs `equalities` or `inequalities` (both are None).")
    iterations = one_of("find_point", iterations=iterations, max_steps=max_steps, default=64)
    return search(
        _joint(equalities, inequalities),
        ts,
        xs,
        args,
        t_bounds=t_bounds,
        tol=tol,
        num_starts=num_starts,
        iterations=iterations,
    )


def search(
    constraints: Callable,
    ts: Float[Array, " N"],
    xs: Float[Array, "N n"],
    args: Any = None,
    *,
    t_bounds: tuple[Any, Any] | None = None,
    tol: float = 1e-10,
    num_starts: int = 8,
    iterations: int = 64,
) -> Witness:
    """`find_point` with the constraints given by one function, `constraints(t, x, args) ->
    (equalities, inequalities)` (two 1-D arrays), for constraints that share their work."""
    ts = jnp.asarray(ts)
    xs = jnp.asarray(xs)
    if xs.ndim != 2 or ts.shape != xs.shape[:1]:
        raise ValueError(f"find_point: `ts` must be (N,) and `xs` (N, n); got {ts.shape} and {xs.shape}.")
    dtype = jnp.result_type(xs.dtype, ts.dtype, float)
    ts, xs = ts.astype(dtype), xs.astype(dtype)
    k = min(int(num_starts), xs.shape[0])

    def violation(t, x):
        return _violation(constraints, t_bounds, t, x, args)

    scores = jax.vmap(violation)(ts, xs)
    _, best = jax.lax.top_k(-scores, k)
    t0, x0 = ts[best], xs[best]
    # A trust region (dogleg) rather than Levenberg-Marquardt: at the kink of min(c, 0), where
    # an inequality becomes active, Levenberg-Marquardt's damping crawls (a unit circle tangent
    # to a half-plane: 64 steps, still 1e-3 away; dogleg: 16 steps to rounding). Least squares
    # close to least-norm, as the Jacobian is often rank-deficient (a constraint not involving
    # every component, fewer constraints than unknowns).
    solver = optx.Dogleg(rtol=1e-12, atol=1e-14, linear_solver=_DampedLeastSquares())

    def refine(t, x):
        # One flat vector of unknowns: `_DampedLeastSquares` solves with the Jacobian's matrix.
        if t_bounds is None:
            fn = _with_jacobian(lambda y: _finite(_residuals(constraints, None, t, y, args)))
            sol = optx.least_squares(fn, solver, x, max_steps=iterations, throw=False)
            return t, sol.value
        fn = _with_jacobian(
            lambda y: _finite(_residuals(constraints, None, _time_of(y[0], *t_bounds), y[1:], args))
        )
        y0 = jnp.concatenate([_angle_of(t, *t_bounds)[None].astype(dtype), x])
        sol = optx.least_squares(fn, solver, y0, max_steps=iterations, throw=False)
        return _time_of(sol.value[0], *t_bounds).astype(dtype), sol.value[1:]

    t1, x1 = jax.vmap(refine)(t0, x0)
    cand_t = jnp.concatenate([t0, t1])
    cand_x = jnp.concatenate([x0, x1])
    cand_v = jax.vmap(violation)(cand_t, cand_x)
    i = jnp.argmin(cand_v)
    return Witness(found=cand_v[i] <= tol, t=cand_t[i], x=cand_x[i], violation=cand_v[i])


def box_samples(
    key: PRNGKeyArray,
    bounds: tuple[Float[ArrayLike, " n"], Float[ArrayLike, " n"]] | None = None,
    num_samples: int | None = None,
    *positional: Any,
    **shorthands: Any,
) -> Float[Array, "num_samples n"]:
    r"""`num_samples` points drawn uniformly in the box `bounds = (lower, upper)`
    (componentwise), from the `jax.random` key `key`:
    $x = \text{lower} + u\,(\text{upper} - \text{lower})$ with $u \sim U[0, 1)^n$.

    **Keyword shorthands:** `lower=`, `upper=` build `bounds`; `num` is `num_samples`
    (passing a name with its shorthand is a `ValueError` naming both). The positional form
    `box_samples(key, lower, upper, num_samples)` is the same call.

    !!! Example

        ```python
        xs = hj.box_samples(jax.random.key(0), (-2.0 * jnp.ones(2), 2.0 * jnp.ones(2)), 64)
        ```
    """
    if len(positional) == 1:  # box_samples(key, lower, upper, num_samples)
        if bounds is None or num_samples is None or {"lower", "upper", "num"} & set(shorthands):
            raise TypeError("box_samples: pass box_samples(key, bounds, num_samples) or "
                            "box_samples(key, lower, upper, num_samples).")
        bounds, num_samples = (bounds, num_samples), positional[0]
    elif positional:
        raise TypeError(f"box_samples() takes at most 4 positional arguments, got {3 + len(positional)}.")
    lower, upper = bounds_of("box_samples", bounds, shorthands)
    num = one_of("box_samples", num_samples=num_samples, num=shorthands.pop("num", None), default=None)
    if shorthands:
        raise TypeError(f"box_samples() got an unexpected keyword argument {sorted(shorthands)[0]!r}.")
    if lower is None or upper is None or num is None:
        raise TypeError("box_samples: needs bounds=(lower, upper) and num_samples.")
    lower, upper = jnp.asarray(lower), jnp.asarray(upper)
    dtype = jnp.result_type(lower.dtype, upper.dtype, float)
    u = jax.random.uniform(key, (num,) + lower.shape, dtype)
    return lower[None] + u * (upper - lower)[None]
