"""Where the device time of problem A goes: `jax.vmap(hj.simulate)` and the plain diffrax
lock-step loop, one traced run each, device time by control-flow region.

Each kernel of a `jax.profiler` trace is attributed to its HLO instruction (the trace's `hlo_op`,
or a kernel name whose last `_` stands for the instruction name's `.`), and the instruction to
the control-flow path of its `op_name` (`while/body/cond/branch_1_fun/...`): the event phase, the
root and minimum searches and the hot step are separate regions of that path. Only leaf kernels
are summed (a `while` or `conditional` instruction's own event spans its body). On a GPU the
run's time beyond the kernels' sum is spent outside them: kernel launches, and the host's reads of
each conditional's predicate and each while loop's condition. On a CPU the thunks of nested
computations overlap in the trace, and the regions' sums can exceed the run: read them as shares.

    python benchmarks/gpu_profile.py                  # N = 1e6; results/gpu_profile.json
    python benchmarks/gpu_profile.py --n 1e4 --depth 8
"""

import argparse
import collections
import glob
import gzip
import json
import pathlib
import re
import tempfile
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import problems as P
from _baselines import diffrax_lockstep
from _common import machine_info

import hybridjax as hj

jax.config.update("jax_enable_x64", True)
CONTROL = ("while", "cond", "branch_", "body", "checkpointed", "closed_call", "eval_jaxpr", "root_find")


def ways(prob):
    ctrl = diffrax.PIDController(rtol=1e-9, atol=1e-9)
    lock = diffrax_lockstep(prob.system, solver=diffrax.Tsit5(), t1=prob.t1, max_epochs=prob.max_epochs,
                            max_steps=20_000, controller=ctrl)

    def one(x, m):
        return hj.simulate(prob.system, x, m, 0.0, prob.t1, prob.args, solver=diffrax.Tsit5(),
                           stepsize_controller=ctrl, max_epochs=prob.max_epochs, max_steps=20_000,
                           event_tol=1e-12).final_state

    return {"hybridjax vmap(simulate)": jax.jit(jax.vmap(one)),
            "diffrax lock-step loop": jax.jit(lambda x, m: lock(x, m, prob.args)[2])}


