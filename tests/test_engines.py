"""The fast engine (unrolled explicit RK step, written-out I controller) against diffrax's own.

Truths: diffrax's `solver.step` and `PIDController.adapt_step_size` for the pieces, and the
diffrax engine (itself tested against closed forms throughout the suite) for whole runs.
"""

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj
from hybridjax import examples
from hybridjax._step.runge_kutta import (
    FastIController,
    UnrolledERK,
    fold,
    inverse_root,
    unrolled_rms_norm,
    unrolled_sum,
)

from helpers import BALL, BALL_ARGS, CEILING, THERMO, TIGHT, WALL

SOLVERS = [diffrax.Heun(), diffrax.Midpoint(), diffrax.Ralston(), diffrax.Bosh3(),
           diffrax.Tsit5(), diffrax.Dopri5(), diffrax.Dopri8()]


def _terms():
    # A nonlinear, time-dependent field so that every stage's c_i and a_ij matter.
    return diffrax.ODETerm(lambda t, y, a: jnp.stack([y[1] * jnp.cos(t), -a * jnp.sin(y[0]) + t * y[1]]))


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: type(s).__name__)
def test_unrolled_step_equals_diffrax_step(solver):
    terms, fast = _terms(), UnrolledERK(solver)
    y0, t0, t1, a = jnp.array([0.3, -1.2]), 0.4, 0.47, 2.0
    for made_jump in (True, False):
        state = solver.init(terms, t0, t1, y0, a)
        if state is not None:  # FSAL: a stored last stage that a jump must not reuse
            state = (state[0], terms.vf(t0, y0, a) if not made_jump else 1e3 + state[1])
        want = solver.step(terms, t0, t1, y0, a, state, jnp.array(made_jump))
        got = fast.step(terms, t0, t1, y0, a, state, jnp.array(made_jump))
        for w, g in zip(want[:2], got[:2], strict=True):  # y1, error estimate
            np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(got[2]["k"], want[2]["k"], rtol=1e-13, atol=1e-15)
        if state is not None:
            np.testing.assert_allclose(got[3][1], want[3][1], rtol=1e-13, atol=1e-15)
    # Its dense output is diffrax's interpolation of the same stages.
    assert fast.interpolation_cls == solver.interpolation_cls


def test_fast_controller_equals_diffrax_pid_controller():
    rng = np.random.default_rng(1)
    pid = diffrax.PIDController(rtol=1e-7, atol=1e-9)
    fast = FastIController(pid)
    state = pid.init(_terms(), 0.0, 1.0, jnp.ones(2), 0.1, 1.0, None, 5)[1]
    for _ in range(200):
        y0, y1 = rng.normal(size=2), rng.normal(size=2)
        err = rng.normal(size=2) * 10.0 ** rng.uniform(-12, -5)
        t0, h = rng.uniform(0, 10), 10.0 ** rng.uniform(-6, 0)
        want = pid.adapt_step_size(t0, t0 + h, y0, y1, None, err, 5, state)
        got = fast.adapt_step_size(t0, t0 + h, jnp.asarray(y0), jnp.asarray(y1), None, jnp.asarray(err),
                                   5, state)
        assert bool(got[0]) == bool(want[0])
        np.testing.assert_allclose(got[1:3], want[1:3], rtol=1e-14)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32], ids=["float64", "float32"])
def test_inverse_root_is_the_correctly_rounded_power(dtype):
    # e^(-1/q) by Newton's method from the exponent bits, against an extended-precision power
    # (np.longdouble; float64's own pow with the rounded exponent 1/q is ~|ln e| ulps off)
    rng = np.random.default_rng(3)
    lim = 12 if dtype == jnp.float64 else 6
    e = (10.0 ** rng.uniform(-lim, lim, 20_000)).astype(dtype)
    eps = np.finfo(dtype).eps
    for q in (2, 3, 4, 5, 6, 8, 9):
        got = np.asarray(jax.jit(lambda x, q=q: inverse_root(x, q))(jnp.asarray(e)), np.longdouble)
        want = (1 / e.astype(np.longdouble)) ** (np.longdouble(1) / q)
        assert np.max(np.abs(got / want - 1)) <= 4 * eps, q
    special = jnp.asarray([0.0, np.inf, np.nan, 1.0], dtype)
    np.testing.assert_array_equal(np.asarray(inverse_root(special, 5)), [np.inf, 0.0, np.nan, 1.0])
    # a non-integer order falls back to the power itself
    np.testing.assert_allclose(inverse_root(jnp.asarray(4.0, dtype), 2.5), 4.0 ** -0.4, rtol=4 * eps)


