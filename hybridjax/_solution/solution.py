"""The result of `simulate`: the hybrid time domain of an execution and the states on it."""

import html
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._core.status import STATUS_NAMES, Status
from .._core.transforms import adjoint_for, derivative_modes, warn_if_forward_mode_beneath
from .._definition.kernels import Kernels
from .._definition.system import HybridSystem
from .._engines.event_record import event_field
from . import dense as _dense


def stepping(solver, stepsize_controller) -> dict:
    """The `Solution` fields that hold a run's solver and controller (`Solution.solver`)."""
    arrays, static = eqx.partition((solver, stepsize_controller), eqx.is_array)
    return dict(stepping_arrays=arrays, stepping_static=static)


def _solve_options(dtype, solver, stepsize_controller, run=None):
    """`evaluate`'s solver and controller: those given; with neither given, the run's (`run`, a
    `Solution`) where its controller is adaptive; else (a constant step, whose size is the
    run's own, or one of the two given) Tsit5 and rtol = atol = 1e-10 (float64) or 1e-6
    (float32) for the one not given."""
    own = run is not None and solver is None and stepsize_controller is None
    if own and isinstance(run.stepsize_controller, diffrax.AbstractAdaptiveStepSizeController):
        solver, stepsize_controller = run.solver, run.stepsize_controller
    solver = diffrax.Tsit5() if solver is None else solver
    if stepsize_controller is None:
        tol = 1e-10 if dtype == jnp.float64 else 1e-6
        stepsize_controller = diffrax.PIDController(rtol=tol, atol=tol)
    return solver, stepsize_controller


class Epoch(NamedTuple):
    """One epoch T_i = [start, end] of a hybrid time domain, spent in one mode."""

    index: int
    mode: int
    mode_name: str
    start: float
    end: float

    @property
    def length(self) -> float:
        return self.end - self.start


