"""Each execution rule (`hybridjax._rules`) alone, against cases derived by hand in the tests.

The engines call these functions (the per-execution loop directly, the batched loop lifted over
its lanes); `tests/test_architecture.py` checks that both do. Whole runs are tested elsewhere.
"""

import math
from unittest.mock import patch

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from hybridjax import _rules as R
from hybridjax import examples
from hybridjax._core.jaxprs import equation_count
from hybridjax._core.status import Status
from hybridjax._definition.kernels import GuardJets, Kernels
from hybridjax._rules.locate import BracketedNewton
from hybridjax._rules.zeno import ZenoOptions
from hybridjax._step.runge_kutta import (
    PIDState,
    UnrolledERK,
    explicit_rk_step,
    pid_controller,
    rk_error_estimate,
    scaled_error,
)

EPS = float(np.finfo(np.float64).eps)
TOL = 1e-10  # an event-time tolerance
BALL_KERN = Kernels(examples.bouncing_ball(), {"g": 9.8, "e": 0.8}, jnp.float64)
G = 9.8


def _jets(L0, L1, L2=0.0, L3=0.0, band=1e-6, scale1=1.0):
    def arr(v):
        return jnp.broadcast_to(jnp.asarray(v, jnp.float64), jnp.shape(jnp.asarray(L0)))

    return GuardJets(*(arr(v) for v in (L0, L1, L2, L3, band, scale1)))


# ---------------------------------------------------------------------------- tolerances
def test_event_time_tol_is_relative_to_the_step_floored_at_8_ulp_of_t():
    # max(1e-12 * 0.5, 8 eps 10) = 5e-13; max(1e-12 * 1e-3, 8 eps 1e6) = 8 eps 1e6
    assert float(R.event_time_tol(1e-12, 10.0, 0.5, EPS)) == pytest.approx(5e-13, rel=1e-15)
    assert float(R.event_time_tol(1e-12, 1e6, 1e-3, EPS)) == pytest.approx(8 * EPS * 1e6, rel=1e-15)
    assert float(R.event_time_tol(1e-12, 3.0, -0.5, EPS)) == pytest.approx(5e-13, rel=1e-15)


def test_step_end_moves_t_by_at_least_one_ulp_and_stops_at_t1():
    one = jnp.asarray(1.0)
    assert float(R.step_end(one, 0.5, 10.0)) == 1.5
    assert float(R.step_end(one, 0.0, 10.0)) == np.nextafter(1.0, 2.0)
    assert float(R.step_end(one, 1e-300, 10.0)) == np.nextafter(1.0, 2.0)
    assert float(R.step_end(jnp.asarray(9.8), 1.0, 10.0)) == 10.0


def test_a_run_that_reaches_t1_at_an_epochs_start_continues_by_its_flow():
    # x + ((t1 - t_s) - its value) F: the value is x, the tangent F (dt1 - dt_s) where the run
    # ended at its last epoch's start, x's own elsewhere; a non-finite field adds nothing.
    x, F = jnp.array([1.0, 2.0]), jnp.array([0.5, -9.8])

    def cont(field, at_start):
        return jax.jvp(lambda x, ts, t1: R.continued_past_start(x, field, ts, t1, at_start),
                       (x, jnp.asarray(0.25), jnp.asarray(0.25)),
                       (jnp.array([1.0, 0.0]), jnp.asarray(1.0), jnp.asarray(3.0)))

    value, tangent = cont(F, jnp.array(True))
    np.testing.assert_array_equal(value, x)
    np.testing.assert_allclose(tangent, [1.0 + 0.5 * 2.0, -9.8 * 2.0])
    value, tangent = cont(F, jnp.array(False))
    np.testing.assert_array_equal(value, x)
    np.testing.assert_array_equal(tangent, [1.0, 0.0])
    value, tangent = cont(jnp.array([jnp.inf, jnp.nan]), jnp.array(True))
    np.testing.assert_array_equal(value, x)
    np.testing.assert_array_equal(tangent, [1.0, 0.0])


def test_a_step_that_lands_on_t1_takes_t1s_derivative():
    # t + h = t1 to the last bit: the step ends at t1 with t1's tangent (jnp.minimum would give
    # half of each argument's). Tangents: t 1, h 0, t1 3 -> 3; elsewhere the smaller one's.
    def end(t, h, t1):
        return jax.jvp(R.step_end, (jnp.asarray(t), jnp.asarray(h), jnp.asarray(t1)),
                       (jnp.asarray(1.0), jnp.asarray(0.0), jnp.asarray(3.0)))

    assert tuple(map(float, end(0.75, 0.25, 1.0))) == (1.0, 3.0)
    assert tuple(map(float, end(0.5, 0.25, 1.0))) == (0.75, 1.0)
    assert tuple(map(float, end(0.875, 0.25, 1.0))) == (1.0, 3.0)
    assert np.isnan(float(R.step_end(jnp.asarray(0.5), jnp.nan, 1.0)))  # as jnp.minimum's
    assert np.isnan(float(R.step_end(jnp.asarray(0.5), 0.25, jnp.nan)))
    # clip_to_times: a jump time at t1 is not stepped to, and t1 keeps its tangent at the tie
    _, t_next, _ = jax.jvp(lambda t1: R.clip_to_times(jnp.asarray(0.5), jnp.asarray(1.0), t1, None,
                                                      jnp.array([1.0])), (jnp.asarray(1.0),), (jnp.asarray(3.0),))[1]
    assert float(t_next) == 3.0


def test_a_save_time_at_the_steps_end_keeps_its_derivative():
    # x(s) moves with s: at s = t_next (a save at t1 in the last step) the tangent is s's own,
    # 3 (jnp.clip against the constant end gives 1.5); outside the step, the end, tangent 0.
    def at(s):
        return tuple(map(float, jax.jvp(lambda s_: R.within_step(s_, jnp.asarray(0.5), jnp.asarray(1.0)),
                                        (jnp.asarray(s),), (jnp.asarray(3.0),))))

    assert at(1.0) == (1.0, 3.0) and at(0.5) == (0.5, 3.0) and at(0.7) == (0.7, 3.0)
    assert at(1.2) == (1.0, 0.0) and at(0.2) == (0.5, 0.0)


