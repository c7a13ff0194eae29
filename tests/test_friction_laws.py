"""Tangential laws as objects: static and kinetic friction, and a law written here in one class,
each read by the friction builder both as the slip force and as the stick limit, checked against
the closed forms of a block on a slope and on flat ground."""

import functools
import math
from collections.abc import Callable

import diffrax
import jax.numpy as jnp
import pytest

import hybridjax as hj

TIGHT = diffrax.PIDController(rtol=1e-11, atol=1e-11)
G, THETA, MU_S, MU_K = 9.81, 0.3, 0.5, 0.2  # mu_k < tan(theta) = 0.309 < mu_s
V0, T1 = 1.0, 1.0


def slope_forces(t, q, dq, p):
    # q = (s, n): along and normal to a slope of angle theta; gravity is -g (sin, cos) there.
    return -p["g"] * jnp.stack([jnp.sin(p["theta"]) + 0 * q[0], jnp.cos(p["theta"]) + 0 * q[1]])


def block_system(friction, initial, args_values):
    floor = hj.Constraint("floor", lambda t, q, p: q[1], tangent=lambda t, q, p: q[0], friction=friction)
    scene = hj.Scene(
        2, lambda q, p: jnp.eye(2), slope_forces, [floor], bounds=((-1.0, -1.0, -2.0, -2.0), (1.0, 1.0, 2.0, 2.0))
    )
    return hj.contact_system(scene, initial, args_values=args_values)


def slope_args(theta=THETA, **mus):
    return {"g": jnp.asarray(G), "theta": jnp.asarray(theta), **{k: jnp.asarray(v) for k, v in mus.items()}}


# Built on first use, so that collecting the tests compiles nothing.
@functools.cache
def static_kinetic_system():
    return block_system(hj.StaticKineticCoulomb(MU_S, MU_K), ["floor:slip+"], [slope_args()])


@functools.cache
def coulomb_system():
    return block_system(hj.Coulomb(MU_K), ["floor:slip+"], [slope_args()])


def run(system, x0, mode, args):
    # x0, the mode and args as arrays: one compile per system serves every run.
    return hj.simulate(
        system, jnp.asarray(x0), jnp.asarray(system.mode_index(mode)), 0.0, T1, args,
        stepsize_controller=TIGHT, max_epochs=8,
    )  # fmt: skip


def mode_names(system, sol):
    return [system.modes[int(m)].name for m in sol.epoch_modes[: int(sol.num_events) + 1]]


# ----------------------------------------------------------------------------- static and kinetic

# Sliding up the slope, gravity and kinetic friction both decelerate the block.
A_UP = G * (math.sin(THETA) + MU_K * math.cos(THETA))
T_STOP, S_STOP = V0 / A_UP, V0**2 / (2 * A_UP)


def test_static_kinetic_block_stops_up_the_slope_and_sticks():
    # Stopped, the force needed to hold it, lambda_t = g sin(theta), is within mu_s g cos(theta):
    # it sticks for good.
    system = static_kinetic_system()
    sol = run(system, [0.0, 0.0, V0, 0.0], "floor:slip+", slope_args())
    assert mode_names(system, sol) == ["floor:slip+", "floor:stick"] and sol.status == hj.Status.T1_REACHED
    assert abs(float(sol.event_times[0]) - T_STOP) < 1e-8
    assert abs(float(sol.final_state[0]) - S_STOP) < 1e-8
    assert abs(float(sol.final_state[2])) < 1e-10


def test_coulomb_block_with_the_kinetic_coefficient_slides_back_down():
    # With mu = mu_k < tan(theta) the stop cannot stick: it slips back down with acceleration
    # g (sin(theta) - mu_k cos(theta)) from where it stopped.
    system = coulomb_system()
    sol = run(system, [0.0, 0.0, V0, 0.0], "floor:slip+", slope_args())
    assert mode_names(system, sol) == ["floor:slip+", "floor:slip-"]
    assert abs(float(sol.event_times[0]) - T_STOP) < 1e-8
    a_down = G * (math.sin(THETA) - MU_K * math.cos(THETA))
    s1 = S_STOP - a_down * (T1 - T_STOP) ** 2 / 2
    assert abs(float(sol.final_state[0]) - s1) < 1e-8
    assert abs(float(sol.final_state[2]) + a_down * (T1 - T_STOP)) < 1e-8


# ----------------------------------------------------------------------------- a law in one class


class AnisotropicCoulomb(hj.AbstractTangentialLaw):
    """Coulomb friction with `mu_pos` against motion towards +b and `mu_neg` against motion
    towards -b (functions of args): slip s feels -mu_s s lambda_n, and sticking holds while
    -mu_pos lambda_n <= lambda_t <= mu_neg lambda_n."""

    mu_pos: Callable
    mu_neg: Callable
    states = ("stick", "slip+", "slip-")

    def holds_tangent(self, state):
        return state == "stick"

    def slip_sign(self, state):
        return {"slip+": 1.0, "slip-": -1.0}.get(state, 0.0)

    def slip_coefficient(self, state, args):
        return self.mu_pos(args) if state == "slip+" else self.mu_neg(args)

    def stick_limit(self, d, args):
        return self.mu_pos(args) if d > 0 else self.mu_neg(args)

    def changes(self, state):
        if state == "stick":
            return (("slip", 1.0, "slip+"), ("slip", -1.0, "slip-"))
        return (("stop", True, "stick"), ("stop", None, "slip-" if state == "slip+" else "slip+"))


