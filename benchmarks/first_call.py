"""The first call, as a new user meets it: import, trace, lowering, XLA compilation and first run.

Four systems (the bouncing ball; the thermostat; the wall particle, whose two modes have
dimensions 4 and 2; the integrate-and-fire neuron) and three calls on each:

- forward: `jax.jit(lambda x0, args: hj.simulate(...).final_state)`;
- reverse: `jax.jit(jax.grad(lambda x0, args: hj.simulate(...).final_state[0]))`;
- jvp: `jax.jit(lambda x0, v, args: jax.jvp(lambda x: hj.simulate(..., adjoint=diffrax.ForwardMode())
  .final_state, (x0,), (v,)))`.

Float64, default tolerances (rtol = atol = 1e-8), Tsit5, XLA's default flags; `x0` and `args`
are arrays (inputs of the program, not constants). Each (system, call) runs in a fresh Python
process (this script re-runs itself with `--one SYSTEM CALL [--cache DIR]`), which times:
`import jax`, `import hybridjax`, tracing (`fn.trace`), lowering (`.lower()`), XLA compilation
(`.compile()`), the first run, and the time from the process's first line to the first result
(wall time, and the process's CPU time beside it: the machine may be shared);
the same call on the plain diffrax loop (a `lax.scan` over 64 epochs of `diffeqsolve` +
`diffrax.Event`, `_baselines.diffrax_epoch_scan`), also in a fresh process, whose import is
`import jax` and `import diffrax` (the hybridjax and the baselines' module its process imports
for the problem's definition are left out of its times);
and records the size of the program (the lowered StableHLO text: bytes, lines, operations; the
optimised HLO that XLA compiled: instructions). Then the same with JAX's persistent compilation
cache: a first process that fills a fresh temporary cache directory, and a second that reads it
(tracing and lowering still run: the cache is keyed by the lowered program). Then the
program's own XLA options, `jax.jit(..., compiler_options=...)`, the one of a direct call of
`hj.simulate` that shortens its compilation (`hybridjax._solve.eager.FAST_COMPILE_CPU`:
XLA:CPU's own fusion emitters in place of its MLIR ones), on hybridjax and on the lock-step
loop; and the call made directly, outside `jax.jit` (`hj.simulate(...)`, under `jax.grad` or `jax.jvp` for the
derivatives), as in a notebook: compiled by hybridjax (`hybridjax._solve.eager`), its first
result timed as a whole. The direct call and the lock-step loop, the comparison a user makes, run
in `--pairs` (default 5) alternating pairs of fresh processes; each of their rows is the pair's best
first result, with every run's time beside it. Each result is checked against a closed form (derivatives: central
differences of the closed form), and the error recorded beside the time.

hybridjax's modules are byte-compiled first (`compileall`), as `pip install` leaves them: a
process started from a checkout with `PYTHONDONTWRITEBYTECODE=1` would otherwise compile them from
source at every import, a cost the installed jax and diffrax of the lock-step rows do not pay.

    python benchmarks/first_call.py                     # prints a table, writes results/first_call.json
    python benchmarks/first_call.py --systems ball lif  # a subset
    python benchmarks/first_call.py --pairs 7           # more alternating pairs
"""

import time

T_START = time.perf_counter()

import compileall  # noqa: E402
import functools  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402

SYSTEMS = ("ball", "thermostat", "wall", "lif")
CALLS = ("forward", "reverse", "jvp")
PROCESSES = ("no cache", "cache: first process", "cache: later process")
# A program's own XLA options (`jax.jit(..., compiler_options=...)`), the one of a direct call that
# shortens its compilation (`FAST_COMPILE_CPU`): kernels compiled by XLA:CPU's own fusion
# emitters, not its MLIR ones.
FAST = "fusion emitters off"
EAGER = "direct call"
# The same call on the plain diffrax loop (`_baselines.diffrax_epoch_scan`), in a fresh process
# without cache: what a user would compile without hybridjax. Not for the wall particle, whose
# modes have different dimensions (one diffeqsolve carries one state shape).
LOCK = "lock-step loop"