def test_clip_to_times_ends_steps_at_step_times_and_steps_over_jump_times():
    # diffrax's ClipStepSizeController rule, by hand: a step ends at the next step time, just
    # before the next jump time, and the step after starts just after the jump time.
    up, down = (lambda x: float(np.nextafter(x, np.inf))), (lambda x: float(np.nextafter(x, -np.inf)))

    def clip(t, t_next, t1=10.0, step_ts=None, jump_ts=None):
        ts = [None if x is None else jnp.asarray(x) for x in (step_ts, jump_ts)]
        t, t_next, jumped = R.clip_to_times(jnp.asarray(t), jnp.asarray(t_next), jnp.asarray(t1), *ts)
        return float(t), float(t_next), bool(jumped)

    assert clip(0.0, 1.0, step_ts=[0.3, 0.7]) == (0.0, 0.3, False)
    assert clip(0.3, 1.0, step_ts=[0.3, 0.7]) == (0.3, 0.7, False)  # the next one after t
    assert clip(0.8, 1.0, step_ts=[0.3, 0.7]) == (0.8, 1.0, False)  # none left
    assert clip(0.0, 1.0, jump_ts=[0.6]) == (0.0, down(0.6), False)
    assert clip(down(0.6), 1.0, jump_ts=[0.6]) == (up(0.6), 1.0, True)  # moved past it
    assert clip(0.6, 1.0, jump_ts=[0.6]) == (up(0.6), 1.0, True)
    assert clip(down(0.6), up(up(0.6)), jump_ts=[0.6]) == (up(0.6), up(up(0.6)), True)
    assert clip(0.0, 0.6, t1=0.6, jump_ts=[0.6]) == (0.0, 0.6, False)  # at t1: not stepped before
    # a time both: the step ends before it, the next one starts after it
    assert clip(0.0, 1.0, step_ts=[0.5], jump_ts=[0.5]) == (0.0, down(0.5), False)
    assert clip(down(0.5), 1.0, step_ts=[0.5], jump_ts=[0.5]) == (up(0.5), 1.0, True)
    # lanes broadcast
    t, t_next, jumped = R.clip_to_times(
        jnp.array([0.0, down(0.6)]),
        jnp.array([1.0, 1.0]),
        jnp.asarray(10.0),
        jnp.array([0.3]),
        jnp.array([0.6]),
    )
    np.testing.assert_array_equal(t, [0.0, up(0.6)])
    np.testing.assert_array_equal(t_next, [0.3, 1.0])
    np.testing.assert_array_equal(jumped, [False, True])


# ---------------------------------------------------------------------------- start of an epoch
def test_trending_negative_reads_the_first_nonzero_lie_derivative():
    tn = lambda *a: bool(R.trending_negative(*(jnp.asarray(x) for x in a), EPS))  # noqa: E731
    assert tn(-1.0, 5.0, 5.0, 1.0)  # L1 < 0
    assert not tn(1.0, -5.0, -5.0, 1.0)  # L1 > 0 decides
    assert tn(0.0, -1.0, 5.0, 1.0)  # L1 = 0, L2 < 0
    assert tn(0.0, 0.0, -1.0, 1.0)  # L1 = L2 = 0, L3 < 0
    # |L1| = 1e-20 is below 64 eps scale1 (1.4e-14): cancellation, so L2 > 0 decides
    assert not tn(-1e-20, 2.0, 0.0, 1.0)
    assert tn(-1e-12, 2.0, 0.0, 1.0)  # above it: L1 decides


def test_start_decision_fires_inside_or_trending_in_and_disarms_departing_guards():
    # inside (L0 < -band), in the band and falling, in the band and leaving, positive
    jets = _jets([-1.0, 0.0, 0.0, 0.5], [0.0, -1.0, 1.0, -1.0])
    fire, g_start = R.start_decision(jets, jnp.array([True, True, True, True]), EPS)
    np.testing.assert_array_equal(fire, [True, True, False, False])
    np.testing.assert_array_equal(g_start, [0.0, 0.0, 0.0, 0.5])  # disarmed: 0; leaving: 0
    np.testing.assert_array_equal(R.strictly_inside(jets), [True, False, False, False])
    # a guard of another mode never fires and starts at +1
    fire, g_start = R.start_decision(jets, jnp.array([False, True, True, True]), EPS)
    assert not bool(fire[0]) and float(g_start[0]) == 1.0


def test_unresolved_departure_fires_a_guard_that_turns_back_within_the_resolution():
    # g(s) = L0 + L1 s + L2 s^2 / 2 with L1 = 2, L2 = -4: apex at s* = 0.5, value L0 + 0.5.
    # tol_t = 0.4: resolved (s* > tol_t, apex 0.5 > 0); tol_t = 0.6: unresolved (s* <= tol_t);
    # L0 = -0.6 (inside the band of a wide band): the apex -0.1 <= 0, never positive.
    jets = _jets([0.0, 0.0, -0.6, 0.0, 0.0], [2.0, 2.0, 2.0, -2.0, 2.0], [-4.0, -4.0, -4.0, -4.0, 4.0], band=1.0)
    tol = jnp.array([0.4, 0.6, 0.4, 0.6, 0.6])
    got = jax.vmap(lambda j, t: R.unresolved_departure(j, t))(jets, tol)
    # falling (L1 < 0) or accelerating away (L2 > 0): not a departure that turns back
    np.testing.assert_array_equal(got, [False, True, True, False, False])
    fire, _ = R.start_decision(jets, jnp.ones(5, bool), EPS, 0.5)
    np.testing.assert_array_equal(fire, [True, True, True, True, False])  # the 4th falls (L1 < 0)
    fire, _ = R.start_decision(jets, jnp.ones(5, bool), EPS, 0.4)
    np.testing.assert_array_equal(fire, [False, False, True, True, False])


def test_departure_step_bound_is_the_return_time_halved():
    # g(s) = L1 s + L2 s^2 / 2 returns to 0 at s = 2 L1 / |L2| = 1.0; half of it: 0.5
    jets = _jets([0.0, 0.0], [2.0, 2.0], [-4.0, -4.0])
    assert float(R.departure_step_bound(jets, jnp.array([True, False]), jnp.array([False, False]))) == 0.5
    # not departing (not outgoing, or firing): no bound
    assert float(R.departure_step_bound(jets, jnp.array([False, False]), jnp.array([False, False]))) == np.inf
    assert float(R.departure_step_bound(jets, jnp.array([True, True]), jnp.array([True, True]))) == np.inf


