"""Zeno detection and completion, blocking, chattering, and Monte Carlo of them."""

import json
import math
import os
import subprocess
import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj
from hybridjax import examples

from helpers import BALL, TIGHT, line_system


def test_chapter_ball_is_zeno_at_the_closed_form_time():
    e = 1 / math.sqrt(2)
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 5.0, {"g": 9.8, "e": e},
                      stepsize_controller=TIGHT)
    assert sol.status == hj.Status.ZENO
    t_inf = examples.zeno_time(1.0, 9.8, e)  # sqrt(2 h0 / g) (1 + e) / (1 - e) = 2.6330...
    assert abs(t_inf - 2.6330) < 1e-4
    np.testing.assert_allclose(sol.zeno_time, t_inf, atol=1e-6)
    np.testing.assert_allclose(sol.zeno_state, [0.0, 0.0], atol=1e-6)
    # stopped well before grinding: a handful of events, at the last one
    assert int(sol.num_events) <= 8
    assert float(sol.final_time) == float(sol.event_times[int(sol.num_events) - 1])


def test_vmapped_random_balls_zeno_times():
    rng = np.random.default_rng(3)
    e = rng.uniform(0.3, 0.85, 128)
    h = rng.uniform(0.5, 1.5, 128)
    run = jax.jit(jax.vmap(lambda h, e: hj.simulate(
        BALL, jnp.stack([h, 0.0 * h]), "flight", 0.0, 20.0, {"g": 9.8, "e": e},
        stepsize_controller=TIGHT, max_epochs=32)))
    sol = run(jnp.asarray(h), jnp.asarray(e))
    assert np.all(np.asarray(sol.status_code) == hj.STATUS_NAMES.index("ZENO"))
    expected = np.sqrt(2 * h / 9.8) * (1 + e) / (1 - e)
    np.testing.assert_allclose(sol.zeno_time, expected, atol=1e-5)


def test_no_zeno_when_the_accumulation_point_is_after_t1():
    # e = 0.8, h0 = 1: t_inf = 4.066 > 3
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, {"g": 9.8, "e": 0.8},
                      stepsize_controller=TIGHT)
    assert sol.status == hj.Status.T1_REACHED and np.isinf(float(sol.zeno_time))


def test_zeno_completion_brings_the_ball_to_rest():
    rest = hj.Mode("rest", lambda t, x, p: jnp.zeros_like(x), dim=1)
    sys_ = hj.HybridSystem([BALL.modes[0], rest], BALL.transitions,
                           completions=[hj.ZenoCompletion("flight", "rest", reset=lambda t, x, p: x[:1])])
    e = 1 / math.sqrt(2)
    sol = hj.simulate(sys_, jnp.array([1.0, 0.0]), "flight", 0.0, 4.0, {"g": 9.8, "e": e},
                      stepsize_controller=TIGHT)
    assert sol.status == hj.Status.T1_REACHED
    assert sys_.mode_names[int(sol.final_mode)] == "rest"
    assert abs(float(sol.final_state[0])) < 1e-6
    n = int(sol.num_events)
    assert int(sol.transitions[n - 1]) == sys_.num_transitions  # completion 0
    np.testing.assert_allclose(sol.event_times[n - 1], examples.zeno_time(1.0, 9.8, e), atol=1e-6)
    assert [ep.mode_name for ep in sol.hybrid_time_domain()][-1] == "rest"
    # dense output: the accumulating tail (last bounce to t_inf) is not re-integrated
    t_last_bounce = float(sol.event_times[n - 2])
    x_tail, m_tail = sol.evaluate(0.5 * (t_last_bounce + float(sol.zeno_time)))
    assert np.all(np.isinf(np.asarray(x_tail))) and int(m_tail) == -1
    x_rest, m_rest = sol.evaluate(3.5)
    assert int(m_rest) == 1 and abs(float(x_rest[0])) < 1e-6


def test_completion_definition_errors():
    rest = hj.Mode("rest", lambda t, x, p: jnp.zeros_like(x), dim=1)
    with pytest.raises(ValueError, match="identity reset needs equal dimensions"):
        hj.HybridSystem([BALL.modes[0], rest], BALL.transitions,
                        completions=[hj.ZenoCompletion("flight", "rest")])
    with pytest.raises(hj.DefinitionError, match=r"Completion 0 .*reset returned shape \(2,\); expected \(1,\)"):
        hj.HybridSystem([BALL.modes[0], rest], BALL.transitions,
                        completions=[hj.ZenoCompletion("flight", "rest", reset=lambda t, x, p: x)])


