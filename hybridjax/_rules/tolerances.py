"""Tolerances: the event-time tolerance and the end of a step (the step and jump times it is
clipped to, too)."""

import jax.numpy as jnp
from jax import lax

sg = lax.stop_gradient


# ---------------------------------------------------------------------------- tolerances
def event_time_tol(event_tol, t, h, eps):
    """The event-time tolerance: `event_tol` relative to the step h, floored at 8 ulp of t,

    tol = max(event_tol |h|, 8 eps |t|).

    Root brackets are narrowed below it; guards reached within it of the first event are
    simultaneous (`simultaneous_set`); at an epoch's start it widens the band of "zero"
    (`Kernels.guard_jets`).
    """
    return jnp.maximum(event_tol * jnp.abs(h), 8 * eps * jnp.abs(t))


def at_most_end(t_next, t1):
    """min(t_next, t1), with t1's derivative where they are equal.

    A step that reaches the end time ends at t1, so the final state is the state at t1, and
    its derivative is t1's (the final time of a run is a parameter, not a consequence of the
    trajectory). `jnp.minimum` gives each argument half the derivative at a tie (`lax.min`'s
    balanced rule): where a proposed step lands on t1 to the last bit, the final state's
    derivative would take half of t's (the last event time's) with it. Values are
    `jnp.minimum`'s, NaN included (a NaN t_next or t1 stays NaN, for the non-finite-step rule
    to see), written as one selection.
    """
    return jnp.where((t_next >= t1) | jnp.isnan(t1), t1, t_next)


def continued_past_start(x, field, t_start, t1, at_start):
    """The state at t1 of a run that reaches t1 at the start of its last epoch, with no step
    after it (`at_start`: t1 = t0, or an event at t1 exactly):

    x(t1) = x + ((t1 - t_s) - (t1 - t_s)|_value) F(t1, x),

    whose value is x and whose derivative is the epoch's flow continued past its start,
    F (dt1 - dt_s): the one-sided derivative of the run continued a little past t1, the same as
    where a step reaches t1 (`at_most_end`). Elsewhere x. A non-finite field adds nothing.
    """
    delta = (t1 - sg(t1)) - (t_start - sg(t_start))  # zero, with the derivative of t1 - t_s
    return jnp.where(at_start, x + delta * jnp.where(jnp.isfinite(field), field, 0.0), x)


def step_end(t, h, t1):
    """The end of the next step: t_next = min(max(t + h, nextafter(t)), t1) (`at_most_end`).

    A step always moves t by at least one ulp (a proposal below the resolution of t would
    leave it in place) and never passes the end time t1.
    """
    return at_most_end(jnp.maximum(t + h, t + (jnp.nextafter(sg(t), jnp.inf) - sg(t))), t1)


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
        s = _time_at(step_ts, jnp.searchsorted(step_ts, past, side="right"))
        t_next = jnp.where(s < t_next, s, t_next)  # t_next's derivative at a tie: t1's, for s = t1
    if jump_ts is not None and jump_ts.shape[0]:
        moved, made_jump = _moved_past(jump_ts, t_sg, t1)
        t = t + (moved - t_sg)  # the derivative of t kept
        t_next = jnp.maximum(jnp.nextafter(moved, jnp.inf), t_next)
        j = _time_at(jump_ts, jnp.searchsorted(jump_ts, moved, side="right"))
        t_next = at_most_end(jnp.where(j < t1, jnp.minimum(t_next, jnp.nextafter(j, -jnp.inf)), t_next), t1)
    return t, t_next, made_jump