def test_first_step_carries_the_proposal_only_when_asked():
    assert R.carries_step(None, True) and not R.carries_step(0.1, True) and not R.carries_step(None, False)
    assert float(R.first_step(0.01, 0.1, True)) == 0.1
    assert float(R.first_step(0.01, 0.0, True)) == 0.01  # the first epoch: no proposal yet
    assert float(R.first_step(0.01, 0.1, False)) == 0.01


def test_epoch_start_of_the_ball_on_the_floor():
    # The guard h with flow (v, -g): L0 = h, L1 = v, L2 = -g.
    def start(h, v, initial=1.0):
        return R.epoch_start(
            BALL_KERN,
            jnp.asarray(0),
            jnp.asarray(0.0),
            jnp.array([h, v]),
            {"g": G, "e": 0.8},
            jnp.asarray(0.0),
            jnp.asarray(initial),
            carry=False,
            rtol=1e-8,
            atol=1e-8,
            event_tol=1e-12,
            eps=EPS,
        )

    falling = start(0.0, -1.0)
    assert bool(falling.fire) and int(falling.k) == 0 and not bool(falling.inside)
    assert not bool(falling.simultaneous) and bool(falling.finite)
    np.testing.assert_array_equal(falling.F, [-1.0, -G])
    leaving = start(0.0, 0.98)
    # departing: disarmed, and the first step capped at v / g = 0.1 (half the flight 2 v / g)
    assert not bool(leaving.fire) and float(leaving.g_start[0]) == 0.0
    assert float(leaving.h) == pytest.approx(0.98 / G, rel=1e-15)
    high = start(1.0, 0.0, initial=0.25)
    assert not bool(high.fire) and float(high.g_start[0]) == 1.0 and float(high.h) == 0.25


# ---------------------------------------------------------------------------- a step
def test_nonfinite_step_shrinks_by_four_then_stops_at_the_resolution_of_t():
    out = R.nonfinite_step(jnp.array(True), jnp.array(True), 0.3, 0.1, 1.0, EPS)
    assert bool(out.finite) and float(out.next_h) == 0.3 and not bool(out.stuck)
    out = R.nonfinite_step(jnp.array(False), jnp.array(True), 0.3, 0.1, 1.0, EPS)
    assert not bool(out.finite) and float(out.next_h) == 0.025 and not bool(out.stuck)
    # h = 1e-16 <= 64 eps max(|t|, h) = 1.4e-14: nothing left to shrink
    assert bool(R.nonfinite_step(jnp.array(True), jnp.array(False), 0.3, 1e-16, 1.0, EPS).stuck)


def test_step_stops_precedence():
    # next_h = 1e-16 <= 16 eps |t| = 3.6e-15 at t = 1: collapsed (when finite)
    assert bool(R.step_collapsed(jnp.array(True), 1e-16, 1.0, EPS))
    assert not bool(R.step_collapsed(jnp.array(False), 1e-16, 1.0, EPS))
    assert not bool(R.step_collapsed(jnp.array(True), 1e-13, 1.0, EPS))
    stops = R.step_stops(jnp.array(True), jnp.array(True), 1e-16, 1.0, EPS, 10, 10)
    assert [s for _, s in stops] == [Status.NONFINITE, Status.STEP_COLLAPSE, Status.MAX_STEPS]
    done, code = R.stop_first(jnp.array(False), jnp.asarray(0, jnp.int32), *stops)
    assert bool(done) and int(code) == int(Status.NONFINITE)  # all three hold: the first wins
    done, code = R.stop_first(
        jnp.array(False),
        jnp.asarray(0, jnp.int32),
        *R.step_stops(jnp.array(False), jnp.array(True), 0.5, 1.0, EPS, 10, 10),
    )
    assert int(code) == int(Status.MAX_STEPS)


def test_stop_first_keeps_the_status_of_a_finished_execution():
    done, code = R.stop_first(
        jnp.array(True), jnp.asarray(int(Status.BLOCKED), jnp.int32), (jnp.array(True), Status.NONFINITE)
    )
    assert bool(done) and int(code) == int(Status.BLOCKED)
    done, code = R.stop_first(jnp.array(False), jnp.asarray(0, jnp.int32), (jnp.array(False), Status.ZENO))
    assert not bool(done) and int(code) == 0


# ---------------------------------------------------------------------------- detection
def test_crossing_and_first_crossings():
    assert bool(R.crossing(1.0, 0.0)) and bool(R.crossing(1.0, -1.0))
    assert not bool(R.crossing(0.0, -1.0)) and not bool(R.crossing(-1.0, 1.0))
    has, j = R.first_crossings(jnp.array([1.0, 1.0, 1.0]), jnp.array([[0.5, -1.0, 2.0], [-0.5, -2.0, 3.0]]))
    np.testing.assert_array_equal(has, [True, True, False])
    np.testing.assert_array_equal(j[:2], [1, 0])


def test_dip_interval_from_the_end_tangents():
    # g(s) = (s - 0.5)^2 + c on [0, 1]: V = 0.25 + c at both ends, D = -1, +1. The tangents
    # meet at u = (V1 - V0 - D1 h) / (D0 - D1) = 0.5, where the left one is V0 - 0.5 = c - 0.25.
    for c, cand in ((-0.01, True), (0.3, False), (0.25, True)):
        cross, is_cand, u = R.dip_interval(0.25 + c, 0.25 + c, -1.0, 1.0, 1.0)
        assert not bool(cross) and bool(is_cand) == cand and float(u) == 0.5
    # no minimum inside (slopes of one sign), or a sign change: not a dip
    assert not bool(R.dip_interval(0.3, 0.2, -1.0, -0.5, 1.0)[1])
    assert bool(R.dip_interval(0.3, -0.2, -1.0, 1.0, 1.0)[0])
    # a non-finite slope reads 0: no dip
    assert not bool(R.dip_interval(0.3, 0.3, np.nan, 1.0, 1.0)[1])


def test_dip_candidates_and_filter():
    # g(s) = (s - 1.5)^2 - 0.01 sampled at s = 0, 1, 2: values 2.24, 0.24, 0.24, slopes
    # -3, -1, 1; the second interval is a candidate, the tangents meeting at s = 1.5.
    s = jnp.array([0.0, 1.0, 2.0])
    V, D = (s - 1.5) ** 2 - 0.01, 2 * (s - 1.5)
    suspect, i, x0 = R.dip_candidates(V[:, None], D[:, None], s)
    assert bool(suspect[0]) and int(i[0]) == 1 and float(x0[0]) == 1.5
    t, f = jnp.array(True), jnp.array(False)
    assert bool(R.dip_filter(t, jnp.array(2), t, jnp.array(1)))  # before the crossing
    assert not bool(R.dip_filter(t, jnp.array(1), t, jnp.array(1)))  # not before it
    assert bool(R.dip_filter(f, jnp.array(0), t, jnp.array(3)))  # no crossing


