"""`Simulator`: how an execution is computed (solver, controller, saving, adjoint, engine,
options), as one object that the functions which simulate on a user's behalf (shooting, iLQR,
property checks, Monte Carlo) take in place of `simulate`'s keywords."""

from typing import Any

import diffrax
import equinox as eqx
from jaxtyping import ArrayLike, Float, Int

from .._definition.system import AbstractHybridSystem
from .._rules.options import SolveOptions
from .._solution.solution import Solution
from .engines import AbstractEngine, as_engine
from .prepare import SHORTHANDS, solve_options
from .simulate import simulate
from .simulate_batch import simulate_batch

# The keywords a function that simulates for the user accepts in place of `simulator=`.
SIMULATOR_FIELDS = ("solver", "stepsize_controller", "saveat", "adjoint", "engine", "options")


class Simulator(eqx.Module):
    r"""How an execution is computed: everything `simulate` takes besides the problem
    (`system`, `x0`, `mode0`, `t0`, `t1`, `args`), in one validated object.

    `hj.Simulator(...)(system, x0, mode0, t0, t1, args)` is
    `hj.simulate(system, x0, mode0, t0, t1, args, solver=..., ..., options=...)`, and
    `.batch(...)` is `hj.simulate_batch` with the same settings. `hj.Shooting`, `hj.HybridILQR`,
    `hj.check_properties` and `hj.monte_carlo` take one as `simulator=`; their keywords
    `solver`, `stepsize_controller`, `saveat`, `max_epochs`, `max_steps`, ... are shorthands
    that build it.

    **Fields** (each as in `simulate`):

    - `solver`: a diffrax solver. Default `diffrax.Tsit5()`.
    - `stepsize_controller`: a diffrax step-size controller; None (default): a
      `PIDController` at 1e-8 in float64 (1e-5 in float32).
    - `saveat`: save times (a 1-D array or `diffrax.SaveAt(ts=...)`), or None.
    - `adjoint`: a diffrax adjoint. Default `diffrax.RecursiveCheckpointAdjoint()`.
    - `engine`: an `hj` engine or its shorthand string. Default `"auto"`.
    - `options`: an `hj.SolveOptions` (record length, step budget, event location, Zeno). The
      keyword shorthands of `simulate` (`max_epochs=16`, `event_tol=...`) build it:
      `hj.Simulator(max_epochs=16)`.

    !!! Example

        ```python
        import hybridjax as hj, jax.numpy as jnp, diffrax
        ball = hj.examples.bouncing_ball()
        sim = hj.Simulator(stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
                           max_epochs=8)
        sol = sim(ball, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, {"g": 9.8, "e": 0.8})
        ```
    """

    solver: diffrax.AbstractSolver
    stepsize_controller: diffrax.AbstractStepSizeController | None
    saveat: Any
    adjoint: diffrax.AbstractAdjoint
    engine: AbstractEngine | str  # as given (a string kept as one): `simulate` reads both alike
    options: SolveOptions

    def __init__(
        self,
        solver: diffrax.AbstractSolver = diffrax.Tsit5(),
        stepsize_controller: diffrax.AbstractStepSizeController | None = None,
        saveat: Any = None,
        adjoint: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint(),
        engine: AbstractEngine | str = "auto",
        options: SolveOptions | None = None,
        **shorthands,
    ):
        if not isinstance(solver, diffrax.AbstractSolver):
            raise TypeError(f"Simulator: solver must be a diffrax solver, got {type(solver).__name__}.")
        if stepsize_controller is not None and not isinstance(
                stepsize_controller, diffrax.AbstractStepSizeController):
            raise TypeError("Simulator: stepsize_controller must be a diffrax step-size controller or None, "
                            f"got {type(stepsize_controller).__name__}.")
        if not isinstance(adjoint, diffrax.AbstractAdjoint):
            raise TypeError(f"Simulator: adjoint must be a diffrax adjoint, got {type(adjoint).__name__}.")
        self.solver = solver
        self.stepsize_controller = stepsize_controller
        self.saveat = saveat
        self.adjoint = adjoint
        as_engine(engine)  # a ValueError naming the choices for an unknown engine
        self.engine = engine
        self.options = solve_options(options, shorthands, "Simulator")

    def keywords(self) -> dict[str, Any]:
        """The settings as `simulate`'s keywords."""
        return {name: getattr(self, name) for name in SIMULATOR_FIELDS}

    def __call__(
        self,
        system: AbstractHybridSystem,
        x0: Float[ArrayLike, " dim"],
        mode0: str | int | Int[ArrayLike, ""],
        t0: Float[ArrayLike, ""],
        t1: Float[ArrayLike, ""],
        args: Any = None,
    ) -> Solution:
        """One execution: `hj.simulate` with these settings."""
        return simulate(system, x0, mode0, t0, t1, args, **self.keywords())

    def batch(
        self,
        system: AbstractHybridSystem,
        x0: Float[ArrayLike, "batch dim"],
        mode0: str | int | Int[ArrayLike, " batch"],
        t0: Float[ArrayLike, "*batch"],
        t1: Float[ArrayLike, "*batch"],
        args: Any = None,
        *,
        args_batched: bool = False,
    ) -> Solution:
        """N executions, one per row of `x0`: `hj.simulate_batch` with these settings."""
        return simulate_batch(system, x0, mode0, t0, t1, args, args_batched=args_batched, **self.keywords())


def simulator_of(owner: str, simulator: Simulator | None, given: dict[str, Any],
                 defaults: dict[str, Any] | None = None) -> Simulator:
    """The `Simulator` of a function that simulates for the user: `simulator` itself, or one built
    from the keyword shorthands in `given` (`simulate`'s keywords; None counts as not given),
    `defaults` filling what was not given. Both at once is a `ValueError` naming them; an unknown
    keyword a `TypeError` naming it."""
    given = {name: value for name, value in given.items() if value is not None}
    unknown = sorted(set(given) - set(SIMULATOR_FIELDS) - set(SHORTHANDS))
    if unknown:
        raise TypeError(f"{owner}() got an unexpected keyword argument {unknown[0]!r}.")
    if simulator is not None:
        if not isinstance(simulator, Simulator):
            raise TypeError(f"{owner}: simulator must be an hj.Simulator, got {type(simulator).__name__}.")
        if given:
            raise ValueError(f"{owner}: simulator=hj.Simulator(...) holds the run's settings: pass "
                             f"{', '.join(sorted(given))} there, not beside it.")
        return simulator
    defaults = dict(defaults or {})
    if "options" in given:  # the options object replaces the defaults of its shorthands
        defaults = {name: value for name, value in defaults.items() if name not in SHORTHANDS}
    return Simulator(**{**defaults, **given})
