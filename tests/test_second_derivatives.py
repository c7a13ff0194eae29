"""Second derivatives through events, against differentiated closed forms.

Hessians of event times and of states after many events, taken through the simulation by
forward over reverse mode (`jax.hessian`, default adjoint) and forward over forward mode
(`jax.jacfwd` twice, `diffrax.ForwardMode()`), in both engines. The exact Hessians
differentiate each closed form (written in jax.numpy) twice. Errors after k events must stay
within BOUND * TOL * k * max(1, |exact|), the bound the first derivatives meet.
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from long_sequences import CONTROLLER, PROBLEMS, TOL, _ball_closed, simulated_times

import hybridjax as hj

BOUND = 10.0

# --- the bouncing ball, p = (h0, v0, e, g): impacts k = 1, 5, 20, the speed after each, and
# the final height, at T halfway between impacts 20 and 21.
BALL = hj.examples.bouncing_ball()
BALL_P0 = np.array([1.0, 0.0, 0.9, 9.8])
KS = np.array([1, 5, 20])
_T0 = np.asarray(_ball_closed(jnp.asarray(BALL_P0), 21))
T_FINAL = float(0.5 * (_T0[19] + _T0[20]))
EVENTS = np.concatenate([KS, KS, [20]])  # the events before each output


def ball_closed(p):
    """(t_1, t_5, t_20, v_1, v_5, v_20, h(T)): after impact k the ball leaves the floor at
    speed v_k = e^k W, W = sqrt(v0^2 + 2 g h0), so h(T) = v_20 (T - t_20) - g (T - t_20)^2 / 2."""
    h0, v0, e, g = p
    times = _ball_closed(p, 20)[KS - 1]
    speeds = e**KS * jnp.sqrt(v0 * v0 + 2 * g * h0)
    s = T_FINAL - times[-1]
    return jnp.concatenate([times, speeds, (speeds[-1] * s - 0.5 * g * s * s)[None]])


def ball_simulated(engine, adjoint):
    opts = dict(stepsize_controller=CONTROLLER, max_epochs=28, zeno=False, adjoint=adjoint)

    def run(p):
        x0, args = p[:2], {"e": p[2], "g": p[3]}
        if engine == "simulate":
            sol = hj.simulate(BALL, x0, "flight", 0.0, T_FINAL, args, **opts)
            times, after, final = sol.event_times, sol.states_after, sol.final_state
        else:
            sol = hj.simulate_batch(BALL, x0[None], "flight", 0.0, T_FINAL, args, **opts)
            times, after, final = sol.event_times[0], sol.states_after[0], sol.final_state[0]
        return jnp.concatenate([times[KS - 1], after[KS - 1, 1], final[:1]])

    return run


def _check(H, exact, events, label):
    scale = np.asarray(events, float).reshape((-1,) + (1,) * (exact.ndim - 1)) * np.maximum(1.0, np.abs(exact))
    worst = np.max(np.abs(H - exact) / scale)
    assert worst <= BOUND * TOL, f"{label}: max |error| / (k max(1, |exact|)) = {worst:.3g}"


HESSIANS = {
    "forward over reverse": lambda f: jax.hessian(f(diffrax.RecursiveCheckpointAdjoint())),
    "forward over forward": lambda f: jax.jacfwd(jax.jacfwd(f(diffrax.ForwardMode()))),
}


BALL_CASES = [("simulate", "forward over reverse"), ("simulate", "forward over forward"),
              ("simulate_batch", "forward over forward"),
              pytest.param("simulate_batch", "forward over reverse", marks=pytest.mark.slow)]


@pytest.mark.parametrize("engine,mode", BALL_CASES)
def test_ball_hessian_of_impact_times_speeds_and_final_height(engine, mode):
    hess = jax.jit(HESSIANS[mode](lambda adjoint: ball_simulated(engine, adjoint)))
    p0 = jnp.asarray(BALL_P0)
    exact = np.asarray(jax.hessian(ball_closed)(p0))
    assert np.max(np.abs(exact)) > 1.0  # the Hessians are not trivially zero
    _check(np.asarray(hess(p0)), exact, EVENTS, f"ball {engine} {mode}")


def test_integrate_and_fire_second_derivative_in_the_current_over_50_spikes():
    # t_k = tau ln((I - V0) / (I - 1)) + (k - 1) tau ln(I / (I - 1)): d2 t_k / dI2 grows with k.
    pb = PROBLEMS["lif"]
    times = simulated_times("lif", "simulate", diffrax.RecursiveCheckpointAdjoint())
    p0 = jnp.asarray(pb.p0)

    def first50(current):
        return times(p0.at[0].set(current))[:50]

    def closed(current):
        return hj.examples.integrate_and_fire_closed_form(current, p0[1], p0[2], 50)

    d2 = np.asarray(jax.jit(jax.hessian(first50))(p0[0]))
    exact = np.asarray(jax.hessian(closed)(p0[0]))
    assert exact[-1] > 3.0
    _check(d2, exact, np.arange(1, 51), "integrate-and-fire d2 t_k / dI2")


def test_moving_table_hessian_with_a_time_varying_guard():
    # Guard h - u t and reset v -> u - e (v - u): relative to the table, the ball above.
    pb = PROBLEMS["table"]
    p0 = jnp.asarray(pb.p0)
    hess = jax.jit(jax.hessian(simulated_times("table", "simulate", diffrax.RecursiveCheckpointAdjoint())))
    exact = np.asarray(jax.hessian(pb.closed)(p0))
    _check(np.asarray(hess(p0)), exact, np.arange(1, pb.num_events + 1), "moving table")