def test_needs_location_is_any_crossing_or_dip_candidate():
    # Whether a step is held (`needs_location`) against where (`first_crossings`,
    # `dip_candidates`): random samples of 3 watched functions at 6 sample times, with values
    # near zero so that crossings, dips and neither all occur.
    rng = np.random.default_rng(3)
    s = jnp.array([0.0, 0.2, 0.4, 0.6, 0.8, 1.0])
    seen = set()
    for _ in range(200):
        V = jnp.asarray(rng.uniform(-0.2, 1.0, (6, 3)))
        D = jnp.asarray(rng.normal(0.0, 2.0, (6, 3)))
        g_start = jnp.asarray(rng.uniform(0.0, 1.0, 3))
        has, _ = R.first_crossings(g_start, V[1:])
        suspect, _, _ = R.dip_candidates(jnp.concatenate([g_start[None], V[1:]]), D, s)
        need = bool(R.needs_location(g_start, V, D, s))
        assert need == bool(jnp.any(has) | jnp.any(suspect))
        seen.add((bool(jnp.any(has)), bool(jnp.any(suspect))))
    assert seen == {(False, False), (False, True), (True, False), (True, True)}


# ---------------------------------------------------------------------------- location
@pytest.mark.parametrize("one_copy", [False, True])
def test_locate_root_brackets_the_root_from_the_right(one_copy):
    r = float(R.locate_root(lambda x: 2.0 - x * x, jnp.asarray(1.0), jnp.asarray(2.0), 1e-12, one_copy=one_copy))
    assert 0.0 <= r - math.sqrt(2.0) <= 1e-12 and 2.0 - r * r <= 0.0


def test_the_root_search_holds_a_large_function_once():
    # Written out, the search evaluates f at five places in its program; as one loop, at one.
    # `equation_count` counts the equations of nested jaxprs too (here a while loop's body).
    def small(x):
        return 2.0 - x * x

    def large(x):
        return lax.fori_loop(0, 3, lambda i, v: v + 0.0 * jnp.sin(v) * jnp.cos(v), 2.0 - x * x)

    x = jnp.asarray(1.5)
    n_small, n_large = equation_count(small, x), equation_count(large, x)
    assert n_small == 2 and n_large > n_small + 5  # small: mul, sub

    def copies(f, one_copy):
        jaxpr = jax.make_jaxpr(lambda a, b: R.locate_root(f, a, b, 1e-12, one_copy=one_copy))(x - 0.5, x + 0.5)
        return str(jaxpr).count("sin")

    # A value-and-slope evaluation of `large` holds sin twice (sin, and -sin in cos' tangent), a
    # value alone once: written out, the ends, the iterate and b (3 x 2) and the probe and the
    # candidates (2 x 1); as one loop, one value-and-slope evaluation.
    assert copies(large, False) == 8 and copies(large, True) == 2
    # Within `across_lanes` (the batched engine) the candidates have a copy each (3 x 1, in place
    # of the map's one): 10.
    with R.locate.across_lanes():
        assert copies(large, False) == 10 and copies(large, True) == 2
    with patch.object(R.locate, "ONE_COPY_ABOVE", n_small):
        assert copies(large, None) == copies(large, True)
    with patch.object(R.locate, "ONE_COPY_ABOVE", n_large):
        assert copies(large, None) == copies(large, False)


@pytest.mark.parametrize("one_copy", [False, True])
def test_root_bracket_closes_in_a_few_newton_iterations_on_a_million_roots(one_copy):
    # Under vmap every execution waits for the slowest: the search must close its bracket in
    # Newton's few iterations on every root, also where a converged Newton point lands within
    # rounding of the bracket's end (a bisection from there takes ~40 halvings).
    n = 1_000_000
    rng = np.random.default_rng(0)
    r, c = rng.uniform(0.2, 3.0, n), rng.uniform(-2.0, 2.0, n)
    a, b = r - rng.uniform(0.01, 0.5, n), r + rng.uniform(0.01, 0.5, n)

    def one(r, c, a, b):
        def f(x):  # decreasing through its only root r in [a, b]
            return (r - x) * (1.0 + 0.3 * c * (x - r)) * (2.0 + jnp.sin(x))

        tol = 1e-12 * (b - a)
        return R.root_bracket(f, a, b, tol, one_copy=one_copy)[2], R.locate_root(f, a, b, tol, one_copy=one_copy), tol

    iterations, x, tol = map(np.asarray, jax.jit(jax.vmap(one))(r, c, a, b))
    assert iterations.max() <= 8
    assert np.all((x - r <= tol) & (x - r >= -4e-16 * r))


def _hermite_start(f, a, b):
    (fa, fb), (da, db) = jax.vmap(lambda x: jax.jvp(f, (x,), (jnp.ones_like(x),)))(jnp.stack([a, b]))
    return R.hermite_root(a, b, fa, fb, da, db)


def test_hermite_start_is_the_root_of_a_cubic():
    # The cubic Hermite interpolant of a cubic is the cubic itself: its root, found by Newton
    # steps from the regula-falsi point, is the function's root r (by construction).
    n = 100_000
    rng = np.random.default_rng(1)
    r, c, d = rng.uniform(0.2, 3.0, n), rng.uniform(-1.0, 1.0, n), rng.uniform(-1.0, 1.0, n)
    a, b = r - rng.uniform(0.01, 0.5, n), r + rng.uniform(0.01, 0.5, n)

    def one(r, c, d, a, b):
        return _hermite_start(lambda x: (r - x) * (1.0 + 0.3 * c * (x - r) + 0.2 * d * (x - r) ** 2), a, b)

    err = np.abs(np.asarray(jax.jit(jax.vmap(one))(r, c, d, a, b)) - r) / (b - a)
    assert np.median(err) <= 1e-15 and err.max() <= 2e-15


