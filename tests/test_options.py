"""The options as objects: `SolveOptions`, `EventOptions`, the engines and event locators; a
subclass of a fast-path solver; `Solution.evaluate` with the run's solver and tolerances."""

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax import lax

import hybridjax as hj
from hybridjax import examples

from helpers import BALL, BALL_ARGS, TIGHT

X0 = jnp.array([1.0, 0.0])
G, E = BALL_ARGS["g"], BALL_ARGS["e"]


def _ball_event_times(k: int) -> np.ndarray:
    """The ball's first k impacts from h0 = 1 at rest: t_1 = sqrt(2 h0 / g), each flight after
    the i-th impact 2 e^i t_1 long (closed form)."""
    t1 = math.sqrt(2.0 / G)
    return t1 * (1.0 + 2.0 * np.cumsum([0.0] + [E**i for i in range(1, k)]))


def _assert_impacts(event_times, t1: float) -> None:
    """`event_times` (padded with inf) are the closed-form impacts before t1, to 1e-9."""
    want = _ball_event_times(np.size(event_times))
    want = np.where(want <= t1, want, np.inf)
    np.testing.assert_allclose(event_times, want, rtol=0, atol=1e-9)


# ---------------------------------------------------------------------------- validation
@pytest.mark.parametrize("kwargs, field", [
    (dict(max_epochs=0), "max_epochs"),
    (dict(max_steps=2.5), "max_steps"),
    (dict(max_zero_epochs=-1), "max_zero_epochs"),
    (dict(dt0=-0.1), "dt0"),
    (dict(events="tight"), "events"),
    (dict(zeno=True), "zeno"),
    (dict(throw="yes"), "throw"),
])
def test_solve_options_name_the_field_at_fault(kwargs, field):
    with pytest.raises((ValueError, TypeError), match=f"SolveOptions: {field} must be"):
        hj.SolveOptions(**kwargs)


@pytest.mark.parametrize("kwargs, field", [
    (dict(interior_points=-1), "interior_points"),
    (dict(interior_points=True), "interior_points"),
    (dict(tol=2.0), "tol"),
    (dict(locator=hj.BracketedNewton), "locator"),
])
def test_event_options_name_the_field_at_fault(kwargs, field):
    with pytest.raises((ValueError, TypeError), match=f"EventOptions: {field} must be"):
        hj.EventOptions(**kwargs)


@pytest.mark.parametrize("make, field", [
    (lambda: hj.BatchedEngine(block=(3, 2)), "BatchedEngine: block"),
    (lambda: hj.BatchedEngine(lanes=0), "BatchedEngine: lanes"),
    (lambda: hj.BatchedEngine(devices="cpu"), "BatchedEngine: devices"),
    (lambda: hj.VmapEngine(hj.BatchedEngine()), "VmapEngine: inner"),
    (lambda: hj.BracketedNewton(max_iter=0), "BracketedNewton: max_iter"),
])
def test_engines_and_locators_name_the_field_at_fault(make, field):
    with pytest.raises(ValueError, match=field):
        make()


def test_shorthands_and_options_are_one_or_the_other():
    with pytest.raises(ValueError, match="not beside it"):
        hj.simulate(BALL, X0, "flight", 0.0, 1.0, BALL_ARGS, options=hj.SolveOptions(), max_epochs=8)
    with pytest.raises(TypeError, match="unexpected keyword argument 'max_epoch'"):
        hj.simulate(BALL, X0, "flight", 0.0, 1.0, BALL_ARGS, max_epoch=8)
    with pytest.raises(ValueError, match="simulate_batch"):
        hj.simulate(BALL, X0, "flight", 0.0, 1.0, BALL_ARGS, engine=hj.BatchedEngine())
    with pytest.raises(ValueError, match="not beside it"):
        hj.simulate_batch(BALL, X0[None], "flight", 0.0, 1.0, BALL_ARGS, engine=hj.BatchedEngine(), lanes=2)


# ---------------------------------------------------------------------------- the objects at work
ROOT_TRACES = []  # one entry per trace of `Bisection.root`


class Bisection(hj.AbstractEventLocator):
    """Plain bisection (a textbook root finder, written here): keeps f(a) > 0 >= f(b) and halves
    [a, b] until it is narrower than tol; its right end is the event time. The minimum search is
    golden-section on [a, b]."""

    def root(self, f, a, b, tol):
        ROOT_TRACES.append(1)

        def body(c):
            a, b = c
            m = 0.5 * (a + b)
            right = f(m) <= 0
            return jnp.where(right, a, m), jnp.where(right, m, b)

        return lax.while_loop(lambda c: c[1] - c[0] > tol, body, (a, b))[1]

    def minimum(self, f, a, b, x0, tol):
        r = (math.sqrt(5.0) - 1.0) / 2.0

        def body(c):
            a, b = c
            x1, x2 = b - r * (b - a), a + r * (b - a)
            lower = f(x1) < f(x2)
            return jnp.where(lower, a, x1), jnp.where(lower, x2, b)

        a, b = lax.while_loop(lambda c: c[1] - c[0] > tol, body, (a, b))
        x = 0.5 * (a + b)
        return x, f(x)


