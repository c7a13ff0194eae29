"""Coulomb friction in scenes: stick and slip modes, checked against closed forms (a block on a
slope, a block stopping on flat ground) and against a rod's motion computed by hand with scipy."""

import functools
import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj
from hybridjax import examples

from helpers import evaluations_agree

TIGHT = diffrax.PIDController(rtol=1e-11, atol=1e-11)
G, MU = 9.81, 0.5


# ----------------------------------------------------------------------------- a block on a slope


def slope_forces(t, q, dq, p):
    # q = (s, n): along and normal to a slope of angle theta; gravity is -g (sin, cos) there.
    return -p["g"] * jnp.stack([jnp.sin(p["theta"]) + 0 * q[0], jnp.cos(p["theta"]) + 0 * q[1]])


FLOOR = hj.Constraint("floor", lambda t, q, p: q[1], tangent=lambda t, q, p: q[0], friction=lambda p: p["mu"])
BLOCK_SCENE = hj.Scene(
    2, lambda q, p: jnp.eye(2), slope_forces, [FLOOR], bounds=((-1.0, -1.0, -2.0, -2.0), (1.0, 1.0, 2.0, 2.0))
)
# tan(0.3) = 0.31 < mu = 0.5 < tan(0.6) = 0.68: the block sticks on the first two slopes, slides
# down the third.
THETAS = (0.0, 0.3, 0.6)


def block_args(theta):
    return {"g": jnp.asarray(G), "theta": jnp.asarray(theta), "mu": jnp.asarray(MU)}


@functools.cache
def block_system():
    """The block's system over the three slopes, built on first use (collection compiles nothing)."""
    return hj.contact_system(
        BLOCK_SCENE, ["floor:stick", "floor:slip+"], args_values=[block_args(th) for th in THETAS]
    )


def run_block(x0, mode, theta):
    # x0 and the mode as arrays: one compile serves every run.
    return hj.simulate(
        block_system(),
        jnp.asarray(x0),
        jnp.asarray(block_system().mode_index(mode)),
        0.0,
        1.0,
        block_args(theta),
        stepsize_controller=TIGHT,
        saveat=jnp.array([0.5]),
        max_epochs=8,
    )


def mode_names(system, sol):
    return [system.modes[int(m)].name for m in sol.epoch_modes[: int(sol.num_events) + 1]]


def test_block_modes_by_hand():
    # On the slope the stick force is lambda_t = g sin(theta) (up the slope), lambda_n = g cos:
    # it leaves the cone (slip-, down the slope) only where tan(theta) > mu, the third angle. A
    # sliding block (either way) decelerates where tan(theta) < mu and stops: it sticks there.
    # Sliding up the steep slope it stops and the stick force g sin > mu g cos sends it back
    # down (slip+ -> slip-). Slip+ never follows: the slope pulls towards -s. No lift-off:
    # lambda_n = g cos(theta) > 0.
    edges = {(kind, src, tgt) for src, tgt, kind, _, _ in block_system().achievable}
    assert edges == {
        ("slip", "floor:stick", "floor:slip-"),
        ("stick", "floor:slip+", "floor:stick"),
        ("stick", "floor:slip-", "floor:stick"),
        ("reverse", "floor:slip+", "floor:slip-"),
    }
    text = repr(block_system())
    assert "only for args_values [2]" in text and "pruned: lift-off floor" in text


def test_block_sticks_on_a_shallow_slope():
    th = THETAS[1]
    sol = run_block([0.0, 0.0, 0.0, 0.0], "floor:stick", th)
    assert mode_names(block_system(), sol) == ["floor:stick"] and sol.status == hj.Status.T1_REACHED
    np.testing.assert_allclose(sol.final_state, 0.0, atol=1e-12)
    # Statics: lambda_n = g cos(theta), lambda_t = g sin(theta) (columns floor, floor.t).
    forces = block_system().contact_forces(sol)
    np.testing.assert_allclose(forces, [[G * math.cos(th), G * math.sin(th)]], atol=1e-10)


