"""Numerical stress: grazing, exact-instant events, near-simultaneous guards, stiffness,
extreme time and state scales, long runs, float32, and bad user functions.

Every number is checked against a closed form computed independently (in 50-digit decimal
arithmetic where float64 itself would be the limit), a conserved quantity, or a second method.
"""

import decimal
import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj
from hybridjax import examples

from helpers import BALL, TIGHT

G = 9.8

# ------------------------------------------------------------------ grazing a ceiling
# A ball thrown up at v0 from 0 under a ceiling at c (guard c - x): its apex H = v0^2 / 2g
# passes the ceiling by d = H - c. The flow is a polynomial that Tsit5 integrates exactly,
# so steps are long and a shallow crossing lies between two samples of the dense output.
_fly = hj.Mode("fly", lambda t, x, c: jnp.array([x[1], -G + 0.0 * x[0]]), 2)
_stuck = hj.Mode("stuck", lambda t, x, c: jnp.zeros_like(x), 2)
CEILING_GRAZE = hj.HybridSystem([_fly, _stuck], [hj.Transition("fly", "stuck", guard=lambda t, x, c: c - x[0])])
V0 = 3.0


@pytest.fixture(scope="module")
def graze():
    return jax.jit(lambda c: hj.simulate(CEILING_GRAZE, jnp.array([0.0, V0]), "fly", 0.0, 2.0, c,
                                         stepsize_controller=TIGHT))


def _crossing_time(c: float) -> tuple[float, float]:
    """t* = (v0 - w) / g and dt*/dc = 1 / w, w = sqrt(v0^2 - 2 g c), in 50-digit arithmetic
    from the exact binary values of c and g (float64 loses the digits that matter here)."""
    ctx = decimal.Context(prec=50)
    D = decimal.Decimal
    v0, g, c = D(V0), D(G), D(c)
    w = ctx.sqrt(v0 * v0 - 2 * g * c)
    return float(ctx.divide(v0 - w, g)), float(ctx.divide(1, w))


@pytest.mark.parametrize("depth, grazing", [(1e-3, False), (1e-6, False), (1e-9, False),
                                            (1e-10, True), (1e-12, True)])
def test_near_grazing_crossing_is_found_and_flagged(graze, depth, grazing):
    c = V0 * V0 / (2 * G) - depth
    sol = graze(c)
    assert int(sol.num_events) == 1, f"missed a crossing of depth {depth:g}"
    slope = math.sqrt(2 * G * depth)  # |dg/dt| at the crossing
    # An error of one rounding unit in g moves the root by eps / slope; g on the dense output
    # carries tens of them (its polynomial's coefficients are sums of the stages with weights of
    # either sign), how many depends on the compiler's evaluation order. Measured at depths
    # 1e-6 .. 1e-12: 0.6e-15 / slope with XLA's default flags, 5.3e-15 / slope at -O0 (this
    # suite's flags, conftest.py).
    t_ref, dt_dc_ref = _crossing_time(c)
    np.testing.assert_allclose(sol.event_times[0], t_ref, rtol=0, atol=1e-13 + 1e-14 / slope)
    assert bool(sol.grazing[0]) == grazing
    # The event-time derivative dt*/dc = 1 / |dg/dt| grows as depth^(-1/2) towards grazing, and
    # its relative error as (g dt*)/|dg/dt| ~ a few eps / depth: ill-conditioned, hence the flag.
    # (Measured: 3e-16 / depth with XLA's default optimisation, 2.6e-15 / depth with the suite's
    # unoptimised compiles: the same IEEE operations, rounded in another order.)
    dt_dc = jax.grad(lambda c: graze(c).event_times[0])(c)
    np.testing.assert_allclose(dt_dc, dt_dc_ref, rtol=max(1e-7, 4e-15 / depth))


