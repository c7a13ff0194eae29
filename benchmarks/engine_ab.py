"""Two versions of hybridjax against each other: forward run time, compile time and reverse-mode
gradient time on the ball, Van der Pol with relay and the thermostat (problems A, B, C).

Each measurement runs in a fresh Python process that imports hybridjax from the given source
tree (so compile times include nothing cached), the two versions alternating, A B A B ...,
`--rounds` times; the best of the rounds is kept for each version and reported with the ratio
B / A (the machine may be loaded by other work: alternating pairs see the same load). Per
problem and entry point: `trace + lower + compile` time, and the best of `--repeat` runs of the
compiled program. Entry points: one execution (`jax.jit(simulate)`), `jax.jit(jax.vmap(simulate))`
and `jax.jit(simulate_batch)` over `--n` executions (x0 sampled as in problems.py), and the
reverse-mode gradient (`jax.grad` of the sum of the final states) of one execution, of
`jax.vmap(simulate)` and of `simulate_batch`. `--env-b NAME=VALUE` sets an environment variable
in version B's processes alone (for one tree run both ways by a private switch read from the
environment). Float64, Tsit5, PIDController(rtol = atol = 1e-8), XLA's default flags. Also the
lines of the engines and their rules in each tree (the modules of `hybridjax/_engines`, `_rules`
and `_step`, or, in a tree with the flat layout, `_loop`, `_batched`, `_events`, `_rules`,
`_fast_rk` and `_zeno`).

    python benchmarks/engine_ab.py --a /path/to/old/tree --b .   # writes results/engine_ab.json
    python benchmarks/engine_ab.py --a /path/to/old/tree --b . --entries "simulate,grad vmap(simulate)"
"""

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
ENGINE_FILES = ("_loop.py", "_batched.py", "_events.py", "_rules.py", "_fast_rk.py", "_zeno.py")  # flat layout
ENGINE_PACKAGES = ("_engines", "_rules", "_step")
PROBLEMS = ("ball", "vdp_relay", "thermostat")


ENTRIES = ("simulate", "vmap(simulate)", "simulate_batch", "grad simulate", "grad vmap(simulate)",
           "grad simulate_batch")


def one(n: int, repeat: int, entries) -> dict:
    """The measurements of the hybridjax found first on sys.path (run in a child process)."""
    import diffrax
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import hybridjax as hj

    sys.path.insert(0, str(HERE))
    import problems

    ctrl = diffrax.PIDController(rtol=1e-8, atol=1e-8)
    out = {}
    for name in PROBLEMS:
        pb = getattr(problems, name)()
        x0, mode0 = pb.sample(np.random.default_rng(0), n)
        x0 = np.asarray(x0, np.float64)
        m0 = int(mode0[0])
        opts = dict(stepsize_controller=ctrl, max_epochs=pb.max_epochs)

        def final(x, pb=pb, m0=m0, opts=opts):
            return hj.simulate(pb.system, x, m0, 0.0, pb.t1, pb.args, **opts).final_state

        def batch(X, pb=pb, m0=m0, opts=opts):
            return hj.simulate_batch(pb.system, X, m0, 0.0, pb.t1, pb.args, **opts).final_state

        fns = {
            "simulate": (jax.jit(final), x0[0]),
            "vmap(simulate)": (jax.jit(jax.vmap(final)), x0),
            "simulate_batch": (jax.jit(batch), x0),
            "grad simulate": (jax.jit(jax.grad(lambda x, f=final: f(x).sum())), x0[0]),
            "grad vmap(simulate)": (jax.jit(jax.grad(lambda X, f=final: jax.vmap(f)(X).sum())), x0),
            "grad simulate_batch": (jax.jit(jax.grad(lambda X, f=batch: f(X).sum())), x0),
        }
        res = {}
        for key, (fn, arg) in fns.items():
            if key not in entries:
                continue
            t = time.perf_counter()
            compiled = fn.trace(arg).lower().compile()
            compile_s = time.perf_counter() - t
            runs = []
            for _ in range(repeat):
                t = time.perf_counter()
                jax.block_until_ready(compiled(arg))
                runs.append(time.perf_counter() - t)
            res[key] = dict(compile_s=compile_s, run_s=min(runs))
        out[name] = res
    return out


