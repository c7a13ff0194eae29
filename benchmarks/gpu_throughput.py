"""Problem A (the bouncing ball) on one accelerator, N = 10^4 ... 10^7 executions at once.

The ways, in the order each N measures them:

- hybridjax's batched engine, `jax.jit(hj.simulate_batch)` with `engine="batched"` and
  `devices=1`, with its default block (the rare work in passes over N/32 executions) and with
  `block=N` (one pass);
- hybridjax per execution, `jax.jit(jax.vmap(hj.simulate))` (what `simulate_batch` runs on a
  GPU), with the loop's bound on the iterations an execution waits for the event phase
  (`MAX_WAIT`, 16) and with 4 and 64 in its place (the phase's cost is shared by more
  executions the longer they wait, while waiting executions make no steps);
- the plain diffrax lock-step loop (`_baselines.diffrax_lockstep`: a jitted `vmap` of
  `diffeqsolve` + `diffrax.Event`, one solve per epoch);
- the closed form, jitted (`work_precision.ball_closed_form_jax`): no integration at all, the
  speed limit.

Tsit5, rtol = atol = 1e-9, float64, h0 ~ U(0.5, 1.5), v0 ~ U(-1, 1), e = 0.8, T = 2.5 (before the
Zeno point). Per way and N: the compile time (first call less the best run), the best of
`--rounds` runs, executions per second, and the largest error of the final state against the
ball's closed form in numpy (`problems.ball().truth`) on 2,000 executions drawn from the batch
(with the count of those whose number of bounces differs). A way that runs out of the
accelerator's memory is recorded so. The results are written after every measurement, so a
run cut short keeps what it measured. `--ways` measures some of the ways only; `--append` adds
the run to those already in the output file (each run is reported as its own table); the
batched engine (about 3e4 executions/s on a GPU) is measured up to `--batched-max-n`.

    python benchmarks/gpu_throughput.py                      # N = 1e4, 1e5, 1e6, 1e7
    python benchmarks/gpu_throughput.py --n 1000,10000 --out /tmp/t.json
    python benchmarks/gpu_throughput.py --n 1e5,1e6 --ways "block = N;diffrax lock-step loop" --append
"""

import argparse
import json
import os
import pathlib

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import problems as P
from _baselines import diffrax_lockstep
from _common import machine_info, timed
from work_precision import ball_closed_form_jax, errors, runner

import hybridjax as hj
from hybridjax._engines import loop as hj_loop

G, E = 9.8, 0.8
CHECKED = 2000


def ways(prob):
    """{name: (fn of (x0, mode0), reads (num_events, final_state) off its output)}."""
    lock = diffrax_lockstep(prob.system, solver=diffrax.Tsit5(), t1=prob.t1, max_epochs=prob.max_epochs,
                            max_steps=20_000, controller=diffrax.PIDController(rtol=1e-9, atol=1e-9))
    closed = ball_closed_form_jax(prob.max_epochs)
    per_execution = runner(prob, "Tsit5", engine="vmap")

    def waiting(max_wait):
        """vmap(simulate) traced with the loop's phase-wait bound set to `max_wait`."""

        @jax.jit
        def run(x0, mode0):
            default, hj_loop.MAX_WAIT = hj_loop.MAX_WAIT, max_wait
            try:
                return jax.vmap(lambda x, m: hj.simulate(
                    prob.system, x, m, 0.0, prob.t1, prob.args, solver=diffrax.Tsit5(),
                    stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-9), event_tol=1e-12,
                    max_epochs=prob.max_epochs, max_steps=20_000))(x0, mode0)
            finally:
                hj_loop.MAX_WAIT = default

        return run, lambda r: (r.num_events, r.final_state)

    def batched(block):
        @jax.jit
        def run(x0, mode0):
            return hj.simulate_batch(prob.system, x0, mode0, 0.0, prob.t1, prob.args, solver=diffrax.Tsit5(),
                                     stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-9),
                                     event_tol=1e-12, max_epochs=prob.max_epochs, max_steps=20_000, devices=1,
                                     engine="batched", block=x0.shape[0] if block == "N" else None)

        return run, lambda r: (r.num_events, r.final_state)

    return {
        "hybridjax batched engine": batched(None),
        "hybridjax batched engine, block = N": batched("N"),
        "hybridjax vmap(simulate)": (lambda x, m: per_execution(x, m, 1e-9, 1e-12),
                                     lambda r: (r.num_events, r.final_state)),
        "hybridjax vmap(simulate), phase wait 4": waiting(4),
        "hybridjax vmap(simulate), phase wait 64": waiting(64),
        "diffrax lock-step loop": (jax.jit(lambda x, m: lock(x, m, prob.args)), lambda r: (r[1], r[2])),
        "closed form": (jax.jit(lambda x, m: closed(x, G, E, prob.t1)), lambda r: r),
    }


def measure(prob, fn, read, x, m, rounds, idx, truths):
    compile_s, run_s, out = timed(fn, x, m, repeat=rounds)
    ne, fs = (np.asarray(a)[idx] for a in read(out))
    error, wrong = errors(prob, truths, fs, ne)
    return dict(compile_s=compile_s, run_s=run_s, exec_per_s=len(x) / run_s, error=error, wrong=wrong)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", default="10000,100000,1000000,10000000", help="comma-separated batch sizes")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--ways", default="", help="semicolon-separated: measure only the ways whose names end so")
    ap.add_argument("--batched-max-n", type=float, default=1e5, help="largest N for the batched engine")
    ap.add_argument("--append", action="store_true", help="add this run to the output file's runs")
    ap.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "gpu_throughput.json"))
    a = ap.parse_args()
    prob = P.ball()
    sizes = [int(float(s)) for s in a.n.split(",")]
    rng = np.random.default_rng(5)
    x_all, m_all = prob.sample(rng, max(sizes))
    wanted = [w.strip() for w in a.ways.split(";") if w.strip()]
    fns = {k: v for k, v in ways(prob).items() if not wanted or any(w == k or k.endswith(w) for w in wanted)}
    res = dict(machine=machine_info(), commit=os.environ.get("HJ_COMMIT", ""), rounds=a.rounds, checked=CHECKED, rows={})
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    runs = json.loads(out.read_text())["runs"] if a.append and out.exists() else []
    runs.append(res)
    for n in sizes:
        idx = np.sort(rng.choice(n, min(n, CHECKED), replace=False))
        truths = [prob.truth(x_all[i], m_all[i]) for i in idx]
        x, m = jnp.asarray(x_all[:n]), jnp.asarray(m_all[:n])
        for name, (fn, read) in fns.items():
            if "batched" in name and n > a.batched_max_n:
                continue
            try:
                row = measure(prob, fn, read, x, m, a.rounds, idx, truths)
            except Exception as err:  # out of the accelerator's memory: recorded, the next way goes on
                if "RESOURCE_EXHAUSTED" not in str(err) and "out of memory" not in str(err).lower():
                    raise
                row = dict(out_of_memory=True)
            res["rows"].setdefault(name, {})[str(n)] = row
            out.write_text(json.dumps(dict(runs=runs), indent=1))
            shown = (f"{row['exec_per_s']:12.4g} exec/s, compile {row['compile_s']:6.1f} s, error "
                     f"{row['error']:.1e}, wrong {row['wrong']}" if "run_s" in row else "out of memory")
            print(f"N = {n:>9d}  {name:<26s} {shown}", flush=True)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
