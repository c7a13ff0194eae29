"""Execution semantics of API.md: epoch-start test, priority, zero-length epochs, mixed dims."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj
from hybridjax import examples

from helpers import BALL, CEILING, THERMO, TIGHT, WALL


@pytest.fixture(scope="module")
def ball_from():
    """jit(simulate) of the ball (e = 0.5) from an arbitrary state, to t1 = 0.5."""
    return jax.jit(lambda x0: hj.simulate(BALL, x0, "flight", 0.0, 0.5, {"g": 9.8, "e": 0.5},
                                          stepsize_controller=TIGHT, max_epochs=8))


@pytest.mark.parametrize(
    "x0, fires_at_t0",
    [
        ([0.0, -1.0], True),   # on the guard, g' = v < 0: trending into the guard
        ([0.0, 1.0], False),   # on the guard, g' = v > 0: leaving it (the ball after a bounce)
        ([0.0, 0.0], True),    # g' = 0, g'' = -g < 0: trending in at second order
        ([-0.1, 1.0], True),   # strictly inside the guard
        ([-1e-14, 1.0], False),  # inside the tolerance band and leaving
    ],
)
def test_epoch_start_uses_trending_negative(ball_from, x0, fires_at_t0):
    sol = ball_from(jnp.array(x0))
    first = float(sol.event_times[0])
    if fires_at_t0:
        assert first == 0.0
        np.testing.assert_allclose(sol.states_after[0], [x0[0], -0.5 * x0[1]])
    else:
        # next impact of a ball leaving the floor at v: 2 v / g
        np.testing.assert_allclose(first, 2 * 1.0 / 9.8, rtol=1e-10)


def _line_system(g_b, g_c):
    """x' = -1 in mode a; a -> b with guard g_b, a -> c with guard g_c (listed in that order)."""
    a = hj.Mode("a", lambda t, x, p: -jnp.ones_like(x), 1)
    b = hj.Mode("b", lambda t, x, p: jnp.zeros_like(x), 1)
    c = hj.Mode("c", lambda t, x, p: jnp.zeros_like(x), 1)
    return hj.HybridSystem([a, b, c], [
        hj.Transition("a", "b", guard=g_b, reset=lambda t, x, p: x + 10.0),
        hj.Transition("a", "c", guard=g_c, reset=lambda t, x, p: x + 20.0),
    ])


def test_priority_by_listing_order_for_simultaneous_guards():
    same = lambda t, x, p: x[0] - 0.5  # noqa: E731
    for order, winner in ((0, 1), (1, 2)):
        sys = _line_system(same, same)
        if order:
            sys = hj.HybridSystem(sys.modes, sys.transitions[::-1])
        sol = hj.simulate(sys, jnp.array([1.0]), "a", 0.0, 2.0, stepsize_controller=TIGHT)
        assert int(sol.num_events) == 1 and int(sol.final_mode) == winner
        assert bool(sol.simultaneous[0])
        np.testing.assert_allclose(sol.event_times[0], 0.5, atol=1e-12)


def test_first_guard_reached_wins_whatever_the_order():
    sys = _line_system(lambda t, x, p: x[0] - 0.4, lambda t, x, p: x[0] - 0.5)
    sol = hj.simulate(sys, jnp.array([1.0]), "a", 0.0, 2.0, stepsize_controller=TIGHT)
    assert int(sol.final_mode) == 2 and not bool(sol.simultaneous[0])
    np.testing.assert_allclose(sol.event_times[0], 0.5, atol=1e-12)
    np.testing.assert_allclose(sol.final_state, [0.5 + 20.0], atol=1e-10)


def test_ceiling_reset_into_guard_gives_a_zero_length_epoch():
    p = {"g": 9.8, "H": 2.0}
    sol = hj.simulate(CEILING, jnp.array([0.0, 7.0]), "flight", 0.0, 1.0, p, stepsize_controller=TIGHT)
    ref = examples.ceiling_ball_closed_form(0.0, 7.0, p, 1.0)
    assert sol.status == hj.Status.T1_REACHED
    assert int(sol.num_events) == 2
    np.testing.assert_array_equal(sol.epoch_modes[:3], [0, 1, 0])
    np.testing.assert_array_equal(sol.transitions[:2], [0, 1])
    np.testing.assert_allclose(sol.event_times[:2], [ref["event_time"]] * 2, atol=1e-10)
    assert float(sol.event_times[0]) == float(sol.event_times[1])
    np.testing.assert_allclose(sol.states_before[0, 1], ref["impact_velocity"], atol=1e-9)
    np.testing.assert_allclose(sol.states_after[0], [2.0, 0.0], atol=1e-10)
    np.testing.assert_allclose(sol.final_state, ref["final_state"], atol=1e-9)
    epochs = sol.hybrid_time_domain()
    assert [e.mode_name for e in epochs] == ["flight", "contact", "flight"]
    assert epochs[1].length == 0.0 and epochs[2].end == 1.0


