"""Trajectory optimisation by single shooting through hybrid executions.

A `Shooting` problem maps a pytree of parameters theta to an execution of a hybrid system
(initial state, `args`, final time, each a value or a function of theta) and a scalar cost on it;
`shoot` minimises that cost with an optax optimiser, every iterate a full `simulate` and the
gradient by `jax.grad` through it. The gradient is that of the execution with its event
sequence held fixed (the implicit function theorem at each event, A. M. Johnson, "Hybrid
Dynamical Systems", section 3.6): the cost is piecewise smooth in theta, smooth between changes
of the event sequence, so every iterate records its sequence and whether it changed. A required
sequence (exactly k bounces, say) is enforced by backtracking: a step whose execution takes other
transitions is halved until it does not.
"""

from collections.abc import Callable, Sequence
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PyTree

from .._core.checks import check_int
from .._core.names import bounds_of, one_of
from .._definition.system import AbstractHybridSystem, HybridSystem, Mode, Transition
from .._solution.solution import Solution
from .._solve.simulator import Simulator, simulator_of


def _value(spec, params):
    """A problem field: a function of the parameters, or a value used as given."""
    return spec(params) if callable(spec) else spec


class Shooting(eqx.Module):
    r"""A trajectory-optimisation problem: minimise $J(\theta) = c(\theta, \varphi_\theta)$ over
    a pytree of parameters $\theta$, where $\varphi_\theta$ is the execution of `system` from
    `x0(theta)` in `mode0` over $[t_0, t_1(\theta)]$ with `args(theta)`.

    **Arguments:**

    - `system`: the `HybridSystem`.
    - `cost`: `cost(params, sol) -> scalar`, any function of the parameters and the
      `Solution` (final state, event times, states before and after events, saved states;
      a running cost through `with_running_cost`).
    - `x0`, `args`, `t0`, `t1`: each a value or a function of the parameters. `t1` a function
      of them is a free final time; an open-loop control is an array or a
      `diffrax.LinearInterpolation` in `args`; a feedback policy is a function in the flow
      reading its weights from `args`.
    - `mode0`: the initial mode (name or index).
    - `transitions`: optional required event sequence, transition indices (or `Transition`s)
      in order: an execution is admissible when it takes exactly these transitions. A step to
      an inadmissible execution is halved, up to `max_backtracks` times, and refused if it
      stays inadmissible.
    - `bounds`: optional `(lower, upper)`, each a pytree of the parameters' structure, a
      scalar, or None for no bound on that side; each iterate is projected onto the box.
    - `simulator`: an `hj.Simulator`, how each execution is computed (solver, step-size
      controller, save times, `max_epochs`, `max_steps`, ...). Default: `hj.Simulator(max_epochs=16)`.
    - `max_backtracks`: the most halvings of a step whose execution is inadmissible.

    **Keyword shorthands** (pass a name or its shorthands, not both: a `ValueError` names both;
    an unknown keyword is a `TypeError` naming it):

    - `lower`, `upper`: `bounds=(lower, upper)`.
    - `solver`, `stepsize_controller`, `saveat`, `max_epochs` (16), `max_steps` (4096) and
      `simulate`'s other keywords: `simulator=hj.Simulator(...)` with these settings.

    !!! Example

        ```python
        ball = hj.examples.bouncing_ball()
        problem = hj.Shooting(
            ball, x0=lambda v: jnp.stack([0.0 * v, v]), mode0="flight", t1=10.0,
            args={"g": 9.8, "e": 0.5},
            cost=lambda v, sol: (sol.event_times[1] - 2.0) ** 2,   # second impact at t = 2
            bounds=(0.0, 20.0), simulator=hj.Simulator(max_epochs=2))
        result = hj.shoot(problem, jnp.asarray(6.0), optax.adam(0.1), iterations=200)
        ```
    """

    system: HybridSystem
    cost: Callable
    x0: Any
    mode0: str | int = eqx.field(static=True)
    t0: Any
    t1: Any
    args: Any
    transitions: tuple[int, ...] | None = eqx.field(static=True)
    bounds: tuple[Any, Any]
    simulator: Simulator
    max_backtracks: int = eqx.field(static=True)  # static: the backtracking loop's bound

    def __init__(
        self,
        system: HybridSystem,
        cost: Callable,
        x0: Any,
        mode0: str | int,
        *,
        t0: Any = 0.0,
        t1: Any = 1.0,
        args: Any = None,
        transitions: Sequence[int | Transition] | None = None,
        bounds: tuple[Any, Any] | None = None,
        simulator: Simulator | None = None,
        max_backtracks: int = 8,
        **shorthands,
    ):
        if not isinstance(system, AbstractHybridSystem):
            raise TypeError(
                f"Shooting: system must be a hybridjax.HybridSystem, got {type(system).__name__}.")
        if not callable(cost):
            raise TypeError("Shooting: `cost` must be a function cost(params, sol) -> scalar.")
        system.mode_index(mode0)  # raises, naming the mode, when it is unknown
        bounds = bounds_of("Shooting", bounds, shorthands)
        simulator = simulator_of("Shooting", simulator, shorthands, defaults={"max_epochs": 16})
        max_epochs = simulator.options.max_epochs
        if transitions is not None:
            transitions = tuple(system.transition_index(tr) for tr in transitions)
            if len(transitions) > max_epochs:
                raise ValueError(
                    f"Shooting: the required sequence has {len(transitions)} transitions but "
                    f"max_epochs={max_epochs} records fewer; raise max_epochs."
                )
        check_int("Shooting", "max_backtracks", max_backtracks, 0)
        self.system, self.cost, self.x0, self.mode0 = system, cost, x0, mode0
        self.t0, self.t1, self.args, self.transitions = t0, t1, args, transitions
        self.bounds, self.simulator, self.max_backtracks = bounds, simulator, max_backtracks

    # The box's sides and the simulator's settings, readable under their shorthands' names.
    @property
    def lower(self) -> Any:
        return self.bounds[0]

    @property
    def upper(self) -> Any:
        return self.bounds[1]

    @property
    def solver(self) -> diffrax.AbstractSolver:
        return self.simulator.solver

    @property
    def stepsize_controller(self) -> diffrax.AbstractStepSizeController | None:
        return self.simulator.stepsize_controller

    @property
    def saveat(self) -> Any:
        return self.simulator.saveat

    @property
    def max_epochs(self) -> int:
        return self.simulator.options.max_epochs

    @property
    def max_steps(self) -> int:
        return self.simulator.options.max_steps

    def execution(self, params: PyTree) -> Solution:
        """The execution for these parameters (one `simulate`, with `simulator`'s settings)."""
        return self.simulator(self.system, _value(self.x0, params), self.mode0, _value(self.t0, params),
                              _value(self.t1, params), _value(self.args, params))

    def loss(self, params: PyTree) -> tuple[Float[Array, ""], Solution]:
        """The cost and the execution it was computed on."""
        sol = self.execution(params)
        return jnp.asarray(self.cost(params, sol)), sol

    def project(self, params: PyTree) -> PyTree:
        """`params` projected onto the box `bounds` = [lower, upper] (unchanged without bounds)."""
        if self.lower is None and self.upper is None:
            return params
        return optax.projections.projection_box(
            params,
            -jnp.inf if self.lower is None else self.lower,
            jnp.inf if self.upper is None else self.upper,
        )

    def admissible(self, sol: Solution) -> Bool[Array, ""]:
        """Whether `sol` takes exactly the required transitions (always, without a requirement)."""
        if self.transitions is None:
            return jnp.asarray(True)
        return same_sequence(sol.num_events, sol.transitions, self.transitions)