def test_fast_controller_initial_step_equals_diffrax():
    # Hairer's first step with the rms norm written out (`unrolled_rms_norm`): the same step
    # as diffrax's own, up to the order of rounding, over states of 1 to 9 components.
    rng = np.random.default_rng(2)
    for n in (1, 2, 5, 9):
        terms = diffrax.ODETerm(lambda t, y, a: -a * y * jnp.cos(t) + jnp.roll(y, 1))
        pid = diffrax.PIDController(rtol=1e-8, atol=1e-10)
        for _ in range(5):
            y0 = jnp.asarray(rng.normal(size=n) * 10.0 ** rng.uniform(-3, 3))
            t0, a = rng.uniform(0, 5), rng.uniform(0.1, 10)
            want = pid.init(terms, t0, t0 + 10, y0, None, a, diffrax.Tsit5().func, 5)[0]
            got = FastIController(pid).init(terms, t0, t0 + 10, y0, None, a, diffrax.Tsit5().func, 5)[0]
            np.testing.assert_allclose(got - t0, want - t0, rtol=1e-13)


@pytest.mark.parametrize("n", [1, 3, 64, 65, 200])
def test_written_out_reductions_equal_jnp(n):
    x = jnp.asarray(np.random.default_rng(n).normal(size=(n, 4)))
    np.testing.assert_allclose(fold(jnp.add, x), jnp.sum(x, axis=0), rtol=1e-13)
    np.testing.assert_array_equal(fold(jnp.minimum, x), jnp.min(x, axis=0))
    np.testing.assert_array_equal(fold(jnp.logical_or, x > 1.5), jnp.any(x > 1.5, axis=0))
    np.testing.assert_array_equal(fold(jnp.logical_and, x > -1.5), jnp.all(x > -1.5, axis=0))
    np.testing.assert_allclose(unrolled_sum(x[:, 0]), np.sum(np.asarray(x[:, 0])), rtol=1e-13)
    np.testing.assert_allclose(unrolled_rms_norm(x), np.sqrt(np.mean(np.asarray(x) ** 2)), rtol=1e-14)
    assert float(unrolled_sum(jnp.zeros((0,)))) == 0.0 and float(unrolled_rms_norm(jnp.zeros((0,)))) == 0.0


def _pair(system, x0, mode0, t1, args, **kw):
    run = lambda engine: hj.simulate(system, x0, mode0, 0.0, t1, args, engine=engine, **kw)  # noqa: E731
    return run("fast"), run("diffrax")


CASES = {
    "bouncing ball": (BALL, [1.0, 0.3], "flight", 3.0, BALL_ARGS),
    "thermostat": (THERMO, [19.0], "off", 40.0, dict(a=0.1, T_amb=5.0, P_heat=2.5, P_cool=2.0, s=20.0)),
    "wall particle": (WALL, [0.0, 1.0, 1.5, 3.0], "flight", 3.0, {"g": 9.8, "w": 2.0, "c": 0.7}),
    "ceiling ball": (CEILING, [0.0, 7.0], "flight", 1.0, {"g": 9.8, "H": 2.0}),
    "rimless wheel": (examples.rimless_wheel(), [0.1, 0.6], 0, 4.0, {"alpha": 0.3, "gamma": 0.08}),
    "pendulum wall": (examples.pendulum_wall(), [-0.5, 0.8], "swing", 9.0, {"theta_w": 0.2, "e": 0.7}),
    "truncated ball": (examples.truncated_ball(), [1.0, 0.0], "flight", 4.0,
                       {"g": 9.8, "e": 1 / math.sqrt(2), "v_min": 0.05}),
    "van der pol relay": (examples.van_der_pol_relay(), [-1.0, 0.5], 0, 10.0, 5.0),
    "stiff relay, mild": (examples.stiff_relay(), [0.0, 0.0], 0, 5.0, 20.0),
}


