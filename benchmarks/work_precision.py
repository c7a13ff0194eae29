"""Speed versus accuracy: work-precision diagrams, throughput, baselines and presets.

For problems A-D (`problems.py`), all measured in one run on this machine:

- work-precision: max final-state error over the batch (against the closed form, or the
  reference run) and wall time, per solver (Bosh3, Tsit5, Dopri5, Dopri8; Kvaerno3/5 for the
  stiff D) and tolerance (rtol = atol = 1e-3 ... 1e-12), in float64 and float32; executions
  whose number of events differs from the truth are counted apart ("wrong");
- event tolerance: problem A at rtol = 1e-9 for event_tol = 1e-4 ... 1e-12;
- hybridjax is `jax.jit(hj.simulate_batch)` (the batched engine, explicit and implicit
  solvers);
- baselines at Tsit5, rtol = atol = 1e-9: scipy `solve_ivp` (RK45 and DOP853) in a Python loop
  over epochs, a plain diffrax lock-step loop (`_baselines.py`: epochs in a bounded while loop,
  and in a `lax.while_loop`), and hybridjax's per-execution
  engine under `jax.vmap` (fast step and diffrax's step), reported as ratios;
- throughput against the batch size (A, 1 ... 100,000) and against the number of modes and
  guards (a ring of M modes);
- the accuracy presets (`hj.accuracy_preset`) on A, B, C.

Compile time is reported apart from run time (best of up to 5 runs after a compile run).

    python benchmarks/work_precision.py [--quick]   # tables; results/work_precision.json, .png
    python benchmarks/report.py                     # writes the docs' benchmark pages
"""

import argparse
import time
import warnings

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import problems as P
from _baselines import ball_bare_loop, diffrax_lockstep, scipy_loop
from _common import machine_info, write_json

import hybridjax as hj
from hybridjax import examples
from hybridjax._demo import one_device_per_core

one_device_per_core()  # hybridjax splits its batches over the cores, as the docs advise
jax.config.update("jax_enable_x64", True)
warnings.filterwarnings("ignore", message="rtol=")

SOLVERS = {"Bosh3": diffrax.Bosh3, "Tsit5": diffrax.Tsit5, "Dopri5": diffrax.Dopri5, "Dopri8": diffrax.Dopri8,
           "Kvaerno3": diffrax.Kvaerno3, "Kvaerno5": diffrax.Kvaerno5}
TOLS = {"Bosh3": [1e-3, 1e-5, 1e-7, 1e-8], "Tsit5": [1e-3, 1e-5, 1e-7, 1e-9, 1e-11, 1e-12],
        "Dopri5": [1e-3, 1e-5, 1e-7, 1e-9, 1e-11, 1e-12], "Dopri8": [1e-5, 1e-7, 1e-9, 1e-11, 1e-12],
        "Kvaerno3": [1e-3, 1e-5, 1e-7], "Kvaerno5": [1e-3, 1e-5, 1e-7, 1e-9]}
TOLS32 = [1e-2, 1e-3, 1e-4, 1e-5, 1e-6]

_RUNNERS = {}


def runner(problem, solver_name, dtype=jnp.float64, max_steps=20_000, engine="auto", devices=None):
    """jit(simulate_batch) with rtol = atol and event_tol traced: one compile per solver/dtype.

    engine: "auto" (`simulate_batch`: the batched engine), "vmap"
    (`jax.vmap(simulate)`), "diffrax" (`jax.vmap(simulate(..., engine="diffrax"))`).
    devices: `simulate_batch`'s (None: every device, one per core here)."""
    key = (problem.name, solver_name, jnp.dtype(dtype).name, engine, devices)
    if key not in _RUNNERS:
        solver = SOLVERS[solver_name]()

        @jax.jit
        def run(x0, mode0, tol, event_tol):
            kw = dict(solver=solver, stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
                      max_epochs=problem.max_epochs, max_steps=max_steps, event_tol=event_tol)
            if engine == "auto":
                return hj.simulate_batch(problem.system, x0, mode0, 0.0, problem.t1, problem.args,
                                         devices=devices, **kw)
            return jax.vmap(lambda x, m: hj.simulate(
                problem.system, x, m, 0.0, problem.t1, problem.args,
                engine="auto" if engine == "vmap" else engine, **kw))(x0, mode0)

        _RUNNERS[key] = run
    return _RUNNERS[key]


