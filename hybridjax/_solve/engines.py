"""The engines: how the steps of `simulate` and `simulate_batch` are computed, as objects.

A per-execution engine (`FastEngine`, `DiffraxEngine`) turns the diffrax solver and controller
into the stepper and step-size rule of the per-execution loop (`_engines.loop.Loop`); the batch
engines (`BatchedEngine`, `VmapEngine`) say how `simulate_batch` runs its executions; `AutoEngine`
chooses among them by what the solver, the controller and the platform allow (as lineax's
`AutoLinearSolver` chooses a linear solver). The strings `"auto"`, `"fast"`, `"diffrax"`,
`"batched"`, `"vmap"` are shorthands for them (`as_engine`).
"""

import abc

import equinox as eqx
import jax
import numpy as np

from .._engines.batched import can_map_step
from .._step.runge_kutta import (
    FastIController,
    UnrolledERK,
    can_batch_controller,
    can_unroll,
    can_use_fast_controller,
)

_FAST_SOLVERS = "Heun, Midpoint, Ralston, Bosh3, Tsit5, Dopri5, Dopri8 (or a subclass with the same tableau)"


def _check_block(block) -> None:
    def size(b):
        return isinstance(b, (int, np.integer)) and not isinstance(b, bool) and b >= 1

    if block is None or size(block):
        return
    if isinstance(block, tuple) and len(block) == 2 and size(block[0]):
        if block[1] is None or (size(block[1]) and block[0] < block[1]):
            return
    raise ValueError("BatchedEngine: block must be a positive integer, None (the default), or a tuple "
                     "(small, large) of block sizes with small < large (large None: the default); "
                     f"got {block!r}.")


class AbstractEngine(eqx.Module):
    """How a run's steps are computed: `hj.AutoEngine()` (the default), `hj.FastEngine()`,
    `hj.DiffraxEngine()` for each execution; `hj.BatchedEngine()`, `hj.VmapEngine()` for the
    executions of `simulate_batch`. Every engine gives the same executions to rounding; they
    differ in speed and in what they support."""


class AbstractStepEngine(AbstractEngine):
    """An engine for the per-execution loop: it chooses the stepper and the step-size rule."""

    @abc.abstractmethod
    def stepper(self, solver, controller) -> tuple:
        """`(solver, controller)` as the loop steps them; a `ValueError` where this engine cannot
        run them."""


class DiffraxEngine(AbstractStepEngine):
    """Each step by diffrax's own `solver.step` and `stepsize_controller.adapt_step_size`: any
    diffrax solver and controller."""

    def stepper(self, solver, controller):
        return solver, controller


class FastEngine(AbstractStepEngine):
    r"""Each step from the solver's Butcher tableau with the stages unrolled,

    $$k_i = h F(t_0 + c_i h,\ y_0 + \textstyle\sum_{j<i} a_{ij} k_j), \quad
    y_1 = y_0 + \textstyle\sum_i b_i k_i,$$

    and the I-controller rule of diffrax's `PIDController` written out: the same steps as
    `DiffraxEngine` to rounding, faster under `jax.vmap`. Requires an explicit Runge-Kutta
    solver with the tableau of Heun, Midpoint, Ralston, Bosh3, Tsit5, Dopri5 or Dopri8 and
    diffrax's step (a subclass that keeps both qualifies) and a `PIDController` with default
    coefficients (pcoeff=0, icoeff=1, dcoeff=0), the rms norm and no dtmin, dtmax.
    """

    def stepper(self, solver, controller):
        if not can_unroll(solver):
            why = f"solver {type(solver).__name__} is not one of {_FAST_SOLVERS}"
        elif not can_use_fast_controller(controller):
            why = (f"stepsize_controller {controller!r} is not a PIDController with default "
                   "coefficients (pcoeff=0, icoeff=1, dcoeff=0), rms norm and no dtmin, dtmax")
        else:
            return UnrolledERK(solver), FastIController(controller)
        raise ValueError(f"engine='fast': {why}; use engine='diffrax' (or 'auto').")


