"""`simulate`: run one execution of a hybrid system (vmap it for many)."""

import warnings
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from diffrax._root_finder import use_stepsize_tol  # private: as diffeqsolve, fill implicit tols
from diffrax._saveat import save_y as _save_y  # private: to refuse SaveAt(fn=...) we ignore
from jaxtyping import ArrayLike, Float, Int

from .._core.status import Status
from .._core.transforms import (
    adjoint_for,
    derivative_modes,
    naming_the_forward_mode_fix,
    warn_if_forward_mode_beneath,
)
from .._definition.system import HybridSystem, as_mode_index
from .._definition.validation import as_state_array, check_time_span
from .._engines.loop import Loop
from .._rules.zeno import ZenoOptions, zeno_options
from .._solution.solution import Solution
from .._solve.eager import compiled_when_eager
from .._step.runge_kutta import FastIController, UnrolledERK, can_unroll, can_use_fast_controller


def _loop_kind(adjoint) -> tuple[str, int | None]:
    if isinstance(adjoint, diffrax.RecursiveCheckpointAdjoint):
        return "checkpointed", adjoint.checkpoints
    if isinstance(adjoint, diffrax.ForwardMode):
        return "lax", None
    if isinstance(adjoint, diffrax.DirectAdjoint):
        return "bounded", None
    raise TypeError(
        f"adjoint={adjoint!r} is not supported: use diffrax.RecursiveCheckpointAdjoint() "
        "(reverse mode, the default), diffrax.ForwardMode() (forward mode: jax.jvp, "
        "jax.jacfwd) or diffrax.DirectAdjoint() (both, at a higher cost)."
    )


def _save_times(saveat, t0, t1, dtype) -> jax.Array:
    if saveat is None:
        return jnp.zeros((0,), dtype)
    if isinstance(saveat, diffrax.SaveAt):
        sub = saveat.subs
        if not isinstance(sub, diffrax.SubSaveAt) or sub.steps or sub.fn is not _save_y:
            raise ValueError("saveat: only diffrax.SaveAt(t0=..., t1=..., ts=...) is supported.")
        parts = []
        if sub.t0:
            parts.append(jnp.reshape(t0, (1,)))
        if sub.ts is not None:
            parts.append(jnp.asarray(sub.ts, dtype).reshape(-1))
        if sub.t1:
            parts.append(jnp.reshape(t1, (1,)))
        return jnp.concatenate(parts).astype(dtype) if parts else jnp.zeros((0,), dtype)
    ts = jnp.asarray(saveat, dtype)
    if ts.ndim != 1:
        raise ValueError(f"saveat: expected a 1-D array of times, got shape {ts.shape}.")
    return ts


def _prepare_solver(solver, controller, kind: str):
    """What `diffrax.diffeqsolve` does to a solver before stepping it, done here as well.

    - the RK stage loop must not be a custom_vjp under forward mode (as diffrax's
      `ForwardMode`/`DirectAdjoint` do);
    - an implicit solver's root finder takes the controller's rtol/atol/norm where it was
      left at diffrax's `use_stepsize_tol`.
    """
    if (
        kind != "checkpointed"
        and isinstance(solver, diffrax.AbstractRungeKutta)
        and solver.scan_kind is None
    ):
        solver = eqx.tree_at(lambda s: s.scan_kind, solver, kind, is_leaf=lambda x: x is None)
    if isinstance(solver, diffrax.AbstractImplicitSolver):
        attrs = [a for a in ("rtol", "atol", "norm")
                 if getattr(solver.root_finder, a) is use_stepsize_tol]
        if attrs:
            if not isinstance(controller, diffrax.AbstractAdaptiveStepSizeController):
                raise ValueError(
                    f"{type(solver).__name__} with a fixed step size needs explicit root-finder "
                    "tolerances, e.g. root_finder=diffrax.VeryChord(rtol=..., atol=..., "
                    "norm=optimistix.max_norm); or use an adaptive controller."
                )
            solver = eqx.tree_at(
                lambda s: tuple(getattr(s.root_finder, a) for a in attrs),
                solver,
                tuple(getattr(controller, a) for a in attrs),
            )
    return solver


