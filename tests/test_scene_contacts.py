"""Scenes: a contact armed only under a condition, and two frictional contacts that stop at one
instant, each against a closed form."""

import functools
import math

import diffrax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj

TIGHT = diffrax.PIDController(rtol=1e-11, atol=1e-11)
G = 9.81


# ----------------------------------------------------------------------------- an armed contact

ARMED_ARGS = {"g": jnp.asarray(G)}


@functools.cache
def armed_floor_system():
    """A point (x, z) over a floor z >= 0 that can be hit only where x >= 0 (built on first use)."""
    floor = hj.Constraint("floor", lambda t, q, p: q[1], armed=lambda t, q, p: q[0])
    scene = hj.Scene(
        2,
        lambda q, p: jnp.eye(2),
        lambda t, q, dq, p: jnp.stack([0.0 * q[0], -p["g"] + 0.0 * q[1]]),
        [floor],
        bounds=((-1.0, -1.0, -3.0, -3.0), (1.0, 1.0, 3.0, 3.0)),
        names=("x", "z"),
    )
    return hj.contact_system(scene, ["free"], ARMED_ARGS)


def test_armed_floor_is_passed_through_where_disarmed_and_hit_where_armed():
    system = armed_floor_system()
    # Built: free and floor (the lift-off, lambda = g > 0, is pruned into "unbuilt: free").
    assert [m.name for m in system.modes] == ["free", "floor", "unbuilt: free"]
    # The impact's witness lies where the floor is armed (x >= 0).
    (_, _, kind, _, text), = [a for a in system.achievable if a[2] == "impact"]
    x_witness = float(text.split("q=(")[1].split(",")[0])
    assert x_witness >= 0.0
    # The guard max(z, -x): positive below the floor where disarmed, the gap where armed.
    guard = system.transitions[0].guard
    assert float(guard(0.0, jnp.array([-0.5, -0.2, 0.0, 0.0]), ARMED_ARGS)) == pytest.approx(0.5)
    assert float(guard(0.0, jnp.array([0.5, -0.2, 0.0, 0.0]), ARMED_ARGS)) == pytest.approx(-0.2)
    # Thrown up from below the floor at x = -0.5, moving right at 1: it rises through the floor
    # while disarmed, is armed at x = 0 (t = 0.5, z > 0) and lands at z0 + v0 t - g t^2 / 2 = 0.
    z0, v0, vx = -0.1, 3.0, 1.0
    sol = hj.simulate(
        system, jnp.array([-0.5, z0, vx, v0]), "free", 0.0, 1.0, ARMED_ARGS, stepsize_controller=TIGHT
    )
    t_hit = (v0 + math.sqrt(v0**2 + 2 * G * z0)) / G
    assert int(sol.num_events) == 1 and system.modes[int(sol.final_mode)].name == "floor"
    np.testing.assert_allclose(sol.event_times[0], t_hit, rtol=0, atol=1e-10)
    # Plastic: it slides on at vx.
    np.testing.assert_allclose(sol.final_state, [-0.5 + vx * 1.0, 0.0, vx, 0.0], atol=1e-10)


# ----------------------------------------------------------------------------- two ends that stop together

ROD_MU = 0.3
ROD_ARGS = {"m": jnp.asarray(1.0), "g": jnp.asarray(G), "L": jnp.asarray(1.0), "mu": jnp.asarray(ROD_MU)}


@functools.cache
def rod_system():
    """The rod with friction at both ends (built on first use)."""
    return hj.contact_system(hj.examples.rod_scene(friction=("left", "right")), ["free"], ROD_ARGS)


# 16 states (45 modes, 128 transitions): its build and the compile of `simulate` take minutes on
# 2 cores.
@pytest.mark.slow
@pytest.mark.costly  # building the rod's 16 contact states and compiling its run: tens of minutes
def test_rod_dropped_flat_lands_on_both_ends_slides_and_sticks_at_the_closed_form_times():
    # Dropped flat from height z0 with speed v0 along x: both ends land at sqrt(2 z0 / g) (taken
    # one after the other at that instant), slide with deceleration mu g (each end carries
    # m g / 2 and its friction mu m g / 2, no torque) and stop together after v0 / (mu g).
    x0, z0, v0 = 0.1, 0.5, 1.0
    rod = rod_system()
    sol = hj.simulate(
        rod,
        jnp.array([x0, z0, 0.0, v0, 0.0, 0.0]),
        "free",
        0.0,
        1.0,
        ROD_ARGS,
        stepsize_controller=TIGHT,
        saveat=jnp.array([0.9]),
        max_epochs=8,
    )
    t1 = math.sqrt(2 * z0 / G)
    t_stop = v0 / (ROD_MU * G)
    names = [rod.modes[int(m)].name for m in sol.epoch_modes[: int(sol.num_events) + 1]]
    assert names == ["free", "left:slip+", "left:slip++right:slip+", "left:stick+right:stick"]
    assert sol.status == hj.Status.T1_REACHED
    np.testing.assert_allclose(sol.event_times[:3], [t1, t1, t1 + t_stop], rtol=0, atol=1e-9)
    x_end = x0 + v0 * t1 + v0**2 / (2 * ROD_MU * G)
    np.testing.assert_allclose(sol.final_state, [x_end, 0.0, 0.0, 0.0, 0.0, 0.0], atol=1e-9)
    # At rest: m g / 2 on each end, no tangential force (least norm; columns left, right, left.t,
    # right.t).
    np.testing.assert_allclose(rod.contact_forces(sol), [[G / 2, G / 2, 0.0, 0.0]], atol=1e-9)
