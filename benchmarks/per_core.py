"""Problem A on one core and on every core, each way of computing it, in one process.

The benchmarks' ratios compare hybridjax with what a user would write. The ratios depend on how many
cores each side may use: hybridjax splits its batch over the cores (`simulate_batch`'s
`devices`), the baselines as written run on one. This script runs every way on one core
*and* split over every core (one CPU device per core: hybridjax by its own `devices`, the
others by hand, an equal part of the executions put on each device and the same jitted
function called there, the parts running at once), in alternating rounds, and reports each rate and
the ratios between them:

- the plain diffrax lock-step loop (`_baselines.diffrax_lockstep`, epochs in a bounded loop);
- a bare hand-written loop for the ball alone (`_baselines.ball_bare_loop`);
- the closed form, jitted (`work_precision.ball_closed_form_jax`): no integration at all;
- hybridjax (`jax.jit(hj.simulate_batch)`, `devices=1` and every device), and
  `jax.jit(jax.vmap(hj.simulate))` on one core (what `simulate_batch` runs on a GPU);
- on one core, `hj.simulate_batch` and `jax.vmap(hj.simulate)` (`engine="vmap"`) called
  directly (outside `jax.jit`: the program the call compiles itself, with
  `hybridjax._solve.eager.BATCH_CPU`), and the lock-step loop compiled with the same XLA options
  (`jax.jit(..., compiler_options=...)`).

Tsit5, rtol = atol = 1e-9, float64, the ball of problem A (h0 ~ U(0.5, 1.5), v0 ~ U(-1, 1),
e = 0.8, T = 2.5), N executions; each rate is the best of `--rounds` runs, errors against the
closed form (numpy, `examples.bouncing_ball_closed_form`) for every execution.

Problems B (Van der Pol relay) and C (thermostat) follow on one core: the lock-step loop,
hybridjax's batched engine and `jax.vmap(hj.simulate)`, `--n-other` executions each, errors
against `work_precision.reference` (C's closed form; for B a Dopri8 run at 1e-13).

"One core" is one JAX CPU device: XLA may still run a device's work on its pool of threads, one per
core of the process. So problem A is also run, the lock-step loop, hybridjax and `jax.vmap(hj.simulate)`,
in a child process allowed a single core (`os.sched_setaffinity` before JAX starts: one device, all
its threads on that core), in alternating rounds of its own.

    python benchmarks/per_core.py [--n 10000] [--n-other 2000] [--rounds 7]   # results/per_core.json
"""

import os
import sys

PINNED = "--pinned"  # the child process on a single core (`pinned`)
if PINNED in sys.argv:  # before JAX sizes its thread pool by the cores this process may use
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import problems as P  # noqa: E402
from _baselines import ball_bare_loop, diffrax_lockstep  # noqa: E402
from _common import machine_info, write_json  # noqa: E402
from work_precision import (  # noqa: E402  (also: one device per core, x64)
    ball_closed_form_jax,
    errors,
    reference,
    runner,
    with_constants,
)

import hybridjax as hj  # noqa: E402
from hybridjax._solve.eager import BATCH_CPU  # noqa: E402

G, E = 9.8, 0.8


def split(fn):
    """`fn` (x0, mode0 with executions first -> a pytree of arrays, executions first) on equal
    parts of the executions, one part per device, as a user splits by hand: each part put on its
    device and the jitted `fn` called there (JAX dispatches asynchronously, so the parts run at
    once); returns the parts' outputs, a list. (`jax.shard_map` would be one program, but the
    diffrax loop fails inside it: equinox's closure conversion, patrick-kidger/equinox#1261.)"""
    jfn, devs = with_constants(fn), jax.devices()

    def run(x, m):
        xs, ms = np.array_split(np.asarray(x), len(devs)), np.array_split(np.asarray(m), len(devs))
        return [jfn(jax.device_put(a, d), jax.device_put(b, d)) for a, b, d in zip(xs, ms, devs, strict=True)]

    return run


def joined(read):
    """`read` for the output of `split`: the parts' (num_events, final_state) joined."""
    def out(parts):
        pieces = [read(p) for p in parts]
        return tuple(np.concatenate([np.asarray(q[i]) for q in pieces]) for i in range(2))
    return out


def lockstep(prob):
    """The lock-step loop for `prob` (Tsit5, 1e-9), as `fn(x0, mode0, args)`."""
    return diffrax_lockstep(prob.system, solver=diffrax.Tsit5(), t1=prob.t1, max_epochs=prob.max_epochs,
                            max_steps=20_000, controller=diffrax.PIDController(rtol=1e-9, atol=1e-9))


