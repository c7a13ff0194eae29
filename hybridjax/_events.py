"""Event logic: the epoch-start test, crossing detection on a step, and root location.

- Start of an epoch (execution rule 3, docs: Execution semantics): transition k fires at
  once when g_k < -band, or when |g_k| <= band and g_k is *trending negative*: its first
  non-zero Lie derivative along the flow is negative (A. M. Johnson, "Hybrid Dynamical
  Systems", eq. (7)). A guard inside the band that is not trending negative is *departing*:
  it is disarmed (its previous value is taken as 0) until the flow has been seen to leave it
  (g > 0), so that a bouncing ball does not re-fire after its reset.
- Within a step (execution rule 2): each guard is sampled on the step's dense interpolant at
  `interior_points` interior points and the end; a crossing is the first sample with g <= 0
  after a sample with g > 0, so a guard that dips below zero and comes back inside one step
  is caught (as DifferentialEquations.jl's `interp_points`). Between two samples, g may still
  dip below zero and come back (a near-grazing crossing): where g has a local minimum between
  two positive samples (slopes - then +) and the end tangents allow a value <= 0, the minimum
  is found on the interpolant (`locate_minimum`); a minimum < 0 is a crossing. A minimum of
  exactly 0 (tangency) is not: the guard is touched, not entered.
- Location: a bracketed Newton iteration on the interpolant, falling back to bisection,
  stopping when the bracket is narrower than the event tolerance; the event time is the
  bracket's right end, where g <= 0 (so the pre-event state lies in the guard set).
"""

import jax
import jax.numpy as jnp
from jax import lax

from ._fast_rk import fold


def trending_negative(L1, L2, L3, scale1, eps) -> jax.Array:
    """First non-zero Lie derivative negative. L1 counts as zero below 64 eps * scale1."""
    l1_nonzero = jnp.abs(L1) > 64 * eps * scale1
    higher = jnp.where(L2 != 0, L2 < 0, L3 < 0)
    return jnp.where(l1_nonzero, L1 < 0, higher)


def strictly_inside(jets) -> jax.Array:
    """Per watched function, whether the state lies strictly inside its set, beyond the
    tolerance band: g < -band. A transition that fires at the start of an epoch for this
    reason was not reached by the flow: a reset (or the initial state) put the state inside
    its guard. Legitimate where resets chain (a plastic impact that lands inside the lift-off
    guard), and the mark of a modelling mistake elsewhere (a hopper whose apex lies below its
    touchdown height); `Solution.inside_guard` records it per event."""
    return jets["L0"] < -jets["band"]


def start_decision(jets, outgoing, eps):
    """Which guards fire at the start of an epoch, and the guards' starting values.

    Returns `(fire, g_start)`: `fire` (K,) bool; `g_start` (K,) the value each guard starts
    the epoch with, 0 for departing (disarmed) guards, +1 for guards not leaving the mode.
    """
    L0, band = jets["L0"], jets["band"]
    in_band = jnp.abs(L0) <= band
    neg = trending_negative(jets["L1"], jets["L2"], jets["L3"], jets["scale1"], eps)
    fire = outgoing & (strictly_inside(jets) | (in_band & neg))
    g_start = jnp.where(outgoing, jnp.where(L0 > band, L0, jnp.zeros_like(L0)), 1.0)
    return fire, g_start


def carries_step(dt0, explicit: bool) -> bool:
    """Whether epochs after the first start with the controller's last proposal (`first_step`):
    with an explicit solver and no `dt0` given."""
    return dt0 is None and explicit


