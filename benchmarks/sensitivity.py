"""Global sensitivity at scale: Sobol' indices of the bouncing ball from 10^6 executions.

Parameters h0 ~ U(0.5, 1.5), g ~ U(5, 15) (v0 = 0, e = 0.8), to T = 1.5 (Tsit5, PID 1e-8,
float64); outputs: the first impact time t1 = sqrt(2 h0 / g) and the number of impacts before
T (discrete). Saltelli's scheme with n base samples runs n (d + 2) = 4 n executions, in chunks;
the indices are compared with the closed form (t1) and a quadrature (the count). Reports the
executions/s of the model (compile excluded), the compile time, the bootstrap time and the
peak resident memory of the process.

Writes results/sensitivity.json.

    python benchmarks/sensitivity.py [log2 n] [chunk]   # default 18 (1,048,576 executions), 50,000
"""

import resource
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from _common import machine_info, write_json

import hybridjax as hj

jax.config.update("jax_enable_x64", True)

E, T = 0.8, 1.5
BOUNDS = np.array([[0.5, 1.5], [5.0, 15.0]])


def inputs(theta):
    return jnp.stack([theta[0], jnp.zeros_like(theta[0])]), {"g": theta[1], "e": E}


def outputs(sol):
    return jnp.stack([sol.event_times[:, 0], sol.num_events.astype(sol.event_times.dtype)], axis=1)


def reference(grid=2000):
    """t1: closed form (a product of independent factors); count: midpoint quadrature."""
    (a, b), (c, d) = BOUNDS
    Eu, Eu2 = (2 / 3) * (b**1.5 - a**1.5) / (b - a), (a + b) / 2
    Ew, Ew2 = 2 * (d**0.5 - c**0.5) / (d - c), np.log(d / c) / (d - c)
    V = Eu2 * Ew2 - (Eu * Ew) ** 2
    Vh, Vg = (Eu2 - Eu**2) * Ew**2, (Ew2 - Ew**2) * Eu**2
    t1_ref = ([Vh / V, Vg / V], [1 - Vg / V, 1 - Vh / V])
    h = a + (np.arange(grid) + 0.5) / grid * (b - a)
    g = c + (np.arange(grid) + 0.5) / grid * (d - c)
    t1 = np.sqrt(2 * h[:, None] / g[None, :])
    N = sum((t1 * (1 + 2 * E * (1 - E ** (k - 1)) / (1 - E)) <= T).astype(float) for k in range(1, 40))
    V = N.var()
    Vh, Vg = N.mean(axis=1).var(), N.mean(axis=0).var()
    return t1_ref, ([Vh / V, Vg / V], [1 - Vg / V, 1 - Vh / V])


def main():
    log2n = int(sys.argv[1]) if len(sys.argv) > 1 else 18
    chunk = int(sys.argv[2]) if len(sys.argv) > 2 else 50_000
    model = hj.execution_model(hj.examples.bouncing_ball(), inputs, outputs, t1=T)
    options = hj.SensitivityOptions(chunk_size=chunk, n_bootstrap=200)
    t = time.perf_counter()
    res = hj.sobol_indices(model, BOUNDS, 2**log2n, names=("h0", "g"), options=options)
    wall = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    ref = reference()
    print(res.table(("t1", "bounces before T")))
    print(f"{res.evaluations} executions: {res.run_s:.2f} s run, {res.executions_per_s:,.0f} executions/s, "
          f"{res.compile_s:.1f} s compile, {wall:.1f} s in all, peak RSS {peak:.0f} MiB")
    payload = dict(
        machine=machine_info(), n_base=res.n, executions=res.evaluations, chunk=chunk,
        run_s=res.run_s, executions_per_s=res.executions_per_s, wall_s=wall,
        compile_s=res.compile_s, bootstrap_and_sampling_s=wall - res.run_s - res.compile_s, peak_rss_mib=peak,
        outputs=["t1", "bounces before T"], names=list(res.names),
        first_order=res.first_order.tolist(), total=res.total.tolist(),
        first_order_interval=res.first_order_interval.tolist(), total_interval=res.total_interval.tolist(),
        reference_first_order=[ref[0][0], ref[1][0]], reference_total=[ref[0][1], ref[1][1]],
    )
    print(write_json("sensitivity", payload))


if __name__ == "__main__":
    main()
