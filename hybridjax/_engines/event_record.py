"""The event record, stored by dtype: per event its time and states side by side (`real`), its
transition and the mode of the epoch it starts (`index`), its flags (`flag`); max_epochs + 1
slots, the last a scratch slot (`with_scratch`).

The batched engine writes a block of events with one scatter per dtype, three where eight
arrays would take eight: on XLA:CPU a scatter costs about as much for a row of several values
as for one. The `Solution` keeps the three arrays as they are written and reads each of its
event arrays off them where it is asked for (`event_field`): returned from a program, the
record is not copied into eight arrays (one copy of the whole record, a tenth of a batched run
of the bouncing ball), and inside `jax.jit` an event array that is not read is not computed."""

import jax
import jax.numpy as jnp


def empty_events(shape: tuple, n: int, dtype) -> tuple[jax.Array, jax.Array, jax.Array]:
    """`(real, index, flag)` of a record without events, `shape` the leading axes (executions,
    events): times and states inf, transitions and modes -1, flags False."""
    return (jnp.full(shape + (1 + 2 * n,), jnp.inf, dtype), jnp.full(shape + (2,), -1, jnp.int32),
            jnp.zeros(shape + (3,), bool))


def event_rows(t_ev, y_before, y_after, k, target, simultaneous, grazing, inside, dtype) -> tuple:
    """The rows `(real, index, flag)` of events, one per leading entry of the arguments
    (`t_ev` (m,), states (m, n), the rest (m,))."""
    real = jnp.concatenate([jnp.asarray(t_ev, dtype)[:, None], jnp.asarray(y_before, dtype),
                            jnp.asarray(y_after, dtype)], axis=1)
    index = jnp.stack([jnp.asarray(k, jnp.int32), jnp.asarray(target, jnp.int32)], axis=1)
    flag = jnp.stack([jnp.asarray(f, bool) for f in (simultaneous, grazing, inside)], axis=1)
    return real, index, flag


def with_scratch(real, index, flag) -> tuple[jax.Array, jax.Array, jax.Array]:
    """A record of E events (on the second-to-last axis) with the scratch slot E appended: the
    layout the `Solution` keeps, in which the batched engine writes the events it does not
    keep to that slot (every write in bounds)."""
    n = (real.shape[-1] - 1) // 2
    empty = empty_events(real.shape[:-2] + (1,), n, real.dtype)
    return tuple(jnp.concatenate([a, e], axis=-2) for a, e in zip((real, index, flag), empty, strict=True))


def event_field(name: str, real, index, flag, first_modes) -> jax.Array:
    """The `Solution`'s event array `name` (`event_times`, `states_before`, `states_after`,
    `transitions`, `epoch_modes`, `simultaneous`, `grazing` or `inside_guard`) from the record (E + 1 slots
    on the second-to-last axis of each, the last the scratch slot; `first_modes` the initial
    modes, the record's leading axes): `epoch_modes` is the initial mode followed by the mode
    each event starts."""
    n = (real.shape[-1] - 1) // 2
    events = slice(None, -1)
    if name == "epoch_modes":
        first = jnp.broadcast_to(jnp.asarray(first_modes, jnp.int32), index.shape[:-2])
        return jnp.concatenate([first[..., None], index[..., events, 1]], axis=-1)
    array, column = {"event_times": (real, 0), "states_before": (real, slice(1, 1 + n)),
                     "states_after": (real, slice(1 + n, None)), "transitions": (index, 0),
                     "simultaneous": (flag, 0), "grazing": (flag, 1), "inside_guard": (flag, 2)}[name]
    return array[..., events, column]

