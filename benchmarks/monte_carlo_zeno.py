"""Monte Carlo of Zeno behaviour: 1,000,000 bouncing balls with random restitution.

h0 ~ U(0.5, 1.5), v0 = 0, e ~ U(0.3, 0.9), g = 9.8, to t1 = 4 (Tsit5, PID 1e-8, float64).
An execution is Zeno before t1 when sqrt(2 h0 / g) (1 + e) / (1 - e) <= t1; the measured
Zeno fraction is compared with the closed-form fraction of the same samples. Reports the
run time, executions/s, peak resident memory and the Zeno fraction with its 95% interval.

Writes results/monte_carlo_zeno.json (the run's figures, the status counts, the Zeno fraction with
its interval and the closed-form fraction, Zeno-time and event-count statistics).

    python benchmarks/monte_carlo_zeno.py [N] [chunk] [lanes]   # default 1,000,000, 50,000, 10,000

Lanes: 10,000 per chunk, refilled as executions end (Zeno executions stop early, at different
times); `simulate_batch`'s own default for a chunk of 50,000 is one lane per execution.
"""

import resource
import sys

import jax
import jax.numpy as jnp
import numpy as np
from _common import machine_info, write_json

import hybridjax as hj

jax.config.update("jax_enable_x64", True)


def sampler(key, m):
    k1, k2 = jax.random.split(key)
    e = jax.random.uniform(k1, (m,), minval=0.3, maxval=0.9)
    h = jax.random.uniform(k2, (m,), minval=0.5, maxval=1.5)
    return jnp.stack([h, 0 * h], 1), {"g": jnp.full((m,), 9.8), "e": e}


def main():
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
    chunk = int(sys.argv[2]) if len(sys.argv) > 2 else 50_000
    lanes = int(sys.argv[3]) if len(sys.argv) > 3 else 10_000
    key = jax.random.PRNGKey(42)
    ball = hj.examples.bouncing_ball()
    res = hj.monte_carlo(ball, sampler, n, mode0="flight", t1=4.0, key=key, chunk_size=chunk,
                         keep="summary", max_epochs=32, lanes=lanes)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    # closed-form Zeno fraction of the very same samples (regenerated chunk by chunk)
    zeno_cf = 0
    n_dev = len(jax.devices())
    size = int(np.ceil(min(chunk, n) / n_dev) * n_dev)  # monte_carlo's chunk shape
    for c in range(res.chunks):
        x0, a = sampler(jax.random.fold_in(key, c), size)
        m = min(size, n - c * size)
        h, e = np.asarray(x0[:m, 0]), np.asarray(a["e"][:m])
        zeno_cf += int(np.sum(np.sqrt(2 * h / 9.8) * (1 + e) / (1 - e) <= 4.0))
    print(res.table())
    frac, (lo, hi) = res.status_fractions["ZENO"]
    print(f"closed-form Zeno fraction of the same samples: {zeno_cf / n:.5f} (measured {frac:.5f}, "
          f"95% interval [{lo:.5f}, {hi:.5f}])")
    print(f"peak resident memory: {peak_mb:.0f} MiB")
    path = write_json("monte_carlo_zeno", dict(
        machine=machine_info(), n=n, chunk=chunk, lanes=lanes, run_s=res.run_s, compile_s=res.compile_s,
        executions_per_s=res.executions_per_s, peak_rss_mib=peak_mb,
        status_counts=res.status_counts, zeno_fraction=frac, zeno_interval=[lo, hi],
        zeno_fraction_closed_form=zeno_cf / n, zeno_time=res.zeno_time, num_events=res.num_events))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
