"""`simulate_batch` runs its own engine (`engine="batched"` refuses to fall back to
`jax.vmap(simulate)`) for what the per-execution engine does: Zeno completions, every option
of diffrax's `PIDController` (step_ts and jump_ts too), implicit solvers, and
`SaveAt(t0=True, t1=True)` with per-execution t0 / t1."""

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj
from hybridjax import examples

from helpers import BALL, TIGHT

REST = hj.Mode("rest", lambda t, x, p: jnp.zeros_like(x), dim=1)
COMPLETED = hj.HybridSystem(
    [BALL.modes[0], REST],
    BALL.transitions,
    completions=[hj.ZenoCompletion("flight", "rest", reset=lambda t, x, p: x[:1])],
)
X0 = jnp.array([[1.0, 0.0], [0.5, 0.0], [2.0, -1.0]])
E = jnp.array([1 / math.sqrt(2), 0.5, 0.6])
ARGS = {"g": jnp.full(3, 9.8), "e": E}


def test_zeno_completions_in_the_batched_engine():
    kw = dict(stepsize_controller=TIGHT, saveat=jnp.linspace(0.0, 4.0, 9), args_batched=True)
    # block=1: the events are located lane by lane, and the Zeno test and the completion run on
    # every lane after the last block
    got = hj.simulate_batch(COMPLETED, X0, "flight", 0.0, 4.0, ARGS, engine="batched", block=1, **kw)
    assert list(got.status_name) == ["T1_REACHED"] * 3
    K = COMPLETED.num_transitions
    for i in range(3):
        n = int(got.num_events[i])
        assert int(got.transitions[i, n - 1]) == K  # the completion, the last event
        assert COMPLETED.mode_names[int(got.final_mode[i])] == "rest"
        assert abs(float(got.final_state[i, 0])) < 1e-6
    # dropped from rest: t_inf = sqrt(2 h0 / g) (1 + e) / (1 - e)
    for i in (0, 1):
        want = examples.zeno_time(float(X0[i, 0]), 9.8, float(E[i]))
        np.testing.assert_allclose(got.zeno_time[i], want, atol=1e-6)
        np.testing.assert_allclose(got.event_times[i, int(got.num_events[i]) - 1], want, atol=1e-6)
    # the per-execution engine, a second method, on every field
    want = hj.simulate_batch(COMPLETED, X0, "flight", 0.0, 4.0, ARGS, engine="vmap", **kw)
    np.testing.assert_array_equal(got.num_events, want.num_events)
    np.testing.assert_array_equal(got.transitions, want.transitions)
    np.testing.assert_array_equal(got.epoch_modes, want.epoch_modes)
    np.testing.assert_array_equal(got.saved_modes, want.saved_modes)
    np.testing.assert_allclose(got.event_times, want.event_times, rtol=1e-10)
    np.testing.assert_allclose(got.ys, want.ys, rtol=1e-9, atol=1e-9)


def test_zeno_completion_without_room_in_the_record_stops_after_the_last_event():
    # Zeno is detected at the sixth impact (the completion is the seventh event with room), so
    # with max_epochs = 5 the completion finds the record full: like any event, it is neither
    # recorded nor applied, and the execution stops with MAX_EPOCHS at the state after the fifth
    # impact. Dropped from rest: t_5 = t_1 (1 + 2 (e + e^2 + e^3 + e^4)), t_1 = sqrt(2 h0 / g),
    # and the speed after it e^5 sqrt(2 g h0).
    kw = dict(stepsize_controller=TIGHT, args_batched=True, max_epochs=5)
    for engine in ("batched", "vmap"):
        got = hj.simulate_batch(COMPLETED, X0, "flight", 0.0, 4.0, ARGS, engine=engine, **kw)
        assert list(got.status_name) == ["MAX_EPOCHS"] * 3
        np.testing.assert_array_equal(got.num_events, [5, 5, 5])
        assert np.all(np.asarray(got.transitions) < COMPLETED.num_transitions)  # no completion recorded
        np.testing.assert_array_equal(got.final_mode, [0, 0, 0])
        np.testing.assert_allclose(got.final_state, got.states_after[:, -1], atol=1e-14)
        for i in (0, 1):
            h0, e = float(X0[i, 0]), float(E[i])
            t1 = math.sqrt(2 * h0 / 9.8)
            np.testing.assert_allclose(got.event_times[i, -1], t1 * (1 + 2 * sum(e**j for j in range(1, 5))),
                                       rtol=1e-9)
            np.testing.assert_allclose(got.final_state[i], [0.0, e**5 * math.sqrt(2 * 9.8 * h0)], atol=1e-8)