@pytest.mark.parametrize("depth", [-1e-12, -1e-6, -1e-3])
def test_passing_just_below_the_guard_is_no_event(graze, depth):
    sol = graze(V0 * V0 / (2 * G) - depth)
    assert int(sol.num_events) == 0 and sol.status_name == "T1_REACHED"
    np.testing.assert_allclose(sol.final_state, [V0 * 2.0 - 0.5 * G * 4.0, V0 - 2 * G], atol=1e-12)


def test_exact_tangency_is_no_event():
    # x' = 1 into the guard (x - a)^2, which touches zero at x = a and never goes below.
    m = hj.Mode("m", lambda t, x, a: jnp.ones_like(x), 1)
    done = hj.Mode("done", lambda t, x, a: jnp.zeros_like(x), 1)
    sys = hj.HybridSystem([m, done], [hj.Transition("m", "done", guard=lambda t, x, a: (x[0] - a) ** 2)])
    for a in (0.3, 1 / 3, 0.7071067811865476):
        sol = hj.simulate(sys, jnp.array([0.0]), "m", 0.0, 1.0, a, stepsize_controller=TIGHT)
        assert int(sol.num_events) == 0 and sol.status_name == "T1_REACHED"
        np.testing.assert_allclose(sol.final_state, [1.0], rtol=1e-14)


def test_double_crossing_inside_one_long_step_needs_no_interior_points():
    # The guard (x - 0.5)^2 - 1e-4 is negative only for x in (0.49, 0.51); one step of length 1
    # from x = 0 jumps over it. The minimum search on the step's dense output finds it.
    m = hj.Mode("m", lambda t, x, p: jnp.ones_like(x), 1)
    done = hj.Mode("done", lambda t, x, p: jnp.zeros_like(x), 1)
    sys = hj.HybridSystem([m, done], [hj.Transition("m", "done", guard=lambda t, x, p: (x[0] - 0.5) ** 2 - 1e-4)])
    for points in (0, 4):
        sol = hj.simulate(sys, jnp.array([0.0]), "m", 0.0, 1.0, solver=diffrax.Tsit5(),
                          stepsize_controller=diffrax.ConstantStepSize(), dt0=1.0, interior_points=points)
        assert int(sol.num_events) == 1 and int(sol.final_mode) == 1
        np.testing.assert_allclose(sol.event_times[0], 0.49, atol=1e-12)


# ------------------------------------------------------------------ events at t0 and t1
@pytest.mark.parametrize("offset, events", [(-1e-12, 0), (1e-12, 1)])
def test_event_just_before_and_just_after_t1(offset, events):
    # Dropped from h = 1 with g = 8 the ball lands at t = 1/2 exactly.
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 0.5 + offset, {"g": 8.0, "e": 0.5},
                      stepsize_controller=TIGHT)
    assert int(sol.num_events) == events and sol.status_name == "T1_REACHED"
    if events:
        np.testing.assert_allclose(sol.event_times[0], 0.5, atol=1e-14)
        np.testing.assert_allclose(sol.final_state[1], 2.0 - 8.0 * offset, atol=1e-10)
    else:
        np.testing.assert_allclose(sol.final_state, [4 * 1e-12, -4.0], atol=1e-11)


def test_event_exactly_at_t1_ends_consistently():
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 0.5, {"g": 8.0, "e": 0.5},
                      stepsize_controller=TIGHT)
    assert sol.status_name == "T1_REACHED" and float(sol.final_time) == 0.5
    n = int(sol.num_events)
    assert n in (0, 1)  # g(t1) is 0 to rounding: the crossing may be seen at t1 or not at all
    np.testing.assert_allclose(sol.final_state, [0.0, [-4.0, 2.0][n]], atol=1e-12)


def _landing_system():
    """a: x' = -1 until x <= 0, reset to x = 1 in b, exactly on b's guard 1 - x (b: x' = p)."""
    a = hj.Mode("a", lambda t, x, p: -jnp.ones_like(x), 1)
    b = hj.Mode("b", lambda t, x, p: p * jnp.ones_like(x), 1)
    c = hj.Mode("c", lambda t, x, p: jnp.zeros_like(x), 1)
    return hj.HybridSystem([a, b, c], [
        hj.Transition("a", "b", guard=lambda t, x, p: x[0], reset=lambda t, x, p: jnp.ones_like(x)),
        hj.Transition("b", "c", guard=lambda t, x, p: 1.0 - x[0]),
    ])