@pytest.mark.parametrize("one_copy", [False, True])
def test_a_falling_balls_root_closes_in_one_iteration(one_copy):
    # A height h0 + v t - g t^2 / 2 (the ball's guard along its exact flow) is its own Hermite
    # interpolant: on a bracket where it falls, the search starts at the landing time and its
    # first probe closes the bracket.
    n = 10_000
    rng = np.random.default_rng(2)
    h0, v = rng.uniform(0.1, 2.0, n), rng.uniform(-3.0, 3.0, n)
    land = (v + np.sqrt(v * v + 2 * 9.8 * h0)) / 9.8
    fall = land - np.maximum(v / 9.8, 0.0)  # from the apex (or t = 0) to the landing
    a, b = land - fall * rng.uniform(0.01, 0.25, n), land + fall * rng.uniform(0.01, 0.25, n)

    def one(h0, v, a, b):
        def f(t):
            return h0 + v * t - 4.9 * t * t

        tol = 1e-12
        return R.root_bracket(f, a, b, tol, one_copy=one_copy)[2], R.locate_root(f, a, b, tol, one_copy=one_copy)

    iterations, t = map(np.asarray, jax.jit(jax.vmap(one))(h0, v, a, b))
    assert iterations.max() == 1
    assert np.abs(t - land).max() <= 1e-12


def test_searches_across_lanes_locate_the_same_roots_to_the_bit():
    # The fixed points of the searches (the ends, the polish's candidates, the first event's
    # simultaneity values) in one pass across lanes, or in one copy under `lax.map`: another
    # program, the same arithmetic. Roots of cubics whose root r is known, and the simultaneity rule.
    n = 10_000
    rng = np.random.default_rng(3)
    r, c = rng.uniform(0.2, 3.0, n), rng.uniform(-1.0, 1.0, n)
    a, b = r - rng.uniform(0.01, 0.5, n), r + rng.uniform(0.01, 0.5, n)

    def one(r, c, a, b):
        def f(x):
            return (r - x) * (1.0 + 0.3 * c * (x - r)) * (2.0 + jnp.sin(x))

        return R.locate_root(f, a, b, 1e-12 * (b - a), one_copy=False)

    mapped = np.asarray(jax.jit(jax.vmap(one))(r, c, a, b))
    with R.locate.across_lanes():
        across = np.asarray(jax.jit(jax.vmap(one))(r, c, a, b))
        ev = _first_event_of(1e-14, 0.0, 0.5)
    np.testing.assert_array_equal(across, mapped)
    assert np.all((mapped - r <= 1e-12 * (b - a)) & (mapped - r >= -4e-16 * r))
    assert int(ev.index) == 0 and bool(ev.simultaneous) and 0.0 <= float(ev.t_star) - 1.0 <= 1e-12


def test_locate_minimum():
    x, f = R.locate_minimum(
        lambda x: (x - 0.3) ** 2 + 0.1, jnp.asarray(0.0), jnp.asarray(1.0), jnp.asarray(0.5), 1e-12
    )
    assert float(x) == pytest.approx(0.3, abs=1e-8) and float(f) == pytest.approx(0.1, abs=1e-15)
    x, f = R.locate_minimum(
        lambda x: (x - 0.3) ** 2 - 0.1, jnp.asarray(0.0), jnp.asarray(1.0), jnp.asarray(0.5), 1e-12
    )
    assert float(f) < 0.0 and (float(x) - 0.3) ** 2 < 0.1  # a point inside, found early


def test_event_brackets_turn_a_dip_into_a_bracket():
    # g = (x - 1.5)^2 - 0.01 dips below 0 between the samples 1 and 2 (roots 1.4 and 1.6);
    # the minimum search from 1.5 finds g < 0 at once, so the bracket is [1, 1.5].
    def values_at(x):
        return jnp.stack([(x - 1.5) ** 2 - 0.01])

    det = R.Detection(jnp.array([False]), jnp.array([0]), jnp.array([True]), jnp.array([1]), jnp.array([1.5]))
    br = R.event_brackets(values_at, det, jnp.array([0.0, 1.0, 2.0]), 1e-12)
    assert bool(br.has[0]) and float(br.a[0]) == 1.0 and float(br.b[0]) == 1.5
    ev = R.first_event(values_at, br, 1e-12, jnp.asarray(2.0))
    assert float(ev.t_star) == pytest.approx(1.4, abs=1e-12) and int(ev.index) == 0


def test_a_dip_that_stays_above_zero_leaves_the_crossing_after_it():
    # g = u^2 + 0.01 - u^3, u = x - 1.5, on the samples 0, 1, 2, 3: a dip candidate on [1, 2]
    # whose minimum (0.01 at 1.5) stays above zero, then a crossing between 2 and 3. The first
    # event is the crossing, at brentq's root of g.
    from scipy.optimize import brentq

    def g(x):
        u = x - 1.5
        return u * u + 0.01 - u**3

    det = R.Detection(jnp.array([True]), jnp.array([2]), jnp.array([True]), jnp.array([1]), jnp.array([1.5]))
    s_ext = jnp.array([0.0, 1.0, 2.0, 3.0])
    br = R.event_brackets(lambda x: jnp.stack([g(x)]), det, s_ext, 1e-12)
    assert bool(br.has[0]) and float(br.a[0]) == 2.0 and float(br.b[0]) == 3.0
    ev = R.first_event(lambda x: jnp.stack([g(x)]), br, 1e-12, jnp.asarray(3.0))
    r = brentq(g, 2.0, 3.0, xtol=1e-15)
    assert 0.0 <= float(ev.t_star) - r <= 1e-12 and g(float(ev.t_star)) <= 0.0


def test_the_minimum_search_runs_only_for_dip_candidates():
    # Guard 0 dips below zero between samples 1 and 2 (found at the first Newton point); guard 1,
    # 5 - x, has no candidate. Its search would halve [1, 2] to 1e-12 (~32 iterations); with the
    # empty bracket it does not run, and the loop over both stops after guard 0's one iteration.
    calls = []

    def values_at(x):
        jax.debug.callback(lambda: calls.append(1))
        return jnp.stack([(x - 1.5) ** 2 - 0.01, 5.0 - x])

    det = R.Detection(jnp.array([False, False]), jnp.array([0, 0]), jnp.array([True, False]),
                      jnp.array([1, 1]), jnp.array([1.5, 1.2]))
    br = jax.jit(lambda d: R.event_brackets(values_at, d, jnp.array([0.0, 1.0, 2.0]), 1e-12))(det)
    assert np.array_equal(br.has, [True, False]) and float(br.b[0]) == 1.5
    assert 1 <= len(calls) <= 2


