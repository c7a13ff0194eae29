"""`simulate`: run one execution of a hybrid system (vmap it for many)."""

from typing import Any

import diffrax
import jax.numpy as jnp
from jaxtyping import ArrayLike, Float, Int

from .._core.status import Status
from .._core.transforms import naming_the_forward_mode_fix
from .._definition.system import HybridSystem, as_mode_index
from .._definition.validation import as_state_array, check_time_span
from .._engines.event_record import event_rows, with_scratch
from .._engines.loop import Loop
from .._rules.options import SolveOptions
from .._solution.solution import Solution, stepping
from .._step.runge_kutta import split_clip
from .eager import compiled_when_eager
from .end_time import at_t1_from_epoch_start
from .engines import AbstractEngine, as_engine, step_engine
from .prepare import initial_state, prepare, promote_args, save_times, solve_options


@compiled_when_eager(check_time_span, one_execution=True)
def simulate(
    system: HybridSystem,
    x0: Float[ArrayLike, " dim"],
    mode0: str | int | Int[ArrayLike, ""],
    t0: Float[ArrayLike, ""],
    t1: Float[ArrayLike, ""],
    args: Any = None,
    *,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    saveat: diffrax.SaveAt | Float[ArrayLike, " saves"] | None = None,
    adjoint: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint(),
    engine: AbstractEngine | str = "auto",
    options: SolveOptions | None = None,
    **shorthands,
) -> Solution:
    r"""Simulate one execution of `system` from `(x0, mode0)` at `t0` until `t1` or a stop.

    Within an epoch in mode I the state follows dx/dt = F_I(t, x) (one diffrax integration);
    transition (I, J) fires when g_IJ crosses from > 0 to <= 0, at the time t* found on the
    solver's dense output, and the state jumps to x(t*^+) = R_IJ(t*, x(t*^-)). At the start
    of an epoch a transition fires at once (a zero-length epoch) if the state is already in
    its guard: g < -band, or |g| <= band and g trending negative (first non-zero Lie
    derivative along F_I negative). Guards reached at the same instant fire in listing
    order. See `Solution` for what comes back.

    Pure in its array arguments: `jax.jit`, `jax.vmap` over `x0`, `mode0`, `args`, `t0`,
    `t1`; `jax.grad`/`jax.jacrev` (reverse mode) and `jax.jvp`/`jax.jacfwd` (forward mode)
    with respect to `x0`, `args`, `t0`, `t1`. Forward mode runs with
    `adjoint=diffrax.ForwardMode()`, which the call chooses itself in place of the default
    (reverse-mode) adjoint where it sees the `jax.jvp` (the JVP taken at or inside the call's
    `jax.jit`); a `jax.jvp` taken outside a `jax.jit` made around the call cannot be seen from
    it: pass `adjoint=diffrax.ForwardMode()` there (a warning says so).

    Called outside `jax.jit` (as in a notebook), also under `jax.grad`, `jax.jvp`,
    `jax.jacfwd`, `jax.jacrev`, `jax.vmap` and their compositions, the call is compiled once
    and the program kept (`eqx.filter_jit`, which JAX differentiates and batches): a later call
    with arrays of the same shapes and dtypes, equal other arguments and the same
    transformations runs it at once, so a loop of `jax.grad` steps compiles once. Python numbers
    (in `args`, `t0`, `t1`, the options) are constants of the program, so a changed one
    compiles a new program: pass a parameter you vary as an array (`jnp.asarray(0.8)`). On the
    CPU, such a call without `jax.vmap` or reverse mode compiles with XLA:CPU's own fusion
    emitters (`compiler_options={"xla_cpu_use_fusion_emitters": False}`), in about half the XLA
    time, running as fast; under `jax.vmap`, without reverse mode, with wider vectors
    (`{"xla_cpu_prefer_vector_width": 512}`; faster for a batch); either with fewer copies of
    the arrays its loops carry (`{"xla_cpu_copy_insertion_use_region_analysis": True}`; FAQ,
    "Compile time"). Inside `jax.jit` the call is traced with its caller, as any JAX function,
    and compiled with the caller's options.

    **Arguments:**

    - `system`: the `HybridSystem`.
    - `x0`: the initial state, of `mode0`'s dimension (or padded to the largest dimension,
      which is required when `mode0` is traced, e.g. under `vmap`). Its float type is the
      solution's (float32 or float64); an integer `x0` (`jnp.array([1, 0])`) is promoted to the
      default float type, float64 with `jax.config.update("jax_enable_x64", True)`.
    - `mode0`: initial mode, by name or index.
    - `t0`, `t1`: the time interval, t1 >= t0: checked at the call (`ValueError`) where both
      are known, inside the run (`eqx.error_if`) where either is traced.
    - `args`: any pytree passed to every flow, guard, reset and domain. Its integer array
      leaves are converted to the solution's float type (Python numbers are left as given:
      they take the float type of the state they meet); `sol.args` holds them so converted.
    - `solver`: a diffrax solver (default `Tsit5()`); implicit ones (`Kvaerno5()`) work.
    - `stepsize_controller`: a diffrax controller; default `PIDController(rtol=1e-8,
      atol=1e-8)` in float64, `1e-5` in float32. `PIDController(step_ts=..., jump_ts=...)`
      as in diffrax: a step ends at each step time; at a jump time (a discontinuity of the
      flow in t) a step ends just before it and the next starts just after it, the flow
      evaluated anew.
    - `saveat`: times to save the state at: a 1-D array or `diffrax.SaveAt(ts=..., t0=...,
      t1=...)`.
    - `adjoint`: `diffrax.RecursiveCheckpointAdjoint()` (reverse mode; replaced by
      `ForwardMode()` under `jax.jvp`/`jax.jacfwd` alone), `ForwardMode()` (forward mode) or
      `DirectAdjoint()` (both): selects the kind of while loop.
    - `engine`: how each step is computed: `hj.AutoEngine()` (default, shorthand `"auto"`):
      `hj.FastEngine()` where the solver and controller allow it, `hj.DiffraxEngine()`
      otherwise. `hj.DiffraxEngine()` (`"diffrax"`): diffrax's own `solver.step` and
      `stepsize_controller.adapt_step_size`. `hj.FastEngine()` (`"fast"`): the same step
      from the solver's Butcher tableau with the stages unrolled, and the same I-controller
      rule written out (requires the tableau of Heun, Midpoint, Ralston, Bosh3, Tsit5,
      Dopri5 or Dopri8, a subclass of one of them included, and a `PIDController` with
      default coefficients and no dtmin/dtmax); the same steps to rounding, faster under
      `vmap` (the docs' Work-precision page).
    - `options`: an `hj.SolveOptions`: the record's length (`max_epochs`), the step budget
      (`max_steps`), `dt0`, `max_zero_epochs`, event location (`hj.EventOptions`), Zeno
      detection (`hj.ZenoOptions`) and `throw`. Default: `hj.SolveOptions()`.

    **Keyword shorthands** for the fields of `options` (pass these or `options`, not both):

    - `max_epochs` (64): the most transitions recorded; one more ends with `MAX_EPOCHS`.
    - `max_steps` (4096): the most solver steps (accepted and rejected, all epochs
      together); more end with `MAX_STEPS`.
    - `dt0` (None): first step size of every epoch; default: from the tolerances (Hairer's
      rule) for the first epoch and, with an explicit Runge-Kutta solver, the step-size
      controller's last proposal for the later ones (implicit solvers: Hairer's rule for every
      epoch); capped so that a departing guard is seen positive before it can return.
    - `event_tol` (None), `interior_points` (4): `EventOptions(tol=..., interior_points=...)`:
      the event time is located to `event_tol` times the step in which it lies (floored at 8
      ulp of t; default 1e-12 in float64, 1e-6 in float32); guards are also checked at
      `interior_points` interior points of each step's dense output, and between samples a
      local minimum of a guard that may reach zero is searched for, so near-grazing crossings
      (down to rounding level) are found too.
    - `max_zero_epochs` (16): more zero-length epochs in a row end with `CHATTERING`.
    - `zeno` (True), `zeno_window` (3), `zeno_ratio_tol` (0.05), `zeno_max_ratio` (0.99): Zeno
      detection, `ZenoOptions(window, ratio_tol, max_ratio)` (`zeno` may be a `ZenoOptions`
      itself; `zeno=False` switches detection off). After each event, if the last
      `zeno_window` ratios r = |T_{i+1}| / |T_i| of consecutive epoch lengths lie in
      (0, zeno_max_ratio] and agree with the latest to `zeno_ratio_tol` (relative), and the
      extrapolated accumulation time t_inf = t_n + |T_n| r / (1 - r) is <= t1, the execution
      stops with `ZENO` (`sol.zeno_time`, `sol.zeno_state`), or jumps to the limit through the
      mode's `ZenoCompletion` and continues.
    - `throw` (False): raise (via `eqx.error_if`) if the status is not `T1_REACHED`.

    !!! Example

        ```python
        import hybridjax as hj, jax.numpy as jnp
        ball = hj.examples.bouncing_ball()
        sol = hj.simulate(ball, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0,
                          args={"g": 9.8, "e": 0.8})
        sol.event_times[:3]   # impacts at sqrt(2 h0 / g) (1 + 2 e + 2 e^2 + ...)
        ```
    """
    options = solve_options(options, shorthands, "simulate")
    stepper = step_engine(as_engine(engine))
    x0_arr = as_state_array(x0, "simulate")
    run = prepare(system, x0_arr, args, solver, stepsize_controller, options, adjoint)
    dtype, options = run.dtype, run.options
    # step_ts / jump_ts: `clip_to_times` in the loop, around the controller they wrap
    controller, step_ts, jump_ts = split_clip(run.controller, dtype)
    solver, controller = stepper.stepper(run.solver, controller)
    args = promote_args(args, dtype)

    y0 = initial_state(system, x0_arr, mode0, dtype)
    m0 = as_mode_index(system, mode0)
    given = (t0, t1)
    t0 = jnp.asarray(t0, dtype)
    t1 = jnp.asarray(t1, dtype)
    t1, t1_before_t0 = check_time_span(t0, t1, "simulate", given=given)
    loop = Loop(
        system,
        t1=t1,
        args=args,
        solver=solver,
        controller=controller,
        save_ts=save_times(saveat, t0, t1, dtype),
        options=options,
        loop_kind=run.kind,
        checkpoints=run.checkpoints,
        dtype=dtype,
        step_ts=step_ts,
        jump_ts=jump_ts,
    )
    with naming_the_forward_mode_fix():
        st, rec = loop.run(t0, y0, m0)
    final_time = st.t
    status = Status.where(t1_before_t0, Status.T1_BEFORE_T0, st.status)
    if options.throw:
        final_time = status.error_if(final_time, status != Status.T1_REACHED)
    final_state, ys = at_t1_from_epoch_start(loop.kern, st.y, st.mode, status, st.num_events, rec.event_times,
                                             rec.ys, loop.save_ts, t0, t1, args)
    events_real, events_index, events_flag = with_scratch(*event_rows(
        rec.event_times, rec.states_before, rec.states_after, rec.transitions, rec.epoch_modes[1:],
        rec.simultaneous, rec.grazing, rec.inside_guard, dtype))
    return Solution(
        events_real=events_real,
        events_index=events_index,
        events_flag=events_flag,
        num_events=st.num_events,
        zeno_time=st.zeno_time,
        zeno_state=st.zeno_state,
        final_time=final_time,
        final_mode=st.mode,
        final_state=final_state,
        status=status,
        ts=loop.save_ts,
        ys=ys,
        saved_modes=rec.saved_modes,
        num_steps=st.num_steps,
        num_rejected=st.num_rejected,
        t0=t0,
        x0=y0,
        mode0=m0,
        args=args,
        system=system,
        **stepping(run.solver, run.controller),
    )

