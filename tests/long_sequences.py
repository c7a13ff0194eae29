"""Long event sequences with closed-form event times, for the derivative-accuracy tests.

Each problem maps a parameter vector p to (x0, args) and has its event times t_k(p) in closed
form, written in jax.numpy so that their exact derivatives come from differentiating the
formula (independent of the simulator). `derivative_runners` builds, once per (problem,
engine), the compiled reverse-mode (`jax.jacrev`, default adjoint) and forward-mode
(`jax.jacfwd`, `diffrax.ForwardMode()`) Jacobians of the simulated event times.
"""

import functools
from typing import NamedTuple

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import hybridjax as hj
from hybridjax import examples

TOL = 1e-10
CONTROLLER = diffrax.PIDController(rtol=TOL, atol=TOL)


class Problem(NamedTuple):
    system: hj.HybridSystem
    mode0: str
    t1: float
    num_events: int
    p0: np.ndarray
    names: tuple
    setup: object  # p -> (x0, args)
    closed: object  # p -> (num_events,) event times
    x0_params: tuple  # indices of p that are components of x0, in order


# --- ball bouncing on a floor: impacts at t_1 = (v0 + W) / g, then flights 2 e^j W / g.
def _ball_closed(p, n):
    h0, v0, e, g = p
    W = jnp.sqrt(v0 * v0 + 2 * g * h0)
    flights = jnp.concatenate([jnp.zeros(1), jnp.cumsum(2 * W / g * e ** jnp.arange(1, n))])
    return (v0 + W) / g + flights


# --- ball on a table moving at constant velocity u (height u t): a time-varying guard
# h - u t and reset v -> u - e (v - u); relative to the table it is the ball above.
def _table_system():
    flight = hj.Mode("flight", lambda t, x, p: jnp.array([x[1], -p["g"]]), dim=2)
    hit = hj.Transition(
        "flight", "flight", guard=lambda t, x, p: x[0] - p["u"] * t,
        reset=lambda t, x, p: jnp.array([x[0], p["u"] - p["e"] * (x[1] - p["u"])]), name="impact")
    return hj.HybridSystem([flight], [hit])


def _table_closed(p, n):
    h0, v0, e, u = p
    return _ball_closed(jnp.stack([h0, v0 - u, e, jnp.asarray(9.8)]), n)


# --- thermostat cycling off -> heat -> off ... from T0 in `off`: T' = a (T_amb - T) + P.
def _thermo_closed(p, n):
    a, T_amb, P_heat, s, T0 = p
    T_eq = T_amb + P_heat / a
    first = jnp.log((T0 - T_amb) / (s - 4 - T_amb)) / a
    heating = jnp.log((s - 4 - T_eq) / (s - 2 - T_eq)) / a
    cooling = jnp.log((s - 2 - T_amb) / (s - 4 - T_amb)) / a
    k = jnp.arange(n)
    return first + (k + 1) // 2 * heating + k // 2 * cooling


def _thermo_args(p):
    a, T_amb, P_heat, s, T0 = p
    return jnp.stack([T0]), {"a": a, "T_amb": T_amb, "P_heat": P_heat, "P_cool": jnp.asarray(1.0), "s": s}


def _midway(times) -> float:
    """A final time halfway between the last two event times given (the last one not reached)."""
    return float(0.5 * (times[-2] + times[-1]))


LIF_PERIOD = 0.02 * np.log(3.0)
THERMO_P0 = np.array([0.5, 10.0, 10.0, 20.0, 19.0])
PROBLEMS = {
    "lif": Problem(examples.integrate_and_fire(), "subthreshold", 100.5 * LIF_PERIOD, 100, np.array([1.5, 0.02, 0.0]),
                   ("I", "tau", "V0"), lambda p: (p[2:3], {"I": p[0], "tau": p[1]}),
                   lambda p: examples.integrate_and_fire_closed_form(*p, 100), (2,)),
    "ball": Problem(examples.bouncing_ball(), "flight", _midway(_ball_closed(np.array([1.0, 0.0, 0.9, 9.8]), 31)),
                    30, np.array([1.0, 0.0, 0.9, 9.8]), ("h0", "v0", "e", "g"),
                    lambda p: (p[:2], {"e": p[2], "g": p[3]}), lambda p: _ball_closed(p, 30), (0, 1)),
    "table": Problem(_table_system(), "flight", _midway(_table_closed(np.array([1.0, 0.0, 0.9, 0.3]), 21)),
                     20, np.array([1.0, 0.0, 0.9, 0.3]), ("h0", "v0", "e", "u"),
                     lambda p: (p[:2], {"e": p[2], "u": p[3], "g": jnp.asarray(9.8)}),
                     lambda p: _table_closed(p, 20), (0, 1)),
    "thermostat": Problem(examples.thermostat(), "off",
                          _midway(_thermo_closed(THERMO_P0, 101)), 100, THERMO_P0,
                          ("a", "T_amb", "P_heat", "s", "T0"), _thermo_args,
                          lambda p: _thermo_closed(p, 100), (4,)),
}


def simulated_times(name: str, engine: str, adjoint: diffrax.AbstractAdjoint):
    """p -> the first `num_events` simulated event times of problem `name`."""
    pb = PROBLEMS[name]
    opts = dict(stepsize_controller=CONTROLLER, max_epochs=pb.num_events + 8, zeno=False,
                adjoint=adjoint, max_steps=16 * 4096)

    def times(p):
        x0, args = pb.setup(p)
        if engine == "simulate":
            return hj.simulate(pb.system, x0, pb.mode0, 0.0, pb.t1, args, **opts).event_times[:pb.num_events]
        sol = hj.simulate_batch(pb.system, x0[None], pb.mode0, 0.0, pb.t1, args, **opts)
        return sol.event_times[0, :pb.num_events]

    return times


class Runners(NamedTuple):
    reverse: object
    forward: object


@functools.cache
def derivative_runners(name: str, engine: str) -> Runners:
    """Compiled d t_k / d p of problem `name`: reverse mode and forward mode."""
    rev = jax.jit(jax.jacrev(simulated_times(name, engine, diffrax.RecursiveCheckpointAdjoint())))
    fwd = jax.jit(jax.jacfwd(simulated_times(name, engine, diffrax.ForwardMode())))
    return Runners(rev, fwd)


def exact_jacobian(name: str) -> np.ndarray:
    pb = PROBLEMS[name]
    return np.asarray(jax.jacfwd(pb.closed)(jnp.asarray(pb.p0)))


def growth_exponent(err: np.ndarray, floor: float, k_from: int = 10) -> float:
    """Least-squares slope of log(running max of |err_k| + floor k) against log k, k >= k_from.

    1 for an error growing linearly with the event count, 2 for one growing with its square;
    the running max makes errors that change sign count by their envelope, and the floor
    (a small fraction of the error allowed per event) keeps errors at rounding level, which
    jump from 0 to a few ulps, from reading as fast growth."""
    k = np.arange(1, err.shape[0] + 1)
    env = np.maximum.accumulate(np.abs(err)) + floor * k
    sel = k >= k_from
    return float(np.polyfit(np.log(k[sel]), np.log(env[sel]), 1)[0])
