"""The execution rules: each rule of a hybrid execution written once, as a pure function of
one execution.

Both engines call these functions: the per-execution loop (`_loop.Loop`) directly, the batched
loop (`_batched.BatchedLoop`) lifted over its lanes, with `jax.vmap` (`BatchedLoop.lane_map`) or,
for the functions written elementwise over a leading axis of components, by broadcasting over
the lanes-last axis. An engine holds only storage and iteration (its state, the event record,
gathering and scattering of lanes, the while loop); what an execution *does* is decided here.
The rules, in the order an iteration meets them (docs: Architecture has the table of rules,
functions and tests):

- tolerances: `event_time_tol`, `step_end` (the t_next clamp), `clip_to_times` (step_ts,
  jump_ts);
- the start of an epoch: `epoch_start` (`start_decision`: the trending-negative band and Lie
  derivatives; `first_step`, `departure_step_bound`);
- a step: `nonfinite_step`, `step_collapsed`, `step_stops`;
- detection on a step's dense output: `crossing`, `dip_interval`, `first_crossings`,
  `dip_candidates`, `dip_filter`;
- location: `event_brackets` (`locate_minimum`), `first_event` (`locate_root`; the guards
  reached at one instant, `simultaneous_set`, and the simultaneity rule,
  `resolve_simultaneous`), `event_point` (the implicit-function event time);
- the jump: `blocks`, `jump_outcome`, `push_recent`, `zeno_completion`;
- saving: `saved_in_step`;
- the precedence of statuses: `stop_first`.

Event logic in detail:

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

from collections.abc import Callable
from typing import NamedTuple

import equinox.internal as eqxi
import jax
import jax.numpy as jnp
from jax import lax

from ._fast_rk import fold, unrolled_sum
from ._kernels import Kernels, mask_inputs
from ._status import Status

sg = lax.stop_gradient


# ---------------------------------------------------------------------------- typed records
class EpochStart(NamedTuple):
    """The start test of an epoch (`epoch_start`)."""

    fire: jax.Array  # () bool: some watched function fires at once (a zero-length epoch)
    k: jax.Array  # () int32: the first that fires (a guard if < K, a domain component if >= K)
    g_start: jax.Array  # (K + W,) the value each watched function starts the epoch with
    F: jax.Array  # (n,) the vector field at the start (the next step's first stage)
    finite: jax.Array  # () bool: F and the mode's watched values are finite
    h: jax.Array  # () the epoch's first step (no gradient)
    simultaneous: jax.Array  # () bool: more than one guard fires at once
    inside: jax.Array  # () bool: the state lies strictly inside the first firing set


class Detection(NamedTuple):
    """Crossings and dip candidates of each watched function on one step (`first_crossings`,
    `dip_candidates`); each field (K,) or, in the batched engine, (slots, lanes)."""

    has: jax.Array  # a crossing between samples j - 1 and j
    j: jax.Array
    suspect: jax.Array  # a dip candidate on sample interval i_d
    i_d: jax.Array
    x0_d: jax.Array  # the end tangents' intersection there (a start for `locate_minimum`)


class Brackets(NamedTuple):
    """Per watched function, whether it has an event in the step and a bracket [a, b] of its
    first one (`event_brackets`)."""

    has: jax.Array
    a: jax.Array
    b: jax.Array


class EventChoice(NamedTuple):
    """The step's first event (`first_event`)."""

    t_star: jax.Array  # its time (the step's end where there is none)
    index: jax.Array  # () int32: which watched function (0 where there is none)
    simultaneous: jax.Array  # () bool: another one is reached at the same instant


class NonfiniteStep(NamedTuple):
    """The non-finite-step rule's decision (`nonfinite_step`)."""

    finite: jax.Array
    next_h: jax.Array
    stuck: jax.Array


