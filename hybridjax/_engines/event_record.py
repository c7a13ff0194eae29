"""The batched engine's event record (`LaneRecord`), stored by dtype: per event its time and
states side by side (`real`), its transition and the mode of the epoch it starts (`index`), its
flags (`flag`).

A block of events is written with one scatter per dtype, three where the `Solution`'s arrays
would take eight: on XLA:CPU a scatter costs about as much for a row of several values as for
one. `solution_arrays` reads the `Solution`'s arrays off the three once, at the end."""

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


def solution_arrays(real, index, flag, first_modes) -> dict:
    """The `Solution`'s event arrays from the record (events on the second-to-last axis of
    each; `first_modes` the initial modes, the record's leading axes)."""
    n = (real.shape[-1] - 1) // 2
    return dict(event_times=real[..., 0], states_before=real[..., 1:1 + n], states_after=real[..., 1 + n:],
                transitions=index[..., 0],
                epoch_modes=jnp.concatenate([jnp.asarray(first_modes)[..., None], index[..., 1]], axis=-1),
                simultaneous=flag[..., 0], grazing=flag[..., 1], inside_guard=flag[..., 2])
