"""What watching guards costs per step, on the batched engine and under `jax.vmap(simulate)`,
against a bare hand-written loop.

A harmonic oscillator x'' = -4 x (N = 10,000 executions, x0 ~ U(0.5, 1.5), v0 ~ U(-1, 1),
to T = 2.5, Tsit5, rtol = atol = 1e-9, float64: ~70 steps each, the same steps in every
row) with no transition, with one transition whose guard never fires (x + 1000: sampled at
every step, never located), and that guard with fewer interior samples; then the bouncing
ball of problem A; each on `jax.jit(hj.simulate_batch)` (the batched engine) and on
`jax.jit(jax.vmap(hj.simulate))` (the per-execution loop, the path a GPU runs); and the ball on
the bare loop of `_baselines.ball_bare_loop`. Time per step = run time / the largest step
count (every lane steps in every iteration until the slowest is done). Same process, best of
7, alternating.

Twice, each in a fresh process (JAX reads `XLA_FLAGS` once; the script re-runs itself with
`--one`): with XLA's defaults, and with `--xla_cpu_experimental_ynn_fusion_type=` (XLA:CPU in
jaxlib 0.10 hands reductions, dot products among them, to YNNPACK, in calls that do not fuse
with their inputs; the flag turns that off). hybridjax's own loops write their small
reductions out, so the setting moves only code that reduces (a user's flow that sums over
components, `jnp.sum(x)` or `x @ w`, pays that price).

    python benchmarks/guard_cost.py      # prints a table, writes results/guard_cost.json
"""

import json
import sys
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import problems as P
from _baselines import ball_bare_loop
from _common import machine_info, run_per_setting, write_json

import hybridjax as hj

jax.config.update("jax_enable_x64", True)
N, T = 10_000, 2.5
CTRL = diffrax.PIDController(rtol=1e-9, atol=1e-9)


def oscillator(guarded: bool) -> hj.HybridSystem:
    mode = hj.Mode("swing", flow=lambda t, x, a: jnp.array([x[1], -4.0 * x[0]]), dim=2)
    never = hj.Transition("swing", "swing", guard=lambda t, x, a: x[0] + 1e3, reset=lambda t, x, a: x,
                          name="never")
    return hj.HybridSystem([mode], [never] if guarded else [])


SETTINGS = {"default": "", "YNNPACK fusions off": "--xla_cpu_experimental_ynn_fusion_type="}


def one() -> list[dict]:
    rng = np.random.default_rng(0)
    x0 = jnp.asarray(np.stack([rng.uniform(0.5, 1.5, N), rng.uniform(-1, 1, N)], 1))
    m0 = jnp.zeros(N, jnp.int32)
    ball = P.ball()

    def engine(system, t1, args, **kw):
        return jax.jit(lambda x, m: hj.simulate_batch(system, x, m, 0.0, t1, args, stepsize_controller=CTRL,
                                                      max_epochs=32, max_steps=20_000, **kw))

    def vmapped(system, t1, args, **kw):
        return jax.jit(jax.vmap(lambda x, m: hj.simulate(system, x, m, 0.0, t1, args, stepsize_controller=CTRL,
                                                         max_epochs=32, max_steps=20_000, **kw)))

    bare = ball_bare_loop()
    cases = {}
    for way, make in (("batched engine", engine), ("jax.vmap(simulate)", vmapped)):
        cases |= {
            f"oscillator, no transition; {way}": make(oscillator(False), T, None),
            f"oscillator, 1 guard never firing, interior_points=4 (default); {way}": make(oscillator(True), T, None),
            f"oscillator, 1 guard never firing, interior_points=0; {way}": make(oscillator(True), T, None,
                                                                               interior_points=0),
            f"ball (problem A); {way}": make(ball.system, ball.t1, ball.args),
        }
    cases["ball (problem A); bare loop"] = lambda x, m: bare(x, 9.8, 0.8, ball.t1)
    outs = {k: jax.block_until_ready(f(x0, m0)) for k, f in cases.items()}
    best = dict.fromkeys(cases, np.inf)
    for _ in range(7):
        for k, f in cases.items():
            t = time.perf_counter()
            jax.block_until_ready(f(x0, m0))
            best[k] = min(best[k], time.perf_counter() - t)
    rows = []
    for k, out in outs.items():
        steps = int(np.max(out.num_steps)) if hasattr(out, "num_steps") else None
        rows.append(dict(case=k, run_s=best[k], exec_per_s=N / best[k], max_steps=steps,
                         per_step_s=best[k] / steps if steps else None))
    return rows


def main():
    settings = {name: dict(flags=SETTINGS[name], rows=r) for name, r in run_per_setting(__file__, SETTINGS).items()}
    print(f"{'case':88s} {'setting':20s} {'run ms':>8s} {'max steps':>9s} {'us/step':>8s}")
    for name, s in settings.items():
        for row in s["rows"]:
            steps = row["max_steps"]
            per = f"{row['per_step_s'] * 1e6:8.0f}" if steps else f"{'':8s}"
            print(f"{row['case']:88s} {name:20s} {row['run_s'] * 1e3:8.1f} {steps if steps else '':>9} {per}")
    path = write_json("guard_cost", dict(machine=machine_info(), n=N, rows=settings["default"]["rows"],
                                         settings=settings))
    print(f"wrote {path}")


if __name__ == "__main__":
    if "--one" in sys.argv:
        print(json.dumps(one()))
    else:
        main()