class Solution(eqx.Module):
    """One execution (or, under `jax.vmap`, a batch of them) of a hybrid system.

    The hybrid time domain is T = [t_1, t_2] u [t_2, t_3] u ... with t_1 = `t0` and
    t_{i+1} = `event_times[i-1]`; epoch i is spent in mode `epoch_modes[i]`.

    **Padding.** Event arrays have length `max_epochs` (the most transitions recorded);
    entries past `num_events` hold `inf` (times and states) or `-1` (indices). Padding is
    constant, so it never carries a gradient. States are padded to the system's largest
    dimension; mode I's state is the first n_I components.

    **Contents** (the event arrays, `event_times` ... `inside_guard`, are read-only properties,
    read off the event record; see below):

    - `event_times` (E,): t_2, t_3, ... the times at which transitions fired.
    - `num_events`: the number of transitions taken.
    - `epoch_modes` (E+1,): the mode index of each epoch (`-1` past the last).
    - `transitions` (E,): the index (in `system.transitions`) of each transition taken; an
      index K + c (K transitions) marks a jump through `system.completions[c]`.
    - `states_before`, `states_after` (E, n): x(t_i^-) and x(t_i^+) at each event.
    - `simultaneous` (E,): True where another guard was reached at the same instant (within
      the event tolerance) and lost on priority.
    - `grazing` (E,): True where the flow met the guard nearly tangentially,
      |dg/dt| <= eps^(1/3) (|D_t g| + |D_x g| |F|) (6e-6 in float64): the event time's derivative
      -(dg/dtheta) / (dg/dt) is ill-conditioned there (infinite at exact tangency, where
      hybridjax divides by 1 instead of 0, so this flag is the warning to read).
    - `inside_guard` (E,): True where the transition fired at the start of an epoch because
      the state lay strictly inside its guard (g < -band, beyond the tolerance band): a reset,
      or the initial state, put it there, and the flow never crossed the guard. A chain of
      such zero-length epochs is legitimate where resets are meant to chain (a plastic impact
      landing inside the lift-off guard) and otherwise marks a modelling mistake, e.g. a
      hopper whose apex lies below its touchdown height; the repr counts these events.
    - `final_time`, `final_mode`, `final_state`: where the execution stopped.
    - `zeno_time`, `zeno_state`: the extrapolated accumulation time and limit state of a Zeno
      execution (`inf` otherwise), whether it stopped with `ZENO` or was completed.
    - `status`: an `hj.Status`; everything before the stop is kept. It is also the status's
      integer code: `int(sol.status)` for one execution, `np.asarray(sol.status)` for a batch,
      `==` with `hj.Status` members and with integer codes (see `Status`).
    - `ts`, `ys`, `saved_modes`: the requested save times, the state there and its mode
      (`inf` / `-1` for times the execution did not reach). At an event time the saved
      state is the pre-event one.
    - `num_steps`, `num_rejected`: solver steps attempted and rejected.
    - `t0`, `x0`, `mode0`, `args`, `system`: the problem, kept for `evaluate`.

    The event arrays are read, where they are asked for, off the event record the engines
    write, kept in three arrays by dtype (`events_real`: each event's time and states
    side by side; `events_index`: its transition and the mode of the epoch it starts;
    `events_flag`: its three flags; `max_epochs + 1` slots, the last a scratch slot that the
    event arrays leave out): a program that returns a `Solution` does not copy the
    record into eight arrays, and inside `jax.jit` an event array that is not read is not
    computed. They are properties, so `eqx.tree_at` reaches them through these three (and
    `epoch_modes[0]` through `mode0`); a transformation of the leaves must keep the batch
    axes leading (the record's last two axes are events and values).
    """

    # The event record as the engines write it, by dtype (`_engines.event_record`); the event
    # arrays above are read off it (`event_times` ... `inside_guard`, properties).
    # E + 1 slots each: the last is scratch, where the batched engine writes events not kept.
    events_real: Float[Array, "*batch epochs_plus_one two_dim_plus_one"]  # time, x(t_i^-), x(t_i^+)
    events_index: Int[Array, "*batch epochs_plus_one 2"]  # transition, the mode of the epoch it starts
    events_flag: Bool[Array, "*batch epochs_plus_one 3"]  # simultaneous, grazing, inside the guard
    num_events: Int[Array, "*batch"]
    zeno_time: Float[Array, "*batch"]
    zeno_state: Float[Array, "*batch dim"]
    final_time: Float[Array, "*batch"]
    final_mode: Int[Array, "*batch"]
    final_state: Float[Array, "*batch dim"]
    status: Status
    ts: Float[Array, "*batch saves"]
    ys: Float[Array, "*batch saves dim"]
    saved_modes: Int[Array, "*batch saves"]
    num_steps: Int[Array, "*batch"]
    num_rejected: Int[Array, "*batch"]
    t0: Float[Array, "*batch"]
    x0: Float[Array, "*batch dim"]
    mode0: Int[Array, "*batch"]
    args: Any
    system: HybridSystem = eqx.field(static=True)
    # The run's solver and step-size controller (`evaluate` integrates with them), split as
    # `eqx.partition` splits them: their arrays here (batched like the other fields), the rest
    # static (a solver's settings, a controller's Python-number tolerances and norm function).
    stepping_arrays: Any = None
    stepping_static: Any = eqx.field(static=True, default=None)

    def _event(self, name: str):
        record = (self.events_real, self.events_index, self.events_flag, self.mode0)
        if np.shape(record[1])[-1:] != (2,) or np.shape(record[2])[-1:] != (3,):
            raise ValueError(
                f"Solution.{name}: the event record's last two axes are not (events, values) "
                f"(events_index {np.shape(record[1])}, events_flag {np.shape(record[2])}): a batch "
                "axis was moved behind them, e.g. by jax.vmap(..., out_axes=-1). Keep batch axes "
                "leading (out_axes=0) and move the axes of the event array itself.")
        if any(isinstance(a, jax.ShapeDtypeStruct) for a in record):  # a solution from `jax.eval_shape`
            return jax.eval_shape(lambda *r: event_field(name, *r), *record)
        return event_field(name, *record)

    @property
    def event_times(self) -> Float[Array, "*batch epochs"]:
        """t_2, t_3, ... the times at which transitions fired (`inf` past `num_events`)."""
        return self._event("event_times")

    @property
    def epoch_modes(self) -> Int[Array, "*batch epochs_plus_one"]:
        """The mode index of each epoch (`-1` past the last)."""
        return self._event("epoch_modes")

    @property
    def transitions(self) -> Int[Array, "*batch epochs"]:
        """The index of each transition taken (K + c: a jump through `system.completions[c]`)."""
        return self._event("transitions")

    @property
    def states_before(self) -> Float[Array, "*batch epochs dim"]:
        """x(t_i^-) at each event."""
        return self._event("states_before")

    @property
    def states_after(self) -> Float[Array, "*batch epochs dim"]:
        """x(t_i^+) at each event."""
        return self._event("states_after")

    @property
    def simultaneous(self) -> Bool[Array, "*batch epochs"]:
        """True where another guard was reached at the same instant and lost on priority."""
        return self._event("simultaneous")

    @property
    def grazing(self) -> Bool[Array, "*batch epochs"]:
        """True where the flow met the guard nearly tangentially (see the class docstring)."""
        return self._event("grazing")

    @property
    def inside_guard(self) -> Bool[Array, "*batch epochs"]:
        """True where the transition fired at an epoch's start from strictly inside its guard."""
        return self._event("inside_guard")

    @property
    def solver(self) -> diffrax.AbstractSolver | None:
        """The diffrax solver of the run (None where the solution was built without one)."""
        return None if self.stepping_static is None else eqx.combine(self.stepping_arrays,
                                                                     self.stepping_static)[0]

    @property
    def stepsize_controller(self) -> diffrax.AbstractStepSizeController | None:
        """The run's step-size controller, its default filled in (None where not recorded)."""
        return None if self.stepping_static is None else eqx.combine(self.stepping_arrays,
                                                                     self.stepping_static)[1]

    # ------------------------------------------------------------------ reading
    @property
    def status_code(self) -> Int[Array, "*batch"]:
        """The status as an integer array (index into `hj.STATUS_NAMES`); traced inside `jax.jit`,
        where `int(sol.status)` and `np.asarray(sol.status)` need concrete values."""
        return self.status._value

    @property
    def status_name(self):
        """The status name (a str, or a numpy array of str for a batch)."""
        names = np.asarray(STATUS_NAMES)[np.asarray(self.status._value)]
        return str(names) if names.ndim == 0 else names

    def _check_single(self, what: str) -> None:
        if np.ndim(self.num_events) != 0:
            raise ValueError(
                f"`{what}` works on one execution; index the batch first, e.g. "
                "`jax.tree_util.tree_map(lambda a: a[i], sol)` or `sol[i]`."
            )

    def __getitem__(self, i) -> "Solution":
        """Execution i of a batched solution (numpy-style index into the batch axes)."""
        return jax.tree_util.tree_map(lambda a: a[i], self)

    def hybrid_time_domain(self) -> list[Epoch]:
        """The epochs [t_i, t_{i+1}] with their modes, as a list (one execution only).

        Zero-length epochs (a reset into another guard) appear with start == end.
        """
        self._check_single("hybrid_time_domain")
        n = int(self.num_events)
        starts = [float(self.t0)] + [float(x) for x in np.asarray(self.event_times)[:n]]
        ends = starts[1:] + [float(self.final_time)]
        modes = np.asarray(self.epoch_modes)[: n + 1]
        names = self.system.mode_names
        return [
            Epoch(i, int(m), names[int(m)], s, e)
            for i, (m, s, e) in enumerate(zip(modes, starts, ends, strict=True))
        ]

    def evaluate(
        self,
        t,
        *,
        solver: diffrax.AbstractSolver | None = None,
        stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    ) -> tuple[Float[Array, "*times dim"], Int[Array, "*times"]]:
        """The state x(t) and mode at time t of one execution (dense output).

        Finds the epoch containing t (right-continuous: at an event time the post-event
        state x(t_i^+) of the last transition at that instant, unlike `saveat`, which keeps the
        pre-event state), and integrates that epoch's flow from its initial state x(t_i^+) to t
        with diffrax: with the run's own solver and step-size controller (`sol.solver`,
        `sol.stepsize_controller`), so to the run's tolerance; with `solver` /
        `stepsize_controller` where given, or where the run's controller has no error estimate
        (a constant step): the one not given Tsit5, rtol = atol = 1e-10 (float64) or 1e-6
        (float32). Times outside [t0, final_time], and
        times inside the accumulating tail of a completed Zeno execution (the epoch that ends
        in a `ZenoCompletion` jump, which stands for infinitely many unsimulated bounces),
        return `inf` and mode -1. Differentiable (in `t` too), in forward and reverse mode
        (forward mode where the JVP is taken outside any `jax.jit` around the call, as for
        `simulate`: a JVP of a jitted `evaluate` warns).

        **Many times.** `t` may be a 1-D array of N times (any order): the result is the states
        (N, n) and modes (N,), computed in one pass over the epochs, integrating each epoch's
        flow once through the query times inside it (saved with `diffrax.SaveAt(ts=...)`), so
        hundreds of times cost about one simulation. The compiled program is shared by all
        epochs and modes and reused by later calls with other times. Under a JAX transform
        (`jax.jit`, `jax.grad`: a traced solution or traced times) the array form
        re-integrates per time, as `jax.vmap(sol.evaluate)` does, and stays differentiable.

        ```python
        sol = hj.simulate(ball, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, {"g": 9.8, "e": 0.8})
        x, mode = sol.evaluate(0.3)                       # (2,), ()
        xs, modes = sol.evaluate(jnp.linspace(0, 3, 400))  # (400, 2), (400,)
        ```
        """
        self._check_single("evaluate")
        if np.ndim(t) == 1:
            if _dense.is_concrete(t, self):
                solver, stepsize_controller = _solve_options(self.final_time.dtype, solver,
                                                             stepsize_controller, self)
                return _dense.evaluate_many(self, t, solver, stepsize_controller)
            one = lambda s: self.evaluate(s, solver=solver,  # noqa: E731
                                          stepsize_controller=stepsize_controller)
            return jax.vmap(one)(jnp.asarray(t))
        if np.ndim(t) != 0:
            raise ValueError(f"`evaluate` takes a scalar time or a 1-D array of times; got `t` "
                             f"of shape {np.shape(t)}.")
        t = jnp.asarray(t, self.final_time.dtype)
        i = jnp.sum(self.event_times <= t).astype(jnp.int32)
        i = jnp.minimum(i, self.num_events)
        start_t = jnp.where(i == 0, self.t0, self.event_times[jnp.maximum(i - 1, 0)])
        start_x = jnp.where(i == 0, self.x0, self.states_after[jnp.maximum(i - 1, 0)])
        mode = self.epoch_modes[i]
        kern = Kernels(self.system, self.args, start_x.dtype)
        term = diffrax.ODETerm(lambda tt, y, a: kern.flow(mode, tt, y, a))
        solver, stepsize_controller = _solve_options(start_x.dtype, solver, stepsize_controller, self)
        # The epoch that ends in a Zeno completion stands for infinitely many epochs that were
        # not simulated (the accumulating tail); re-integrating its flow would not be the execution.
        tail = (i < self.num_events) & (self.transitions[i] >= self.system.num_transitions)
        inside = (t >= self.t0) & (t <= self.final_time) & ~tail
        t_end = jnp.where(inside, jnp.maximum(t, start_t), start_t)
        same = t_end == start_t
        adjoint = adjoint_for(diffrax.RecursiveCheckpointAdjoint(), derivative_modes())
        warn_if_forward_mode_beneath(adjoint, "Solution.evaluate")
        sol = diffrax.diffeqsolve(
            term, solver, start_t, jnp.where(same, start_t + 1, t_end), None, start_x,
            args=self.args, saveat=diffrax.SaveAt(t1=True),
            stepsize_controller=stepsize_controller, max_steps=_dense.MAX_STEPS, throw=False,
            # forward mode (jax.jvp, jax.jacfwd in t) needs a loop JAX differentiates forwards
            adjoint=adjoint,
        )
        # At the epoch's start the state is start_x itself, moving with t (and against the start
        # time) as the integration's state does elsewhere, to second order: x + F m + F' m^2 / 2,
        # F' = dF/dt along the flow, m = (t - t) - (t_i - t_i) of value zero (a t outside the
        # run counts as t_i, so that no NaN reaches a derivative through the masked branch).
        sg = jax.lax.stop_gradient
        t_at = jnp.where(inside, t, start_t)
        moved = (t_at - sg(t_at)) - (start_t - sg(start_t))
        field = lambda tt, xx: kern.flow(mode, tt, xx, self.args)  # noqa: E731
        F = field(start_t, start_x)
        F_dot = jax.jvp(field, (start_t, start_x), (jnp.ones_like(start_t), F))[1]
        F, F_dot = (jnp.where(jnp.isfinite(v), v, 0.0) for v in (F, F_dot))
        at_start = start_x + moved * (F + 0.5 * moved * F_dot)
        x = jnp.where(same, at_start, sol.ys[-1])
        return jnp.where(inside, x, jnp.inf), jnp.where(inside, mode, -1)

    def _repr_html_(self) -> str:
        esc = html.escape
        if np.ndim(self.num_events) != 0:
            codes = np.asarray(self.status._value).ravel()
            counts = np.bincount(codes, minlength=len(STATUS_NAMES))
            rows = "".join(
                f"<tr><td>{name}</td><td>{c}</td><td>{c / codes.size:.4f}</td></tr>"
                for name, c in zip(STATUS_NAMES, counts, strict=True) if c
            )
            inside = self.inside_guard_count()
            note = (f"; {inside} executions with events fired from inside a guard (`inside_guard`)"
                    if inside else "")
            return (f"<div><b>Solution</b>: batch {np.shape(self.num_events)}, mean events "
                    f"{float(np.mean(self.num_events)):.2f}{note}<table><tr><th>status</th><th>count</th>"
                    f"<th>fraction</th></tr>{rows}</table></div>")
        sys_ = self.system
        n = int(self.num_events)
        labels = [tr.label for tr in sys_.transitions] + [c.label for c in sys_.completions]
        # Each event array read once, as NumPy (each property reads it off the record anew).
        times, tr, modes, sim, graz, inside = (np.asarray(a) for a in (
            self.event_times, self.transitions, self.epoch_modes, self.simultaneous, self.grazing,
            self.inside_guard))
        rows = "".join(
            f"<tr><td>{i}</td><td>{float(times[i]):.10g}</td>"
            f"<td>{esc(labels[int(tr[i])])}</td>"
            f"<td>{esc(sys_.mode_names[int(modes[i])])} &rarr; "
            f"{esc(sys_.mode_names[int(modes[i + 1])])}</td>"
            f"<td>{'simultaneous ' if bool(sim[i]) else ''}"
            f"{'grazing ' if bool(graz[i]) else ''}"
            f"{'inside guard' if bool(inside[i]) else ''}</td></tr>"
            for i in range(n)
        )
        return (f"<div><b>Solution</b>: {self.status_name}, {n} events, final time "
                f"{float(self.final_time):.10g} in mode '{esc(sys_.mode_names[int(self.final_mode)])}'"
                "<table><tr><th>event</th><th>time</th><th>transition</th><th>modes</th>"
                f"<th>flags</th></tr>{rows}</table></div>")

    def __repr__(self) -> str:
        if np.ndim(self.num_events) != 0:
            shape = np.shape(self.num_events)
            codes, counts = np.unique(np.asarray(self.status._value), return_counts=True)
            tally = ", ".join(f"{STATUS_NAMES[c]}: {k}" for c, k in zip(codes, counts, strict=True))
            inside = self.inside_guard_count()
            note = f"; {inside} with events fired from inside a guard (inside_guard)" if inside else ""
            return f"Solution(batch {shape}; {tally}{note})"
        inside = self.inside_guard_count()
        note = f", inside_guard={inside} events" if inside else ""
        mode = self.system.modes[int(self.final_mode)]
        state = ", ".join(f"{name}={float(v):.6g}" for name, v in
                          zip(mode.component_names, np.asarray(self.final_state)[: mode.dim], strict=True))
        return (
            f"Solution(status={self.status_name}, num_events={int(self.num_events)}, "
            f"final_time={float(self.final_time):.6g}, final_mode='{mode.name}', "
            f"final_state=({state}){note})"
        )

    def inside_guard_count(self) -> int:
        """Events fired from strictly inside a guard (`inside_guard`) for one execution; for a
        batch, the executions with at least one."""
        flags = np.asarray(self.inside_guard)
        if flags.ndim == 1:
            return int(flags.sum())
        return int(flags.reshape(-1, flags.shape[-1]).any(axis=-1).sum())
