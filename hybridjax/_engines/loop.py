"""The execution loop: one bounded/checkpointed while loop whose iterations are solver steps,
with the rare work of an execution (its events and epoch starts) in a separate phase.

Each iteration does, in order:

1. `event_phase`, where it is due (`due`): for every execution waiting for it, `resolve_stage`
   locates the first event on its held step's dense output (where the step's samples cross or
   dip, `detection`) and jumps (record the event, apply the reset), or accepts the step; then
   `start_stage`, at the start of an epoch, decides whether a guard fires at once (a
   zero-length epoch, `_rules.start.epoch_start`) and if not chooses the epoch's first step.
   A guard that fires at once is applied by the next event phase's `resolve_stage`, through
   the same jump (the execution waits at the epoch's start meanwhile), so that the program
   holds one copy of the jump.
2. `step_stage`, the hot path: one step of the solver with its step-size controller for every
   execution not waiting; the watched values at the step's samples and whether they cross or
   may dip (`needs_location`). A step without a candidate is accepted (and its save times
   written); a step with one is held, with its samples, and the execution waits for the event
   phase, which works out where from what it keeps. Only the yes-or-no is computed at every
   step: the first crossing's and dip's indices and the tangents' intersection would be
   computed for every execution at every step, and under `jax.vmap` XLA:CPU then keeps the
   samples as (executions, samples, n) arrays read by many fusions, slower than the yes-or-no
   alone (`benchmarks/guard_cost.py`).
3. `flush`: the events of the phase written into the max_epochs-long `EventRecord`.

Alone, an execution enters the event phase at the iteration after it needs it, so its
sequence of steps and events is the same as a loop that locates each event at once. Under
`jax.vmap` the phase runs when every running execution waits for it, or when one has waited
`MAX_WAIT` iterations: its cost (root searches, Lie derivatives, resets) is then paid once for
many executions, where a `lax.cond` taken whenever any execution needs it would be taken at
almost every iteration of a large batch. Only the small per-execution state passes through
the phase's `lax.cond` (a conditional copies what it passes through).

An epoch is therefore one integration by the solver's own `step`, the controller's
`adapt_step_size` and dense interpolation, ended by an event. For reverse mode (diffrax's
`RecursiveCheckpointAdjoint()`) the loop is `checkpointed_while_loop`, which differentiates the
carried fields of `DIFFERENTIABLE_FIELDS` through checkpoints; with a number of checkpoints
given, equinox's checkpointed loop, which keeps to it; for `ForwardMode` equinox's `lax` while
loop, for `DirectAdjoint` its `bounded` one (both modes; a bare `lax.while_loop` cannot be
reverse-differentiated).
The guards are sampled on the dense output at constant fractions of the step (for an explicit
Runge-Kutta solver, constant weights of its stages, `dense_weights`: elementwise arithmetic,
where diffrax's interpolation is a small matrix product per sample); events are located on
diffrax's interpolation itself.

Event times are differentiated by the implicit function theorem with the true vector field,
dt*/dtheta = -(dg/dtheta) / (D_t g + D_x g F(t*, x*)), rather than through the root finder's
iterations, with the event held at a fixed elapsed time within its step (`event_point`), so
that a shift of an epoch's start time moves its event time one-for-one; the next epoch starts
at that traced time, so AD through the loop composes flows and resets into the saltation
matrix.
"""

import dataclasses
from typing import Any

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax import lax

from .._core.status import Status
from .._core.transforms import runs_batched
from .._definition.kernels import Kernels, mask_inputs
from .._rules.detect import dip_candidates, dip_filter, first_crossings, needs_location
from .._rules.jump import blocks, jump_outcome, push_recent, zeno_completion
from .._rules.locate import event_brackets, event_point, first_event
from .._rules.options import SolveOptions
from .._rules.records import Detection
from .._rules.save import saved_in_step, within_step
from .._rules.start import carries_step, epoch_start
from .._rules.status import stop_first
from .._rules.step import nonfinite_step, step_stops
from .._rules.tolerances import clip_to_times, event_time_tol, step_end
from .._rules.zeno import detect_zeno
from .._step.runge_kutta import UnrolledERK
from .checkpointed import checkpointed_while_loop
from .dense_weights import ChebyshevDense, chebyshev_weights, dense_weights, stage_combination
from .seeding import perturbed_like_the_body

sg = lax.stop_gradient
# Save rows interpolated as a window when every execution's rows in a step lie within this many
# consecutive indices (all rows otherwise).
SAVE_WINDOW = 16
# Under `jax.vmap`, the most iterations an execution waits for the event phase (`Loop.body`).
MAX_WAIT = 16
# Events an event phase can record before they are written into the record: its one jump (a
# held step's event or a transition fired at an epoch's start) and a Zeno completion.
PEND_SLOTS = 2


