"""Where the run time goes on one CPU core, by part of the execution semantics.

Problems A (the ball, 10,000 executions), C (thermostat) and B (Van der Pol relay, 2,000 each),
Tsit5, rtol = atol = 1e-9, on one JAX CPU device: hybridjax's batched engine (`simulate_batch`,
`devices=1`), `jax.vmap(hj.simulate)` and the plain diffrax lock-step loop, and for the ball the
bare hand-written loop (`_baselines`). Each way is compiled once, timed (best of `--repeat`
runs), then traced with `jax.profiler` for `--traced` runs.

XLA:CPU runs a program as a sequence of *thunks* (one per fusion, gather, scatter, copy or
library call; a while loop or conditional runs the thunks of its body). Each thunk of the
trace is matched to its instruction in the compiled program, and the instruction to the
innermost function of its source stack frames (the program's own stack-frame table) that names
a part of the semantics (`PARTS`): the solver's step, the guard samples, the root search, the
epoch-start test, the gathering of a block of lanes, and so on. Instructions without source
frames (the loops' copies of their state; in the program, also the fusions' parameters and
constants) are *copies and loop control*. The thunks run on two threads (XLA's intra-op pool),
so thread time can exceed the run's wall time: the parts are compared as shares of thread time.
Tracing adds a cost to every thunk (a run of many small thunks traces several times slower),
so the traced run is timed too, and each part comes with its thunks: a part of many small
thunks is overstated. Per way, also the thunks per run and their mean thread time, and the
steps and events of the run (hybridjax's own counts), from which the thread time of the rare
work (all but the step) per event.

The same attribution counts the instructions of the ball's first-call programs (one
execution, `jax.jit(simulate)` and `jax.jit(jax.grad(...))`, as on the first-call page): the
program XLA compiles, by part, and its kernels (fusions and copies, `kernels_of`) by part.

    python benchmarks/cpu_profile.py [--problems ball,thermostat,vdp_relay] [--n N] [--repeat 7] [--traced 3]
    # writes results/cpu_profile.json
"""

import argparse
import collections
import glob
import os
import re
import tempfile
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import problems as P
from _baselines import ball_bare_loop, diffrax_lockstep
from _common import machine_info, write_json
from first_call import _problem
from work_precision import runner, with_constants

import hybridjax as hj

PACKAGE = os.path.dirname(hj.__file__) + os.sep

# (part, functions whose frames mark it: a name, or the end of a qualified name after a dot).
# A thunk's part is that of the innermost function of its stack found here; where none is, the
# stage it runs in (`STAGES`).
PARTS = (
    ("root search", ("locate_root", "root_bracket")),
    ("minimum search (dips)", ("locate_minimum", "event_brackets")),
    ("first event and simultaneity", ("first_event", "simultaneous_set", "resolve_simultaneous")),
    ("event point (implicit function)", ("event_point", "onto_the_guard")),
    ("epoch-start test", ("epoch_start", "_start_lane", "start_decision")),
    ("Zeno detection", ("detect_zeno", "zeno_stage", "zeno_completion")),
    ("event record", ("record", "_record", "flush")),
    ("jump: reset and the next epoch", ("jump", "begin_epoch", "jump_outcome", "_begin_epoch")),
    ("gathering and scattering blocks of lanes", ("_gather_lanes", "_scatter_lanes", "take", "first_lanes",
                                                  "running_count")),
    ("guard samples and crossing tests", ("guard_samples", "_detect", "_samples", "detection",
                                          "needs_location", "dip_interval", "first_crossings",
                                          "dip_candidates")),
    ("solver step and step-size rule", ("explicit_rk_step", "mapped_step", "pid_controller", "error_norm",
                                        "nonfinite_step", "step_end")),
    ("saves, refill and output", ("save", "_save", "save_at_t1", "refill_stage", "fresh", "fields", "init",
                                  "init_record")),
)
STAGES = (
    ("event phase: other (state updates)", ("events", "_event_lane", "resolve_stage", "event_phase")),
    ("epoch-start test", ("start_stage",)),
    ("step: other (state updates)", ("step_stage",)),
    ("loop body: choice of phase, selections", ("body", "due")),
    ("the loop around the body (its condition, equinox's checkpointing)", ("Loop.run", "BatchedLoop.run", "BatchedLoop._run")),
)


