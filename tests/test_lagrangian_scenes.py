"""Scenes with a configuration-dependent mass matrix: the Coriolis and centrifugal forces that
`hj.Scene` derives from M(q) (the Euler-Lagrange equations), checked against closed forms and
against hand-written equations of motion integrated by scipy.

Systems are built on first use (module-level caches), not at import."""

import functools
import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj

TIGHT = diffrax.PIDController(rtol=1e-11, atol=1e-11)

# ----------------------------------------------------------------------------- polar particle


def polar_forces(t, q, dq, p):
    """The velocity forces of M = diag(1, r^2), written by hand, times p["k"] (0: none)."""
    r, dr, dth = q[0], dq[0], dq[1]
    return p["k"] * jnp.stack([r * dth**2, -2.0 * r * dr * dth])


RING = 2.0


def polar_scene(velocity_terms):
    """A particle of unit mass in polar coordinates q = (r, theta), T = (r'^2 + r^2 theta'^2) / 2,
    no applied force (with p["k"] = 0), inside a ring r <= 2."""
    return hj.Scene(
        2,
        lambda q, p: jnp.diag(jnp.stack([1.0 + 0.0 * q[0], q[0] ** 2])),
        polar_forces,
        [hj.Constraint("ring", lambda t, q, p: RING - q[0])],
        bounds=((0.9, -1.0, -2.0, -2.0), (RING, 1.0, 2.0, 2.0)),
        velocity_terms=velocity_terms,
    )


@functools.cache
def polar_system(velocity_terms):
    return hj.contact_system(polar_scene(velocity_terms), ["free"], {"k": jnp.asarray(0.0)})


def _polar_run(x0, mode):
    # mode as an array and the same saves: one compiled program for both runs.
    system = polar_system(True)
    return hj.simulate(system, jnp.asarray(x0), jnp.asarray(system.mode_names.index(mode)), 0.0, 1.0,
                       {"k": jnp.asarray(0.0)}, stepsize_controller=TIGHT, saveat=jnp.array([0.5, 1.0]))


def test_polar_particle_moves_on_a_straight_line():
    # Started at (x, y) = (1, 0) with velocity (0, 1): the straight line x = 1, y = t, so
    # r = sqrt(1 + t^2), theta = atan(t), r' = t / r, theta' = 1 / r^2; at t = 1 (sqrt 2, pi/4, ...).
    sol = _polar_run([1.0, 0.0, 0.0, 1.0], "free")
    assert sol.status == hj.Status.T1_REACHED and int(sol.num_events) == 0
    t = np.array([0.5, 1.0])
    r = np.sqrt(1 + t**2)
    np.testing.assert_allclose(sol.ys, np.stack([r, np.arctan(t), t / r, 1 / r**2], axis=1), rtol=0, atol=1e-9)
    np.testing.assert_allclose(sol.final_state, [math.sqrt(2), math.pi / 4, 1 / math.sqrt(2), 0.5],
                               rtol=0, atol=1e-9)


def test_polar_particle_on_the_ring_feels_the_centripetal_force():
    # Sliding along the ring r = 2 at theta' = w: uniform circular motion, the ring's force the
    # centripetal m r w^2 (the centrifugal term r theta'^2 of the velocity forces, balanced).
    w = 0.5
    system = polar_system(True)
    sol = _polar_run([RING, 0.0, 0.0, w], "ring")
    assert sol.status == hj.Status.T1_REACHED and int(sol.num_events) == 0
    np.testing.assert_allclose(sol.final_state, [RING, w, 0.0, w], rtol=0, atol=1e-9)
    np.testing.assert_allclose(system.contact_forces(sol), [[RING * w**2]] * 2, rtol=0, atol=1e-9)


