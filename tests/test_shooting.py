"""Trajectory optimisation by shooting (`hj.Shooting`, `hj.shoot`), on problems whose optimum is
known in closed form, derived here:

- a ball launched from the floor at angle phi makes its k-th impact at x = x*;
- a heating thermostat's upper threshold tuned for a duty cycle of 1/2;
- a ball whose position at t1 is fixed, required to bounce exactly twice before t1 (the optimum
  on the boundary of the admissible speeds), and the same without the requirement, where the
  iterates' bounce count changes;
- a rimless wheel whose push-off gain minimises the spectral radius of its return map's Jacobian;
- a pytree of an open-loop thrust table (a `diffrax.LinearInterpolation` in `args`) and a feedback
  gain, recovered from the impact and a post-impact height computed by scipy.
"""

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
import pytest
from scipy.integrate import solve_ivp

import hybridjax as hj

from helpers import TIGHT

G, E, PHI = 9.8, 0.6, 0.9


# ----------------------------------------------------------------------------- a planar ball


def _planar_ball():
    """State (x, h, v_x, v_h); impacts on the floor h = 0 reverse v_h with restitution e."""
    flight = hj.Mode("flight", lambda t, s, a: jnp.stack([s[2], s[3], 0.0 * s[2], -a["g"] + 0.0 * s[3]]), dim=4)
    bounce = hj.Transition("flight", "flight", guard=lambda t, s, a: s[1],
                           reset=lambda t, s, a: s.at[3].multiply(-a["e"]), name="bounce")
    return hj.HybridSystem([flight], [bounce])


PLANAR = _planar_ball()
# The same ball with int h dt (a running cost) as state component 0: (cost, x, h, v_x, v_h).
PLANAR_AREA = hj.with_running_cost(PLANAR, lambda t, s, a: s[1])
BALL_ARGS = {"g": jnp.asarray(G), "e": jnp.asarray(E)}


def _launch(v):
    """From the floor at x = 0 with speed v at angle PHI (h = 0 and rising: no impact at t0)."""
    return jnp.stack([0.0 * v, 0.0 * v, v * math.cos(PHI), v * math.sin(PHI)])


def _flight_times(v, n):
    """Impact times t_j = (2 v sin phi / g) (1 - e^j) / (1 - e): the j-th flight lasts
    2 e^{j-1} v sin phi / g (each impact scales the vertical speed by e)."""
    j = np.arange(1, n + 1)
    return 2 * v * math.sin(PHI) / G * (1 - E ** j) / (1 - E)


K, X_STAR = 3, 4.0
# k-th impact at x = x*: x_k = v cos phi t_k = v^2 sin(2 phi) (1 - e^k) / (g (1 - e)), so
V_STAR = math.sqrt(X_STAR * G * (1 - E) / (math.sin(2 * PHI) * (1 - E ** K)))

KTH_IMPACT = hj.Shooting(
    PLANAR_AREA, lambda v, sol: (sol.states_before[K - 1, 1] / X_STAR - 1) ** 2,
    x0=lambda v: jnp.concatenate([jnp.zeros(1), _launch(v)]), mode0="flight",
    t1=20.0, args=BALL_ARGS, max_epochs=K, stepsize_controller=TIGHT)
# The cost is (v / v* )^4 - 2 (v / v*)^2 + 1 near v*: curvature 8 / v*^2 ~ 0.4, so a step of 1.5 /
# curvature-ish contracts the error by ~0.4 per iteration.
SGD_BALL = optax.sgd(1.5)


def test_kth_impact_at_target_from_several_guesses():
    result = hj.shoot(KTH_IMPACT, jnp.array([4.0, 5.0]), SGD_BALL, steps=30, batched=True)
    np.testing.assert_allclose(result.params, V_STAR, rtol=1e-9)
    assert result.costs.shape == (2, 31) and np.all(result.costs[:, -1] < 1e-18)
    # costs decrease; every iterate made (at least) the k impacts it was stopped after
    assert np.all(np.diff(result.costs, axis=1) <= 1e-15)
    assert np.all(result.num_events == K) and not np.any(result.sequence_changed)
    # the returned history is the parameters' own: its last entry is the result
    np.testing.assert_array_equal(result.params_history[:, -1], result.params)