def timed_run(fn, *args, repeats=5, budget_s=3.0):
    """(compile time: the first call less the best run, best run time, output). The best of
    `repeats` runs after the first, fewer (at least 2) once they have taken `budget_s`: a best
    of 2 once read the ball at half its rate (a pause of this machine in both runs)."""
    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t
    best, spent = np.inf, 0.0
    for i in range(repeats):
        if i >= 2 and spent > budget_s:
            break
        t = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        dt = time.perf_counter() - t
        best, spent = min(best, dt), spent + dt
    return max(first - best, 0.0), best, out


def with_constants(fn):
    """`jax.jit(fn)`: the problem's parameters that `fn` closes over (g, e, t1, ...) are compiled
    in as constants, as `runner` compiles hybridjax's. Passed at each call, a Python float is a
    traced argument instead, and a program of a few operations can run several times slower for
    it (the ball's closed form, N = 10,000: 2.5 ms with g, e, t1 traced, 0.36 ms with them
    compiled in; `benchmarks/per_core.py`)."""
    return jax.jit(fn)


def errors(problem, truths, final_state, num_events):
    fs, ne = np.asarray(final_state, np.float64), np.asarray(num_events)
    ref_fs = np.stack([t["final_state"] for t in truths])
    ref_ne = np.array([t["num_events"] for t in truths])
    ok = ne == ref_ne
    err = float(np.max(np.abs(fs[ok] - ref_fs[ok]))) if ok.any() else float("nan")
    return err, int((~ok).sum())


def reference(problem, x0, m0):
    """Truths: closed form, or (B) a Dopri8 run at rtol = atol = 1e-13, checked against DOP853."""
    if problem.truth is not None:
        return [problem.truth(x, m) for x, m in zip(x0, m0, strict=True)]
    out = runner(problem, "Dopri8", max_steps=200_000)(jnp.asarray(x0), jnp.asarray(m0), 1e-13, 1e-14)
    truths = [dict(final_state=np.asarray(out.final_state[i]), num_events=int(out.num_events[i]))
              for i in range(len(x0))]
    check = []
    for i in range(3):
        n, y = scipy_loop(problem, x0[i], m0[i], method="DOP853", rtol=1e-13, atol=1e-13)
        check.append(dict(events_agree=n == truths[i]["num_events"],
                          max_diff=float(np.max(np.abs(y - truths[i]["final_state"])))))
    problem.reference_check = check
    return truths


def work_precision(problem, n, solvers, rng, float32=()):
    x0, m0 = problem.sample(rng, n)
    truths = reference(problem, x0, m0)
    rows = []
    for dtype, names in ((jnp.float64, solvers), (jnp.float32, float32)):
        for name in names:
            tols = TOLS[name] if dtype == jnp.float64 else TOLS32
            fn = runner(problem, name, dtype)
            xa, ma = jnp.asarray(x0, dtype), jnp.asarray(m0)
            compile_s = None
            for tol in tols:
                ev_tol = 1e-12 if dtype == jnp.float64 else 1e-6
                c, run_s, out = timed_run(fn, xa, ma, jnp.asarray(tol, dtype), jnp.asarray(ev_tol, dtype))
                compile_s = c if compile_s is None else compile_s
                err, wrong = errors(problem, truths, out.final_state, out.num_events)
                status = np.asarray(out.status_name)
                rows.append(dict(solver=name, dtype=jnp.dtype(dtype).name, tol=tol, run_s=run_s,
                                 exec_per_s=n / run_s, error=err, wrong=wrong, n=n,
                                 not_t1=int((status != "T1_REACHED").sum()),
                                 mean_steps=float(np.mean(np.asarray(out.num_steps))), compile_s=compile_s))
                print(f"  {problem.name[:2]} {name:>8} {jnp.dtype(dtype).name:>7} tol {tol:7.0e}: {run_s:7.3f} s"
                      f" {n / run_s:9.0f}/s  error {err:8.1e}  wrong {wrong:4d}  steps {rows[-1]['mean_steps']:7.1f}"
                      f"  compile {compile_s:5.1f} s", flush=True)
    return rows, truths, (x0, m0)