def lines(root: pathlib.Path) -> dict:
    pkg = root / "hybridjax"
    files = [pkg / f for f in ENGINE_FILES if (pkg / f).exists()]
    files += [p for d in ENGINE_PACKAGES if (pkg / d).is_dir() for p in sorted((pkg / d).glob("*.py"))]
    counts = {str(p.relative_to(pkg)): len(p.read_text().splitlines()) for p in files}
    return dict(files=counts, total=sum(counts.values()))


def _tree_name(root: pathlib.Path) -> str:
    """The tree's git commit (with "+changes" when it has uncommitted ones), or its folder name."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "hybridjax"], cwd=root, capture_output=True,
                               text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return root.name
    return head + (" +changes" if dirty else "")


def _env_b(a) -> dict:
    """`--env-b NAME=VALUE` options as a dict."""
    pairs = [item.split("=", 1) for item in a.env_b]
    if any(len(p) != 2 or not p[0] for p in pairs):
        raise SystemExit(f"--env-b: expected NAME=VALUE, got {a.env_b}")
    return dict(pairs)


def summary(a, roots, runs, loads) -> dict:
    """Best of the completed rounds per version, and the ratio B / A; `loads` the machine's
    1-minute load average as each process started."""
    table = {}
    for name in PROBLEMS:
        for key in runs["A"][0][name]:
            for what in ("run_s", "compile_s"):
                best = {v: min(run[name][key][what] for run in runs[v]) for v in roots}
                table[f"{name} | {key} | {what}"] = dict(
                    A=best["A"], B=best["B"], ratio=best["B"] / best["A"]
                )
    return dict(
        a=_tree_name(roots["A"]),
        b=_tree_name(roots["B"]) + "".join(f" {k}={v}" for k, v in _env_b(a).items()),
        rounds=len(runs["B"]),
        repeat=a.repeat,
        n=a.n,
        lines=dict(A=lines(roots["A"]), B=lines(roots["B"])),
        best=table,
        load=loads,
        runs=runs,
    )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--a", required=True, help="source tree of version A (the reference)")
    ap.add_argument("--b", default=str(HERE.parent), help="source tree of version B")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--n", type=int, default=100)
    ap.add_argument("--entries", default=",".join(ENTRIES), help="comma-separated, of " + ", ".join(ENTRIES))
    ap.add_argument("--env-b", action="append", default=[], metavar="NAME=VALUE",
                    help="an environment variable for version B's processes (repeatable)")
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", default=str(HERE / "results" / "engine_ab.json"))
    a = ap.parse_args()
    if a.one:
        print(json.dumps(one(a.n, a.repeat, a.entries.split(","))))
        return
    roots = {"A": pathlib.Path(a.a).resolve(), "B": pathlib.Path(a.b).resolve()}
    runs: dict = {"A": [], "B": []}
    loads: list = []
    for r in range(a.rounds):
        for v, root in roots.items():
            env = dict(os.environ, PYTHONPATH=str(root), **(_env_b(a) if v == "B" else {}))
            cmd = [
                sys.executable,
                __file__,
                "--a",
                a.a,
                "--one",
                "--n",
                str(a.n),
                "--repeat",
                str(a.repeat),
                "--entries",
                a.entries,
            ]
            loads.append(os.getloadavg()[0])
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True, cwd=root)
            runs[v].append(json.loads(proc.stdout.strip().splitlines()[-1]))
            print(f"round {r + 1}/{a.rounds}, {v} done", file=sys.stderr, flush=True)
        result = summary(a, roots, runs, loads)  # written after every round: a long run can be cut short
        pathlib.Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(a.out).write_text(json.dumps(result, indent=1))
    table = result["best"]
    print(f"{'problem | entry point | measure':60s} {'A':>9s} {'B':>9s} {'B/A':>6s}")
    for k, v in table.items():
        print(f"{k:60s} {v['A']:9.4f} {v['B']:9.4f} {v['ratio']:6.3f}")
    print(f"load average as each process started: {min(loads):.1f} to {max(loads):.1f} ({os.cpu_count()} cores)")
    print("lines of engines + rules:", result["lines"]["A"]["total"], "->", result["lines"]["B"]["total"])


if __name__ == "__main__":
    main()
