"""The bouncing ball against its closed form: single, batched, tiny epochs, defaults."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj

from helpers import BALL, BALL_ARGS, TIGHT, ball_reference, ball_runner


def test_impact_times_and_velocities_single():
    sol = ball_runner(3.0)(jnp.array([1.0, 0.0]), BALL_ARGS)
    ref = ball_reference(1.0, 0.0, 9.8, 0.8, 3.0)
    n = len(ref["event_times"])
    assert sol.status == hj.Status.T1_REACHED
    assert int(sol.num_events) == n
    np.testing.assert_allclose(sol.event_times[:n], ref["event_times"], rtol=0, atol=1e-8)
    np.testing.assert_allclose(sol.states_after[:n, 1], ref["post_velocities"], rtol=0, atol=1e-8)
    # pre-event states lie in the guard: h(t_i^-) <= 0 and within the tolerance of 0
    assert np.all(np.asarray(sol.states_before[:n, 0]) <= 0)
    assert np.all(np.asarray(sol.states_before[:n, 0]) > -1e-10)
    np.testing.assert_allclose(sol.final_state, ref["final_state"], atol=1e-8)
    assert np.all(np.isinf(np.asarray(sol.event_times[n:])))
    assert np.all(np.asarray(sol.transitions[:n]) == 0) and np.all(np.asarray(sol.transitions[n:]) == -1)


def test_batch_of_1000_random_initial_conditions():
    rng = np.random.default_rng(1)
    x0 = np.stack([rng.uniform(0.5, 1.5, 1000), rng.uniform(-1, 1, 1000)], axis=1)
    sol = jax.jit(jax.vmap(ball_runner(2.5).__wrapped__, in_axes=(0, None)))(jnp.asarray(x0), BALL_ARGS)
    refs = [ball_reference(h, v, 9.8, 0.8, 2.5) for h, v in x0]
    assert np.all(np.asarray(sol.status_code) == 0)
    np.testing.assert_array_equal(sol.num_events, [len(r["event_times"]) for r in refs])
    np.testing.assert_allclose(sol.final_state, np.stack([r["final_state"] for r in refs]), atol=1e-6)
    first = np.array([r["event_times"][0] for r in refs])
    np.testing.assert_allclose(sol.event_times[:, 0], first, atol=1e-8)


def test_lanes_far_out_of_phase_match_their_solo_runs_and_the_closed_form():
    # Under vmap an execution that needs the event phase waits for the others (at most
    # MAX_WAIT iterations); with heights over four orders of magnitude the lanes' events fall
    # at unrelated iterations, so they wait. Each lane's events must be those of its own run.
    h0 = np.array([0.002, 0.05, 1.0, 40.0])
    x0 = jnp.asarray(np.stack([h0, np.zeros_like(h0)], axis=1))
    solo = ball_runner(3.0)
    many = jax.jit(jax.vmap(solo.__wrapped__, in_axes=(0, None)))(x0, BALL_ARGS)
    for i, h in enumerate(h0):
        one = solo(x0[i], BALL_ARGS)
        n = int(one.num_events)
        assert int(many.num_events[i]) == n and int(many.status_code[i]) == int(one.status_code)
        np.testing.assert_allclose(many.event_times[i, :n], one.event_times[:n], rtol=0, atol=1e-12)
        # The batched and the single program are compiled apart and round differently: after
        # the bounces their final states agree to the accuracy of a run (problem A's largest
        # final-state error against the closed form is a few 1e-12: benchmarks/per_core.py).
        np.testing.assert_allclose(many.final_state[i], one.final_state, rtol=0, atol=5e-12)
        ref = ball_reference(h, 0.0, 9.8, 0.8, 3.0)
        m = min(n, len(ref["event_times"]))
        np.testing.assert_allclose(one.event_times[:m], ref["event_times"][:m], rtol=0, atol=1e-8)
    # the two low balls are Zeno before t1 (t_inf = 9 sqrt(2 h0 / g)); the others reach t1
    np.testing.assert_array_equal(np.asarray(many.status_code),
                                  [hj.STATUS_NAMES.index("ZENO")] * 2 + [0, 0])


def test_vmapped_restitution_coefficients():
    es = jnp.linspace(0.3, 0.9, 16)
    run = ball_runner(2.0).__wrapped__
    sol = jax.jit(jax.vmap(lambda e: run(jnp.array([1.0, 0.0]), {"g": 9.8, "e": e})))(es)
    for i, e in enumerate(np.asarray(es)):
        ref = ball_reference(1.0, 0.0, 9.8, e, 2.0)
        n = len(ref["event_times"])
        if n < 64:
            assert int(sol.num_events[i]) == n
            np.testing.assert_allclose(sol.event_times[i, :n], ref["event_times"], atol=1e-8)
            np.testing.assert_allclose(sol.final_state[i], ref["final_state"], atol=1e-7)


def test_epochs_of_a_microsecond_and_shorter_are_not_skipped():
    # Ball on the floor moving up at v0: flights of 2 v0 / g, 2 e v0 / g, ... The epochs are
    # far shorter than diffrax's default first step (0.01); none may be skipped.
    run = jax.jit(lambda v0, t1: hj.simulate(
        BALL, jnp.stack([0.0 * v0, v0]), "flight", 0.0, t1, {"g": 9.8, "e": 0.9},
        stepsize_controller=TIGHT, max_epochs=16))
    for flight in (1e-6, 1e-9):
        v0 = 9.8 * flight / 2
        t1 = 3.2 * flight  # impacts at 1, 1.9, 2.71 flights
        sol = run(jnp.asarray(v0), jnp.asarray(t1))
        ref = ball_reference(0.0, v0, 9.8, 0.9, t1)
        n = len(ref["event_times"])
        assert n == 3 and int(sol.num_events) == n
        np.testing.assert_allclose(sol.event_times[:n], ref["event_times"], rtol=1e-9)
        np.testing.assert_allclose(sol.states_after[:n, 1], ref["post_velocities"], rtol=1e-8)


def _long_then_short(short: float):
    """x' = -1 in both modes; "long" starts at x = 1 (an epoch of 1 s), its reset puts x at
    `short` in "short" (an epoch of `short` s), whose reset puts x back at 1 in "long"."""
    flow = lambda t, x, p: -jnp.ones_like(x)  # noqa: E731
    modes = [hj.Mode("long", flow, dim=1), hj.Mode("short", flow, dim=1)]
    trs = [hj.Transition("long", "short", guard=lambda t, x, p: x[0], reset=lambda t, x, p: jnp.full_like(x, short)),
           hj.Transition("short", "long", guard=lambda t, x, p: x[0], reset=lambda t, x, p: jnp.ones_like(x))]
    return hj.HybridSystem(modes, trs)


@pytest.mark.parametrize("short", [1e-6, 1e-9])
def test_a_short_epoch_after_a_long_one_is_not_skipped(short):
    # An epoch after the first starts with the step the controller proposed before the reset
    # (here, with a linear flow and no error, ~10x the last step of a 1 s epoch), not Hairer's
    # step: the short epoch that follows must still be found, in every engine. Closed form:
    # events at k + (k - 1) short and k + k short.
    system = _long_then_short(short)
    ref = np.array([t for k in (1, 2, 3) for t in (k + (k - 1) * short, k + k * short)])
    runs = {engine: hj.simulate(system, jnp.array([1.0]), "long", 0.0, 3.5, stepsize_controller=TIGHT,
                                engine=engine) for engine in ("fast", "diffrax")}
    runs["batch"] = hj.simulate_batch(system, jnp.array([[1.0]]), "long", 0.0, 3.5, stepsize_controller=TIGHT)[0]
    for engine, sol in runs.items():
        assert int(sol.num_events) == 6, engine
        np.testing.assert_allclose(sol.event_times[:6], ref, rtol=0, atol=1e-12, err_msg=engine)
        np.testing.assert_allclose(sol.final_state, [1.0 - (3.5 - ref[-1])], atol=1e-12, err_msg=engine)


def test_default_tolerances_give_event_times_to_1e8():
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, BALL_ARGS)
    ref = ball_reference(1.0, 0.0, 9.8, 0.8, 3.0)
    n = len(ref["event_times"])
    np.testing.assert_allclose(sol.event_times[:n], ref["event_times"], atol=1e-8)


def test_implicit_solver_runs_through_the_epoch_loop():
    ctrl = diffrax.PIDController(rtol=1e-8, atol=1e-8)
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 1.5, BALL_ARGS,
                      solver=diffrax.Kvaerno5(), stepsize_controller=ctrl)
    ref = ball_reference(1.0, 0.0, 9.8, 0.8, 1.5)
    n = len(ref["event_times"])
    assert int(sol.num_events) == n
    np.testing.assert_allclose(sol.event_times[:n], ref["event_times"], atol=1e-7)