# On flat ground, with different coefficients each way; on the slope, the block at rest is held
# by the limit against sliding down (mu_neg > tan(theta) > mu_pos) or not (the two swapped).
FLAT = slope_args(0.0, mu_pos=0.3, mu_neg=0.6)
HELD_ON_SLOPE = slope_args(mu_pos=0.2, mu_neg=0.5)
FREED_ON_SLOPE = slope_args(mu_pos=0.5, mu_neg=0.2)


@functools.cache
def anisotropic_system():
    law = AnisotropicCoulomb(lambda p: p["mu_pos"], lambda p: p["mu_neg"])
    return block_system(law, ["floor:slip+", "floor:slip-", "floor:stick"], [FLAT, HELD_ON_SLOPE, FREED_ON_SLOPE])


@pytest.mark.parametrize("direction, mu", [(1.0, 0.3), (-1.0, 0.6)])
def test_law_written_in_one_class_stops_each_way_at_v0_over_its_mu_g(direction, mu):
    system = anisotropic_system()
    mode = "floor:slip+" if direction > 0 else "floor:slip-"
    sol = run(system, [0.0, 0.0, direction * V0, 0.0], mode, FLAT)
    assert mode_names(system, sol) == [mode, "floor:stick"]
    assert abs(float(sol.event_times[0]) - V0 / (mu * G)) < 1e-8
    assert abs(float(sol.final_state[0]) - direction * V0**2 / (2 * mu * G)) < 1e-8


def test_law_written_in_one_class_holds_on_the_slope_by_its_downhill_limit():
    system = anisotropic_system()
    held = run(system, [0.0, 0.0, 0.0, 0.0], "floor:stick", HELD_ON_SLOPE)
    assert mode_names(system, held) == ["floor:stick"] and abs(float(held.final_state[0])) < 1e-12
    freed = run(system, [0.0, 0.0, 0.0, 0.0], "floor:stick", FREED_ON_SLOPE)
    assert mode_names(system, freed) == ["floor:stick", "floor:slip-"]
    a_down = G * (math.sin(THETA) - 0.2 * math.cos(THETA))
    assert abs(float(freed.final_state[0]) + a_down * T1**2 / 2) < 1e-8


# ----------------------------------------------------------------------------- construction


def gap(t, q, args):
    return q[1]


def along(t, q, args):
    return q[0]


def test_law_objects_are_validated_naming_the_field():
    with pytest.raises(ValueError, match="StaticKineticCoulomb: `mu_static` must be >= `mu_kinetic`"):
        hj.StaticKineticCoulomb(0.2, 0.5)
    with pytest.raises(ValueError, match="StaticKineticCoulomb: `mu_kinetic` must be a number >= 0"):
        hj.StaticKineticCoulomb(0.5, -0.1)
    with pytest.raises(ValueError, match="StaticKineticCoulomb: `mu_static` must be a number >= 0"):
        hj.StaticKineticCoulomb("0.5", 0.1)
    with pytest.raises(ValueError, match="Coulomb: `mu` must be a number >= 0"):
        hj.Coulomb(-1.0)
    with pytest.raises(ValueError, match=r"Newton: `e` must be a number in \[0, 1\]"):
        hj.Newton(1.5)
    # A law object needs what its number would: a unilateral contact, with a tangent for friction.
    with pytest.raises(ValueError, match="'floor'.*`friction` needs.*`tangent`"):
        hj.Constraint("floor", gap, friction=hj.StaticKineticCoulomb(0.5, 0.2))
    with pytest.raises(ValueError, match="'floor'.*`friction` needs.*`tangent`"):
        hj.Constraint("floor", gap, kind="bilateral", tangent=along, friction=hj.Coulomb(0.5))
    with pytest.raises(ValueError, match="'floor'.*holds no tangent row"):
        hj.Constraint("floor", gap, tangent=along, friction=hj.Frictionless())
    with pytest.raises(ValueError, match="'floor'.*bilateral constraint has no restitution"):
        hj.Constraint("floor", gap, kind="bilateral", restitution=hj.Newton(0.5))
    # Coefficients given as functions of args are checked at every args value of a build.
    law = hj.StaticKineticCoulomb(lambda p: p["mu_s"], lambda p: p["mu_k"])
    with pytest.raises(ValueError, match="'floor'.*`mu_static` must be >= `mu_kinetic`, got 0.1 < 0.4"):
        block_system(law, ["floor:stick"], [slope_args(mu_s=0.1, mu_k=0.4)])


def test_constraint_takes_law_objects_where_it_takes_numbers():
    # The law objects are the ones a number or a function would give, read the same way.
    c = hj.Constraint("floor", gap, tangent=along, friction=hj.StaticKineticCoulomb(0.5, 0.2),
                      restitution=hj.Newton(0.25))  # fmt: skip
    law = c.tangential_law
    assert [law.slip_coefficient(s, {}) for s in ("slip+", "slip-")] == [0.2, 0.2]
    assert [law.stick_limit(d, {}) for d in (1.0, -1.0)] == [0.5, 0.5]
    assert c.coefficient({}) == 0.25 and c.restitutes
    plastic = hj.Constraint("floor", gap, restitution=hj.Plastic())
    assert plastic.coefficient({}) == 0.0 and not plastic.restitutes
    by_number = hj.Constraint("floor", gap, tangent=along, friction=0.4).tangential_law
    assert by_number == hj.Coulomb(0.4) and by_number.stick_limit(-1.0, {}) == 0.4