class ZenoCompletionStep(NamedTuple):
    """The jump of a Zeno execution to its limit (`zeno_completion`)."""

    completes: jax.Array  # Zeno detected and the mode has a completion
    index: jax.Array  # the event's transition index, K + c for completion c
    target: jax.Array  # the completion's target mode
    t: jax.Array  # the accumulation time t_inf (gradients cut where it does not complete)
    x: jax.Array  # the limit state x_inf (likewise)
    y_after: jax.Array  # the completion's reset of it


class JumpOutcome(NamedTuple):
    """What a transition does to the execution (`jump_outcome`)."""

    recorded: jax.Array  # the event fits in the record (num_events < max_epochs)
    applied: jax.Array  # recorded, and its reset is finite: the execution moves on
    zero_run: jax.Array  # the count of zero-length epochs in a row, after it
    stops: tuple  # ((pred, Status), ...) in precedence order (`stop_first`)


# ---------------------------------------------------------------------------- tolerances
def event_time_tol(event_tol, t, h, eps):
    """The event-time tolerance: `event_tol` relative to the step h, floored at 8 ulp of t,

    tol = max(event_tol |h|, 8 eps |t|).

    Root brackets are narrowed below it; guards reached within it of the first event are
    simultaneous (`simultaneous_set`); at an epoch's start it widens the band of "zero"
    (`Kernels.guard_jets`).
    """
    return jnp.maximum(event_tol * jnp.abs(h), 8 * eps * jnp.abs(t))


def step_end(t, h, t1):
    """The end of the next step: t_next = min(max(t + h, nextafter(t)), t1).

    A step always moves t by at least one ulp (a proposal below the resolution of t would
    leave it in place) and never passes the end time t1.
    """
    return jnp.minimum(jnp.maximum(t + h, t + (jnp.nextafter(sg(t), jnp.inf) - sg(t))), t1)


def _time_at(ts, i):
    """`ts[i]`, inf for i = len(ts) (no such time)."""
    return jnp.where(i < ts.shape[0], ts[jnp.minimum(i, ts.shape[0] - 1)], jnp.inf)


def _moved_past(ts, t, t1):
    """t moved past a time s of `ts` (s < t1) that it lies on (to nextafter(s)) or just before
    (t = prevbefore(s): to nextafter(s)); and whether it was."""
    up = jnp.nextafter(t, jnp.inf)
    s = _time_at(ts, jnp.searchsorted(ts, t, side="left"))  # the first time >= t
    on, before = (s == t) & (s < t1), (s == up) & (s < t1)
    return jnp.where(on, up, jnp.where(before, jnp.nextafter(up, jnp.inf), t)), on | before


def clip_to_times(t, t_next, t1, step_ts, jump_ts):
    """The step from t to t_next (`step_end`) clipped to the times the solver must step to,
    diffrax's `ClipStepSizeController` rule (`PIDController(step_ts=..., jump_ts=...)`):

    - a step time s: the step ends there, t_next = min(t_next, s), s the first of `step_ts`
      after t (after nextafter(t): where a step ended just before a jump time equal to it);
    - a jump time j, a discontinuity of the field: a step ends at prevbefore(j), the last
      float before the first j > t, and the next starts at nextafter(j), with the state of
      prevbefore(j) and the field evaluated anew there (`made_jump`). So that no stage reads
      the field at j itself: which side's value it takes there is the user's definition's.

    Jump times at or after t1 are not stepped to (the execution ends at t1). Elementwise in t,
    t_next, t1 (lanes broadcast); `step_ts`, `jump_ts` sorted 1-D arrays or None. Returns
    `(t, t_next, made_jump)`, t moved past a jump time it lies on, or just before.
    """
    t_sg = sg(t)
    made_jump = jnp.zeros(jnp.shape(t), bool)
    if step_ts is not None and step_ts.shape[0]:
        past, _ = _moved_past(step_ts, t_sg, jnp.inf)
        t_next = jnp.minimum(t_next, _time_at(step_ts, jnp.searchsorted(step_ts, past, side="right")))
    if jump_ts is not None and jump_ts.shape[0]:
        moved, made_jump = _moved_past(jump_ts, t_sg, t1)
        t = t + (moved - t_sg)  # the derivative of t kept
        t_next = jnp.maximum(jnp.nextafter(moved, jnp.inf), t_next)
        j = _time_at(jump_ts, jnp.searchsorted(jump_ts, moved, side="right"))
        t_next = jnp.minimum(jnp.where(j < t1, jnp.minimum(t_next, jnp.nextafter(j, -jnp.inf)), t_next), t1)
    return t, t_next, made_jump