def _first_event_of(*offsets, has=None):
    # Guards 1 + o - x, crossing at 1 + o, each bracketed by [0, 2].
    o = jnp.asarray(offsets)
    has = jnp.ones(o.shape, bool) if has is None else jnp.asarray(has)
    br = R.Brackets(has, jnp.zeros(o.shape), jnp.full(o.shape, 2.0))
    return R.first_event(lambda x: 1.0 + o - x, br, 1e-12, jnp.asarray(2.0))


def test_first_event_and_the_simultaneity_rule():
    ev = _first_event_of(0.3, 0.0, 0.5)
    assert int(ev.index) == 1 and not bool(ev.simultaneous)
    assert 0.0 <= float(ev.t_star) - 1.0 <= 1e-12
    # reached within the event-time tolerance: simultaneous, the first listed fires
    ev = _first_event_of(1e-14, 0.0, 0.5)
    assert int(ev.index) == 0 and bool(ev.simultaneous)
    # outside it: not simultaneous
    assert not bool(_first_event_of(1e-9, 0.0).simultaneous)
    # a guard without a bracket of its own that is <= 0 at t_min and was > 0 at the start of
    # the earliest bracket is simultaneous too
    ev = _first_event_of(0.0, 0.0, has=[False, True])
    assert int(ev.index) == 0 and bool(ev.simultaneous)
    # no event: the step's end
    ev = _first_event_of(0.0, has=[False])
    assert float(ev.t_star) == 2.0 and int(ev.index) == 0 and not bool(ev.simultaneous)


class _CountingLocator(BracketedNewton):
    """The default locator, counting its root searches as they run."""

    def root(self, f, a, b, tol):
        t = super().root(f, a, b, tol)
        jax.debug.callback(lambda _: _ROOT_SEARCHES.append(1), t)
        return t


_ROOT_SEARCHES: list = []


def test_first_event_searches_only_the_brackets_that_can_hold_it():
    # Guards 1 + o - x cross at 1 + o; brackets start at `a`. The earliest crossing is guard 1's
    # at 1; guard 2 crosses 1e-14 later (simultaneous, within the event tolerance), so guard 1
    # fires (listing order). Guard 3's bracket starts at 1.05 and guard 0's at 1.2, after the
    # earliest crossing: neither can be first or simultaneous, and neither is searched.
    o = jnp.asarray([0.3, 0.0, 1e-14, 0.05])
    br = R.Brackets(jnp.ones(4, bool), jnp.asarray([1.2, 0.9, 0.95, 1.05]), jnp.asarray([1.4, 1.1, 1.05, 1.1]))
    _ROOT_SEARCHES.clear()
    ev = R.first_event(lambda x: 1.0 + o - x, br, 1e-12, jnp.asarray(2.0), _CountingLocator())
    jax.effects_barrier()
    assert int(ev.index) == 1 and bool(ev.simultaneous)
    assert 0.0 <= float(ev.t_star) - 1.0 <= 1e-12
    assert len(_ROOT_SEARCHES) == 2


class _FreeFall(eqx.Module):
    """The ball's exact dense output from (h0, v0) at t0: h0 + v0 s - g s^2 / 2, s = t - t0."""

    t0: jax.Array
    h0: jax.Array
    v0: jax.Array
    t1: float = math.inf  # the step's end

    def evaluate(self, t):
        s = t - self.t0
        return jnp.stack([self.h0 + self.v0 * s - 0.5 * G * s * s, self.v0 - G * s])


def test_event_point_derivatives_by_the_implicit_function_theorem():
    # Dropped from h0 at t0: t* = t0 + sqrt(2 h0 / g), so dt*/dh0 = 1 / (g sqrt(2 h0 / g)) and
    # dt*/dt0 = 1 (an autonomous flow and guard: one-for-one).
    def t_event(h0, t0):
        fall = _FreeFall(t0, h0, jnp.asarray(0.0))
        t_star = jax.lax.stop_gradient(t0 + jnp.sqrt(2 * h0 / G))
        t_ev, y_before, grazing = R.event_point(
            BALL_KERN, EPS, jnp.asarray(0), jnp.asarray(0), t_star, fall, {"g": G, "e": 0.8}, TOL
        )
        return t_ev, (y_before, grazing)

    h0, t0 = jnp.asarray(1.0), jnp.asarray(0.5)
    (d_h0, d_t0), (y_before, grazing) = jax.grad(t_event, argnums=(0, 1), has_aux=True)(h0, t0)
    assert float(d_h0) == pytest.approx(1 / (G * math.sqrt(2 / G)), rel=1e-12)
    assert float(d_t0) == pytest.approx(1.0, rel=1e-12)
    np.testing.assert_allclose(y_before, [0.0, -math.sqrt(2 * G)], atol=1e-12)
    assert not bool(grazing)
    # at rest on the guard, the flow is tangent to it: grazing
    _, (_, grazing) = t_event(jnp.asarray(0.0), t0)
    assert bool(grazing)


def test_onto_the_guard_is_a_newton_step_only_where_the_state_is_outside():
    assert float(R.onto_the_guard(jnp.asarray(-1e-14), jnp.asarray(-3.0))) == 0.0
    assert float(R.onto_the_guard(jnp.asarray(2e-14), jnp.asarray(4.0))) == 0.0  # leaving: not a crossing
    assert float(R.onto_the_guard(jnp.asarray(3e-14), jnp.asarray(-2.0))) == 1.5e-14


def test_event_point_reports_a_state_in_the_guard_when_the_dense_output_rounds_outside():
    # The dense output read at the located time lies 1e-14 above the floor (its rounding, at the
    # scale of a long step's change): the reported state is moved along the flow onto the guard,
    # and the time with it, by 1e-14 / |v|.
    h0, t0 = jnp.asarray(1.0), jnp.asarray(0.5)
    t_star = t0 + jnp.sqrt(2 * h0 / G)
    v = math.sqrt(2 * G)
    above = _FreeFall(t0, h0 + 1e-14, jnp.asarray(0.0))
    t_ev, y_before, _ = R.event_point(BALL_KERN, EPS, jnp.asarray(0), jnp.asarray(0), t_star, above,
                                      {"g": G, "e": 0.8}, TOL)
    assert float(above.evaluate(t_star)[0]) > 0
    assert -1e-15 <= float(y_before[0]) <= 0.0
    np.testing.assert_allclose(float(t_ev - t_star), 1e-14 / v, atol=2 * EPS * float(t_star))  # ulps of t
    np.testing.assert_allclose(float(y_before[1]), -v, rtol=1e-12)


