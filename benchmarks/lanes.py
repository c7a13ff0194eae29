"""Lanes of the batched engine: one lane per execution against lanes refilled, in one process.

`simulate_batch` runs its executions on lanes (`lanes=`): with one lane per execution, lanes
whose executions have ended idle until the last one ends; with fewer lanes, a lane whose
execution ends takes the next one not yet started (a refill: a pass over every lane in each
iteration where some execution ends). Settings per batch size N: 10,000 lanes refilled and one
lane per execution (`lanes=N`), and which of them `simulate_batch` picks by default
(`hybridjax._engines.lanes.default_lanes`). Problems A (the ball), C (thermostat) and B (Van der
Pol relay) of problems.py, in that order, Tsit5, rtol = atol = 1e-9, float64, one device; each setting
compiled once, then the settings run in turn, alternating order, best of `--rounds` (default 3).
Error: the largest final-state difference against the closed form (A, C) or between the two
settings (B; the lanes give identical results, so any difference would be a bug).

    python benchmarks/lanes.py        # prints a table, writes results/lanes.json
"""

import sys

import diffrax
import jax
import numpy as np
from _common import compiled_and_alternated, machine_info, write_json
from problems import ball, thermostat, vdp_relay

import hybridjax as hj
from hybridjax._engines.lanes import REFILL_LANES, default_lanes

jax.config.update("jax_enable_x64", True)

CASES = (("A: bouncing ball", ball, (40_000, 100_000, 200_000, 400_000)),
         ("C: thermostat", thermostat, (40_000, 200_000)),
         ("B: Van der Pol relay", vdp_relay, (40_000,)))
REFILLED, ONE_EACH = f"{REFILL_LANES:,} lanes, refilled", "one lane per execution"


def main(rounds: int = 3):
    ctrl = diffrax.PIDController(rtol=1e-9, atol=1e-9)
    rows = []
    print(f"{'problem':22s} {'N':>8s} {'lanes':26s} {'compile':>8s} {'run':>9s} {'exec/s':>9s} {'default':>8s} "
          f"{'error':>8s}")
    for name, make, sizes in CASES:
        p = make()
        for n in sizes:
            x0, m0 = p.sample(np.random.default_rng(0), n)
            settings = {REFILLED: REFILL_LANES, ONE_EACH: n}
            fns = {label: jax.jit(lambda x, lanes=lanes: hj.simulate_batch(
                p.system, x, m0, 0.0, p.t1, p.args, stepsize_controller=ctrl, max_epochs=p.max_epochs,
                lanes=lanes, devices=1)) for label, lanes in settings.items()}
            sols, best = compiled_and_alternated(fns, x0, rounds)
            if p.truth is not None:
                want = np.stack([p.truth(x, m)["final_state"] for x, m in zip(x0, m0, strict=True)])
                against = "closed form"
            else:
                want, against = np.asarray(sols[REFILLED][0].final_state), REFILLED
            default = default_lanes(n, differentiated=False)
            for label, lanes in settings.items():
                sol, compile_s = sols[label]
                err = float(np.max(np.abs(np.asarray(sol.final_state) - want)))
                row = dict(problem=name, n=n, lanes=lanes, label=label, default=lanes == default,
                           compile_s=compile_s, run_s=best[label], per_s=n / best[label],
                           ratio=best[label] / best[REFILLED], error=err, error_against=against)
                rows.append(row)
                print(f"{name:22s} {n:8d} {label:26s} {compile_s:7.1f}s {best[label] * 1e3:7.0f}ms "
                      f"{n / best[label]:9.0f} {'yes' if row['default'] else '':>8s} {err:8.1e}", flush=True)
            path = write_json("lanes", dict(machine=machine_info(), rounds=rounds, refill_lanes=REFILL_LANES,
                                            rows=rows))  # after every size: a partial run keeps what it measured
    print("wrote", path)


if __name__ == "__main__":
    main(int(sys.argv[sys.argv.index("--rounds") + 1]) if "--rounds" in sys.argv else 3)
