"""The engines' dense output: the weights of diffrax's interpolation at fixed fractions of a step,
and its Chebyshev form about the step's ends, as linear maps of the step's stages."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._core.xla_options import FAST_COMPILE_CPU
from .._step.runge_kutta import (
    weighted_sum,
)


def dense_weights(interpolation_cls, num_stages: int, thetas, dtype):
    """Weights of the solver's dense output on the unit interval at the fractions `thetas`.

    Returns `(value, slope)`, each a list of (a, b, [c_i]) with
    y(theta) = a y0 + b y1 + sum_i c_i k_i and dy/dtheta likewise (diffrax's interpolations
    are linear in y0, y1 and the stage increments k_i); computed at trace time, once per
    (solver, thetas, dtype) in a process, from the interpolation's program, traced once per solver
    and dtype: evaluated by numpy (`_numpy_weights`), or, where it uses a primitive
    `_eval_numpy` does not know, compiled (thetas padded to a multiple of `_THETA_PAD`, so that
    every call shares it). (Evaluated op by op in JAX, each primitive would compile on its own.)
    """
    return _dense_weights(interpolation_cls, num_stages, tuple(float(t) for t in thetas),
                          jnp.dtype(dtype).name)


_THETA_PAD = 16


@functools.lru_cache(maxsize=64)
def _dense_weights(interpolation_cls, num_stages: int, thetas: tuple, dtype: str):
    m = len(thetas)
    dtype = jnp.dtype(dtype)
    try:
        both = _numpy_weights(interpolation_cls, num_stages, thetas, dtype)
    except _NotInNumpy:
        th = np.zeros(-(-m // _THETA_PAD) * _THETA_PAD, dtype)
        th[:m] = thetas
        both = _dense_weights_fn(interpolation_cls, num_stages, th.shape[0], dtype)(th)
    out = []
    for weights in both:
        weights = np.asarray(weights)[:m]  # (thetas, basis)
        out.append([(float(w[0]), float(w[1]), [float(v) for v in w[2:]]) for w in weights])
    return out


def stage_combination(weights, y0, y1, ks):
    """a y0 + b y1 + sum_i c_i k_i for one `(a, b, [c_i])` of `dense_weights` (or a row of
    `chebyshev_weights`, one coefficient of q): the dense output's value or slope at one
    fraction, elementwise."""
    a, b, c = weights
    return a * y0 + b * y1 + weighted_sum(c, list(ks), y0)


def _basis_interpolant(interpolation_cls, num_stages: int, dtype):
    """theta -> the interpolant at theta on the unit interval for y0 = e_0, y1 = e_1 and
    k_i = e_(2+i): the interpolant is linear in (y0, y1, k_i), so its value is the row of weights."""
    eye = np.eye(2 + num_stages, dtype=dtype)

    def value(th):
        one, e = jnp.ones_like(th), jnp.asarray(eye)
        return interpolation_cls(t0=0 * one, t1=one, y0=e[0], y1=e[1], k=e[2:]).evaluate(th)

    return value


@functools.lru_cache(maxsize=16)
def _interpolant_program(interpolation_cls, num_stages: int, dtype):
    """The program (a closed jaxpr) of the interpolant and its theta-derivative at one theta,
    traced once per solver and dtype: every set of thetas (`chebyshev_weights`'s nodes, the
    engines' samples) evaluates the same one."""
    value = _basis_interpolant(interpolation_cls, num_stages, dtype)
    return jax.make_jaxpr(lambda th: jax.jvp(value, (th,), (jnp.ones_like(th),)))(np.zeros((), dtype))


def _numpy_weights(interpolation_cls, num_stages: int, thetas: tuple, dtype):
    """(value, slope) rows at each theta, as `_dense_weights_fn` computes them:
    `_interpolant_program` evaluated by numpy at each theta (`_eval_numpy`). Raises
    `_NotInNumpy` where the program uses a primitive `_eval_numpy` does not know.

    Why: the weights are needed while the caller's program is traced; compiling a program of
    their own costs about a tenth of a second of a process's first call, tracing this one and
    evaluating it about ten milliseconds."""
    closed = _interpolant_program(interpolation_cls, num_stages, jnp.dtype(dtype))
    rows = [_eval_numpy(closed.jaxpr, closed.consts, np.asarray(th, dtype)) for th in thetas]
    return tuple(np.stack([r[i] for r in rows]) for i in range(2))


class _NotInNumpy(Exception):
    """A primitive `_eval_numpy` does not evaluate."""


def _broadcast_in_dim(x, shape, broadcast_dimensions, **_):
    kept = [1] * len(shape)
    for axis, size in zip(broadcast_dimensions, np.shape(x), strict=True):
        kept[axis] = size
    return np.broadcast_to(np.reshape(x, kept), shape)


def _dot_general(a, b, dimension_numbers, **_):
    (ca, cb), (ba, bb) = dimension_numbers
    letters = iter("abcdefghijklmnopqrstuvwxyz")
    sa = [next(letters) for _ in range(np.ndim(a))]
    sb = [next(letters) for _ in range(np.ndim(b))]
    for i, j in zip((*ca, *ba), (*cb, *bb), strict=True):
        sb[j] = sa[i]
    out = [sa[i] for i in ba] + [c for i, c in enumerate(sa) if i not in (*ca, *ba)]
    out += [c for j, c in enumerate(sb) if j not in (*cb, *bb)]
    return np.einsum(f"{''.join(sa)},{''.join(sb)}->{''.join(out)}", a, b)


def _scan(*args, jaxpr, length, reverse, num_consts, num_carry, **_):
    if length == 0:
        raise _NotInNumpy("scan of length 0")
    split = num_consts + num_carry
    consts, carry, xs = args[:num_consts], args[num_consts:split], args[split:]
    ys = []
    for i in (reversed(range(length)) if reverse else range(length)):
        out = _eval_numpy(jaxpr.jaxpr, jaxpr.consts, *consts, *carry, *(x[i] for x in xs))
        carry, y = out[:num_carry], out[num_carry:]
        ys.append(y)
    ys = ys[::-1] if reverse else ys
    stacked = [np.stack([y[j] for y in ys]) for j in range(len(jaxpr.jaxpr.outvars) - num_carry)]
    return (*carry, *stacked)


def _divide(a, b):
    if not np.issubdtype(np.result_type(a, b), np.inexact):
        raise _NotInNumpy("div of integers")  # XLA rounds toward zero, numpy down
    return np.divide(a, b)


def _elementwise(fn):
    """A numpy function of the inputs alone (an elementwise primitive's parameters, such as its
    result's dtype, are applied by `_eval_numpy`)."""
    return lambda *xs, **_: fn(*xs)


# primitive name -> numpy function of (*inputs, **params) returning one array or a tuple.
_NUMPY = {
    **{name: _elementwise(fn) for name, fn in {
        "add": np.add, "add_any": np.add, "sub": np.subtract, "mul": np.multiply, "div": _divide,
        "neg": np.negative, "max": np.maximum, "min": np.minimum, "abs": np.abs, "sqrt": np.sqrt,
        "exp": np.exp, "log": np.log, "sin": np.sin, "cos": np.cos, "square": np.square,
        "eq": np.equal, "ne": np.not_equal, "lt": np.less, "le": np.less_equal, "gt": np.greater,
        "ge": np.greater_equal, "and": np.logical_and, "or": np.logical_or, "not": np.logical_not,
    }.items()},
    "integer_pow": lambda x, y: x**y,
    "select_n": lambda which, *cases: np.choose(np.asarray(which, int), np.broadcast_arrays(*cases)),
    "convert_element_type": lambda x, new_dtype, **_: np.asarray(x).astype(new_dtype),
    "slice": lambda x, start_indices, limit_indices, strides: x[tuple(
        slice(a, b, c) for a, b, c in zip(start_indices, limit_indices, strides or [1] * len(start_indices),
                                          strict=True))],
    "squeeze": lambda x, dimensions: np.squeeze(x, axis=tuple(dimensions)),
    "reshape": lambda x, new_sizes, dimensions=None, **_: np.reshape(x, new_sizes),
    "stack": lambda *xs, axis: np.stack(xs, axis=axis),
    "concatenate": lambda *xs, dimension: np.concatenate(xs, axis=dimension),
    "transpose": lambda x, permutation: np.transpose(x, permutation),
    "reduce_sum": lambda x, axes, **_: np.sum(x, axis=tuple(axes)),
    "broadcast_in_dim": _broadcast_in_dim,
    "dot_general": _dot_general,
    "copy": lambda x: x, "copy_p": lambda x: x,
    "jit": lambda *xs, jaxpr, **_: _eval_numpy(jaxpr.jaxpr, jaxpr.consts, *xs),
    "pjit": lambda *xs, jaxpr, **_: _eval_numpy(jaxpr.jaxpr, jaxpr.consts, *xs),
    "scan": _scan,
}


def _eval_numpy(jaxpr, consts, *args) -> list:
    """The outputs of `jaxpr` evaluated by numpy, each in its variable's dtype; raises
    `_NotInNumpy` at a primitive that `_NUMPY` lacks."""
    env = {}

    def read(v):
        return np.asarray(v.val, v.aval.dtype) if hasattr(v, "val") else env[v]

    for var, value in zip((*jaxpr.constvars, *jaxpr.invars), (*consts, *args), strict=True):
        env[var] = np.asarray(value)
    for eqn in jaxpr.eqns:
        rule = _NUMPY.get(eqn.primitive.name)
        if rule is None:
            raise _NotInNumpy(eqn.primitive.name)
        try:
            out = rule(*map(read, eqn.invars), **eqn.params)
        except _NotInNumpy:
            raise
        except Exception as e:  # a form of the primitive the rule does not cover: compile instead
            raise _NotInNumpy(f"{eqn.primitive.name}: {e}") from e
        outs = out if eqn.primitive.multiple_results else (out,)
        for var, value in zip(eqn.outvars, outs, strict=True):
            env[var] = np.asarray(value).astype(var.aval.dtype, copy=False)
    return [read(v) for v in jaxpr.outvars]


@functools.lru_cache(maxsize=16)
def _dense_weights_fn(interpolation_cls, num_stages: int, num_thetas: int, dtype: str):
    """The compiled function behind `_dense_weights`: the interpolant and its theta-derivative
    on the unit interval at each of `num_thetas` thetas, for each basis vector.

    Compiled ahead of time, once per key, and called: it runs at once, even while the caller's
    program is being traced (a jitted call would be staged into it; under
    `ensure_compile_time_eval` each operation on constants inside it would be run, and
    compiled, on its own)."""

    dtype = jnp.dtype(dtype)
    value = _basis_interpolant(interpolation_cls, num_stages, dtype)

    def both(th):
        return jax.vmap(lambda s: jax.jvp(value, (s,), (jnp.ones_like(s),)))(th)

    # A few kernels run once: compiled by XLA:CPU's own emitters, which compile it sooner.
    return jax.jit(both).lower(jax.ShapeDtypeStruct((num_thetas,), dtype)).compile(
        compiler_options=FAST_COMPILE_CPU if jax.default_backend() == "cpu" else None)


CHEB_DEGREE = 9  # >= the degree in theta of every unrolled solver's dense output


def chebyshev_weights(interpolation_cls, num_stages: int, dtype, degree: int = CHEB_DEGREE):
    r"""The solver's dense output on the unit interval, written about the step's ends,

    $$y(\theta) = y_0 + \theta\,\Delta y + \theta (1 - \theta)\, q(\theta), \qquad
    \Delta y = y_1 - y_0,$$

    with $q$ in the Chebyshev basis: $q(\theta) = \sum_m T_m(2\theta - 1)\,(A_{m1} \Delta y +
    \sum_i A_{m(2+i)} k_i)$. $q = (y - y_0 - \theta\,[y(1) - y_0]) / (\theta (1 - \theta))$ is a
    polynomial (the numerator vanishes at both ends): the numerator's Chebyshev transform at
    `degree` + 1 nodes (exact for degrees <= `degree`) divided by $\theta (1 - \theta)$ as a
    series; $y(1) = y_1$ for the solver's own step, to rounding (Dopri8's interpolant ends
    ~1e-12 from it; the form meets $y_0 + \Delta y$, spreading that miss linearly). Near the
    start the terms are as small as the change since it (a Chebyshev series of $y$ itself sums
    terms of the size of the whole step's change: a long step's dense output would round at
    that scale where a guard crosses zero early in the step); towards the end,
    $y_0 + \theta\,\Delta y$ rounds at the scale of $|y_0|$ and $|\Delta y|$, one part in 1e16 of the
    step's change. Returns A as nested lists, columns (y0, y1, k_1, ...) with
    $A_{m0} = -A_{m1}$, one row per degree up to $q$'s own."""
    nodes = np.cos(np.pi * (np.arange(degree + 1) + 0.5) / (degree + 1))
    thetas = (nodes + 1) / 2
    value, _ = dense_weights(interpolation_cls, num_stages, (*thetas, 1.0), dtype)
    V = np.array([[a, b, *c] for a, b, c in value])  # (nodes + 1, 2 + stages)
    V, end = V[:-1], V[-1]
    start = np.zeros_like(end)
    start[0] = 1.0
    L = V - (1 - thetas)[:, None] * start - thetas[:, None] * end  # y - [(1 - th) y(0) + th y(1)]
    T = np.cos(np.outer(np.arange(degree + 1), np.arccos(nodes)))  # T_m(x_j)
    C = (2.0 / (degree + 1)) * T @ L
    C[0] /= 2
    # Rows past the interpolant's true degree (4 for Tsit5 and Dopri5, 3 for Bosh3, 6 for
    # Dopri8) hold only rounding: dropped, each evaluation's recurrence is that much shorter.
    size = np.abs(C).max(axis=1)
    big = np.nonzero(size > 64 * np.finfo(dtype).eps * max(size.max(), 1.0))[0]
    C = C[:max(3, 1 + int(big.max()) if big.size else 0)]
    # q = L / (theta (1 - theta)), theta (1 - theta) = (1 - x^2) / 4 = (T_0 - T_2) / 8: exact
    # division of Chebyshev series (L vanishes at x = +-1), column by column.
    A = np.zeros((C.shape[0] - 2, C.shape[1]))
    for j in range(C.shape[1]):
        q, rem = np.polynomial.chebyshev.chebdiv(C[:, j], [0.125, 0.0, -0.125])  # zero rows trimmed
        # L vanishes at theta = 1 by construction (the interpolant's own y(1) is subtracted), at
        # theta = 0 only if the interpolant starts at y0: else the division leaves a remainder,
        # and the series would not be the interpolant's.
        if np.max(np.abs(rem)) > 1e3 * np.finfo(dtype).eps * max(np.abs(C[:, j]).max(), 1.0):
            raise ValueError(f"{interpolation_cls.__name__}: its dense output does not meet the step's ends "
                             f"(remainder {np.max(np.abs(rem)):.1e} in column {j})")
        A[:q.shape[0], j] = q
    # y0's weight is minus y1's (constants reproduced): the series reads y1 - y0, once.
    A[:, 0] = -A[:, 1]
    return A.tolist()


class ChebyshevDense(eqx.Module):
    r"""One lane's dense output on $[t_0, t_1]$, $y_0 + \theta\,\Delta y + \theta(1-\theta)\,q(\theta)$
    with $q$ a Chebyshev series in $x = 2\theta - 1$ (Clenshaw's recurrence; `chebyshev_weights`):
    the same polynomial as diffrax's interpolation, evaluated without the small matrix products
    that vmap turns into batched dots."""

    t0: jax.Array
    t1: jax.Array
    y0: jax.Array  # (n,)
    dy: jax.Array  # (n,), y1 - y0
    coeffs: jax.Array  # (degree + 1, n), q's

    @classmethod
    def from_stages(cls, A, t0, t1, y0, y1, ks):
        """The dense output of the step from `y0` to `y1` with stages `ks` (`chebyshev_weights`
        `A`). A component constant over the step ($y_1 = y_0$, its stages zero) has $\Delta y = 0$
        and $q = 0$ exactly and evaluates to $y_0$ bit for bit (a table index kept in the state
        must not read 2 as 1.999... and truncate to 1)."""
        dy = y1 - y0
        rows = [r[1] * dy + weighted_sum(r[2:], list(ks), y0) for r in A]
        return cls(t0=t0, t1=t1, y0=y0, dy=dy, coeffs=jnp.stack(rows))

    def evaluate(self, t):
        span = self.t1 - self.t0
        theta = jnp.where(span == 0, 0.0, (t - self.t0) / jnp.where(span == 0, 1.0, span))
        x = 2 * theta - 1
        b1, b2 = jnp.zeros_like(self.coeffs[0]), jnp.zeros_like(self.coeffs[0])
        for c in self.coeffs[:0:-1]:
            b1, b2 = 2 * x * b1 - b2 + c, b1
        q = x * b1 - b2 + self.coeffs[0]
        return self.y0 + theta * self.dy + (theta * (1 - theta)) * q