def test_event_point_at_the_end_of_a_step_without_an_event_keeps_the_state_and_time():
    # A held step whose dip stays positive reaches event_point with t* its end and g > 0
    # (the values are discarded there): no shift, and finite derivatives.
    h0, t0 = jnp.asarray(1.0), jnp.asarray(0.5)

    def at_end(h0):
        fall = _FreeFall(t0, h0, jnp.asarray(0.0), 0.6)
        t_ev, y, _ = R.event_point(BALL_KERN, EPS, jnp.asarray(0), jnp.asarray(0), jnp.asarray(0.6), fall,
                                   {"g": G, "e": 0.8}, TOL)
        return t_ev, y

    t_ev, y = at_end(h0)
    assert float(t_ev) == 0.6
    np.testing.assert_array_equal(y, _FreeFall(t0, h0, jnp.asarray(0.0)).evaluate(jnp.asarray(0.6)))
    assert np.all(np.isfinite(jax.jacfwd(lambda h: at_end(h)[1])(h0)))


def test_event_point_near_tangency_moves_the_time_no_further_than_the_event_tolerance():
    # The dense output rounds 1e-14 above the floor where the ball falls at 1e-7 (grazing): the
    # Newton step -g / gdot would move the time by 1e-7, far past the search's accuracy; it is
    # cut to the event-time tolerance, the state moved by tol F, the derivatives finite.
    t0, v0 = jnp.asarray(0.5), jnp.asarray(-1e-7)

    def near(h0):
        fall = _FreeFall(t0, h0, v0)
        return R.event_point(BALL_KERN, EPS, jnp.asarray(0), jnp.asarray(0), t0, fall, {"g": G, "e": 0.8}, TOL)

    t_ev, y_before, grazing = near(jnp.asarray(1e-14))
    assert bool(grazing)
    np.testing.assert_allclose(float(t_ev - t0), TOL, rtol=1e-6)
    np.testing.assert_allclose(y_before, [1e-14 + TOL * float(v0), float(v0) - TOL * G], rtol=1e-12, atol=1e-30)
    dt, dy = jax.jacfwd(lambda h: near(h)[:2])(jnp.asarray(1e-14))
    assert np.isfinite(float(dt)) and np.all(np.isfinite(dy))
    # the implicit function theorem at the shifted time: dt/dh0 = -1 / (v0 - g tol)
    np.testing.assert_allclose(float(dt), -1.0 / (float(v0) - G * TOL), rtol=1e-9)


# ---------------------------------------------------------------------------- the jump
def test_blocks_is_a_domain_component_first():
    assert bool(R.blocks(jnp.asarray(2), 2)) and not bool(R.blocks(jnp.asarray(1), 2))


def test_jump_outcome():
    ok = R.jump_outcome(jnp.asarray(2), 3, jnp.array([1.0, 2.0]), jnp.array(False), jnp.asarray(5), 16)
    assert bool(ok.recorded) and bool(ok.applied) and int(ok.zero_run) == 0
    assert not any(bool(p) for p, _ in ok.stops)
    full = R.jump_outcome(jnp.asarray(3), 3, jnp.array([1.0, 2.0]), jnp.array(False), jnp.asarray(0), 16)
    assert not bool(full.recorded) and not bool(full.applied)
    assert [s for p, s in full.stops if bool(p)] == [Status.MAX_EPOCHS]
    bad = R.jump_outcome(jnp.asarray(0), 3, jnp.array([1.0, np.nan]), jnp.array(False), jnp.asarray(0), 16)
    assert bool(bad.recorded) and not bool(bad.applied)
    assert [s for p, s in bad.stops if bool(p)] == [Status.NONFINITE]
    # the 17th zero-length epoch in a row with max_zero_epochs = 16
    chat = R.jump_outcome(jnp.asarray(0), 3, jnp.array([1.0, 2.0]), jnp.array(True), jnp.asarray(16), 16)
    assert int(chat.zero_run) == 17 and [s for p, s in chat.stops if bool(p)] == [Status.CHATTERING]
    # lanes last: finiteness over the leading (component) axis
    lanes = R.jump_outcome(
        jnp.array([0, 0]), 3, jnp.array([[1.0, 1.0], [2.0, np.inf]]), jnp.array(False), jnp.array([0, 0]), 16
    )
    np.testing.assert_array_equal(lanes.applied, [True, False])


def test_push_recent_and_saved_in_step():
    np.testing.assert_array_equal(
        R.push_recent(jnp.array([np.inf, 1.0, 2.0]), jnp.asarray(3.0)), [1.0, 2.0, 3.0]
    )
    np.testing.assert_array_equal(R.push_recent(jnp.zeros((2, 2)), jnp.ones(2)), [[0.0, 0.0], [1.0, 1.0]])
    # (t, t_end] = (1, 1.5]
    np.testing.assert_array_equal(
        R.saved_in_step(jnp.array([0.5, 1.0, 1.25, 1.5, 2.0]), 1.0, 1.5), [False, False, True, True, False]
    )