@pytest.mark.parametrize("p, zero_length", [(1.0, True), (-1.0, False), (0.0, False)])
def test_reset_landing_exactly_on_a_guard_boundary(p, zero_length):
    # b's guard 1 - x is 0 at the landing point; it fires at once only if the flow enters it.
    sol = hj.simulate(_landing_system(), jnp.array([0.5]), "a", 0.0, 1.0, p, stepsize_controller=TIGHT)
    modes = [int(m) for m in sol.epoch_modes[: int(sol.num_events) + 1]]
    assert modes == ([0, 1, 2] if zero_length else [0, 1])
    if zero_length:
        assert float(sol.event_times[1]) == float(sol.event_times[0])
        np.testing.assert_allclose(sol.event_times[0], 0.5, atol=1e-14)
    np.testing.assert_allclose(sol.final_state, [1.0 + (0.0 if zero_length else p * 0.5)], atol=1e-12)


# ------------------------------------------------------------------ (nearly) simultaneous guards
def _two_guards(first_offset, second_offset):
    """x' = -1 from 1; guards x - 0.5 + offset (entered at t = 0.5 + offset) to modes b, c."""
    a = hj.Mode("a", lambda t, x, p: -jnp.ones_like(x), 1)
    b = hj.Mode("b", lambda t, x, p: jnp.zeros_like(x), 1)
    c = hj.Mode("c", lambda t, x, p: jnp.zeros_like(x), 1)
    return hj.HybridSystem([a, b, c], [
        hj.Transition("a", "b", guard=lambda t, x, p: x[0] - 0.5 + first_offset),
        hj.Transition("a", "c", guard=lambda t, x, p: x[0] - 0.5 + second_offset),
    ])


@pytest.mark.parametrize("offsets, winner, simultaneous", [
    ((0.0, 1e-14), 1, True),    # b reached first, 1e-14 before c: b
    ((1e-14, 0.0), 1, True),    # c reached 1e-14 before b, within the event tolerance: b, listed first
    ((0.0, 1e-6), 1, False),    # 1e-6 apart: the first reached wins, whatever the listing order
    ((1e-6, 0.0), 2, False),
])
def test_nearly_simultaneous_guards_are_deterministic(offsets, winner, simultaneous):
    sys = _two_guards(*offsets)
    runs = [hj.simulate(sys, jnp.array([1.0]), "a", 0.0, 1.0, stepsize_controller=TIGHT) for _ in range(2)]
    for sol in runs:
        assert int(sol.final_mode) == winner and bool(sol.simultaneous[0]) == simultaneous
        np.testing.assert_allclose(sol.event_times[0], 0.5 + min(offsets), atol=2e-14 if simultaneous else 1e-13)
    assert float(runs[0].event_times[0]) == float(runs[1].event_times[0])


# ------------------------------------------------------------------ stiff: relay with a fast lag
LAM = 1e6


RELAY = examples.stiff_relay()


@pytest.mark.parametrize("tol", [1e-8, 1e-5])
def test_stiff_relay_with_kvaerno5_matches_the_closed_form(tol):
    # Each switch restarts a 1e-6 s lag: an implicit step across it is stable and accurate at
    # its end, but its dense output (where the switch is located) is not, so every epoch
    # starts from Hairer's rule, which sees the lag (a step carried over located all
    # switches after the first wrongly at 1e-5).
    ctrl = diffrax.PIDController(rtol=tol, atol=tol)
    sol = hj.simulate(RELAY, jnp.zeros(2), "up", 0.0, 20.0, LAM, solver=diffrax.Kvaerno5(),
                      stepsize_controller=ctrl, max_steps=2000)
    ref = examples.stiff_relay_closed_form(0.0, LAM, 20.0)  # switches at (1 + 1/LAM)(1 + 2k)
    n = len(ref["event_times"])
    assert sol.status_name == "T1_REACHED" and int(sol.num_events) == n == 10
    np.testing.assert_allclose(sol.event_times[:n], ref["event_times"], rtol=0, atol=1e-9)
    assert int(sol.num_steps) < 500  # an explicit solver needs ~ LAM * 20 / 3 steps
    assert RELAY.mode_names[int(sol.final_mode)] == ref["final_mode"]
    np.testing.assert_allclose(sol.final_state, ref["final_state"], atol=1e-8)