def first_step(initial, proposed, carry: bool):
    """The first step of an epoch, before `departure_step_bound` caps it.

    The first epoch starts with `initial`, the controller's initial step (Hairer's rule, or
    `dt0`). With an explicit solver and no `dt0` (`carry`, from `carries_step`), a later
    epoch (`proposed` > 0: the step size the controller proposed after the step that ended
    the previous epoch) starts with that proposal, as DifferentialEquations.jl keeps its step
    size across a callback: Hairer's rule does not know the scale the solve has already
    found and at tight tolerances starts far below it, which costs several more steps per
    epoch. If the reset has changed the scale, the controller rejects and shrinks the step as
    it would anywhere:
    an explicit step across a transient faster than itself is unstable, its error estimate
    large. An implicit step across one is stable and can be accepted while its dense output
    (Hermite, where events are located) is far off: the stiff relay with Kvaerno3/5, a
    1e-6 s lag restarted at each switch, located every switch after the first wrongly.
    Implicit solvers therefore start every epoch with Hairer's rule, which sees the
    transient. A `dt0` given by the user starts every epoch.

    The epochs' first steps are then taken at the tolerance rather than far inside it: at a
    given tolerance the error can be larger (the thermostat at 1e-8: 1.8e-6 against 1.9e-7),
    at a given error the run is as fast or faster (`benchmarks/work_precision.py`).
    """
    return jnp.where(proposed > 0, proposed, initial) if carry else initial


def departure_step_bound(jets, outgoing, fire) -> jax.Array:
    """A first step short enough to see a departing guard positive before it returns.

    Along the Taylor polynomial g(s) = L0 + L1 s + L2 s^2 / 2 of a departing guard (L0 ~ 0,
    L1 > 0, L2 < 0) the flow comes back into the guard at s = 2 L1 / |L2|; half of that,
    so that an interior sample sees g > 0 (e.g. a ball bouncing with tiny velocity).
    """
    L0, L1, L2, band = jets["L0"], jets["L1"], jets["L2"], jets["band"]
    departing = outgoing & (jnp.abs(L0) <= band) & ~fire & (L1 > 0) & (L2 < 0)
    safe_L2 = jnp.where(departing, L2, -1.0)
    tau = jnp.where(departing, L1 / (-safe_L2), jnp.inf)
    return fold(jnp.minimum, tau) if tau.shape[0] else jnp.asarray(jnp.inf, tau.dtype)


def nonfinite_step(finite_state, finite_watched, proposed, h, t, eps):
    """The rule for a step with a non-finite value in it: reject it and shrink, or stop.

    A step whose end state (so some flow stage) or whose watched values (guards and domain
    functions, at the interior samples and the end) are not all finite is rejected, whatever
    its error estimate, and the next try is a quarter as long: a guard or flow that is
    undefined only beyond some time (e.g. NaN past t = 1) is then approached from below, and
    the events before it are located as usual. Only when the step has shrunk to the
    resolution of t, h <= 64 eps max(|t|, h), is the non-finite value at the current time
    itself: the execution ends there (`NONFINITE`), keeping everything computed before.

    Returns `(finite, next_h, stuck)`: whether the step is finite, the next step size (the
    controller's `proposed` where finite, h / 4 otherwise) and whether to stop.
    """
    finite = finite_state & finite_watched
    next_h = jnp.where(finite, proposed, 0.25 * h)
    stuck = ~finite & (h <= 64 * eps * jnp.maximum(jnp.abs(t), h))
    return finite, next_h, stuck


def step_collapsed(finite, next_h, t, eps):
    """The rule for a step size that has collapsed: the next step proposed by the controller,
    with every value finite, is at the resolution of t, next_h <= 16 eps |t|. The solver cannot
    meet its tolerance with any step that still moves t (a flow blowing up in finite time,
    x' = x^2 near t = 1 / x0, is the common cause): the execution ends `STEP_COLLAPSE` at t,
    instead of creeping on by an ulp per step until `MAX_STEPS`."""
    return finite & (next_h <= 16 * eps * jnp.abs(t))


def first_crossings(g_start, samples):
    """Per guard, whether and where it first goes from > 0 to <= 0 over the samples.

    `g_start` (K,) the values at the step's start; `samples` (m+1, K) at the interior points
    and the end. Returns `(has, j)`: crossing between sample j-1 and j (sample -1 = start).
    """
    prev = jnp.concatenate([g_start[None], samples[:-1]], axis=0)
    cross = (samples <= 0) & (prev > 0)
    return jnp.any(cross, axis=0), jnp.argmax(cross, axis=0)