def same_sequence(num_events, transitions, required) -> Bool[Array, ""]:
    """Whether an execution's event sequence (`num_events`, padded `transitions`) is `required`."""
    required = jnp.asarray(required, jnp.int32)
    k = required.shape[0]
    return (num_events == k) & jnp.all(transitions[:k] == required)


class ShootingResult(eqx.Module):
    """What `shoot` returns; a leading batch axis on every field for `batched=True`.

    Iterate 0 is the initial guess (projected onto the bounds); iterate i > 0 the accepted
    parameters after step i (the previous ones again when a step was refused).

    - `params`, `cost`: the last iterate and its cost.
    - `costs` (iterations + 1,), `params_history` (the parameters' pytree with a leading
      iterations + 1 axis): every iterate.
    - `num_events`, `transitions` (iterations + 1, max_epochs): each iterate's event sequence
      (transition indices, -1 past `num_events`); `status`: each iterate's `hj.Status` code.
    - `sequence_changed` (iterations + 1,): whether the iterate's event sequence differs from the
      previous iterate's, where the cost's gradient may jump.
    - `accepted` (iterations + 1,): whether the step was taken (its execution finite and
      admissible); `backtracks`: how many halvings it needed.
    """

    params: PyTree
    cost: Float[Array, "*batch"]
    costs: Float[Array, "*batch iterates"]
    params_history: PyTree
    num_events: Int[Array, "*batch iterates"]
    transitions: Int[Array, "*batch iterates epochs"]
    status: Int[Array, "*batch iterates"]
    sequence_changed: Bool[Array, "*batch iterates"]
    accepted: Bool[Array, "*batch iterates"]
    backtracks: Int[Array, "*batch iterates"]

    @property
    def changes(self) -> np.ndarray:
        """Indices of the iterates whose event sequence changed (one run, not a batch)."""
        return np.flatnonzero(np.asarray(self.sequence_changed))


