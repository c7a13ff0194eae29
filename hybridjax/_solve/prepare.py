"""What `simulate` and `simulate_batch` share before their loops run: the options built from
`options=` or the keyword shorthands (`solve_options`, the one place the shorthands are listed),
checked and completed for the run's dtype (`prepare`), the initial state, the save times and the
promotion of `args`."""

import warnings
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from diffrax._root_finder import use_stepsize_tol  # private: as diffeqsolve, fill implicit tols
from diffrax._saveat import save_y as _save_y  # private: to refuse SaveAt(fn=...) we ignore

from .._core.transforms import adjoint_for, derivative_modes, warn_if_forward_mode_beneath
from .._definition.system import AbstractHybridSystem, HybridSystem
from .._rules.options import EventOptions, SolveOptions
from .._rules.zeno import DEFAULT_MAX_RATIO, DEFAULT_RATIO_TOL, DEFAULT_WINDOW, zeno_options

# The keyword shorthands of `simulate` and `simulate_batch` for the fields of `SolveOptions`
# (and its `EventOptions`, `ZenoOptions`), with their defaults.
SHORTHANDS: dict[str, Any] = dict(
    dt0=None, max_epochs=64, max_steps=4096, max_zero_epochs=16, event_tol=None, interior_points=4,
    zeno=True, zeno_window=DEFAULT_WINDOW, zeno_ratio_tol=DEFAULT_RATIO_TOL, zeno_max_ratio=DEFAULT_MAX_RATIO,
    throw=False,
)


def solve_options(options: SolveOptions | None, shorthands: dict[str, Any], where: str) -> SolveOptions:
    """The run's `SolveOptions`: `options` itself, or built from the keyword shorthands (the
    others at their defaults; a shorthand given as None counts as not given). Both at once is a
    `ValueError`; an unknown keyword a `TypeError` naming it."""
    shorthands = {name: value for name, value in shorthands.items() if value is not None}
    unknown = sorted(set(shorthands) - set(SHORTHANDS))
    if unknown:
        raise TypeError(f"{where}() got an unexpected keyword argument {unknown[0]!r}.")
    if options is not None:
        if not isinstance(options, SolveOptions):
            raise TypeError(f"{where}: options must be an hj.SolveOptions, got {type(options).__name__}.")
        if shorthands:
            raise ValueError(f"{where}: options=hj.SolveOptions(...) holds the run's settings: pass "
                             f"{', '.join(sorted(shorthands))} there, not beside it.")
        return options
    o = {**SHORTHANDS, **shorthands}
    window = o["zeno_window"]
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1:
        raise ValueError(f"zeno_window must be an int >= 1, got {window!r}.")
    if not 0 < o["zeno_max_ratio"] < 1:
        raise ValueError(f"zeno_max_ratio must be in (0, 1), got {o['zeno_max_ratio']!r}.")
    return SolveOptions(
        dt0=o["dt0"],
        max_epochs=o["max_epochs"],
        max_steps=o["max_steps"],
        max_zero_epochs=o["max_zero_epochs"],
        events=EventOptions(tol=o["event_tol"], interior_points=o["interior_points"]),
        zeno=zeno_options(o["zeno"], window, o["zeno_ratio_tol"], o["zeno_max_ratio"]),
        throw=bool(o["throw"]),
    )


class Prepared(NamedTuple):
    """`prepare`'s result: the run's float type, loop kind and checkpoints, the solver and
    controller as diffrax would step them, and the options with the event tolerance filled in."""

    dtype: Any
    kind: str
    checkpoints: int | None
    solver: Any
    controller: Any
    options: SolveOptions


def prepare(system, x0_arr, args, solver, controller, options: SolveOptions, adjoint) -> Prepared:
    """Check a run's inputs and complete its options (`args` of one execution): the float
    type, the loop kind of `adjoint`, the default controller, the solver prepared as
    `diffrax.diffeqsolve` prepares it, and `options.events.tol` for the dtype where None."""
    if not isinstance(system, AbstractHybridSystem):
        raise TypeError(
            f"system must be a hybridjax.HybridSystem (an AbstractHybridSystem), got {type(system).__name__}."
        )
    dtype = float_type(x0_arr.dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"x0 must be real, got dtype {x0_arr.dtype}.")
    system.check(promote_args(args, dtype), dtype)
    adjoint = adjoint_for(adjoint, derivative_modes())
    warn_if_forward_mode_beneath(adjoint, "A hybridjax simulation")
    kind, checkpoints = _loop_kind(adjoint)
    controller = _default_controller(dtype) if controller is None else controller
    solver = _prepare_solver(solver, controller, kind)
    if options.dt0 is None and not isinstance(controller, diffrax.AbstractAdaptiveStepSizeController):
        raise ValueError(f"{type(controller).__name__} needs dt0 (no error estimate to pick one).")
    if options.events.tol is None:
        options = eqx.tree_at(lambda o: o.events.tol, options, 1e-12 if dtype == jnp.float64 else 1e-6,
                              is_leaf=lambda x: x is None)
    _warn_unreachable_tolerance(controller, dtype)
    return Prepared(dtype, kind, checkpoints, solver, controller, options)


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


def save_times(saveat, t0, t1, dtype) -> jax.Array:
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


def initial_state(system: HybridSystem, x0, mode0, dtype) -> jax.Array:
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