def test_stiff_relay_with_an_explicit_solver_stops_with_max_steps_and_keeps_its_progress():
    sol = hj.simulate(RELAY, jnp.zeros(2), "up", 0.0, 20.0, LAM, solver=diffrax.Tsit5(),
                      stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8), max_steps=300)
    assert sol.status_name == "MAX_STEPS"
    t = float(sol.final_time)
    assert 0 < t < 1 and np.all(np.isfinite(sol.final_state))
    np.testing.assert_allclose(sol.final_state[0], t, rtol=1e-8)  # s = t on the way up


# ------------------------------------------------------------------ time and state scales
@pytest.fixture(scope="module")
def scaled_ball():
    """The ball dropped from L at rest with g = 2 L / T^2: first impact at t = T."""

    @jax.jit
    def run(T, L):
        # atol per component in the component's own unit (height L, velocity L / T).
        ctrl = diffrax.PIDController(rtol=1e-10, atol=1e-10 * jnp.stack([L, L / T]))
        return hj.simulate(BALL, jnp.stack([L, 0.0 * L]), "flight", 0.0 * T, 3.5 * T,
                           {"g": 2 * L / T**2, "e": 0.5}, stepsize_controller=ctrl)

    return run


@pytest.mark.parametrize("T", [1e-9, 1e-3, 1.0, 1e6])
@pytest.mark.parametrize("L", [1e-8, 1.0, 1e8])
def test_relative_accuracy_holds_from_nanoseconds_to_megaseconds(scaled_ball, T, L):
    sol = scaled_ball(T, L)
    ref = examples.bouncing_ball_closed_form(L, 0.0, 2 * L / T**2, 0.5, 3.0 * T)
    n = int(sol.num_events)
    assert sol.status_name == "ZENO" and n >= 4
    np.testing.assert_allclose(sol.event_times[:n] / T, ref["event_times"][:n] / T, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.states_after[:n, 1] / (L / T), ref["post_velocities"][:n] / (L / T),
                               rtol=0, atol=1e-11)
    np.testing.assert_allclose(sol.zeno_time / T, examples.zeno_time(L, 2 * L / T**2, 0.5) / T, rtol=1e-11)


# ------------------------------------------------------------------ long runs
@pytest.mark.slow
def test_ten_thousand_elastic_bounces_keep_energy_and_timing():
    # e = 1 from h0 = 1 at rest: impacts at T (1 + 2k), T = sqrt(2 / g); energy g h + v^2 / 2 = g.
    n_bounces = 10_000
    T = math.sqrt(2 / G)
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 2 * n_bounces * T, {"g": G, "e": 1.0},
                      stepsize_controller=TIGHT, max_epochs=n_bounces + 2, max_steps=8 * n_bounces)
    assert sol.status_name == "T1_REACHED" and int(sol.num_events) == n_bounces
    ref = T * (1 + 2 * np.arange(n_bounces))
    np.testing.assert_allclose(sol.event_times[:n_bounces], ref, rtol=1e-9)
    x = np.asarray(sol.states_after[:n_bounces])
    energy = G * x[:, 0] + 0.5 * x[:, 1] ** 2
    np.testing.assert_allclose(energy, G, rtol=1e-8)