def test_polar_particle_flow_with_velocity_terms_written_by_hand():
    # Euler-Lagrange by hand: r'' = r theta'^2, theta'' = -2 r' theta' / r. With `velocity_terms`
    # off, the flow is M^-1 forces: 0 without the hand-written terms, the same accelerations with them.
    rng = np.random.default_rng(1)
    derived = polar_system(True).modes[0].flow
    by_hand = polar_system(False).modes[0].flow
    for _ in range(3):
        r, th = rng.uniform(0.8, 2.0), rng.uniform(-1.0, 1.0)
        dr, dth = rng.uniform(-2.0, 2.0, 2)
        x = jnp.array([r, th, dr, dth])
        expected = [dr, dth, r * dth**2, -2.0 * dr * dth / r]
        np.testing.assert_allclose(derived(0.0, x, {"k": jnp.asarray(0.0)}), expected, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(by_hand(0.0, x, {"k": jnp.asarray(1.0)}), expected, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(by_hand(0.0, x, {"k": jnp.asarray(0.0)}), [dr, dth, 0.0, 0.0], atol=1e-15)


def test_velocity_terms_must_be_a_bool():
    with pytest.raises(TypeError, match="velocity_terms"):
        hj.Scene(1, lambda q, p: jnp.eye(1), lambda t, q, dq, p: 0 * q,
                 [hj.Constraint("floor", lambda t, q, p: q[0])], velocity_terms="yes")


# ----------------------------------------------------------------------------- compass gait

# Goswami, Thuilot and Espiau, "A study of the passive gait of a compass-like biped robot"
# (IJRR 1998): leg masses m at distance a from the foot (b from the hip), hip mass m_H, slope 3
# degrees (it enters at heel strike only; the swing phase below has angles from the vertical).
M_LEG, M_HIP, A, B, GRAV = 5.0, 10.0, 0.5, 0.5, 9.81
L = A + B
SLOPE = math.radians(3.0)


def textbook_acceleration(theta, dtheta):
    """The textbook swing phase, theta = (theta_ns, theta_s), stance foot pinned:
    M(theta) theta'' + C(theta, theta') theta' + g(theta) = 0."""
    tns, ts = theta
    dns, ds = dtheta
    c, s = math.cos(ts - tns), math.sin(ts - tns)
    M = np.array([[M_LEG * B**2, -M_LEG * L * B * c],
                  [-M_LEG * L * B * c, (M_HIP + M_LEG) * L**2 + M_LEG * A**2]])
    C = np.array([[0.0, M_LEG * L * B * s * ds],
                  [-M_LEG * L * B * s * dns, 0.0]])
    g = np.array([M_LEG * B * GRAV * math.sin(tns),
                  -(M_HIP * L + M_LEG * A + M_LEG * L) * GRAV * math.sin(ts)])
    return np.linalg.solve(M, -C @ np.asarray(dtheta) - g)


def _point_masses(q):
    """Hip, stance leg's and swing leg's masses in the plane; q = (x, z, theta_s, theta_ns), (x, z)
    the hip, the stance foot where the stance leg (angle theta_s from the vertical) ends."""
    hip = jnp.stack([q[0], q[1]])
    stance = hip - B * jnp.stack([jnp.sin(q[2]), jnp.cos(q[2])])
    swing = hip - B * jnp.stack([jnp.sin(q[3]), jnp.cos(q[3])])
    return hip, stance, swing


MASSES = (M_HIP, M_LEG, M_LEG)


def compass_mass(q, p):
    """M = sum_i m_i J_i^T J_i over the point masses: configuration-dependent (4 x 4)."""
    return sum(m * J.T @ J for m, J in zip(MASSES, jax.jacfwd(_point_masses)(q), strict=True))


def compass_forces(t, q, dq, p):
    return -jax.grad(lambda q_: GRAV * sum(m * P[1] for m, P in zip(MASSES, _point_masses(q_), strict=True)))(q)


@functools.cache
def compass_system():
    """The swing phase as a scene: a floating hip and two legs, the stance foot pinned at the
    origin by two bilateral constraints (one mode)."""
    scene = hj.Scene(
        4, compass_mass, compass_forces,
        [hj.Constraint("foot_x", lambda t, q, p: q[0] - L * jnp.sin(q[2]), kind="bilateral"),
         hj.Constraint("foot_z", lambda t, q, p: q[1] - L * jnp.cos(q[2]), kind="bilateral")],
        bounds=(-1.0, 1.0), names=("x", "z", "theta_s", "theta_ns"),
    )
    return hj.contact_system(scene, ["free"])


def compass_state(theta_ns, theta_s, dtheta_ns, dtheta_s):
    """The scene's state with the stance foot at the origin (hip on the stance leg's tip)."""
    return jnp.array([L * math.sin(theta_s), L * math.cos(theta_s), theta_s, theta_ns,
                      L * math.cos(theta_s) * dtheta_s, -L * math.sin(theta_s) * dtheta_s, dtheta_s, dtheta_ns])


def test_compass_gait_flow_matches_textbook_equations():
    flow = jax.jit(compass_system().modes[0].flow)
    rng = np.random.default_rng(2)
    for _ in range(5):
        tns, ts, dns, ds = rng.uniform(-0.6, 0.6, 4) * np.array([1, 1, 3, 3])
        dx = np.asarray(flow(0.0, compass_state(tns, ts, dns, ds), None))
        np.testing.assert_allclose(dx[[7, 6]], textbook_acceleration((tns, ts), (dns, ds)), rtol=0, atol=1e-10)


def test_compass_gait_swing_phase_against_scipy():
    from scipy.integrate import solve_ivp

    # A start of a swing phase on the 3 degree slope (down towards -x): both feet on the slope
    # (theta_ns + theta_s = -2 slope), the swing foot behind and uphill, both legs rotating downhill.
    tns, ts, dns, ds = -0.3 - SLOPE, 0.3 - SLOPE, -0.4, -1.1
    T = 0.4

    def rhs(t, y):
        return np.concatenate([y[2:], textbook_acceleration(y[:2], y[2:])])

    ref = solve_ivp(rhs, (0.0, T), [tns, ts, dns, ds], rtol=1e-12, atol=1e-12, method="DOP853").y[:, -1]
    sol = hj.simulate(compass_system(), compass_state(tns, ts, dns, ds), 0, 0.0, T, None,
                      stepsize_controller=TIGHT)
    assert sol.status == hj.Status.T1_REACHED
    x = np.asarray(sol.final_state)
    np.testing.assert_allclose(x[[3, 2, 7, 6]], ref, rtol=0, atol=1e-8)
    # The hip stays on the stance leg's tip (the pin's rows held).
    np.testing.assert_allclose(x[:2], [L * math.sin(x[2]), L * math.cos(x[2])], atol=1e-9)