def test_running_cost_integrates_along_the_flow():
    # a flight launched with vertical speed w encloses int_0^{2w/g} (w s - g s^2 / 2) ds = 2 w^3 / (3 g^2);
    # flight j starts with vertical speed v sin(phi) e^j
    v = 4.2
    areas = np.cumsum([2 * (v * math.sin(PHI) * E**j) ** 3 / (3 * G**2) for j in range(K)])
    sol = KTH_IMPACT.execution(jnp.asarray(v))
    np.testing.assert_allclose(sol.states_before[:, 0], areas, rtol=1e-9)
    np.testing.assert_allclose(sol.states_after[:, 0], areas, rtol=1e-9)   # resets keep it


def test_multiple_shooting_over_epochs_finds_the_kth_impact_speed():
    # unknowns: v, the post-impact states z_1, z_2 and the three flight durations; residuals: the
    # floor h = 0 at each epoch's end, continuity through the resets, and x = x* at the third impact
    problem = hj.MultipleShooting(PLANAR, (0,) * K, _launch, lambda v, ts, xs: xs[-1, :1] - X_STAR,
                                  args=BALL_ARGS, substeps=8)
    v0 = jnp.asarray(3.5)
    first_guess = hj.simulate(PLANAR, _launch(v0), "flight", 0.0, 20.0, BALL_ARGS, max_epochs=K)
    result = hj.multiple_shooting(problem, v0, hj.EpochGuess.from_solution(first_guess, K))
    assert result.result == optx.RESULTS.successful and float(result.max_residual) < 1e-10
    assert bool(result.success) and np.all(np.asarray(result.epochs.durations) > 0)
    # RK4 is exact on the quadratic flights: the closed form to rounding
    np.testing.assert_allclose(result.params, V_STAR, rtol=1e-12)
    np.testing.assert_allclose(result.event_times, _flight_times(V_STAR, K), rtol=1e-12)
    np.testing.assert_allclose(result.states_before[:, 0], V_STAR * math.cos(PHI) * _flight_times(V_STAR, K),
                               rtol=1e-12)


# ----------------------------------------------------------------------------- multiple shooting, checked

# A ball launched at angle PHI_L with restitution E_L whose third impact lands at x = X_L. After
# each bounce an epoch starts on its own guard (h = 0, rising): a zero duration meets h = 0 too.
G_L, E_L, PHI_L, X_L = 9.81, 0.7, 0.6, 5.0
LAUNCH_ARGS = {"g": jnp.asarray(G_L), "e": jnp.asarray(E_L)}


def _launch_l(v):
    return jnp.stack([0.0 * v, 0.0 * v, v * math.cos(PHI_L), v * math.sin(PHI_L)])


def _impacts_by_flights(v, n):
    """Impact times and x by stepping flight by flight: flight j lasts 2 w_j / g with
    w_0 = v sin phi, w_{j+1} = e w_j, at the constant horizontal speed v cos phi."""
    w, t, ts = v * math.sin(PHI_L), 0.0, []
    for _ in range(n):
        t += 2 * w / G_L
        ts.append(t)
        w *= E_L
    ts = np.array(ts)
    return ts, v * math.cos(PHI_L) * ts


# x_3 = v^2 sin(2 phi) (1 - e^3) / (g (1 - e)) = X_L
V_L = math.sqrt(X_L * G_L * (1 - E_L) / (math.sin(2 * PHI_L) * (1 - E_L**3)))
LAUNCH = hj.MultipleShooting(PLANAR, (0,) * K, _launch_l, lambda v, ts, xs: xs[-1, :1] - X_L,
                             args=LAUNCH_ARGS, substeps=8)
# the check's settings, so that the test's forward simulate is the same compiled program
LAUNCH_CHECK = hj.MultipleShootingCheck(stepsize_controller=TIGHT)


