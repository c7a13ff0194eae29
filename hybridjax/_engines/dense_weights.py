"""The batched engine's dense output: the weights of diffrax's interpolation at fixed fractions of a
step, and its Chebyshev series, as linear maps of the step's stages."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

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
    eye = np.eye(2 + num_stages, dtype=dtype)  # basis: y0 = 1, y1 = 1, or one k_i = 1, the rest 0
    basis = (th, eye[:, :1], eye[:, 1:2], eye[:, 2:, None])
    both = _dense_weights_fn(interpolation_cls, num_stages, th.shape[0], dtype)(*basis)
    out = []
    for weights in both:
        weights = np.asarray(weights)[:m, :, 0]  # (thetas, basis)
        out.append([(float(w[0]), float(w[1]), [float(v) for v in w[2:]]) for w in weights])
    return out


def stage_combination(weights, y0, y1, ks):
    """a y0 + b y1 + sum_i c_i k_i for one `(a, b, [c_i])` of `dense_weights` (or a row of
    `chebyshev_weights`): the dense output's value or slope at one fraction, elementwise."""
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

    def value(th, y0, y1, k):
        one = jnp.ones_like(th)
        return interpolation_cls(t0=0 * one, t1=one, y0=y0, y1=y1, k=k).evaluate(th)

    def slope(th, y0, y1, k):
        return jax.jvp(lambda s: value(s, y0, y1, k), (th,), (jnp.ones_like(th),))[1]

    dtype = jnp.dtype(dtype)
    B = 2 + num_stages
    shapes = [jax.ShapeDtypeStruct(shape, dtype)
              for shape in ((num_thetas,), (B, 1), (B, 1), (B, num_stages, 1))]
    return jax.jit(lambda th, *b: [jax.vmap(jax.vmap(fn, in_axes=(None, 0, 0, 0)),
                                            in_axes=(0, None, None, None))(th, *b)
                                   for fn in (value, slope)]).lower(*shapes).compile()
CHEB_DEGREE = 9  # >= the degree in theta of every unrolled solver's dense output


def chebyshev_weights(interpolation_cls, num_stages: int, dtype, degree: int = CHEB_DEGREE):
    """The solver's dense output y(theta) on the unit interval in the Chebyshev basis:
    y(theta) = sum_m T_m(2 theta - 1) (A_m0 y0 + A_m1 y1 + sum_i A_m(2+i) k_i), exact for
    polynomials of degree <= `degree` (the discrete Chebyshev transform at degree + 1 nodes,
    well conditioned where monomial coefficients are not). Returns A as nested lists, one row
    per degree up to the interpolant's own."""
    nodes = np.cos(np.pi * (np.arange(degree + 1) + 0.5) / (degree + 1))
    value, _ = dense_weights(interpolation_cls, num_stages, (nodes + 1) / 2, dtype)
    V = np.array([[a, b, *c] for a, b, c in value])  # (nodes, 2 + stages)
    T = np.cos(np.outer(np.arange(degree + 1), np.arccos(nodes)))  # T_m(x_j)
    A = (2.0 / (degree + 1)) * T @ V
    A[0] /= 2
    # Rows past the interpolant's true degree (4 for Tsit5 and Dopri5, 3 for Bosh3, 6 for
    # Dopri8) hold only rounding: dropped, each evaluation's recurrence is that much shorter.
    size = np.abs(A).max(axis=1)
    keep = 1 + int(np.nonzero(size > 64 * np.finfo(dtype).eps * size.max())[0].max())
    return A[:keep].tolist()


class ChebyshevDense(eqx.Module):
    """One lane's dense output as a Chebyshev series in x = 2 theta - 1 (Clenshaw's
    recurrence): the same polynomial as diffrax's interpolation, evaluated without the small
    matrix products that vmap turns into batched dots."""

    t0: jax.Array
    t1: jax.Array
    coeffs: jax.Array  # (degree + 1, n)

    @classmethod
    def from_stages(cls, A, t0, t1, y0, y1, ks):
        """The series of the step from `y0` to `y1` with stages `ks` (`chebyshev_weights` `A`),
        written as $y_0$ plus the series of $y - y_0$: the interpolant reproduces constants
        ($a_j + b_j = [j = 0]$), so this is the same polynomial, and a component constant over
        the step ($y_1 = y_0$, its stages zero) has the coefficients $y_0, 0, 0, \dots$ exactly
        and evaluates to $y_0$ bit for bit, where $a_j y_0 + b_j y_1$ is off by rounding (a
        table index kept in the state would read 2 as 1.999... and truncate to 1)."""
        dy = y1 - y0
        rows = [r[1] * dy + weighted_sum(r[2:], list(ks), y0) for r in A]
        rows[0] = rows[0] + y0
        return cls(t0=t0, t1=t1, coeffs=jnp.stack(rows))

    def evaluate(self, t):
        span = self.t1 - self.t0
        theta = jnp.where(span == 0, 0.0, (t - self.t0) / jnp.where(span == 0, 1.0, span))
        x = 2 * theta - 1
        b1, b2 = jnp.zeros_like(self.coeffs[0]), jnp.zeros_like(self.coeffs[0])
        for c in self.coeffs[:0:-1]:
            b1, b2 = 2 * x * b1 - b2 + c, b1
        return x * b1 - b2 + self.coeffs[0]
