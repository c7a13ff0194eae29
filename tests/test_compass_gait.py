"""The compass-gait walker's period-one gait and Floquet multipliers (Goswami, Thuilot and Espiau's
model: m = 5, m_H = 10, a = b = 0.5, a 3 degree slope), found by `hj.periodic_orbit` on
`hj.examples.compass_gait()`, against a computation without hybridjax: the equations of motion and
the heel strike written out here, the swing phase integrated by scipy's `solve_ivp` phase by phase
(until the swing foot passes the stance foot, then until it touches the slope), the fixed point of
that stride map by `scipy.optimize.fsolve`, and its multipliers from a central-difference Jacobian.

The orbit and the reference are computed once, on first use (module-level caches)."""

import functools
import math

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import fsolve

import hybridjax as hj

M_LEG, M_HIP, A, B, GRAV = 5.0, 10.0, 0.5, 0.5, 9.81
L = A + B
SLOPE = math.radians(3.0)
AHEAD = 0.05  # the swing foot's heel strike counts once it is 5 cm ahead of the stance foot
PARAMS = {"m": M_LEG, "m_H": M_HIP, "a": A, "b": B, "g": GRAV, "gamma": SLOPE, "ahead": AHEAD}
RTOL = 1e-11

# ----------------------------------------------------------------------------- reference by hand
# Angles from the vertical of each leg's foot-to-hip direction e(theta) = (sin, cos), in a plane
# with x forward and y up; the stance foot at the origin, the slope y = -x tan(gamma).
DOWNHILL = np.array([math.cos(SLOPE), -math.sin(SLOPE)])
NORMAL = np.array([math.sin(SLOPE), math.cos(SLOPE)])


def _e(th):
    return np.array([math.sin(th), math.cos(th)])


def _de(th):
    return np.array([math.cos(th), -math.sin(th)])


def points(y):
    """(mass, position, velocity) of the stance leg's mass, the hip and the swing leg's mass, and
    the swing foot's position; y = (theta_ns, theta_s, theta_ns', theta_s')."""
    tns, ts, wns, ws = y
    hip, dhip = L * _e(ts), L * ws * _de(ts)
    bodies = [(M_LEG, A * _e(ts), A * ws * _de(ts)), (M_HIP, hip, dhip),
              (M_LEG, hip - B * _e(tns), dhip - B * wns * _de(tns))]
    return bodies, hip - L * _e(tns)


def acceleration(y):
    """The textbook swing phase M(q) q'' + C(q, q') q' + G(q) = 0, q = (theta_ns, theta_s)."""
    tns, ts, wns, ws = y
    c, s = math.cos(ts - tns), math.sin(ts - tns)
    M = np.array([[M_LEG * B**2, -M_LEG * L * B * c], [-M_LEG * L * B * c, M_LEG * A**2 + (M_HIP + M_LEG) * L**2]])
    Cw = M_LEG * L * B * s * np.array([ws**2, -(wns**2)])
    G = GRAV * np.array([M_LEG * B * math.sin(tns), -(M_LEG * A + (M_HIP + M_LEG) * L) * math.sin(ts)])
    return np.linalg.solve(M, -Cw - G)


def rhs(t, y):
    return np.concatenate([y[2:], acceleration(y)])


def energy(y):
    bodies, _ = points(y)
    return sum(0.5 * m * v @ v + m * GRAV * p[1] for m, p, v in bodies)


def kinetic(y):
    bodies, _ = points(y)
    return sum(0.5 * m * v @ v for m, p, v in bodies)


def _cross(u, v):
    return u[0] * v[1] - u[1] * v[0]


def momenta(y, foot):
    """The walker's angular momentum about `foot` and the stance leg's about the hip."""
    bodies, _ = points(y)
    hip = bodies[1][1]
    whole = sum(m * _cross(p - foot, v) for m, p, v in bodies)
    stance_leg = M_LEG * _cross(bodies[0][1] - hip, bodies[0][2])
    return np.array([whole, stance_leg])


