"""The typed records the rules pass between the stages of an iteration."""

from typing import NamedTuple

import jax


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