# ---------------------------------------------------------------------------- start of an epoch
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
    return jets.L0 < -jets.band


def start_decision(jets, outgoing, eps):
    """Which guards fire at the start of an epoch, and the guards' starting values.

    Returns `(fire, g_start)`: `fire` (K,) bool; `g_start` (K,) the value each guard starts
    the epoch with, 0 for departing (disarmed) guards, +1 for guards not leaving the mode.
    """
    L0, band = jets.L0, jets.band
    in_band = jnp.abs(L0) <= band
    neg = trending_negative(jets.L1, jets.L2, jets.L3, jets.scale1, eps)
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
    L0, L1, L2, band = jets.L0, jets.L1, jets.L2, jets.band
    departing = outgoing & (jnp.abs(L0) <= band) & ~fire & (L1 > 0) & (L2 < 0)
    safe_L2 = jnp.where(departing, L2, -1.0)
    tau = jnp.where(departing, L1 / (-safe_L2), jnp.inf)
    return fold(jnp.minimum, tau) if tau.shape[0] else jnp.asarray(jnp.inf, tau.dtype)


def epoch_start(
    kern: Kernels, mode, t, y, args, h_prev, initial, *, carry: bool, rtol, atol, event_tol, eps
) -> EpochStart:
    """The start test of an epoch at (t, y) in `mode`: which watched function fires at once, and
    otherwise the epoch's first step.

    The watched functions' Lie derivatives L0..L3 and band (`Kernels.guard_jets`, with the
    event-time tolerance of the previous step h_prev) decide which fire (`start_decision`);
    the first that fires is k (listing order: guards, then domain components). The first step
    is `first_step(initial, h_prev, carry)`, `initial` the controller's initial step, capped by
    `departure_step_bound`. The values are taken without gradients; F, the vector field at
    (t, y), keeps those of (t, y, args) (the next step's first stage).
    """
    ts, ys, a_sg = sg(t), sg(y), sg(args)
    tol_t = event_time_tol(event_tol, ts, h_prev, eps)
    jets = kern.guard_jets(mode, ts, ys, a_sg, rtol, atol, tol_t)
    outgoing = kern.outgoing_mask(mode)
    fire, g_start = start_decision(jets, outgoing, eps)
    F = kern.flow(mode, t, y, args)
    finite = jnp.all(jnp.isfinite(F)) & jnp.all(jnp.isfinite(jnp.where(outgoing, jets.L0, 0.0)))
    k, simultaneous = resolve_simultaneous(fire, kern.num_transitions)
    inside = strictly_inside(jets)[k] if kern.num_watch else jnp.array(False)
    h = jnp.minimum(first_step(initial, h_prev, carry), departure_step_bound(jets, outgoing, fire))
    return EpochStart(
        fire=jnp.any(fire),
        k=k,
        g_start=g_start,
        F=F,
        finite=finite,
        h=sg(h),
        simultaneous=simultaneous,
        inside=inside,
    )


# ---------------------------------------------------------------------------- a step
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
    return NonfiniteStep(finite, next_h, stuck)


def step_collapsed(finite, next_h, t, eps):
    """The rule for a step size that has collapsed: the next step proposed by the controller,
    with every value finite, is at the resolution of t, next_h <= 16 eps |t|. The solver cannot
    meet its tolerance with any step that still moves t (a flow blowing up in finite time,
    x' = x^2 near t = 1 / x0, is the common cause): the execution ends `STEP_COLLAPSE` at t,
    instead of creeping on by an ulp per step until `MAX_STEPS`."""
    return finite & (next_h <= 16 * eps * jnp.abs(t))


