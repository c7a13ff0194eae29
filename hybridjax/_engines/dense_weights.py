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
    (solver, thetas, dtype) in a process, by one small function compiled once per solver and
    dtype (thetas padded to a multiple of `_THETA_PAD`, so that every call shares it).
    (Evaluated op by op, each primitive would compile on its own.)
    """
    return _dense_weights(interpolation_cls, num_stages, tuple(float(t) for t in thetas),
                          jnp.dtype(dtype).name)


_THETA_PAD = 16


@functools.lru_cache(maxsize=64)
def _dense_weights(interpolation_cls, num_stages: int, thetas: tuple, dtype: str):
    m = len(thetas)
    dtype = jnp.dtype(dtype)
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


@functools.lru_cache(maxsize=16)
def _dense_weights_fn(interpolation_cls, num_stages: int, num_thetas: int, dtype: str):
    """The compiled function behind `_dense_weights`: the interpolant and its theta-derivative
    on the unit interval at each of `num_thetas` thetas, for each basis vector.

    Compiled ahead of time, once per key, and called: it runs at once, even while the caller's
    program is being traced (a jitted call would be staged into it; under
    `ensure_compile_time_eval` each operation on constants inside it would be run, and
    compiled, on its own)."""

    dtype = jnp.dtype(dtype)
    B = 2 + num_stages
    # The interpolant is linear in (y0, y1, k_i): evaluated on a state of dimension B with
    # y0 = e_0, y1 = e_1 and k_i = e_(2+i), its value is the row of weights itself.
    eye = np.eye(B, dtype=dtype)

    def value(th):
        one, e = jnp.ones_like(th), jnp.asarray(eye)
        return interpolation_cls(t0=0 * one, t1=one, y0=e[0], y1=e[1], k=e[2:]).evaluate(th)

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