def test_options_object_and_a_new_locator_give_the_closed_form_impacts():
    opts = hj.SolveOptions(max_epochs=5, events=hj.EventOptions(locator=Bisection(), tol=1e-13,
                                                               interior_points=2))
    sol = hj.simulate(BALL, X0, "flight", 0.0, 3.0, BALL_ARGS, stepsize_controller=TIGHT, options=opts)
    assert ROOT_TRACES, "the locator of EventOptions was not used"
    assert sol.event_times.shape == (5,) and sol.status == hj.Status.MAX_EPOCHS
    np.testing.assert_allclose(sol.event_times, _ball_event_times(5), rtol=0, atol=1e-9)


class MyTsit5(diffrax.Tsit5):
    """A user's subclass that keeps Tsit5's tableau and step: the fast path takes it."""


class LoggedTsit5(diffrax.Tsit5):
    """A subclass with its own `step`: diffrax steps it (the fast path would skip the override)."""

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        return super().step(terms, t0, t1, y0, args, solver_state, made_jump)


def test_a_tsit5_subclass_takes_the_fast_path():
    runs = {}
    for name, solver in (("plain", diffrax.Tsit5()), ("subclass", MyTsit5())):
        runs[name] = hj.simulate(BALL, X0, "flight", 0.0, 3.0, BALL_ARGS, solver=solver, engine="fast",
                                 stepsize_controller=TIGHT, max_epochs=8)
    for sol in runs.values():
        _assert_impacts(sol.event_times, 3.0)
    # the subclass on the fast path: the plain Tsit5 run's steps, to rounding
    np.testing.assert_allclose(runs["subclass"].event_times, runs["plain"].event_times, rtol=0, atol=1e-13)
    assert int(runs["subclass"].num_steps) == int(runs["plain"].num_steps)
    # a subclass with its own step: diffrax's step (`auto`), refused by the fast engine
    with pytest.raises(ValueError, match="LoggedTsit5 is not one of"):
        hj.FastEngine().stepper(LoggedTsit5(), TIGHT)
    solver, _ = hj.AutoEngine().stepper(LoggedTsit5(), TIGHT)
    assert type(solver) is LoggedTsit5


def test_batch_engine_objects_give_the_closed_form_impacts():
    x0 = jnp.array([[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]])
    for engine in (hj.BatchedEngine(lanes=2, block=1), hj.VmapEngine(hj.DiffraxEngine())):
        sols = hj.simulate_batch(BALL, x0, "flight", 0.0, 3.0, BALL_ARGS, stepsize_controller=TIGHT,
                                 engine=engine, max_epochs=6)
        for i in range(3):
            _assert_impacts(sols.event_times[i], 3.0)


# ---------------------------------------------------------------------------- evaluate
DECAY = hj.HybridSystem(
    modes=[hj.Mode("m", flow=lambda t, x, a: -x, dim=1)],
    transitions=[hj.Transition("m", "m", guard=lambda t, x, a: x[0] - 0.5, reset=lambda t, x, a: x * 2.0)],
)


@pytest.mark.parametrize("solver, tol, match", [(diffrax.Tsit5(), 1e-12, 1e-12), (diffrax.Bosh3(), 1e-5, 2e-6)])
def test_evaluate_integrates_with_the_runs_solver_and_tolerance(solver, tol, match):
    # x' = -x from 1, reset to 2x at x = 0.5: x(t) = exp(-(t mod ln 2)) (closed form). `evaluate`
    # re-integrates each epoch with the run's solver and controller, so it matches the run's own
    # saved states to the run's tolerance (measured: 4e-13 at 1e-12 with Tsit5, 8e-7 at 1e-5
    # with Bosh3), closer than either is to the closed form at the coarse tolerance (5e-5, the
    # run's global error); Tsit5 at 1e-10 in their place gives 3.5e-11 and 1.2e-5.
    ts = jnp.linspace(0.05, 2.0, 9)
    sol = hj.simulate(DECAY, jnp.array([1.0]), "m", 0.0, 2.0, solver=solver, saveat=ts,
                      stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol))
    assert type(sol.solver) is type(solver) and sol.stepsize_controller.rtol == tol
    exact = np.exp(-np.mod(np.asarray(ts), math.log(2.0)))[:, None]
    ys, modes = sol.evaluate(ts)
    np.testing.assert_allclose(sol.ys, exact, rtol=0, atol=10 * tol)
    np.testing.assert_allclose(ys, exact, rtol=0, atol=10 * tol)
    np.testing.assert_allclose(ys, sol.ys, rtol=0, atol=match)
    assert np.all(np.asarray(modes) == 0)
    if tol < 1e-10:  # a solution passed into jax.jit (its solver and controller static), one time
        y_one, _ = jax.jit(lambda s, t: s.evaluate(t))(sol, ts[3])
        np.testing.assert_allclose(y_one, ys[3], rtol=0, atol=match)