def test_zeno_completion_gradient_in_the_batched_engine():
    # d t_inf / d h0 = (1 + e) / (1 - e) / sqrt(2 g h0), for a ball dropped from rest
    def total(h0):
        x0 = jnp.stack([h0, jnp.zeros(3)], 1)
        return hj.simulate_batch(
            COMPLETED,
            x0,
            "flight",
            0.0,
            4.0,
            ARGS,
            engine="batched",
            stepsize_controller=TIGHT,
            args_batched=True,
        ).zeno_time.sum()

    h0 = jnp.array([1.0, 0.5, 2.0])
    g = jax.grad(total)(h0)
    want = (1 + E) / (1 - E) / jnp.sqrt(2 * 9.8 * h0)
    np.testing.assert_allclose(g, want, rtol=1e-6)


# Van der Pol with relay: the step size varies over orders of magnitude, so the controller's
# history, bounds and rejections all act.
@pytest.mark.parametrize(
    "controller",
    [
        diffrax.PIDController(rtol=1e-8, atol=1e-8, pcoeff=0.3, icoeff=0.4, dtmax=0.05),
        diffrax.PIDController(
            rtol=1e-6, atol=1e-6, pcoeff=0.2, icoeff=0.5, dcoeff=0.1, dtmin=1e-2, force_dtmin=True
        ),
    ],
    ids=["PI, dtmax", "PID, dtmin"],
)
def test_pid_options_in_the_batched_engine(controller):
    vdp = examples.van_der_pol_relay()
    x0 = jnp.array([[-1.0, 0.5], [0.2, -1.0], [-1.5, 1.5]])
    got, want = (
        hj.simulate_batch(vdp, x0, 0, 0.0, 10.0, 5.0, stepsize_controller=controller, engine=engine)
        for engine in ("batched", "vmap")
    )
    # The same rule as diffrax's own controller (in `jax.vmap(simulate)`): the same steps.
    np.testing.assert_array_equal(got.num_steps, want.num_steps)
    np.testing.assert_array_equal(got.num_rejected, want.num_rejected)
    assert int(np.min(got.num_rejected)) > 0
    np.testing.assert_array_equal(got.num_events, want.num_events)
    np.testing.assert_allclose(got.event_times, want.event_times, rtol=1e-11)
    np.testing.assert_allclose(got.final_state, want.final_state, rtol=1e-9, atol=1e-11)


def _ball_impact_times(h0, v0, g, e, count):
    """The ball's impact times, by hand: the first at (v0 + v1) / g with the impact speed
    v1 = sqrt(v0^2 + 2 g h0), then one flight of 2 e^k v1 / g after the k-th impact."""
    v1 = math.sqrt(v0 * v0 + 2 * g * h0)
    times = [(v0 + v1) / g]
    for k in range(1, count):
        times.append(times[-1] + 2 * e**k * v1 / g)
    return np.array(times)