def _problem(name: str):
    """(system, x0, mode0, t1, args, closed-form final state as a function of x0)."""
    import math

    import numpy as np

    import hybridjax as hj

    ex = hj.examples
    if name == "ball":
        p = dict(g=9.8, e=0.8)
        return (ex.bouncing_ball(), [1.0, 0.0], "flight", 3.0, p,
                lambda x: ex.bouncing_ball_closed_form(x[0], x[1], p["g"], p["e"], 3.0)["final_state"])
    if name == "thermostat":
        p = dict(a=0.1, T_amb=5.0, P_heat=2.5, P_cool=2.0, s=20.0)
        return (ex.thermostat(), [19.0], "off", 40.0, p,
                lambda x: ex.thermostat_closed_form(x[0], "off", p, 40.0)["final_state"])
    if name == "wall":
        p = dict(g=9.8, w=2.0, c=0.7)
        return (ex.wall_particle(), [0.0, 1.0, 1.5, 3.0], "flight", 3.0, p,
                lambda x: ex.wall_particle_closed_form(x, p, 3.0)["final_state"])
    if name == "lif":
        p = dict(I=1.5, tau=0.02)

        def lif(x, t1=0.5):
            spikes = np.asarray(ex.integrate_and_fire_closed_form(p["I"], p["tau"], x[0], 200))
            fired = spikes[spikes <= t1]
            t_last, v_last = (fired[-1], 0.0) if fired.size else (0.0, x[0])
            return np.array([p["I"] + (v_last - p["I"]) * math.exp(-(t1 - t_last) / p["tau"])])

        return ex.integrate_and_fire(), [0.0], "subthreshold", 0.5, p, lif
    raise ValueError(name)


def _sizes(lowered, compiled) -> dict:
    text = lowered.as_text()
    op = re.compile(r"^\s*(%[\w#:]+(, %[\w#:]+)* = )?\"?(stablehlo|chlo|func|mhlo|sdy|shardy)\.")
    hlo = compiled.as_text() or ""
    instr = re.compile(r"^\s*(ROOT )?%?[\w.\-]+ = ")
    return dict(stablehlo_bytes=len(text.encode()), stablehlo_lines=text.count("\n") + 1,
                stablehlo_ops=sum(1 for line in text.splitlines() if op.match(line)),
                stablehlo_functions=text.count("func.func "),
                stablehlo_while_loops=text.count("stablehlo.while"),
                hlo_instructions=sum(1 for line in hlo.splitlines() if instr.match(line)))


def _errors(call: str, out, x0_list, closed) -> dict:
    """The error against the closed form (derivatives: its central differences)."""
    import numpy as np

    x = np.asarray(x0_list, dtype=float)
    ref = np.asarray(closed(x), dtype=float)

    def cd(f, d, h=1e-6):
        return (np.asarray(f(x + h * d), dtype=float) - np.asarray(f(x - h * d), dtype=float)) / (2 * h)

    if call == "forward":
        return dict(error=float(np.max(np.abs(np.asarray(out)[: ref.size] - ref))))
    if call == "reverse":
        want = np.array([cd(closed, e)[0] for e in np.eye(x.size)])
        return dict(error=float(np.max(np.abs(np.asarray(out) - want))))
    primal, tangent = (np.asarray(o)[: ref.size] for o in out)
    want = cd(closed, np.ones_like(x))
    return dict(error=float(np.max(np.abs(tangent - want))), primal_error=float(np.max(np.abs(primal - ref))))


def _eager_result(fn, inputs, call, x0_list, closed, import_jax_s, import_hj_s) -> dict:
    """The first and second direct calls, timed as wholes (tracing, lowering and compiling inside
    hybridjax are not separated)."""
    import jax

    t = time.perf_counter()
    out = jax.block_until_ready(fn(*inputs))
    first_call_s = time.perf_counter() - t
    first_result_s, first_result_cpu_s = time.perf_counter() - T_START, time.process_time()
    t = time.perf_counter()
    jax.block_until_ready(fn(*inputs))
    second_run_s = time.perf_counter() - t
    return dict(import_jax_s=import_jax_s, import_hybridjax_s=import_hj_s, first_call_s=first_call_s,
                second_run_s=second_run_s, first_result_s=first_result_s, first_result_cpu_s=first_result_cpu_s,
                **_errors(call, out, x0_list, closed))