@pytest.mark.parametrize("name", list(CASES))
def test_fast_engine_agrees_with_diffrax_engine_on_every_example(name):
    system, x0, mode0, t1, args = CASES[name]
    fast, ref = _pair(system, jnp.asarray(x0), mode0, t1, args, stepsize_controller=TIGHT,
                      saveat=jnp.linspace(0.0, t1, 7))
    assert fast.status == ref.status
    n = int(ref.num_events)
    assert n >= 1 and int(fast.num_events) == n
    np.testing.assert_array_equal(fast.transitions, ref.transitions)
    np.testing.assert_allclose(fast.event_times[:n], ref.event_times[:n], rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(fast.final_state, ref.final_state, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(fast.ys, ref.ys, rtol=1e-8, atol=1e-9)
    # the same steps: the same controller rule on the same error estimates (to rounding)
    assert abs(int(fast.num_steps) - int(ref.num_steps)) <= max(2, int(ref.num_steps) // 50)


@pytest.mark.parametrize("solver", [diffrax.Bosh3(), diffrax.Dopri5(), diffrax.Dopri8()],
                         ids=lambda s: type(s).__name__)
def test_fast_engine_with_other_tableaus_matches_the_closed_form(solver):
    ref = examples.bouncing_ball_closed_form(1.0, 0.3, 9.8, 0.8, 3.0)
    sol = hj.simulate(BALL, jnp.array([1.0, 0.3]), "flight", 0.0, 3.0, BALL_ARGS, solver=solver,
                      stepsize_controller=TIGHT, engine="fast")
    n = len(ref["event_times"])
    assert int(sol.num_events) == n
    np.testing.assert_allclose(sol.event_times[:n], ref["event_times"], atol=1e-8)
    np.testing.assert_allclose(sol.final_state, ref["final_state"], atol=1e-7)


def test_fast_engine_gradient_matches_diffrax_engine():
    def final_height(x0, engine):
        return hj.simulate(BALL, x0, "flight", 0.0, 2.0, BALL_ARGS, stepsize_controller=TIGHT,
                           engine=engine).final_state[0]

    x0 = jnp.array([1.0, 0.3])
    g_fast = jax.grad(final_height)(x0, "fast")
    g_ref = jax.grad(final_height)(x0, "diffrax")
    np.testing.assert_allclose(g_fast, g_ref, rtol=1e-7, atol=1e-9)


def test_engine_choice_errors_and_fallback():
    x0 = jnp.array([1.0, 0.0])
    with pytest.raises(ValueError, match="Kvaerno5"):
        hj.simulate(BALL, x0, "flight", 0.0, 1.0, BALL_ARGS, solver=diffrax.Kvaerno5(), engine="fast")
    with pytest.raises(ValueError, match="PIDController"):
        hj.simulate(BALL, x0, "flight", 0.0, 1.0, BALL_ARGS, engine="fast",
                    stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8, pcoeff=0.4, icoeff=0.3))
    with pytest.raises(ValueError, match="engine must be"):
        hj.simulate(BALL, x0, "flight", 0.0, 1.0, BALL_ARGS, engine="turbo")
    # "auto" keeps diffrax's step where the fast one does not apply, and takes it where it does.
    kv, pid = diffrax.Kvaerno5(), diffrax.PIDController(rtol=1e-6, atol=1e-6)
    s, c = hj.AutoEngine().stepper(kv, pid)
    assert s is kv and isinstance(c, FastIController)
    s, c = hj.AutoEngine().stepper(diffrax.Tsit5(), diffrax.ConstantStepSize())
    assert isinstance(s, UnrolledERK) and isinstance(c, diffrax.ConstantStepSize)


# a few save times per step, more than SAVE_WINDOW per step, and unsorted (rows of one step
# scattered over the array)
@pytest.mark.parametrize("num_saves, order", [(7, "sorted"), (400, "sorted"), (30, "shuffled")])
def test_saved_states_match_free_flight_and_a_bounce(num_saves, order):
    # h0 = 1, v0 = 0: free fall until sqrt(2/g), then the rebound at e = 0.8 (closed form).
    ts = np.linspace(0.0, 0.6, num_saves)
    if order == "shuffled":
        ts = np.random.default_rng(2).permutation(ts)
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 0.6, BALL_ARGS, stepsize_controller=TIGHT,
                      saveat=jnp.asarray(ts))
    t_hit = math.sqrt(2 / 9.8)
    v_up = 0.8 * 9.8 * t_hit
    s = np.maximum(ts - t_hit, 0.0)
    h = np.where(ts < t_hit, 1.0 - 4.9 * ts**2, v_up * s - 4.9 * s**2)
    v = np.where(ts < t_hit, -9.8 * ts, v_up - 9.8 * s)
    np.testing.assert_allclose(sol.ys[:, 0], h, atol=1e-9)
    np.testing.assert_allclose(sol.ys[:, 1], np.where(ts == t_hit, -9.8 * t_hit, v), atol=1e-8)
    assert np.all(np.asarray(sol.saved_modes) == 0)