def test_implicit_solver_in_the_batched_engine():
    # Kvaerno3's own step mapped over the lanes, its dense output (cubic Hermite) locating the
    # impacts; the step-size rule the shared one.
    kw = dict(
        solver=diffrax.Kvaerno3(),
        stepsize_controller=TIGHT,
        saveat=jnp.linspace(0.0, 1.2, 5),
        args_batched=True,
    )
    got = hj.simulate_batch(BALL, X0, "flight", 0.0, 1.2, ARGS, engine="batched", **kw)
    # the second ball accumulates its impacts at 0.96 (`examples.zeno_time`)
    assert list(got.status_name) == ["T1_REACHED", "ZENO", "T1_REACHED"]
    for i in range(3):
        n = int(got.num_events[i])
        assert n >= 1
        want = _ball_impact_times(float(X0[i, 0]), float(X0[i, 1]), 9.8, float(E[i]), n)
        # Kvaerno3 at rtol = atol = 1e-10 on a quadratic flight, its root finds at the same
        # tolerance: the impact times to 1e-8.
        np.testing.assert_allclose(got.event_times[i, :n], want, atol=1e-8)
    want = hj.simulate_batch(BALL, X0, "flight", 0.0, 1.2, ARGS, engine="vmap", **kw)
    np.testing.assert_array_equal(got.num_events, want.num_events)
    np.testing.assert_array_equal(got.num_steps, want.num_steps)
    np.testing.assert_array_equal(got.saved_modes, want.saved_modes)
    np.testing.assert_allclose(got.event_times, want.event_times, rtol=1e-10)
    np.testing.assert_allclose(got.ys, want.ys, rtol=1e-9, atol=1e-9)


def test_per_execution_t0_t1_saves_in_the_batched_engine():
    # SaveAt(t0=True, t1=True): each execution saves at its own t0 and t1.
    t0, t1 = jnp.array([0.0, 0.1, 0.2]), jnp.array([0.3, 0.7, 1.0])
    ts = np.array([0.25, 0.5])
    kw = dict(
        saveat=diffrax.SaveAt(t0=True, t1=True, ts=jnp.asarray(ts)),
        stepsize_controller=TIGHT,
        args_batched=True,
    )
    got = hj.simulate_batch(BALL, X0, "flight", t0, t1, ARGS, engine="batched", **kw)
    assert list(got.status_name) == ["T1_REACHED"] * 3
    for i in range(3):
        np.testing.assert_array_equal(got.ts[i], [t0[i], *ts, t1[i]])
        h0, v0, e = float(X0[i, 0]), float(X0[i, 1]), float(E[i])
        for k, s in enumerate([float(t0[i]), *ts, float(t1[i])]):
            if s > float(t1[i]):  # after the execution's end: not saved
                assert np.all(np.isinf(got.ys[i, k])) and int(got.saved_modes[i, k]) == -1
                continue
            # at or before t0 the initial state; after it the closed form from (t0, x0)
            want = examples.bouncing_ball_closed_form(h0, v0, 9.8, e, max(s - float(t0[i]), 0.0))
            np.testing.assert_allclose(got.ys[i, k], want["final_state"], atol=1e-8)
    want = hj.simulate_batch(BALL, X0, "flight", t0, t1, ARGS, engine="vmap", **kw)
    np.testing.assert_array_equal(got.ts, want.ts)
    np.testing.assert_array_equal(got.saved_modes, want.saved_modes)
    np.testing.assert_allclose(got.ys, want.ys, rtol=1e-9, atol=1e-9)


# dx/dt = (t - 0.3)_+ + [t >= 0.6]: a kink at 0.3 (a step time) and a jump of the field at 0.6
# (a jump time); x reaching 0.5 resets it to x - 1. Piecewise a polynomial of degree 1 in t,
# which Tsit5 integrates exactly on each step that does not straddle 0.3 or 0.6.
FORCED = hj.HybridSystem(
    [
        hj.Mode(
            "m",
            lambda t, x, p: (jnp.maximum(t - 0.3, 0.0) + jnp.where(t < 0.6, 0.0, 1.0)) * jnp.ones_like(x),
            dim=1,
        )
    ],
    [hj.Transition("m", "m", guard=lambda t, x, p: 0.5 - x[0], reset=lambda t, x, p: x - 1.0)],
)


