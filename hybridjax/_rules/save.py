"""Saving: which save times a step covers, and where its dense output is read for them."""

import jax.numpy as jnp
from jax import lax

sg = lax.stop_gradient


# ---------------------------------------------------------------------------- saving
def saved_in_step(save_ts, t, t_end):
    """Which save times a step from t writes: those in (t, t_end], t_end the event time in a
    step with an event, the step's end otherwise (a time equal to an event time is saved
    before the jump: the pre-event state)."""
    return (save_ts > t) & (save_ts <= t_end)


def within_step(s, t, t_next):
    """A time s of the step [t, t_next] at which its dense output is read (a save time),
    kept inside it (t and t_next without their derivatives): s's own value and derivative
    where t <= s <= t_next, its ends (derivative zero) outside.

    The saved state at s is x(s), whose derivative in s is the field there: a save at t1
    (`SaveAt(t1=True)`) differentiated in t1 gives F(x(t1)). `jnp.clip` against the constant
    end gives half of s's derivative where s = t_next, which every save at t1 is.
    """
    lo, hi = sg(t), sg(t_next)
    return jnp.where(s < lo, lo, jnp.where(s > hi, hi, s))
