"""The batched engine: N executions in one loop, their state as structure of arrays.

`Loop` (`loop.py`) is one execution; `jax.vmap` makes a batch of it, which stores every array
as (N, ...) and turns each per-execution selection into a copy of the whole state. Here the
batch is explicit and *lanes-last*: the state is (n, N), one contiguous vector per component,
so that the Runge-Kutta stages, the error norm, the step-size rule and the guard samples fuse
into a few loops over the batch. Each iteration, every execution ("lane") that is still running
either starts an epoch or takes one step, as in `Loop`, with the same semantics:

- the work every step needs (stages, controller, guard samples on the dense output, crossing
  and dip detection) is written on the lanes-last arrays, each field updated once per
  iteration under a lane mask; the guards are sampled, and events located, by *slot*, a
  mode's own watched functions (`Kernels.slot_guards`), so the width is the most any one mode
  watches, not all;
- the work only some lanes need (the epoch-start test with its Lie derivatives and the
  epoch's first step; root and minimum location, the implicit-function event point and the reset)
  runs under a `lax.cond` taken only when some lane needs it, on those lanes gathered into
  blocks of lanes/32, updated there and scattered back once per changed field, block after
  block (a loop of at most lanes/block passes, checkpointed for reverse mode) until every lane
  that needs it is done; each pass costs a few hundred small kernels whatever its lanes, so
  what can run on every lane at once does: the first epoch's start test (every lane needs it,
  before the loop) and the Zeno test of the step's events (`step_zeno_stage`, after the
  last block: it reads each lane's window of recent events alone);
- events are written into the max_epochs-long record (the `Solution`'s own arrays) in place;
  the record is the while loop's `buffers` (write-once), so reverse mode does not store it
  in every checkpoint;
- with fewer lanes than executions, a lane whose execution has ended hands in its final
  values and takes the next execution not yet started (`refill_stage`), so the batch stays
  full while executions of different lengths finish.

The rules (`_rules`), the per-lane pieces (`Kernels`, diffrax's interpolation and initial step) are the
ones `Loop` uses, so both engines make the same decisions; `tests/test_engines.py` holds them
to each other. The dense output at the guard samples uses weights w(theta) with
y(theta) = a y0 + b y1 + sum_i c_i k_i, read off diffrax's own interpolation (it is linear in
y0, y1, k) once at trace time. An implicit solver (ImplicitEuler, Kvaerno3/4/5), whose stages
are root finds, takes diffrax's own `solver.step` mapped over the lanes (`mapped_step`); its
stage increments feed the same dense output, and its error estimate the same step-size rule.

Beside this loop: the lanes' storage (`lanes.py`), the dense-output weights
(`dense_weights.py`) and the XLA:CPU work-arounds with their invariants (`xla_cpu.py`).
"""

import functools
from typing import NamedTuple

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax import lax

from .._core.status import Status
from .._definition.kernels import Kernels, mask_inputs
from .._rules.detect import dip_filter, dip_interval
from .._rules.jump import blocks, jump_outcome, push_recent, zeno_completion
from .._rules.locate import across_lanes, event_brackets, event_point, first_event
from .._rules.options import SolveOptions
from .._rules.records import Detection, EpochStart
from .._rules.save import saved_in_step, within_step
from .._rules.start import carries_step, epoch_start
from .._rules.status import stop_first
from .._rules.step import nonfinite_step, step_stops
from .._rules.tolerances import clip_to_times, event_time_tol, step_end
from .._rules.zeno import detect_zeno
from .._step.runge_kutta import (
    PIDState,
    UnrolledERK,
    explicit_rk_step,
    has_history,
    pid_controller,
    rk_error_estimate,
    scaled_error,
)
from .dense_weights import ChebyshevDense, chebyshev_weights, dense_weights, stage_combination
from .event_record import event_rows
from .lanes import Finals, LaneRecord, Lanes, _gather_lanes, _scatter_lanes, _take_lanes, default_block
from .seeding import perturbed_like_the_body
from .xla_cpu import _computed_once, _materialize, _rows_all, _rows_any, first_lanes, running_count

sg = lax.stop_gradient


def _stop(st: Lanes, *rules: tuple) -> Lanes:
    """`st` with its running lanes stopped by the first of the rules `(pred, Status)` that holds
    (`stop_first`), in one update of `done` and `status`: each update is a pass over every lane."""
    done, code = stop_first(st.done, st.status, *rules)
    return eqx.tree_at(lambda s: (s.done, s.status), st, (done, code))


def _detect(g_prev, G_e, D_e, times, pred) -> Detection:
    """`first_crossings` and `dip_candidates` of `_rules`, lanes last, the sample axis unrolled
    (`dip_interval` on each interval).

    `G_e`, `D_e`: guard values and slopes at the step's start, interior points and end (lists
    of (S, N), S the watched functions' slots); `times` the sample times ((N,) each); `pred` as
    `_materialize`'s. Returns the `Detection`, each field (S, N).
    """
    V = [g_prev, *G_e[1:]]
    m = len(V) - 1
    parts = [dip_interval(V[i], V[i + 1], D_e[i], D_e[i + 1], times[i + 1] - times[i]) for i in range(m)]
    # Per interval, computed once; the first crossing and the first dip candidate from them.
    cross, cand = _materialize(([p[0] for p in parts], [p[1] for p in parts]), pred)
    has = jnp.zeros(g_prev.shape, bool)
    j = jnp.zeros(g_prev.shape, jnp.int32)
    suspect = jnp.zeros(g_prev.shape, bool)
    i_d = jnp.zeros(g_prev.shape, jnp.int32)
    for i in range(m):
        j = jnp.where(cross[i] & ~has, i, j)
        has = has | cross[i]
        i_d = jnp.where(cand[i] & ~suspect, i, i_d)
        suspect = suspect | cand[i]

    # The estimated minimum on the first candidate's interval alone, from its values picked out
    # again: computed for every interval, or under a `lax.cond` on any candidate, it is slower
    # (candidates are common).
    def pick(xs):
        out = xs[0]
        for i in range(1, m):
            out = jnp.where(i_d == i, xs[i], out)
        return out

    t0 = pick(times[:m])
    _, _, u = dip_interval(pick(V[:m]), pick(V[1:]), pick(D_e[:m]), pick(D_e[1:]), pick(times[1:]) - t0)
    x0_d = jnp.where(suspect, t0 + u, times[0])
    return Detection(has, j, suspect, i_d, x0_d)


SAVE_WINDOW = 16  # sorted save times interpolated per pass
PER_COMPONENT_MAX_DIM = 8  # `BatchedLoop.flows` traces the field once per component up to this


# diffrax's implicit solvers for an ODE, whose dense output is linear in y0, y1 and the stage
# increments (`dense_weights`): stepped by `BatchedLoop.mapped_step`.
MAPPED_SOLVERS = (diffrax.ImplicitEuler, diffrax.Kvaerno3, diffrax.Kvaerno4, diffrax.Kvaerno5)


