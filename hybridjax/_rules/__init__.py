"""The execution rules: each rule of a hybrid execution written once, as a pure function of
one execution.

Both engines call these functions: the per-execution loop (`_engines.loop.Loop`) directly, the batched
loop (`_engines.batched.BatchedLoop`) lifted over its lanes, with `jax.vmap` (`BatchedLoop.lane_map`) or,
for the functions written elementwise over a leading axis of components, by broadcasting over
the lanes-last axis. An engine holds only storage and iteration (its state, the event record,
gathering and scattering of lanes, the while loop); what an execution *does* is decided here.
The rules, in the order an iteration meets them (docs: Architecture has the table of rules,
functions and tests):

- tolerances: `event_time_tol`, `step_end` (the t_next clamp, `at_most_end`), `continued_past_start`
  (t1 reached at an epoch's start), `clip_to_times` (step_ts,
  jump_ts);
- the start of an epoch: `epoch_start` (`start_decision`: the trending-negative band and Lie
  derivatives; `first_step`, `departure_step_bound`);
- a step: `nonfinite_step`, `step_collapsed`, `step_stops`;
- detection on a step's dense output: `crossing`, `dip_interval`, `needs_location`,
  `first_crossings`, `dip_candidates`, `dip_filter`;
- location: `event_brackets` (`locate_minimum`), `first_event` (`locate_root`, started at
  `hermite_root`; the guards reached at one instant, `simultaneous_set`, and the simultaneity
  rule, `resolve_simultaneous`), `event_point` (the implicit-function event time; its state in
  the guard, `onto_the_guard`);
- the jump: `blocks`, `jump_outcome`, `push_recent`, `zeno_completion`;
- Zeno: `detect_zeno` (on one execution's window, or on lanes' windows, lanes last);
- saving: `saved_in_step`, `within_step` (a save time inside its step);
- the precedence of statuses: `stop_first`.

Event logic in detail:

- Start of an epoch (execution rule 3, docs: Execution semantics): transition k fires at
  once when g_k < -band, or when |g_k| <= band and g_k is *trending negative*: its first
  non-zero Lie derivative along the flow is negative (A. M. Johnson, "Hybrid Dynamical
  Systems", eq. (7)). A guard inside the band that is not trending negative is *departing*:
  it is disarmed (its previous value is taken as 0) until the flow has been seen to leave it
  (g > 0), so that a bouncing ball does not re-fire after its reset.
- Within a step (execution rule 2): each guard is sampled on the step's dense interpolant at
  `interior_points` interior points and the end; a crossing is the first sample with g <= 0
  after a sample with g > 0, so a guard that dips below zero and comes back inside one step
  is caught (as DifferentialEquations.jl's `interp_points`). Between two samples, g may still
  dip below zero and come back (a near-grazing crossing): where g has a local minimum between
  two positive samples (slopes - then +) and the end tangents allow a value <= 0, the minimum
  is found on the interpolant (`locate_minimum`); a minimum < 0 is a crossing. A minimum of
  exactly 0 (tangency) is not: the guard is touched, not entered.
- Location: a bracketed Newton iteration on the interpolant, falling back to bisection,
  stopping when the bracket is narrower than the event tolerance; the event time is the
  bracket's right end, where g <= 0 (so the pre-event state lies in the guard set).
"""

from .detect import crossing as crossing
from .detect import dip_candidates as dip_candidates
from .detect import dip_filter as dip_filter
from .detect import dip_interval as dip_interval
from .detect import first_crossings as first_crossings
from .detect import needs_location as needs_location
from .jump import blocks as blocks
from .jump import jump_outcome as jump_outcome
from .jump import push_recent as push_recent
from .jump import zeno_completion as zeno_completion
from .locate import event_brackets as event_brackets
from .locate import event_point as event_point
from .locate import first_event as first_event
from .locate import hermite_root as hermite_root
from .locate import locate_minimum as locate_minimum
from .locate import locate_root as locate_root
from .locate import onto_the_guard as onto_the_guard
from .locate import resolve_simultaneous as resolve_simultaneous
from .locate import root_bracket as root_bracket
from .locate import simultaneous_set as simultaneous_set
from .records import Brackets as Brackets
from .records import Detection as Detection
from .records import EpochStart as EpochStart
from .records import EventChoice as EventChoice
from .records import JumpOutcome as JumpOutcome
from .records import NonfiniteStep as NonfiniteStep
from .records import ZenoCompletionStep as ZenoCompletionStep
from .save import saved_in_step as saved_in_step
from .save import within_step as within_step
from .start import carries_step as carries_step
from .start import departure_step_bound as departure_step_bound
from .start import epoch_start as epoch_start
from .start import first_step as first_step
from .start import start_decision as start_decision
from .start import strictly_inside as strictly_inside
from .start import trending_negative as trending_negative
from .start import unresolved_departure as unresolved_departure
from .status import stop_first as stop_first
from .step import nonfinite_step as nonfinite_step
from .step import step_collapsed as step_collapsed
from .step import step_stops as step_stops
from .tolerances import at_most_end as at_most_end
from .tolerances import clip_to_times as clip_to_times
from .tolerances import continued_past_start as continued_past_start
from .tolerances import event_time_tol as event_time_tol
from .tolerances import step_end as step_end
from .zeno import detect_zeno as detect_zeno