def one(system: str, call: str, cache: str | None, lock: bool = False, fast: bool = False,
        eager: bool = False) -> dict:
    t = time.perf_counter()
    import jax

    import_jax_s = time.perf_counter() - t
    jax.config.update("jax_enable_x64", True)
    if cache:
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    t = time.perf_counter()
    import diffrax
    import jax.numpy as jnp

    # `import_hybridjax_s`: the second import, hybridjax's (with diffrax), or diffrax's alone in
    # a lock-step process: its user imports jax and diffrax, and the process imports hybridjax
    # (for the problem's definition and closed form) and the baselines' module outside the times
    # it reports.
    import_hj_s = time.perf_counter() - t
    assert not (lock and eager), "the direct call is hybridjax's"
    t, c = time.perf_counter(), time.process_time()
    import hybridjax as hj

    if lock:
        from _baselines import diffrax_epoch_scan
    untimed_s, untimed_cpu_s = (time.perf_counter() - t, time.process_time() - c) if lock else (0.0, 0.0)
    import_hj_s += 0.0 if lock else time.perf_counter() - t

    sysm, x0_list, mode0, t1, p, closed = _problem(system)
    x0 = jnp.asarray(x0_list, dtype=jnp.float64)
    args = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in p.items()}
    v = jnp.ones_like(x0)

    if lock:
        def final(x, a, adjoint=None):
            run = diffrax_epoch_scan(sysm, solver=diffrax.Tsit5(), controller=diffrax.PIDController(rtol=1e-8, atol=1e-8),
                                     t1=t1, adjoint=adjoint)
            return run(x, sysm.mode_index(mode0), a)
    else:
        def final(x, a, **kw):
            return hj.simulate(sysm, x, mode0, 0.0, t1, a, **kw).final_state

    if eager:
        # Called directly: hybridjax compiles the call (and picks forward mode's adjoint itself).
        if call == "forward":
            fn, inputs = final, (x0, args)
        elif call == "reverse":
            fn, inputs = jax.grad(lambda x, a: final(x, a)[0]), (x0, args)
        else:
            fn, inputs = (lambda x, w, a: jax.jvp(lambda y: final(y, a), (x,), (w,))), (x0, v, args)
        return _eager_result(fn, inputs, call, x0_list, closed, import_jax_s, import_hj_s)
    from hybridjax._solve.eager import FAST_COMPILE_CPU

    jit = functools.partial(jax.jit, compiler_options=FAST_COMPILE_CPU if fast else None)
    if call == "forward":
        fn, inputs = jit(final), (x0, args)
    elif call == "reverse":
        fn, inputs = jit(jax.grad(lambda x, a: final(x, a)[0])), (x0, args)
    else:
        fn = jit(lambda x, w, a: jax.jvp(lambda y: final(y, a, adjoint=diffrax.ForwardMode()), (x,), (w,)))
        inputs = (x0, v, args)

    t, c = time.perf_counter(), time.process_time()
    traced = fn.trace(*inputs)
    trace_s, trace_cpu_s = time.perf_counter() - t, time.process_time() - c
    t, c = time.perf_counter(), time.process_time()
    lowered = traced.lower()
    lower_s, lower_cpu_s = time.perf_counter() - t, time.process_time() - c
    t, c = time.perf_counter(), time.process_time()
    compiled = lowered.compile()
    compile_s, compile_cpu_s = time.perf_counter() - t, time.process_time() - c
    t = time.perf_counter()
    out = jax.block_until_ready(compiled(*inputs))
    first_run_s = time.perf_counter() - t
    first_result_s = time.perf_counter() - T_START - untimed_s
    first_result_cpu_s = time.process_time() - untimed_cpu_s
    t = time.perf_counter()
    jax.block_until_ready(compiled(*inputs))
    second_run_s = time.perf_counter() - t

    errors = _errors(call, out, x0_list, closed)
    res = dict(import_jax_s=import_jax_s, import_hybridjax_s=import_hj_s, trace_s=trace_s, lower_s=lower_s,
               trace_lower_s=trace_s + lower_s, compile_s=compile_s, first_run_s=first_run_s,
               second_run_s=second_run_s, first_result_s=first_result_s, trace_cpu_s=trace_cpu_s,
               lower_cpu_s=lower_cpu_s, compile_cpu_s=compile_cpu_s, first_result_cpu_s=first_result_cpu_s, **_sizes(lowered, compiled), **errors)
    if cache:
        res["cache_entries"] = len(os.listdir(cache))
    return res


def _run(system: str, call: str, cache: str | None = None, lock: bool = False, fast: bool = False,
         eager: bool = False) -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--one", system, call] + (["--cache", cache] if cache else [])
    cmd += ["--lock"] * lock + ["--fast"] * fast + ["--eager"] * eager
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=os.path.dirname(os.path.abspath(__file__)))
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        print(proc.stderr[-3000:], file=sys.stderr)
        return dict(failed=proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "failed",
                    process_s=wall)
    return dict(json.loads(proc.stdout.splitlines()[-1]), process_s=wall)