def test_domain_exit_without_a_guard_blocks_at_the_exit():
    sys_ = line_system(domain=lambda t, x, p: 1.0 - x[0])
    sol = hj.simulate(sys_, jnp.array([0.25]), "m", 0.0, 2.0, stepsize_controller=TIGHT)
    assert sol.status == hj.Status.BLOCKED
    np.testing.assert_allclose(sol.final_time, 0.75, atol=1e-8)
    np.testing.assert_allclose(sol.final_state, [1.0], atol=1e-8)


def test_domain_exit_covered_by_a_guard_transitions():
    sys_ = line_system(domain=lambda t, x, p: 1.0 - x[0], guard=lambda t, x, p: 1.0 - x[0])
    sol = hj.simulate(sys_, jnp.array([0.25]), "m", 0.0, 2.0, stepsize_controller=TIGHT)
    assert sol.status == hj.Status.T1_REACHED and int(sol.final_mode) == 1
    np.testing.assert_allclose(sol.event_times[0], 0.75, atol=1e-8)


def test_reset_outside_the_target_domain_blocks():
    a = hj.Mode("a", lambda t, x, p: jnp.ones_like(x), dim=1)
    b = hj.Mode("b", lambda t, x, p: jnp.zeros_like(x), dim=1, domain=lambda t, x, p: x[0])
    sys_ = hj.HybridSystem([a, b], [hj.Transition("a", "b", guard=lambda t, x, p: 0.5 - x[0],
                                                  reset=lambda t, x, p: x - 1.0)])
    sol = hj.simulate(sys_, jnp.array([0.0]), "a", 0.0, 2.0, stepsize_controller=TIGHT)
    assert sol.status == hj.Status.BLOCKED and int(sol.num_events) == 1
    np.testing.assert_allclose(sol.final_time, 0.5, atol=1e-8)
    np.testing.assert_allclose(sol.final_state, [-0.5], atol=1e-8)
    assert int(sol.final_mode) == 1


def test_initial_state_outside_the_domain_blocks_at_t0():
    sys_ = line_system(domain=lambda t, x, p: 1.0 - x[0])
    sol = hj.simulate(sys_, jnp.array([1.5]), "m", 0.0, 2.0)
    assert sol.status == hj.Status.BLOCKED and float(sol.final_time) == 0.0


def test_wilson_interval_published_value():
    # Wilson (1927) 95% interval for 5 successes in 10 trials: (0.2366, 0.7634)
    lo, hi = hj.wilson_interval(5, 10)
    np.testing.assert_allclose([lo, hi], [0.2366, 0.7634], atol=1e-4)


def _mc_inputs(n=96):
    rng = np.random.default_rng(7)
    h = rng.uniform(0.5, 1.5, n)
    e = rng.uniform(0.3, 0.9, n)
    return np.stack([h, 0 * h], 1), {"g": np.full(n, 9.8), "e": e}


def test_monte_carlo_matches_closed_form_and_direct_vmap():
    x0, args = _mc_inputs()
    res = hj.monte_carlo(BALL, x0=x0, args=args, mode0="flight", t1=4.0, chunk_size=40,
                         progress=False, max_epochs=32)
    assert res.n == 96 and res.chunks == 3
    t_inf = np.sqrt(2 * x0[:, 0] / 9.8) * (1 + args["e"]) / (1 - args["e"])
    zeno = res.per_execution["status"] == hj.Status.ZENO
    np.testing.assert_array_equal(zeno, res.per_execution["status"] == hj.STATUS_NAMES.index("ZENO"))
    clear = np.abs(t_inf - 4.0) > 0.2  # away from the horizon, Zeno iff t_inf <= t1
    np.testing.assert_array_equal(zeno[clear], (t_inf <= 4.0)[clear])
    np.testing.assert_allclose(res.per_execution["zeno_time"][zeno], t_inf[zeno], atol=1e-6)
    k = res.status_counts["ZENO"]
    frac, (lo, hi) = res.status_fractions["ZENO"]
    assert frac == k / 96 and (lo, hi) == hj.wilson_interval(k, 96)
    assert res.num_events["n"] == 96 and int(np.sum(res.event_histogram)) == 96
    # Another horizon is another program (t1 is a constant of it), not the one kept above.
    res2 = hj.monte_carlo(BALL, x0=x0, args=args, mode0="flight", t1=2.0, chunk_size=40,
                          progress=False, max_epochs=32)
    zeno2 = res2.per_execution["status"] == hj.STATUS_NAMES.index("ZENO")
    clear2 = np.abs(t_inf - 2.0) > 0.2
    assert res2.compile_s > 0 and 0 < np.sum(zeno2[clear2]) < np.sum(zeno[clear])
    np.testing.assert_array_equal(zeno2[clear2], (t_inf <= 2.0)[clear2])