class LoopState(eqx.Module):
    """Everything one execution carries from one iteration to the next."""

    t: jax.Array
    y: jax.Array
    mode: jax.Array
    h: jax.Array  # the next step's size (0 before the first)
    solver_state: Any
    controller_state: Any
    made_jump: jax.Array
    at_start: jax.Array
    g_prev: jax.Array  # (K + W,) the watched values at the last sample (the epoch's start values)
    num_events: jax.Array
    zero_run: jax.Array
    num_steps: jax.Array
    num_rejected: jax.Array
    done: jax.Array
    status: Status
    # Events recorded in an event phase (at most PEND_SLOTS), written into the `EventRecord`
    # once at the end of the phase. Keeping the max_epochs-long record out of the state keeps
    # it out of the many per-execution selects of the phase.
    pend_count: jax.Array
    pend_at: jax.Array
    pend_time: jax.Array
    pend_transition: jax.Array
    pend_before: jax.Array
    pend_after: jax.Array
    pend_target: jax.Array
    pend_simultaneous: jax.Array
    pend_grazing: jax.Array
    pend_inside: jax.Array
    zeno_time: jax.Array
    zeno_state: jax.Array
    recent_times: jax.Array  # the last zeno_window + 2 event times, oldest first (Zeno test)
    recent_states: jax.Array  # the last 3 post-event states
    # A step whose samples show a crossing or a dip, held for the event phase (`Loop.event_phase`):
    # the execution stays at the step's start (t, y) until the phase locates its event.
    pending: jax.Array  # () bool
    waited: jax.Array  # () int32: iterations spent waiting for the event phase
    p_t0: jax.Array  # the step's start (after `clip_to_times`) and end
    p_t1: jax.Array
    p_y1: jax.Array
    p_dense: Any  # the solver's dense-output coefficients of the step
    p_solver_state: Any
    p_made_jump: jax.Array
    # The watched values and their slopes at the step's samples (start, interior points, end)
    # as the step stage computed them: the event phase reads its crossings and dips from them.
    # One stacked array: carried as two, the program compiled wrong under the test suite's
    # XLA flags (level 0, fusion emitters off; a vmapped batch of balls with save times
    # located a bounce late), and right under every other setting tried.
    p_GD: jax.Array  # (2, interior_points + 2, K + W): values, slopes
    # A transition that fires at the start of an epoch (`start_stage`), waiting for the next
    # event phase, whose one jump (`resolve_stage`) applies it: the program has one copy of the
    # jump (reset, record, Zeno test) for the events of held steps and of epoch starts.
    f_fire: jax.Array  # () bool
    f_k: jax.Array  # () int32: the transition that fires
    f_simultaneous: jax.Array
    f_inside: jax.Array
    f_finite: jax.Array  # the start's vector field and watched values are finite (else NONFINITE)


class EventRecord(eqx.Module):
    """The events of one execution, padded to max_epochs (inf / -1 / False), and its saved
    states (inf / -1 where not reached). Kept out of `LoopState`: both are long, and the
    per-execution selects of an iteration would otherwise copy them several times."""

    event_times: jax.Array
    transitions: jax.Array
    states_before: jax.Array
    states_after: jax.Array
    epoch_modes: jax.Array
    simultaneous: jax.Array
    grazing: jax.Array
    inside_guard: jax.Array
    ys: jax.Array
    saved_modes: jax.Array


def _put_rows(arr, rows, value):
    """`arr` with the rows where `rows` (bool, arr.shape[0]) is True set to `value`: a masked
    write, for the short per-execution arrays (a pass over a few rows costs less than a
    scatter, which under vmap has one index per execution)."""
    m = rows.reshape(rows.shape + (1,) * (arr.ndim - 1))
    return jnp.where(m, jnp.asarray(value, arr.dtype), arr)


def _select(pred, a, b):
    """Per-execution `a if pred else b` on whole pytrees (Status items included). Leaves that
    are the same value in both (most of a state: a stage changes a few fields) are not
    selected: the program carries one select per field that differs."""
    return jtu.tree_map(lambda x, y: x if x is y else jnp.where(pred, x, y), a, b)


def _stop(st: LoopState, *rules) -> LoopState:
    """`st` stopped by the first of the rules `(pred, Status)` that holds (`stop_first`)."""
    done, code = stop_first(st.done, st.status._value, *rules)
    return eqx.tree_at(lambda s: (s.done, s.status._value), st, (done, code))


# The carried fields that the loop's body computes from the state, and so from the inputs
# (t0, x0, args, t1), whichever of them is differentiated; the others (step size, controller
# state, the watched values, which the loop keeps without gradients, and the integer and
# boolean fields) never carry a derivative. `perturbed_like_the_body` seeds them; reverse mode
# differentiates exactly them (`checkpointed_while_loop`), so a field missing here loses its
# derivative: tests/test_gradients.py checks the list against equinox's search.
DIFFERENTIABLE_FIELDS = (
    "t", "y", "solver_state", "pend_time", "pend_before", "pend_after", "zeno_time", "zeno_state",
    "recent_times", "recent_states", "p_t0", "p_t1", "p_y1", "p_dense", "p_solver_state",
    "event_times", "states_before", "states_after", "ys",
)


def differentiated_leaves(carry) -> list[bool]:
    """Per leaf of the loop's carry `(LoopState, EventRecord)`, whether it may carry a
    derivative: the inexact leaves of `DIFFERENTIABLE_FIELDS` (`checkpointed_while_loop`)."""
    return [name in DIFFERENTIABLE_FIELDS and eqx.is_inexact_array(leaf)
            for part in carry for name in (f.name for f in dataclasses.fields(part))
            for leaf in jtu.tree_leaves(getattr(part, name))]


