"""Saltation matrices, the variational solver, periodic orbits and grazing, against hand derivations."""

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import quad

import hybridjax as hj
from hybridjax import examples

from helpers import BALL, BALL_ARGS, CEILING, THERMO, with_trace_counter

TIGHT = diffrax.PIDController(rtol=1e-11, atol=1e-11)
FWD = diffrax.ForwardMode()


def _ad_jacobians(system, x0, mode0, t1, args, n_events):
    """jacfwd of the final, pre- and post-event states and event times w.r.t. x0."""
    def outs(x):
        s = hj.simulate(system, x, mode0, 0.0, t1, args, stepsize_controller=TIGHT, adjoint=FWD)
        return s.final_state, s.states_before[:n_events], s.states_after[:n_events], s.event_times[:n_events]
    return jax.jacfwd(outs)(x0)


def test_bouncing_ball_saltation_closed_form():
    g, e = 9.8, 0.8
    for v in (-3.0, -0.25):
        Xi = hj.saltation_matrix(BALL, BALL.transitions[0], 0.7, jnp.array([0.0, v]), {"g": g, "e": e})
        np.testing.assert_allclose(Xi, [[-e, 0.0], [-(1 + e) * g / v, -e]], rtol=1e-12, atol=1e-10)


def _moving_threshold_system():
    # mode I (p, q): flow (a, r); guard p - c t (a threshold moving at speed c);
    # reset to mode J (dim 1): p + q + b t; mode J: flow d.
    I = hj.Mode("I", lambda t, x, k: jnp.array([k["a"] + 0.0 * x[0], k["r"] + 0.0 * x[1]]), dim=2)
    J = hj.Mode("J", lambda t, x, k: jnp.array([k["d"] + 0.0 * x[0]]), dim=1)
    return hj.HybridSystem([I, J], [hj.Transition(
        "I", "J", guard=lambda t, x, k: x[0] - k["c"] * t,
        reset=lambda t, x, k: jnp.array([x[0] + x[1] + k["b"] * t]))])


def test_time_varying_guard_and_reset_rectangular_saltation():
    k = dict(a=-1.0, r=0.5, c=0.75, b=2.0, d=-0.3)
    sys = _moving_threshold_system()
    # Hand derivation: t* = p0 / (c - a); x(T) = p0 + q0 + (a + r + b) t* + d (T - t*), so
    # dx(T)/dp0 = 1 + (a + r + b - d) / (c - a), dx(T)/dq0 = 1; the flows' Phi are identities.
    expected = np.array([[1 + (k["a"] + k["r"] + k["b"] - k["d"]) / (k["c"] - k["a"]), 1.0]])
    x_minus = jnp.array([0.6, 0.2])
    Xi = hj.saltation_matrix(sys, 0, 0.6 / 0.75, x_minus, k)
    assert Xi.shape == (1, 2)
    np.testing.assert_allclose(Xi, expected, rtol=1e-12)
    x0 = jnp.array([1.75, -0.3])
    J_ad = _ad_jacobians(sys, x0, "I", 2.0, k, 1)[0]
    sol = hj.simulate(sys, x0, "I", 0.0, 2.0, k, stepsize_controller=TIGHT)
    np.testing.assert_allclose(sol.event_times[0], 1.75 / (0.75 + 1.0), rtol=1e-12)
    np.testing.assert_allclose(J_ad[:1], expected, rtol=1e-9)
    np.testing.assert_allclose(hj.variational_jacobian(sol).final_state, expected, rtol=1e-9)