def direct_call(prob, devices, engine=None):
    """`hj.simulate_batch` called directly (Tsit5, 1e-9, as `runner`), as `fn(x0, mode0)`; with
    `engine="vmap"`, `jax.vmap(hj.simulate)` called directly."""
    kw = dict(solver=diffrax.Tsit5(), stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-9),
              max_epochs=prob.max_epochs, max_steps=20_000, event_tol=1e-12)
    if engine is not None:
        kw["engine"] = engine
    return lambda x, m: hj.simulate_batch(prob.system, x, m, 0.0, prob.t1, prob.args, devices=devices, **kw)


def with_direct_options(fn):
    """`jax.jit(fn)` compiled with the XLA options of a direct batch call (`BATCH_CPU`)."""
    return jax.jit(fn, compiler_options=BATCH_CPU)


def read_solution(r):
    """(num_events, final_state) of a hybridjax `Solution`."""
    return r.num_events, r.final_state


def ways(prob):
    """{name: (fn of (x0, mode0), reads (num_events, final_state) off its output)}."""
    t1 = prob.t1
    lock = lockstep(prob)
    bare = ball_bare_loop()
    closed = ball_closed_form_jax(prob.max_epochs)
    out = {}
    for cores in ("one core", "every core"):
        wrap = with_constants if cores == "one core" else split
        rd = (lambda r: r) if cores == "one core" else joined
        out[f"diffrax lock-step loop, {cores}"] = (wrap(lambda x, m: lock(x, m, prob.args)),
                                                   rd(lambda r: (r[1], r[2])))
        out[f"bare hand-written loop, {cores}"] = (wrap(lambda x, m: bare(x, G, E, t1)), rd(lambda r: r))
        out[f"closed form, {cores}"] = (wrap(lambda x, m: closed(x, G, E, t1)), rd(lambda r: r))
        fn = runner(prob, "Tsit5", devices=1 if cores == "one core" else None)
        out[f"hybridjax, {cores}"] = (lambda x, m, fn=fn: fn(x, m, 1e-9, 1e-12), read_solution)
        if cores == "one core":
            out["hybridjax, direct call, one core"] = (direct_call(prob, 1), read_solution)
            out["diffrax lock-step loop, direct call's options, one core"] = (
                with_direct_options(lambda x, m: lock(x, m, prob.args)), lambda r: (r[1], r[2]))
            # the path simulate_batch takes on a GPU, jitted and called directly
            fn = with_constants(lambda x, m, fn=runner(prob, "Tsit5", engine="vmap"): fn(x, m, 1e-9, 1e-12))
            out["hybridjax vmap(simulate), one core"] = (fn, read_solution)
            out["hybridjax vmap(simulate), direct call, one core"] = (direct_call(prob, 1, "vmap"), read_solution)
    return out


def one_core_ways(prob):
    """Problems B and C on one core: {name: (fn of (x0, mode0), reads (num_events, final_state))}."""
    lock = lockstep(prob)
    batched, vmapped = runner(prob, "Tsit5", devices=1), runner(prob, "Tsit5", engine="vmap")
    return {
        "diffrax lock-step loop": (with_constants(lambda x, m: lock(x, m, prob.args)), lambda r: (r[1], r[2])),
        "diffrax lock-step loop, direct call's options": (with_direct_options(lambda x, m: lock(x, m, prob.args)),
                                                          lambda r: (r[1], r[2])),
        "hybridjax": (lambda x, m: batched(x, m, 1e-9, 1e-12), read_solution),
        "hybridjax, direct call": (direct_call(prob, 1), read_solution),
        "hybridjax vmap(simulate)": (with_constants(lambda x, m: vmapped(x, m, 1e-9, 1e-12)), read_solution),
        "hybridjax vmap(simulate), direct call": (direct_call(prob, 1, "vmap"), read_solution),
    }


def timed(fns, truths, prob, xa, ma, rounds):
    """{name: row}: each way's first call (compile and run), error, wrong event counts and the
    times of `rounds` alternating runs."""
    rows = {}
    for name, (fn, read) in fns.items():
        t = time.perf_counter()
        res = jax.block_until_ready(fn(xa, ma))
        ne, fs = read(res)
        err, wrong = errors(prob, truths, fs, ne)
        rows[name] = dict(first_call_s=time.perf_counter() - t, error=err, wrong=wrong, runs_s=[])
    for _ in range(rounds):  # alternating, so that the machine's drift touches every way alike
        for name, (fn, _) in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(fn(xa, ma))
            rows[name]["runs_s"].append(time.perf_counter() - t)
    n = xa.shape[0]
    for r in rows.values():
        r["exec_per_s"] = n / min(r["runs_s"])
    return rows