def baselines(problem, truths, x0, m0, n_scipy, n_lockstep, ours_per_s, ours_error=None):
    out = dict(ours_exec_per_s=ours_per_s, ours_error=ours_error, devices=len(jax.devices()))
    for method in ("RK45", "DOP853"):
        t = time.perf_counter()
        res = [scipy_loop(problem, x0[i], m0[i], method=method, rtol=1e-9, atol=1e-9) for i in range(n_scipy)]
        dt = time.perf_counter() - t
        ne = [r[0] for r in res]
        fs = np.stack([r[1] for r in res])
        err, wrong = errors(problem, truths[:n_scipy], fs, ne)
        out[f"scipy_{method}"] = dict(exec_per_s=n_scipy / dt, error=err, wrong=wrong, n=n_scipy,
                                      ratio=ours_per_s / (n_scipy / dt))
    xa, ma = jnp.asarray(x0[:n_lockstep]), jnp.asarray(m0[:n_lockstep])
    # The lock-step loop (epochs in a bounded loop), then its epochs in a
    # lax.while_loop (forward only).
    for key, loop in (("diffrax_lockstep", "bounded"), ("diffrax_lockstep_lax", "lax")):
        fn = diffrax_lockstep(problem.system, solver=diffrax.Tsit5(), t1=problem.t1,
                              max_epochs=problem.max_epochs, max_steps=20_000, loop=loop,
                              controller=diffrax.PIDController(rtol=1e-9, atol=1e-9))
        c, run_s, res = timed_run(with_constants(lambda x, m, fn=fn: fn(x, m, problem.args)), xa, ma)
        err, wrong = errors(problem, truths[:n_lockstep], res[2], res[1])
        out[key] = dict(exec_per_s=n_lockstep / run_s, error=err, wrong=wrong, n=n_lockstep,
                        compile_s=c, ratio=ours_per_s / (n_lockstep / run_s))
    # hybridjax on one device (one core), as the lock-step loop runs: the engine's own share.
    c, run_s, res = timed_run(runner(problem, "Tsit5", devices=1), xa, ma, 1e-9, 1e-12)
    err, wrong = errors(problem, truths[:n_lockstep], res.final_state, res.num_events)
    out["one_device"] = dict(exec_per_s=n_lockstep / run_s, error=err, wrong=wrong, n=n_lockstep, compile_s=c,
                             ratio=ours_per_s / (n_lockstep / run_s),
                             lockstep_ratio=(n_lockstep / run_s) / out["diffrax_lockstep"]["exec_per_s"])
    if problem.name.startswith("A"):
        cf = ball_closed_form_jax(problem.max_epochs)
        c, run_s, res = timed_run(with_constants(lambda x: cf(x, 9.8, 0.8, problem.t1)), xa)
        err, wrong = errors(problem, truths[:n_lockstep], res[1], res[0])
        out["closed_form_jax"] = dict(exec_per_s=n_lockstep / run_s, error=err, wrong=wrong, n=n_lockstep,
                                      compile_s=c, ratio=ours_per_s / (n_lockstep / run_s))
        # A bare hand-written loop for this one problem: how fast event-driven integration of this
        # one problem gets in JAX on this machine, with nothing general about it.
        bare = ball_bare_loop()
        c, run_s, res = timed_run(with_constants(lambda x: bare(x, 9.8, 0.8, problem.t1)), xa)
        err, wrong = errors(problem, truths[:n_lockstep], res[1], res[0])
        out["bare_loop"] = dict(exec_per_s=n_lockstep / run_s, error=err, wrong=wrong, n=n_lockstep,
                                compile_s=c, ratio=ours_per_s / (n_lockstep / run_s),
                                lockstep_ratio=(n_lockstep / run_s) / out["diffrax_lockstep"]["exec_per_s"])
    # hybridjax's per-execution engine under vmap (with its fast RK step, and with diffrax's own
    # solver.step / adapt_step_size)
    for key, engine in (("engine_vmap", "vmap"), ("engine_diffrax", "diffrax")):
        c, run_s, res = timed_run(runner(problem, "Tsit5", engine=engine), xa, ma, 1e-9, 1e-12)
        err, wrong = errors(problem, truths[:n_lockstep], res.final_state, res.num_events)
        out[key] = dict(exec_per_s=n_lockstep / run_s, error=err, wrong=wrong, n=n_lockstep,
                        compile_s=c, ratio=ours_per_s / (n_lockstep / run_s))
    return out