def _choose_engine(engine: str, solver, controller):
    """The solver and controller the loop steps with (see `simulate`'s `engine`)."""
    if engine not in ("auto", "fast", "diffrax"):
        raise ValueError(f"engine must be 'auto', 'fast' or 'diffrax', got {engine!r}.")
    if engine == "diffrax":
        return solver, controller
    fast_solver, fast_controller = can_unroll(solver), can_use_fast_controller(controller)
    if engine == "fast" and not (fast_solver and fast_controller):
        why = (f"solver {type(solver).__name__} is not one of Heun, Midpoint, Ralston, "
               "Bosh3, Tsit5, Dopri5, Dopri8" if not fast_solver else
               f"stepsize_controller {controller!r} is not a PIDController with default "
               "coefficients (pcoeff=0, icoeff=1, dcoeff=0), rms norm and no dtmin, dtmax, "
               "step_ts or jump_ts")
        raise ValueError(f"engine='fast': {why}; use engine='diffrax' (or 'auto').")
    if fast_solver:
        solver = UnrolledERK(solver)
    if fast_controller:
        controller = FastIController(controller)
    return solver, controller


def _default_controller(dtype) -> diffrax.PIDController:
    tol = 1e-8 if dtype == jnp.float64 else 1e-5
    return diffrax.PIDController(rtol=tol, atol=tol)


def _warn_unreachable_tolerance(controller, dtype) -> None:
    """Warn when rtol is below what `dtype` resolves: steps then shrink to rounding level,
    so the run costs many more steps (or ends with MAX_STEPS) without gaining accuracy."""
    rtol = getattr(controller, "rtol", None)
    if rtol is None:
        return
    try:
        rtol = float(np.min(np.asarray(rtol)))
    except jax.errors.TracerArrayConversionError:  # traced tolerances: nothing to check
        return
    floor = 8 * float(jnp.finfo(dtype).eps)
    if rtol < floor:
        warnings.warn(
            f"rtol={rtol:g} is below what {jnp.dtype(dtype).name} resolves "
            f"(8 eps = {floor:.1e}); the solver cannot honour it. Use rtol >= {floor:.0e}, "
            "or float64 (jax.config.update('jax_enable_x64', True) and float64 x0).",
            stacklevel=4,
        )


def _initial_state(system: HybridSystem, x0, mode0, dtype) -> jax.Array:
    x0 = jnp.asarray(x0, dtype)
    n = system.max_dim
    if x0.ndim != 1:
        raise ValueError(f"x0 must be a 1-D state vector, got shape {x0.shape}.")
    m = x0.shape[0]
    if isinstance(mode0, (str, int, np.integer)):
        mode = system.modes[system.mode_index(mode0)]
        if m not in (mode.dim, n):
            raise ValueError(
                f"x0 has {m} components but mode '{mode.name}' has dim {mode.dim}"
                + (f" (padded state: {n})." if n != mode.dim else ".")
            )
    elif m != n:
        raise ValueError(
            f"x0 has {m} components; with a traced mode0 pass the padded state of "
            f"length {n} (the largest mode dimension)."
        )
    return x0 if m == n else jnp.concatenate([x0, jnp.zeros((n - m,), dtype)])


def float_type(x0_dtype):
    """The solution's dtype: x0's float type (at least float32); for an integer or boolean x0,
    the default float type (float64 with `jax_enable_x64`)."""
    if jnp.issubdtype(x0_dtype, jnp.integer) or jnp.issubdtype(x0_dtype, jnp.bool_):
        return jnp.result_type(float)
    return jnp.result_type(x0_dtype, jnp.float32)


def promote_args(args, dtype):
    """`args` with its integer array leaves (NumPy or JAX) converted to `dtype`, so that the
    flows, guards and resets compute in the solution's float type. Booleans, floats and Python
    numbers (weakly typed: they take the type of the state they meet) are left as given."""
    def promote(leaf):
        if eqx.is_array(leaf) and jnp.issubdtype(leaf.dtype, jnp.integer):
            return jnp.asarray(leaf, dtype)
        return leaf

    return jax.tree_util.tree_map(promote, args)


