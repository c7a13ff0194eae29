"""The batched engine's storage: the lanes' state, the finished executions' values, the event record,
and gathering and scattering of lanes."""

import equinox as eqx
import jax
import jax.numpy as jnp

from .._core.status import Status
from .event_record import empty_events


class Lanes(eqx.Module):
    """The running state of N executions, lanes last (see `LoopState` for the fields)."""

    t: jax.Array  # (N,)
    y: jax.Array  # (n, N)
    mode: jax.Array
    h: jax.Array
    f0: jax.Array  # (n, N): F at (t, y), the first stage of the next step
    at_start: jax.Array
    done: jax.Array
    status: jax.Array  # (N,) int32: `Status` codes
    g_prev_slots: jax.Array  # (S, N): `LoopState.g_prev`, by slot (`Kernels.to_slots`)
    num_events: jax.Array
    zero_run: jax.Array
    num_steps: jax.Array
    num_rejected: jax.Array
    zeno_time: jax.Array
    zeno_state: jax.Array  # (n, N)
    recent_times: jax.Array  # (R, N)
    recent_states: jax.Array  # (3, n, N)
    inv_error: jax.Array  # (N,) the step-size rule's history (`PIDState`; unused by an I controller)
    prev_inv_error: jax.Array
    at_dtmin: jax.Array
    save_ptr: jax.Array  # (N,): the next save time, in sorted order, not yet written
    t1: jax.Array  # (N,): the end time of each lane's execution
    exec_id: jax.Array  # (N,) int32: the execution each lane runs (num_executions: none)
    next_exec: jax.Array  # () int32: the first execution not yet given to a lane


class Finals(eqx.Module):
    """The final values of every execution, lanes last (`Lanes`' fields of the same name),
    written when its lane finishes: with fewer lanes than executions, a lane runs several."""

    t: jax.Array
    y: jax.Array
    mode: jax.Array
    status: jax.Array
    num_events: jax.Array
    num_steps: jax.Array
    num_rejected: jax.Array
    zeno_time: jax.Array
    zeno_state: jax.Array

    @classmethod
    def of(cls, st: "Lanes") -> "Finals":
        return cls(**{f: getattr(st, f) for f in cls.__dataclass_fields__})


class LaneRecord(eqx.Module):
    """The events of the executions (executions first, stored by dtype: `event_record`), written
    in place by one scatter per dtype in iterations with events; the loop's output is the
    record itself, and the `Solution` keeps it as it is (`fields`): a call on one device copies
    none of it."""

    # (N, E + 1, 1 + 2n): event time, state before, state after. Column E takes the writes of
    # events not kept (`BatchedLoop.record`): every write in bounds, since a loop buffer's
    # reverse pass reads each written index back (out of bounds: NaN), and with writes out of
    # bounds, runs under XLA:CPU's optimization level 0 with its fusion emitters off came out
    # wrong. The `Solution` keeps the column and reads the first E (`event_record`).
    real: jax.Array
    index: jax.Array  # (N, E + 1, 2) int32: transition, the mode of the epoch it starts
    flag: jax.Array  # (N, E + 1, 3) bool: simultaneous, grazing, inside the guard
    ys: jax.Array  # (N, S, n) saved states
    saved_modes: jax.Array  # (N, S)
    finals: Finals | None  # with fewer lanes than executions; else the lanes' own state

    @classmethod
    def empty(cls, num_exec: int, max_epochs: int, n: int, dtype, ys, saved_modes, finals) -> "LaneRecord":
        """A record without events (`empty_events`), with the scratch column E."""
        real, index, flag = empty_events((num_exec, max_epochs + 1), n, dtype)
        return cls(real=real, index=index, flag=flag, ys=ys, saved_modes=saved_modes, finals=finals)

    def buffers(self) -> list:
        """The event and final-value arrays, selected by attribute as `eqxi.while_loop`'s
        `buffers` wants them. (Not the saved states: written from a nested loop inside a
        `lax.cond`, as buffers their reverse-mode gradient came out NaN.)"""
        events = [self.real, self.index, self.flag]
        finals = self.finals
        if not isinstance(finals, Finals):  # None (tree_at sees it as a leaf)
            return events
        return events + [getattr(finals, f) for f in Finals.__dataclass_fields__]

    def fields(self) -> dict:
        """The `Solution` fields: the record itself, scratch column included (the `Solution`
        reads around it)."""
        return dict(events_real=self.real, events_index=self.index, events_flag=self.flag, ys=self.ys,
                    saved_modes=self.saved_modes)


