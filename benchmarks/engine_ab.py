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
    python benchmarks/engine_ab.py --a /path/to/old/tree --b . --problems vdp_relay   # one problem
    python benchmarks/engine_ab.py --a /path/to/old/tree --b . --same-process   # both trees in one process

With `--same-process` both trees are imported into one Python process, under the names
`hybridjax_a` and `hybridjax_b` (the package uses relative imports only). Each round compiles
each entry point for A and B (the order swapped every round; `jax.clear_caches()` before every
compile, so each round traces and compiles afresh), then calls the two programs in turn, A B A B
..., for about `--call-seconds` each (at least `--repeat` calls); the best over `--rounds` rounds
of each program's minimum (`run_s`) and median (`run_median_s`) call is reported. Two compiles
of one program can differ in run time by up to 1.8x (seen on the ball's gradient), so the run
times of one round are compared under the same machine state, and several rounds sample the
compiles.
"""

import argparse
import importlib
import importlib.util
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
ENGINE_FILES = (
    "_loop.py",
    "_batched.py",
    "_events.py",
    "_rules.py",
    "_fast_rk.py",
    "_zeno.py",
)  # flat layout
ENGINE_PACKAGES = ("_engines", "_rules", "_step")
PROBLEMS = ("ball", "vdp_relay", "thermostat")


ENTRIES = (
    "simulate",
    "vmap(simulate)",
    "simulate_batch",
    "grad simulate",
    "grad vmap(simulate)",
    "grad simulate_batch",
)


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
        opts = dict(stepsize_controller=ctrl, max_epochs=pb.max_epochs)
        fns = _entry_fns(hj, pb, np.asarray(x0, np.float64), int(mode0[0]), opts, entries)
        res = {}
        for key, (make, arg) in fns.items():
            fn = make()
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


def _entry_fns(hj, pb, x0, m0, opts, entries):
    """The jitted entry points of one problem for the hybridjax module `hj`, with their arguments."""
    import jax

    def final(x):
        return hj.simulate(pb.system, x, m0, 0.0, pb.t1, pb.args, **opts).final_state

    def batch(X):
        return hj.simulate_batch(pb.system, X, m0, 0.0, pb.t1, pb.args, **opts).final_state

    makers = {
        "simulate": (lambda: jax.jit(final), x0[0]),
        "vmap(simulate)": (lambda: jax.jit(jax.vmap(final)), x0),
        "simulate_batch": (lambda: jax.jit(batch), x0),
        "grad simulate": (lambda: jax.jit(jax.grad(lambda x: final(x).sum())), x0[0]),
        "grad vmap(simulate)": (lambda: jax.jit(jax.grad(lambda X: jax.vmap(final)(X).sum())), x0),
        "grad simulate_batch": (lambda: jax.jit(jax.grad(lambda X: batch(X).sum())), x0),
    }
    return {k: v for k, v in makers.items() if k in entries}


def _import_tree(root: pathlib.Path, alias: str):
    """hybridjax from the source tree `root` imported as the package `alias`, and benchmarks/problems.py
    bound to it (its `import hybridjax` answered by that package while it loads)."""
    link_dir = pathlib.Path(tempfile.mkdtemp(prefix=f"{alias}_"))
    (link_dir / alias).symlink_to(root / "hybridjax", target_is_directory=True)
    sys.path.insert(0, str(link_dir))
    hj = importlib.import_module(alias)
    examples = importlib.import_module(alias + ".examples")
    saved = {k: sys.modules.get(k) for k in ("hybridjax", "hybridjax.examples")}
    sys.modules["hybridjax"], sys.modules["hybridjax.examples"] = hj, examples
    try:
        spec = importlib.util.spec_from_file_location(f"problems_{alias}", HERE / "problems.py")
        problems = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(problems)
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
    return hj, problems


def same_process(roots: dict, n: int, repeat: int, rounds: int, entries, call_s: float) -> dict:
    """Both trees in this process: per problem and entry point, `rounds` rounds, each compiling A
    and B (the order swapped every round) and then calling the two compiled programs in turn,
    A B A B ..., at least `repeat` times each and for about `call_s` seconds of each; the
    minimum and the median of each program's calls are kept. Two compiles of one program can
    differ in run time (memory layout); alternating calls see the same machine state."""
    import statistics

    import diffrax
    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    trees = {v: _import_tree(root, f"hybridjax_{v.lower()}") for v, root in roots.items()}
    ctrl = diffrax.PIDController(rtol=1e-8, atol=1e-8)
    runs: dict = {v: [{} for _ in range(rounds)] for v in roots}
    for name in PROBLEMS:
        fns = {}
        for v, (hj, problems) in trees.items():
            pb = getattr(problems, name)()
            x0, mode0 = pb.sample(np.random.default_rng(0), n)
            opts = dict(stepsize_controller=ctrl, max_epochs=pb.max_epochs)
            fns[v] = _entry_fns(hj, pb, np.asarray(x0, np.float64), int(mode0[0]), opts, entries)
        for key in fns["A"]:
            for r in range(rounds):
                compiled, compile_s = {}, {}
                for v in ("A", "B") if r % 2 == 0 else ("B", "A"):
                    make, arg = fns[v][key]
                    jax.clear_caches()
                    t = time.perf_counter()
                    compiled[v] = make().trace(arg).lower().compile()
                    compile_s[v] = time.perf_counter() - t
                    jax.block_until_ready(compiled[v](arg))  # first call outside the timing
                times: dict = {"A": [], "B": []}
                while len(times["A"]) < repeat or sum(times["A"]) + sum(times["B"]) < 2 * call_s:
                    for v in ("A", "B"):
                        arg = fns[v][key][1]
                        t = time.perf_counter()
                        jax.block_until_ready(compiled[v](arg))
                        times[v].append(time.perf_counter() - t)
                for v in ("A", "B"):
                    runs[v][r].setdefault(name, {})[key] = dict(
                        compile_s=compile_s[v],
                        run_s=min(times[v]),
                        run_median_s=statistics.median(times[v]),
                        calls=len(times[v]),
                    )
            print(f"{name} | {key} done", file=sys.stderr, flush=True)
    return runs


def lines(root: pathlib.Path) -> dict:
    pkg = root / "hybridjax"
    files = [pkg / f for f in ENGINE_FILES if (pkg / f).exists()]
    files += [p for d in ENGINE_PACKAGES if (pkg / d).is_dir() for p in sorted((pkg / d).glob("*.py"))]
    counts = {str(p.relative_to(pkg)): len(p.read_text().splitlines()) for p in files}
    return dict(files=counts, total=sum(counts.values()))


def _tree_name(root: pathlib.Path) -> str:
    """The tree's git commit (with "+changes" when it has uncommitted ones), or its folder name."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "hybridjax"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
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
            for what in ("run_s", "run_median_s", "compile_s"):
                if what not in runs["A"][0][name][key]:
                    continue
                best = {v: min(run[name][key][what] for run in runs[v]) for v in roots}
                table[f"{name} | {key} | {what}"] = dict(
                    A=best["A"], B=best["B"], ratio=best["B"] / best["A"]
                )
    return dict(
        a=_tree_name(roots["A"]),
        b=_tree_name(roots["B"]) + "".join(f" {k}={v}" for k, v in _env_b(a).items()),
        rounds=len(runs["B"]),
        same_process=a.same_process,
        repeat=a.repeat,
        n=a.n,
        lines=dict(A=lines(roots["A"]), B=lines(roots["B"])),
        best=table,
        load=loads,
        runs=runs,
    )


def main():
    global PROBLEMS
    ap = argparse.ArgumentParser()
    ap.add_argument("--a", required=True, help="source tree of version A (the reference)")
    ap.add_argument("--b", default=str(HERE.parent), help="source tree of version B")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--n", type=int, default=100)
    ap.add_argument("--entries", default=",".join(ENTRIES), help="comma-separated, of " + ", ".join(ENTRIES))
    ap.add_argument("--problems", default=",".join(PROBLEMS), help="comma-separated, of " + ", ".join(PROBLEMS))
    ap.add_argument(
        "--env-b",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="an environment variable for version B's processes (repeatable)",
    )
    ap.add_argument(
        "--same-process",
        action="store_true",
        help="import both trees into this process and alternate within it",
    )
    ap.add_argument(
        "--call-seconds",
        type=float,
        default=1.0,
        help="with --same-process: call each compiled program for about this long per round",
    )
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", default=str(HERE / "results" / "engine_ab.json"))
    a = ap.parse_args()
    PROBLEMS = tuple(a.problems.split(","))
    if a.one:
        print(json.dumps(one(a.n, a.repeat, a.entries.split(","))))
        return
    roots = {"A": pathlib.Path(a.a).resolve(), "B": pathlib.Path(a.b).resolve()}
    runs: dict = {"A": [], "B": []}
    loads: list = []
    if a.same_process:
        loads.append(os.getloadavg()[0])
        runs = same_process(roots, a.n, a.repeat, a.rounds, a.entries.split(","), a.call_seconds)
        loads.append(os.getloadavg()[0])
        result = summary(a, roots, runs, loads)
        pathlib.Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(a.out).write_text(json.dumps(result, indent=1))
    for r in range(0 if a.same_process else a.rounds):
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
                "--problems",
                a.problems,
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
    print(
        f"load average {'at start and end' if a.same_process else 'as each process started'}: {min(loads):.1f} to {max(loads):.1f} ({os.cpu_count()} cores)"
    )
    print("lines of engines + rules:", result["lines"]["A"]["total"], "->", result["lines"]["B"]["total"])


if __name__ == "__main__":
    main()