def test_block_slides_down_a_steep_slope():
    th = THETAS[2]
    sol = run_block([0.0, 0.0, 0.0, 0.0], "floor:stick", th)
    assert mode_names(block_system(), sol) == ["floor:stick", "floor:slip-"]
    np.testing.assert_allclose(sol.event_times[0], 0.0, atol=1e-12)
    a = G * (math.sin(th) - MU * math.cos(th))  # down the slope
    np.testing.assert_allclose(sol.final_state, [-a / 2, 0.0, -a, 0.0], atol=1e-9)
    # Slipping, the tangential column is the friction force mu lambda_n, up the slope.
    lam_n = G * math.cos(th)
    np.testing.assert_allclose(block_system().contact_forces(sol), [[lam_n, MU * lam_n]], atol=1e-10)


def test_block_stops_on_flat_ground_at_v0_over_mu_g():
    v0 = 1.0
    sol = run_block([0.0, 0.0, v0, 0.0], "floor:slip+", THETAS[0])
    assert mode_names(block_system(), sol) == ["floor:slip+", "floor:stick"]
    t_stop = v0 / (MU * G)  # deceleration mu g
    np.testing.assert_allclose(sol.event_times[0], t_stop, rtol=0, atol=1e-10)
    np.testing.assert_allclose(sol.final_state, [v0**2 / (2 * MU * G), 0.0, 0.0, 0.0], atol=1e-10)
    np.testing.assert_allclose(block_system().contact_forces(sol), [[G, 0.0]], atol=1e-10)


# ----------------------------------------------------------------------------- definitions


def test_mask_evaluation_equals_the_modes_own_functions():
    """The block's one masked evaluation per call (`FrictionEvaluation`: stick and slip modes,
    cone, stop and Painleve guards, impacts with their outcome) against its modes' and
    transitions' own functions, at states across the scene's ranges, at rest and in contact.
    The start test's jets to first order (L0, L1, the band): the modes' own functions' L2 and
    L3, nested jvps through every mode's contact solve, compile for over a minute on 2 cores;
    the frictionless scenes' evaluations are compared to L3 (test_scenes.py)."""
    assert block_system().form == "mask" and block_system().mode_indexed() is block_system().evaluation
    rng = np.random.default_rng(2)
    xs = rng.uniform([-1.0, -0.5, -3.0, -3.0], [1.0, 0.5, 3.0, 3.0], size=(48, 4))
    xs[:12, 1] = 0.0  # on the floor
    xs[:6, 3] = 0.0  # on it at rest (normal rate 0)
    xs[6:12, 2:] = 0.0  # at rest: the stop guards' choice is read
    assert evaluations_agree(block_system(), block_args(0.3), jnp.asarray(xs), jet_order=1) > 500


def test_negative_friction_coefficient_is_named():
    with pytest.raises(ValueError, match="Constraint 'floor'.*friction coefficient.*-0.2"):
        hj.Constraint("floor", lambda t, q, p: q[1], tangent=lambda t, q, p: q[0], friction=-0.2)
    with pytest.raises(ValueError, match="'floor'.*`friction` needs.*`tangent`"):
        hj.Constraint("floor", lambda t, q, p: q[1], friction=0.2)
    # A coefficient given as a function of args is checked when the system is built.
    bad = {"g": jnp.asarray(G), "theta": jnp.asarray(0.0), "mu": jnp.asarray(-0.1)}
    with pytest.raises(ValueError, match="Constraint 'floor'.*friction coefficient must be >= 0"):
        hj.contact_system(BLOCK_SCENE, ["floor:stick"], bad)
    with pytest.raises(ValueError, match="'floor' has friction: name its state"):
        hj.contact_system(BLOCK_SCENE, ["floor"], block_args(0.0))


# ----------------------------------------------------------------------------- a rod, two frictional ends

ROD_MU = 0.3
ROD_ARGS = {"m": jnp.asarray(1.0), "g": jnp.asarray(G), "L": jnp.asarray(1.0), "mu": jnp.asarray(ROD_MU)}