def heel_strike(y):
    """The impulse at the new foot conserves the whole walker's angular momentum about that foot
    and the old stance leg's about the hip (no impulse acts on it elsewhere); the legs swap. The
    post-strike momenta (the new swing leg is the old stance leg) are linear in the rates: solved
    column by column."""
    _, foot = points(y)
    before = momenta(y, foot)
    # After: the new stance foot is at `foot`; in the new stance frame it is the origin and the
    # old stance leg is the swing leg: its angular momentum about the hip is the swing leg's.
    q_plus = np.array([y[1], y[0]])

    def after(w):
        bodies, _ = points(np.concatenate([q_plus, w]))
        hip = bodies[1][1]
        whole = sum(m * _cross(p, v) for m, p, v in bodies)
        swing_leg = M_LEG * _cross(bodies[2][1] - hip, bodies[2][2])
        return np.array([whole, swing_leg])

    K = np.stack([after(np.array([1.0, 0.0])), after(np.array([0.0, 1.0]))], axis=1)
    return np.concatenate([q_plus, np.linalg.solve(K, before)])


def _swing_ahead(t, y):
    return points(y)[1] @ DOWNHILL - AHEAD


def _swing_height(t, y):
    return points(y)[1] @ NORMAL


_swing_ahead.terminal, _swing_ahead.direction = True, 1.0
_swing_height.terminal, _swing_height.direction = True, -1.0


def stride(x):
    """The stride map by scipy: (the state just after the next heel strike, its time), from x just
    after a heel strike. Phase 1 until the swing foot is AHEAD in front of the stance foot (it
    passes through the slope at mid-stance, as the model allows), phase 2 until it touches."""
    first = solve_ivp(rhs, (0.0, 2.0), x, method="DOP853", rtol=RTOL, atol=RTOL, events=_swing_ahead)
    t1, y1 = first.t_events[0][0], first.y_events[0][0]
    second = solve_ivp(rhs, (t1, 3.0), y1, method="DOP853", rtol=RTOL, atol=RTOL, events=_swing_height)
    return heel_strike(second.y_events[0][0]), second.t_events[0][0]


@functools.cache
def reference():
    """The fixed point of the stride map on the section theta_ns + theta_s = 2 gamma (feet on the
    slope), by fsolve from a rough guess; the step period; the stride map's Jacobian by central
    differences (step 1e-6: an error of at most about the integration error over the step,
    1e-11 / 1e-6, plus a truncation error of order 1e-12) and its eigenvalues, largest modulus
    first."""

    def state(z):
        return np.array([2 * SLOPE - z[0], *z])

    z = fsolve(lambda z: stride(state(z))[0][1:] - z, [-0.2, 0.4, 1.1], xtol=1e-13)
    x = state(z)
    P, period = stride(x)
    h = 1e-6
    J = np.stack([(stride(x + h * e)[0] - stride(x - h * e)[0]) / (2 * h) for e in np.eye(4)], axis=1)
    eig = np.linalg.eigvals(J)
    return dict(state=x, image=P, period=period, jacobian=J, multipliers=eig[np.argsort(-np.abs(eig))])


@functools.cache
def orbit():
    args = {key: jnp.asarray(value) for key, value in PARAMS.items()}
    guess = jnp.asarray(reference()["state"] * 1.02)
    return hj.periodic_orbit(hj.examples.compass_gait(), 0, guess, args, max_epochs=4, t_max=2.0)


# ----------------------------------------------------------------------------- tests


def test_reference_conserves_energy_in_the_swing_and_balances_it_over_a_stride():
    # Checks the hand-written equations of motion against the point masses' energy (an independent
    # formula), and the fixed point against the energy balance of a periodic gait: the strike
    # dissipates the kinetic energy that descending one step, s sin(gamma), released.
    ref = reference()
    x = ref["state"]
    swing = solve_ivp(rhs, (0.0, ref["period"]), x, method="DOP853", rtol=RTOL, atol=RTOL, dense_output=True)
    E = [energy(swing.sol(t)) for t in np.linspace(0.0, ref["period"], 9)]
    np.testing.assert_allclose(E, E[0], rtol=0, atol=1e-8)
    before = swing.y[:, -1]
    after = heel_strike(before)
    np.testing.assert_allclose(after, x, rtol=0, atol=1e-8)
    step = points(before)[1] @ DOWNHILL
    dissipated = kinetic(before) - kinetic(after)
    np.testing.assert_allclose(dissipated, (M_HIP + 2 * M_LEG) * GRAV * step * math.sin(SLOPE), rtol=1e-7)