def _launch_execution(v, t1):
    return hj.simulate(PLANAR, _launch_l(jnp.asarray(v)), "flight", 0.0, t1, LAUNCH_ARGS, max_epochs=K + 1,
                       stepsize_controller=TIGHT)


def test_multiple_shooting_launch_finds_the_execution_from_each_guess():
    # the closed form against an impact-by-impact sum, and the value the problem was posed with
    np.testing.assert_allclose(_impacts_by_flights(V_L, K)[1][-1], X_L, rtol=1e-14)
    np.testing.assert_allclose(V_L, 4.902079901814787, rtol=1e-14)
    for v0 in (3.0, 7.0, 10.0):
        first = _launch_execution(v0, 40.0)
        result = hj.multiple_shooting(LAUNCH, jnp.asarray(v0), hj.EpochGuess.from_solution(first, K),
                                      check=LAUNCH_CHECK)
        assert bool(result.success), (v0, result.reason)
        assert np.all(np.asarray(result.epochs.durations) > 0)
        np.testing.assert_allclose(result.params, V_L, rtol=1e-12)
        # RK4 is exact on the quadratic flights
        np.testing.assert_allclose(result.event_times, _impacts_by_flights(V_L, K)[0], rtol=1e-12)
        forward = _launch_execution(result.params, 40.0)
        np.testing.assert_array_equal(forward.transitions[:K], [0] * K)
        np.testing.assert_allclose(result.event_times, forward.event_times[:K], rtol=0, atol=1e-9)
    # from v = 10 the first round stops short (its last flights shrinking towards zero length)
    # and the rounds restarted from the forward execution reach v*
    assert int(result.restarts) >= 1


def _up_through():
    """A ball thrown up from h = 0 (state (h, w)); the transition fires when h reaches H_UP
    (guard H_UP - h: positive below, crossed into on the way up)."""
    flight = hj.Mode("flight", lambda t, s, a: jnp.stack([s[1], -G_L + 0.0 * s[1]]), dim=2)
    above = hj.Mode("above", lambda t, s, a: 0.0 * s, dim=2)
    return hj.HybridSystem([flight, above], [hj.Transition("flight", "above", guard=lambda t, s, a: 1.0 - s[0])])


def test_multiple_shooting_reports_a_root_the_execution_does_not_take():
    # Target: speed 3 downwards at the event. H - h(T) = 0 also on the way down, at
    # T = (v + sqrt(v^2 - 2 g H)) / g, where the speed is -sqrt(v^2 - 2 g H): v = sqrt(9 + 2 g H).
    # The execution from that v takes the transition on the way up, at (v - 3) / g.
    v = math.sqrt(9 + 2 * G_L)
    problem = hj.MultipleShooting(_up_through(), (0,), lambda v: jnp.stack([0.0 * v, v]),
                                  lambda v, ts, xs: xs[0, 1:2] + 3.0)
    guess = hj.EpochGuess(jnp.zeros((0, 2)), jnp.array([0.95]))
    result = hj.multiple_shooting(problem, jnp.asarray(5.0), guess, restarts=0)
    np.testing.assert_allclose(result.params, v, rtol=1e-12)
    np.testing.assert_allclose(result.event_times, [(v + 3) / G_L], rtol=1e-12)
    assert float(result.max_residual) < 1e-12 and result.result == optx.RESULTS.successful
    assert not bool(result.success) and result.status == hj.MultipleShootingStatus.EVENT_TIMES_DIFFER
    assert "event times" in result.reason
    np.testing.assert_allclose(result.execution.event_times[0], (v - 3) / G_L, rtol=1e-9)
    # restarted from that execution (the way up), the target has no root: still a failure
    restarted = hj.multiple_shooting(problem, jnp.asarray(5.0), guess)
    assert not bool(restarted.success) and int(restarted.restarts) >= 1


