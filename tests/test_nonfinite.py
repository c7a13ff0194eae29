"""Runs that cannot go on, in both engines: a value that is not finite only beyond some time
(the step that reaches it is rejected and shrunk, the events before it are kept, and the
execution ends `NONFINITE` where the value stops being finite: the rule `nonfinite_step`), and
a flow that blows up in finite time (the step size collapses: `step_collapsed`)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj
from hybridjax._rules.step import nonfinite_step, step_collapsed

from helpers import TIGHT

G, E = 9.8, 0.5


def _nan_after(t, limit, value):
    return jnp.where(t > limit, jnp.nan, value)


# The ball, whose guard, flow or domain function is NaN beyond t = args["guard"], args["flow"]
# or args["domain"] (one compiled program for the three cases).
_flight = hj.Mode(
    "flight", lambda t, x, a: _nan_after(t, a["flow"], jnp.array([x[1], -G])), dim=2,
    domain=lambda t, x, a: _nan_after(t, a["domain"], jnp.ones(1)))
BALL = hj.HybridSystem([_flight], [hj.Transition(
    "flight", "flight", guard=lambda t, x, a: _nan_after(t, a["guard"], x[0]),
    reset=lambda t, x, a: jnp.array([x[0], -E * x[1]]))])
X0 = jnp.array([1.0, 0.0])
T_FIRST = math.sqrt(2.0 / G)
IMPACTS = [T_FIRST, T_FIRST * (1 + 2 * E), T_FIRST * (1 + 2 * E + 2 * E * E)]  # 0.45, 0.90, 1.13

_run = jax.jit(lambda a: hj.simulate(BALL, X0, "flight", 0.0, 2.0, a, stepsize_controller=TIGHT))
_run_batch = jax.jit(lambda a: hj.simulate_batch(BALL, X0[None], "flight", 0.0, 2.0, a,
                                                 stepsize_controller=TIGHT))


def test_the_rule_rejects_shrinks_and_stops_only_at_the_resolution_of_t():
    eps = float(jnp.finfo(jnp.float64).eps)
    ok, h_next, stuck = nonfinite_step(jnp.array(True), jnp.array(True), 0.3, 0.1, 2.0, eps)
    assert bool(ok) and float(h_next) == 0.3 and not bool(stuck)
    for state, watched in ((False, True), (True, False), (False, False)):
        ok, h_next, stuck = nonfinite_step(jnp.array(state), jnp.array(watched), jnp.nan, 0.1, 2.0, eps)
        assert not bool(ok) and float(h_next) == 0.025 and not bool(stuck)
    # At t = 2 the resolution is 64 eps 2 = 2.8e-14: a step of 1e-14 cannot shrink further.
    _, _, stuck = nonfinite_step(jnp.array(True), jnp.array(False), jnp.nan, 1e-14, 2.0, eps)
    assert bool(stuck)


@pytest.mark.parametrize("where", ["guard", "flow", "domain"])
@pytest.mark.parametrize("engine", ["simulate", "simulate_batch"])
def test_a_value_undefined_beyond_t_1_keeps_the_events_before_it(where, engine):
    args = {"guard": jnp.inf, "flow": jnp.inf, "domain": jnp.inf}
    args[where] = jnp.asarray(1.0)
    sol = _run(args) if engine == "simulate" else _run_batch(args)  # one execution, or a batch of one
    status = int(np.asarray(sol.status).reshape(-1)[0])
    n = int(np.asarray(sol.num_events).reshape(-1)[0])
    times = np.asarray(sol.event_times).reshape(-1, sol.event_times.shape[-1])[0]
    final_time = float(np.asarray(sol.final_time).reshape(-1)[0])
    assert status == int(hj.Status.NONFINITE)
    assert n == 2
    np.testing.assert_allclose(times[:2], IMPACTS[:2], rtol=1e-9)
    # Ends where the value stops being finite, approached from below.
    assert 1.0 - 1e-9 <= final_time <= 1.0


# x' = x^2 from x(0) = x0 blows up at t = 1 / x0.
BLOWUP = hj.HybridSystem([hj.Mode("m", lambda t, x, a: x * x, dim=1)], [])
_blowup = jax.jit(lambda x0: hj.simulate(BLOWUP, x0, "m", 0.0, 2.0))
_blowup_batch = jax.jit(lambda x0: hj.simulate_batch(BLOWUP, x0[None], "m", 0.0, 2.0))


def test_the_collapse_rule_is_at_the_resolution_of_t():
    eps = float(jnp.finfo(jnp.float64).eps)
    assert bool(step_collapsed(jnp.array(True), 16 * eps * 0.5, 0.5, eps))
    assert not bool(step_collapsed(jnp.array(True), 32 * eps * 0.5, 0.5, eps))
    assert not bool(step_collapsed(jnp.array(False), 0.0, 0.5, eps))  # non-finite: the other rule


@pytest.mark.parametrize("engine", ["simulate", "simulate_batch"])
def test_a_blow_up_in_finite_time_ends_with_a_collapsed_step_at_its_time(engine):
    x0 = jnp.array([2.0])
    sol = _blowup(x0) if engine == "simulate" else _blowup_batch(x0)
    assert int(np.asarray(sol.status).reshape(-1)[0]) == int(hj.Status.STEP_COLLAPSE)
    t = float(np.asarray(sol.final_time).reshape(-1)[0])
    x = float(np.asarray(sol.final_state).reshape(-1)[0])
    # At the pole 1 / x0, to the default tolerance (1e-8) amplified by the pole's growth.
    np.testing.assert_allclose(t, 0.5, rtol=1e-7)
    assert np.isfinite(x) and x > 1e12
    assert int(np.asarray(sol.num_steps).reshape(-1)[0]) < 4096
