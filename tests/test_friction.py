"""Coulomb friction in scenes: stick and slip modes, checked against closed forms (a block on a
slope, a block stopping on flat ground) and against a rod's motion computed by hand with scipy."""

import math

import diffrax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj

TIGHT = diffrax.PIDController(rtol=1e-11, atol=1e-11)
G, MU = 9.81, 0.5


# ----------------------------------------------------------------------------- a block on a slope


def slope_forces(t, q, dq, p):
    # q = (s, n): along and normal to a slope of angle theta; gravity is -g (sin, cos) there.
    return -p["g"] * jnp.stack([jnp.sin(p["theta"]) + 0 * q[0], jnp.cos(p["theta"]) + 0 * q[1]])


FLOOR = hj.Constraint("floor", lambda t, q, p: q[1], tangent=lambda t, q, p: q[0], friction=lambda p: p["mu"])
BLOCK_SCENE = hj.Scene(
    2, lambda q, p: jnp.eye(2), slope_forces, [FLOOR], q_range=(-1.0, 1.0), dq_range=(-2.0, 2.0)
)
# tan(0.3) = 0.31 < mu = 0.5 < tan(0.6) = 0.68: the block sticks on the first two slopes, slides
# down the third.
THETAS = (0.0, 0.3, 0.6)


def block_args(theta):
    return {"g": jnp.asarray(G), "theta": jnp.asarray(theta), "mu": jnp.asarray(MU)}


BLOCK = hj.contact_system(
    BLOCK_SCENE, ["floor:stick", "floor:slip+"], args_values=[block_args(th) for th in THETAS]
)


def run_block(x0, mode, theta):
    # x0 and the mode as arrays: one compile serves every run.
    return hj.simulate(
        BLOCK,
        jnp.asarray(x0),
        jnp.asarray(BLOCK.mode_index(mode)),
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
    edges = {(kind, src, tgt) for src, tgt, kind, _, _ in BLOCK.achievable}
    assert edges == {
        ("slip", "floor:stick", "floor:slip-"),
        ("stick", "floor:slip+", "floor:stick"),
        ("stick", "floor:slip-", "floor:stick"),
        ("reverse", "floor:slip+", "floor:slip-"),
    }
    text = repr(BLOCK)
    assert "only for args_values [2]" in text and "pruned: lift-off floor" in text


def test_block_sticks_on_a_shallow_slope():
    th = THETAS[1]
    sol = run_block([0.0, 0.0, 0.0, 0.0], "floor:stick", th)
    assert mode_names(BLOCK, sol) == ["floor:stick"] and sol.status == hj.Status.T1_REACHED
    np.testing.assert_allclose(sol.final_state, 0.0, atol=1e-12)
    # Statics: lambda_n = g cos(theta), lambda_t = g sin(theta) (columns floor, floor.t).
    np.testing.assert_allclose(BLOCK.contact_forces(sol), [[G * math.cos(th), G * math.sin(th)]], atol=1e-10)


def test_block_slides_down_a_steep_slope():
    th = THETAS[2]
    sol = run_block([0.0, 0.0, 0.0, 0.0], "floor:stick", th)
    assert mode_names(BLOCK, sol) == ["floor:stick", "floor:slip-"]
    np.testing.assert_allclose(sol.event_times[0], 0.0, atol=1e-12)
    a = G * (math.sin(th) - MU * math.cos(th))  # down the slope
    np.testing.assert_allclose(sol.final_state, [-a / 2, 0.0, -a, 0.0], atol=1e-9)
    # Slipping, the tangential column is the friction force mu lambda_n, up the slope.
    lam_n = G * math.cos(th)
    np.testing.assert_allclose(BLOCK.contact_forces(sol), [[lam_n, MU * lam_n]], atol=1e-10)


def test_block_stops_on_flat_ground_at_v0_over_mu_g():
    v0 = 1.0
    sol = run_block([0.0, 0.0, v0, 0.0], "floor:slip+", THETAS[0])
    assert mode_names(BLOCK, sol) == ["floor:slip+", "floor:stick"]
    t_stop = v0 / (MU * G)  # deceleration mu g
    np.testing.assert_allclose(sol.event_times[0], t_stop, rtol=0, atol=1e-10)
    np.testing.assert_allclose(sol.final_state, [v0**2 / (2 * MU * G), 0.0, 0.0, 0.0], atol=1e-10)
    np.testing.assert_allclose(BLOCK.contact_forces(sol), [[G, 0.0]], atol=1e-10)


# ----------------------------------------------------------------------------- definitions


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