class BatchedEngine(AbstractEngine):
    """`simulate_batch`'s own loop: all executions as structure of arrays, every one advancing
    one step per iteration, the rare work (epoch starts, event location, resets) done on gathered
    blocks. For the explicit solvers of `FastEngine` and diffrax's ImplicitEuler, Kvaerno3,
    Kvaerno4, Kvaerno5, with a `PIDController` (rms norm, Python-number coefficients).

    **Fields** (the `block`, `lanes`, `devices` keywords of `simulate_batch` set them; the docs of
    `simulate_batch` say what each does): `block` (an int, `(small, large)` or None), `lanes`
    (an int or None), `devices` (None, an int, or a list of devices).
    """

    block: int | tuple[int, int | None] | None = None
    lanes: int | None = None
    devices: int | tuple | None = eqx.field(default=None,
                                           converter=lambda d: tuple(d) if isinstance(d, list) else d)

    def __check_init__(self):
        _check_block(self.block)
        lanes = self.lanes
        if lanes is not None and (isinstance(lanes, bool) or not isinstance(lanes, (int, np.integer))
                                  or lanes < 1):
            raise ValueError("BatchedEngine: lanes must be a positive integer (or None: the default), "
                             f"got {lanes!r}.")
        d = self.devices
        if isinstance(d, (int, np.integer)) and not isinstance(d, bool):
            ok = d >= 1
        else:
            ok = d is None or (isinstance(d, tuple) and len(d) > 0
                               and all(isinstance(x, jax.Device) for x in d))
        if not ok:
            raise ValueError("BatchedEngine: devices must be None (every device of the default backend), a "
                             f"positive integer (the first ones) or a list of jax devices; got {d!r}.")

    def refusal(self, solver, controller) -> str | None:
        """Why this engine cannot run `solver` with `controller` (None when it can)."""
        if not (can_unroll(solver) or can_map_step(solver)):
            return (f"solver {type(solver).__name__} is not one of {_FAST_SOLVERS}, ImplicitEuler, "
                    "Kvaerno3, Kvaerno4, Kvaerno5")
        if not can_batch_controller(controller):
            return (f"stepsize_controller {controller!r} is not a PIDController with the rms norm and "
                    "Python-number coefficients (step_ts, jump_ts allowed)")
        return None


class VmapEngine(AbstractEngine):
    """`simulate_batch` as `jax.vmap(simulate)`, each execution run by `inner` (a per-execution
    engine; default `AutoEngine()`)."""

    inner: AbstractEngine = eqx.field(default_factory=lambda: AutoEngine())

    def __check_init__(self):
        if not isinstance(self.inner, AbstractStepEngine | AutoEngine):
            raise ValueError(f"VmapEngine: inner must be AutoEngine(), FastEngine() or DiffraxEngine(), "
                             f"got {type(self.inner).__name__}.")


class AutoEngine(AbstractStepEngine):
    """Chooses the engine itself. For one execution (`simulate`, and each execution of a
    `VmapEngine`): `FastEngine`'s step where the solver allows it and its step-size rule where
    the controller does, diffrax's otherwise (each part on its own). For `simulate_batch`:
    `batched` (a `BatchedEngine`, default `BatchedEngine()`) where it applies and the executions
    run on CPU, `VmapEngine()` otherwise: on a GPU the per-execution loop under `jax.vmap` runs
    each iteration as wide as the batch with no gathering, and is the faster of the two (docs:
    Benchmarks, On one GPU); on a few CPU cores the batched loop saves the work of executions
    that do not need it."""

    batched: BatchedEngine = BatchedEngine()

    def stepper(self, solver, controller):
        if can_unroll(solver):
            solver = UnrolledERK(solver)
        if can_use_fast_controller(controller):
            controller = FastIController(controller)
        return solver, controller

    def batch_engine(self, platform: str, refusal: str | None) -> AbstractEngine:
        """The engine for a batch on `platform` (`"cpu"`, `"gpu"`, ...), given the batched
        engine's `refusal` of the solver and controller."""
        return self.batched if platform == "cpu" and refusal is None else VmapEngine()


_SHORTHANDS = ("auto", "fast", "diffrax", "batched", "vmap")


def as_engine(engine, *, block=None, lanes=None, devices=None) -> AbstractEngine:
    """The engine object of `engine` (an `hj` engine, or one of the strings `"auto"`, `"fast"`,
    `"diffrax"`, `"batched"`, `"vmap"`); `block`, `lanes`, `devices` set the batched engine of
    `"auto"` and `"batched"` (of an engine object: pass them to its `BatchedEngine`)."""
    batch_settings = (block, lanes, devices) != (None, None, None)
    if isinstance(engine, AbstractEngine):
        if batch_settings:
            raise ValueError(f"engine={type(engine).__name__}(...) holds the engine's settings: pass block, "
                             "lanes and devices to its BatchedEngine, not beside it.")
        return engine
    if isinstance(engine, str) and engine in _SHORTHANDS:
        batched = BatchedEngine(block, lanes, devices)
        return {"auto": lambda: AutoEngine(batched=batched), "fast": FastEngine, "diffrax": DiffraxEngine,
                "batched": lambda: batched, "vmap": VmapEngine}[engine]()
    raise ValueError("engine must be an engine object (hj.AutoEngine(), hj.FastEngine(), hj.DiffraxEngine(), "
                     f"hj.BatchedEngine(), hj.VmapEngine()) or one of {', '.join(map(repr, _SHORTHANDS))}; "
                     f"got {engine!r}.")


def step_engine(engine: AbstractEngine) -> AbstractStepEngine:
    """`engine` for one execution (`simulate`): a `ValueError` for a batch engine."""
    if not isinstance(engine, AbstractStepEngine):
        raise ValueError(f"engine must be 'auto', 'fast' or 'diffrax' (hj.AutoEngine(), hj.FastEngine(), "
                         f"hj.DiffraxEngine()) in simulate, got {type(engine).__name__}: it runs the "
                         "executions of simulate_batch.")
    return engine