def against_lockstep(rows, label):
    """`rows` of `one_core_ways` with each way's rate over the lock-step loop's (`vs_lockstep`),
    printed after `label`."""
    lock = rows["diffrax lock-step loop"]["exec_per_s"]
    for name, r in rows.items():
        r["vs_lockstep"] = r["exec_per_s"] / lock
        print(f"{label}, {name:<26} {r['exec_per_s']:11.0f}/s {r['vs_lockstep']:6.2f}x the lock-step loop"
              f"  error {r['error']:8.1e} wrong {r['wrong']}")
    return rows


def others(n, rounds):
    """Problems B and C on one core (`one_core_ways`)."""
    out = {}
    for prob in (P.vdp_relay(), P.thermostat()):
        x0, m0 = prob.sample(np.random.default_rng(5), n)
        rows = timed(one_core_ways(prob), reference(prob, x0, m0), prob, jnp.asarray(x0), jnp.asarray(m0), rounds)
        out[prob.name] = dict(n=n, rows=against_lockstep(rows, prob.name))
    return out


def pinned(n, rounds, prob, x0, m0, truths):
    """In the child process on a single core: problem A three ways (`one_core_ways`), printed as
    one JSON line."""
    rows = timed(one_core_ways(prob), truths, prob, jnp.asarray(x0), jnp.asarray(m0), rounds)
    rows = against_lockstep(rows, "pinned to one core")
    print(json.dumps(dict(cores=len(os.sched_getaffinity(0)), devices=len(jax.devices()), n=n, rows=rows)))


def run_pinned(opts) -> dict:
    """`pinned`'s result, from this script run again in a child process on a single core."""
    out = subprocess.run([sys.executable, __file__, PINNED, "--n", str(opts.n), "--rounds", str(opts.rounds)],
                         capture_output=True, text=True, check=True)
    lines = out.stdout.strip().splitlines()
    print("\n".join(lines[:-1]))  # the child's rows, as `against_lockstep` printed them
    return json.loads(lines[-1])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=10_000, help="executions")
    ap.add_argument("--n-other", type=int, default=2_000, help="executions of problems B and C")
    ap.add_argument("--rounds", type=int, default=7, help="timed rounds, alternating the ways")
    ap.add_argument(PINNED, action="store_true", help=argparse.SUPPRESS)
    opts = ap.parse_args()
    prob = P.ball()
    x0, m0 = prob.sample(np.random.default_rng(5), opts.n)
    truths = [prob.truth(x, m) for x, m in zip(x0, m0, strict=True)]
    if opts.pinned:
        return pinned(opts.n, opts.rounds, prob, x0, m0, truths)
    xa, ma = jnp.asarray(x0), jnp.asarray(m0)
    rows = timed(ways(prob), truths, prob, xa, ma, opts.rounds)
    lock1 = opts.n / min(rows["diffrax lock-step loop, one core"]["runs_s"])
    closed1 = opts.n / min(rows["closed form, one core"]["runs_s"])
    print(f"problem A, N = {opts.n}, {len(jax.devices())} device(s), Tsit5, 1e-9, float64; best of {opts.rounds}")
    print(f"{'way':<34} {'exec/s':>11} {'x lock-step (1 core)':>21} {'x closed form (1 core)':>23}"
          f" {'error':>8} {'wrong':>5}")
    for name, r in rows.items():
        r["vs_lockstep_one_core"] = r["exec_per_s"] / lock1
        r["vs_closed_form_one_core"] = r["exec_per_s"] / closed1
        print(f"{name:<34} {r['exec_per_s']:11.0f} {r['vs_lockstep_one_core']:21.2f}"
              f" {r['vs_closed_form_one_core']:23.3f} {r['error']:8.1e} {r['wrong']:5d}")
    for cores in ("one core", "every core"):
        h, b = rows[f"hybridjax, {cores}"], rows[f"bare hand-written loop, {cores}"]
        lk, cf = rows[f"diffrax lock-step loop, {cores}"], rows[f"closed form, {cores}"]
        print(f"{cores}: hybridjax {h['exec_per_s'] / lk['exec_per_s']:.2f}x the lock-step loop, "
              f"{h['exec_per_s'] / cf['exec_per_s']:.3f}x the closed form, {h['exec_per_s'] / b['exec_per_s']:.2f}x "
              f"the bare loop; the bare loop {b['exec_per_s'] / lk['exec_per_s']:.2f}x the lock-step loop, "
              f"{b['exec_per_s'] / cf['exec_per_s']:.3f}x the closed form (each on {cores})")
    other = others(opts.n_other, opts.rounds)
    single = run_pinned(opts)
    path = write_json("per_core", dict(machine=machine_info(), n=opts.n, rounds=opts.rounds, rows=rows,
                                       others=other, pinned=single, direct_options=BATCH_CPU))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