def ball_closed_form_jax(max_events: int):
    """The ball's closed form (`examples.bouncing_ball_closed_form`) jitted over a batch: the
    speed limit of problem A (no integration, no root finding)."""

    @jax.jit
    def run(x0, g, e, t1):
        h0, v0 = x0[:, 0], x0[:, 1]
        w = jnp.sqrt(v0 * v0 + 2 * g * h0)
        t = (v0 + w) / g
        t_last, v_last, h_last, count = jnp.zeros_like(t), v0, h0, jnp.zeros(t.shape, jnp.int32)
        for _ in range(max_events):
            hit = t <= t1
            t_last, v_last = jnp.where(hit, t, t_last), jnp.where(hit, e * w, v_last)
            h_last, count = jnp.where(hit, 0.0, h_last), count + hit
            w = jnp.where(hit, e * w, w)
            t = jnp.where(hit, t + 2 * w / g, t)
        dt = t1 - t_last
        return count, jnp.stack([h_last + v_last * dt - 0.5 * g * dt * dt, v_last - g * dt], 1)

    return run


def ring(M: int) -> hj.HybridSystem:
    """M modes in a ring: x' = 1 + i / M in mode i; at x >= 1, x -> 0 and on to mode i + 1."""
    modes = [hj.Mode(f"m{i}", lambda t, x, p, i=i: (1.0 + i / M) * jnp.ones_like(x), 1) for i in range(M)]
    trs = [hj.Transition(f"m{i}", f"m{(i + 1) % M}", guard=lambda t, x, p: 1.0 - x[0],
                         reset=lambda t, x, p: jnp.zeros_like(x)) for i in range(M)]
    return hj.HybridSystem(modes, trs)


def throughput(quick):
    prob = P.ball()
    rng = np.random.default_rng(1)
    sizes = [1, 10, 100, 1000, 10_000] + ([] if quick else [100_000])
    fn = runner(prob, "Tsit5")
    lock = diffrax_lockstep(prob.system, solver=diffrax.Tsit5(), t1=prob.t1, max_epochs=prob.max_epochs,
                            controller=diffrax.PIDController(rtol=1e-9, atol=1e-9))
    lock_run = with_constants(lambda x, m: lock(x, m, prob.args))
    rows = []
    for n in sizes:
        x0, m0 = prob.sample(rng, n)
        _, ours, _ = timed_run(fn, jnp.asarray(x0), jnp.asarray(m0), 1e-9, 1e-12)
        _, theirs, _ = timed_run(lock_run, jnp.asarray(x0), jnp.asarray(m0))
        rows.append(dict(n=n, ours_exec_per_s=n / ours, lockstep_exec_per_s=n / theirs))
        print(f"  batch {n:>6}: hybridjax {n / ours:9.0f}/s   diffrax lock-step {n / theirs:9.0f}/s", flush=True)
    modes = []
    for M in (1, 2, 4, 8, 16):
        sys = ring(M)
        n = 1000

        @jax.jit
        def run(x0, sys=sys):
            return hj.simulate_batch(sys, x0, 0, 0.0, 10.0, stepsize_controller=diffrax.PIDController(
                rtol=1e-9, atol=1e-9), max_epochs=32)

        x0 = jnp.asarray(np.random.default_rng(2).uniform(0, 0.5, (n, 1)))
        c, run_s, out = timed_run(run, x0)
        modes.append(dict(modes=M, guards=M, exec_per_s=n / run_s, compile_s=c,
                          mean_events=float(np.mean(np.asarray(out.num_events)))))
        print(f"  ring of {M:>2} modes: {n / run_s:9.0f}/s, compile {c:5.1f} s", flush=True)
    return dict(batch=rows, modes=modes)