_SHARDED = r"""
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
sys.path[:0] = [sys.argv[1], sys.argv[2]]
import hybridjax as hj
from test_zeno_blocking import _mc_inputs
x0, args = _mc_inputs()
res = hj.monte_carlo(hj.examples.bouncing_ball(), x0=x0, args=args, mode0="flight", t1=4.0,
                     chunk_size=40, progress=False, max_epochs=32)
print(json.dumps(dict(devices=res.devices, **{k: v.tolist() for k, v in res.per_execution.items()})))
"""


def test_monte_carlo_sharded_over_four_host_devices_matches_one_device():
    x0, args = _mc_inputs()
    one = hj.monte_carlo(BALL, x0=x0, args=args, mode0="flight", t1=4.0, chunk_size=40,
                         progress=False, max_epochs=32)
    # The suite's compiler settings (conftest.py) plus four devices.
    flags = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
    env = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu")
    here = os.path.dirname(__file__)
    out = subprocess.run([sys.executable, "-c", _SHARDED, here, os.path.dirname(here)], capture_output=True, text=True,
                         env=env, cwd=here, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    four = json.loads(out.stdout.strip().splitlines()[-1])
    assert four["devices"] == 4
    # Not bit for bit: each device runs a quarter of the chunk, compiled for that shape, and
    # some lanes round differently; every epoch after the first starts with the step proposed
    # before it, so that rounding carries through the bounces (~3e-12 in final velocities).
    for k, v in one.per_execution.items():
        np.testing.assert_allclose(np.asarray(four[k]), v, rtol=1e-10, atol=1e-11, err_msg=k)


def test_chunked_arrays_and_sampler_paths_agree():
    x0, args = _mc_inputs(48)

    def sampler(key, m):
        # ignores the key: returns the same fixed rows as the arrays path
        return jnp.asarray(x0[:m]), jax.tree_util.tree_map(lambda v: jnp.asarray(v[:m]), args)

    a = hj.monte_carlo(BALL, x0=x0, args=args, mode0="flight", t1=4.0, chunk_size=48,
                       progress=False, max_epochs=32)
    b = hj.monte_carlo(BALL, sampler, 48, mode0="flight", t1=4.0, chunk_size=48,
                       progress=False, max_epochs=32, keep="summary")
    assert b.per_execution is None and a.status_counts == b.status_counts
    # Same configuration and chunk shapes: b ran the program a compiled.
    assert a.compile_s > 0 and b.compile_s == 0
    assert a.zeno_time["mean"] == pytest.approx(b.zeno_time["mean"], rel=1e-12)
    with pytest.raises(ValueError, match="either a sampler"):
        hj.monte_carlo(BALL, t1=1.0)
    assert diffrax is not None


def test_monte_carlo_takes_a_simulator_and_num_samples():
    x0, args = _mc_inputs(48)

    def sampler(key, m):
        return jnp.asarray(x0[:m]), jax.tree_util.tree_map(lambda v: jnp.asarray(v[:m]), args)

    run = dict(mode0="flight", t1=4.0, chunk_size=48, progress=False)
    a = hj.monte_carlo(BALL, sampler, num_samples=48, simulator=hj.Simulator(max_epochs=32), **run)
    b = hj.monte_carlo(BALL, sampler, 48, max_epochs=32, **run)  # n positional, a shorthand
    c = hj.monte_carlo(BALL, sampler, n=48, max_epochs=32, devices=1, **run)
    # The same simulator: one compiled program for the three runs.
    assert b.compile_s == 0 and c.compile_s == 0 and a.n == b.n == c.n == 48
    for k, v in a.per_execution.items():
        np.testing.assert_array_equal(b.per_execution[k], v, err_msg=k)
        np.testing.assert_array_equal(c.per_execution[k], v, err_msg=k)
    # Zeno time of the ball from rest at h: sqrt(2 h / g) (1 + e) / (1 - e)
    t_inf = np.sqrt(2 * x0[:, 0] / 9.8) * (1 + args["e"]) / (1 - args["e"])
    zeno = a.per_execution["status"] == hj.Status.ZENO
    assert zeno.any()
    np.testing.assert_allclose(a.per_execution["zeno_time"][zeno], t_inf[zeno], atol=1e-6)
    with pytest.raises(ValueError, match="num_samples and n are the same option"):
        hj.monte_carlo(BALL, sampler, 48, n=48, **run)
    with pytest.raises(ValueError, match="simulator and devices are the same option"):
        hj.monte_carlo(BALL, sampler, 48, simulator=hj.Simulator(), devices=1, **run)
    with pytest.raises(ValueError, match="pass max_epochs there"):
        hj.monte_carlo(BALL, sampler, 48, simulator=hj.Simulator(), max_epochs=32, **run)
    with pytest.raises(TypeError, match="unexpected keyword argument 'samples'"):
        hj.monte_carlo(BALL, sampler, samples=48, **run)


def test_progress_estimate_counts_run_time_only():
    from hybridjax._analysis.montecarlo import _Progress, _progress_line

    # 200 of 1000 executions ran in 0.8 s after the compile: 800 more at 4 ms each is 3.2 s.
    line = _progress_line(200, 1000, 0.8)
    assert " 20.0% 200/1000" in line and "0.8 s run" in line and "3.2 s left" in line
    assert "nan s left" in _progress_line(0, 1000, 0.0) and "0.0 s left" in _progress_line(5, 5, 1.0)

    # A fake clock: 3.4 s of compile, then two chunks of 0.5 s each for 250 executions.
    import io
    ticks = iter([0.0, 3.4, 3.9, 4.4])
    out = io.StringIO()
    bar = _Progress(1000, True, stream=out, clock=lambda: next(ticks))
    bar.compiling()
    bar.compiled(3.4)  # the run clock starts here, at 3.4
    bar.update(250)  # 0.5 s for 250: 750 left at 2 ms is 1.5 s
    bar.update(500)  # 1.0 s for 500: 1.0 s left
    text = out.getvalue()
    assert text.count("compiled in 3.40 s") == 1
    assert "0.5 s run,    1.5 s left" in text and "1.0 s run,    1.0 s left" in text
    silent = io.StringIO()
    quiet = _Progress(10, False, stream=silent)
    quiet.compiled(1.0)
    quiet.update(10)
    assert silent.getvalue() == ""


def test_monte_carlo_progress_reports_the_compile_apart(capsys):
    x0, args = _mc_inputs(48)
    hj.monte_carlo(BALL, x0=x0, args=args, mode0="flight", t1=4.0, chunk_size=48, progress=True,
                   max_epochs=32)
    err = capsys.readouterr().err
    lines = err.split("\n")
    assert sum(("compiled in" in ln) or ("reused a compiled program" in ln) for ln in lines) == 1
    assert "48/48" in lines[-2] and "s left" in lines[-2] and "compiled" not in lines[-2]


def test_truncation_example_settles_after_finitely_many_bounces():
    p = {"g": 9.8, "e": 1 / math.sqrt(2), "v_min": 0.05}
    sys_ = examples.truncated_ball()
    sol = hj.simulate(sys_, jnp.array([1.0, 0.0]), "flight", 0.0, 4.0, p, stepsize_controller=TIGHT,
                      zeno=False)
    ref = examples.truncated_ball_closed_form(1.0, 9.8, p["e"], p["v_min"])
    n = len(ref["bounce_times"])
    assert sol.status == hj.Status.T1_REACHED and sys_.mode_names[int(sol.final_mode)] == "rest"
    assert int(sol.num_events) == n + 1
    np.testing.assert_allclose(sol.event_times[:n], ref["bounce_times"], atol=1e-8)
    np.testing.assert_allclose(sol.event_times[n], ref["settle_time"], atol=1e-8)
    assert int(sol.transitions[n]) == 0  # "settle"


@pytest.mark.parametrize("engine", ["simulate", "batched"])
def test_zeno_tail_without_detection_ends_chattering_at_the_accumulation_time(engine):
    # The chapter's ball with Zeno detection off: the bounces shrink geometrically below the
    # resolution of t. Each bounce's departure then turns back within the event-time tolerance
    # and fires at once (`unresolved_departure`), so the run ends CHATTERING at t_inf on the
    # floor, never below it with its guard unseen.
    e = 1 / math.sqrt(2)
    kw = dict(zeno=False, max_epochs=1000)
    if engine == "simulate":
        sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, {"g": 9.8, "e": e}, **kw)
        status, t_end, x_end = sol.status_code, sol.final_time, sol.final_state
        times = np.asarray(sol.event_times)[: int(sol.num_events)]
    else:
        sol = hj.simulate_batch(BALL, jnp.array([[1.0, 0.0]]), "flight", 0.0, 3.0, {"g": 9.8, "e": e},
                                engine="batched", **kw)
        status, t_end, x_end = sol.status_code[0], sol.final_time[0], sol.final_state[0]
        times = np.asarray(sol.event_times[0])[: int(sol.num_events[0])]
    t_inf = examples.zeno_time(1.0, 9.8, e)
    assert int(status) == hj.STATUS_NAMES.index("CHATTERING")
    assert float(x_end[0]) >= -1e-12  # on the floor, not inside its guard
    np.testing.assert_allclose(float(t_end), t_inf, atol=1e-9)
    assert len(times) > 50 and np.all(times <= t_inf + 1e-9)
    # the first bounces at the closed form's times, t_k = t_inf - sqrt(2 h0 / g) 2 e^k / (1 - e), k >= 1
    k = np.arange(1, 6)
    np.testing.assert_allclose(times[:5], t_inf - math.sqrt(2 / 9.8) * 2 * e**k / (1 - e), atol=1e-9)