def _relay():
    """x' = p in A until x = 1, reset to x + 1 in B, whose guard 1.5 - x the reset lands inside (B
    is left at once, a zero-length epoch), x' = -p in C until x = 1/2."""
    flow = lambda c: lambda t, x, p: c * p["p"] + 0.0 * x   # noqa: E731
    modes = [hj.Mode("A", flow(1.0), 1), hj.Mode("B", flow(1.0), 1), hj.Mode("C", flow(-1.0), 1),
             hj.Mode("D", flow(0.0), 1)]
    return hj.HybridSystem(modes, [
        hj.Transition("A", "B", guard=lambda t, x, p: 1.0 - x[0], reset=lambda t, x, p: x + 1.0),
        hj.Transition("B", "C", guard=lambda t, x, p: 1.5 - x[0]),
        hj.Transition("C", "D", guard=lambda t, x, p: x[0] - 0.5)])


def test_multiple_shooting_keeps_an_epoch_the_start_rule_makes_zero_length():
    # Events at 1/p, 1/p (zero-length epoch in B) and 1/p + 1.5/p: the last at t = 5 for p = 1/2.
    relay = _relay()
    problem = hj.MultipleShooting(relay, (0, 1, 2), jnp.zeros(1), lambda p, ts, xs: ts[-1:] - 5.0,
                                  args=lambda p: {"p": p})
    first = hj.simulate(relay, jnp.zeros(1), "A", 0.0, 10.0, {"p": jnp.asarray(0.8)}, max_epochs=4,
                        stepsize_controller=TIGHT)
    guess = hj.EpochGuess.from_solution(first, 3)
    np.testing.assert_allclose(guess.durations, [1.25, 0.0, 1.875], rtol=1e-9)
    result = hj.multiple_shooting(problem, jnp.asarray(0.8), guess)
    assert bool(result.success), result.reason
    np.testing.assert_allclose(result.params, 0.5, rtol=1e-12)
    np.testing.assert_allclose(result.event_times, [2.0, 2.0, 5.0], rtol=1e-12)
    np.testing.assert_allclose(result.epochs.durations, [2.0, 0.0, 3.0], rtol=1e-12)
    # guessed to flow for 0.1 in B, the epoch cannot shrink to zero length (its guard value is
    # -1/2 there, deflated to -inf); the round fails, and the restart from the forward execution
    # holds it at zero length
    flowing = hj.EpochGuess(guess.states, guess.durations.at[1].set(0.1))
    result = hj.multiple_shooting(problem, jnp.asarray(0.8), flowing)
    assert bool(result.success) and int(result.restarts) == 1, result.reason
    np.testing.assert_allclose(result.epochs.durations, [2.0, 0.0, 3.0], rtol=1e-12)


def test_multiple_shooting_options_name_the_culprit():
    bad = hj.EpochGuess(jnp.zeros((K - 1, 4)), jnp.array([0.5, -0.1, 0.3]))
    with pytest.raises(ValueError, match="guess.durations"):
        hj.multiple_shooting(LAUNCH, jnp.asarray(4.0), bad)
    with pytest.raises(ValueError, match="time_rtol"):
        hj.MultipleShootingCheck(time_rtol=-1.0)
    with pytest.raises(TypeError, match="stepsize_controller"):
        hj.MultipleShootingCheck(stepsize_controller=1e-10)
    with pytest.raises(ValueError, match="restarts"):
        hj.multiple_shooting(LAUNCH, jnp.asarray(4.0), bad, restarts=-1)


# ----------------------------------------------------------------------------- thermostat

A, T_AMB, P_HEAT, T_LO = 0.5, 10.0, 10.0, 18.0


def _heating_thermostat():
    """T' = a (T_amb - T) + P in "heat", a (T_amb - T) in "off"; heat off at T >= T_hi, heat on
    at T <= T_lo."""
    def flow(on):
        return lambda t, x, p: p["a"] * (p["T_amb"] - x) + on * p["P"]

    return hj.HybridSystem(
        [hj.Mode("heat", flow(1.0), 1), hj.Mode("off", flow(0.0), 1)],
        [hj.Transition("heat", "off", guard=lambda t, x, p: p["T_hi"] - x[0], name="heater off"),
         hj.Transition("off", "heat", guard=lambda t, x, p: x[0] - p["T_lo"], name="heater on")])