def step_stops(stuck, finite, next_h, t, eps, num_steps, max_steps) -> tuple:
    """The stops after a step, in precedence order (`stop_first`): a non-finite step that
    cannot shrink further (`NONFINITE`, `nonfinite_step`), then a collapsed step size
    (`STEP_COLLAPSE`, `step_collapsed`), then the step limit (`MAX_STEPS`: num_steps >=
    max_steps)."""
    return (
        (stuck, Status.NONFINITE),
        (step_collapsed(finite, next_h, t, eps), Status.STEP_COLLAPSE),
        (num_steps >= max_steps, Status.MAX_STEPS),
    )


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


def dip_filter(has, j, suspect, i_d):
    """Which dip candidates to search: those before the guard's first crossing in the step (or
    of guards without one), suspect & (~has | i_d < j); a dip after a crossing is never the
    first event."""
    return suspect & (~has | (i_d < j))


# ---------------------------------------------------------------------------- location
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

    init = (
        a,
        b,
        jnp.clip(x0, a, b),
        jnp.asarray(jnp.inf, x0.dtype),
        jnp.asarray(jnp.inf, x0.dtype),
        x0,
        jnp.array(0),
    )
    _, _, _, _, f_best, x_best, _ = lax.while_loop(cond, body, init)
    return x_best, f_best


def event_brackets(values_at: Callable, det: Detection, s_ext, tol) -> Brackets:
    """Per watched function, a bracket of its first event in the step: of a dip where the
    minimum search on a dip candidate (`locate_minimum`, run only when some execution has a
    candidate) finds g < 0 (from the interval's start to that point), else of the first
    crossing (samples j - 1 to j).

    `values_at(x)`: the watched values on the step's dense output at time x; `det`: the step's
    `Detection` (`suspect` already `dip_filter`ed); `s_ext` the sample times.
    """
    has, j, suspect, i_d, x0_d = det
    s = s_ext[1:]

    def refine(_):
        def lowest(k, a_k, b_k, x_k):
            return locate_minimum(lambda x: values_at(x)[k], a_k, b_k, x_k, tol)

        return jax.vmap(lowest)(jnp.arange(has.shape[0]), s_ext[i_d], s_ext[i_d + 1], x0_d)

    x_min, g_min = lax.cond(
        eqxi.unvmap_any(jnp.any(suspect)), refine, lambda _: (x0_d, jnp.ones_like(x0_d)), None
    )
    dip = suspect & (g_min < 0)
    a = jnp.where(dip, s_ext[i_d], jnp.where(has, s_ext[j], s[j]))
    b = jnp.where(dip, x_min, s[j])
    return Brackets(has | dip, a, b)


def simultaneous_set(has, tk, t_min, tol, g_at, g_from):
    """Which watched functions are reached at the same instant as the first event, at t_min.

    Those with an event located within the event-time tolerance of t_min, tk <= t_min + tol,
    and those that are <= 0 at t_min but were > 0 at the start of the earliest bracket (their
    own bracket may be narrower than the samples): g(t_min) <= 0 < g(a_first). Which of them
    fires: `resolve_simultaneous`.
    """
    any_event = jnp.any(has)
    return has & (tk <= t_min + tol) | ((g_at <= 0) & (g_from > 0) & any_event)


def resolve_simultaneous(reached, num_counted: int | None = None):
    """The simultaneity rule: of the watched functions reached at one instant (`reached`, in
    listing order: guards in the order of the system's transitions, then domain components),
    the first fires; the event is *simultaneous* when more than one of the first `num_counted`
    (all: None) was reached. Used at the start of an epoch (`epoch_start`, counting the
    guards) and within a step (`first_event`). Returns `(index, simultaneous)`; index 0 when
    none was reached."""
    if reached.shape[0] == 0:
        return jnp.array(0, jnp.int32), jnp.array(False)
    counted = reached if num_counted is None else reached[:num_counted]
    return jnp.argmax(reached).astype(jnp.int32), jnp.sum(counted) > 1