def _checked_options(system, x0_arr, args, *, solver, stepsize_controller, dt0, max_epochs,
                     max_steps, event_tol, interior_points, max_zero_epochs, zeno_window,
                     zeno_max_ratio, adjoint):
    """Validate `simulate`'s options; returns (dtype, loop kind, checkpoints, solver,
    controller, event_tol) with the defaults filled in (`args` of one execution)."""
    if not isinstance(system, HybridSystem):
        raise TypeError(f"system must be a hybridjax.HybridSystem, got {type(system).__name__}.")
    for name, value, low in (
        ("max_epochs", max_epochs, 1),
        ("max_steps", max_steps, 1),
        ("interior_points", interior_points, 0),
        ("max_zero_epochs", max_zero_epochs, 0),
        ("zeno_window", zeno_window, 1),
    ):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}.")
    dtype = float_type(x0_arr.dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"x0 must be real, got dtype {x0_arr.dtype}.")
    system.check(promote_args(args, dtype), dtype)
    adjoint = adjoint_for(adjoint, derivative_modes())
    warn_if_forward_mode_beneath(adjoint, "A hybridjax simulation")
    kind, checkpoints = _loop_kind(adjoint)
    controller = _default_controller(dtype) if stepsize_controller is None else stepsize_controller
    solver = _prepare_solver(solver, controller, kind)
    if dt0 is None and not isinstance(controller, diffrax.AbstractAdaptiveStepSizeController):
        raise ValueError(f"{type(controller).__name__} needs dt0 (no error estimate to pick one).")
    if not 0 < zeno_max_ratio < 1:
        raise ValueError(f"zeno_max_ratio must be in (0, 1), got {zeno_max_ratio!r}.")
    if event_tol is None:
        event_tol = 1e-12 if dtype == jnp.float64 else 1e-6
    _warn_unreachable_tolerance(controller, dtype)
    return dtype, kind, checkpoints, solver, controller, event_tol