# One period from T_lo: heating ends at t_on (event 0), the heater is on again at t_on + t_off.
DUTY = hj.Shooting(
    _heating_thermostat(), lambda T_hi, sol: (sol.event_times[0] / sol.event_times[1] - 0.5) ** 2,
    x0=jnp.array([T_LO]), mode0="heat", t1=50.0,
    args=lambda T_hi: {"a": A, "T_amb": T_AMB, "P": P_HEAT, "T_lo": T_LO, "T_hi": T_hi},
    max_epochs=2, lower=jnp.asarray(T_LO + 0.5), upper=jnp.asarray(29.0), stepsize_controller=TIGHT)
# d(duty)/dT_hi ~ 0.026 at the optimum: the cost's curvature is 2 * 0.026^2 ~ 1.4e-3.
SGD_DUTY = optax.sgd(500.0)


def _duty_half_threshold():
    """T relaxes to T_eq (T_amb + P / a heating, T_amb off): t_on = ln((T_lo - H) / (T_hi - H)) / a,
    t_off = ln((T_hi - T_amb) / (T_lo - T_amb)) / a with H = T_amb + P / a. Duty 1/2 is t_on =
    t_off: (T_hi - T_amb)(T_hi - H) = (T_lo - T_amb)(T_lo - H), a quadratic in T_hi."""
    H = T_AMB + P_HEAT / A
    mid = (T_AMB + H) / 2
    return mid + math.sqrt(((H - T_AMB) / 2) ** 2 + (T_LO - T_AMB) * (T_LO - H))


def test_thermostat_threshold_for_half_duty_cycle():
    t_star = _duty_half_threshold()   # 22 for these numbers
    result = hj.shoot(DUTY, jnp.asarray(21.0), SGD_DUTY, steps=25)
    np.testing.assert_allclose(result.params, t_star, rtol=1e-7)
    assert np.all(result.num_events == 2) and np.all(result.accepted)


def test_thermostat_bound_is_active_when_the_optimum_lies_outside():
    # The same compiled program (the bound is an array): the iterates stop on the upper bound.
    capped = eqx.tree_at(lambda p: p.upper, DUTY, jnp.asarray(21.5))
    result = hj.shoot(capped, jnp.asarray(21.0), SGD_DUTY, steps=25)
    assert float(result.params) == 21.5
    assert np.all(np.asarray(result.params_history) <= 21.5)


def test_shooting_takes_simulator_and_bounds_and_their_shorthands():
    # DUTY written with the package-wide names is the same problem (and the same compiled program)
    problem = hj.Shooting(DUTY.system, DUTY.cost, x0=DUTY.x0, mode0="heat", t1=50.0, args=DUTY.args,
                          bounds=(jnp.asarray(T_LO + 0.5), jnp.asarray(29.0)),
                          simulator=hj.Simulator(stepsize_controller=TIGHT, max_epochs=2))
    assert eqx.tree_equal(problem, DUTY)
    assert (problem.max_epochs, problem.max_steps, problem.stepsize_controller) == (2, 4096, TIGHT)
    assert float(problem.lower) == T_LO + 0.5 and float(problem.upper) == 29.0
    result = hj.shoot(problem, jnp.asarray(21.0), SGD_DUTY, iterations=25)
    np.testing.assert_allclose(result.params, _duty_half_threshold(), rtol=1e-7)
    # the defaults: no bounds, simulate's settings with 16 events recorded
    bare = hj.Shooting(DUTY.system, DUTY.cost, x0=DUTY.x0, mode0="heat")
    assert bare.bounds == (None, None) and eqx.tree_equal(bare.simulator, hj.Simulator(max_epochs=16))
    sim = hj.Simulator(max_epochs=2)
    for both, names in ((dict(bounds=(0.0, 1.0), lower=0.0), "bounds and lower"),
                        (dict(simulator=sim, max_epochs=2), "pass max_epochs there"),
                        (dict(simulator=sim, solver=diffrax.Tsit5()), "pass solver there")):
        with pytest.raises(ValueError, match=names):
            hj.Shooting(DUTY.system, DUTY.cost, x0=DUTY.x0, mode0="heat", **both)
    with pytest.raises(TypeError, match="'max_epoch'"):
        hj.Shooting(DUTY.system, DUTY.cost, x0=DUTY.x0, mode0="heat", max_epoch=2)


