"""Tolerances: the event-time tolerance and the end of a step."""

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


def step_end(t, h, t1):
    """The end of the next step: t_next = min(max(t + h, nextafter(t)), t1).

    A step always moves t by at least one ulp (a proposal below the resolution of t would
    leave it in place) and never passes the end time t1.
    """
    return jnp.minimum(jnp.maximum(t + h, t + (jnp.nextafter(sg(t), jnp.inf) - sg(t))), t1)