def _compare_variational(system, x0, mode0, t1, args, min_events):
    sol = hj.simulate(system, x0, mode0, 0.0, t1, args, stepsize_controller=TIGHT)
    n = int(sol.num_events)
    assert n >= min_events and sol.status == hj.Status.T1_REACHED
    var = hj.variational_jacobian(sol)
    J_final, J_before, J_after, J_times = _ad_jacobians(system, x0, mode0, t1, args, n)
    n_final = system.modes[int(sol.final_mode)].dim
    np.testing.assert_allclose(var.final_state, J_final[:n_final], rtol=1e-6, atol=1e-8)
    for i in range(n):
        n_b = system.modes[int(sol.epoch_modes[i])].dim
        n_a = system.modes[int(sol.epoch_modes[i + 1])].dim
        np.testing.assert_allclose(var.states_before[i], J_before[i, :n_b], rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(var.states_after[i], J_after[i, :n_a], rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(var.event_times[i], J_times[i], rtol=1e-6, atol=1e-8)


def test_ad_equals_variational_bouncing_ball():
    _compare_variational(BALL, jnp.array([1.0, 0.3]), "flight", 2.0, BALL_ARGS, min_events=3)


def test_ad_equals_variational_thermostat():
    p = dict(a=0.1, T_amb=5.0, P_heat=2.5, P_cool=2.0, s=20.0)
    _compare_variational(THERMO, jnp.array([19.0]), "off", 12.0, p, min_events=3)


def test_ad_equals_variational_nonlinear_pendulum_against_a_wall():
    p = {"theta_w": 0.2, "e": 0.7}
    _compare_variational(examples.pendulum_wall(), jnp.array([-0.5, 0.8]), "swing", 9.0, p, min_events=3)


def test_variational_chain_of_zero_length_epochs_ceiling():
    p = {"g": 9.8, "H": 2.0}
    sol = hj.simulate(CEILING, jnp.array([0.0, 7.0]), "flight", 0.0, 1.0, p, stepsize_controller=TIGHT)
    var = hj.variational_jacobian(sol)
    np.testing.assert_allclose(var.final_state[1, 1], 1 - math.sqrt(5), rtol=1e-8)
    # both transitions share the event time, so their time sensitivities are equal
    np.testing.assert_allclose(var.event_times[0], var.event_times[1])


@pytest.mark.slow
def test_rimless_wheel_periodic_orbit_and_floquet_multipliers():
    alpha, gamma = 0.3, 0.08
    ref = examples.rimless_wheel_closed_form(alpha, gamma)
    wheel, calls = with_trace_counter(examples.rimless_wheel())
    orbit = hj.periodic_orbit(wheel, 0, ref["state"] * np.array([1.0, 1.2]),
                              {"alpha": jnp.asarray(alpha), "gamma": jnp.asarray(gamma)})
    np.testing.assert_allclose(orbit.state, ref["state"], rtol=1e-9)
    assert orbit.residual < 1e-10
    # period: time from theta = gamma - alpha to gamma + alpha with omega^2 = w*^2 + 2 (cos(g - a) - cos th)
    w2 = ref["state"][1] ** 2
    period = quad(lambda th: 1 / math.sqrt(w2 + 2 * (math.cos(gamma - alpha) - math.cos(th))),
                  gamma - alpha, gamma + alpha, epsabs=1e-13, epsrel=1e-13)[0]
    np.testing.assert_allclose(orbit.period, period, rtol=1e-8)
    for multipliers in (orbit.multipliers_ad, orbit.multipliers_saltation):
        np.testing.assert_allclose(np.sort(multipliers.real), np.sort([1.0, ref["multiplier"]]), atol=1e-7)
    np.testing.assert_allclose(orbit.monodromy_ad, orbit.monodromy_saltation, rtol=1e-6, atol=1e-8)
    eig_dp = np.sort(np.abs(np.linalg.eigvals(orbit.poincare_jacobian)))
    np.testing.assert_allclose(eig_dp, [0.0, ref["multiplier"]], atol=1e-7)
    # Another slope, given as arrays like the first: the compiled programs are reused (the
    # flow is not traced again) and the orbit is the new slope's.
    traced = len(calls)
    ref2 = examples.rimless_wheel_closed_form(alpha, 0.1)
    orbit2 = hj.periodic_orbit(wheel, 0, ref2["state"] * np.array([1.0, 0.9]),
                               {"alpha": jnp.asarray(alpha), "gamma": jnp.asarray(0.1)})
    assert len(calls) == traced
    np.testing.assert_allclose(orbit2.state, ref2["state"], rtol=1e-9)
    np.testing.assert_allclose(np.sort(orbit2.multipliers_saltation.real), np.sort([1.0, ref2["multiplier"]]),
                               atol=1e-7)


def test_grazing_crossing_is_flagged():
    # (x, z) moving at unit speed along z = 0 into the guard z + (x - 1)^2 - delta: it enters
    # at x = 1 - sqrt(delta) with dg/dt = -2 sqrt(delta), the cosine of the angle between
    # the flow and the guard's normal. Constant steps put a sample at x = 1, inside the guard.
    fly = hj.Mode("fly", lambda t, x, p: jnp.array([1.0 + 0.0 * x[0], 0.0 * x[1]]), dim=2)
    stop = hj.Mode("stop", lambda t, x, p: jnp.zeros_like(x), dim=2)
    sys = hj.HybridSystem([fly, stop], [hj.Transition(
        "fly", "stop", guard=lambda t, x, delta: x[1] + (x[0] - 1.0) ** 2 - delta)])
    run = jax.jit(lambda delta: hj.simulate(sys, jnp.zeros(2), "fly", 0.0, 2.0, delta,
                                            stepsize_controller=diffrax.ConstantStepSize(), dt0=0.5))
    for delta, grazing in ((1e-2, False), (1e-12, True)):
        sol = run(delta)
        assert int(sol.num_events) == 1 and bool(sol.grazing[0]) == grazing
        np.testing.assert_allclose(sol.event_times[0], 1 - math.sqrt(delta), atol=1e-12)