# ---------------------------------------------------------------------------- one name for one thing
def test_the_optimisers_and_the_filter_take_the_package_wide_names():
    ts = jnp.linspace(0.0, 1.0, 5)
    lqr = dict(control_args=lambda u: BALL_ARGS, x0=X0, mode0="flight", ts=ts, reference=jnp.zeros((5, 2)),
               Q=jnp.eye(2), R=jnp.eye(1), Qf=jnp.eye(2))
    # max_epochs: the most transitions recorded, as in simulate; max_events the same option
    for kw in (dict(max_epochs=3), dict(max_events=3)):
        problem = hj.HybridLQRProblem(BALL, **lqr, **kw)
        assert problem.max_epochs == problem.max_events == 3
        kf = hj.SaltedKalmanFilter(BALL, lambda t, x, a: x[:1], **kw)
        assert kf.max_epochs == kf.max_events == 3
    with pytest.raises(ValueError, match="max_epochs and max_events are the same option"):
        hj.HybridLQRProblem(BALL, **lqr, max_epochs=3, max_events=3)
    with pytest.raises(ValueError, match="max_epochs and max_events are the same option"):
        hj.SaltedKalmanFilter(BALL, lambda t, x, a: x[:1], max_epochs=3, max_events=4)
    # iterations: the optimiser's updates, in shoot as in hybrid_ilqr; steps the same option
    problem = hj.Shooting(BALL, lambda p, sol: sol.final_state[0], X0, "flight", t1=1.0, args=BALL_ARGS)
    with pytest.raises(ValueError, match="iterations and steps are the same option"):
        hj.shoot(problem, jnp.asarray(1.0), optax.sgd(0.1), iterations=2, steps=2)



def test_the_searches_take_iterations_for_their_optimiser_steps():
    # find_point: the unit circle on the line y = 0, at (+-1, 0), from starts off it;
    # `max_steps` (optimistix's name) is the same option as `iterations`.
    circle = lambda t, x, a: jnp.array([x[0] ** 2 + x[1] ** 2 - 1.0, x[1]])  # noqa: E731
    xs = jnp.array([[2.0, 0.3], [1.5, -0.2], [0.5, 0.1]])
    found = [hj.find_point(circle, None, jnp.zeros(3), xs, **kw) for kw in (dict(iterations=32),
                                                                                 dict(max_steps=32))]
    for w in found:
        assert bool(w.found)
        np.testing.assert_allclose(np.abs(np.asarray(w.x)), [1.0, 0.0], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(found[0].x), np.asarray(found[1].x))
    with pytest.raises(ValueError, match="iterations and max_steps are the same option"):
        hj.find_point(circle, None, jnp.zeros(3), xs, iterations=8, max_steps=8)
    with pytest.raises(ValueError, match="iterations and max_steps are the same option"):
        hj.check_properties(examples.thermostat(), None, bounds={}, iterations=8, max_steps=8)
    with pytest.raises(ValueError, match="iterations and max_steps are the same option"):
        hj.multiple_shooting(None, None, None, iterations=8, max_steps=8)

_FLOOR = hj.Constraint("floor", lambda t, q, a: q[0], restitution=lambda a: a["e"])


def _unit_mass(q, a):
    return jnp.eye(1)


def _gravity(t, q, dq, a):
    return -a["g"] + 0.0 * q


def _ball_scene(**box):
    return hj.Scene(1, _unit_mass, _gravity, [_FLOOR], **box)