def can_map_step(solver) -> bool:
    """Whether the batched engine steps `solver` by mapping its own `step` over the lanes."""
    return type(solver) in MAPPED_SOLVERS


def mapped_solver_shape(solver, terms, n: int, lane_args, dtype) -> tuple[bool, int]:
    """For a diffrax solver stepped as it is (`BatchedLoop.mapped_step`): whether it stores its
    last stage for the next step (FSAL: its state is `(first_step, f)`), and how many stage
    increments its dense output reads (0 where it reads none, e.g. a linear interpolation)."""
    y = jnp.zeros((n,), dtype)
    t0, t1 = jnp.zeros((), dtype), jnp.ones((), dtype)
    a = (jnp.zeros((), jnp.int32), lane_args)
    out = jax.eval_shape(lambda: solver.step(terms, t0, t1, y, a, solver.init(terms, t0, t1, y, a),
                                             jnp.array(False)))
    dense, state = out[2], out[3]
    return state is not None, dense["k"].shape[0] if "k" in dense else 0


@functools.cache
def stage_interpolation(interpolation_cls, num_stages: int):
    """`interpolation_cls` called as `dense_weights` calls it, with the stage increments `k`;
    for a dense output that reads none (`num_stages` 0), a wrapper that drops them."""
    if num_stages:
        return interpolation_cls

    def without_k(*, t0, t1, y0, y1, k):
        del k
        return interpolation_cls(t0=t0, t1=t1, y0=y0, y1=y1)

    return without_k


class LaneStart(NamedTuple):
    """A lane's epoch-start test (`g_start` by slot) and the reset of the transition that fires
    at once, if one does."""

    start: EpochStart
    y_after: jax.Array


class LaneStep(NamedTuple):
    """One lane's step: from (t, y) to (t_next, y1), with the stages' increments ks."""

    t: jax.Array
    t_next: jax.Array
    y: jax.Array
    y1: jax.Array
    ks: list


class StepEvent(NamedTuple):
    """One lane's first event in its step (`BatchedLoop._event_lane`), and the start test of the
    epoch after it (`next`)."""

    event: jax.Array  # the lane has an event in the step
    k: jax.Array  # the watched function (a guard if < K; a domain component: `blocks`)
    t_ev: jax.Array  # the event time (`event_point`)
    y_before: jax.Array
    y_after: jax.Array
    simultaneous: jax.Array
    grazing: jax.Array
    next: EpochStart


# The carried fields (of `Lanes` and `LaneRecord`) that the body computes from the inputs
# (t0, x0, args, t1), whichever of them is differentiated (`perturbed_like_the_body`).
LANE_DIFFERENTIABLE_FIELDS = (
    "t", "y", "f0", "zeno_time", "zeno_state", "recent_times", "recent_states",
    "real", "ys", "finals",
)