def rod_by_hand(x0, z0, phi0, mu, L=1.0, g=G, t_end=2.0):
    """The rod (centre (x, z), angle phi, m = 1, I = L^2 / 12, friction mu at its left end only)
    dropped from rest with its left end lower, computed without hybridjax, phase by phase.

    - Free fall to the left end's landing; its frictionless plastic impact by hand.
    - On the left end (z = h sin phi, h = L/2; the end's x-speed v_e = x' + h sin(phi) phi'):
      slipping with sign s, friction -mu s lambda_n at the end: m x'' = -mu s lambda_n,
      m z'' = lambda_n - m g, I phi'' = -h lambda_n (cos phi + mu s sin phi), with
      z'' = h (cos phi phi'' - sin phi phi'^2), solved for phi'' and lambda_n; sticking, the rod
      pivots about the fixed end: (I + m h^2) phi'' = -m g h cos phi, lambda_t = m x''.
      Events: v_e = 0 (stick if the sticking force is in the cone, else slip back), the cone
      |lambda_t| = mu lambda_n (slip against lambda_t), the right end's landing phi = 0.
    - The right end (frictionless) lands flat: both normal impulses stop z' and phi' (x' kept,
      no tangential impulse); both positive (checked). Flat, the left end slips with x' at
      deceleration mu g / 2 (each lambda_n = m g / 2, no torque) and stops; the rod rests.

    Returns the mode names, the event times and the final state (x, z, phi, x', z', phi')."""
    from scipy.integrate import solve_ivp

    m, I, h = 1.0, L**2 / 12, L / 2

    def dynamics(y, s):
        x, phi, vx, w = y
        c, sn = math.cos(phi), math.sin(phi)
        if s == 0:  # sticking: pivot about the end
            ddphi = -m * g * h * c / (I + m * h * h)
            ddx = -h * (sn * ddphi + c * w * w)
            lam_n = m * (g + h * (c * ddphi - sn * w * w))
            return ddx, ddphi, lam_n, m * ddx
        k = c + mu * s * sn
        D = I + m * h * h * c * k
        assert D > 0  # no Painleve inconsistency along this motion
        ddphi = -h * k * m * (g - h * sn * w * w) / D
        lam_n = m * g + m * h * (c * ddphi - sn * w * w)
        return -mu * s * lam_n / m, ddphi, lam_n, -mu * s * lam_n

    t = math.sqrt(2 * (z0 - h * math.sin(phi0)) / g)
    # Left end's plastic impact: J = (0, 1, -h cos phi), P = -J dq / (J M^-1 J^T).
    c = h * math.cos(phi0)
    vz = -g * t
    P = -vz / (1 / m + c * c / I)
    w = -c * P / I
    y = [x0, phi0, 0.0, w]
    v_e = h * math.sin(phi0) * w
    s = 1 if v_e >= 0 else -1
    name = {1: "left:slip+", -1: "left:slip-", 0: "left:stick"}
    modes, times = ["free", name[s]], [t]
    while True:
        rhs = lambda t_, y_, s=s: [y_[2], y_[3], *dynamics(y_, s)[:2]]  # noqa: E731
        events = [lambda t_, y_: y_[1]]  # the right end lands
        if s != 0:
            events.append(lambda t_, y_, s=s: s * (y_[2] + h * math.sin(y_[1]) * y_[3]))
        else:
            events.append(lambda t_, y_: mu * dynamics(y_, 0)[2] - dynamics(y_, 0)[3])
            events.append(lambda t_, y_: mu * dynamics(y_, 0)[2] + dynamics(y_, 0)[3])
        events.append(lambda t_, y_, s=s: dynamics(y_, s)[2])  # lift-off
        for e in events:
            e.terminal, e.direction = True, -1
        sol = solve_ivp(rhs, (t, t + 5), y, events=events, rtol=1e-12, atol=1e-12)
        which = [i for i, te in enumerate(sol.t_events) if len(te)]
        assert len(which) == 1 and which[0] != len(events) - 1  # one event, not a lift-off
        i = which[0]
        t, y = sol.t_events[i][0], list(sol.y_events[i][0])
        times.append(t)
        if i == 0:
            break
        if s != 0:  # stopped: stick if the sticking force is in the cone, else slip back
            _, _, lam_n, lam_t = dynamics(y, 0)
            s = 0 if abs(lam_t) <= mu * lam_n else (-1 if lam_t > 0 else 1)
        else:  # the cone is left: slip against the force that could not hold it
            s = -1 if i == 1 else 1
        modes.append(name[s])
    # Right end lands (phi = 0, z = 0, z' = h phi'): both normal impulses.
    x, _, vx, w = y
    vz = h * w
    P_left, P_right = 0.5 * (-m * vz + I * w / h), 0.5 * (-m * vz - I * w / h)
    assert P_left > 0 and P_right > 0
    # Flat: the left end slips with x' (friction mu m g / 2, each lambda_n = m g / 2, no torque
    # at phi = 0) and stops; sticking there needs no tangential force (it is in the cone).
    t_stop = abs(vx) / (mu * g / 2)
    modes += ["left:slip++right" if vx >= 0 else "left:slip-+right", "left:stick+right"]
    times.append(t + t_stop)
    x += vx * t_stop / 2
    return modes, times, [x, 0.0, 0.0, 0.0, 0.0, 0.0]