def _forced(x0, t):
    return x0 + 0.5 * max(t - 0.3, 0.0) ** 2 + max(t - 0.6, 0.0)


def test_step_ts_and_jump_ts_in_the_batched_engine():
    x0 = np.array([0.0, 0.05, 0.1])
    ts = np.array([0.3, 0.6, 0.9, 1.2])
    # Loose tolerances: a step across 0.3 or 0.6 leaves an error of 1e-5 to 1e-3 here (without
    # step_ts / jump_ts, 6.6e-5 at the kink and 3.7e-3 at the jump in x(1)); steps that end at
    # 0.3, just before 0.6 and start just after it (the field evaluated anew), none.
    kw = dict(
        stepsize_controller=diffrax.PIDController(rtol=1e-4, atol=1e-4, step_ts=[0.3], jump_ts=[0.6]),
        saveat=jnp.asarray(ts),
    )
    got = hj.simulate_batch(FORCED, jnp.asarray(x0[:, None]), "m", 0.0, 1.2, engine="batched", **kw)
    assert list(got.status_name) == ["T1_REACHED"] * 3
    np.testing.assert_array_equal(got.num_events, [1, 1, 1])
    for i in range(3):
        # the event: (t* - 0.3)^2 / 2 + t* - 0.6 = 0.5 - x0 (t* > 0.6)
        t_star = 0.3 - 1 + math.sqrt(1 + 2 * (0.8 - x0[i]))
        np.testing.assert_allclose(got.event_times[i, 0], t_star, rtol=1e-12)
        saved = [_forced(x0[i], s) - (s > t_star) for s in ts]
        np.testing.assert_allclose(got.ys[i, :, 0], saved, atol=1e-12)
        np.testing.assert_allclose(got.final_state[i, 0], _forced(x0[i], 1.2) - 1, atol=1e-12)
    want = hj.simulate_batch(FORCED, jnp.asarray(x0[:, None]), "m", 0.0, 1.2, engine="vmap", **kw)
    np.testing.assert_array_equal(got.num_steps, want.num_steps)
    np.testing.assert_array_equal(got.num_rejected, want.num_rejected)
    np.testing.assert_allclose(got.event_times, want.event_times, rtol=1e-12)
    np.testing.assert_allclose(got.ys, want.ys, rtol=1e-9, atol=1e-12)


def test_implicit_solver_gradient_in_the_batched_engine():
    # d t_1 / d h0 = 1 / sqrt(2 g h0): the first impact of a ball dropped from rest, through
    # Kvaerno3's root finds mapped over the lanes
    def first_impacts(h0):
        x0 = jnp.stack([h0, jnp.zeros(3)], 1)
        sol = hj.simulate_batch(
            BALL,
            x0,
            "flight",
            0.0,
            0.5,
            ARGS,
            args_batched=True,
            solver=diffrax.Kvaerno3(),
            stepsize_controller=TIGHT,
            engine="batched",
        )
        return sol.event_times[:, 0].sum()

    h0 = jnp.array([1.0, 0.5, 0.8])
    np.testing.assert_allclose(jax.grad(first_impacts)(h0), 1 / np.sqrt(2 * 9.8 * h0), rtol=1e-7)


def test_auto_engine_is_the_batched_one_on_cpu_only():
    auto = hj.AutoEngine(batched=hj.BatchedEngine(lanes=4))
    assert auto.batch_engine("cpu", None) is auto.batched
    assert isinstance(auto.batch_engine("gpu", None), hj.VmapEngine)
    assert isinstance(auto.batch_engine("tpu", None), hj.VmapEngine)
    # where the batched engine refuses the solver, vmap on every platform
    assert isinstance(auto.batch_engine("cpu", "solver X is not ..."), hj.VmapEngine)