def first_event(values_at: Callable, br: Brackets, tol, t_end) -> EventChoice:
    """The step's first event: each bracketed root located on the dense output (`locate_root`),
    the earliest time t_min, and of the watched functions reached then (`simultaneous_set`) the
    first in listing order. Located only when some execution has an event in the step (under
    `jax.vmap`, `eqxi.unvmap_any`); none: `t_end`, index 0.
    """
    has, a, b = br
    any_event = jnp.any(has)

    def locate(_):
        def root(k, a_k, b_k):
            return locate_root(lambda x: values_at(x)[k], a_k, b_k, tol)

        tk = jax.vmap(root)(jnp.arange(has.shape[0]), a, b)
        tk = jnp.where(has, tk, jnp.inf)
        first = jnp.argmin(tk)
        t_min = tk[first]
        t_at = jnp.where(any_event, t_min, b[first])
        cand = simultaneous_set(has, tk, t_min, tol, values_at(t_at), values_at(a[first]))
        i, simultaneous = resolve_simultaneous(cand)
        tk = jnp.where(cand & ~has, t_min, tk)
        return EventChoice(jnp.where(any_event, tk[i], t_end), i, simultaneous)

    def none(_):
        return EventChoice(t_end, jnp.array(0, jnp.int32), jnp.array(False))

    return lax.cond(eqxi.unvmap_any(any_event), locate, none, None)


def event_point(kern: Kernels, eps, mode, k, t_star, interp, args):
    """The event time and pre-event state, differentiable by the implicit function theorem.

    The event lies at the elapsed time u* = t* - t_s after the start t_s of its step. The
    returned time is t_s + u* - (g(t, x*) - [g]) / [D_t g + D_x g F] and the state
    x* + [F] (t - t*), with x* the dense output at the fixed elapsed time u*, F = F(t*, x*)
    the true vector field and [.] meaning stop_gradient: equal in value to (t*, x*), with

        dt = dt_s - (D_t g dt_s + D_x g dx*) / gdot,    dx = dx* + F (dt - dt_s),

    where dx* carries the dependence on the epoch's start state and parameters (the dense
    output's coefficients). Holding u* fixed, rather than t*, makes a shift of the epoch's
    start time reach the event time directly: for an autonomous flow and guard the event time
    moves one-for-one with it, exactly, whatever the solver's local error. (Through t* it
    would arrive as D_x g xdot / D_x g F, with xdot the dense output's slope: 1 + O(tol) at
    every epoch, an error of every later event's derivative that grows with the square of the
    event count.) The denominator uses F, not xdot: the true slope, accurate to the
    tolerance where the dense output's slope is one order less so.

    Also returns whether the crossing is grazing: |gdot| <= eps^(1/3) (|D_t g| + |D_x g| |F|)
    (6e-6 in float64), the flow nearly tangent to the guard, where that derivative is
    ill-conditioned.
    """
    t_s = interp.t0
    t_at = t_s + sg(t_star - t_s)  # the value t* (to rounding), the derivative of the step's start
    # The dense output at the fixed elapsed time u* for the derivative ((t_at - t_s) / h has
    # none), and at t* itself for the value: t_s + (t* - t_s) can round to a neighbour of t*.
    x_at = interp.evaluate(t_at)
    x_star = sg(interp.evaluate(t_star)) + (x_at - sg(x_at))
    F = kern.flow(mode, t_at, x_star, args)

    def g(tt, xx):
        return kern.guards(mode, tt, xx, args)[k]

    g_val = g(t_at, x_star)
    gt, gx = jax.grad(g, argnums=(0, 1))(sg(t_star), sg(x_star))
    gdot = sg(gt + unrolled_sum(gx * sg(F)))  # dg/dt along the true vector field (see `fold`)
    size = jnp.abs(gt) + jnp.sqrt(unrolled_sum(gx * gx)) * jnp.sqrt(unrolled_sum(sg(F) ** 2))
    grazing = jnp.abs(gdot) <= jnp.cbrt(eps) * size
    safe = jnp.where(gdot != 0, gdot, 1.0)
    shift = -(g_val - sg(g_val)) / safe  # zero in value
    t_ev = t_star + (t_at - sg(t_at)) + shift
    return t_ev, x_star + F * shift, grazing