def locate_root(f, a, b, tol, max_iter: int = 64):
    """Right end of a bracket [a, b] of a root of f, f(a) > 0 >= f(b), narrower than `tol`.

    Newton's method with the derivative of f (forward-mode AD) from the regula-falsi point,
    falling back to bisection when a Newton step leaves the bracket or is not at most half
    the step before last (Numerical Recipes' rtsafe). Each iterate x_k is followed by a probe
    at x_k + delta_k if f(x_k) > 0, else at x_k - delta_k (towards the root), delta_k =
    2 |x_k - x_{k-1}| clipped to [max(tol/1000, 4 ulp), tol/2]: once Newton converges
    quadratically the root lies well within |x_k - x_{k-1}| of x_k, so x_k and the probe
    straddle it and the bracket closes at once (a fixed tiny delta would wait for Newton to
    land within rounding noise of the root, and bisect ~40 times instead). A final
    Newton step from the right end then puts it a few ulps past the root (g <= 0 kept).
    No gradients: the caller differentiates the event time by the implicit function theorem.
    """
    a, b, tol = lax.stop_gradient((a, b, tol))
    fa, fb = f(a), f(b)
    denom = fa - fb
    x0 = jnp.where(denom > 0, a + (b - a) * fa / jnp.where(denom > 0, denom, 1.0), 0.5 * (a + b))
    x0 = jnp.clip(x0, a, b)

    def cond(c):
        a, b, *_, i = c
        return (b - a > tol) & (i < max_iter)

    def body(c):
        a, b, x, dx, dx_old, i = c
        fx, dfx = jax.jvp(f, (x,), (jnp.ones_like(x),))
        floor = jnp.maximum(1e-3 * tol, 4 * jnp.finfo(x.dtype).eps * jnp.abs(x))
        delta = jnp.clip(2 * jnp.abs(dx), floor, jnp.maximum(0.5 * tol, floor))
        # One probe, on the side of x where the root lies (a probe on the other side moves the
        # bracket only if f changes sign twice within delta). The two points are written out,
        # not stacked: elementwise code that XLA fuses into a few kernels per iteration (a stack
        # and a reduction over it do not fuse under vmap).
        probe = jnp.clip(jnp.where(fx > 0, x + delta, x - delta), a, b)
        a_new, b_new = a, b
        for p, fp in ((x, fx), (probe, f(probe))):
            finite = jnp.isfinite(fp)
            a_new = jnp.where(finite & (fp > 0), jnp.maximum(a_new, p), a_new)
            b_new = jnp.where(finite & (fp <= 0), jnp.minimum(b_new, p), b_new)
        step = fx / jnp.where(dfx != 0, dfx, 1.0)
        xn = x - step
        # As in rtsafe: take Newton's step if it stays in the bracket and is at most half the
        # step before last (converging); bisect otherwise.
        ok = (dfx != 0) & jnp.isfinite(xn) & (xn > a_new) & (xn < b_new)
        ok = ok & (2 * jnp.abs(step) <= jnp.abs(dx_old))
        mid = 0.5 * (a_new + b_new)
        xn = jnp.where(ok, xn, mid)
        return a_new, b_new, xn, jnp.abs(xn - x), dx, i + 1

    a, b, *_ = lax.while_loop(cond, body, (a, b, x0, b - a, 2 * (b - a), jnp.array(0)))
    # Polish: one Newton step from b (within tol of the root, so it lands within rounding of
    # it), then the first of three points 4, 16, 64 ulp to its right where f <= 0, else b. The
    # few ulps of margin keep g <= 0 when the caller re-evaluates the state there (its
    # arithmetic rounds differently by an ulp or so).
    fb, dfb = jax.jvp(f, (b,), (jnp.ones_like(b),))
    xp = b - fb / jnp.where(dfb != 0, dfb, 1.0)
    ulp = jnp.finfo(b.dtype).eps * jnp.maximum(jnp.abs(xp), jnp.finfo(b.dtype).tiny)
    out = b
    for m in (64.0, 16.0, 4.0):  # the last one written wins: the first good one
        cand = xp + m * ulp
        good = (f(cand) <= 0) & (cand > a) & (cand <= b) & jnp.isfinite(cand) & (dfb != 0)
        out = jnp.where(good, cand, out)
    return out