def test_the_scene_takes_the_package_wide_names():
    # bounds: (lower, upper) over x = (q, dq); q_range, dq_range its halves, t_range t_bounds
    box = dict(bounds=((0.0, -5.0), (2.0, 5.0)), t_bounds=(0.0, 1.0))
    scene = _ball_scene(**box)
    assert scene == _ball_scene(q_range=(0.0, 2.0), dq_range=(-5.0, 5.0), t_range=(0.0, 1.0))
    assert scene.bounds == ((0.0, -5.0), (2.0, 5.0)) and scene.t_bounds == scene.t_range == (0.0, 1.0)
    assert scene.q_range == ((0.0,), (2.0,)) and scene.dq_range == ((-5.0,), (5.0,))
    # a scalar lower or upper holds for every component of x; the default box is [-1, 1]^(2n)
    assert _ball_scene(bounds=(-1.0, 1.0)).bounds == _ball_scene().bounds == ((-1.0, -1.0), (1.0, 1.0))
    for both, names in ((dict(bounds=box["bounds"], q_range=(0.0, 2.0)), "bounds and q_range"),
                        (dict(t_bounds=(0.0, 1.0), t_range=(0.0, 1.0)), "t_bounds and t_range")):
        with pytest.raises(ValueError, match=f"{names} are the same option"):
            _ball_scene(**both)
    with pytest.raises(ValueError, match="`bounds` must be"):
        _ball_scene(bounds=((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)))
    # key: the point search's jax.random key; seed=s is key=jax.random.key(s). The witness states
    # of the build report come from the samples that key draws.
    args = {"g": 9.81, "e": 0.8}
    by_seed = hj.contact_system(scene, ["free"], args, seed=3)
    by_key = hj.contact_system(scene, ["free"], args, key=jax.random.key(3))
    other = hj.contact_system(scene, ["free"], args, key=jax.random.key(0))
    assert by_seed.report == by_key.report != other.report
    with pytest.raises(ValueError, match="key and seed are the same option"):
        hj.contact_system(scene, ["free"], args, key=jax.random.key(3), seed=3)


@pytest.mark.parametrize("kwargs, field", [
    (dict(num_starts=0), "num_starts"), (dict(iterations=2.5), "iterations"), (dict(tol=-1.0), "tol"),
])
def test_search_options_name_the_field_at_fault(kwargs, field):
    with pytest.raises(ValueError, match=f"SearchOptions: {field} must be"):
        hj.SearchOptions(**kwargs)


def test_contact_system_takes_search_options_and_keyword_shorthands():
    # The build of the test above (its compiled search): search=hj.SearchOptions(...) and its
    # shorthands num_starts, tol give the same system. The ball on a floor with e > 0 bounces:
    # the impact's witness is on the floor (q = 0) moving down, its target the free set again.
    scene = _ball_scene(bounds=((0.0, -5.0), (2.0, 5.0)), t_bounds=(0.0, 1.0))
    args = {"g": 9.81, "e": 0.8}
    by_object = hj.contact_system(scene, ["free"], args, seed=3, search=hj.SearchOptions(num_starts=8, tol=1e-14))
    by_keywords = hj.contact_system(scene, ["free"], args, seed=3, num_starts=8, tol=1e-14)
    assert by_object.report == by_keywords.report and by_object.mode_names == ("free",)
    (src, tgt, kind, name, text), = by_object.achievable
    assert (src, tgt, name) == ("free", "free", "floor")
    q, dq = (float(text.split(f"{v}=(")[1].split(")")[0]) for v in ("q", "dq"))
    assert abs(q) < 1e-6 and dq <= -1e-3  # on the floor, approaching by at least `margin`
    with pytest.raises(ValueError, match="search and tol are the same option"):
        hj.contact_system(scene, ["free"], args, search=hj.SearchOptions(), tol=1e-14)
    with pytest.raises(TypeError, match="unexpected keyword argument 'sed'"):
        hj.contact_system(scene, ["free"], args, sed=3)


# ---------------------------------------------------------------------------- Simulator
@pytest.mark.parametrize("kwargs, match", [
    (dict(solver="tsit5"), "Simulator: solver must be"),
    (dict(stepsize_controller=1e-8), "Simulator: stepsize_controller must be"),
    (dict(adjoint="reverse"), "Simulator: adjoint must be"),
    (dict(engine="fastest"), "engine must be"),
    (dict(max_epoch=8), "unexpected keyword argument 'max_epoch'"),
    (dict(options=hj.SolveOptions(), max_epochs=8), "pass max_epochs there"),
])
def test_simulator_names_the_field_at_fault(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        hj.Simulator(**kwargs)


def test_a_simulator_runs_simulate_and_simulate_batch_with_its_settings():
    sim = hj.Simulator(solver=diffrax.Tsit5(), engine="fast", stepsize_controller=TIGHT, max_epochs=8)
    assert sim.options == hj.SolveOptions(max_epochs=8)
    _assert_impacts(sim(BALL, X0, "flight", 0.0, 3.0, BALL_ARGS).event_times, 3.0)
    batch = hj.Simulator(stepsize_controller=TIGHT, engine=hj.BatchedEngine(lanes=2, block=1), max_epochs=6)
    sols = batch.batch(BALL, jnp.stack([X0] * 3), "flight", 0.0, 3.0, BALL_ARGS)
    for i in range(3):
        _assert_impacts(sols.event_times[i], 3.0)