# ---------------------------------------------------------------------------- the jump
def blocks(k, num_transitions: int):
    """Whether the first event, watched function k, blocks the execution: a domain component
    (k >= K) reached before any guard, so the flow leaves the domain outside every guard
    (`BLOCKED`, at the exit, the state kept)."""
    return k >= num_transitions


def jump_outcome(
    num_events, max_epochs: int, y_after, zero_length, zero_run, max_zero_epochs: int
) -> JumpOutcome:
    """What a transition does: it is recorded if the record has room (num_events <
    max_epochs, else `MAX_EPOCHS`, the execution ending before it); applied if also its reset
    y_after is finite (else `NONFINITE`: the event kept, the execution ending at the pre-event
    state); and a zero-length epoch extends the run of them, which ends with `CHATTERING`
    beyond `max_zero_epochs` (any other epoch resets it to 0). `y_after` (n, ...): finiteness
    is taken over its leading axis."""
    recorded = num_events < max_epochs
    applied = recorded & fold(jnp.logical_and, jnp.isfinite(y_after))
    zero_run = jnp.where(zero_length, zero_run + 1, 0)
    stops = (
        (~recorded, Status.MAX_EPOCHS),
        (recorded & ~applied, Status.NONFINITE),
        (applied & (zero_run > max_zero_epochs), Status.CHATTERING),
    )
    return JumpOutcome(recorded, applied, zero_run, stops)


def push_recent(window, value):
    """The window of recent event times (or states), oldest first, after an event: the oldest
    dropped, `value` appended (the Zeno test reads it, `detect_zeno`)."""
    return jnp.concatenate([window[1:], value[None].astype(window.dtype)])


def zeno_completion(kern: Kernels, mode, is_zeno, t_inf, x_inf, args) -> ZenoCompletionStep:
    """The completion of a Zeno execution: where Zeno is detected (`detect_zeno`) and `mode`
    has a `ZenoCompletion` c, the execution jumps at the accumulation time t_inf from the limit
    state x_inf through c's reset into c's target mode, recorded as the event of transition
    index K + c (A. D. Ames, H. Zheng, R. D. Gregg, S. Sastry, "Is there life after Zeno?",
    ACC 2006). Elsewhere it stops with `ZENO`."""
    c = kern.completion_of_mode[mode]
    completes = is_zeno & (c >= 0)
    c = jnp.maximum(c, 0)
    t_c, x_c, a_c = mask_inputs(completes, (t_inf, x_inf, args))
    y_after = kern.completion_reset(c, t_c, x_c, a_c)
    return ZenoCompletionStep(
        completes, kern.num_transitions + c, kern.completion_targets[c], t_c, x_c, y_after
    )


# ---------------------------------------------------------------------------- saving
def saved_in_step(save_ts, t, t_end):
    """Which save times a step from t writes: those in (t, t_end], t_end the event time in a
    step with an event, the step's end otherwise (a time equal to an event time is saved
    before the jump: the pre-event state)."""
    return (save_ts > t) & (save_ts <= t_end)


# ---------------------------------------------------------------------------- statuses
def stop_first(done, code, *rules):
    """The precedence of statuses: `(done, code)` after the stop rules `(pred, Status)` in
    order; an execution already done keeps its status, and of two rules that hold at once the
    first wins. `code`: the integer status codes (a `Status` item's `_value`)."""
    for pred, status in rules:
        pred = pred & ~done
        done, code = done | pred, jnp.where(pred, status._value, code)
    return done, code
