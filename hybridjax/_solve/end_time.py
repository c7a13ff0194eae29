"""The end-time derivative of a run that reaches t1 at an epoch's start (`continued_past_start`),
for one execution, as both entry points apply it to what their engines return."""

import jax.numpy as jnp
from jax import lax

from .._core.status import Status
from .._rules.tolerances import continued_past_start


def at_t1_from_epoch_start(kern, final_state, final_mode, status, num_events, event_times, ys, save_ts,
                           t0, t1, args):
    """`(final_state, ys)` of one execution with t1's derivative where the run reached t1 at the
    start of its last epoch (its start, t0 or the last event time, is its final time): the final
    state, and the saves at t1 that hold it, continued by the epoch's flow
    (`continued_past_start`)."""
    last = jnp.maximum(num_events - 1, 0)
    t_start = jnp.where(num_events > 0, event_times[last], t0)
    at_start = (status == Status.T1_REACHED) & (lax.stop_gradient(t_start) >= lax.stop_gradient(t1))
    field = kern.flow(final_mode, t1, final_state, args)
    x = continued_past_start(final_state, field, t_start, t1, at_start)
    if not save_ts.shape[0]:
        return x, ys
    # A save at t1 holding the final state (not the state before an event at t1 exactly).
    rows = at_start & (save_ts == t1) & jnp.all(ys == final_state[None, :], axis=-1)
    return x, jnp.where(rows[:, None], x[None, :], ys)