def test_elastic_impact_oscillator_energy_drift_per_bounce_is_at_the_tolerance():
    # x'' = -x against a wall at x = -a, elastic: from (1, 0) impacts at pi - phi + k (2 pi - 2 phi),
    # phi = arccos(a). Tsit5 is not exact here, so energy drifts; the drift per bounce is ~ rtol.
    a, n_bounces = 0.5, 100
    osc = hj.HybridSystem([hj.Mode("free", lambda t, x, a: jnp.array([x[1], -x[0]]), 2)], [
        hj.Transition("free", "free", guard=lambda t, x, a: x[0] + a,
                      reset=lambda t, x, a: jnp.array([x[0], -x[1]]))])
    phi = math.acos(a)
    period = 2 * math.pi - 2 * phi
    sol = hj.simulate(osc, jnp.array([1.0, 0.0]), "free", 0.0, math.pi - phi + (n_bounces - 0.5) * period, a,
                      stepsize_controller=TIGHT, max_epochs=n_bounces + 2, max_steps=100 * n_bounces)
    assert sol.status_name == "T1_REACHED" and int(sol.num_events) == n_bounces
    energy = 0.5 * np.sum(np.asarray(sol.states_after[:n_bounces]) ** 2, axis=1)
    assert np.max(np.abs(energy - 0.5)) < n_bounces * 1e-10
    ref = math.pi - phi + period * np.arange(n_bounces)
    np.testing.assert_allclose(sol.event_times[:n_bounces], ref, rtol=1e-8)


# ------------------------------------------------------------------ float32
F32_BALL = {"g": np.float32(9.8), "e": np.float32(0.8)}


@pytest.mark.parametrize("tol", [None, 1e-6])
def test_float32_ball_reaches_its_zeno_point(tol):
    ctrl = None if tol is None else diffrax.PIDController(rtol=tol, atol=tol)
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0], jnp.float32), "flight", 0.0, 5.0, F32_BALL,
                      stepsize_controller=ctrl)
    assert sol.status_name == "ZENO" and sol.event_times.dtype == jnp.float32
    n = int(sol.num_events)
    ref = examples.bouncing_ball_closed_form(1.0, 0.0, 9.8, 0.8, 5.0)
    np.testing.assert_allclose(sol.event_times[:n], ref["event_times"][:n], rtol=2e-5)
    # t_inf = t_n + T_n r / (1 - r) is extrapolated from the last epoch lengths: with r = 0.8 an
    # error of one float32 event time (located to event_tol, ~1e-6 of its step) is amplified
    # up to 1 / (1 - r)^2 = 25 times in the ratio's term.
    np.testing.assert_allclose(sol.zeno_time, examples.zeno_time(1.0, 9.8, 0.8), rtol=1e-4)


def test_float32_with_an_unreachable_tolerance_warns_and_ends_with_a_status():
    ctrl = diffrax.PIDController(rtol=1e-9, atol=1e-9)
    with pytest.warns(UserWarning, match="below what float32 resolves"):
        sol = hj.simulate(BALL, jnp.array([1.0, 0.0], jnp.float32), "flight", 0.0, 5.0, F32_BALL,
                          stepsize_controller=ctrl, max_steps=2000)
    assert sol.status_name in ("ZENO", "MAX_STEPS")
    n = int(sol.num_events)
    assert n >= 1 and np.all(np.isfinite(sol.event_times[:n]))
    ref = examples.bouncing_ball_closed_form(1.0, 0.0, 9.8, 0.8, 5.0)
    np.testing.assert_allclose(sol.event_times[:n], ref["event_times"][:n], rtol=2e-5)


def test_float32_grazing_below_its_resolution_is_a_documented_limit():
    # In float32 the apex height 0.459 is resolved to 3e-8: a crossing 1e-3 deep is found, one
    # 1e-9 deep (below resolution) may or may not be; either way the run ends normally.
    run = jax.jit(lambda c: hj.simulate(CEILING_GRAZE, jnp.array([0.0, V0], jnp.float32), "fly", 0.0, 2.0, c))
    H = V0 * V0 / (2 * G)
    deep = run(np.float32(H - 1e-3))
    assert int(deep.num_events) == 1
    np.testing.assert_allclose(deep.event_times[0], _crossing_time(float(np.float32(H - 1e-3)))[0], rtol=5e-5)
    shallow = run(np.float32(H - 1e-9))
    assert shallow.status_name == "T1_REACHED" and int(shallow.num_events) in (0, 1)
    assert np.all(np.isfinite(shallow.final_state))


