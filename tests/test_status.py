"""Every status, with the partial results it must keep, against hand-derived values."""

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj

from helpers import BALL, BALL_ARGS, TIGHT, ball_reference, ball_runner


def test_t1_reached():
    sol = ball_runner(3.0)(jnp.array([1.0, 0.0]), BALL_ARGS)
    assert sol.status == hj.Status.T1_REACHED and sol.status_name == "T1_REACHED"
    assert float(sol.final_time) == 3.0


def test_max_epochs_keeps_the_events_and_stops_before_the_next():
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, BALL_ARGS,
                      stepsize_controller=TIGHT, max_epochs=3)
    ref = ball_reference(1.0, 0.0, 9.8, 0.8, 3.0)
    assert sol.status == hj.Status.MAX_EPOCHS
    assert int(sol.num_events) == 3
    np.testing.assert_allclose(sol.event_times, ref["event_times"][:3], atol=1e-10)
    # stopped at the 4th impact, with the pre-impact state
    np.testing.assert_allclose(sol.final_time, ref["event_times"][3], atol=1e-10)
    np.testing.assert_allclose(sol.final_state, [0.0, -ref["post_velocities"][2]], atol=1e-9)


def test_a_status_is_its_integer_code():
    # The run of test_max_epochs_keeps_the_events_and_stops_before_the_next (its program reused).
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, BALL_ARGS,
                      stepsize_controller=TIGHT, max_epochs=3)
    code = hj.STATUS_NAMES.index("MAX_EPOCHS")
    assert int(sol.status) == int(hj.Status.MAX_EPOCHS) == code
    assert hj.STATUS_NAMES[sol.status] == "MAX_EPOCHS"
    assert [int(getattr(hj.Status, name)) for name in hj.STATUS_NAMES] == list(range(len(hj.STATUS_NAMES)))
    for same in (code, np.int32(code), jnp.asarray(code), hj.Status.MAX_EPOCHS):
        assert bool(sol.status == same) and bool(same == sol.status) and not bool(sol.status != same)
    assert not bool(sol.status == hj.Status.T1_REACHED) and bool(sol.status != 0)
    # against integer codes as a Monte Carlo table holds them (NumPy on either side)
    table = np.array([0, code, 3])
    np.testing.assert_array_equal(table == sol.status, [False, True, False])
    np.testing.assert_array_equal(sol.status == table, [False, True, False])
    np.testing.assert_array_equal(table == hj.Status.ZENO, [False, False, True])
    # traced, inside jax.jit
    assert bool(jax.jit(lambda s: s == hj.Status.MAX_EPOCHS)(sol.status))
    assert bool(jax.jit(lambda s: s == code)(sol.status))
    # two executions' statuses stacked, as vmap stacks them: np.asarray gives the codes
    reached = ball_runner(3.0)(jnp.array([1.0, 0.0]), BALL_ARGS).status
    batch = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), reached, sol.status)
    np.testing.assert_array_equal(np.asarray(batch), [0, code])
    np.testing.assert_array_equal(batch == hj.Status.MAX_EPOCHS, [False, True])
    with pytest.raises(ValueError, match="integer status codes"):
        sol.status == 1.0  # noqa: B015


def test_max_steps_keeps_the_partial_trajectory():
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, BALL_ARGS,
                      stepsize_controller=TIGHT, max_steps=3)
    assert sol.status == hj.Status.MAX_STEPS and int(sol.num_steps) == 3
    t = float(sol.final_time)
    assert 0.0 < t < 3.0
    # free fall from rest until the stop: h = 1 - g t^2 / 2, v = -g t
    np.testing.assert_allclose(sol.final_state, [1 - 4.9 * t * t, -9.8 * t], atol=1e-10)


def test_nonfinite_flow():
    m = hj.Mode("m", lambda t, x, p: jnp.where(t < 0.5, -jnp.ones_like(x), jnp.nan), 1)
    sys = hj.HybridSystem([m], [hj.Transition("m", "m", guard=lambda t, x, p: x[0] + 10.0)])
    sol = hj.simulate(sys, jnp.array([1.0]), "m", 0.0, 1.0, stepsize_controller=TIGHT)
    assert sol.status == hj.Status.NONFINITE
    t = float(sol.final_time)
    assert 0.4 < t <= 0.5
    np.testing.assert_allclose(sol.final_state, [1.0 - t], atol=1e-10)
    assert np.all(np.isfinite(np.asarray(sol.final_state)))


def test_nonfinite_reset_keeps_the_event():
    sys = hj.HybridSystem(BALL.modes, [hj.Transition(
        "flight", "flight", guard=lambda t, x, p: x[0],
        reset=lambda t, x, p: jnp.array([x[0], jnp.log(x[1])]))])  # log of a negative speed
    sol = hj.simulate(sys, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, BALL_ARGS,
                      stepsize_controller=TIGHT)
    assert sol.status == hj.Status.NONFINITE
    assert int(sol.num_events) == 1
    t_hit = math.sqrt(2 / 9.8)
    np.testing.assert_allclose(sol.event_times[0], t_hit, atol=1e-10)
    assert np.isnan(float(sol.states_after[0, 1]))
    np.testing.assert_allclose(sol.final_time, t_hit, atol=1e-10)
    np.testing.assert_allclose(sol.final_state, [0.0, -9.8 * t_hit], atol=1e-9)


