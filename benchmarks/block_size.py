"""Block size of the batched engine's rare work: run time and compile time, in one process.

`simulate_batch` does the work only some executions need in an iteration (epoch start, event
location, reset) on blocks of them, pass after pass until every one is done (results do not
depend on the size). Settings: the default (lanes/32), lanes/4, lanes/16, lanes/64,
the pair (lanes/64, default) (both sizes compiled; the small one taken where it holds every
execution that needs it) and the whole batch. Problems: the bouncing ball (A) and the Van der Pol relay (B) at N = 10,000,
the thermostat (C) at N = 2,000; Tsit5, rtol = atol = 1e-9, float64. Each setting is compiled
once (trace + XLA compile time reported), then the settings run in turn, alternating order,
best of `--rounds` (default 5) each. Error: the largest final-state difference against the
problem's closed form (A, C) or against the default setting (B; block sizes give identical
results, so any difference would be a bug).

    python benchmarks/block_size.py        # prints a table, writes results/block_size.json
"""

import sys

import diffrax
import jax
import numpy as np
from _common import compiled_and_alternated, machine_info, write_json
from problems import ball, thermostat, vdp_relay

import hybridjax as hj

jax.config.update("jax_enable_x64", True)

DEFAULT = "default (N/32)"
CASES = {"A: bouncing ball": (ball, 10_000), "B: Van der Pol relay": (vdp_relay, 10_000),
         "C: thermostat": (thermostat, 2_000)}


def settings(n: int) -> dict:
    return {DEFAULT: None, "N/4": n // 4, "N/16": n // 16, "N/64": n // 64, "(N/64, N/32)": (n // 64, None), "N": n}


def main(rounds: int = 5):
    ctrl = diffrax.PIDController(rtol=1e-9, atol=1e-9)
    rows = []
    print(f"{'problem':22s} {'block':14s} {'compile':>8s} {'run':>9s} {'exec/s':>9s} {'x default':>9s} "
          f"{'error':>8s} {'vs':>11s}")
    for name, (make, n) in CASES.items():
        p = make()
        x0, m0 = p.sample(np.random.default_rng(0), n)
        fns = {label: jax.jit(lambda x, block=block: hj.simulate_batch(
            p.system, x, m0, 0.0, p.t1, p.args, stepsize_controller=ctrl, max_epochs=p.max_epochs,
            block=block)) for label, block in settings(n).items()}
        sols, best = compiled_and_alternated(fns, x0, rounds)
        if p.truth is not None:
            want, against = np.stack([p.truth(x, m)["final_state"] for x, m in zip(x0, m0, strict=True)]), "closed form"
        else:
            want, against = np.asarray(sols[DEFAULT][0].final_state), "default"
        base = best[DEFAULT]
        for label, block in settings(n).items():
            sol, compile_s = sols[label]
            err = float(np.max(np.abs(np.asarray(sol.final_state) - want)))
            row = dict(problem=name, n=n, block=str(block), label=label, compile_s=compile_s, run_s=best[label],
                       per_s=n / best[label], ratio=best[label] / base, error=err, error_against=against)
            rows.append(row)
            print(f"{name:22s} {label:14s} {compile_s:7.1f}s {best[label] * 1e3:7.1f}ms {n / best[label]:9.0f} "
                  f"{row['ratio']:9.2f} {err:8.1e} {against:>11s}", flush=True)
    path = write_json("block_size", dict(machine=machine_info(), rounds=rounds, rows=rows))
    print("wrote", path)


if __name__ == "__main__":
    main(int(sys.argv[sys.argv.index("--rounds") + 1]) if "--rounds" in sys.argv else 5)
