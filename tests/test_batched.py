"""The batched engine (`simulate_batch`) against the per-execution engine and closed forms.

Truths: `jax.vmap(simulate)` (itself held to closed forms and diffrax's steps by the rest of the
suite) for whole runs on every example and every status, the bouncing ball's closed form, central
differences for gradients, and diffrax's own interpolation for the dense-output representation.
Batches are small and `block=2`, so that an iteration's rare work runs on gathered blocks, in
one pass (at most two executions need it) or in several (more do).
"""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

import hybridjax as hj
from hybridjax import examples
from hybridjax._definition.kernels import Kernels
from hybridjax._engines.batched import PER_COMPONENT_MAX_DIM
from hybridjax._engines.dense_weights import (
    ChebyshevDense,
    _dense_weights_fn,
    _NotInNumpy,
    _numpy_weights,
    chebyshev_weights,
    dense_weights,
)
from hybridjax._engines.xla_cpu import first_lanes, running_count
from hybridjax._solve.simulate_batch import carries_derivatives

from helpers import BALL, BALL_ARGS, CEILING, THERMO, TIGHT, WALL, central_difference, line_system

THERMO_ARGS = dict(a=0.1, T_amb=5.0, P_heat=2.5, P_cool=2.0, s=20.0)


def _ball_with_passengers(k: int = 7):
    # A ball carrying k decaying coordinates: a 9-dimensional state, above the dimension up to
    # which the batched engine evaluates the field one component at a time.
    rates = jnp.arange(1.0, k + 1.0)
    flight = hj.Mode("flight", lambda t, x, p: jnp.concatenate([jnp.array([x[1], -p["g"]]), -rates * x[2:]]),
                     2 + k)
    bounce = hj.Transition("flight", "flight", guard=lambda t, x, p: x[0],
                           reset=lambda t, x, p: x.at[1].multiply(-p["e"]))
    system = hj.HybridSystem([flight], [bounce])
    assert system.max_dim > PER_COMPONENT_MAX_DIM
    return system


CASES = {
    "bouncing ball": (BALL, [1.0, 0.3], "flight", 3.0, BALL_ARGS),
    "thermostat": (THERMO, [19.0], "off", 40.0, THERMO_ARGS),
    "wall particle": (WALL, [0.0, 1.0, 1.5, 3.0], "flight", 3.0, {"g": 9.8, "w": 2.0, "c": 0.7}),
    "ceiling ball": (CEILING, [0.0, 7.0], "flight", 1.0, {"g": 9.8, "H": 2.0}),
    "rimless wheel": (examples.rimless_wheel(), [0.1, 0.6], 0, 4.0, {"alpha": 0.3, "gamma": 0.08}),
    "pendulum wall": (examples.pendulum_wall(), [-0.5, 0.8], "swing", 9.0, {"theta_w": 0.2, "e": 0.7}),
    "van der pol relay": (examples.van_der_pol_relay(), [-1.0, 0.5], 0, 10.0, 5.0),
    "stiff relay, mild": (examples.stiff_relay(), [0.0, 0.0], 0, 5.0, 20.0),
    "9-dimensional ball": (_ball_with_passengers(), [1.0, 0.3] + [1.0] * 7, "flight", 2.0, BALL_ARGS),
}


def _both(system, x0, mode0, t1, args, **kw):
    run = lambda engine: hj.simulate_batch(system, x0, mode0, 0.0, t1, args, engine=engine,  # noqa: E731
                                           stepsize_controller=TIGHT, block=2, **kw)
    return run("batched"), run("vmap")