def test_detect_zeno_on_the_ball_window_and_on_a_batch_of_lanes_last():
    # A ball dropped from h0 at rest, restitution e: impacts at t_k = t_1 (1 + 2 (e + ... + e^(k-1))),
    # t_1 = sqrt(2 h0 / g), flights shrinking by e, accumulating at t_1 (1 + e) / (1 - e)
    # (`examples.zeno_time`); the post-impact states (0, e^k sqrt(2 g h0)) contract by e to (0, 0).
    g, opts = 9.8, ZenoOptions()
    R_ = opts.window + 2

    def window(h0, e, k):  # the last R_ impacts up to the k-th, and the last three states
        t1 = math.sqrt(2 * h0 / g)
        times = [t1 * (1 + 2 * sum(e**j for j in range(1, i))) for i in range(k - R_ + 1, k + 1)]
        states = [[0.0, e**i * math.sqrt(2 * g * h0)] for i in range(k - 2, k + 1)]
        return np.array(times), np.array(states)

    cases = [(1.0, 1 / math.sqrt(2), 8, 100.0), (0.5, 0.5, 6, 100.0), (2.0, 0.6, 7, 1.0), (1.0, 0.8, 9, 100.0)]
    T, X = zip(*(window(h0, e, k) for h0, e, k, _ in cases), strict=True)
    T, X = np.stack(T, -1), np.stack(X, -1)  # (R, N), (3, n, N): lanes last
    T[0, 3] = np.inf  # fewer events than the window: never Zeno
    t1 = np.array([c[3] for c in cases])
    is_zeno, t_inf, x_inf = R.detect_zeno(jnp.asarray(T), jnp.asarray(X), jnp.asarray(t1), opts)
    # the third lane's accumulation point lies after its t1
    np.testing.assert_array_equal(is_zeno, [True, True, False, False])
    for i in range(3):
        h0, e = cases[i][0], cases[i][1]
        np.testing.assert_allclose(t_inf[i], examples.zeno_time(h0, g, e), rtol=1e-12)
        np.testing.assert_allclose(x_inf[:, i], [0.0, 0.0], atol=1e-12)
    assert np.isinf(t_inf[3])
    # each lane alone, as the per-execution engine calls it: the same values
    for i in range(4):
        one = R.detect_zeno(jnp.asarray(T[:, i]), jnp.asarray(X[..., i]), jnp.asarray(t1[i]), opts)
        np.testing.assert_array_equal([one[0], one[1]], [is_zeno[i], t_inf[i]])
        np.testing.assert_array_equal(one[2], x_inf[:, i])


# ---------------------------------------------------------------------------- the step
def test_explicit_rk_step_of_heun_on_exponential_growth():
    # Heun on y' = y: k1 = h y0, k2 = h (y0 + k1), y1 = y0 + (k1 + k2) / 2 = y0 (1 + h + h^2 / 2);
    # error estimate (b - b_err) . k = (k1 - k2) / 2 up to sign = -h^2 y0 / 2.
    tab = UnrolledERK(diffrax.Heun())
    y0, h = jnp.array([2.0]), 0.1

    def field(t, y, scale):
        return y if scale is None else y * scale

    y1, ks, f_last = explicit_rk_step(tab, field, 0.0, y0, h, y0)
    np.testing.assert_allclose(y1, 2.0 * (1 + h + h * h / 2), rtol=1e-15)
    np.testing.assert_allclose(f_last, 2.0 * (1 + h), rtol=1e-15)  # F at the last stage
    np.testing.assert_allclose(jnp.abs(rk_error_estimate(tab, ks, y0)), h * h * 2.0 / 2, rtol=1e-13)


def test_scaled_error_and_the_step_size_rule():
    # err / (atol + rtol max|y|) = (3e-6 / 1e-6, 4e-6 / 2e-6) = (3, 2): e = sqrt((9 + 4) / 2)
    e = scaled_error(jnp.array([0.0, 1.0]), jnp.array([0.0, -1.0]), jnp.array([3e-6, 4e-6]), 1e-6, 1e-6)
    assert float(e) == pytest.approx(math.sqrt(6.5), rel=1e-14)
    # a NaN in y1 reads y0 in the scale; lanes last: one e per column
    e = scaled_error(
        jnp.ones((2, 2)), jnp.array([[np.nan, 1.0], [1.0, 1.0]]), jnp.full((2, 2), 2e-6), 0.0, 1e-6
    )
    np.testing.assert_allclose(e, [2.0, 2.0], rtol=1e-14)
    # The I controller (safety 0.9, factors in [0.2, 10]), q = 5: e = 1/32 gives 0.9 * 2 = 1.8
    # (kept); e = 32 gives 0.9 / 2 = 0.45 (rejected, in [0.2, 0.9]); the bounds clip the others.
    c = diffrax.PIDController(rtol=1e-6, atol=1e-6)
    one = jnp.ones(4)
    state = PIDState(one, one, jnp.zeros(4, bool))
    keep, h_next, same = pid_controller(jnp.array([1 / 32, 32.0, 1e-30, 1e30]), state, 5, 0.1 * one, c)
    np.testing.assert_array_equal(keep, [True, False, True, False])
    np.testing.assert_allclose(h_next, 0.1 * np.array([1.8, 0.45, 10.0, 0.2]), rtol=1e-14)
    assert same is state  # no history to keep
    # PI (p = 0.2, i = 0.5), q = 5, e = 1/32 after an accepted step with 1/e = 4:
    # 0.9 * 32^(0.7 / 5) * 4^(-0.2 / 5) = 0.9 * 2^0.62; with h = 0.1 and dtmax = 0.12: 0.12
    c = diffrax.PIDController(rtol=1e-6, atol=1e-6, pcoeff=0.2, icoeff=0.5)
    state = PIDState(jnp.asarray(4.0), jnp.asarray(1.0), jnp.asarray(False))
    keep, h_next, new = pid_controller(jnp.asarray(1 / 32), state, 5, jnp.asarray(0.1), c)
    assert bool(keep) and float(h_next) == pytest.approx(0.1 * 0.9 * 2**0.62, rel=1e-13)
    assert float(new.inv_error) == 32.0 and float(new.prev_inv_error) == 4.0
    c = diffrax.PIDController(rtol=1e-6, atol=1e-6, pcoeff=0.2, icoeff=0.5, dtmax=0.12, dtmin=0.2)
    _, h_next, new = pid_controller(jnp.asarray(1 / 32), state, 5, jnp.asarray(0.1), c)
    assert float(h_next) == 0.2 and bool(new.at_dtmin)  # dtmax, then dtmin over it
    # rejected (e = 32): the history moves back one step
    _, _, new = pid_controller(jnp.asarray(32.0), state, 5, jnp.asarray(0.1), c)
    assert float(new.inv_error) == 4.0 and float(new.prev_inv_error) == 1.0


def test_resolve_simultaneous_first_listed_fires():
    index, simultaneous = R.resolve_simultaneous(jnp.array([False, True, True]))
    assert int(index) == 1 and bool(simultaneous)
    index, simultaneous = R.resolve_simultaneous(jnp.array([False, True, False]))
    assert int(index) == 1 and not bool(simultaneous)
    # counting the first two only (the guards, at an epoch's start)
    index, simultaneous = R.resolve_simultaneous(jnp.array([True, False, True]), 2)
    assert int(index) == 0 and not bool(simultaneous)
    index, simultaneous = R.resolve_simultaneous(jnp.zeros((0,), bool))
    assert int(index) == 0 and not bool(simultaneous)