class BatchedLoop:
    """The loop for the executions of one system; `run(t0, y0, mode0)` with lanes-last inputs.

    `lanes` executions advance together; with fewer lanes than executions (`t1` has one entry
    per execution), a lane whose execution ends takes the next one not yet started (its final
    values go to `LaneRecord.finals`), so that the batch stays full until the queue is empty.
    """

    def __init__(self, system, *, t1, args, args_axis, solver, controller, options: SolveOptions,
                 loop_kind: str, checkpoints, dtype, lanes: int,
                 block: int | tuple | None = None, save_ts=None, save_t0: bool = False,
                 save_t1: bool = False, step_ts=None, jump_ts=None):
        dt0, max_epochs, max_steps, zeno = options.dt0, options.max_epochs, options.max_steps, options.zeno
        interior_points, event_tol, max_zero_epochs = (options.events.interior_points, options.events.tol,
                                                       options.max_zero_epochs)
        self.locator = options.events.locator
        self.num_exec = int(t1.shape[0])
        lanes = min(lanes, self.num_exec)
        self.refill = lanes < self.num_exec
        lane_args = args if args_axis is None else jtu.tree_map(lambda a: a[0], args)
        self.kern = Kernels(system, lane_args, dtype, located=True)
        self.system, self.t1, self.args, self.args_axis = system, t1, args, args_axis
        self.solver, self.controller, self.dt0 = solver, controller, dt0
        self.step_ts, self.jump_ts = step_ts, jump_ts  # `clip_to_times`
        # `UnrolledERK`: the explicit step written lanes last; another (implicit) diffrax solver:
        # its own `step` mapped over the lanes (`mapped_step`).
        self.mapped = not isinstance(solver, UnrolledERK)
        self.carry_step = carries_step(dt0, explicit=not self.mapped)  # (`first_step`)
        self.max_epochs, self.max_steps = max_epochs, max_steps
        self.interior_points, self.event_tol = interior_points, event_tol
        self.max_zero_epochs, self.zeno = max_zero_epochs, zeno
        self.recent = (zeno.window + 2) if zeno is not None else 2
        self.loop_kind, self.checkpoints, self.dtype = loop_kind, checkpoints, dtype
        self.eps = jnp.finfo(dtype).eps
        self.N = lanes
        self.save_ts = jnp.zeros((0,), dtype) if save_ts is None else save_ts
        # `SaveAt(t0=True)` / `SaveAt(t1=True)`: the first / last save is each execution's own
        # t0 / t1, not a time of `save_ts` (there a placeholder, -inf / inf: never reached by
        # the shared save times' pass). At t0 the initial state (`init`); at t1 the state
        # written by `save_at_t1`.
        self.save_t0, self.save_t1 = save_t0, save_t1
        self.save_order = jnp.argsort(self.save_ts)
        self.save_sorted = self.save_ts[self.save_order]
        # Small batches compute the rare work on every lane; large ones on blocks of lanes/32
        # (benchmarks/block_size.py: with passes until every lane is done, small blocks cost
        # little in event-dense iterations and save much where few lanes need the work).
        small, block = block if isinstance(block, tuple) else (None, block)
        self.block = default_block(lanes) if block is None else block
        self.small_block = small if small is not None and small < min(self.block, lanes) else None
        self.terms = diffrax.ODETerm(lambda t, y, a: self.kern.flow(a[0], t, y, a[1]))
        self.error_order = solver.error_order(self.terms)
        self.rtol, self.atol = controller.rtol, controller.atol
        m = interior_points
        self.thetas = np.concatenate([[0.0], np.arange(1, m + 2) / (m + 1)])
        if self.mapped:
            self.fsal, self.num_stages = mapped_solver_shape(solver, self.terms, self.kern.n, lane_args,
                                                             dtype)
            interpolation = stage_interpolation(solver.interpolation_cls, self.num_stages)
        else:
            self.fsal, self.num_stages = solver.fsal, len(solver.c) + 1
            interpolation = solver.interpolation_cls
        self.w_value, self.w_slope = dense_weights(interpolation, self.num_stages, self.thetas, dtype)
        self.cheb = chebyshev_weights(interpolation, self.num_stages, dtype)

    # ------------------------------------------------------------------ helpers
    def lane_args(self, st: Lanes, idx=None):
        """The args of the executions on lanes `idx` (default: all lanes), leading axis theirs."""
        if self.args_axis is None:
            return self.args
        ids = st.exec_id if self.refill else None
        if idx is not None:
            ids = idx if ids is None else jnp.take(ids, idx, mode="clip")
        if ids is None:
            return self.args
        return jtu.tree_map(lambda a: jnp.take(a, ids, axis=0, mode="clip"), self.args)

    def lane_map(self, fn, *tree, args):
        """`fn(*tree_i, args_i)` on every lane (lanes last in and out); `args` those of the
        lanes in `tree` (`lane_args`)."""
        return jax.vmap(fn, in_axes=(-1,) * len(tree) + (self.args_axis,), out_axes=-1)(*tree, args)

    def on_block(self, mask, fn, operand, in_blocks: bool = True):
        """`operand` after `fn(idx, operand)` on every lane in `mask`, a block at a time
        (`in_blocks` False: on every lane at once, `idx` None).

        `idx` (block,): the next `block` lanes where `mask` holds, in order, padded with N
        (spare slots). Passes over blocks repeat, in a while loop of at most N/block passes
        (of the main loop's kind: checkpointed for reverse mode; a `bounded` loop would copy the
        event record in every pass), until every lane of `mask` is done, so that no lane waits
        for a later iteration (lanes beyond the block are done in the same iteration). `fn` is
        compiled once, for one
        block size; with `small_block`, a second time, for that size, taken (one pass) where all
        of `mask` fits in it. With a block as large as the batch, `idx` is None (every lane is
        computed where it is). `fn` gathers the block's lanes (`_gather_lanes`), updates them on
        the block alone and scatters them back once per changed field (`_scatter_lanes`), rather
        than writing each output into N-wide zeros and merging it into the state with N-wide
        selects.
        """
        if self.block >= self.N or not in_blocks:
            return fn(None, operand)
        count = running_count(mask)
        total = count[-1]

        def passes(op):
            # Every lane of `mask`, in order, padded with N to whole blocks: compacted once, each
            # pass slices its block (a compaction per pass is a scatter over all N lanes).
            most = -(-self.N // self.block)
            order = first_lanes(mask, most * self.block, count)

            def one(c):
                done, op = c
                return done + self.block, fn(lax.dynamic_slice(order, (done,), (self.block,)), op)

            _, op = eqxi.while_loop(lambda c: c[0] < total, one, (jnp.zeros_like(total), op),
                                    max_steps=most, kind=self.loop_kind,
                                    checkpoints=most if self.loop_kind == "checkpointed" else None)
            return op

        small = self.small_block
        if small is None:
            return passes(operand)
        # Two compiled sizes: the small block where all of `mask` fits in it.
        return lax.cond(total <= small, lambda op: fn(first_lanes(mask, small, count), op), passes, operand)

    def take(self, tree, idx):
        """Lanes `idx` of every array in `tree` (lanes last); `idx` None: `tree` itself."""
        return tree if idx is None else jtu.tree_map(lambda a: _take_lanes(a, idx), tree)

    def in_block(self, idx, mask):
        """Which of the block's slots hold a lane: `mask` itself without a block."""
        return mask if idx is None else idx < self.N

    def flows(self, mode, t, y, args, scale=None):
        """F_mode(t, y) on every lane, times `scale` ((N,)) if given: (n, N).

        One vmapped call per component, stacked: vmapped whole, the field comes out (N, n) and
        every stage that reads it transposes it inside its fusion (strided reads); per component
        each output is already a lanes-last vector. Each component is cut from each mode's
        field before the modes' selection (`Kernels.flow_component`): selected whole, XLA
        keeps the (N, n) field. Above PER_COMPONENT_MAX_DIM components the field is traced
        once, to keep the trace small, and so is the field of a `ModeIndexed` system (one
        evaluation for every mode, whose cost is its solve, not the layout of its output);
        with one component it is the field itself.
        """
        if self.kern.n == 1 or self.kern.n > PER_COMPONENT_MAX_DIM or self.kern.indexed is not None:
            F = self.lane_map(lambda m, tt, yy, a: self.kern.flow(m, tt, yy, a), mode, t, y, args=args)
            return F if scale is None else F * scale
        comps = [self.lane_map(lambda m, tt, yy, a, i=i: self.kern.flow_component(m, tt, yy, a, i),
                               mode, t, y, args=args) for i in range(self.kern.n)]
        return jnp.stack(comps if scale is None else [c * scale for c in comps])

    # ------------------------------------------------------------------ init
    def fresh(self, ids, next_exec) -> Lanes:
        """Lanes at the start of executions `ids` (clipped to the last one)."""
        t0, y0, mode0 = self.inputs
        t0, y0, mode0, t1 = (jnp.take(a, ids, axis=-1, mode="clip") for a in (t0, y0, mode0, self.t1))
        N, n, S, dtype = ids.shape[0], self.kern.n, self.kern.num_slots, self.dtype
        return Lanes(
            t=t0, y=y0, mode=mode0, h=jnp.zeros((N,), dtype), f0=jnp.zeros((n, N), dtype),
            at_start=jnp.ones((N,), bool), done=jnp.zeros((N,), bool),
            status=jnp.full((N,), Status.T1_REACHED._value, jnp.int32),
            g_prev_slots=jnp.zeros((S, N), dtype), num_events=jnp.zeros((N,), jnp.int32),
            zero_run=jnp.zeros((N,), jnp.int32), num_steps=jnp.zeros((N,), jnp.int32),
            num_rejected=jnp.zeros((N,), jnp.int32), zeno_time=jnp.full((N,), jnp.inf, dtype),
            zeno_state=jnp.full((n, N), jnp.inf, dtype),
            recent_times=jnp.full((self.recent, N), jnp.inf, dtype),
            recent_states=jnp.full((3, n, N), jnp.inf, dtype),
            inv_error=jnp.ones((N,), dtype), prev_inv_error=jnp.ones((N,), dtype),
            at_dtmin=jnp.zeros((N,), bool),
            save_ptr=jnp.searchsorted(self.save_sorted, t0, side="right").astype(jnp.int32),
            t1=t1, exec_id=ids.astype(jnp.int32), next_exec=jnp.asarray(next_exec, jnp.int32),
        )

    def init(self, t0, y0, mode0) -> tuple[Lanes, LaneRecord]:
        self.inputs = (t0, y0, mode0)
        N, n, E, dtype = self.num_exec, self.kern.n, self.max_epochs, self.dtype
        st = self.fresh(jnp.arange(self.N), self.N)
        lane_ts = jnp.broadcast_to(self.save_ts, (N,) + self.save_ts.shape)  # (N, S)
        if self.save_t0:
            lane_ts = lane_ts.at[:, 0].set(t0)
        if self.save_t1:
            lane_ts = lane_ts.at[:, -1].set(self.t1)
        at_t0 = lane_ts <= t0[:, None]
        ys = jnp.where(at_t0[:, :, None], y0.T[:, None, :], jnp.inf).astype(dtype)
        saved_modes = jnp.where(at_t0, mode0[:, None], -1).astype(jnp.int32)
        finals = None
        if self.refill:
            # Every execution MAX_STEPS until its lane hands it in, plus entry N where lanes
            # without an execution write; no gradient, as each entry is overwritten once.
            unrun = _stop(self.fresh(jnp.arange(N + 1), N), (jnp.ones((N + 1,), bool), Status.MAX_STEPS))
            finals = sg(Finals.of(unrun))
        rec = LaneRecord.empty(N, E, n, dtype, ys, saved_modes, finals)
        return st, rec

    # ------------------------------------------------------------------ refill
    def flush(self, st: Lanes, rec: LaneRecord, mask) -> LaneRecord:
        """Write the final values of the lanes in `mask` to their executions' `finals`."""
        ids = jnp.where(mask, st.exec_id, self.num_exec)  # num_exec: the entry not returned
        finals = Finals(**{f: getattr(rec.finals, f).at[..., ids].set(getattr(st, f))
                           for f in Finals.__dataclass_fields__})  # (field by field: they are buffers)
        return eqx.tree_at(lambda r: r.finals, rec, finals)

    def refill_stage(self, st: Lanes, rec: LaneRecord):
        """Lanes whose execution has ended hand it in (`flush`) and take the next ones."""
        ended = st.done & (st.exec_id < self.num_exec)

        def run(carry):
            st, rec = carry
            rec = self.flush(st, rec, ended)
            new_id = st.next_exec + running_count(ended) - 1
            take = ended & (new_id < self.num_exec)
            fresh = self.fresh(new_id, st.next_exec + jnp.sum(take, dtype=jnp.int32))
            new = jtu.tree_map(lambda a, b: jnp.where(take, a, b), fresh, st)
            new = eqx.tree_at(lambda s: (s.exec_id, s.next_exec), new,
                              (jnp.where(ended & ~take, self.num_exec, new.exec_id), fresh.next_exec))
            return new, rec

        return lax.cond(jnp.any(ended), run, lambda c: c, (st, rec))

    # ------------------------------------------------------------------ jump
    def record(self, st: Lanes, rec: LaneRecord, kept, k, t_ev, target, y_before, y_after,
               simultaneous=None, grazing=None, inside=None) -> LaneRecord:
        """`rec` with event k at t_ev written as the next event (`num_events`) of the lanes in
        `kept` (the others write to the scratch column E of an execution's row). `st` is the
        block of lanes (`on_block`) the events can happen on: the record is written from those
        alone."""
        row = jnp.where(kept, st.num_events, self.max_epochs)
        # A lane without a kept event (a block's spare slot, a lane past the last execution:
        # exec_id N) writes to the scratch column of a row in bounds.
        ids = jnp.minimum(st.exec_id, self.num_exec - 1)
        no = jnp.zeros_like(kept)
        rows = event_rows(t_ev, y_before.T, y_after.T, k, target, *(no if f is None else f
                                                                   for f in (simultaneous, grazing, inside)),
                          dtype=self.dtype)
        return eqx.tree_at(lambda r: (r.real, r.index, r.flag), rec,
                           tuple(a.at[ids, row].set(v) for a, v in zip((rec.real, rec.index, rec.flag), rows,
                                                                      strict=True)))

    def begin_epoch(self, st: Lanes, mask, kept, t, y, mode, zero_run, window: bool = True) -> Lanes:
        """The lanes in `mask` at the start of an epoch at (t, y) in `mode`, after an event
        (recorded where `kept`, and added to the Zeno test's window unless `window` is False:
        `push_window`)."""
        st = eqx.tree_at(
            lambda s: (s.t, s.y, s.mode, s.at_start, s.zero_run, s.num_events), st,
            (jnp.where(mask, t, st.t), jnp.where(mask, y, st.y), jnp.where(mask, mode, st.mode),
             st.at_start | mask, jnp.where(mask, zero_run, st.zero_run),
             st.num_events + kept.astype(jnp.int32)),
        )
        return self.push_window(st, kept, t, y) if window else st

    def push_window(self, st: Lanes, kept, t, y) -> Lanes:
        """The Zeno test's window of recent events (`push_recent`) of the lanes in `kept`, after
        an event at (t, y) (the state after its reset); none without the test."""
        if self.zeno is None:
            return st
        return eqx.tree_at(lambda s: (s.recent_times, s.recent_states), st,
                           (jnp.where(kept, push_recent(st.recent_times, t), st.recent_times),
                            jnp.where(kept, push_recent(st.recent_states, y), st.recent_states)))

    def jump(self, st: Lanes, rec: LaneRecord, mask, k, t_ev, y_before, y_after, simultaneous,
             grazing, zero_length: bool, inside=None, window: bool = True):
        """Record transition k at t_ev on the lanes in `mask` and apply its reset (computed by
        the caller); then stop on too many epochs, non-finite values or chattering. `st` is the
        block of lanes (`on_block`) the jumps can happen on. Also returns the lanes whose reset
        was applied, for the Zeno test (`zeno_stage`), which the caller runs next; `window`
        False: the caller adds the events to the test's window too (`push_window`)."""
        K = self.kern.num_transitions
        out = jump_outcome(st.num_events, self.max_epochs, y_after, zero_length, st.zero_run,
                           self.max_zero_epochs)
        kept, jumped = mask & out.recorded, mask & out.applied
        target = self.kern.targets[jnp.clip(k, 0, K - 1)]
        rec = self.record(st, rec, kept, k, t_ev, target, y_before, y_after, simultaneous, grazing, inside)
        # Where the reset is not applied (not finite), the execution ends at the pre-event state.
        st = self.begin_epoch(st, jumped, kept, t_ev, y_after, target, out.zero_run, window)
        st = eqx.tree_at(lambda s: (s.t, s.y), st,
                         (jnp.where(mask, t_ev, st.t), jnp.where(mask & ~jumped, y_before, st.y)))
        st = _stop(st, *((mask & pred, status) for pred, status in out.stops))
        return st, rec, jumped

    def zeno_stage(self, st: Lanes, rec: LaneRecord, jumped, args) -> tuple[Lanes, LaneRecord]:
        """The Zeno test of the lanes in `jumped`, after their jump (`zeno_test`): where event
        times accumulate before t1, a lane stops with `ZENO`, or completes its execution
        through its mode's completion (`zeno_outcome`). `st`: all lanes, or a block of them
        (`on_block`); `args` theirs.

        The test reads each lane's window of recent events alone, so it can run wherever the
        jumps leave the lanes: the start stage's on its block; the step's events, located block
        by block, are tested together on every lane after the last block (`step_zeno_stage`: a
        few kernels over the batch per iteration, not a dozen per block)."""
        if self.zeno is None:
            return st, rec
        return self.zeno_outcome(st, rec, self.zeno_test(st, jumped), args)

    def step_zeno_stage(self, st: Lanes, new: Lanes, rec: LaneRecord, args) -> tuple[Lanes, LaneRecord]:
        """`zeno_stage` of a step's events, on every lane after the last block: `st` the lanes
        before the events, `new` after them. Each event kept adds one to the count and leaves
        the lane at (t_ev, y_after), its window's entry (`push_window`), or, where its reset is
        not applied, ends the execution. Under a conditional on some lane having jumped: an
        event-sparse batch skips the test in most iterations."""
        kept = new.num_events > st.num_events

        def test(new):
            new = self.push_window(new, kept, new.t, new.y)
            return (new.recent_times, new.recent_states), self.zeno_test(new, kept & ~new.done)

        def untested(new):
            return (new.recent_times, new.recent_states), jnp.zeros_like(kept)

        window, z = lax.cond(jnp.any(kept), test, untested, new)
        new = eqx.tree_at(lambda s: (s.recent_times, s.recent_states), new, window)
        return self.zeno_outcome(new, rec, z, args)

    def zeno_test(self, st: Lanes, jumped):
        """The lanes of `jumped` whose window of recent events is Zeno (`detect_zeno`)."""
        return jumped & detect_zeno(st.recent_times, st.recent_states, st.t1, self.zeno)[0] & ~st.done

    def zeno_outcome(self, st: Lanes, rec: LaneRecord, z, args) -> tuple[Lanes, LaneRecord]:
        """The lanes in `z`, found Zeno (`zeno_test`), with their accumulation time and state
        (`detect_zeno`), stopped with `ZENO`, or completed through their mode's completion
        (`zeno_completion`: recorded as an event, its epoch started; `MAX_EPOCHS` without room)."""
        window = (st.recent_times, st.recent_states, st.t1)

        def limits(ops):
            # The accumulation time and state, where some lane is Zeno (rare): the state's
            # extrapolation reads every component of the window.
            z, window, zeno_time, zeno_state = ops
            _, t_inf, x_inf = detect_zeno(*window, self.zeno)
            return jnp.where(z, t_inf, zeno_time), jnp.where(z, x_inf, zeno_state), t_inf, x_inf

        some = jnp.any(z)
        ops = (z, window, st.zeno_time, st.zeno_state)
        zeno_time, zeno_state, t_inf, x_inf = lax.cond(
            some, limits, lambda ops: (ops[2], ops[3], jnp.zeros_like(ops[2]), jnp.zeros_like(ops[3])), ops)
        st = eqx.tree_at(lambda s: (s.zeno_time, s.zeno_state), st, (zeno_time, zeno_state))
        if not self.system.completions:
            return _stop(st, (z, Status.ZENO)), rec

        def complete(carry):
            st, rec = carry
            E = self.max_epochs
            comp = self.lane_map(
                lambda m, zz, tt, xx, ne, a: zeno_completion(self.kern, m, zz, tt, xx, a, ne, E),
                st.mode, z, t_inf, x_inf, st.num_events, args=args,
            )
            completed = comp.completes
            rec = self.record(st, rec, completed, comp.index, comp.t, comp.target, comp.x, comp.y_after)
            st = self.begin_epoch(st, completed, completed, comp.t, comp.y_after, comp.target, 0)
            st = _stop(st, (comp.no_room, Status.MAX_EPOCHS))
            return _stop(st, (z & ~completed, Status.ZENO)), rec

        return lax.cond(some, complete, lambda c: c, (st, rec))

    # ------------------------------------------------------------------ start of an epoch
    def _start_lane(self, t, y, mode, h_prev, t1, args, after_step: bool = False) -> "LaneStart":
        """One lane's epoch-start test (`epoch_start`), its g_start by slot, and the reset of
        the transition that fires at once. `after_step`: the epoch follows an accepted step,
        whose proposal `h_prev` (> 0) starts it unless the user gave `dt0` (`first_step`), so
        Hairer's initial step is not computed."""
        kern, K = self.kern, self.kern.num_transitions
        if after_step and self.carry_step:
            initial = h_prev
        else:
            t_init, _ = self.controller.init(self.terms, sg(t), t1, sg(y), self.dt0, (mode, sg(args)),
                                             self.solver.func, self.error_order)
            initial = t_init - sg(t)
        start = epoch_start(kern, mode, t, y, args, h_prev, initial, carry=self.carry_step, rtol=self.rtol,
                            atol=self.atol, event_tol=self.event_tol, eps=self.eps)
        if K:
            t_m, y_m, a_m = mask_inputs(start.fire & ~blocks(start.k, K), (t, y, args))
            y_after = kern.reset(jnp.minimum(start.k, K - 1), t_m, y_m, a_m)
        else:
            y_after = y
        start = start._replace(g_start=kern.to_slots(mode, start.g_start.astype(self.dtype)),
                               h=start.h.astype(self.dtype))
        return LaneStart(start, y_after)

    def restart_step_rule(self, st: Lanes, mask) -> Lanes:
        """The lanes in `mask` with the step-size rule's history of a new epoch (diffrax's
        `PIDController.init`: 1, 1, not at dtmin), as the per-execution engine restarts its
        controller at each epoch."""
        if not has_history(self.controller):
            return st
        return eqx.tree_at(lambda s: (s.inv_error, s.prev_inv_error, s.at_dtmin), st,
                           (jnp.where(mask, 1.0, st.inv_error), jnp.where(mask, 1.0, st.prev_inv_error),
                            st.at_dtmin & ~mask))

    def start_stage(self, st: Lanes, rec: LaneRecord, in_blocks: bool = True):
        """The epoch-start test of every running lane at the start of an epoch, block by block
        (`on_block`; `in_blocks` False: on every lane at once)."""
        active = st.at_start & ~st.done

        def run(idx, carry):
            st_all, rec = carry
            st = b0 = _gather_lanes(st_all, idx)
            active_now = self.in_block(idx, active)
            start, y_after = self.lane_map(self._start_lane, st.t, st.y, st.mode, st.h, st.t1,
                                           args=self.lane_args(st_all, idx))
            start, y_after = _materialize((start, y_after), jnp.any(active))
            fire = active_now & start.fire
            K = self.kern.num_transitions
            go = active_now & ~start.fire
            st = eqx.tree_at(
                lambda s: (s.at_start, s.g_prev_slots, s.h, s.f0), st,
                (st.at_start & ~go, jnp.where(go, start.g_start, st.g_prev_slots),
                 jnp.where(go, start.h, st.h), jnp.where(go, start.F, st.f0)))
            st = self.restart_step_rule(st, go)
            st = _stop(st, (go & (st.t >= st.t1), Status.T1_REACHED))
            st = _stop(st, (fire & blocks(start.k, K), Status.BLOCKED))
            if K:
                st, rec, jumped = self.jump(st, rec, fire & ~blocks(start.k, K), start.k, st.t, st.y, y_after,
                                            start.simultaneous, jnp.zeros_like(fire), zero_length=True,
                                            inside=start.inside)
                st, rec = self.zeno_stage(st, rec, jumped, self.lane_args(st_all, idx))
            st = _stop(st, (active_now & ~start.finite, Status.NONFINITE))
            return _scatter_lanes(st_all, b0, st, idx), rec

        return lax.cond(jnp.any(active), lambda c: self.on_block(active, run, c, in_blocks), lambda c: c,
                        (st, rec))

    # ------------------------------------------------------------------ one step
    def sample_times(self, t, t_next) -> list:
        """The guard samples' times in the step from t to t_next: t, t + h theta_i, t_next
        (h = t_next - t; no gradient). The event stage computes them again on its lanes, the
        same arithmetic, rather than gathering them."""
        t, t_next = sg(t), sg(t_next)
        hs = t_next - t
        last = len(self.thetas) - 1
        return [t if i == 0 else t_next if i == last else t + hs * float(th)
                for i, th in enumerate(self.thetas)]

    def _event_lane(self, step: "LaneStep", det: Detection, mode, h_new, t1, args) -> "StepEvent":
        """One lane's first event in its step (as `Loop.step_stage`): dips and root
        (`event_brackets`, `first_event`), IFT point (`event_point`), reset; then the next
        epoch's start test (`_start_lane`) on the reset state, so that the common case (no guard
        fires at once) needs no separate start stage."""
        kern, K = self.kern, self.kern.num_transitions
        t, t_next, y, y1, ks = step
        s_ext = jnp.stack(self.sample_times(t, t_next))
        # The search runs on the step's slots, `mode`'s own watched functions (`slot_guards`;
        # unused slots read 1 and never fire); the event's function is mapped back at the end.
        interp_sg = ChebyshevDense.from_stages(self.cheb, sg(t), sg(t_next), sg(y), sg(y1), sg(ks))
        a_sg = sg(args)
        tol = event_time_tol(self.event_tol, sg(t_next), sg(t_next - t), self.eps)

        def values_at(x):
            return kern.slot_guards(mode, x, interp_sg.evaluate(x), a_sg)

        # The searches' fixed points in one pass over the block: a `lax.map` over them would run
        # the kernels over the block once per point (`across_lanes`).
        with across_lanes():
            br = event_brackets(values_at, det, s_ext, tol, self.locator)
            t_star, slot, simultaneous = first_event(values_at, br, tol, sg(t_next), self.locator)
        any_event = jnp.any(br.has)
        k = jnp.where(any_event, jnp.asarray(kern.slot_watch)[mode, slot], 0).astype(jnp.int32)
        ks_e, y_e, y1_e, t_e, tn_e, a_e = mask_inputs(any_event, (ks, y, y1, t, t_next, args))
        interp = ChebyshevDense.from_stages(self.cheb, t_e, tn_e, y_e, y1_e, ks_e)
        # The coefficients computed once: without the barrier XLA recomputes their sums of the
        # stages inside each fusion that reads the interpolant (event_point's several
        # evaluations), a third of the run time of a batch of balls.
        interp = eqx.tree_at(lambda i: i.coeffs, interp, lax.optimization_barrier(interp.coeffs))
        t_ev, y_before, grazing = event_point(kern, self.eps, mode, k, t_star, interp, a_e, tol)
        k = kern.select(mode, k, t_ev, y_before, a_e)
        if K:
            t_r, y_r, a_r = mask_inputs(any_event & ~blocks(k, K), (t_ev, y_before, args))
            y_after = kern.reset(jnp.minimum(k, K - 1), t_r, y_r, a_r)
        else:
            y_after = y_before
        target = kern.targets[jnp.clip(k, 0, max(K - 1, 0))] if K else mode
        nxt, _ = self._start_lane(t_ev, y_after, target, h_new, t1, args, after_step=True)
        return StepEvent(event=any_event, k=k, t_ev=t_ev, y_before=y_before, y_after=y_after,
                         simultaneous=simultaneous, grazing=grazing, next=nxt)

    def mapped_step(self, mode, t, t_next, y, f0, args):
        """The diffrax solver's own `step` from t to t_next on every lane (`jax.vmap` over the
        lanes: for implicit solvers, whose stages are root finds). An FSAL solver's stored
        first stage is the lane's `f0` (F at (t, y), fresh at an epoch's start), so no lane
        re-evaluates it. Returns `(y1, ks, f_last, y_err)` lanes last, ks the stages'
        increments of the dense output (none for a solver whose dense output is linear)."""

        def one(m, t, t_next, y, f0, a):
            state = (jnp.array(False), f0) if self.fsal else None
            y1, y_err, dense, new_state, _ = self.solver.step(self.terms, t, t_next, y, (m, a), state,
                                                              jnp.array(False))
            k = dense.get("k", jnp.zeros((0,) + y.shape, y.dtype))
            return y1, y_err, k, new_state[1] if self.fsal else f0

        y1, y_err, k, f_last = self.lane_map(one, mode, t, t_next, y, f0, args=args)
        return y1, list(k), f_last, y_err

    def step_stage(self, st: Lanes, rec: LaneRecord):
        kern, solver, c = self.kern, self.solver, self.controller
        num_watch, K = kern.num_watch, kern.num_transitions
        stepping = ~st.done & ~st.at_start
        # Lanes that do not step still compute one; their inputs get no gradient (double where).
        t, y, f0 = mask_inputs(stepping, (st.t, st.y, st.f0))
        args = self.lane_args(st)
        t_next = step_end(t, st.h, st.t1)
        t_from = t  # the step's start before `clip_to_times`, for the saves
        if self.step_ts is not None or self.jump_ts is not None:
            t, t_next, jumped = clip_to_times(t, t_next, st.t1, self.step_ts, self.jump_ts)
            if self.fsal and self.jump_ts is not None:  # past a jump time: the field anew
                f0 = lax.cond(jnp.any(jumped), lambda: jnp.where(jumped, self.flows(st.mode, t, y, args), f0),
                              lambda: f0)
        hh = t_next - t
        if self.mapped:
            y1, ks, f_last, y_err = self.mapped_step(st.mode, t, t_next, y, f0, args)
        else:
            if not self.fsal:
                f0 = self.flows(st.mode, t, y, args)
            # The stages' increments k_i = h F_i come out of `flows` scaled: with F_i and h F_i
            # apart, XLA computes each stage twice, in two fusions.
            y1, ks, f_last = explicit_rk_step(
                solver, lambda tt, z, scale: self.flows(st.mode, tt, z, args, scale=scale), t, y, hh, f0)
            y_err = None

        def error_norm(ops):
            y, y1, ks, y_err = ops
            err = rk_error_estimate(solver, ks, y) if y_err is None else y_err
            return scaled_error(y, y1, err, c.rtol, c.atol), _rows_all(jnp.isfinite(y1))

        # Read by many fusions below, each of which would recompute it from the stages.
        e, finite_y1 = _computed_once(error_norm, sg((y, y1, ks, y_err)), jnp.any(stepping))
        # The step-size rule of `FastIController`, per lane (a step with a non-finite value is
        # rejected and shrunk by `nonfinite_step`, whatever the rule proposes).
        pid = PIDState(st.inv_error, st.prev_inv_error, st.at_dtmin)
        keep, proposed, pid_new = pid_controller(e, pid, c._get_error_order(self.error_order), hh, c)
        keep = keep & finite_y1
        if num_watch:
            hs = sg(hh)
            times = self.sample_times(t, t_next)

            def guard_samples(ops):
                y_sg, y1_sg, ks_sg, hs, times, mode, args = ops
                safe_h = jnp.maximum(hs, jnp.finfo(self.dtype).tiny)
                samples, slopes = [], []
                last = len(self.thetas) - 1
                for i in range(len(self.thetas)):
                    samples.append(y_sg if i == 0 else y1_sg if i == last else
                                   stage_combination(self.w_value[i], y_sg, y1_sg, ks_sg))
                    slopes.append(stage_combination(self.w_slope[i], y_sg, y1_sg, ks_sg) / safe_h)

                def guard_jvp(m, tt, yy, yd, a):
                    return jax.jvp(lambda t_, y_: kern.slot_guards(m, t_, y_, sg(a)), (tt, yy),
                                   (jnp.ones_like(tt), yd))

                pairs = [self.lane_map(guard_jvp, mode, tt, yy, yd, args=args)
                         for tt, yy, yd in zip(times, samples, slopes, strict=True)]
                G_e, D_e = [p[0] for p in pairs], [p[1] for p in pairs]  # (S, N) each
                finite_G = _rows_all(jnp.stack([_rows_all(jnp.isfinite(g)) for g in G_e[1:]]))
                return G_e, D_e, finite_G

            # Zeros where no lane steps: every use below is masked by `stepping`.
            some_step = jnp.any(stepping)
            ops = (sg(y), sg(y1), [sg(k) for k in ks], hs, times, st.mode, sg(args))
            G_e, D_e, finite_G = _computed_once(guard_samples, ops, some_step)
        else:
            finite_G = jnp.ones_like(keep)
        # A non-finite value anywhere in the step rejects it and shrinks it (`nonfinite_step`).
        finite, h_new, stuck = nonfinite_step(finite_y1, finite_G, proposed, sg(hh), sg(t), self.eps)
        h_new = sg(h_new)
        keep = keep & finite
        counted = eqx.tree_at(
            lambda s: (s.h, s.num_steps, s.num_rejected), st,
            (jnp.where(stepping, h_new, st.h), st.num_steps + stepping.astype(jnp.int32),
             st.num_rejected + (stepping & ~keep).astype(jnp.int32)))
        if pid_new is not pid:  # a rule with history (`has_history`): kept where the step is finite
            kept_rule = tuple(jnp.where(stepping & finite, a, b) for a, b in zip(pid_new, pid, strict=True))
            counted = eqx.tree_at(lambda s: (s.inv_error, s.prev_inv_error, s.at_dtmin), counted, kept_rule)
        if num_watch:
            ok = keep & stepping
            det = _detect(st.g_prev_slots, G_e, D_e, times, some_step)
            has = det.has & ok
            det = det._replace(has=has, suspect=dip_filter(has, det.j, det.suspect & ok, det.i_d))
            need = _rows_any(has | det.suspect)
        acc = stepping & keep
        new = eqx.tree_at(
            lambda s: (s.t, s.y, s.f0, s.zero_run), counted,
            (jnp.where(acc, t_next, counted.t), jnp.where(acc, y1, counted.y),
             jnp.where(acc, f_last, counted.f0), jnp.where(acc, 0, counted.zero_run)))
        if num_watch:
            new = eqx.tree_at(lambda s: s.g_prev_slots, new, jnp.where(acc, G_e[-1], new.g_prev_slots))
        reached = acc & (t_next >= st.t1)
        if num_watch:
            def events(idx, carry):
                # Lanes with an event in this step: undo the acceptance above, then locate,
                # jump, and start the next epoch (all only when some lane needs it), on the
                # block of those lanes.
                new_all, rec, t_end = carry
                out = self.lane_map(self._event_lane,
                                    *self.take((LaneStep(t, t_next, y, y1, ks), det, st.mode, h_new,
                                                st.t1), idx),
                                    args=self.lane_args(st, idx))
                # The event's state and the next epoch's start test feed several fields'
                # updates each: computed once (`_materialize`). The flags and indices, cheap to
                # recompute, are not copied (each copy is a kernel per block).
                nxt = out.next
                shared = (out.t_ev, out.y_before, out.y_after, nxt.fire, nxt.finite, nxt.g_start, nxt.h,
                          nxt.F)
                t_ev, y_before, y_after, fire, finite, g_start, h, F = _materialize(shared, jnp.any(need))
                out = out._replace(t_ev=t_ev, y_before=y_before, y_after=y_after,
                                   next=nxt._replace(fire=fire, finite=finite, g_start=g_start, h=h, F=F))
                back = ("t", "y", "f0", "g_prev_slots", "zero_run")
                new = b0 = _gather_lanes(new_all, idx)
                before = _gather_lanes(st, idx)
                in_block = self.in_block(idx, need)
                ev = in_block & out.event
                new = eqx.tree_at(lambda s: [getattr(s, f) for f in back], new,
                                  [jnp.where(ev, getattr(before, f), getattr(new, f)) for f in back])
                new = _stop(new, (in_block & self.take(reached, idx) & ~ev, Status.T1_REACHED))
                blocked = ev & blocks(out.k, K)
                new = eqx.tree_at(lambda s: (s.t, s.y), new,
                                  (jnp.where(blocked, out.t_ev, new.t),
                                   jnp.where(blocked, out.y_before, new.y)))
                new = _stop(new, (blocked, Status.BLOCKED))
                if K:
                    jumping = ev & ~blocks(out.k, K)
                    new, rec, _ = self.jump(new, rec, jumping, out.k, out.t_ev, out.y_before, out.y_after,
                                            out.simultaneous, out.grazing, zero_length=False, window=False)
                    # The new epoch's start test was done with the event: where no guard fires
                    # at once, start it here (the start stage handles the rest next iteration,
                    # and the epoch after a Zeno completion, which starts it anew). The Zeno
                    # test follows the last block (`zeno_stage`).
                    go = (jumping & new.at_start & ~new.done & ~out.next.fire
                          & out.next.finite & (new.t < new.t1))
                    new = eqx.tree_at(
                        lambda s: (s.at_start, s.g_prev_slots, s.h, s.f0), new,
                        (new.at_start & ~go, jnp.where(go, out.next.g_start, new.g_prev_slots),
                         jnp.where(go, out.next.h, new.h), jnp.where(go, out.next.F, new.f0)))
                    new = self.restart_step_rule(new, go)
                new_all = _scatter_lanes(new_all, b0, new, idx)
                # An event lane's step saves up to its event time (elsewhere to t_next).
                if self.save_ts.shape[0]:
                    t_save = jnp.where(ev, sg(out.t_ev), self.take(t_end, idx))
                    t_end = t_save if idx is None else t_end.at[idx].set(t_save, mode="drop")
                return new_all, rec, t_end

            def some_events(carry):
                new, rec, t_end = carry
                new = _stop(new, (reached & ~need, Status.T1_REACHED))
                return self.on_block(need, events, (new, rec, t_end))

            def no_events(carry):
                new, rec, t_end = carry
                return _stop(new, (reached, Status.T1_REACHED)), rec, t_end

            new, rec, t_end = lax.cond(jnp.any(need), some_events, no_events, (new, rec, sg(t_next)))
            if K and self.zeno is not None:
                new, rec = self.step_zeno_stage(st, new, rec, args)
            took = acc
        else:
            new = _stop(new, (reached, Status.T1_REACHED))
            took, t_end = acc, sg(t_next)
        if self.save_ts.shape[0]:
            new, rec = self.save(new, rec, st.mode, took, t, t_next, t_end, y, y1, ks, t_from)
        # A non-finite step that cannot be shrunk any further stops the lane at the step's
        # start, where everything was finite.
        stops = step_stops(stuck, finite, h_new, sg(t), self.eps, new.num_steps, self.max_steps)
        new = _stop(new, *((stepping & pred, status) for pred, status in stops))
        return new, rec

    # ------------------------------------------------------------------ saved states
    def save(self, st: Lanes, rec: LaneRecord, mode, took, t, t_next, t_end, y, y1, ks, t_from):
        """Write the save times in (t_from, t_end] of each lane whose step was taken, from the
        step's dense output on [t, t_next] (the pre-event state at an event time; t_from <= t
        the step's start before `clip_to_times` moved it past a jump time), SAVE_WINDOW sorted
        save times per pass; a bounded loop of passes covers a step with more."""
        S = self.save_ts.shape[0]
        lanes = st.exec_id
        dense = ChebyshevDense.from_stages(self.cheb, t, t_next, y, y1, ks)  # coeffs (D+1, n, N)
        # The same, its arrays with a save-time axis before the lanes' (lanes last).
        windowed = ChebyshevDense(t0=t, t1=t_next, y0=dense.y0[:, None, :], dy=dense.dy[:, None, :],
                                  coeffs=dense.coeffs[:, :, None, :])

        def pending(ptr):
            return took & (ptr < S) & (self.save_sorted[jnp.minimum(ptr, S - 1)] <= t_end)

        def window(carry):
            rec, ptr = carry
            idx = ptr[None, :] + jnp.arange(SAVE_WINDOW)[:, None]  # (SAVE_WINDOW, N)
            tt = self.save_sorted[jnp.minimum(idx, S - 1)]
            ok = took & (idx < S) & saved_in_step(tt, sg(t_from), t_end)
            vals = windowed.evaluate(within_step(tt, t, t_next)[None])  # (n, SAVE_WINDOW, N)
            rows = jnp.where(ok, self.save_order[jnp.minimum(idx, S - 1)], S)  # S: dropped
            ys = rec.ys.at[lanes[None, :], rows].set(jnp.moveaxis(vals, 0, -1), mode="drop")
            modes = rec.saved_modes.at[lanes[None, :], rows].set(
                jnp.broadcast_to(mode, rows.shape), mode="drop")
            rec = eqx.tree_at(lambda r: (r.ys, r.saved_modes), rec, (ys, modes))
            return rec, ptr + jnp.sum(ok, axis=0, dtype=ptr.dtype)

        def run(carry):
            return eqxi.while_loop(lambda c: jnp.any(pending(c[1])), window, carry,
                                   max_steps=-(-S // SAVE_WINDOW) + 1, kind=self.loop_kind)

        rec, ptr = lax.cond(jnp.any(pending(st.save_ptr)), run, lambda c: c, (rec, st.save_ptr))
        if self.save_t1:
            rec = self.save_at_t1(st, rec, mode, took, t, t_next, t_end, dense, t_from)
        return eqx.tree_at(lambda s: s.save_ptr, st, ptr), rec

    def save_at_t1(self, st: Lanes, rec: LaneRecord, mode, took, t, t_next, t_end, dense,
                   t_from) -> LaneRecord:
        """Write the last save, at each lane's own t1 (`SaveAt(t1=True)`), where t1 lies in the
        step's (t_from, t_end] (`saved_in_step`; `save`'s arguments), from the step's dense output."""
        hit = took & saved_in_step(st.t1, sg(t_from), t_end)

        def put(rec):
            vals = dense.evaluate(within_step(st.t1, t, t_next))
            ids = jnp.where(hit, st.exec_id, self.num_exec)  # num_exec: dropped
            ys = rec.ys.at[ids, -1].set(vals.T, mode="drop")
            modes = rec.saved_modes.at[ids, -1].set(mode, mode="drop")
            return eqx.tree_at(lambda r: (r.ys, r.saved_modes), rec, (ys, modes))

        return lax.cond(jnp.any(hit), put, lambda r: r, rec)

    # ------------------------------------------------------------------ the loop
    def body(self, carry):
        if self.refill:
            carry = self.refill_stage(*carry)
        return self.step_stage(*self.start_stage(*carry))

    def run(self, t0, y0, mode0) -> tuple[Finals, LaneRecord]:
        """The executions from (t0 (N,), y0 (n, N), mode0 (N,)): their final values and record."""
        # Lanes-last by design: per-lane (N,) masks and scalars broadcast against (k, N)
        # arrays along the leading axis, whatever the caller's rank-promotion setting.
        with jax.numpy_rank_promotion("allow"):
            return self._run(t0, y0, mode0)

    def _run(self, t0, y0, mode0) -> tuple[Finals, LaneRecord]:
        rounds = -(-self.num_exec // self.N)  # executions per lane, at most
        carry = perturbed_like_the_body(self.init(t0, y0, mode0), (t0, y0, self.args, self.t1),
                                        LANE_DIFFERENTIABLE_FIELDS)
        # Every lane starts its first epoch: tested on all lanes at once, before the loop, in one
        # pass rather than lanes/block passes of the loop's first iteration (at the price of
        # one more compiled copy of the start stage).
        carry = self.start_stage(*carry, in_blocks=False)
        st, rec = eqxi.while_loop(
            lambda c: jnp.any(~c[0].done) | (c[0].next_exec < self.num_exec),
            self.body,
            carry,
            max_steps=rounds * (self.max_steps + self.max_epochs + 2),
            # The record is write-only in the loop, each entry written once: as buffers it is
            # updated in place and kept out of the reverse pass's checkpoints.
            buffers=lambda c: c[1].buffers(),
            kind=self.loop_kind,
            checkpoints=self.checkpoints if self.loop_kind == "checkpointed" else None,
        )
        st = _stop(st, (jnp.ones_like(st.done), Status.MAX_STEPS))
        if not self.refill:
            return Finals.of(st), rec
        rec = self.flush(st, rec, st.exec_id < self.num_exec)
        finals = jtu.tree_map(lambda a: a[..., :self.num_exec], rec.finals)
        return finals, eqx.tree_at(lambda r: r.finals, rec, None, is_leaf=lambda x: x is None)
