"""Solution: saved states, dense evaluation, the hybrid time domain, dtypes, retracing."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj

from helpers import BALL, BALL_ARGS, TIGHT, ball_reference, compile_count


def _ball_state(t, h0=1.0, g=9.8, e=0.8):
    """Closed-form (h, v) of the ball dropped from rest, right-continuous at impacts."""
    ref = ball_reference(h0, 0.0, g, e, t)
    return ref["final_state"]


def test_saveat_against_closed_form():
    ts = jnp.linspace(0.0, 2.0, 41)
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 2.0, BALL_ARGS,
                      stepsize_controller=TIGHT, saveat=diffrax.SaveAt(ts=ts))
    expected = np.stack([_ball_state(float(t)) for t in ts])
    np.testing.assert_allclose(sol.ys, expected, atol=1e-9)
    np.testing.assert_array_equal(sol.saved_modes, np.zeros(41, int))


def test_saveat_beyond_a_stop_is_padded():
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, BALL_ARGS,
                      stepsize_controller=TIGHT, saveat=jnp.array([0.1, 2.9]), max_epochs=2)
    assert sol.status == hj.Status.MAX_EPOCHS
    np.testing.assert_allclose(sol.ys[0], [1 - 4.9 * 0.01, -0.98], atol=1e-10)
    assert np.all(np.isinf(np.asarray(sol.ys[1]))) and int(sol.saved_modes[1]) == -1


def test_evaluate_and_hybrid_time_domain():
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 2.0, BALL_ARGS,
                      stepsize_controller=TIGHT)
    ref = ball_reference(1.0, 0.0, 9.8, 0.8, 2.0)
    times = jnp.array([0.0, 0.3, 0.9, 1.5, 1.99])
    xs, modes = jax.vmap(sol.evaluate)(times)
    np.testing.assert_allclose(xs, np.stack([_ball_state(float(t)) for t in times]), atol=1e-8)
    np.testing.assert_array_equal(modes, 0)
    x_out, m_out = sol.evaluate(2.5)
    assert np.all(np.isinf(np.asarray(x_out))) and int(m_out) == -1
    epochs = sol.hybrid_time_domain()
    assert len(epochs) == len(ref["event_times"]) + 1
    np.testing.assert_allclose([e.end for e in epochs[:-1]], ref["event_times"], atol=1e-10)
    assert epochs[0].start == 0.0 and epochs[-1].end == 2.0
    assert all(a.end == b.start for a, b in zip(epochs, epochs[1:], strict=False))


def test_evaluate_is_differentiable_in_time_forward_and_reverse():
    # dx/dt = F(x(t)) = (v, -g): at t0 (v = 0), in flight at 0.3 (v = -g t), at the first
    # impact's time itself (right-continuous: v = e sqrt(2 g h0), where no integration runs)
    # and after it at 0.6 (v = e sqrt(2 g h0) - g (t - t_1)); jax.jacfwd and jax.jacrev alike.
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 2.0, BALL_ARGS, stepsize_controller=TIGHT)
    t_1, v_1 = np.sqrt(2 / 9.8), 0.8 * np.sqrt(2 * 9.8)
    times = jnp.array([0.0, 0.3, float(sol.event_times[0]), 0.6])
    exact = np.array([[0.0, -9.8], [-9.8 * 0.3, -9.8], [v_1, -9.8], [v_1 - 9.8 * (0.6 - t_1), -9.8]])
    for jac in (jax.jacfwd, jax.jacrev):
        got = jax.jit(jax.vmap(jac(lambda s: sol.evaluate(s)[0])))(times)
        np.testing.assert_allclose(got, exact, rtol=1e-8, atol=1e-12)
    # and the second, d^2 x / dt^2 = (-g, 0), at the epochs' starts too
    second = jax.jit(jax.vmap(jax.jacfwd(jax.jacfwd(lambda s: sol.evaluate(s)[0]))))(times)
    np.testing.assert_allclose(second, np.tile([-9.8, 0.0], (4, 1)), rtol=1e-8, atol=1e-10)


def test_batched_solution_indexing_and_repr():
    run = jax.vmap(lambda h: hj.simulate(BALL, jnp.stack([h, 0.0 * h]), "flight", 0.0, 1.0,
                                         BALL_ARGS, max_epochs=4))
    sol = run(jnp.array([1.0, 2.0]))
    assert "batch (2,)" in repr(sol)
    one = sol[1]
    np.testing.assert_allclose(one.event_times[0], np.sqrt(2 * 2.0 / 9.8), atol=1e-8)
    assert list(sol.status_name) == ["T1_REACHED", "T1_REACHED"]


def test_float32_dtypes_are_preserved_and_accurate_to_float32():
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0], dtype=jnp.float32), "flight", 0.0, 2.0,
                      BALL_ARGS, saveat=jnp.array([0.5]))
    for name in ("event_times", "states_before", "states_after", "final_state", "final_time", "ys"):
        assert getattr(sol, name).dtype == jnp.float32, name
    ref = ball_reference(1.0, 0.0, 9.8, 0.8, 2.0)
    n = len(ref["event_times"])
    assert int(sol.num_events) == n
    # float32 resolution of times around 1 is 6e-8; the default float32 tolerances are 1e-5.
    np.testing.assert_allclose(sol.event_times[:n], ref["event_times"], atol=5e-5)


def test_integer_initial_state_and_args_promote_to_the_default_float_type():
    # x0 = (1, 0) and g = 10 as integer arrays: float64 throughout (x64 is on in the tests), and
    # accurate to rounding against the closed form (the flow is polynomial in t, of degree 2,
    # which Tsit5 integrates exactly; the event times are located to 1e-12 relative).
    x0, args = jnp.array([1, 0]), {"g": jnp.array(10), "e": 0.8}
    sol = hj.simulate(BALL, x0, "flight", 0.0, 2.0, args)
    for name in ("event_times", "states_before", "states_after", "final_state", "final_time", "x0"):
        assert getattr(sol, name).dtype == jnp.float64, name
    assert sol.args["g"].dtype == jnp.float64
    ref = ball_reference(1.0, 0.0, 10.0, 0.8, 2.0)
    n = len(ref["event_times"])
    assert int(sol.num_events) == n
    np.testing.assert_allclose(sol.event_times[:n], ref["event_times"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.final_state, ref["final_state"], rtol=0, atol=1e-12)
    # simulate_batch's dtypes, by abstract evaluation (nothing compiled)
    out = jax.eval_shape(lambda: hj.simulate_batch(BALL, jnp.array([[1, 0], [2, 0]]), "flight", 0.0, 2.0, args))
    assert out.final_state.dtype == out.event_times.dtype == out.args["g"].dtype == jnp.float64


def test_batched_entry_point_does_not_retrace():
    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(h0, e):
        return jax.vmap(lambda h: hj.simulate(BALL, jnp.stack([h, 0.0 * h]), "flight", 0.0, 1.0,
                                              {"g": 9.8, "e": e}, max_epochs=4))(h0)

    a = run(jnp.array([1.0, 1.5]), 0.5)
    b = run(jnp.array([0.7, 0.9]), 0.6)
    np.testing.assert_allclose(a.event_times[:, 0], np.sqrt(2 * np.array([1.0, 1.5]) / 9.8), atol=1e-8)
    np.testing.assert_allclose(b.event_times[:, 0], np.sqrt(2 * np.array([0.7, 0.9]) / 9.8), atol=1e-8)


def _ball_closed_form(t, h0=1.0, g=9.8, e=0.8):
    """(h, v) of the ball dropped from rest at time t, from its impact times: a parabola from the
    last impact t_k <= t (right-continuous), with launch speed e^k sqrt(2 g h0)."""
    w = np.sqrt(2 * g * h0)
    t_k, v_k, h_k, t_next = 0.0, 0.0, h0, np.sqrt(2 * h0 / g)
    while t_next <= t:
        w *= e
        t_k, v_k, h_k, t_next = t_next, w, 0.0, t_next + 2 * w / g
    dt = t - t_k
    return np.array([h_k + v_k * dt - 0.5 * g * dt * dt, v_k - g * dt])


@pytest.fixture(scope="module")
def ball_six_bounces():
    return hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, BALL_ARGS,
                       stepsize_controller=TIGHT)


def test_evaluate_many_times_in_one_pass_against_closed_form_and_without_recompiling(ball_six_bounces):
    sol = ball_six_bounces
    assert int(sol.num_events) == 6
    # 200 times over six bounces, shuffled, plus 300 inside the first flight (more than one
    # compiled segment's worth of times in one epoch) and two outside [t0, final_time].
    rng = np.random.default_rng(0)
    ts = np.concatenate([rng.permutation(np.linspace(0.0, 3.0, 200)),
                         np.linspace(0.01, 0.44, 300), [-0.5, 3.5]])
    xs, modes = sol.evaluate(ts)
    assert xs.shape == (502, 2) and modes.shape == (502,)
    expected = np.stack([_ball_closed_form(t) for t in ts[:500]])
    np.testing.assert_allclose(xs[:500], expected, rtol=0, atol=1e-8)
    np.testing.assert_array_equal(modes[:500], 0)
    assert np.all(np.isinf(np.asarray(xs[500:]))) and np.all(np.asarray(modes[500:]) == -1)
    # The same convention as the scalar form: right-continuous, x(t_i^+) at an event time.
    events = np.asarray(sol.event_times[:6])
    at_events, _ = sol.evaluate(events)
    np.testing.assert_array_equal(at_events, sol.states_after[:6])
    x_one, m_one = sol.evaluate(1.3)
    assert x_one.shape == (2,) and m_one.shape == ()
    np.testing.assert_allclose(x_one, sol.evaluate(np.array([1.3]))[0][0], rtol=0, atol=1e-12)
    # Other times, another count: the compiled program is reused.
    before = compile_count()
    xs2, _ = sol.evaluate(np.linspace(0.05, 2.95, 157))
    assert compile_count() == before
    np.testing.assert_allclose(
        xs2, np.stack([_ball_closed_form(t) for t in np.linspace(0.05, 2.95, 157)]), atol=1e-8)


def test_evaluate_rejects_batches_and_higher_rank_times(ball_six_bounces):
    sol = ball_six_bounces
    with pytest.raises(ValueError, match="scalar time or a 1-D array"):
        sol.evaluate(np.zeros((2, 3)))
    batch = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), sol)
    with pytest.raises(ValueError, match="`evaluate` works on one execution"):
        batch.evaluate(np.array([0.1, 0.2]))


def test_the_event_arrays_are_read_off_the_record_with_the_batch_axes_leading():
    # The event arrays are properties over the packed record: under jax.eval_shape they have the
    # shapes of the documented arrays; a batch axis moved behind the record's (out_axes=-1)
    # is refused with the fix, not read as events.
    one = lambda x: hj.simulate(BALL, x, "flight", 0.0, 2.0, BALL_ARGS, max_epochs=8)  # noqa: E731
    sol = jax.eval_shape(jax.vmap(one), jnp.zeros((3, 2)))
    assert sol.event_times.shape == (3, 8) and sol.states_after.shape == (3, 8, 2)
    assert sol.epoch_modes.shape == (3, 9) and sol.inside_guard.dtype == jnp.bool_
    moved = jax.eval_shape(jax.vmap(one, out_axes=-1), jnp.zeros((3, 2)))
    with pytest.raises(ValueError, match="out_axes=-1"):
        moved.event_times  # noqa: B018