def test_period_one_gait_against_scipy():
    assert hj.examples.COMPASS_GAIT_ARGS == pytest.approx(PARAMS)  # the parameters the docs use
    ref, orb = reference(), orbit()
    # Measured: 1.4e-11 and 2.3e-12 (both integrations to 1e-11 or tighter).
    np.testing.assert_allclose(orb.state, ref["state"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(orb.period, ref["period"], rtol=0, atol=1e-10)
    assert float(orb.residual) < 1e-10
    # The gait: feet on the slope at the strike, half inter-leg angle about 0.27 rad, 0.73 s a step.
    assert abs(float(orb.state[0] + orb.state[1]) - 2 * SLOPE) < 1e-9
    assert 0.73 < float(orb.period) < 0.74


def test_floquet_multipliers_against_finite_differences():
    ref, orb = reference(), orbit()
    dp = np.linalg.eigvals(np.asarray(orb.poincare_jacobian))
    dp = dp[np.argsort(-np.abs(dp))]
    # Central differences of a map integrated to 1e-11 with step 1e-6: an error bounded by about
    # 1e-5, measured 1.6e-9 here.
    np.testing.assert_allclose(np.abs(dp), np.abs(ref["multipliers"]), rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.sort_complex(dp[:3]), np.sort_complex(ref["multipliers"][:3]), rtol=0, atol=1e-6)
    # The monodromy matrix: 1 along the flow and the same nontrivial multipliers, by AD and by
    # saltation matrices.
    for mult in (orb.multipliers_ad, orb.multipliers_saltation):
        mult = np.asarray(mult)
        np.testing.assert_allclose(mult[0], 1.0, atol=1e-8)
        np.testing.assert_allclose(np.abs(mult[1:]), np.abs(ref["multipliers"][:3]), rtol=0, atol=1e-6)
    # Stable: a complex pair of modulus 0.58 and a real multiplier 0.13.
    assert np.max(np.abs(dp)) < 1.0 and np.max(np.abs(ref["multipliers"])) < 1.0
    assert abs(dp[0].imag) > 0.1


def scene_state(y):
    """The state of `hj.examples.compass_gait_scene()` (hip, stance leg's mass, swing leg's mass
    and their velocities, in the slope's frame: x downhill, z normal) of the angles y."""
    rot = np.stack([DOWNHILL, NORMAL])  # world to slope frame
    bodies, _ = points(y)
    stance, hip, swing = (rot @ p for _, p, _ in bodies)
    dstance, dhip, dswing = (rot @ v for _, _, v in bodies)
    return np.concatenate([hip, stance, swing, dhip, dstance, dswing])


@pytest.mark.costly
def test_compass_gait_scene_walks_the_same_gait():
    # The scene's stride from the reference gait, with the legs relabelled at the strike, lands on
    # the same gait one period later (build and first simulate about 80 s on 2 cores: left out of
    # the default run, which checks the same gait on `compass_gait` above).
    import diffrax

    ref = reference()
    scene, relabel = hj.examples.compass_gait_scene()
    args = {key: jnp.asarray(value) for key, value in PARAMS.items()}
    system = hj.contact_system(scene, ["foot0"], args, relabels=[relabel])
    strike = [k for k, tr in enumerate(system.transitions) if tr.name == "impact foot1: leg0+leg1+foot0 -> leg0+leg1+foot0"]
    x0 = scene_state(ref["state"])
    sol = hj.simulate(system, jnp.asarray(x0), 0, 0.0, 1.2 * ref["period"], args, max_epochs=4,
                      stepsize_controller=diffrax.PIDController(rtol=1e-11, atol=1e-11))
    assert sol.status == hj.Status.T1_REACHED and int(sol.num_events) == 1
    assert [int(sol.transitions[0])] == strike
    # Measured: 6.3e-12 and 2.5e-11.
    np.testing.assert_allclose(sol.event_times[0], ref["period"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(sol.states_after[0], x0, rtol=0, atol=1e-9)