# ------------------------------------------------------------------ bad user functions
def test_flow_blowing_up_mid_run_gives_nonfinite_with_the_events_before_it():
    # The ball bounces normally until t = 1, where its flow becomes inf.
    flight = hj.Mode("flight", lambda t, x, p: jnp.array([x[1], jnp.where(t < 1.0, -G, jnp.inf)]), 2)
    sys = hj.HybridSystem([flight], [hj.Transition(
        "flight", "flight", guard=lambda t, x, p: x[0], reset=lambda t, x, p: jnp.array([x[0], -0.5 * x[1]]))])
    sol = hj.simulate(sys, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, stepsize_controller=TIGHT)
    assert sol.status_name == "NONFINITE"
    np.testing.assert_allclose(sol.event_times[0], math.sqrt(2 / G), atol=1e-9)
    assert 0.99 < float(sol.final_time) <= 1.0 and np.all(np.isfinite(sol.final_state))


@pytest.mark.parametrize("where, message", [
    ("flow", "Mode 0 'm': flow returned dtype complex"),
    ("guard", "Transition 0 .*guard returned dtype int"),
    ("reset", "Transition 0 .*reset returned dtype bool"),
])
def test_wrong_output_dtypes_are_caught_at_definition(where, message):
    flow = (lambda t, x, p: x.astype(jnp.complex64)) if where == "flow" else (lambda t, x, p: -x)
    guard = (lambda t, x, p: jnp.int32(1)) if where == "guard" else (lambda t, x, p: x[0])
    reset = (lambda t, x, p: x > 0) if where == "reset" else (lambda t, x, p: x)
    with pytest.raises(hj.DefinitionError, match=message):
        hj.HybridSystem([hj.Mode("m", flow, 1)], [hj.Transition("m", "m", guard=guard, reset=reset)])


# ------------------------------------------------------------------ accuracy presets
@pytest.mark.parametrize("name, bound", [("fast", 5e-3), ("balanced", 5e-6), ("precise", 1e-9)])
def test_accuracy_presets_meet_their_error_on_the_thermostat(name, bound):
    # 25 heating/cooling switches from 19 degrees, ambient 30, one hour, against the closed form;
    # errors accumulate along the switches, each epoch's steps at the tolerance (|T| ~ 20:
    # ~2e-7 per step in T at 1e-8; measured: fast ~1.3e-3, balanced ~1.2e-6, precise ~6e-11 by
    # the last switch).
    p = dict(a=0.1, T_amb=30.0, P_heat=2.5, P_cool=2.0, s=20.0)
    sol = hj.simulate(examples.thermostat(), jnp.array([19.0]), "off", 0.0, 60.0, p, **hj.accuracy_preset(name))
    ref = examples.thermostat_closed_form(19.0, "off", p, 60.0)
    n = len(ref["event_times"])
    assert int(sol.num_events) == n and n >= 5
    np.testing.assert_allclose(sol.event_times[:n], ref["event_times"], rtol=0, atol=bound)
    np.testing.assert_allclose(sol.final_state, ref["final_state"], rtol=0, atol=bound)


def test_accuracy_preset_arguments():
    kw = hj.accuracy_preset("precise")
    assert isinstance(kw["solver"], diffrax.Dopri5) and kw["stepsize_controller"].rtol == 1e-12
    kw32 = hj.accuracy_preset("balanced", jnp.float32)
    assert kw32["stepsize_controller"].rtol >= 8 * np.finfo(np.float32).eps
    with pytest.raises(ValueError, match="unknown accuracy preset 'quick'"):
        hj.accuracy_preset("quick")
    with pytest.raises(ValueError, match="float16"):
        hj.accuracy_preset("fast", jnp.float16)