def frames_of(hlo: str):
    """{instruction: [hybridjax's function names in its stack, innermost first]} from the
    compiled program's stack-frame table (`FileNames`, `FunctionNames`, `FileLocations`,
    `StackFrames`), and the names of its while, conditional and call instructions (whose trace
    events span the thunks of their bodies)."""
    lines = hlo.splitlines()
    files, funcs, locs, frames, section = {}, {}, {}, {}, None
    for line in lines:
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            section = line
            continue
        if section and not line.strip():
            section = None
            continue
        if section == "FileNames":
            i, name = line.split(" ", 1)
            files[int(i)] = name.strip('"')
        elif section == "FunctionNames":
            i, name = line.split(" ", 1)
            funcs[int(i)] = name.strip('"')  # qualified: `BatchedLoop.step_stage.<locals>.events`
        elif section == "FileLocations":
            m = re.match(r"(\d+) \{file_name_id=(\d+) function_name_id=(\d+)", line)
            # Only hybridjax's own frames name a part (not diffrax's, equinox's or jax's).
            locs[int(m[1])] = funcs[int(m[3])] if files[int(m[2])].startswith(PACKAGE) else None
        elif section == "StackFrames":
            m = re.match(r"(\d+) \{file_location_id=(\d+) parent_frame_id=(\d+)", line)
            # XLA prints each frame's parent one past its id (a frame whose parent is printed as
            # its own id has none): `check_frames` holds this to a known call stack.
            frames[int(m[1])] = (int(m[2]), int(m[3]) - 1)

    def chain(fid):
        out, seen = [], set()
        while fid in frames and fid not in seen:  # innermost first
            seen.add(fid)
            loc, parent = frames[fid]
            if locs[loc] is not None:
                out.append(locs[loc])
            fid = parent
        return out

    out, containers = {}, set()
    for line in lines:
        m = re.match(r"\s+(?:ROOT )?%?([\w.\-]+) = (.*)", line)
        if not m:
            continue
        frame = re.search(r"stack_frame_id=(\d+)", m[2])
        out[m[1]] = chain(int(frame[1])) if frame else None
        if re.search(r"\b(while|conditional|call)\(", m[2]):
            containers.add(m[1])
    return out, containers


def check_frames(chains: dict, outermost: str):
    """Raise unless some instruction's stack reaches from the engines out to `outermost` (the
    function the program was traced from), the check that the stack-frame table was read right."""
    if not any(c and len(c) > 5 and any(f == outermost for f in c) for c in chains.values()):
        raise RuntimeError(f"no stack in the compiled program reaches {outermost!r}: its stack-frame "
                           "table is printed in a form this script does not read")


def part_of(chain: list[str] | None) -> str:
    if chain is None:
        return "copies and loop control"
    if not chain:
        return "code outside hybridjax (diffrax, equinox, jax, the baselines)"
    for table in (PARTS, STAGES):
        for fn in chain:
            for part, names in table:
                if any(fn == name or fn.endswith("." + name) for name in names):
                    return part
    return "other"


def profile(fn, args, traced: int, repeat: int, check: str | None = None) -> dict:
    compiled = fn.lower(*args).compile()
    out = jax.block_until_ready(compiled(*args))
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        best = min(best, time.perf_counter() - t)
    chains, containers = frames_of(compiled.as_text())
    if check:
        check_frames(chains, check)
    with tempfile.TemporaryDirectory() as d:
        traced_s = 0.0
        with jax.profiler.trace(d):
            for _ in range(traced):
                t = time.perf_counter()
                jax.block_until_ready(compiled(*args))
                traced_s += (time.perf_counter() - t) / traced
        data = jax.profiler.ProfileData.from_file(glob.glob(f"{d}/**/*.xplane.pb", recursive=True)[0])
    seconds, count = collections.Counter(), collections.Counter()
    for plane in data.planes:
        for line in plane.lines:
            # Every thread's: XLA's pool runs most thunks, the calling thread some.
            for ev in line.events:
                name = ev.name
                if name not in chains or name in containers:
                    continue
                part = part_of(chains[name])
                seconds[part] += ev.duration_ns * 1e-9 / traced
                count[part] += 1 / traced
    parts = {k: dict(s=v, thunks=round(count[k])) for k, v in seconds.most_common()}
    return dict(run_s=best, traced_run_s=traced_s, thread_s=sum(seconds.values()),
                thunks=round(sum(count.values())), parts=parts), out


# The parts of the rare work (`simulate_batch` runs it on blocks of lanes, `jax.vmap(simulate)`
# in its event phase): the thread time per event of a run is their sum over its events.
RARE = ("root search", "minimum search (dips)", "first event and simultaneity", "event point (implicit function)",
        "epoch-start test", "Zeno detection", "event record", "jump: reset and the next epoch",
        "gathering and scattering blocks of lanes", "event phase: other (state updates)")


def kernels_of(hlo: str) -> list[str]:
    """The instructions of a compiled program that XLA:CPU emits a kernel for: the fusions and
    copies of its unfused computations (the entry, loop bodies and conditions, branches), each
    emitted, compiled and run as a unit of its own (a thunk)."""
    fused = set(re.findall(r"calls=%?([\w.\-]+)", hlo))
    out, current = [], None
    for line in hlo.splitlines():
        head = re.match(r"(?:ENTRY )?%?([\w.\-]+) [({]", line)
        if head:
            current = head[1]
            continue
        m = re.match(r"\s+(?:ROOT )?%?([\w.\-]+) = \S+ (fusion|copy)\(", line)
        if m and current not in fused:
            out.append(m[1])
    return out