@functools.cache
def rod_system():
    # Built on first use, so that deselecting the costly test skips the build too.
    return hj.contact_system(examples.rod_scene(friction=("left",)), ["free"], ROD_ARGS)


def run_rod(x0, mode, mu, t1):
    args = dict(ROD_ARGS, mu=jnp.asarray(mu))
    return hj.simulate(
        rod_system(),
        jnp.asarray(x0),
        jnp.asarray(rod_system().mode_index(mode)),
        0.0,
        t1,
        args,
        stepsize_controller=TIGHT,
        saveat=jnp.array([0.9]),
        max_epochs=16,
    )


# The system has 8 states (20 modes, 43 transitions): its build and compile take about two
# minutes on 2 cores, so it runs with the costly cases. In every run, the rod's left end with
# friction: the Painleve test below (its slip states, their guards and a jam).
@pytest.mark.costly
def test_rod_lands_slips_back_lands_and_stops_as_computed_by_hand():
    modes, times, final = rod_by_hand(0.1, 0.5, 0.3, ROD_MU)
    # The left end lands slipping to -x, stops and slips back (sticking would need more than
    # mu lambda_n), the right end lands flat, the rod slides on and the left end sticks.
    assert modes == ["free", "left:slip-", "left:slip+", "left:slip++right", "left:stick+right"]
    sol = run_rod([0.1, 0.5, 0.3, 0.0, 0.0, 0.0], "free", ROD_MU, 1.0)
    rod = rod_system()
    assert mode_names(rod, sol) == modes
    np.testing.assert_allclose(sol.event_times[: len(times)], times, rtol=0, atol=1e-8)
    np.testing.assert_allclose(sol.final_state, final, atol=1e-8)
    # At rest on both ends: lambda_n = m g / 2 each, no tangential force (columns left, right,
    # left.t).
    np.testing.assert_allclose(rod.contact_forces(sol), [[G / 2, G / 2, 0.0]], atol=1e-9)


# ----------------------------------------------------------------------------- Painleve's paradox

# A uniform rod (I = m h^2 / 3, h = L / 2) slipping with sign s on its left end at angle phi has
# the normal equation's coefficient D / (m I), D = I + m h^2 cos(phi) (cos(phi) + mu s sin(phi)),
# which is <= 0 somewhere only for mu > 4/3 (D0 = I + m h^2 cos(phi)^2 without friction). With
# mu = 2 and s = -1, D = 0 at phi* = 0.652. The execution ends where D = RHO D0 (docs: Scenes,
# Painleve's paradox).
PAINLEVE_MU, RHO = 2.0, 1e-6


@functools.cache
def painleve_system():
    # The rod with its left end only: its slip states and their terminal modes.
    rod = examples.rod_scene(friction=("left",))
    scene = hj.Scene(
        rod.dim,
        rod.mass,
        rod.forces,
        rod.constraints[:1],
        bounds=rod.bounds,
        names=rod.names,
    )
    return hj.contact_system(scene, ["left:slip-"], dict(ROD_ARGS, mu=jnp.asarray(PAINLEVE_MU)))


