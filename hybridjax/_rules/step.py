"""A step's outcome: a non-finite step, a collapsed step size, and the stops after a step."""

import jax.numpy as jnp

from .._core.status import Status
from .records import NonfiniteStep


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