# ----------------------------------------------------------------------------- free final time

V_UP, H_STAR = 5.0, 1.0
# The ball thrown up from the floor at V_UP passes h = H_STAR first at the smaller root of
# V_UP T - g T^2 / 2 = H_STAR.
T_STAR = (V_UP - math.sqrt(V_UP**2 - 2 * G * H_STAR)) / G
FREE_TIME = hj.Shooting(
    hj.examples.bouncing_ball(), lambda T, sol: (sol.final_state[0] / H_STAR - 1) ** 2,
    x0=jnp.array([0.0, V_UP]), mode0="flight", t1=lambda T: T, args=BALL_ARGS, max_epochs=2,
    lower=jnp.asarray(0.05), upper=jnp.asarray(0.45), stepsize_controller=TIGHT)


def test_free_final_time_within_bounds():
    # dh/dT = V_UP - g T* = 2.32 at T*: the cost's curvature is 2 * 2.32^2 ~ 10.8. The second
    # guess lies beyond the upper bound: its iterate 0 is the guess projected onto the bound.
    result = hj.shoot(FREE_TIME, jnp.array([0.4, 0.9]), optax.sgd(0.08), steps=25, batched=True)
    np.testing.assert_allclose(result.params, T_STAR, rtol=1e-10)
    assert float(result.params_history[1, 0]) == 0.45
    assert np.all(np.asarray(result.params_history) <= 0.45) and np.all(result.num_events == 0)


# ----------------------------------------------------------------------------- event sequences

T1 = 2.0
# x(t1) = v cos phi t1 whatever the bounces: the free optimum is V_FREE (one bounce before t1).
V_FREE = 9.0
X_T1 = V_FREE * math.cos(PHI) * T1
# Exactly j bounces before t1 iff t_j(v) <= t1 < t_{j+1}(v), i.e. v in (V_BOUND(j + 1), V_BOUND(j)]
# with t_j(V_BOUND(j)) = t1.
V_BOUND = lambda j: G * T1 * (1 - E) / (2 * math.sin(PHI) * (1 - E ** j))


def _reach(transitions=None):
    return hj.Shooting(
        PLANAR, lambda v, sol: (sol.final_state[0] / X_T1 - 1) ** 2, x0=_launch, mode0="flight", t1=T1,
        args=BALL_ARGS, max_epochs=4, transitions=transitions, max_backtracks=40, stepsize_controller=TIGHT)


# cost (v / V_FREE - 1)^2: curvature 2 / V_FREE^2
SGD_REACH = optax.sgd(0.45 * V_FREE**2)


def test_event_sequence_changes_are_reported_where_the_bounce_count_changes():
    result = hj.shoot(_reach(), jnp.asarray(7.0), SGD_REACH, steps=12)
    np.testing.assert_allclose(result.params, V_FREE, rtol=1e-9)
    vs = np.asarray(result.params_history)
    bounces = np.array([np.sum(_flight_times(v, 4) <= T1) for v in vs])
    np.testing.assert_array_equal(result.num_events, bounces)
    assert bounces[0] == 2 and bounces[-1] == 1
    np.testing.assert_array_equal(result.sequence_changed[1:], np.diff(bounces) != 0)
    assert not result.sequence_changed[0] and len(result.changes) >= 1


def test_required_sequence_of_exactly_two_bounces():
    result = hj.shoot(_reach((0, 0)), jnp.asarray(7.0), SGD_REACH, steps=30)
    # The constrained optimum is the boundary: the second impact exactly at t1.
    np.testing.assert_allclose(result.params, V_BOUND(2), rtol=1e-7)
    assert np.all(result.num_events == 2) and not np.any(result.sequence_changed)
    assert np.any(result.backtracks > 0)   # steps towards V_FREE leave the admissible set