def dip_candidates(V, D, s_ext):
    """Per guard, an interval of the step where g may dip below zero between two samples.

    `V` (m+2, K) guard values at the step's start, interior points and end (all > 0 for a
    dip), `D` (m+2, K) their derivatives along the step, `s_ext` (m+2,) the sample times.
    An interval with g > 0 at both ends, D < 0 at the left and D > 0 at the right holds a
    local minimum of g. Where g is convex there, it lies above both end tangents, whose
    intersection value `low` is therefore a lower bound; the interval is a candidate when
    low <= 0. Returns `(suspect, i, x0)`: whether each guard has a candidate, the first
    candidate interval, and the tangents' intersection there (a start for `locate_minimum`).
    """
    h = jnp.diff(s_ext)[:, None]
    V0, V1, D0, D1 = V[:-1], V[1:], D[:-1], D[1:]
    shape = (V0 > 0) & (V1 > 0) & (D0 < 0) & (D1 > 0)
    den = jnp.where(shape, D0 - D1, -1.0)
    u = jnp.clip((V1 - V0 - D1 * h) / den, 0.0, h)
    low = V0 + D0 * u
    cand = shape & (low <= 0)
    i = jnp.argmax(cand, axis=0)
    x0 = s_ext[i] + jnp.take_along_axis(u, i[None], axis=0)[0]
    return jnp.any(cand, axis=0), i, x0


def locate_minimum(f, a, b, x0, tol, max_iter: int = 32):
    """The minimum of f on [a, b] (f' < 0 at a, > 0 at b), or the first point found with f < 0.

    Newton's method on f' (f' and f'' by nested forward-mode AD), kept inside a shrinking
    bracket [a, b] with f'(a) < 0 < f'(b), bisecting when a Newton step would leave it; stops
    as soon as some f(x) < 0 (a crossing is proven), when the step or bracket is below
    `tol`, or after `max_iter` iterations. Returns `(x, f(x))` at the lowest point seen.
    """
    a, b, x0, tol = lax.stop_gradient((a, b, x0, tol))
    one = jnp.ones_like(x0)

    def slope(x):
        return jax.jvp(f, (x,), (one,))[1]

    def cond(c):
        a, b, _, step, f_best, _, i = c
        return (f_best >= 0) & (b - a > tol) & (jnp.abs(step) > 0.5 * tol) & (i < max_iter)

    def body(c):
        a, b, x, _, f_best, x_best, i = c
        fx = f(x)
        d1, d2 = jax.jvp(slope, (x,), (one,))
        better = fx < f_best
        f_best, x_best = jnp.where(better, fx, f_best), jnp.where(better, x, x_best)
        a = jnp.where(d1 < 0, x, a)
        b = jnp.where(d1 > 0, x, b)
        xn = x - d1 / jnp.where(d2 > 0, d2, 1.0)
        ok = (d2 > 0) & jnp.isfinite(xn) & (xn > a) & (xn < b)
        xn = jnp.where(ok, xn, 0.5 * (a + b))
        step = jnp.where(d1 == 0, 0.0, xn - x)
        return a, b, xn, step, f_best, x_best, i + 1

    init = (a, b, jnp.clip(x0, a, b), jnp.asarray(jnp.inf, x0.dtype), jnp.asarray(jnp.inf, x0.dtype),
            x0, jnp.array(0))
    _, _, _, _, f_best, x_best, _ = lax.while_loop(cond, body, init)
    return x_best, f_best
