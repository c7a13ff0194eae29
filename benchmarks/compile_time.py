"""Compile time against run time: XLA:CPU's compiler settings, measured on problem A.

JAX reads `XLA_FLAGS` once, when it creates its CPU backend, so each setting runs in a fresh
Python process (this script re-runs itself with `--one`). For each: trace + lower time, XLA
compile time, and the best of 5 runs of `jax.jit(hj.simulate_batch)` on the bouncing ball
(e = 0.8, h0 ~ U(0.5, 1.5), v0 ~ U(-1, 1), T = 2.5, Tsit5, rtol = atol = 1e-9, float64) at
N = 1,000 and 10,000, with the largest final-state error against the closed form.

Settings: XLA's defaults; `--xla_cpu_use_fusion_emitters=false` (the older loop emitters);
and that with `--xla_backend_optimization_level=0` (no LLVM optimisation): what the test suite
uses, tests/conftest.py, run as the suite runs it, in a process on one core (at level 0 XLA:CPU
has run programs with thread-dependent results; docs: FAQ). Then JAX's persistent compilation
cache (`JAX_COMPILATION_CACHE_DIR`, a fresh temporary directory): the default setting in a first process, which compiles and
writes the cache, and in a second one, which reads the compiled program from it (trace and
lowering still run: the cache is keyed by the lowered program). The ratio columns are against
the default setting of the same run. `first result` is the time from the process's first
import of JAX to the first batch's result (N = 1,000: imports, trace, lowering, compilation,
one run).

    python benchmarks/compile_time.py      # prints a table, writes results/compile_time.json
"""

import json
import os
import sys
import tempfile
import time

T_START = time.perf_counter()

SETTINGS = {
    "default": "",
    "fusion emitters off": "--xla_cpu_use_fusion_emitters=false",
    "fusion emitters off, LLVM -O0": "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0",
}
CACHED = ("persistent cache, first process", "persistent cache, a later process")
SIZES = (1000, 10000)


def one() -> dict:
    if "--xla_backend_optimization_level=0" in os.environ.get("XLA_FLAGS", ""):
        # As the test suite runs it: on one core (before JAX starts, which reads the affinity).
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    import diffrax
    import jax
    import numpy as np

    import hybridjax as hj

    jax.config.update("jax_enable_x64", True)
    ball = hj.examples.bouncing_ball()
    ctrl = diffrax.PIDController(rtol=1e-9, atol=1e-9)
    out = {}
    for n in SIZES:
        rng = np.random.default_rng(0)
        x0 = np.stack([rng.uniform(0.5, 1.5, n), rng.uniform(-1, 1, n)], 1)
        fn = jax.jit(lambda x: hj.simulate_batch(ball, x, "flight", 0.0, 2.5, {"g": 9.8, "e": 0.8},
                                                 stepsize_controller=ctrl, max_epochs=32).final_state)
        t = time.perf_counter()
        lowered = fn.trace(x0).lower()
        t_trace = time.perf_counter() - t
        t = time.perf_counter()
        compiled = lowered.compile()
        t_compile = time.perf_counter() - t
        final = jax.block_until_ready(compiled(x0))
        first_result_s = time.perf_counter() - T_START if n == SIZES[0] else None
        best = float("inf")
        for _ in range(5):
            t = time.perf_counter()
            final = jax.block_until_ready(compiled(x0))
            best = min(best, time.perf_counter() - t)
        ref = np.array([hj.examples.bouncing_ball_closed_form(h, v, 9.8, 0.8, 2.5)["final_state"] for h, v in x0])
        out[n] = dict(trace_lower_s=t_trace, compile_s=t_compile, first_result_s=first_result_s,
                      run_s=best, per_s=n / best,
                      max_error=float(np.max(np.abs(np.asarray(final) - ref))))
    return out


def main():
    from _common import machine_info, run_per_setting, write_json

    rows = {name: {"flags": SETTINGS[name], **{int(k): v for k, v in r.items()}}
            for name, r in run_per_setting(__file__, SETTINGS).items()}
    with tempfile.TemporaryDirectory() as cache:
        env = {"JAX_COMPILATION_CACHE_DIR": cache, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "1"}
        for name in CACHED:
            rows[name] = {"flags": "", **{int(k): v for k, v in
                                          run_per_setting(__file__, {name: ""}, env=env)[name].items()}}
    base = rows["default"]
    print(f"{'setting':34s} {'N':>6s} {'trace+lower':>11s} {'XLA compile':>11s} {'1st result':>10s} {'run':>9s} "
          f"{'exec/s':>9s} {'compile x':>9s} {'speed x':>7s} {'max error':>9s}")
    for name, r in rows.items():
        for n in SIZES:
            c = r[n]
            print(f"{name:34s} {n:6d} {c['trace_lower_s']:10.2f}s {c['compile_s']:10.2f}s "
                  + (f"{c['first_result_s']:9.2f}s" if c["first_result_s"] else f"{'-':>10s}")
                  + f" {c['run_s'] * 1e3:7.1f}ms "
                  f"{c['per_s']:9.0f} {c['compile_s'] / base[n]['compile_s']:9.2f} "
                  f"{c['per_s'] / base[n]['per_s']:7.2f} {c['max_error']:9.1e}")
    import jax

    jax.config.update("jax_enable_x64", True)
    path = write_json("compile_time", dict(machine=machine_info(), settings=rows))
    print("wrote", path)


if __name__ == "__main__":
    if "--one" in sys.argv:
        print(json.dumps(one()))
    else:
        main()