def _pairs(system: str, call: str, pairs: int) -> dict:
    """The direct call and the lock-step loop (not for the wall particle) in `pairs` alternating
    fresh processes, so that the machine's drift touches both alike: {name: the best run (least
    time to the first result), with `first_result_runs_s`, every run's}."""
    ways = {EAGER: dict(eager=True)} | ({LOCK: dict(lock=True)} if system != "wall" else {})
    runs = {name: [] for name in ways}
    for _ in range(pairs):
        for name, how in ways.items():
            runs[name].append(_run(system, call, **how))
    rows = {}
    for name, rs in runs.items():
        done = [r for r in rs if "failed" not in r]
        rows[name] = (dict(min(done, key=lambda r: r["first_result_s"]),
                           first_result_runs_s=[r["first_result_s"] for r in done]) if done else rs[-1])
        _print_row(system, call, f"{name}, best of {len(done)}", rows[name])
    return rows


def _print_row(system, call, name, r):
    if "failed" in r:
        print(f"{system:10s} {call:7s} {name:22s} FAILED: {r['failed']}", flush=True)
        return
    if "trace_s" not in r:  # a direct call: its first call as a whole
        print(f"{system:10s} {call:7s} {name:22s} {r['import_jax_s'] + r['import_hybridjax_s']:6.2f}s "
              f"{'first call':>25s} {r['first_call_s']:7.2f}s {r['first_result_s']:8.2f}s {'':33s} "
              f"{r['error']:9.1e}", flush=True)
        return
    print(f"{system:10s} {call:7s} {name:22s} {r['import_jax_s'] + r['import_hybridjax_s']:6.2f}s "
          f"{r['trace_s']:6.2f}s {r['lower_s']:6.2f}s {r['compile_s']:7.2f}s {r['first_run_s']:7.3f}s "
          f"{r['first_result_s']:7.2f}s {r['stablehlo_bytes'] / 1e6:6.2f}MB {r['stablehlo_ops']:7d} "
          f"{r['hlo_instructions']:7d} {r['error']:9.1e}", flush=True)


def main():
    from _common import machine_info, write_json

    systems = SYSTEMS
    if "--systems" in sys.argv:
        systems = tuple(s for s in sys.argv[sys.argv.index("--systems") + 1:] if s in SYSTEMS)
    print(f"{'system':10s} {'call':7s} {'process':22s} {'import':>7s} {'trace':>7s} {'lower':>7s} {'XLA':>8s} "
          f"{'1st run':>8s} {'total':>8s} {'StableHLO':>8s} {'ops':>7s} {'HLO':>7s} {'error':>9s}", flush=True)
    import jax

    import hybridjax as hj
    from hybridjax._solve.eager import FAST_COMPILE_CPU

    jax.config.update("jax_enable_x64", True)
    pairs = int(sys.argv[sys.argv.index("--pairs") + 1]) if "--pairs" in sys.argv else 5
    compileall.compile_dir(os.path.dirname(hj.__file__), quiet=1)  # as `pip install` leaves the package
    payload = dict(machine=machine_info(), systems=list(systems), calls=list(CALLS), processes=list(PROCESSES),
                   fast_compile=FAST_COMPILE_CPU, pairs=pairs, rows={})
    for system in systems:
        for call in CALLS:
            rows = {PROCESSES[0]: _run(system, call)}
            _print_row(system, call, PROCESSES[0], rows[PROCESSES[0]])
            with tempfile.TemporaryDirectory() as cache:
                for name in PROCESSES[1:]:
                    rows[name] = _run(system, call, cache)
                    _print_row(system, call, name, rows[name])
            rows.update(_pairs(system, call, pairs))
            runs = {FAST: dict(fast=True)} | ({f"{LOCK}, {FAST}": dict(lock=True, fast=True)} if system != "wall" else {})
            for name, how in runs.items():
                rows[name] = _run(system, call, **how)
                _print_row(system, call, name, rows[name])
            payload["rows"].setdefault(system, {})[call] = rows
            path = write_json("first_call", payload)  # after every row: a partial run keeps what it measured
    print("wrote", path)


if __name__ == "__main__":
    if "--one" in sys.argv:
        i = sys.argv.index("--one")
        cache = sys.argv[sys.argv.index("--cache") + 1] if "--cache" in sys.argv else None
        print(json.dumps(one(sys.argv[i + 1], sys.argv[i + 2], cache, lock="--lock" in sys.argv,
                             fast="--fast" in sys.argv, eager="--eager" in sys.argv)))
    else:
        main()
