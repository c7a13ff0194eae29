"""Detection of an event on a step's dense output: crossings between guard samples and dips between
them (execution rule 2)."""

import jax.numpy as jnp


# ---------------------------------------------------------------------------- detection
def crossing(g0, g1):
    """A crossing between two consecutive samples of a watched function: g0 > 0 >= g1."""
    return (g0 > 0) & (g1 <= 0)


def dip_interval(V0, V1, D0, D1, h):
    """The dip test on one sample interval of length h, from the values V and slopes D of g at
    its ends (non-finite slopes read 0).

    An interval with g > 0 at both ends, D0 < 0 and D1 > 0 holds a local minimum of g. Where g
    is convex there, it lies above both end tangents, which meet at offset

        u = clip((V1 - V0 - D1 h) / (D0 - D1), 0, h),

    where the tangent from the left has the value V0 + D0 u, a lower bound of g; the interval
    is a dip candidate when that bound is <= 0. Returns `(crossing, candidate, u)`.
    """
    D0 = jnp.where(jnp.isfinite(D0), D0, 0.0)
    D1 = jnp.where(jnp.isfinite(D1), D1, 0.0)
    shape = (V0 > 0) & (V1 > 0) & (D0 < 0) & (D1 > 0)
    den = jnp.where(shape, D0 - D1, -1.0)
    u = jnp.clip((V1 - V0 - D1 * h) / den, 0.0, h)
    return crossing(V0, V1), shape & (V0 + D0 * u <= 0), u


def first_crossings(g_start, samples):
    """Per guard, whether and where it first goes from > 0 to <= 0 over the samples.

    `g_start` (K,) the values at the step's start; `samples` (m+1, K) at the interior points
    and the end. Returns `(has, j)`: crossing between sample j-1 and j (sample -1 = start).
    """
    prev = jnp.concatenate([g_start[None], samples[:-1]], axis=0)
    cross = crossing(prev, samples)
    return jnp.any(cross, axis=0), jnp.argmax(cross, axis=0)


def dip_candidates(V, D, s_ext):
    """Per guard, the first interval of the step where g may dip below zero between two samples
    (`dip_interval` on each).

    `V` (m+2, K) guard values at the step's start, interior points and end, `D` (m+2, K) their
    derivatives along the step, `s_ext` (m+2,) the sample times. Returns `(suspect, i, x0)`:
    whether each guard has a candidate, the first candidate interval, and the tangents'
    intersection there (a start for `locate_minimum`).
    """
    h = jnp.diff(s_ext)[:, None]
    _, cand, u = dip_interval(V[:-1], V[1:], D[:-1], D[1:], h)
    i = jnp.argmax(cand, axis=0)
    x0 = s_ext[i] + jnp.take_along_axis(u, i[None], axis=0)[0]
    return jnp.any(cand, axis=0), i, x0


def needs_location(g_start, V, D, s_ext):
    """Whether a step needs its event located: some watched function crosses between two of
    its samples, or is a dip candidate on some sample interval (`crossing`, `dip_interval`).
    `first_crossings` and `dip_candidates` say where; this says only whether, which is all a
    step without one needs (`V`, `D` as `dip_candidates`'s, with `V[0]` replaced by
    `g_start`, the values carried from the step before)."""
    V = jnp.concatenate([g_start[None], V[1:]])
    cross, cand, _ = dip_interval(V[:-1], V[1:], D[:-1], D[1:], jnp.diff(s_ext)[:, None])
    return jnp.any(cross | cand)


def dip_filter(has, j, suspect, i_d):
    """Which dip candidates to search: those before the guard's first crossing in the step (or
    of guards without one), suspect & (~has | i_d < j); a dip after a crossing is never the
    first event."""
    return suspect & (~has | (i_d < j))