class _Iterate(eqx.Module):
    params: PyTree
    value: Array
    grad: PyTree
    num_events: Array
    transitions: Array
    status: Array


def _evaluate(problem: Shooting, params) -> tuple[_Iterate, Array]:
    (value, sol), grad = jax.value_and_grad(problem.loss, has_aux=True)(params)
    ok = jnp.isfinite(value) & problem.admissible(sol)
    return _Iterate(params, value, grad, sol.num_events, sol.transitions, sol.status_code), ok


def _attempt(problem: Shooting, base, proposal, template: _Iterate):
    """Evaluate `proposal`, halving the step from `base` until its execution is admissible."""

    def cond(c):
        _, ok, tries = c
        return (~ok) & (tries <= problem.max_backtracks)

    def body(c):
        _, _, tries = c
        scale = 0.5 ** tries.astype(template.value.dtype)
        trial = jax.tree_util.tree_map(lambda b, p: b + scale * (p - b), base, proposal)
        it, ok = _evaluate(problem, trial)
        return it, ok, tries + 1

    it, ok, tries = jax.lax.while_loop(cond, body, (template, jnp.asarray(False), jnp.asarray(0)))
    return it, ok, tries - 1


def _select(pred, a, b):
    return jax.tree_util.tree_map(lambda x, y: jnp.where(pred, x, y), a, b)


@eqx.filter_jit
def _run(problem: Shooting, params0, optimiser: optax.GradientTransformation, steps: int):
    params0 = problem.project(params0)
    template, _ = eqx.filter_eval_shape(_evaluate, problem, params0)
    template = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), template)
    template = eqx.tree_at(lambda it: it.params, template, params0)
    opt_state0 = optimiser.init(params0)

    # Iteration 0 evaluates the initial guess through the same code as every step, so the
    # simulation and its gradient are traced (and compiled) once.
    def step(carry, i):
        current, opt_state = carry
        first = i == 0
        # optax's extra arguments, for the transformations that read them (L-BFGS's line search)
        updates, new_state = optimiser.update(
            current.grad, opt_state, current.params, value=current.value, grad=current.grad,
            value_fn=lambda p: problem.loss(p)[0])
        proposal = problem.project(optax.apply_updates(current.params, updates))
        proposal = _select(first, current.params, proposal)
        it, ok, tries = _attempt(problem, current.params, proposal, current)
        accepted = ok | first
        nxt = _select(accepted, it, current)
        changed = (~first) & ~(
            (nxt.num_events == current.num_events) & jnp.all(nxt.transitions == current.transitions))
        opt_state = _select(accepted & ~first, new_state, opt_state)
        record = (nxt.value, nxt.params, nxt.num_events, nxt.transitions, nxt.status, changed,
                  accepted, tries)
        return (nxt, opt_state), record

    (last, _), rec = jax.lax.scan(step, (template, opt_state0), jnp.arange(steps + 1))
    costs, params, num_events, transitions, status, changed, accepted, tries = rec
    return ShootingResult(last.params, last.value, costs, params, num_events, transitions, status,
                          changed, accepted, tries)


