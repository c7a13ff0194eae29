"""Hybrid iLQR (Kong, Council & Johnson, CDC 2021): its linearisation across an event against
AD through `simulate`, tracking a bouncing reference through its impact from controls that
move the impact into another interval (the optimum, u = 0, reproduces the reference), and a
hopper reaching a target apex, checked with the ballistic flight's closed form."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj
from hybridjax._optimise.ilqr import _initial, linearise

# ----------------------------------------------------------------------------- ball with thrust

G, E = 9.8, 0.8
BALL = hj.HybridSystem(
    [hj.Mode("flight", lambda t, x, a: jnp.stack([x[1], -a["g"] + a["u"][0]]), dim=2)],
    [hj.Transition("flight", "flight", guard=lambda t, x, a: x[0],
                   reset=lambda t, x, a: x.at[1].multiply(-a["e"]), name="bounce")])
N, T = 20, 1.0
TS = jnp.linspace(0.0, T, N + 1)
X0 = jnp.array([1.0, 0.0])
ball_args = lambda u: {"g": G, "e": E, "u": u}
Q = jnp.diag(jnp.array([10.0, 1.0]))
# The reference: the passive ball (u = 0) from X0, one impact at sqrt(2 / g) = 0.4518 in [0.45, 0.5).
REFERENCE = _initial(hj.HybridLQRProblem(BALL, ball_args, X0, "flight", TS, jnp.zeros((N + 1, 2)), Q,
                                         1e-3, 10 * Q), jnp.zeros((N, 1)))
TRACK = hj.HybridLQRProblem(BALL, ball_args, X0, "flight", TS, REFERENCE.xs, Q, 1e-3, 10 * Q)
# A thrust of 2.5 delays the impact to sqrt(2 / 7.3) = 0.5234, in the next interval.
U0 = jnp.full((N, 1), 2.5)


def test_linearisation_across_an_impact_matches_ad_through_simulate():
    nominal = _initial(TRACK, U0)
    A, B = linearise(TRACK, nominal)
    k = 10
    assert int(nominal.num_events[k]) == 1 and 0.5 < float(nominal.event_times[k, 0]) < 0.55

    def interval(x, u):
        return hj.simulate(BALL, x, "flight", TS[k], TS[k + 1], ball_args(u), adjoint=diffrax.ForwardMode(),
                           stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12)).final_state

    A_ad, B_ad = jax.jacfwd(interval, argnums=(0, 1))(nominal.xs[k], U0[k])
    # RK4 is exact on the ball's quadratic flights: agreement to the event-location tolerance
    np.testing.assert_allclose(A[k], A_ad, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(B[k], B_ad, rtol=1e-9, atol=1e-10)
    # an interval without events is the flight's own linearisation
    np.testing.assert_allclose(A[3], [[1.0, 0.05], [0.0, 1.0]], atol=1e-14)
    np.testing.assert_allclose(B[3], [[0.05**2 / 2], [0.05]], atol=1e-14)


def test_tracks_a_bouncing_reference_through_its_impact():
    assert REFERENCE.counts[-1] == 1
    result = hj.hybrid_ilqr(TRACK, U0, iterations=8)
    assert np.all(np.diff(result.costs) < 0)
    # The optimum is u = 0 (cost 0): reached to rounding level, through the change of the impact's
    # interval (the reference extension handles the knots between the two impact times).
    assert result.sequence_changed[1] and result.num_events[-1] == 1
    assert float(np.abs(result.controls).max()) < 1e-9
    assert float(np.abs(result.states - REFERENCE.xs).max()) < 1e-10


# ----------------------------------------------------------------------------- hopper

KS, L0, Z_APEX = 100.0, 1.0, 1.5
HOPPER = hj.HybridSystem(
    [hj.Mode("flight", lambda t, x, a: jnp.stack([x[1], -a["g"] + 0.0 * x[1]]), dim=2),
     hj.Mode("stance", lambda t, x, a: jnp.stack([x[1], a["k"] * (a["l0"] - x[0]) - a["g"] + a["u"][0]]), dim=2)],
    [hj.Transition("flight", "stance", guard=lambda t, x, a: x[0] - a["l0"], name="touchdown"),
     hj.Transition("stance", "flight", guard=lambda t, x, a: a["l0"] - x[0], name="liftoff")])


def test_hopper_reaches_a_target_apex():
    """A vertical hopper dropped from its apex at 1.2 (leg spring k, rest length l0, thrust u in
    stance, bounded to [0, 60]) must be at a new apex at 1.5 (state (1.5, 0)) at t = 0.9."""
    n = 18
    ts = jnp.linspace(0.0, 0.9, n + 1)
    target = jnp.zeros((n + 1, 2)).at[-1].set(jnp.array([Z_APEX, 0.0]))
    problem = hj.HybridLQRProblem(HOPPER, lambda u: {"g": G, "k": KS, "l0": L0, "u": u}, jnp.array([1.2, 0.0]),
                                  "flight", ts, target, jnp.zeros((2, 2)), 1e-4, 1e3 * jnp.eye(2),
                                  lower=0.0, upper=60.0)
    result = hj.hybrid_ilqr(problem, jnp.zeros((n, 1)), iterations=6)
    z, v = np.asarray(result.states[-1])
    # ballistic flight from (z, v): apex at z + v^2 / (2 g), reached after v / g; the weights
    # trade |u|^2 (1e-4) against the terminal error (1e3): a residual of ~2e-5 remains
    assert result.modes[-1] == 0 and result.num_events[-1] == 2
    np.testing.assert_allclose(z + v**2 / (2 * G), Z_APEX, atol=1e-4)
    assert abs(v / G) < 1e-4
    u = np.asarray(result.controls)
    assert u.min() >= 0.0 and u.max() <= 60.0 and u.max() > 1.0
    # thrust only acts in stance: on intervals spent wholly in flight, R pulls the controls to 0
    modes, events = np.asarray(result.modes), np.asarray(result.event_times[-1][:, 0])
    flight_only = (modes[:-1] == 0) & (modes[1:] == 0) & ~np.isfinite(events)
    assert flight_only.sum() >= 6 and np.all(u[flight_only] < 1e-6)


# ----------------------------------------------------------------------------- names and shorthands

TRACK_SIM = hj.Simulator(stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10), max_epochs=2)


def test_lqr_problem_takes_simulator_and_bounds_and_their_shorthands():
    track = (BALL, ball_args, X0, "flight", TS, REFERENCE.xs, Q, 1e-3, 10 * Q)
    problem = hj.HybridILQR(*track, simulator=TRACK_SIM)
    assert eqx.tree_equal(problem, TRACK) and isinstance(TRACK, hj.HybridILQR)
    for kw in (dict(max_events=2), dict(max_epochs=2, stepsize_controller=TRACK_SIM.stepsize_controller)):
        assert eqx.tree_equal(hj.HybridLQRProblem(*track, **kw), problem)
    assert problem.max_epochs == problem.max_events == 2 and problem.stepsize_controller.rtol == 1e-10
    # the rollout runs the simulator's executions (the compiled rollout of the linearisation test):
    # thrust 2.5 from rest at h = 1 lands at sqrt(2 / (g - 2.5)) (closed form), in interval 10
    nominal = _initial(problem, U0)
    np.testing.assert_allclose(nominal.event_times[10, 0], np.sqrt(2 / (G - 2.5)), rtol=0, atol=1e-9)
    # bounds=(lower, upper) clip the controls as numpy's clip does
    boxed = hj.HybridLQRProblem(*track, bounds=(0.0, 1.5))
    assert eqx.tree_equal(boxed, hj.HybridLQRProblem(*track, lower=0.0, upper=1.5))
    assert (boxed.lower, boxed.upper) == (0.0, 1.5)
    u = jnp.array([-1.0, 0.5, 2.0])
    np.testing.assert_array_equal(boxed.clip(u), np.clip(np.asarray(u), 0.0, 1.5))
    for both, names in ((dict(bounds=(0.0, 1.0), upper=1.0), "bounds and upper"),
                        (dict(simulator=TRACK_SIM, stepsize_controller=TRACK_SIM.stepsize_controller),
                         "pass stepsize_controller there"),
                        (dict(simulator=TRACK_SIM, max_events=2), "pass max_events there")):
        with pytest.raises(ValueError, match=names):
            hj.HybridLQRProblem(*track, **both)
    with pytest.raises(TypeError, match="'max_event'"):
        hj.HybridLQRProblem(*track, max_event=2)