def instructions(compiled_text: str) -> tuple[dict, set]:
    """{instruction name: op_name} and the names of while and conditional instructions. An
    instruction without metadata of its own (a fusion of ops from several places) takes that of
    the first instruction with metadata in the computation it calls."""
    names, containers, calls, first_in = {}, set(), {}, {}
    computation = None
    for line in compiled_text.splitlines():
        head = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{$", line)
        if head:
            computation = head.group(1)
            continue
        m = re.match(r"\s+(?:ROOT )?%?([\w.\-]+) = (.*)", line)
        if not m:
            continue
        meta = re.search(r"metadata=\{op_name=\"([^\"]*)\"", m.group(2))
        if meta:
            names[m.group(1)] = meta.group(1)
            first_in.setdefault(computation, meta.group(1))
        else:
            callee = re.search(r"calls=%?([\w.\-]+)", m.group(2))
            if callee:
                calls[m.group(1)] = callee.group(1)
        if re.search(r"\b(while|conditional)\(", m.group(2)):
            containers.add(m.group(1))
    for name, callee in calls.items():
        if callee in first_in:
            names[name] = first_in[callee]
    return names, containers


def region(op_name: str, depth: int) -> str:
    return "/".join([t for t in op_name.split("/") if t.startswith(CONTROL)][:depth]) or "(top)"


def device_timeline(events: list) -> dict:
    """The device's side of a trace: per stream-event kind (kernels, copies, sets) the count and
    time, the time the device was busy (union of its events' spans) and the gaps between them.

    Device events are those of a trace process named after the accelerator (`/device:GPU:0`);
    on a CPU there are none. A gap is idle device time inside the run: kernel launches, and the
    host's reads of each conditional's predicate and each while loop's condition."""
    names = {e["pid"]: (e.get("args") or {}).get("name", "") for e in events
             if e.get("ph") == "M" and e.get("name") == "process_name"}
    dev = [e for e in events if e.get("ph") == "X" and "GPU" in names.get(e.get("pid"), "")]
    kinds = collections.Counter()
    times = collections.Counter()
    for e in dev:
        low = e["name"].lower()
        kind = "memcpy" if "memcpy" in low else "memset" if "memset" in low else "kernel"
        kinds[kind] += 1
        times[kind] += e.get("dur", 0) * 1e-6
    spans = sorted((e["ts"], e["ts"] + e.get("dur", 0)) for e in dev)
    busy, gaps, gap_s, end = 0.0, 0, 0.0, None
    for a, b in spans:
        if end is not None and a > end:
            gaps += (a - end) > 5
            gap_s += (a - end) * 1e-6
        if end is None or a > end:
            busy += (b - a) * 1e-6
        elif b > end:
            busy += (b - end) * 1e-6
        end = b if end is None else max(end, b)
    first = spans[0][0] if spans else 0.0
    return dict(processes=sorted(set(names.values())), count=dict(kinds), seconds=dict(times), busy_s=busy, gaps_over_5us=gaps, gap_s=gap_s,
                span_s=((end or 0.0) - first) * 1e-6)


def profile(fn, x, m, depth: int) -> dict:
    jax.block_until_ready(fn(x, m))
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        jax.block_until_ready(fn(x, m))
        best = min(best, time.perf_counter() - t)
    names, containers = instructions(fn.lower(x, m).compile().as_text())
    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d):
            jax.block_until_ready(fn(x, m))
        events = json.load(gzip.open(glob.glob(f"{d}/**/*.trace.json.gz", recursive=True)[0]))
    events = events["traceEvents"] if isinstance(events, dict) else events
    by_region, by_op, calls, unmapped = (collections.Counter() for _ in range(4))
    # On an accelerator, only its own events are kernels (the host's carry the same names).
    procs = {e["pid"]: (e.get("args") or {}).get("name", "") for e in events
             if e.get("ph") == "M" and e.get("name") == "process_name"}
    on_device = any("GPU" in v for v in procs.values())
    for e in events:
        if e.get("ph") != "X" or (on_device and "GPU" not in procs.get(e.get("pid"), "")):
            continue
        op = (e.get("args") or {}).get("hlo_op") or e["name"]
        if op not in names and "_" in op:
            op = "{}.{}".format(*op.rsplit("_", 1)) if op.rsplit("_", 1)[1].isdigit() else op
        if op not in names:
            unmapped[e["name"]] += e.get("dur", 0)
            continue
        if op in containers:
            continue
        by_region[region(names[op], depth)] += e.get("dur", 0)
        by_op[op] += e.get("dur", 0)
        calls[op] += 1
    kernels_s = sum(by_op.values()) * 1e-6
    return dict(
        device=device_timeline(events),
        run_s=best,
        kernels_s=kernels_s,
        kernel_calls=sum(calls.values()),
        regions={k: v * 1e-6 for k, v in by_region.most_common()},
        top=[dict(op=k, s=v * 1e-6, calls=calls[k], op_name=names[k]) for k, v in by_op.most_common(25)],
        unmapped={k: v * 1e-6 for k, v in unmapped.most_common(20)},
    )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", default="1e6", help="executions")
    ap.add_argument("--depth", type=int, default=6, help="control-flow levels a region keeps")
    ap.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "gpu_profile.json"))
    a = ap.parse_args()
    prob = P.ball()
    n = int(float(a.n))
    x, m = (jnp.asarray(v) for v in prob.sample(np.random.default_rng(0), n))
    res = dict(machine=machine_info(), n=n, depth=a.depth, ways={})
    for name, fn in ways(prob).items():
        r = res["ways"][name] = profile(fn, x, m, a.depth)
        print(f"{name}: run {r['run_s'] * 1e3:.1f} ms, kernels {r['kernels_s'] * 1e3:.1f} ms "
              f"({r['kernel_calls']} calls)")
        print(f"  device: {r['device']}")
        for k, v in list(r["regions"].items())[:12]:
            print(f"  {v * 1e3:9.2f} ms  {k}")
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