def program_parts(fn, *args) -> dict:
    """{part: instructions} of the optimised program XLA compiles for `fn(*args)`, each
    instruction given to a part as the thunks are (`part_of`), and the total; likewise its
    kernels (`kernels_of`)."""
    hlo = fn.lower(*args).compile().as_text()
    chains, _ = frames_of(hlo)
    check_frames(chains, "simulate")
    none = "without source frames (fusions' parameters and constants, tuples, copies)"
    count = collections.Counter(none if c is None else part_of(c) for c in chains.values())
    kernels = collections.Counter(none if chains.get(k) is None else part_of(chains[k]) for k in kernels_of(hlo))
    return dict(total=sum(count.values()), parts=dict(count.most_common()),
                kernels_total=sum(kernels.values()), kernels=dict(kernels.most_common()))


def first_call_programs() -> dict:
    """The programs of one execution of the ball, the first-call page's forward and reverse calls
    on its problem (`first_call._problem`), by part (`program_parts`)."""
    system, x0, mode0, t1, p, _ = _problem("ball")
    x0, args = jnp.asarray(x0, jnp.float64), {k: jnp.asarray(v, jnp.float64) for k, v in p.items()}

    def final(x, a):
        return hj.simulate(system, x, mode0, 0.0, t1, a).final_state

    return {"forward": program_parts(jax.jit(final), x0, args),
            "reverse": program_parts(jax.jit(jax.grad(lambda x, a: final(x, a)[0])), x0, args)}


PROBLEMS = {"ball": (P.ball, 10_000), "thermostat": (P.thermostat, 2_000), "vdp_relay": (P.vdp_relay, 2_000)}


def ways_for(prob, x0, m0) -> dict:
    """{way: (jitted function, its arguments, hybridjax's entry point to check the stacks against)}:
    both engines and the lock-step loop, and for the ball the bare hand-written loop."""
    lock = diffrax_lockstep(prob.system, solver=diffrax.Tsit5(), t1=prob.t1, max_epochs=prob.max_epochs,
                            max_steps=20_000, controller=diffrax.PIDController(rtol=1e-9, atol=1e-9))
    vmapped = runner(prob, "Tsit5", engine="vmap")
    ways = {
        "hybridjax batched engine": (runner(prob, "Tsit5", devices=1), (x0, m0, 1e-9, 1e-12), "simulate_batch"),
        "hybridjax vmap(simulate)": (with_constants(lambda x, m: vmapped(x, m, 1e-9, 1e-12)), (x0, m0),
                                     "simulate"),
        "diffrax lock-step loop": (with_constants(lambda x, m: lock(x, m, prob.args)), (x0, m0), None),
    }
    if prob.name.startswith("A:"):
        bare, (g, e) = ball_bare_loop(), (prob.args["g"], prob.args["e"])
        ways["bare hand-written loop"] = (with_constants(lambda x, m: bare(x, g, e, prob.t1)), (x0, m0), None)
    return ways


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--problems", default="ball,thermostat,vdp_relay", help=", ".join(PROBLEMS))
    ap.add_argument("--n", type=int, default=None, help="executions (default: 10,000 balls, 2,000 otherwise)")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--traced", type=int, default=3)
    a = ap.parse_args()
    res = dict(machine=machine_info(), repeat=a.repeat, traced=a.traced, problems={})
    for key in a.problems.split(","):
        make, n = PROBLEMS[key]
        prob, n = make(), a.n or n
        x0, m0 = (jnp.asarray(v) for v in prob.sample(np.random.default_rng(5), n))
        out_p = res["problems"][prob.name] = dict(n=n, ways={})
        for name, (fn, args, outermost) in ways_for(prob, x0, m0).items():
            r, out = profile(fn, args, a.traced, a.repeat, outermost)
            if hasattr(out, "num_steps"):
                r["steps"] = int(np.sum(out.num_steps))
                r["events"] = int(np.sum(out.num_events))
            out_p["ways"][name] = r
        for name, r in out_p["ways"].items():
            if "steps" in r:
                r["rare_s"] = sum(r["parts"].get(p, {}).get("s", 0.0) for p in RARE)
            counts = f", {r['steps']:,} steps, {r['events']:,} events" if "steps" in r else ""
            print(f"{prob.name}, {name}: run {r['run_s'] * 1e3:.1f} ms (traced {r['traced_run_s'] * 1e3:.1f}), "
                  f"thread time {r['thread_s'] * 1e3:.1f} ms, {r['thunks']:,} thunks{counts}")
            for part, v in r["parts"].items():
                print(f"   {v['s'] * 1e3:8.2f} ms {100 * v['s'] / r['thread_s']:5.1f}%  {v['thunks']:7,} thunks  {part}")
    res["programs"] = first_call_programs()
    for call, prog in res["programs"].items():
        print(f"one ball, {call}: {prog['total']:,} HLO instructions, {prog['kernels_total']:,} kernels")
        for part, k in prog["parts"].items():
            print(f"   {k:7,}  {prog['kernels'].get(part, 0):5,}  {part}")
    print(f"wrote {write_json('cpu_profile', res)}")


if __name__ == "__main__":
    main()
