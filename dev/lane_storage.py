"""The batched engine's lane storage, measured on a synthetic loop: one array per field against
the fields packed into one array.

The batched engine keeps each field of its lanes (`_engines/lanes.py`, `Lanes`) in an array of
its own and does the rare work on blocks of lanes: each pass gathers every field it reads at the
block's lanes and scatters every field it changes back, one gather or scatter per field
(`_gather_lanes`, `_scatter_lanes`). With the fields stacked in one (fields, N) array a pass
gathers and scatters once. This script times three loops of the same shape as the engine's, on
float64 fields: `--iterations` iterations, each an N-wide update of every field (the step) and
`--passes` passes over blocks of `--block` lanes (gather, an update that reads every field,
scatter):

- `separate`: one array per field, as the engine stores them;
- `packed per iteration`: the fields stacked before the passes and split after them, so that the
  passes gather and scatter once (what a change inside the event stage alone can do);
- `stored packed`: the fields stored stacked throughout (the loop's carry one array).

Compiled once each, run in alternating rounds in one process, best of `--rounds`. A tool for a
change to the engine's storage, not a benchmark of hybridjax: it writes nothing.

    python dev/lane_storage.py                       # 35 fields, 7 passes per iteration
    python dev/lane_storage.py --fields 20 --passes 3
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax


def loops(n: int, block: int, passes: int, iterations: int, fields: int):
    """The three loops, each a jitted function of its storage."""
    rng = np.random.default_rng(0)
    idxs = jnp.asarray(np.stack([np.sort(rng.choice(n, block, replace=False)) for _ in range(passes)]), jnp.int32)

    def step(x):  # the N-wide update of every field
        return x * 0.999 + 1e-3

    def update(g, total):  # a block's update that reads every field
        return g * 0.5 + total * 1e-3

    @jax.jit
    def separate(fs):
        def iteration(_, fs):
            fs = [step(f) for f in fs]

            def one_pass(p, fs):
                g = [jnp.take(f, idxs[p], mode="clip") for f in fs]
                total = sum(g)
                return [f.at[idxs[p]].set(update(x, total), mode="drop") for f, x in zip(fs, g, strict=True)]

            return lax.fori_loop(0, passes, one_pass, fs)

        return lax.fori_loop(0, iterations, iteration, fs)

    def packed_passes(a):
        def one_pass(p, a):
            g = jnp.take(a, idxs[p], axis=1, mode="clip")
            return a.at[:, idxs[p]].set(update(g, g.sum(0)), mode="drop")

        return lax.fori_loop(0, passes, one_pass, a)

    @jax.jit
    def packed_per_iteration(fs):
        def iteration(_, fs):
            a = packed_passes(jnp.stack([step(f) for f in fs]))
            return [a[k] for k in range(fields)]

        return lax.fori_loop(0, iterations, iteration, fs)

    @jax.jit
    def stored_packed(a):
        return lax.fori_loop(0, iterations, lambda _, a: packed_passes(step(a)), a)

    return separate, packed_per_iteration, stored_packed


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=10_000, help="lanes")
    ap.add_argument("--block", type=int, default=312, help="lanes per pass (the engine's default: n/32)")
    ap.add_argument("--passes", type=int, default=7, help="passes per iteration")
    ap.add_argument("--iterations", type=int, default=21)
    ap.add_argument("--fields", type=int, default=35, help="float64 rows gathered and scattered per pass")
    ap.add_argument("--rounds", type=int, default=15)
    a = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    separate, per_iteration, stored = loops(a.n, a.block, a.passes, a.iterations, a.fields)
    fs = [jnp.arange(a.n, dtype=jnp.float64) + k for k in range(a.fields)]
    ways = {"separate": (separate, fs), "packed per iteration": (per_iteration, fs),
            "stored packed": (stored, jnp.stack(fs))}
    outs = {name: jnp.stack(jax.block_until_ready(fn(x))) for name, (fn, x) in ways.items()}
    for out in outs.values():  # the same arithmetic in each layout
        np.testing.assert_allclose(np.asarray(out), np.asarray(outs["separate"]), rtol=1e-12)
    times = {name: [] for name in ways}
    for _ in range(a.rounds):
        for name, (fn, x) in ways.items():
            t = time.perf_counter()
            jax.block_until_ready(fn(x))
            times[name].append(time.perf_counter() - t)
    base = min(times["separate"])
    print(f"{a.fields} fields, N = {a.n:,}, {a.iterations} iterations of {a.passes} passes of {a.block} lanes "
          f"(best of {a.rounds}):")
    for name, ts in times.items():
        print(f"  {name:<22} {min(ts) * 1e3:8.2f} ms  {min(ts) / base:5.2f}x separate  "
              f"({min(ts) / (a.iterations * a.passes) * 1e6:6.1f} us per pass, step included)")


if __name__ == "__main__":
    main()