def test_definition_errors_name_the_culprit():
    with pytest.raises(ValueError, match="max_epochs"):
        hj.Shooting(PLANAR, lambda v, sol: 0.0, x0=_launch, mode0="flight", transitions=(0, 0, 0),
                    max_epochs=2)
    with pytest.raises(ValueError, match="nowhere"):
        hj.Shooting(PLANAR, lambda v, sol: 0.0, x0=_launch, mode0="nowhere")
    with pytest.raises(TypeError, match="optax"):
        hj.shoot(KTH_IMPACT, 1.0, "adam", steps=1)


# ----------------------------------------------------------------------------- gait stability

ALPHA, GAMMA, W_REF = 0.3, 0.08, 0.6


def _pushed_wheel():
    """The rimless wheel (g / l = 1) with a push-off at heel strike proportional to the speed
    error: omega+ = cos(2 alpha) omega- + k (omega- - omega_ref)."""
    stance = hj.Mode("stance", lambda t, x, p: jnp.array([x[1], jnp.sin(x[0])]), dim=2)
    strike = hj.Transition(
        "stance", "stance", guard=lambda t, x, p: (GAMMA + ALPHA) - x[0],
        reset=lambda t, x, p: jnp.array(
            [x[0] - 2 * ALPHA, math.cos(2 * ALPHA) * x[1] + p["k"] * (x[1] - W_REF)]),
        name="heel strike")
    return hj.HybridSystem([stance], [strike])


WHEEL = _pushed_wheel()


@jax.jit
def _radius_squared(k, guess):
    """The spectral radius of the return map's Jacobian, squared, and its derivative in k, by
    jax.grad through hj.periodic_orbit; DP's eigenvalues are 0 (along the flow) and the
    multiplier, so the radius is |trace DP|. Also the orbit's state (the next guess)."""

    def radius2(k):
        orbit = hj.periodic_orbit(WHEEL, 0, guess, {"k": k}, max_epochs=2, t_max=20.0)
        return jnp.trace(orbit.poincare_jacobian) ** 2, orbit.state

    return jax.value_and_grad(radius2, has_aux=True)(k)


def _radius_squared_closed(k):
    """The multiplier (c + k) omega+ / omega- squared at the fixed point omega+ of
    omega+ + k omega_ref = (c + k) sqrt(omega+^2 + beta): the root of the squared equation
    (1 - a^2) w^2 + 2 k omega_ref w + k^2 omega_ref^2 - a^2 beta = 0 (a = c + k) with
    w + k omega_ref > 0."""
    c, beta = math.cos(2 * ALPHA), 4 * math.sin(ALPHA) * math.sin(GAMMA)
    a = c + k
    A, B, C = 1 - a * a, 2 * k * W_REF, k * k * W_REF**2 - a * a * beta
    w = (-B + jnp.sqrt(B * B - 4 * A * C)) / (2 * A)
    return (a * w / jnp.sqrt(w * w + beta)) ** 2


@pytest.mark.costly  # gradients of multipliers through periodic_orbit: test_periodic_gradients.py
def test_gait_push_off_gain_minimising_the_spectral_radius():
    """Energy from theta+ = gamma - alpha to theta- = gamma + alpha: omega-^2 = omega+^2 + beta,
    beta = 4 sin(alpha) sin(gamma); the return map omega+' = (c + k) omega- - k omega_ref has the
    multiplier (c + k) omega+ / omega- at its fixed point, c = cos(2 alpha): the radius is 0
    (deadbeat) at k* = -c, where omega+* = c omega_ref > 0 is a gait. The gradient in k is a
    second derivative through the impacts, by jax.grad through hj.periodic_orbit."""
    c = math.cos(2 * ALPHA)
    k, guess = -0.7, jnp.array([GAMMA - ALPHA, 0.5])
    (r, _), g = _radius_squared(jnp.asarray(k), guess)
    np.testing.assert_allclose(r, _radius_squared_closed(k), rtol=1e-8)
    np.testing.assert_allclose(g, jax.grad(_radius_squared_closed)(k), rtol=1e-6)
    opt = optax.sgd(0.6)   # the radius squared has curvature ~1.4 in k near k*
    state = opt.init(jnp.asarray(k))
    radii = []
    for _ in range(5):
        (r, guess), g = _radius_squared(jnp.asarray(k), guess)
        radii.append(float(r))
        updates, state = opt.update(g, state)
        k = float(optax.apply_updates(jnp.asarray(k), updates))
    np.testing.assert_allclose(k, -c, atol=1e-4)
    assert radii[-1] < 1e-7 and radii[-1] < radii[0]
    # the orbit at the optimum: omega+* = c omega_ref; the monodromy keeps its multiplier 1
    orbit = hj.periodic_orbit(WHEEL, 0, guess, {"k": jnp.asarray(-c)}, max_epochs=2, t_max=20.0)
    np.testing.assert_allclose(orbit.state, [GAMMA - ALPHA, c * W_REF], atol=1e-9)
    np.testing.assert_allclose(np.max(np.abs(orbit.multipliers_ad)), 1.0, atol=1e-7)