def as_status(codes) -> Status:
    """A `Status` item holding the integer codes `codes` (one per lane)."""
    return eqx.tree_at(lambda s: s._value, Status.T1_REACHED, jnp.asarray(codes, jnp.int32))


def default_block(lanes: int) -> int:
    """The default block size: every lane up to 256 of them, else max(64, lanes // 32)."""
    return lanes if lanes <= 256 else max(64, lanes // 32)


# `default_lanes`: one lane per execution up to these many executions per device (a forward
# run; a differentiated one), else REFILL_LANES lanes, refilled (benchmarks/lanes.py).
ONE_LANE_EACH_UP_TO = 200_000
ONE_LANE_EACH_UP_TO_DIFFERENTIATED = 20_000
REFILL_LANES = 10_000


def default_lanes(executions: int, differentiated: bool) -> int:
    """The default number of lanes of a device running `executions` executions.

    One lane per execution up to `ONE_LANE_EACH_UP_TO` of them; above, `REFILL_LANES` lanes,
    each taking the next execution when its own ends. Part of an iteration's cost does not grow
    with its width (its kernels' start-up, the loop's bookkeeping), and a refill is a pass over
    every lane in each iteration where some execution ends: up to 200,000 executions the one
    wide batch, whose lanes idle once their executions end, runs faster than 10,000 refilled
    lanes (the ball, the thermostat, the Van der Pol relay); above, the cost per execution of
    the wide arrays, which grows with the width, tips it (docs: Lanes, measured). A call
    through which a derivative is taken (`differentiated`, as `simulate_batch` decides it for
    its default block) keeps one lane per execution only up to
    `ONE_LANE_EACH_UP_TO_DIFFERENTIATED`: each lane carries a derivative (a tangent, or in
    reverse mode its state at every checkpoint), which multiplies the memory per lane."""
    cap = ONE_LANE_EACH_UP_TO_DIFFERENTIATED if differentiated else ONE_LANE_EACH_UP_TO
    return executions if executions <= cap else REFILL_LANES


def _take_lanes(a, idx):
    """Lanes `idx` of a lanes-last array (an index past the last lane reads the last lane)."""
    return jnp.take(a, idx, axis=-1, mode="clip")


# The per-lane fields of `Lanes` (all but the queue's head, `next_exec`).
_LANE_FIELDS = tuple(f for f in Lanes.__dataclass_fields__ if f != "next_exec")


def _gather_lanes(st: Lanes, idx) -> Lanes:
    """The lanes `idx` of `st` as a `Lanes` of their own (a block); `idx` None: `st` itself.
    (Fields the block's update does not read are gathers without users: XLA removes them.)"""
    if idx is None:
        return st
    return eqx.tree_at(lambda s: [getattr(s, f) for f in _LANE_FIELDS], st,
                       [_take_lanes(getattr(st, f), idx) for f in _LANE_FIELDS])


def _scatter_lanes(st: Lanes, gathered: Lanes, block: Lanes, idx) -> Lanes:
    """`st` with lanes `idx` replaced by `block`, the update of `gathered` (`_gather_lanes`'
    output): one scatter per field the update changed (by identity; indices >= N, a block's
    spare slots, are dropped)."""
    if idx is None:
        return block
    changed = [f for f in _LANE_FIELDS if getattr(block, f) is not getattr(gathered, f)]
    return eqx.tree_at(lambda s: [getattr(s, f) for f in changed], st,
                       [getattr(st, f).at[..., idx].set(getattr(block, f), mode="drop") for f in changed])