class Loop:
    """The loop for one system and one set of options; `run(t0, x0, mode0, args)` runs it."""

    def __init__(
        self,
        system,
        *,
        t1,
        args,
        solver,
        controller,
        save_ts,
        options: SolveOptions,
        loop_kind: str,
        checkpoints,
        dtype,
        step_ts=None,
        jump_ts=None,
    ):
        self.kern = Kernels(system, args, dtype, located=True)
        self.step_ts, self.jump_ts = step_ts, jump_ts  # `clip_to_times`
        dt0, max_epochs, max_steps, zeno = options.dt0, options.max_epochs, options.max_steps, options.zeno
        interior_points, event_tol, max_zero_epochs = (options.events.interior_points, options.events.tol,
                                                       options.max_zero_epochs)
        self.locator = options.events.locator
        self.zeno = zeno
        self.recent = (zeno.window + 2) if zeno is not None else 2
        self.system = system
        self.t1 = t1
        self.args = args
        self.solver = solver
        self.controller = controller
        self.dt0 = dt0
        # Explicit Runge-Kutta (diffrax's, or the same unrolled): epochs after the first start
        # with the controller's last proposal (`first_step`).
        self.carry_step = carries_step(dt0, isinstance(solver, UnrolledERK | diffrax.AbstractERK))
        self.save_ts = save_ts
        self.max_epochs = max_epochs
        self.max_steps = max_steps
        self.interior_points = interior_points
        self.max_zero_epochs = max_zero_epochs
        self.loop_kind = loop_kind
        self.checkpoints = checkpoints
        self.dtype = dtype
        self.eps = jnp.finfo(dtype).eps
        self.event_tol = event_tol
        self.terms = diffrax.ODETerm(lambda t, y, a: self.kern.flow(a[0], t, y, a[1]))
        rtol = getattr(controller, "rtol", None)
        atol = getattr(controller, "atol", None)
        # Band of "zero" for guards at an epoch's start; solvers without tolerances
        # (constant steps) get sqrt(eps), the accuracy a double-precision step can promise.
        self.rtol = jnp.sqrt(self.eps) if rtol is None else rtol
        self.atol = jnp.sqrt(self.eps) if atol is None else atol
        # An explicit RK's dense output as a Chebyshev series of its stages (`dense`).
        self.cheb = (chebyshev_weights(solver.interpolation_cls, len(solver.c) + 1, dtype)
                     if isinstance(solver, UnrolledERK) else None)

    # ----------------------------------------------------------------- helpers
    def error_order(self):
        return self.solver.error_order(self.terms)

    # ----------------------------------------------------------------- init
    def init(self, t0, y0, mode0) -> LoopState:
        n = self.kern.n
        dtype = self.dtype
        args_ext = (mode0, self.args)
        solver_state = self.solver.init(self.terms, t0, self.t1, y0, args_ext)
        _, controller_state = self.controller.init(
            self.terms, t0, self.t1, y0, self.dt0, args_ext, self.solver.func, self.error_order()
        )
        W = self.kern.num_watch
        # The shapes of a step's dense-output coefficients (no step is computed here).
        dense = jax.eval_shape(lambda: self.solver.step(
            self.terms, t0, t0 + 1, y0, args_ext, solver_state, jnp.array(True))[2])
        return LoopState(
            t=t0,
            y=y0,
            mode=mode0,
            h=jnp.zeros((), dtype),
            solver_state=solver_state,
            controller_state=controller_state,
            made_jump=jnp.array(True),
            at_start=jnp.array(True),
            g_prev=jnp.zeros((self.kern.num_watch,), dtype),
            num_events=jnp.array(0, jnp.int32),
            zero_run=jnp.array(0, jnp.int32),
            num_steps=jnp.array(0, jnp.int32),
            num_rejected=jnp.array(0, jnp.int32),
            done=jnp.array(False),
            status=Status.T1_REACHED,
            pend_count=jnp.array(0, jnp.int32),
            pend_at=jnp.zeros((PEND_SLOTS,), jnp.int32),
            pend_time=jnp.zeros((PEND_SLOTS,), dtype),
            pend_transition=jnp.zeros((PEND_SLOTS,), jnp.int32),
            pend_before=jnp.zeros((PEND_SLOTS, n), dtype),
            pend_after=jnp.zeros((PEND_SLOTS, n), dtype),
            pend_target=jnp.zeros((PEND_SLOTS,), jnp.int32),
            pend_simultaneous=jnp.zeros((PEND_SLOTS,), bool),
            pend_grazing=jnp.zeros((PEND_SLOTS,), bool),
            pend_inside=jnp.zeros((PEND_SLOTS,), bool),
            zeno_time=jnp.array(jnp.inf, dtype),
            zeno_state=jnp.full((n,), jnp.inf, dtype),
            recent_times=jnp.full((self.recent,), jnp.inf, dtype),
            recent_states=jnp.full((3, n), jnp.inf, dtype),
            pending=jnp.array(False),
            waited=jnp.array(0, jnp.int32),
            p_t0=jnp.zeros((), dtype),
            p_t1=jnp.zeros((), dtype),
            p_y1=jnp.zeros((n,), dtype),
            p_dense=jtu.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), dense),
            p_solver_state=solver_state,
            p_made_jump=jnp.array(False),
            p_GD=jnp.zeros((2, self.interior_points + 2, W), dtype),
            f_fire=jnp.array(False),
            f_k=jnp.array(0, jnp.int32),
            f_simultaneous=jnp.array(False),
            f_inside=jnp.array(False),
            f_finite=jnp.array(True),
        )

    # ----------------------------------------------------------------- jump
    def _record(self, st: LoopState, index, t_ev, y_before, y_after, target, simultaneous, grazing,
                inside=False):
        """Record an event (as pending: `flush` writes it into the EventRecord)."""
        slot = jnp.arange(PEND_SLOTS) == st.pend_count

        def put(arr, value):
            return _put_rows(arr, slot, value)

        return eqx.tree_at(
            lambda s: (
                s.pend_at, s.pend_time, s.pend_transition, s.pend_before, s.pend_after, s.pend_target,
                s.pend_simultaneous, s.pend_grazing, s.pend_inside, s.pend_count, s.num_events,
                s.recent_times, s.recent_states,
            ),
            st,
            (
                put(st.pend_at, st.num_events),
                put(st.pend_time, t_ev),
                put(st.pend_transition, index),
                put(st.pend_before, y_before),
                put(st.pend_after, y_after),
                put(st.pend_target, target),
                put(st.pend_simultaneous, simultaneous),
                put(st.pend_grazing, grazing),
                put(st.pend_inside, inside),
                st.pend_count + 1,
                st.num_events + 1,
                push_recent(st.recent_times, jnp.asarray(t_ev)),
                push_recent(st.recent_states, y_after),
            ),
        )

    def init_record(self, t0, y0, mode0) -> EventRecord:
        E, n, dtype = self.max_epochs, self.kern.n, self.dtype
        at_t0 = self.save_ts <= t0
        return EventRecord(
            ys=jnp.where(at_t0[:, None], y0[None, :], jnp.inf).astype(dtype),
            saved_modes=jnp.where(at_t0, mode0, -1).astype(jnp.int32),
            event_times=jnp.full((E,), jnp.inf, dtype),
            transitions=jnp.full((E,), -1, jnp.int32),
            states_before=jnp.full((E, n), jnp.inf, dtype),
            states_after=jnp.full((E, n), jnp.inf, dtype),
            epoch_modes=jnp.full((E + 1,), -1, jnp.int32).at[0].set(mode0),
            simultaneous=jnp.zeros((E,), bool),
            grazing=jnp.zeros((E,), bool),
            inside_guard=jnp.zeros((E,), bool),
        )

    def flush(self, rec: EventRecord, st: LoopState) -> EventRecord:
        """Write the pending events of this iteration into the record: one scatter per field,
        at rows `pend_at` (out-of-range rows, for the empty slots, are dropped). The loop's
        condition is unbatched (`run`), so the record is updated in place: each iteration
        touches the few rows it writes, not the whole max_epochs-long record."""
        E = self.max_epochs
        rows = jnp.where(jnp.arange(PEND_SLOTS) < st.pend_count, st.pend_at, E + 1)

        def put(arr, value, off=0):
            return arr.at[rows + off].set(jnp.asarray(value, arr.dtype), mode="drop")

        return eqx.tree_at(
            lambda r: (r.event_times, r.transitions, r.states_before, r.states_after,
                       r.epoch_modes, r.simultaneous, r.grazing, r.inside_guard),
            rec,
            (
                put(rec.event_times, st.pend_time),
                put(rec.transitions, st.pend_transition),
                put(rec.states_before, st.pend_before),
                put(rec.states_after, st.pend_after),
                put(rec.epoch_modes, st.pend_target, 1),  # epoch i + 1 starts after event i
                put(rec.simultaneous, st.pend_simultaneous),
                put(rec.grazing, st.pend_grazing),
                put(rec.inside_guard, st.pend_inside),
            ),
        )

    def _begin_epoch(self, st: LoopState, t, y, mode, zero_run) -> LoopState:
        """Move to the start of a new epoch at (t, y) in `mode` (its start test comes next)."""
        return eqx.tree_at(
            lambda s: (s.t, s.y, s.mode, s.at_start, s.made_jump, s.zero_run),
            st,
            (t, y, mode, jnp.array(True), jnp.array(True), zero_run),
        )

    def jump(
        self, st: LoopState, k, t_ev, y_before, simultaneous, zero_length, args, grazing=False,
        inside=False,
    ) -> LoopState:
        """Record transition k at t_ev and apply its reset; then stop on too many epochs,
        non-finite values, chattering, or Zeno (or complete the Zeno execution)."""
        y_after = self.kern.reset(k, t_ev, y_before, args)
        out = jump_outcome(st.num_events, self.max_epochs, y_after, zero_length, st.zero_run,
                           self.max_zero_epochs)
        target = self.kern.targets[k]
        recorded = self._record(st, k, t_ev, y_before, y_after, target, simultaneous, grazing, inside)
        jumped = self._begin_epoch(recorded, t_ev, y_after, target, out.zero_run)
        # A non-finite reset keeps the event (its after-state shows the culprit) but ends the
        # execution at the pre-event state; an event the record has no room for is not kept.
        held = eqx.tree_at(lambda s: (s.t, s.y), _select(out.recorded, recorded, st), (t_ev, y_before))
        new = _stop(_select(out.applied, jumped, held), *out.stops)
        if self.zeno is not None:
            new = _select(out.applied, self.zeno_stage(new, args), new)
        return new

    def zeno_stage(self, st: LoopState, args) -> LoopState:
        """After an event: if event times accumulate before t1, stop with ZENO or complete."""
        is_zeno, t_inf, x_inf = detect_zeno(st.recent_times, st.recent_states, self.t1, self.zeno)
        is_zeno = is_zeno & ~st.done
        st = eqx.tree_at(
            lambda s: (s.zeno_time, s.zeno_state),
            st,
            (jnp.where(is_zeno, t_inf, st.zeno_time), jnp.where(is_zeno, x_inf, st.zeno_state)),
        )
        stopped = _stop(st, (is_zeno, Status.ZENO))
        if not self.system.completions:
            return stopped
        comp = zeno_completion(
            self.kern, st.mode, is_zeno, t_inf, x_inf, args, st.num_events, self.max_epochs
        )
        st_c = mask_inputs(comp.completes, st)
        done = self._record(st_c, comp.index, comp.t, comp.x, comp.y_after, comp.target, jnp.array(False),
                            jnp.array(False))
        done = self._begin_epoch(done, comp.t, comp.y_after, comp.target, jnp.array(0, jnp.int32))
        stopped = _stop(st, (comp.no_room, Status.MAX_EPOCHS), (is_zeno, Status.ZENO))
        return _select(comp.completes, done, stopped)

    # ----------------------------------------------------------------- start of an epoch
    def start_stage(self, st: LoopState) -> LoopState:
        """The start test of each new epoch (`epoch_start`): a transition that fires at once is
        kept for the next event phase's jump (`f_fire`, the execution waits at the epoch's
        start), a domain component that fires blocks, otherwise the epoch's first step is set."""
        active = st.at_start & ~st.done & ~st.f_fire

        def run(st):
            t, y, mode = sg(st.t), sg(st.y), st.mode
            t_init, ctrl_state = self.controller.init(
                self.terms, t, self.t1, y, self.dt0, (mode, self.args), self.solver.func, self.error_order()
            )
            start = epoch_start(self.kern, mode, t, y, sg(self.args), st.h, t_init - t, carry=self.carry_step,
                                rtol=self.rtol, atol=self.atol, event_tol=self.event_tol, eps=self.eps)
            K = self.kern.num_transitions
            # A domain component (index >= K) "firing" with no guard before it: the state is
            # outside its domain (a reset outside the target domain, or x0) or leaving it.
            blocked = _stop(st, (jnp.array(True), Status.BLOCKED))
            if K:
                deferred = start.fire & ~blocks(start.k, K)
                fired = eqx.tree_at(
                    lambda s: (s.f_fire, s.f_k, s.f_simultaneous, s.f_inside, s.f_finite),
                    st,
                    (jnp.array(True), jnp.minimum(start.k, K - 1), start.simultaneous, start.inside,
                     start.finite),
                )
                fired = _select(blocks(start.k, K), blocked, fired)
            else:
                deferred = jnp.array(False)
                fired = blocked
            go = eqx.tree_at(
                lambda s: (s.at_start, s.g_prev, s.h, s.controller_state, s.made_jump),
                st,
                (jnp.array(False), start.g_start, start.h.astype(self.dtype), ctrl_state, jnp.array(True)),
            )
            go = _stop(go, (st.t >= self.t1, Status.T1_REACHED))
            new = _select(start.fire, fired, go)
            # A deferred transition is applied first, then stopped (`resolve_stage`).
            new = _stop(new, (~start.finite & ~deferred, Status.NONFINITE))
            return _select(active, new, st)

        return lax.cond(eqxi.unvmap_any(active), run, lambda s: s, st)

    # ----------------------------------------------------------------- one step
    def _sample_times(self, t, t_next):
        """The step's sample times, no gradient: its start, `interior_points` equally spaced
        interior points, its end."""
        frac = jnp.arange(1, self.interior_points + 1, dtype=self.dtype) / (self.interior_points + 1)
        return jnp.concatenate([sg(t)[None], sg(t) + (sg(t_next) - sg(t)) * frac, sg(t_next)[None]])

    def _accept(self, st: LoopState, t_next, y1, solver_state, made_jump, g_end) -> LoopState:
        """`st` moved to the end of its accepted step (the epoch goes on), T1_REACHED at t1."""
        accepted = eqx.tree_at(
            lambda s: (s.t, s.y, s.solver_state, s.made_jump, s.g_prev, s.zero_run),
            st,
            (t_next, y1, solver_state, made_jump, g_end, jnp.array(0, jnp.int32)),
        )
        return _stop(accepted, (t_next >= self.t1, Status.T1_REACHED))

    def _samples(self, kern, mode, t, t_next, y0, y1, dense_info, args_sg):
        """The sample times of a step (start, `interior_points` interior points, end), the dense
        output there and the watched values with their slopes along the step."""
        m = self.interior_points
        s_ext = self._sample_times(t, t_next)
        one = jnp.ones_like(s_ext[0])
        # The dense output on the unit interval, at constant fractions theta: its polynomials
        # in theta fold to constants at compile time, leaving one weighted sum of the stages
        # per sample (the same values as on [t, t_next]: diffrax's stages are increments).
        h_safe = jnp.maximum(sg(t_next - t), jnp.finfo(self.dtype).tiny)
        thetas = np.concatenate([[0.0], np.arange(1, m + 2) / (m + 1)])
        if isinstance(self.solver, UnrolledERK):
            # An explicit RK's dense output is linear in (y0, y1, k_i): the weights at each
            # fraction as constants (`dense_weights`), each sample one elementwise sum, which
            # fuses with the step (a matrix product per sample is a pass over the stages each).
            d = sg(dense_info)
            ks = [d["k"][i] for i in range(d["k"].shape[0])]
            value, slope = dense_weights(self.solver.interpolation_cls, len(ks), thetas, self.dtype)
            # The values at the ends are the step's own ends (below): only the slopes there.
            samples = [(None if i in (0, len(thetas) - 1) else stage_combination(v, d["y0"], d["y1"], ks),
                        stage_combination(w, d["y0"], d["y1"], ks))
                       for i, (v, w) in enumerate(zip(value, slope, strict=True))]
        else:
            unit = self.solver.interpolation_cls(t0=jnp.zeros_like(one), t1=one, **sg(dense_info))
            samples = [jax.jvp(unit.evaluate, (jnp.asarray(th, self.dtype),), (one,)) for th in thetas]
        # The first and last samples are the step's own ends (exact, not re-interpolated); set
        # in the list, before stacking, so that the stack is the one array of samples.
        ys_e = jnp.stack([sg(y0)] + [y for y, _ in samples[1:-1]] + [sg(y1)])
        yd_e = jnp.stack([yd for _, yd in samples]) / h_safe
        G_e, D_e = jax.vmap(lambda x, y, yd: jax.jvp(
            lambda tt, yy: kern.guards(mode, tt, yy, args_sg), (x, y), (one, yd)))(s_ext, ys_e, yd_e)
        return s_ext, G_e, D_e

    def _save(self, saved, mask, mode, make_interp, t, t_next):
        """Write the states at the save times selected by `mask` (inside [t, t_next]) from the
        step's dense output, `make_interp()` (called only where there are save times: the
        program holds no interpolant that nothing reads), into `saved`, the record's
        `(ys, saved_modes)`."""
        if not self.save_ts.shape[0]:
            return saved
        interp = make_interp()
        rec_ys, rec_modes = saved

        def put_all(ys):
            vals = jax.vmap(interp.evaluate)(within_step(self.save_ts, t, t_next))
            return _put_rows(ys, mask, vals)

        S = self.save_ts.shape[0]
        i0 = jnp.argmax(mask)  # the first save row in this step
        span = jnp.where(jnp.any(mask), S - jnp.argmax(mask[::-1]) - i0, 0)

        def put_few(ys):
            # Every execution's save rows in this step lie in i0 .. i0 + SAVE_WINDOW - 1:
            # evaluate the interpolant there (not at all S rows) and scatter those rows (the
            # others, and rows past S, to the dropped row S): the record is written in place
            # (`run`), a few rows per execution rather than a pass over all S.
            idx = i0 + jnp.arange(SAVE_WINDOW)
            idx_c = jnp.minimum(idx, S - 1)
            vals = jax.vmap(interp.evaluate)(within_step(self.save_ts[idx_c], t, t_next))
            rows = jnp.where((idx < S) & mask[idx_c], idx, S)
            return ys.at[rows].set(vals, mode="drop")

        def put(ys):
            few = eqxi.unvmap_max(span) <= SAVE_WINDOW
            return lax.cond(few, put_few, put_all, ys)

        # Most steps of most executions contain no save time: skip the interpolation then.
        ys = lax.cond(eqxi.unvmap_any(mask), put, lambda ys: ys, rec_ys)
        return ys, jnp.where(mask, mode, rec_modes)

    def step_stage(self, st: LoopState, saved):
        """One step of every execution that is not waiting for the event phase: the solver's
        step, the step-size decision, the watched values at the step's samples and the crossing
        and dip tests on them. A step without a crossing or dip candidate is accepted here (and
        its save times written); one with a candidate is held (`pending`) for `event_phase`."""
        active = ~st.done & ~st.at_start & ~st.pending
        # Executions that do not step here still compute a step (vmap); their inputs get no
        # gradient, so a NaN in their discarded results cannot reach one (double where).
        st_all = st
        st, args = mask_inputs(active, (st, self.args))
        kern, mode = self.kern, st.mode
        args_ext = (mode, args)
        t = st.t
        t_next = step_end(t, st.h, self.t1)
        fresh_f = st.made_jump
        if self.step_ts is not None or self.jump_ts is not None:
            t, t_next, jumped = clip_to_times(t, t_next, self.t1, self.step_ts, self.jump_ts)
            fresh_f = fresh_f | jumped  # past a jump time: the field evaluated anew
        y1, y_err, dense_info, solver_state, _ = self.solver.step(
            self.terms, t, t_next, st.y, args_ext, st.solver_state, fresh_f
        )
        keep, nt0, nt1, made_jump, ctrl_state, _ = self.controller.adapt_step_size(
            t, t_next, st.y, y1, args_ext, y_err, self.error_order(), st.controller_state
        )
        # detect: watched values at the start, interior points and end of the step.
        s_ext, G_e, D_e = self._samples(kern, mode, t, t_next, st.y, y1, dense_info, sg(args))
        G = G_e[1:]
        # A non-finite value anywhere in the step rejects it and shrinks it (`nonfinite_step`);
        # the controller's NaN error and proposal are not used.
        h = sg(t_next - t)
        finite, h_new, stuck = nonfinite_step(jnp.all(jnp.isfinite(y1)), jnp.all(jnp.isfinite(G)), nt1 - nt0,
                                              h, sg(t), self.eps)
        keep = keep & finite
        h_new = sg(h_new).astype(self.dtype)
        ctrl_state = _select(finite, ctrl_state, st.controller_state)
        ok = keep & active
        # A step with a crossing or a dip candidate is held for the event phase, which works
        # out where (`detection`) from the step it keeps.
        held = ok & needs_location(st.g_prev, G_e, D_e, s_ext)

        counted = eqx.tree_at(
            lambda s: (s.h, s.controller_state, s.num_steps, s.num_rejected),
            st,
            (h_new, ctrl_state, st.num_steps + 1, st.num_rejected + (~keep).astype(jnp.int32)),
        )
        accepted = self._accept(counted, t_next, y1, solver_state, made_jump, G[-1])
        pending = eqx.tree_at(
            lambda s: (s.pending, s.waited, s.p_t0, s.p_t1, s.p_y1, s.p_dense, s.p_solver_state,
                       s.p_made_jump, s.p_GD),
            counted,
            (jnp.array(True), jnp.array(0, jnp.int32), t, t_next, y1, dense_info, solver_state,
             made_jump, jnp.stack([G_e, D_e])),
        )
        progressed = _select(keep, _select(held, pending, accepted), counted)
        # A non-finite step that cannot be shrunk any further stops the run at the step's
        # start, where everything was finite. A held step's stops are decided with its event.
        stops = step_stops(stuck, finite, h_new, sg(t), self.eps, progressed.num_steps, self.max_steps)
        new = _stop(_select(stuck, counted, progressed), *[(p & ~held, s) for p, s in stops])
        saved = self._save(saved, keep & active & ~held & saved_in_step(self.save_ts, sg(st.t), sg(t_next)),
                           mode, lambda: self.dense(t, t_next, dense_info), t, t_next)
        return _select(active, new, st_all), saved

    def dense(self, t, t_next, dense_info):
        """The step's dense output on [t, t_next], where events are located and saved states
        read: for an explicit RK, the solver's interpolation written as a Chebyshev series of
        its stages (`ChebyshevDense`, as the batched engine's: a few elementwise operations per
        evaluation, where diffrax's interpolation builds its polynomials in theta and contracts
        them with the stages, a small matrix product that `jax.vmap` makes a batched one); for
        any other solver, its own interpolation."""
        if self.cheb is None:
            return self.solver.interpolation_cls(t0=t, t1=t_next, **dense_info)
        ks = [dense_info["k"][i] for i in range(dense_info["k"].shape[0])]
        return ChebyshevDense.from_stages(self.cheb, t, t_next, dense_info["y0"], dense_info["y1"], ks)

    def detection(self, st: LoopState, active, s_ext) -> Detection:
        """The held step's crossings and dip candidates (`first_crossings`, `dip_candidates`,
        `dip_filter`), from the samples `step_stage` took and kept (`p_GD`) at the held step's
        sample times `s_ext`: the values that decided to hold the step decide where its events
        lie, and the event phase holds no second copy of the sampling. Zeros where not
        `active`."""
        G, D_e = st.p_GD[0, 1:], st.p_GD[1]
        has, j = first_crossings(st.g_prev, G)
        # A guard can dip below zero and come back between two samples (near-grazing): where
        # the end tangents allow it, the minimum is searched for on the interpolant.
        suspect, i_d, x0_d = dip_candidates(jnp.concatenate([st.g_prev[None], G]), D_e, s_ext)
        has = has & active
        det = Detection(has, j.astype(jnp.int32), dip_filter(has, j, suspect & active, i_d),
                        i_d.astype(jnp.int32), x0_d)
        return jtu.tree_map(lambda a: jnp.where(active, a, jnp.zeros_like(a)), det)

    def resolve_stage(self, st: LoopState, saved):
        """The held steps: locate the first event on each step's dense output (`event_brackets`,
        `first_event`), take its event point and jump, or accept the step where the candidate
        was a dip that stays positive; save the step's save times up to the event. The same
        jump applies the transitions that fired at an epoch's start (`f_fire`, `start_stage`),
        as a zero-length epoch at the execution's (t, y)."""
        active = st.pending & ~st.done
        fire = st.f_fire & ~st.done  # never pending at once
        st_all = st
        # Inputs of a branch not taken get no gradient (NaN-safe "double where").
        st_f, args_f = mask_inputs(fire, (st, self.args))
        st, args = mask_inputs(active, (st, self.args))
        kern, mode = self.kern, st.mode
        t, t_next, dense_info = st.p_t0, st.p_t1, st.p_dense
        interp = self.dense(t, t_next, dense_info)
        interp_sg = jtu.tree_map(sg, interp)  # the same values, without derivatives
        args_sg = sg(args)
        s_ext = self._sample_times(t, t_next)
        h = sg(t_next - t)
        tol = event_time_tol(self.event_tol, sg(t_next), h, self.eps)

        def values_at(x):
            return kern.guards(mode, x, interp_sg.evaluate(x), args_sg)

        det = self.detection(st, active, s_ext)
        br = event_brackets(values_at, det, s_ext, tol, self.locator)
        t_star, k, simultaneous = first_event(values_at, br, tol, sg(t_next), self.locator)
        any_event = jnp.any(br.has)
        t_ev, y_before, grazing = event_point(self.kern, self.eps, mode, k, t_star, interp, args, tol)
        k = kern.select(mode, k, t_ev, y_before, args)
        # saves up to the event time reported (t* moved onto the guard, `onto_the_guard`)
        t_end = jnp.where(any_event, sg(t_ev), sg(t_next))
        saved = self._save(saved, active & saved_in_step(self.save_ts, sg(st.t), t_end), mode, lambda: interp,
                           t, t_next)

        base = eqx.tree_at(lambda s: s.pending, st, jnp.array(False))
        accepted = self._accept(base, t_next, st.p_y1, st.p_solver_state, st.p_made_jump, st.p_GD[0, -1])
        # The domain left (`blocks`) before any guard: BLOCKED at the exit, state kept.
        blocked = eqx.tree_at(lambda s: (s.t, s.y), base, (t_ev, y_before))
        evented = _stop(blocked, (jnp.array(True), Status.BLOCKED))
        K = kern.num_transitions
        if K:
            base_e = mask_inputs(active & any_event & ~blocks(k, K), base)
            base_f = eqx.tree_at(lambda s: s.f_fire, st_f, jnp.array(False))
            # One jump: the held step's event, or the transition fired at the epoch's start.
            jumped = self.jump(
                _select(fire, base_f, base_e),
                jnp.where(fire, st_all.f_k, jnp.minimum(k, K - 1)),
                jnp.where(fire, st_f.t, t_ev),
                jnp.where(fire, st_f.y, y_before),
                jnp.where(fire, st_all.f_simultaneous, simultaneous),
                fire,
                _select(fire, args_f, args),
                grazing & ~fire,
                inside=fire & st_all.f_inside,
            )
            evented = _select(blocks(k, K), evented, jumped)
            started = _stop(jumped, (~st_all.f_finite, Status.NONFINITE))
        progressed = _select(any_event, evented, accepted)
        new = _stop(progressed, *step_stops(jnp.array(False), jnp.array(True), st.h, sg(t), self.eps,
                                            progressed.num_steps, self.max_steps))
        new = _select(active, new, st_all)
        return (_select(fire, started, new) if K else new), saved

    def event_phase(self, carry):
        """The rare work, for every execution waiting for it at once: the held steps' events
        (`resolve_stage`), then the start test of each new epoch (`start_stage`). Events are
        recorded as pending (`flush` writes them); `carry` is `(state, (ys, saved_modes))`."""
        st, saved = carry
        if self.kern.num_watch:
            st, saved = self.resolve_stage(st, saved)
        st = self.start_stage(st)
        return eqx.tree_at(lambda s: s.waited, st, jnp.zeros_like(st.waited)), saved

    # ----------------------------------------------------------------- the loops
    def due(self, st: LoopState):
        """Whether the event phase is due: every running execution waits for it, or one has
        waited `MAX_WAIT` iterations (under `jax.vmap`, one decision for the whole batch)."""
        waiting = (st.pending | st.at_start) & ~st.done
        return eqxi.unvmap_all(waiting | st.done) | (eqxi.unvmap_max(jnp.where(waiting, st.waited, 0))
                                                     >= MAX_WAIT)

    def body(self, carry):
        """One iteration: the event phase where it is due (`due`), then a step of every
        execution not waiting for it (`step_stage`), then the phase's events written into the
        record (`flush`). Only the small per-execution state passes through the phase's
        `lax.cond` (a conditional copies what it passes through; the saved states only where
        there are save times)."""
        st, rec = carry
        st, saved = lax.cond(self.due(st), self.event_phase, lambda c: c, (st, (rec.ys, rec.saved_modes)))
        new, (ys, saved_modes) = self.step_stage(st, saved)
        rec = self.flush(eqx.tree_at(lambda r: (r.ys, r.saved_modes), rec, (ys, saved_modes)), new)
        still = (new.pending | new.at_start) & ~new.done
        new = eqx.tree_at(lambda s: (s.waited, s.pend_count), new,
                          (jnp.where(still, new.waited + 1, 0), jnp.zeros_like(new.pend_count)))
        return new, rec

    def run(self, t0, y0, mode0) -> tuple[LoopState, EventRecord]:
        carry = (self.init(t0, y0, mode0), self.init_record(t0, y0, mode0))
        carry = perturbed_like_the_body(carry, (t0, y0, self.args, self.t1), DIFFERENTIABLE_FIELDS)
        # Steps, zero-length epochs, and the waits for the event phase: alone, an execution
        # never waits; under vmap at most MAX_WAIT iterations before each event or epoch start
        # (a held step whose dip stays positive waits too, and is not counted here).
        bound = self.max_steps + (self.max_epochs + 2) * (MAX_WAIT + 2)
        # The condition is one decision for the whole batch under `jax.vmap` (`unvmap_any`):
        # with a per-execution condition, vmap's while loop would select every carried array
        # (the record included) between its old and new value at every iteration, a pass over
        # all of it that also keeps the record from being updated in place. Every stage leaves
        # a finished execution as it is, so running the body for it changes nothing.
        cond = lambda c: eqxi.unvmap_any(~c[0].done)  # noqa: E731
        if self.loop_kind == "checkpointed" and self.checkpoints is None:
            # One execution keeps each iteration's linearisation (a smaller program, compiled
            # sooner); a batch keeps its carries, which runs faster under `jax.vmap`.
            st, rec = checkpointed_while_loop(cond, self.body, carry, max_steps=bound, checkpoints=None,
                                              differentiated=differentiated_leaves,
                                              keep="carries" if runs_batched() else "residuals")
        else:
            # A number of checkpoints given is a memory budget (diffrax's meaning): equinox's
            # loop keeps to it, recomputing more where it is small.
            checkpoints = self.checkpoints if self.loop_kind == "checkpointed" else None
            st, rec = eqxi.while_loop(cond, self.body, carry, max_steps=bound, kind=self.loop_kind,
                                      checkpoints=checkpoints)
        # The loop's own bound can only be met by executions that are still running.
        return _stop(st, (jnp.array(True), Status.MAX_STEPS)), rec