def presets(probs, data):
    rows = []
    for prob in probs:
        x0, m0 = data[prob.name]["samples"]
        truths = data[prob.name]["truths"]
        for name in hj.PRESET_NAMES:
            kw = hj.accuracy_preset(name)
            solver = type(kw["solver"]).__name__
            fn = runner(prob, solver)
            tol = kw["stepsize_controller"].rtol
            _, run_s, out = timed_run(fn, jnp.asarray(x0), jnp.asarray(m0), tol, kw["event_tol"])
            err, wrong = errors(prob, truths, out.final_state, out.num_events)
            rows.append(dict(problem=prob.name, preset=name, solver=solver, tol=tol, exec_per_s=len(x0) / run_s,
                             error=err, wrong=wrong))
            print(f"  {prob.name[:2]} {name:>9}: {len(x0) / run_s:9.0f}/s error {err:8.1e} wrong {wrong}", flush=True)
    return rows


def event_tolerance(quick):
    prob = P.ball()
    x0, m0 = prob.sample(np.random.default_rng(3), 1000)
    truths = [prob.truth(x, m) for x, m in zip(x0, m0, strict=True)]
    fn = runner(prob, "Tsit5")
    rows = []
    for ev in (1e-4, 1e-6, 1e-8, 1e-10, 1e-12):
        _, run_s, out = timed_run(fn, jnp.asarray(x0), jnp.asarray(m0), 1e-9, ev)
        ref_t = [examples.bouncing_ball_closed_form(x[0], x[1], 9.8, 0.8, 2.5)["event_times"]
                 for x in x0]
        t_err = max(float(np.max(np.abs(np.asarray(out.event_times[i, : len(r)]) - r))) for i, r in enumerate(ref_t))
        err, wrong = errors(prob, truths, out.final_state, out.num_events)
        rows.append(dict(event_tol=ev, exec_per_s=1000 / run_s, event_time_error=t_err, error=err, wrong=wrong))
        print(f"  event_tol {ev:7.0e}: {1000 / run_s:9.0f}/s  event-time error {t_err:8.1e}  final error {err:8.1e}",
              flush=True)
    return rows


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    wp = results["work_precision"]
    from matplotlib.ticker import NullFormatter

    fig, axes = plt.subplots(2, 2, figsize=(10, 7.5))
    axes = axes.ravel()
    colors = dict(Bosh3="C0", Tsit5="C1", Dopri5="C2", Dopri8="C3", Kvaerno3="C4", Kvaerno5="C5")
    for ax, (name, block) in zip(axes, wp.items(), strict=True):
        for solver in dict.fromkeys(r["solver"] for r in block["rows"]):
            for dtype, style in (("float64", "-o"), ("float32", "--s")):
                rs = [r for r in block["rows"] if r["solver"] == solver and r["dtype"] == dtype and r["error"] == r["error"]]
                if rs:
                    ax.loglog([r["run_s"] / r["n"] * 1e6 for r in rs], [max(r["error"], 1e-16) for r in rs], style,
                              color=colors[solver], ms=3, label=f"{solver} {dtype[-2:]}")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("wall time per execution [us] (batched)")
        ax.set_ylabel("max final-state error")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path / "work_precision.png", dpi=110)
    plt.close(fig)

    tp = results["throughput"]["batch"]
    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.loglog([r["n"] for r in tp], [r["ours_exec_per_s"] for r in tp], "-o", label="hybridjax")
    ax.loglog([r["n"] for r in tp], [r["lockstep_exec_per_s"] for r in tp], "-s", label="diffrax lock-step loop")
    base = results["baselines"]["A: bouncing ball"]
    ax.axhline(base["scipy_RK45"]["exec_per_s"], color="gray", ls=":", label="scipy solve_ivp loop (RK45)")
    ax.set_xlabel("batch size")
    ax.set_ylabel("executions / s")
    ax.set_title("A: bouncing ball, Tsit5, 1e-9", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path / "throughput.png", dpi=110)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="smaller batches (a smoke run)")
    opts = ap.parse_args()
    scale = 0.1 if opts.quick else 1.0
    rng = np.random.default_rng(0)
    specs = [
        (P.ball(), 1000, ["Bosh3", "Tsit5", "Dopri5", "Dopri8"], ["Bosh3", "Tsit5"], 30, 10_000),
        (P.vdp_relay(), 200, ["Bosh3", "Tsit5", "Dopri5", "Dopri8"], ["Tsit5"], 4, 10_000),
        (P.thermostat(), 1000, ["Bosh3", "Tsit5", "Dopri5", "Dopri8"], ["Bosh3", "Tsit5"], 20, 1000),
        (P.stiff_relay(), 50, ["Kvaerno3", "Kvaerno5"], [], 0, 0),
    ]
    results = dict(machine=machine_info(), work_precision={}, baselines={})
    data = {}
    for prob, n, solvers, f32, n_scipy, n_lock in specs:
        n = max(int(n * scale), 10)
        print(f"{prob.name}: work-precision, N = {n}", flush=True)
        rows, truths, samples = work_precision(prob, n, solvers, rng, f32)
        results["work_precision"][prob.name] = dict(n=n, rows=rows,
                                                    reference_check=getattr(prob, "reference_check", None))
        data[prob.name] = dict(truths=truths, samples=samples)
        if n_scipy:
            ours = [r for r in rows if r["solver"] == "Tsit5" and r["dtype"] == "float64" and r["tol"] == 1e-9][0]
            n_lock = max(int(n_lock * scale), 10)
            if n_lock > n:  # more executions for the lock-step baseline: sample them with truths
                x0, m0 = prob.sample(np.random.default_rng(5), n_lock)
                tr = reference(prob, x0, m0)
            else:
                (x0, m0), tr = samples, truths
            ours_rate, ours_err = ours["exec_per_s"], ours["error"]
            if n_lock > n:
                _, run_s, res = timed_run(runner(prob, "Tsit5"), jnp.asarray(x0), jnp.asarray(m0), 1e-9, 1e-12)
                ours_rate, ours_err = n_lock / run_s, errors(prob, tr, res.final_state, res.num_events)[0]
            print(f"{prob.name}: baselines (Tsit5 / RK45 / DOP853 at 1e-9), N = {n_lock}", flush=True)
            b = baselines(prob, tr, x0, m0, max(int(n_scipy * scale), 2), n_lock, ours_rate, ours_err)
            if n_lock > n and prob.truth is None:  # the reference of these executions, checked too
                b["reference_check"] = prob.reference_check
            results["baselines"][prob.name] = b
            for key in ("scipy_RK45", "scipy_DOP853", "diffrax_lockstep", "diffrax_lockstep_lax", "one_device", "engine_vmap",
                        "engine_diffrax", "closed_form_jax", "bare_loop"):
                if key not in b:
                    continue
                print(f"  {key:>17}: {b[key]['exec_per_s']:9.1f}/s error {b[key]['error']:8.1e} wrong {b[key]['wrong']}"
                      f"  -> hybridjax is {b[key]['ratio']:.2f}x", flush=True)
    print("event tolerance (A, Tsit5, rtol = 1e-9)", flush=True)
    results["event_tolerance"] = event_tolerance(opts.quick)
    print("presets", flush=True)
    results["presets"] = presets([s[0] for s in specs[:3]], data)
    print("throughput", flush=True)
    results["throughput"] = throughput(opts.quick)
    path = write_json("work_precision", results)
    plot(results, path.parent)
    print(f"wrote {path} and {path.parent / 'work_precision.png'}, {path.parent / 'throughput.png'}")


if __name__ == "__main__":
    main()