def test_nonfinite_guard():
    m = hj.Mode("m", lambda t, x, p: -jnp.ones_like(x), 1)
    sys = hj.HybridSystem([m], [hj.Transition("m", "m", guard=lambda t, x, p: jnp.sqrt(x[0]))])
    sol = hj.simulate(sys, jnp.array([1.0]), "m", 0.0, 2.0, stepsize_controller=TIGHT)
    # sqrt(x) is 0 at x = 0 (an event at t = 1), then NaN for x < 0
    assert sol.status == hj.Status.NONFINITE
    assert float(sol.final_time) <= 1.0 + 1e-9


def test_chattering_zero_time_loop():
    # A -> B and B -> A, each guard always satisfied: infinitely many transitions at t0.
    a = hj.Mode("A", lambda t, x, p: jnp.zeros_like(x), 1)
    b = hj.Mode("B", lambda t, x, p: jnp.zeros_like(x), 1)
    sys = hj.HybridSystem([a, b], [
        hj.Transition("A", "B", guard=lambda t, x, p: -1.0 + 0.0 * x[0]),
        hj.Transition("B", "A", guard=lambda t, x, p: -1.0 + 0.0 * x[0]),
    ])
    sol = hj.simulate(sys, jnp.array([0.0]), "A", 0.25, 1.0, max_zero_epochs=5)
    assert sol.status == hj.Status.CHATTERING
    assert float(sol.final_time) == 0.25
    assert int(sol.num_events) == 6
    np.testing.assert_array_equal(sol.epoch_modes[:7], [0, 1, 0, 1, 0, 1, 0])


def test_throw_raises_outside_vmap():
    import equinox as eqx

    with pytest.raises(eqx.EquinoxRuntimeError, match="max_epochs"):
        hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, BALL_ARGS,
                    max_epochs=2, throw=True)


def test_constant_step_size_needs_dt0():
    with pytest.raises(ValueError, match="needs dt0"):
        hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 1.0, BALL_ARGS,
                    stepsize_controller=diffrax.ConstantStepSize())


RUNS = {"simulate": (hj.simulate, jnp.array([1.0, 0.0])),
        "simulate_batch": (hj.simulate_batch, jnp.array([[1.0, 0.0], [0.5, 0.1]]))}


@pytest.mark.parametrize("name", RUNS)
def test_t1_before_t0_is_refused_at_the_call(name):
    run, x0 = RUNS[name]
    with pytest.raises(ValueError, match=f"{name}: t1 must be >= t0"):
        run(BALL, x0, "flight", 1.0, 0.5, BALL_ARGS)


@pytest.mark.parametrize("name", RUNS)
def test_no_host_callback_in_the_program_whether_times_are_known_or_traced(name):
    # JAX's persistent compilation cache does not store programs with host callbacks; known
    # t0 and t1 are checked at the call, and traced ones end with a status instead of raising.
    run, x0 = RUNS[name]

    def program(traced_t1: bool) -> str:
        def f(x, t1):
            return run(BALL, x, "flight", 0.0, t1 if traced_t1 else 1.0, BALL_ARGS).final_state
        return jax.jit(f).lower(x0, 1.0).as_text()

    assert "callback" not in program(traced_t1=False)
    assert "callback" not in program(traced_t1=True)


def test_traced_t1_before_t0_ends_that_execution_with_its_own_status():
    # t1 = -1 and t1 = 1 in one vmapped batch, inside jax.jit: the first is refused with
    # T1_BEFORE_T0 at (t0, x0), the second runs to t1 through its first impact at
    # sqrt(2 h0 / g) = 0.4518 s, in both engines.
    x0 = jnp.array([1.0, 0.0])
    t1s = jnp.array([-1.0, 1.0])
    one = jax.jit(jax.vmap(lambda t1: hj.simulate(BALL, x0, "flight", 0.0, t1, BALL_ARGS)))(t1s)
    batch = jax.jit(lambda t1: hj.simulate_batch(BALL, jnp.stack([x0, x0]), "flight", 0.0, t1,
                                                 BALL_ARGS))(t1s)
    for sol in (one, batch):
        assert np.asarray(sol.status).tolist() == [int(hj.Status.T1_BEFORE_T0), int(hj.Status.T1_REACHED)]
        np.testing.assert_array_equal(np.asarray(sol.final_time), [0.0, 1.0])
        np.testing.assert_array_equal(np.asarray(sol.final_state[0]), x0)
        np.testing.assert_array_equal(np.asarray(sol.num_events), [0, 1])
        np.testing.assert_allclose(float(sol.event_times[1, 0]), np.sqrt(2 / 9.8), rtol=1e-6)


@pytest.mark.parametrize("name", RUNS)
def test_a_mode_name_given_as_x0_is_named_in_the_error(name):
    run, x0 = RUNS[name]
    with pytest.raises(TypeError, match=f"{name}: x0 must be an array of numbers, got 'flight'.*swapped"):
        run(BALL, "flight", x0, 0.0, 1.0, BALL_ARGS)
