"""Two versions of the engine in one process: run-time ratio and whether the results are identical.

This machine's speed drifts by +-20 % between runs, more than most engine changes; timings of
two versions are comparable only when taken in one process, alternating. This script extracts
`hybridjax/` at a git commit (`git archive`) as a second package, `hybridjax_base`, imports it
beside the working tree's `hybridjax`, compiles `simulate_batch` of both on the same problems
(`problems.py`, Tsit5, rtol = atol = 1e-9, float64), runs them in turn (alternating order, best
of `--rounds`), and reports the ratio new / base, the compile times, and whether final states,
step counts, event counts and event times are bitwise identical (else by how much they differ).

    python dev/ab_commits.py HEAD                      # working tree against HEAD
    python dev/ab_commits.py <commit> --problems ball,vdp --rounds 11
    python dev/ab_commits.py HEAD --block 156          # both at the same block size

Problems: ball (A, N = 10,000), ballsave (the same with 201 saved states), vdp (B, N = 1,000),
vdp10k (B, N = 10,000), thermo (C, N = 2,000). Prints one line per problem; writes nothing (a tool for changes, not a result).
"""

import argparse
import importlib
import subprocess
import sys
import tarfile
import tempfile
import time
from io import BytesIO
from pathlib import Path

import diffrax
import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # the benchmark problems
import problems  # noqa: E402

# name: (problem, example, N, number of save times over [0, t1])
CASES = {"ball": (problems.ball, "bouncing_ball", 10_000, 0),
         "ballsave": (problems.ball, "bouncing_ball", 10_000, 201),
         "vdp": (problems.vdp_relay, "van_der_pol_relay", 1_000, 0),
         "vdp10k": (problems.vdp_relay, "van_der_pol_relay", 10_000, 0),
         "thermo": (problems.thermostat, "thermostat", 2_000, 0)}
COMPARED = ("final_state", "num_steps", "num_events", "event_times", "ys", "saved_modes")


def base_package(commit: str, into: Path):
    """`hybridjax/` at `commit`, importable as `hybridjax_base` (its imports are relative)."""
    tar = subprocess.run(["git", "archive", commit, "hybridjax"], cwd=ROOT, capture_output=True, check=True).stdout
    with tarfile.open(fileobj=BytesIO(tar)) as t:
        t.extractall(into, filter="data")
    (into / "hybridjax").rename(into / "hybridjax_base")
    sys.path.insert(0, str(into))
    return importlib.import_module("hybridjax_base")


def differences(a, b) -> str:
    """"identical" where every compared field is bitwise equal; else, per differing field, the
    largest difference (float fields; equal infinities count as equal) or how many entries
    differ (integer fields)."""
    out = []
    for f in COMPARED:
        x, y = np.asarray(getattr(a, f)), np.asarray(getattr(b, f))
        if np.array_equal(x, y):
            continue
        if np.issubdtype(x.dtype, np.floating):
            both = np.isfinite(x) & np.isfinite(y)
            same_inf = (x == y) & ~both
            worst = np.max(np.abs(np.where(both, x, 0.0) - np.where(both, y, 0.0)), initial=0.0)
            out.append(f"{f} max |diff| {worst:.1e}" + ("" if np.all(both | same_inf) else " (finite/inf differ)"))
        else:
            out.append(f"{f} {int(np.sum(x != y))} entries differ")
    return "identical" if not out else "differ: " + ", ".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("commit")
    ap.add_argument("--problems", default="ball,thermo,vdp")
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--block", type=int, default=None, help="simulate_batch's block for both (default: theirs)")
    opts = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    import hybridjax

    ctrl = diffrax.PIDController(rtol=1e-9, atol=1e-9)
    with tempfile.TemporaryDirectory() as tmp:
        base = base_package(opts.commit, Path(tmp))
        for name in opts.problems.split(","):
            make, example, n, saves = CASES[name]
            p = make()
            x0, m0 = p.sample(np.random.default_rng(0), n)
            runs = {}
            for tag, hj in (("base", base), ("new", hybridjax)):
                system = getattr(hj.examples, example)()  # built from that version's classes
                fn = jax.jit(lambda x, hj=hj, system=system: hj.simulate_batch(
                    system, x, m0, 0.0, p.t1, p.args, stepsize_controller=ctrl, max_epochs=p.max_epochs,
                    saveat=np.linspace(0.0, p.t1, saves) if saves else None, block=opts.block))
                t = time.perf_counter()
                compiled = fn.trace(x0).lower().compile()
                runs[tag] = (compiled, time.perf_counter() - t, jax.block_until_ready(compiled(x0)))
            same = differences(runs["base"][2], runs["new"][2])
            best = {"base": float("inf"), "new": float("inf")}
            for r in range(opts.rounds):
                for tag in (("base", "new") if r % 2 == 0 else ("new", "base")):
                    t = time.perf_counter()
                    jax.block_until_ready(runs[tag][0](x0))
                    best[tag] = min(best[tag], time.perf_counter() - t)
            print(f"{name} (N = {n:,}): base {best['base'] * 1e3:.1f} ms, new {best['new'] * 1e3:.1f} ms, "
                  f"new/base {best['new'] / best['base']:.3f}; {same}; compile base {runs['base'][1]:.1f} s, "
                  f"new {runs['new'][1]:.1f} s", flush=True)


if __name__ == "__main__":
    main()