# ----------------------------------------------------------------------------- control table and feedback gain

H0, T_CTRL, T_SAVE = 2.0, 1.5, 1.2
KNOT_TS = jnp.array([0.0, T_CTRL])


def _thrust_ball():
    """h'' = -g + u(t) - k h' with u linear between the knots (an open-loop table in `args`) and a
    feedback gain k (a policy's weight in `args`); impacts on h = 0 with restitution E."""
    def flow(t, x, p):
        u = diffrax.LinearInterpolation(KNOT_TS, p["knots"]).evaluate(t)
        return jnp.stack([x[1], -G + u - p["gain"] * x[1]])

    bounce = hj.Transition("flight", "flight", guard=lambda t, x, p: x[0],
                           reset=lambda t, x, p: jnp.stack([x[0], -E * x[1]]))
    return hj.HybridSystem([hj.Mode("flight", flow, dim=2)], [bounce])


def _scipy_targets(knots, gain):
    """First impact time, speed before it, and height at T_SAVE after it: scipy's solve_ivp with
    a terminal event, restarted from the reset state."""
    def f(t, x):
        u = knots[0] + (knots[1] - knots[0]) * t / T_CTRL
        return [x[1], -G + u - gain * x[1]]

    def impact(t, x):
        return x[0]

    impact.terminal, impact.direction = True, -1
    first = solve_ivp(f, (0.0, T_CTRL), [H0, 0.0], events=impact, rtol=1e-12, atol=1e-12)
    t_1, v_1 = first.t_events[0][0], first.y_events[0][0][1]
    after = solve_ivp(f, (t_1, T_SAVE), [0.0, -E * v_1], rtol=1e-12, atol=1e-12)
    return t_1, v_1, after.y[0, -1]


def test_a_control_table_and_a_feedback_gain_are_recovered_as_one_pytree():
    # The parameters (knots (3, 6), gain 0.5) are unknown to the optimiser: it sees only the
    # impact time, the impact speed and a height after the bounce, computed by scipy from them;
    # three conditions, three unknowns (locally unique), so the optimum has cost 0 there.
    t_1, v_1, h_after = _scipy_targets(np.array([3.0, 6.0]), 0.5)

    def cost(p, sol):
        return ((sol.event_times[0] - t_1) ** 2 + ((sol.states_before[0, 1] - v_1) / 5) ** 2
                + (sol.ys[0, 0] - h_after) ** 2)

    problem = hj.Shooting(_thrust_ball(), cost, x0=jnp.array([H0, 0.0]), mode0="flight", t1=T_CTRL,
                          args=lambda p: p, saveat=jnp.array([T_SAVE]), max_epochs=2,
                          stepsize_controller=TIGHT)
    result = hj.shoot(problem, {"knots": jnp.array([2.0, 5.0]), "gain": jnp.asarray(0.3)},
                      optax.lbfgs(), steps=40)
    # scipy's and hybridjax's executions agree to ~1e-10, which bounds how well the targets pin
    # the parameters down.
    np.testing.assert_allclose(result.params["knots"], [3.0, 6.0], atol=1e-7)
    np.testing.assert_allclose(result.params["gain"], 0.5, atol=1e-7)
    assert float(result.costs[-1]) < 1e-16
