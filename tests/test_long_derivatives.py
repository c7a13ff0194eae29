"""Event-time derivatives over long event sequences, against closed forms.

d t_k / d p from reverse mode (default adjoint) and forward mode (`diffrax.ForwardMode()`),
in both engines, for the integrate-and-fire neuron (100 spikes), the bouncing ball (30
bounces), the thermostat (100 switches) and a ball on a moving table (20 impacts, a
time-varying guard and reset). The exact derivatives differentiate each closed form. The
error of the k-th derivative must stay within a few times the tolerance times k, and grow at
most linearly with k (an error multiplied by 1 + O(tol) at every epoch grows with k^2).
"""

import jax.numpy as jnp
import numpy as np
import pytest
from long_sequences import CONTROLLER, PROBLEMS, TOL, derivative_runners, exact_jacobian, growth_exponent

import hybridjax as hj

# Errors per event within BOUND * TOL * k * max(1, |d t_k / d p|).
BOUND = 10.0
# The batched engine on the ball in every run; on the other problems with the costly cases
# (its gradients against the per-execution engine: test_batched.py).
CASES = [(name, "simulate") for name in PROBLEMS] + [
    pytest.param(name, "simulate_batch", marks=() if name == "ball" else pytest.mark.costly) for name in PROBLEMS]


def _check(name: str, J: np.ndarray, label: str) -> None:
    exact = exact_jacobian(name)
    pb = PROBLEMS[name]
    k = np.arange(1, pb.num_events + 1)[:, None]
    err = J - exact
    scale = np.maximum(1.0, np.abs(exact))
    worst = np.max(np.abs(err) / (k * scale))
    assert worst <= BOUND * TOL, f"{name} {label}: max |error| / k = {worst:.3g}"
    for i, p in enumerate(pb.names):
        slope = growth_exponent(err[:, i] / scale[:, i], floor=TOL)
        assert slope <= 1.2, f"{name} {label} d/d{p}: error grows as k^{slope:.2f}"


@pytest.mark.parametrize("name,engine", CASES)
def test_event_time_derivatives_over_long_sequences(name, engine):
    pb = PROBLEMS[name]
    p0 = jnp.asarray(pb.p0)
    run = derivative_runners(name, engine)
    _check(name, np.asarray(run.reverse(p0)), f"{engine} reverse")
    _check(name, np.asarray(run.forward(p0)), f"{engine} forward")


@pytest.mark.parametrize("name", list(PROBLEMS))
def test_variational_jacobian_agrees_with_ad_over_long_sequences(name):
    # Flows' state-transition matrices and saltation matrices composed along the execution
    # give d t_k / d x0; AD through the loop gives the same to the tolerance per event.
    pb = PROBLEMS[name]
    p0 = jnp.asarray(pb.p0)
    x0, args = pb.setup(p0)
    sol = hj.simulate(pb.system, x0, pb.mode0, 0.0, pb.t1, args,
                      stepsize_controller=CONTROLLER,
                      max_epochs=pb.num_events + 8, zeno=False, max_steps=16 * 4096)
    assert int(sol.num_events) == pb.num_events
    k = np.arange(1, pb.num_events + 1)
    times = np.asarray(pb.closed(p0))
    assert np.max(np.abs(np.asarray(sol.event_times)[: pb.num_events] - times) / (k * np.maximum(1.0, times))) <= BOUND * TOL
    var = hj.variational_jacobian(sol)
    dt_var = np.stack(var.event_times)[: pb.num_events]  # (events, n0)
    J = np.asarray(derivative_runners(name, "simulate").reverse(p0))[:, list(pb.x0_params)]
    exact = exact_jacobian(name)[:, list(pb.x0_params)]
    scale = k[:, None] * np.maximum(1.0, np.abs(exact))
    assert np.max(np.abs(dt_var - J) / scale) <= 2 * BOUND * TOL
    assert np.max(np.abs(dt_var - exact) / scale) <= BOUND * TOL