def slip_on_left_end_by_hand(x0, phi0, vx0, mu, t_end, L=1.0, g=G):
    """The rod slipping to -x on its left end (z = h sin phi, m = 1), from phi0 at rest in phi,
    integrated with scipy towards the jam D = I + m h^2 cos(phi) (cos(phi) - mu sin(phi)) = 0:
    I phi'' = -h lambda_n (cos phi - mu sin phi), m x'' = mu lambda_n and
    lambda_n = m g + m h (cos(phi) phi'' - sin(phi) phi'^2) (phi'' and lambda_n grow as 1 / D).
    Returns the time D falls to RHO (I + m h^2 cos(phi)^2) and the state (x, phi, x', phi')
    then; checks that the end slips to -x and lambda_n > 0 on the way."""
    from scipy.integrate import solve_ivp

    m, I, h = 1.0, L**2 / 12, L / 2

    def rates(t, y):
        x, phi, vx, w = y
        c, sn = math.cos(phi), math.sin(phi)
        k = c - mu * sn
        ddphi = -h * k * m * (g - h * sn * w * w) / (I + m * h * h * c * k)
        lam_n = m * g + m * h * (c * ddphi - sn * w * w)
        return [vx, w, mu * lam_n / m, ddphi], lam_n

    def jam(t, y):
        c, sn = math.cos(y[1]), math.sin(y[1])
        return I + m * h * h * c * (c - mu * sn) - RHO * (I + m * h * h * c * c)

    def end_speed(t, y):
        return y[2] + h * math.sin(y[1]) * y[3]

    jam.terminal, jam.direction = True, -1
    sol = solve_ivp(
        lambda t, y: rates(t, y)[0],
        (0.0, t_end),
        [x0, phi0, vx0, 0.0],
        events=[jam],
        rtol=1e-12,
        atol=1e-12,
        dense_output=True,
    )
    assert len(sol.t_events[0]) == 1
    for t in np.linspace(0.0, sol.t_events[0][0], 50):
        y = sol.sol(t)
        assert end_speed(t, y) < 0 and rates(t, y)[1] > 0
    return sol.t_events[0][0], sol.y_events[0][0]


@pytest.mark.slow
def test_painleve_jam_ends_blocked_at_the_time_computed_by_hand():
    rod = painleve_system()
    h, I = 0.5, 1.0 / 12
    # The watched value is det(J M^-1 W^T) - RHO det(J M^-1 J^T) = (D - RHO D0) / (m I), either sign.
    painleve = {tr.source: tr for tr in rod.transitions if tr.name.startswith("painleve")}
    for s, state in ((-1, "left:slip-"), (1, "left:slip+")):
        for phi in (-0.9, 0.0, 0.4, 0.652, 0.9):
            x = jnp.array([0.0, h * math.sin(phi), phi, -1.0, 0.0, 0.0])
            D = I + h * h * math.cos(phi) * (math.cos(phi) + PAINLEVE_MU * s * math.sin(phi))
            D0 = I + h * h * math.cos(phi) ** 2
            assert float(painleve[state].guard(0.0, x, dict(ROD_ARGS, mu=PAINLEVE_MU))) == pytest.approx(
                (D - RHO * D0) / I, abs=1e-12
            )
    t_jam, (x_j, phi_j, vx_j, w_j) = slip_on_left_end_by_hand(0.0, 0.62, -20.0, PAINLEVE_MU, 1.0)
    args = dict(ROD_ARGS, mu=jnp.asarray(PAINLEVE_MU))
    run = jax.jit(
        lambda x0: hj.simulate(
            rod, x0, rod.mode_index("left:slip-"), 0.0, 1.0, args, stepsize_controller=TIGHT, max_epochs=4
        )
    )
    # Slipping into the jam: the execution ends there, BLOCKED, in the terminal mode.
    sol = run(jnp.array([0.0, h * math.sin(0.62), 0.62, -20.0, 0.0, 0.0]))
    assert sol.status == hj.Status.BLOCKED
    assert mode_names(rod, sol) == ["left:slip-", "inconsistent: left:slip-"]
    assert float(sol.event_times[0]) == pytest.approx(t_jam, abs=1e-9)
    np.testing.assert_allclose(np.asarray(sol.final_state)[[0, 2, 3, 5]], [x_j, phi_j, vx_j, w_j], rtol=1e-7)
    # Started inside the inconsistent region: blocked at once, the state kept, no NaN.
    x0 = jnp.array([0.0, h * math.sin(0.9), 0.9, -5.0, 0.0, 0.0])
    sol = run(x0)
    assert sol.status == hj.Status.BLOCKED and float(sol.event_times[0]) == 0.0
    np.testing.assert_array_equal(sol.final_state, x0)