def shoot(
    problem: Shooting,
    params0: PyTree[ArrayLike],
    optimiser: optax.GradientTransformation,
    *,
    iterations: int | None = None,
    batched: bool = False,
    steps: int | None = None,
) -> ShootingResult:
    r"""Minimise `problem`'s cost from `params0` with `iterations` updates of an optax `optimiser`
    (`steps` is the same keyword under another name; `hybrid_ilqr` counts its iterations as
    `iterations` too, and `max_steps` everywhere counts a solver's steps).

    Each step: $g = \nabla_\theta J(\theta_i)$ through `simulate`; the optimiser's update
    $\theta' = \Pi(\theta_i + u(g))$ projected onto the bounds; the step halved,
    $\theta_i + 2^{-j} (\theta' - \theta_i)$, while the execution is non-finite or takes other
    transitions than `problem.transitions` requires. One compiled program runs all iterations
    (`jax.lax.scan`). With `batched=True`, `params0` has a leading axis of initial guesses,
    solved together (`jax.vmap`).

    Each step takes the first derivative through the events, which is what optax's first-order
    methods use (second derivatives through events: `jax.hessian` of the objective).

    !!! Example

        ```python
        result = hj.shoot(problem, jnp.array([5.0, 6.0, 7.0]), optax.adam(0.1), iterations=200,
                          batched=True)
        result.params, result.costs[:, -1], result.changes   # per guess
        ```
    """
    steps = one_of("shoot", iterations=iterations, steps=steps, default=None)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise ValueError(f"shoot: iterations must be an int >= 0, got {steps!r}.")
    if not isinstance(optimiser, optax.GradientTransformation):
        raise TypeError(f"shoot: optimiser must be an optax.GradientTransformation, got {optimiser!r}.")
    optimiser = optax.with_extra_args_support(optimiser)
    params0 = jax.tree_util.tree_map(lambda p: jnp.asarray(p, jnp.result_type(p, float)), params0)
    if batched:
        return eqx.filter_vmap(lambda p: _run(problem, p, optimiser, int(steps)))(params0)
    return _run(problem, params0, optimiser, int(steps))


# ----------------------------------------------------------------------------- running cost


def with_running_cost(system: HybridSystem, running_cost: Callable) -> HybridSystem:
    r"""`system` with its running cost integrated along the flow as state component 0.

    Every mode's state becomes $(c, x)$ with $\dot c = L(t, x, \text{args})$ and every reset
    keeps $c$, so $c(t) = \int_{t_0}^{t} L\,dt$ along the execution (flows only: a cost of a jump
    goes into the `Shooting` cost as a function of the event states). Guards, resets, domains
    and flows see $x$ alone. Start from `jnp.concatenate([jnp.zeros(1), x0])`; the accumulated
    cost is `sol.final_state[0]`, or `sol.states_before[i, 0]` at event i.

    !!! Example

        ```python
        costly = hj.with_running_cost(ball, lambda t, x, args: x[0] ** 2)   # integral of h^2
        ```
    """
    if not callable(running_cost):
        raise TypeError("with_running_cost: running_cost must be a function L(t, x, args).")

    def flow(f):
        return lambda t, z, a: jnp.concatenate([jnp.reshape(running_cost(t, z[1:], a), (1,)), f(t, z[1:], a)])

    def on_x(fn):
        return lambda t, z, a: fn(t, z[1:], a)

    def reset(r):
        return lambda t, z, a: jnp.concatenate([z[:1], r(t, z[1:], a)])

    modes = [Mode(m.name, flow(m.flow), m.dim + 1, None if m.domain is None else on_x(m.domain),
                  None if m.names is None else ("cost", *m.names)) for m in system.modes]
    transitions = [Transition(tr.source, tr.target, on_x(tr.guard), reset(tr.reset), tr.name)
                   for tr in system.transitions]
    completions = [eqx.tree_at(lambda c: c.reset, c, reset(c.reset)) for c in system.completions]
    return HybridSystem(modes, transitions, completions=completions)
