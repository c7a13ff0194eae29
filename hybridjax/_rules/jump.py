"""The jump: `BLOCKED`, the outcome of an event, the Zeno window and the Zeno completion."""

import jax.numpy as jnp

from .._core.status import Status
from .._definition.kernels import Kernels, mask_inputs
from .._step.runge_kutta import fold
from .records import JumpOutcome, ZenoCompletionStep


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