@compiled_when_eager(check_time_span)
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
    dt0: float | None = None,
    max_epochs: int = 64,
    max_steps: int = 4096,
    event_tol: float | None = None,
    interior_points: int = 4,
    max_zero_epochs: int = 16,
    zeno: bool | ZenoOptions = True,
    zeno_window: int = 3,
    zeno_ratio_tol: float = 0.05,
    zeno_max_ratio: float = 0.99,
    adjoint: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint(),
    engine: str = "auto",
    throw: bool = False,
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
    compiles a new program: pass a parameter you vary as an array (`jnp.asarray(0.8)`). Inside
    `jax.jit` the call is traced with its caller, as any JAX function.

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
      atol=1e-8)` in float64, `1e-5` in float32.
    - `saveat`: times to save the state at: a 1-D array or `diffrax.SaveAt(ts=..., t0=...,
      t1=...)`.
    - `dt0`: first step size of every epoch; default: from the tolerances (Hairer's rule) for
      the first epoch and, with an explicit Runge-Kutta solver, the step-size controller's
      last proposal for the later ones (implicit solvers: Hairer's rule for every epoch);
      capped so that a departing guard is seen positive before it can return.
    - `max_epochs`: the most transitions recorded; one more ends with `MAX_EPOCHS`.
    - `max_steps`: the most solver steps (accepted and rejected, all epochs together);
      more ends with `MAX_STEPS`.
    - `event_tol`: event-time tolerance relative to the step in which the event lies
      (floored at 8 ulp of t): the root bracket is narrowed below `event_tol * h`.
      Default 1e-12 (float64), 1e-6 (float32).
    - `interior_points`: guards are also checked at this many interior points of each step's
      dense output, to catch a guard entered and left within one step; between samples, a
      local minimum of a guard that may reach zero is searched for on the dense output, so
      near-grazing crossings (down to rounding level) are found too.
    - `max_zero_epochs`: more zero-length epochs in a row end with `CHATTERING`.
    - `zeno`, `zeno_window`, `zeno_ratio_tol`, `zeno_max_ratio`: Zeno detection (`zeno` may
      also be a `ZenoOptions`, which holds the other three; `zeno=False` switches it off). After each
      event, if the last `zeno_window` ratios r = |T_{i+1}| / |T_i| of consecutive epoch
      lengths lie in (0, zeno_max_ratio] and agree with the latest to `zeno_ratio_tol`
      (relative), and the extrapolated accumulation time t_inf = t_n + |T_n| r / (1 - r) is
      <= t1, the execution stops with `ZENO` (`sol.zeno_time`, `sol.zeno_state`), or jumps to
      the limit through the mode's `ZenoCompletion` and continues.
    - `adjoint`: `diffrax.RecursiveCheckpointAdjoint()` (reverse mode; replaced by
      `ForwardMode()` under `jax.jvp`/`jax.jacfwd` alone), `ForwardMode()` (forward mode) or
      `DirectAdjoint()` (both): selects the kind of while loop.
    - `engine`: how each step is computed. `"diffrax"`: diffrax's own `solver.step` and
      `stepsize_controller.adapt_step_size`. `"fast"`: the same step from the solver's Butcher
      tableau with the stages unrolled, and the same I-controller rule written out (requires
      one of Heun, Midpoint, Ralston, Bosh3, Tsit5, Dopri5, Dopri8 and a
      `PIDController` with default coefficients and no dtmin/dtmax/step_ts/jump_ts); the
      same steps to rounding, faster under `vmap` (the docs' Work-precision page).
      `"auto"` (default): `"fast"` where it applies, `"diffrax"` otherwise.
    - `throw`: raise (via `eqx.error_if`) if the status is not `T1_REACHED`.

    !!! Example

        ```python
        import hybridjax as hj, jax.numpy as jnp
        ball = hj.examples.bouncing_ball()
        sol = hj.simulate(ball, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0,
                          args={"g": 9.8, "e": 0.8})
        sol.event_times[:3]   # impacts at sqrt(2 h0 / g) (1 + 2 e + 2 e^2 + ...)
        ```
    """
    x0_arr = as_state_array(x0, "simulate")
    dtype, kind, checkpoints, solver, controller, event_tol = _checked_options(
        system, x0_arr, args, solver=solver, stepsize_controller=stepsize_controller, dt0=dt0,
        max_epochs=max_epochs, max_steps=max_steps, event_tol=event_tol,
        interior_points=interior_points, max_zero_epochs=max_zero_epochs, zeno_window=zeno_window,
        zeno_max_ratio=zeno_max_ratio, adjoint=adjoint)
    solver, controller = _choose_engine(engine, solver, controller)
    args = promote_args(args, dtype)

    y0 = _initial_state(system, x0_arr, mode0, dtype)
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
        dt0=dt0,
        save_ts=_save_times(saveat, t0, t1, dtype),
        max_epochs=int(max_epochs),
        max_steps=int(max_steps),
        interior_points=int(interior_points),
        event_tol=event_tol,
        max_zero_epochs=int(max_zero_epochs),
        zeno=zeno_options(zeno, zeno_window, zeno_ratio_tol, zeno_max_ratio),
        loop_kind=kind,
        checkpoints=checkpoints,
        dtype=dtype,
    )
    with naming_the_forward_mode_fix():
        st, rec = loop.run(t0, y0, m0)
    final_time = st.t
    status = Status.where(t1_before_t0, Status.T1_BEFORE_T0, st.status)
    if throw:
        final_time = status.error_if(final_time, status != Status.T1_REACHED)
    return Solution(
        event_times=rec.event_times,
        num_events=st.num_events,
        epoch_modes=rec.epoch_modes,
        transitions=rec.transitions,
        states_before=rec.states_before,
        states_after=rec.states_after,
        simultaneous=rec.simultaneous,
        grazing=rec.grazing,
        inside_guard=rec.inside_guard,
        zeno_time=st.zeno_time,
        zeno_state=st.zeno_state,
        final_time=final_time,
        final_mode=st.mode,
        final_state=st.y,
        status=status,
        ts=loop.save_ts,
        ys=rec.ys,
        saved_modes=rec.saved_modes,
        num_steps=st.num_steps,
        num_rejected=st.num_rejected,
        t0=t0,
        x0=y0,
        mode0=m0,
        args=args,
        system=system,
    )