def test_modes_of_different_dimension():
    p = {"g": 9.8, "w": 2.0, "c": 0.7}
    x0 = jnp.array([0.0, 1.0, 1.5, 3.0])
    ref = examples.wall_particle_closed_form(x0, p, 3.0)
    sol = hj.simulate(WALL, x0, "flight", 0.0, 3.0, p, stepsize_controller=TIGHT,
                      saveat=jnp.array([0.5, 2.5]))
    assert int(sol.num_events) == 1 and int(sol.final_mode) == 1
    np.testing.assert_allclose(sol.event_times[0], ref["event_time"], atol=1e-10)
    np.testing.assert_allclose(sol.states_before[0], ref["state_before"], atol=1e-9)
    # the 2-D slide state, padded with zeros to the 4-D carried state
    np.testing.assert_allclose(sol.states_after[0], np.r_[ref["state_after"], 0, 0], atol=1e-9)
    np.testing.assert_allclose(sol.final_state, np.r_[ref["final_state"], 0, 0], atol=1e-8)
    np.testing.assert_array_equal(sol.saved_modes, [0, 1])
    np.testing.assert_allclose(sol.ys[0], [0.75, 1 + 1.5 - 4.9 * 0.25, 1.5, 3 - 4.9], atol=1e-9)
    slide = examples.wall_particle_closed_form(x0, p, 2.5)["final_state"]
    np.testing.assert_allclose(sol.ys[1, :2], slide, atol=1e-8)


def test_vmap_over_initial_modes_of_different_dimension():
    p = {"g": 9.8, "w": 2.0, "c": 0.7}
    run = jax.jit(jax.vmap(lambda x0, m0: hj.simulate(WALL, x0, m0, 0.0, 1.0, p,
                                                       stepsize_controller=TIGHT)))
    x0 = jnp.array([[0.0, 1.0, 1.5, 3.0], [1.0, -2.0, 0.0, 0.0]])  # flight; slide (padded)
    sol = run(x0, jnp.array([0, 1]))
    np.testing.assert_array_equal(sol.num_events, [0, 0])
    np.testing.assert_array_equal(sol.final_mode, [0, 1])
    np.testing.assert_allclose(sol.final_state[0], [1.5, 1 + 3 - 4.9, 1.5, 3 - 9.8], atol=1e-9)
    # slide from (z, v) = (1, -2) for 1 s: the closed form with the impact at t = 0
    ref = examples.wall_particle_closed_form([1.0, 1.0, 1.0, -2.0], {**p, "w": 1.0}, 1.0)
    np.testing.assert_allclose(sol.final_state[1, :2], ref["final_state"], atol=1e-9)


def test_vmap_over_thermostat_modes_and_closed_form_switching():
    p = dict(a=0.1, T_amb=5.0, P_heat=2.5, P_cool=2.0, s=20.0)
    run = jax.jit(jax.vmap(lambda x0, m0, amb: hj.simulate(
        THERMO, x0, m0, 0.0, 40.0, {**p, "T_amb": amb}, stepsize_controller=TIGHT)))
    cases = [(19.0, "off", 5.0), (17.0, "heat", 5.0), (21.0, "off", 35.0), (23.0, "cool", 35.0)]
    sol = run(jnp.array([[c[0]] for c in cases]), jnp.array([THERMO.mode_index(c[1]) for c in cases]),
              jnp.array([c[2] for c in cases]))
    for i, (T0, m0, amb) in enumerate(cases):
        ref = examples.thermostat_closed_form(T0, m0, {**p, "T_amb": amb}, 40.0)
        n = len(ref["event_times"])
        assert n >= 4 and int(sol.num_events[i]) == n
        # heating cycles (amb 5) and cooling cycles (amb 35): switching times to 1e-8
        np.testing.assert_allclose(sol.event_times[i, :n], ref["event_times"], atol=1e-8)
        assert [THERMO.mode_names[int(m)] for m in sol.epoch_modes[i, : n + 1]] == ref["modes"]
        np.testing.assert_allclose(sol.final_state[i], ref["final_state"], atol=1e-8)


def test_event_at_t0_when_the_initial_state_is_in_a_guard():
    p = dict(a=0.1, T_amb=30.0, P_heat=2.5, P_cool=2.0, s=20.0)
    sol = hj.simulate(THERMO, jnp.array([25.0]), "off", 0.0, 5.0, p, stepsize_controller=TIGHT)
    assert float(sol.event_times[0]) == 0.0 and int(sol.epoch_modes[1]) == 2
    ref = examples.thermostat_closed_form(25.0, "off", p, 5.0)
    np.testing.assert_allclose(sol.final_state, ref["final_state"], atol=1e-9)