def _assert_same_executions(got, want, rtol=1e-8, atol=1e-9):
    np.testing.assert_array_equal(got.status_code, want.status_code)
    np.testing.assert_array_equal(got.num_events, want.num_events)
    np.testing.assert_array_equal(got.transitions, want.transitions)
    np.testing.assert_array_equal(got.epoch_modes, want.epoch_modes)
    np.testing.assert_array_equal(got.final_mode, want.final_mode)
    np.testing.assert_array_equal(got.simultaneous, want.simultaneous)
    finite = np.isfinite(np.asarray(want.event_times))
    np.testing.assert_array_equal(np.isfinite(np.asarray(got.event_times)), finite)
    np.testing.assert_allclose(np.asarray(got.event_times)[finite], np.asarray(want.event_times)[finite],
                               rtol=rtol, atol=atol)
    for field in ("states_before", "states_after", "final_state", "final_time", "zeno_time"):
        a, b = np.asarray(getattr(got, field)), np.asarray(getattr(want, field))
        np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b), err_msg=field)
        np.testing.assert_allclose(a[np.isfinite(a)], b[np.isfinite(b)], rtol=rtol, atol=atol, err_msg=field)
    # The same steps: the same controller rule on the same error estimates (to rounding).
    steps_got, steps_want = np.asarray(got.num_steps), np.asarray(want.num_steps)
    assert np.all(np.abs(steps_got - steps_want) <= np.maximum(2, steps_want // 50))


@pytest.mark.parametrize("name", list(CASES))
def test_batched_engine_agrees_with_per_execution_engine_on_every_example(name):
    system, x0, mode0, t1, args = CASES[name]
    # five executions around the example's initial state (different event times and counts)
    scale = 1.0 + 0.07 * np.arange(5)[:, None]
    X = jnp.asarray(np.asarray(x0) * scale + 0.01 * np.arange(5)[:, None])
    ts = np.linspace(0.0, t1, 7)
    got, want = _both(system, X, mode0, t1, args, saveat=jnp.asarray(ts))
    assert int(np.max(want.num_events)) >= 1
    _assert_same_executions(got, want)
    # A save time that is also an event time, to rounding (the wall particle's fifth execution
    # reaches the wall at t = 1 exactly), may fall on either side of the located event: there
    # each engine saves the state just before or just after it. Elsewhere they agree.
    near = np.abs(ts[None, :, None] - np.asarray(want.event_times)[:, None, :]) <= 1e-9  # (exec, save, event)
    tie = np.any(near, axis=-1)
    np.testing.assert_allclose(np.asarray(got.ys)[~tie], np.asarray(want.ys)[~tie], rtol=1e-8, atol=1e-9)
    np.testing.assert_array_equal(np.asarray(got.saved_modes)[~tie], np.asarray(want.saved_modes)[~tie])
    for i, j in zip(*np.nonzero(tie), strict=True):
        events = np.nonzero(near[i, j])[0]
        allowed = [np.asarray(want.states_before)[i, events], np.asarray(want.states_after)[i, events]]
        for sol in (got, want):
            y = np.asarray(sol.ys)[i, j]
            assert any(np.allclose(y, a[e], rtol=1e-8, atol=1e-9) for a in allowed for e in range(len(events)))


def _chatter():
    a = hj.Mode("A", lambda t, x, p: jnp.zeros_like(x), 1)
    b = hj.Mode("B", lambda t, x, p: jnp.zeros_like(x), 1)
    return hj.HybridSystem([a, b], [hj.Transition("A", "B", guard=lambda t, x, p: x[0] - 1.0),
                                    hj.Transition("B", "A", guard=lambda t, x, p: x[0] - 1.0)])


def _nan_reset():
    return hj.HybridSystem(BALL.modes, [hj.Transition(
        "flight", "flight", guard=lambda t, x, p: x[0],
        reset=lambda t, x, p: jnp.where(t > 0.5, jnp.nan, 1.0) * jnp.array([x[0], -p["e"] * x[1]]))])


STATUS_CASES = {
    # name: (system, x0 rows, mode0, t1, args, extra options, status of every row)
    "zeno": (BALL, [[1.0, 0.0], [0.5, 1.0]], "flight", 20.0, BALL_ARGS, dict(max_epochs=200), "ZENO"),
    "max_epochs": (BALL, [[1.0, 0.0], [0.8, 0.5]], "flight", 5.0, BALL_ARGS, dict(max_epochs=3),
                   "MAX_EPOCHS"),
    "max_steps": (BALL, [[1.0, 0.0], [0.8, 0.5]], "flight", 3.0, BALL_ARGS, dict(max_steps=3), "MAX_STEPS"),
    "blocked": (line_system(domain=lambda t, x, p: 1.0 - x[0]), [[0.25], [0.5]], "m", 2.0, None, {}, "BLOCKED"),
    "chattering": (_chatter(), [[0.5], [0.2]], "A", 1.0, None, {}, "CHATTERING"),
    "nonfinite reset": (_nan_reset(), [[1.0, 0.0], [0.9, 0.1]], "flight", 3.0, BALL_ARGS, {}, "NONFINITE"),
    "nonfinite flow": (hj.HybridSystem(
        [hj.Mode("m", lambda t, x, p: jnp.where(t < 0.5, -jnp.ones_like(x), jnp.nan), 1)],
        [hj.Transition("m", "m", guard=lambda t, x, p: x[0] + 10.0)]), [[1.0], [2.0]], "m", 1.0, None, {},
        "NONFINITE"),
}


@pytest.mark.parametrize("name", list(STATUS_CASES))
def test_batched_engine_stops_with_the_same_status_and_keeps_the_partial_results(name):
    system, rows, mode0, t1, args, kw, status = STATUS_CASES[name]
    got, want = _both(system, jnp.asarray(rows, float), mode0, t1, args, **kw)
    assert list(np.asarray(want.status_name)) == [status] * len(rows)
    # a batch's statuses as integer codes, and compared with a member
    np.testing.assert_array_equal(np.asarray(got.status), [int(getattr(hj.Status, status))] * len(rows))
    assert np.all(np.asarray(got.status == getattr(hj.Status, status)))
    _assert_same_executions(got, want, rtol=1e-7, atol=1e-8)


@pytest.fixture(scope="module")
def ball_batch():
    rng = np.random.default_rng(3)
    N = 64
    x0 = np.stack([rng.uniform(0.5, 1.5, N), rng.uniform(-1, 1, N)], 1)
    run = jax.jit(lambda x0: hj.simulate_batch(BALL, x0, "flight", 0.0, 2.5, BALL_ARGS,
                                               stepsize_controller=TIGHT, max_epochs=32))
    return x0, run(jnp.asarray(x0))


def test_batched_ball_matches_the_closed_form(ball_batch):
    x0, sol = ball_batch
    for i in range(x0.shape[0]):
        ref = examples.bouncing_ball_closed_form(x0[i, 0], x0[i, 1], 9.8, 0.8, 2.5)
        n = len(ref["event_times"])
        assert int(sol.num_events[i]) == n
        np.testing.assert_allclose(sol.event_times[i, :n], ref["event_times"], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(sol.final_state[i], ref["final_state"], atol=1e-8)
    assert list(np.unique(np.asarray(sol.status_name))) == ["T1_REACHED"]
    # the batch is a Solution like vmap's: index it, read one execution's time domain
    one = sol[5]
    assert len(one.hybrid_time_domain()) == int(one.num_events) + 1


def test_default_lanes_one_per_execution_up_to_the_cap_then_refilled():
    # The documented default (docs: Batches, "Lanes"): one lane per execution up to 200,000
    # executions per device (20,000 for a differentiated call), else 10,000 lanes refilled.
    from hybridjax._engines.lanes import default_lanes

    assert [default_lanes(n, False) for n in (1, 40_000, 200_000, 200_001, 10**6)] == [
        1, 40_000, 200_000, 10_000, 10_000]
    assert [default_lanes(n, True) for n in (1, 20_000, 20_001, 10**6)] == [1, 20_000, 10_000, 10_000]


def test_batched_args_and_per_execution_times():
    # execution i: its own restitution, start and end time; compared with simulate one by one
    x0 = jnp.array([[1.0, 0.0], [0.7, 0.4], [1.2, -0.5]])
    args = {"g": jnp.array([9.8, 9.8, 3.7]), "e": jnp.array([0.8, 0.5, 0.9])}
    t0, t1 = jnp.array([0.0, 0.2, -0.1]), jnp.array([2.0, 1.5, 3.0])
    got = hj.simulate_batch(BALL, x0, "flight", t0, t1, args, args_batched=True, stepsize_controller=TIGHT,
                            block=1)
    for i in range(3):
        a = {k: v[i] for k, v in args.items()}
        one = hj.simulate(BALL, x0[i], "flight", t0[i], t1[i], a, stepsize_controller=TIGHT)
        assert int(got.num_events[i]) == int(one.num_events)
        n = int(one.num_events)
        np.testing.assert_allclose(got.event_times[i, :n], one.event_times[:n], rtol=1e-9)
        np.testing.assert_allclose(got.final_state[i], one.final_state, rtol=1e-8, atol=1e-9)
        assert got.status_name[i] == one.status_name  # execution 1 (e = 0.5) is Zeno before t1
        np.testing.assert_allclose(got.final_time[i], one.final_time, rtol=1e-9)
    assert list(got.status_name) == ["T1_REACHED", "ZENO", "T1_REACHED"]


# Seven balls with their own args, start and end times (execution 2 is Zeno), and save times.
SEVEN = (jnp.array([[1.0, 0.0], [0.7, 0.4], [1.2, -0.5], [0.5, 0.9], [1.4, 0.1], [0.9, -0.8], [0.6, 0.0]]),
         "flight", jnp.array([0.0, 0.2, -0.1, 0.0, 0.5, 0.0, 0.0]), jnp.array([2.0, 0.4, 3.0, 2.5, 1.0, 2.0, 1.5]),
         {"g": jnp.array([9.8, 9.8, 9.8, 3.7, 9.8, 1.6, 9.8]), "e": jnp.array([0.8, 0.7, 0.5, 0.9, 0.8, 0.6, 0.8])})
SEVEN_KW = dict(args_batched=True, stepsize_controller=TIGHT, saveat=jnp.linspace(0.0, 2.0, 9))


@functools.lru_cache(maxsize=1)
def _seven_by_vmap():
    want = hj.simulate_batch(BALL, *SEVEN, engine="vmap", **SEVEN_KW)
    assert "ZENO" in list(want.status_name) and int(np.min(want.num_events)) < int(np.max(want.num_events))
    return want


def _assert_same_as_seven_by_vmap(got):
    want = _seven_by_vmap()
    _assert_same_executions(got, want)
    np.testing.assert_allclose(got.ys, want.ys, rtol=1e-8, atol=1e-9)
    np.testing.assert_array_equal(got.saved_modes, want.saved_modes)


def test_lanes_fewer_than_executions_take_the_next_execution_when_one_ends():
    # 7 executions on 2 lanes: each lane runs several in turn, with its own args, start and end
    # times, save times and final status; held to vmap(simulate) (the gradient through lane
    # refills: test_batched_reverse_mode_gradients_match_per_execution_engine)
    _assert_same_as_seven_by_vmap(hj.simulate_batch(BALL, *SEVEN, lanes=2, block=1, engine="batched", **SEVEN_KW))


def test_two_block_sizes_run_the_same_executions():
    # block=(1, 3): the rare work on a block of one where at most one execution needs it, else
    # in passes over blocks of three; held to vmap(simulate)
    _assert_same_as_seven_by_vmap(hj.simulate_batch(BALL, *SEVEN, block=(1, 3), engine="batched", **SEVEN_KW))


@pytest.mark.parametrize("block", [0, -2, 2.5, True, (3, 2), (2, 2), (2,), (0, None), [1, 3]])
def test_bad_block_sizes_are_refused(block):
    with pytest.raises(ValueError, match="block must be"):
        hj.simulate_batch(BALL, SEVEN[0], "flight", 0.0, 1.0, BALL_ARGS, block=block)


def test_derivatives_are_seen_through_other_transformations():
    # The default block under differentiation (all lanes) depends on this; the truth is which
    # transformation is applied.
    seen = []

    def f(x):
        seen.append(carries_derivatives({"x": x}))
        return jnp.sum(x ** 2)

    x, xs = jnp.ones(3), jnp.ones((2, 3))
    jax.grad(f)(x)
    jax.jit(jax.grad(f))(x)
    jax.vmap(jax.grad(f))(xs)
    jax.grad(lambda x: jnp.sum(jax.vmap(f)(x)))(xs)
    jax.jvp(f, (x,), (x,))
    jax.jacrev(f)(x)
    assert seen == [True] * 6
    seen.clear()
    f(x)
    jax.jit(f)(x)
    jax.vmap(f)(xs)
    jax.grad(lambda y: f(x) * y)(2.0)  # differentiated, but not with respect to x
    assert seen == [False] * 4


def test_batched_modes_of_different_dimensions_per_execution():
    # the wall particle starts in "flight" (4-D) in one execution and in "slide" (2-D) in another
    x0 = jnp.array([[0.0, 1.0, 1.5, 3.0], [0.5, 0.2, 0.0, 0.0]])
    mode0 = jnp.array([WALL.mode_index("flight"), WALL.mode_index("slide")])
    got, want = _both(WALL, x0, mode0, 3.0, {"g": 9.8, "w": 2.0, "c": 0.7})
    _assert_same_executions(got, want)


def _final_heights(engine, adjoint):
    def f(x0):
        return hj.simulate_batch(BALL, x0, "flight", 0.0, 2.0, BALL_ARGS, stepsize_controller=TIGHT, block=1,
                                 engine=engine, adjoint=adjoint).final_state[:, 0]

    return f


# Three executions on two lanes (one lane refill), a gathered block of one, saves on both sides of
# bounces: one reverse-mode program per engine serves every gradient test below. Its output is a
# vector of losses, each a different part of the solution, and the test of each part pulls back
# its own unit cotangent through the one compiled VJP.
GRAD_X0 = jnp.array([[1.0, 0.0], [0.7, 0.4], [1.2, -0.5]])
LOSS_PARTS = ("final heights", "saved states", "event times and post-event states")


def _losses(x, engine, **options):
    s = hj.simulate_batch(BALL, x, "flight", 0.0, 2.0, BALL_ARGS, saveat=jnp.linspace(0.0, 2.0, 60),
                          stepsize_controller=TIGHT, max_epochs=16, engine=engine, **options)
    # event times weighted by their index, so that a record written in the wrong slot shows
    times = jnp.where(jnp.isfinite(s.event_times), s.event_times, 0.0) * jnp.arange(1.0, 17.0)[None]
    after = jnp.where(jnp.isfinite(s.states_after), s.states_after, 0.0)
    return jnp.stack([jnp.sum(s.final_state[:, 0]), jnp.sum(s.ys[:, 37:45]), jnp.sum(times) + jnp.sum(after)])


@functools.cache
def _loss_pullback(engine):
    options = dict(block=1, lanes=2) if engine == "batched" else {}
    return jax.jit(lambda x, ct: jax.vjp(lambda v: _losses(v, engine, **options), x)[1](ct)[0])


def _loss_gradient(engine, part):
    return _loss_pullback(engine)(GRAD_X0, jnp.eye(len(LOSS_PARTS))[LOSS_PARTS.index(part)])


@pytest.mark.parametrize("part", LOSS_PARTS)
def test_batched_reverse_mode_gradients_match_per_execution_engine(part):
    # the record is written in place (loop buffers kept out of the checkpoints), the saves through
    # the nested loop that writes them, all through the lane refill and the gathered block
    want = np.asarray(_loss_gradient("vmap", part))
    assert np.all(want != 0.0)  # every execution's part depends on its initial state
    np.testing.assert_allclose(_loss_gradient("batched", part), want, rtol=1e-7, atol=1e-9)


def test_batched_gradients_reverse_forward_and_finite_differences_agree():
    # each final height depends on its own initial state only: d sum / d x0 is the per-row gradient
    g_rev = _loss_gradient("batched", "final heights")
    heights = jax.jit(_final_heights("batched", diffrax.ForwardMode()))  # one compile for every call
    J = jax.jit(jax.jacfwd(lambda v: heights(v.reshape(GRAD_X0.shape))))(GRAD_X0.reshape(-1))
    rows = jnp.arange(GRAD_X0.shape[0])
    np.testing.assert_allclose(J.reshape(GRAD_X0.shape[0], *GRAD_X0.shape)[rows, rows], g_rev, rtol=1e-7, atol=1e-9)
    # Step 1e-5, not sqrt(eps): the heights carry ~1e-12 of solver and rounding noise (at
    # rtol 1e-10), which a 1.5e-8 step turns into ~1e-4 of derivative noise; at 1e-5 the noise is
    # ~1e-7 and the truncation error ~h^2 = 1e-10.
    fd = central_difference(lambda v: np.asarray(heights(jnp.asarray(v).reshape(GRAD_X0.shape))),
                            np.asarray(GRAD_X0).reshape(-1), eps=1e-5)
    np.testing.assert_allclose(np.asarray(J), fd, rtol=1e-5, atol=1e-6)


def test_batched_engine_in_float32_matches_the_closed_form():
    x0 = np.array([[1.0, 0.0], [0.6, 0.8]], np.float32)
    sol = hj.simulate_batch(BALL, jnp.asarray(x0), "flight", 0.0, 2.0, BALL_ARGS, engine="batched",
                            stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6))
    assert sol.final_state.dtype == jnp.float32
    for i in range(2):
        ref = examples.bouncing_ball_closed_form(float(x0[i, 0]), float(x0[i, 1]), 9.8, 0.8, 2.0)
        assert int(sol.num_events[i]) == len(ref["event_times"])
        np.testing.assert_allclose(sol.final_state[i], ref["final_state"], atol=2e-4)


@pytest.mark.parametrize("solver", [diffrax.Heun(), diffrax.Midpoint(), diffrax.Ralston(), diffrax.Bosh3(),
                                    diffrax.Tsit5(), diffrax.Dopri5(), diffrax.Dopri8()],
                         ids=lambda s: type(s).__name__)
def test_chebyshev_form_of_the_dense_output_equals_diffrax_interpolation(solver):
    # Random stages (diffrax's k_i: the field's increments over the step), and y1 the step's own
    # end, y0 + sum_i b_i k_i.
    rng = np.random.default_rng(4)
    tableau = type(solver).tableau
    s = len(tableau.c) + 1
    y0, k = jnp.asarray(rng.normal(size=3)), jnp.asarray(rng.normal(size=(s, 3)))
    t0, t1 = 0.7, 0.95
    y1 = y0 + jnp.asarray(tableau.b_sol) @ k
    A = chebyshev_weights(solver.interpolation_cls, s, jnp.float64)
    ours = ChebyshevDense.from_stages(A, t0, t1, y0, y1, k)
    ref = solver.interpolation_cls(t0=t0, t1=t1, y0=y0, y1=y1, k=k)
    # The form meets y0 + (y1 - y0) at the step's end; diffrax's interpolant ends at
    # y0 + sum_i b_i(1) k_i, which is y1 to rounding, but ~1e-12 away for Dopri8 (its
    # interpolation's coefficients are decimals to about that precision): the difference is
    # that miss, spread linearly.
    miss = y1 - ref.evaluate(t1)
    assert np.max(np.abs(miss)) < (2e-12 if isinstance(solver, diffrax.Dopri8) else 1e-14)
    for t in np.linspace(t0, t1, 11):
        want = ref.evaluate(t) + (t - t0) / (t1 - t0) * miss
        np.testing.assert_allclose(ours.evaluate(t), want, rtol=1e-12, atol=1e-13)
    assert np.array_equal(ours.evaluate(t0), y0)  # exact at the step's start


@pytest.mark.parametrize("solver, dtype", [(diffrax.Bosh3(), "float64"), (diffrax.Tsit5(), "float64"),
                                           (diffrax.Dopri8(), "float64"), (diffrax.Tsit5(), "float32")],
                         ids=lambda p: p if isinstance(p, str) else type(p).__name__)
def test_dense_weights_give_diffrax_interpolation_and_its_slope(solver, dtype):
    # y(theta) = a y0 + b y1 + sum_i c_i k_i at fixed fractions, against diffrax's interpolation
    # on [t0, t1] itself (float64), and the slope against its central differences (per unit theta).
    rng = np.random.default_rng(5)
    s = len(type(solver).tableau.c) + 1
    y0, y1, k = rng.normal(size=2), rng.normal(size=2), rng.normal(size=(s, 2))
    t0, t1 = 0.3, 0.8
    ref = solver.interpolation_cls(t0=t0, t1=t1, y0=jnp.asarray(y0), y1=jnp.asarray(y1), k=jnp.asarray(k))
    thetas = np.array([0.0, 0.2, 0.5, 0.9, 1.0])
    value, slope = dense_weights(solver.interpolation_cls, s, thetas, jnp.dtype(dtype))
    tol = 1e-13 if dtype == "float64" else 1e-5
    h, d = t1 - t0, 1e-6
    for th, (a, b, c), (da, db, dc) in zip(thetas, value, slope, strict=True):
        t = t0 + th * h
        np.testing.assert_allclose(a * y0 + b * y1 + np.asarray(c) @ k, ref.evaluate(t), rtol=tol, atol=tol)
        fd = (np.asarray(ref.evaluate(t + d)) - np.asarray(ref.evaluate(t - d))) / (2 * d) * h
        np.testing.assert_allclose(da * y0 + db * y1 + np.asarray(dc) @ k, fd, rtol=max(tol, 1e-7),
                                   atol=max(tol, 1e-7))


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_dense_weights_evaluated_by_numpy_equal_the_compiled_interpolation(dtype):
    # The weights come from the interpolation's program evaluated by numpy (`_numpy_weights`);
    # XLA's compilation of the same program (`_dense_weights_fn`, the fallback) is a second
    # evaluation: equal to rounding, for solvers whose programs use powers, scans, stacks and
    # matrix products.
    thetas = tuple(np.linspace(0.0, 1.0, 7))
    for solver in (diffrax.Tsit5(), diffrax.Dopri5(), diffrax.Dopri8(), diffrax.Bosh3(), diffrax.Kvaerno5()):
        s = len(type(solver).tableau.c) + 1
        ours = _numpy_weights(solver.interpolation_cls, s, thetas, jnp.dtype(dtype))
        padded = np.zeros(16, dtype)
        padded[:7] = thetas
        xla = _dense_weights_fn(solver.interpolation_cls, s, 16, jnp.dtype(dtype))(padded)
        for got, want in zip(ours, xla, strict=True):
            want = np.asarray(want)[:7]
            scale = 32 * np.finfo(dtype).eps * np.max(np.abs(want))
            np.testing.assert_allclose(got, want, rtol=0, atol=scale, err_msg=type(solver).__name__)


class _Interpolant(eqx.Module):
    # the fields diffrax's interpolations take; a subclass gives `evaluate`
    t0: jax.Array
    t1: jax.Array
    y0: jax.Array
    y1: jax.Array
    k: jax.Array


class _CumsumLine(_Interpolant):
    # y0 + theta (y1 - y0), its fraction computed by a cumulative sum (a primitive the numpy
    # evaluation does not know)
    def evaluate(self, t):
        theta = jnp.cumsum(jnp.stack([(t - self.t0) / (self.t1 - self.t0), 0 * t]))[-1]
        return self.y0 + theta * (self.y1 - self.y0)


def test_dense_weights_of_a_program_numpy_cannot_evaluate_are_compiled():
    with pytest.raises(_NotInNumpy, match="cumsum"):
        _numpy_weights(_CumsumLine, 1, (0.5,), jnp.dtype("float64"))
    value, slope = dense_weights(_CumsumLine, 1, [0.0, 0.25, 1.0], jnp.float64)
    for th, (a, b, c), (da, db, dc) in zip((0.0, 0.25, 1.0), value, slope, strict=True):
        np.testing.assert_allclose([a, b, *c], [1 - th, th, 0.0], atol=1e-15)
        np.testing.assert_allclose([da, db, *dc], [-1.0, 1.0, 0.0], atol=1e-15)


class _StartsOff(_Interpolant):
    # an interpolant that does not start at y0: y0 + k_0 + theta (y1 - y0)
    def evaluate(self, t):
        return self.y0 + self.k[0] + (t - self.t0) / (self.t1 - self.t0) * (self.y1 - self.y0)


def test_an_interpolant_that_misses_the_steps_start_is_named():
    with pytest.raises(ValueError, match="_StartsOff: its dense output does not meet the step's ends"):
        chebyshev_weights(_StartsOff, 2, jnp.float64)


def test_dense_output_rounds_at_the_scale_of_the_change_since_the_start():
    # One Tsit5 step of a ball thrown up from 0.3 and caught 900 s later (peak 1e6): the step
    # reproduces the parabola, so the dense output's increment from the start is
    # v0 s - g s^2 / 2. Near the start the form rounds at the scale of the state and of the
    # change since the start (theta times the step's change), where a Chebyshev series of y
    # itself would round at the peak's scale, 1e6 * 1e-16.
    G, T = 9.8, 900.0
    term = diffrax.ODETerm(lambda t, y, a: jnp.stack([y[1], -G + 0 * y[0]]))
    solver = diffrax.Tsit5()
    t0, t1, y0 = 0.0, T, jnp.array([0.3, G * T / 2 + 1e-3])
    y1, _, dense, _, _ = solver.step(term, t0, t1, y0, None, solver.init(term, t0, t1, y0, None), made_jump=False)
    ours = ChebyshevDense.from_stages(chebyshev_weights(solver.interpolation_cls, dense["k"].shape[0], jnp.float64),
                                      t0, t1, y0, y1, dense["k"])
    eps = np.finfo(np.float64).eps
    v = float(y0[1])
    for s in (1e-9, 1e-6, 1e-3, 0.1):
        increment = v * s - 0.5 * G * s * s
        scale = float(y0[0]) + s / T * abs(float(ours.dy[0])) + abs(v * s)
        assert abs(float(ours.evaluate(t0 + s)[0] - y0[0]) - increment) <= 64 * eps * scale, s


# a few save times per step, more than SAVE_WINDOW (16) per step, and unsorted
@pytest.mark.parametrize("num_saves, order", [(400, "sorted"), (30, "shuffled")])
def test_batched_saved_states_match_free_flight_and_bounces(num_saves, order):
    ts = np.linspace(0.0, 2.0, num_saves)
    if order == "shuffled":
        ts = np.random.default_rng(2).permutation(ts)
    x0 = np.array([[1.0, 0.0], [0.6, 0.5], [1.3, -0.4]])
    sol = hj.simulate_batch(BALL, jnp.asarray(x0), "flight", 0.0, 2.0, BALL_ARGS, stepsize_controller=TIGHT,
                            saveat=diffrax.SaveAt(ts=jnp.asarray(ts), t1=True), engine="batched", block=1)
    for i in range(3):  # the closed form between impacts, at every save time
        ref = examples.bouncing_ball_closed_form(x0[i, 0], x0[i, 1], 9.8, 0.8, 2.0)
        starts = np.concatenate([[0.0], ref["event_times"]])
        h = np.concatenate([[x0[i, 0]], np.zeros(len(ref["event_times"]))])
        v = np.concatenate([[x0[i, 1]], ref["post_velocities"]])
        for k, s in enumerate(np.append(ts, 2.0)):
            e = np.searchsorted(starts, s, side="left") - 1 if s > 0 else 0  # pre-event state at an impact
            dt = s - starts[e]
            np.testing.assert_allclose(sol.ys[i, k], [h[e] + v[e] * dt - 4.9 * dt * dt, v[e] - 9.8 * dt],
                                       atol=1e-8)
    assert np.all(np.asarray(sol.saved_modes) == 0)


@pytest.mark.parametrize("engine", ["batched", "vmap"])
def test_save_times_within_ulps_of_an_event_are_written(engine):
    # Save times at each of the engine's own event times and its neighbours, -3 ... +3 ulps (the
    # located time and the reported one, moved onto the guard, can differ by ulps): each is
    # written, with the pre-event state up to the event time and the post-event state after it.
    x0 = np.array([1.0, 0.0])

    def run(ts):
        return hj.simulate_batch(BALL, jnp.asarray(x0[None]), "flight", 0.0, 2.0, BALL_ARGS, block=1,
                                 stepsize_controller=TIGHT, saveat=jnp.asarray(ts), engine=engine)

    events = np.asarray(run(np.linspace(0.0, 2.0, 24)).event_times[0])
    events = events[np.isfinite(events)]
    assert len(events) == 3
    near = []
    for e in events:
        below = above = e
        for _ in range(3):
            below, above = np.nextafter(below, -np.inf), np.nextafter(above, np.inf)
            near += [below, above]
        near.append(e)
    ts = np.sort(np.concatenate([near, np.linspace(0.1, 1.9, 24 - len(near))]))
    sol = run(ts)
    np.testing.assert_array_equal(sol.event_times[0, :3], events)  # the same steps with these saves
    ref = examples.bouncing_ball_closed_form(x0[0], x0[1], 9.8, 0.8, 2.0)
    h = np.concatenate([[x0[0]], np.zeros(3)])
    v = np.concatenate([[x0[1]], ref["post_velocities"][:3]])
    starts = np.concatenate([[0.0], events])
    for k, s in enumerate(ts):
        e = np.searchsorted(events, s, side="left")  # the epoch: up to its event time, inclusive
        dt = s - starts[e]
        np.testing.assert_allclose(sol.ys[0, k], [h[e] + v[e] * dt - 4.9 * dt * dt, v[e] - 9.8 * dt], atol=1e-8,
                                   err_msg=f"save {k} at {s!r}")


def test_engine_choice_and_errors():
    x0 = jnp.array([[1.0, 0.0], [0.5, 0.0]])
    # a solver the batched engine neither unrolls nor steps itself, a controller other than
    # diffrax's PIDController with the rms norm
    with pytest.raises(ValueError, match="ReversibleHeun"):
        hj.simulate_batch(BALL, x0, "flight", 0.0, 1.0, BALL_ARGS, solver=diffrax.ReversibleHeun(), engine="batched")
    with pytest.raises(ValueError, match="PIDController"):
        hj.simulate_batch(BALL, x0, "flight", 0.0, 1.0, BALL_ARGS, stepsize_controller=diffrax.ConstantStepSize(),
                          dt0=0.01, engine="batched")
    with pytest.raises(ValueError, match="lanes must be a positive integer"):
        hj.simulate_batch(BALL, x0, "flight", 0.0, 1.0, BALL_ARGS, lanes=0)
    with pytest.raises(ValueError, match="engine must be"):
        hj.simulate_batch(BALL, x0, "flight", 0.0, 1.0, BALL_ARGS, engine="turbo")
    with pytest.raises(ValueError, match=r"\(N, dim\)"):
        hj.simulate_batch(BALL, x0[0], "flight", 0.0, 1.0, BALL_ARGS)
    with pytest.raises(ValueError, match="no rows"):
        hj.simulate_batch(BALL, x0[:0], "flight", 0.0, 1.0, BALL_ARGS)
    with pytest.raises(ValueError, match="leading axis of 2"):
        hj.simulate_batch(BALL, x0, "flight", 0.0, 1.0, {"g": jnp.ones(3), "e": jnp.ones(3)}, args_batched=True)
    with pytest.raises(ValueError, match="has dim 2"):
        hj.simulate_batch(BALL, jnp.ones((2, 3)), "flight", 0.0, 1.0, BALL_ARGS)
    # "auto" falls back to vmap(simulate) where the batched engine does not apply (Tsit5 is
    # exact on the quadratic flight, whatever its step size)
    sol = hj.simulate_batch(BALL, x0, "flight", 0.0, 0.2, BALL_ARGS, saveat=jnp.array([0.1, 0.2]),
                            stepsize_controller=diffrax.ConstantStepSize(), dt0=0.05)
    np.testing.assert_allclose(sol.ys[:, 1, 0], np.asarray(x0[:, 0]) - 0.5 * 9.8 * 0.2**2, rtol=1e-8)


@pytest.mark.parametrize("frac", [0.0, 0.05, 0.5, 1.0])
def test_block_compaction_equals_nonzero(frac):
    # The event block's lane indices (`first_lanes`: a prefix count and a scatter) against
    # jnp.nonzero with a fixed size, and the prefix count against cumsum: fewer lanes than the
    # block (padding with N), more (the first ones kept), none and all. The passes over blocks
    # slice one compaction padded to whole blocks (`on_block`): pass p's block is nonzero's
    # indices from the (p * block)-th on, padded with N.
    mask = jnp.asarray(np.random.default_rng(int(100 * frac)).random(1000) < frac)
    count = running_count(mask)
    np.testing.assert_array_equal(count, np.cumsum(np.asarray(mask)))
    lanes = np.concatenate([np.nonzero(np.asarray(mask))[0], np.full(2000, 1000)])
    for size in (1, 37, 250, 1000):
        np.testing.assert_array_equal(first_lanes(mask, size), jnp.nonzero(mask, size=size, fill_value=1000)[0])
        most = -(-1000 // size)
        order = first_lanes(mask, most * size, count)
        for p in sorted({p for p in (0, 1, most // 2, most - 1) if p < most}):
            np.testing.assert_array_equal(lax.dynamic_slice(order, (jnp.int32(p * size),), (size,)),
                                          lanes[p * size:(p + 1) * size])


def test_slot_guards_are_each_modes_own_watched_values():
    # `slot_guards` (the guard samples' slots, assembled function by function) against the
    # thermostat's guards and domain components evaluated one by one from their definitions:
    # slot s of mode m holds m's s-th own watched function, the unused slots read 1.
    kern = Kernels(THERMO, THERMO_ARGS)
    rng = np.random.default_rng(3)
    for mode in range(THERMO.num_modes):
        for _ in range(3):
            t, y = jnp.asarray(rng.uniform(0, 10)), jnp.asarray(rng.uniform(10, 30, 1))
            own = [fn(t, y, THERMO_ARGS) for src, fn in kern.watch if src == mode]
            expected = [float(v) for v in own] + [1.0] * (kern.num_slots - len(own))
            np.testing.assert_allclose(kern.slot_guards(jnp.int32(mode), t, y, THERMO_ARGS), expected, rtol=1e-15)
            np.testing.assert_allclose(kern.slot_guards(jnp.int32(mode), t, y, THERMO_ARGS),
                                       kern.to_slots(jnp.int32(mode), kern.guards(jnp.int32(mode), t, y, THERMO_ARGS)),
                                       rtol=0, atol=0)


def test_watched_function_slots_hold_each_modes_own_in_order():
    # The batched engine samples guards by slot: slot s of mode m is m's s-th own watched
    # function (guards by transition index, then domain components). The thermostat watches
    # 8 functions (4 guards, 4 domain components: off has 2 + 2, heat and cool 1 + 1 each).
    kern = Kernels(THERMO, THERMO_ARGS)
    assert kern.num_watch == 8 and kern.num_slots == 4
    values = jnp.arange(1.0, 9.0)  # watched function w reads w + 1
    expected = {0: [], 1: [], 2: []}
    for w, (src, _) in enumerate(kern.watch):
        expected[src].append(w + 1.0)
    for mode, own in expected.items():
        slots = kern.to_slots(jnp.int32(mode), values, fill=-7.0)
        np.testing.assert_array_equal(slots, own + [-7.0] * (4 - len(own)))
        # and back: the event search's slot s of mode m is watched function slot_watch[m, s]
        np.testing.assert_array_equal(values[kern.slot_watch[mode, :len(own)]], own)
