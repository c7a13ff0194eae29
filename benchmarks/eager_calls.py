"""Calls outside `jax.jit` (as in a notebook): each call's wall time, compiled once or every time.

`simulate` and `simulate_batch` called directly are compiled once per configuration and
reused (`hybridjax._eager`); the plain call they wrap (`hj.simulate.__wrapped__`) traces and
compiles its loops on every call, and is measured beside them. Measured in one process,
on the bouncing ball (e = 0.8, T = 2.5, Tsit5, rtol = atol = 1e-9, float64): `simulate` on one
execution and `simulate_batch` on N = 1,000, four calls each way: three with new initial
states (same shapes), then one with a changed Python number in `args` (g = 9.0), which is
part of the program and compiles a new one. The process's one-off costs (JAX's first trace,
the dense-output weights) are paid by a warm-up run of another problem first. Each result is
checked against the closed form (largest final-state error). Then `monte_carlo` (20,000 balls
with v0 ~ U(-1, 1), two chunks, three runs with new keys), with its kept chunk programs dropped
before each run and kept. Then `periodic_orbit` on the rimless wheel, three slopes given as
arrays (compiled once; it has no plain-call form).

JSON: `rows[function][way]`, a list of calls (`call`, `wall_s`, `max_error`, and `g`,
`gamma` or `compile_s` where they apply); ways "compiled every call" and "compiled once".

    python benchmarks/eager_calls.py     # prints a table, writes results/eager_calls.json
"""

import time

import diffrax
import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from _common import machine_info, write_json  # noqa: E402

import hybridjax as hj  # noqa: E402

CTRL = diffrax.PIDController(rtol=1e-9, atol=1e-9)
BALL = hj.examples.bouncing_ball()
T1 = 2.5


def states(rng, n):
    return np.stack([rng.uniform(0.5, 1.5, n), rng.uniform(-1, 1, n)], 1)


def error(final, x0, g):
    ref = np.array([hj.examples.bouncing_ball_closed_form(h, v, g, 0.8, T1)["final_state"] for h, v in x0])
    return float(np.max(np.abs(np.atleast_2d(np.asarray(final)) - ref)))


def calls(fn, batch: bool, seed: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    out = []
    for k, g in enumerate((9.8, 9.8, 9.8, 9.0)):
        x0 = states(rng, 1000 if batch else 1)
        arg = x0 if batch else x0[0]
        t = time.perf_counter()
        sol = fn(BALL, arg, "flight", 0.0, T1, {"g": g, "e": 0.8}, stepsize_controller=CTRL, max_epochs=32)
        final = jax.block_until_ready(sol.final_state)
        out.append(dict(call=k + 1, g=g, wall_s=time.perf_counter() - t, max_error=error(final, x0, g)))
    return out


def sampler(key, m):
    k1, k2 = jax.random.split(key)
    h = jax.random.uniform(k1, (m,), minval=0.5, maxval=1.5)
    v = jax.random.uniform(k2, (m,), minval=-1.0, maxval=1.0)
    return jax.numpy.stack([h, v], 1), {"g": jax.numpy.full(m, 9.8), "e": jax.numpy.full(m, 0.8)}


def monte_carlo_calls(keep_programs: bool) -> list[dict]:
    """Three `monte_carlo` runs of 20,000 balls (chunks of 10,000), new keys; without
    `keep_programs` the kept programs are dropped before each, so that each compiles."""
    from hybridjax._analysis import montecarlo as _montecarlo

    out = []
    _montecarlo._COMPILED.clear()
    for k in range(3):
        if not keep_programs:
            _montecarlo._COMPILED.clear()
        t = time.perf_counter()
        res = hj.monte_carlo(BALL, sampler, 20_000, mode0="flight", t1=T1, key=jax.random.PRNGKey(k), chunk_size=10_000, keep="all", progress=False,
                             stepsize_controller=CTRL, max_epochs=32)
        wall = time.perf_counter() - t
        x0 = np.asarray(jax.vmap(lambda c: sampler(jax.random.fold_in(jax.random.PRNGKey(k), c), 10_000)[0])(
            jax.numpy.arange(2))).reshape(-1, 2)
        out.append(dict(call=k + 1, wall_s=wall, compile_s=res.compile_s,
                        max_error=error(res.per_execution["final_state"], x0, 9.8)))
    return out


def periodic_orbit_calls() -> list[dict]:
    """Three `periodic_orbit` calls on the rimless wheel (alpha = 0.3; gamma 0.08, 0.1, 0.06,
    given as arrays): the first compiles, the others reuse its programs. Error: the nontrivial
    Floquet multiplier against cos(2 alpha)^2."""
    wheel, out = hj.examples.rimless_wheel(), []
    for k, gamma in enumerate((0.08, 0.1, 0.06)):
        ref = hj.examples.rimless_wheel_closed_form(0.3, gamma)
        t = time.perf_counter()
        orbit = hj.periodic_orbit(wheel, 0, ref["state"] * np.array([1.0, 1.1]),
                                  {"alpha": jax.numpy.asarray(0.3), "gamma": jax.numpy.asarray(gamma)})
        wall = time.perf_counter() - t
        out.append(dict(call=k + 1, gamma=gamma, wall_s=wall,
                        max_error=float(np.min(np.abs(orbit.multipliers_ad - ref["multiplier"])))))
    return out


def main():
    # Warm-up: the process's first trace and compile, on another problem.
    jax.block_until_ready(hj.simulate(hj.examples.thermostat(), np.array([20.0]), "off", 0.0, 5.0,
                                      dict(a=0.1, T_amb=30.0, P_heat=2.5, P_cool=2.0, s=20.0)).final_state)
    rows = {}
    for name, fn, batch in (("simulate", hj.simulate, False), ("simulate_batch (N = 1,000)", hj.simulate_batch, True)):
        rows[name] = {"compiled every call": calls(fn.__wrapped__, batch, 0),
                      "compiled once": calls(fn, batch, 1)}
    rows["monte_carlo (20,000 in 2 chunks)"] = {"compiled every call": monte_carlo_calls(False),
                                                "compiled once": monte_carlo_calls(True)}
    rows["periodic_orbit (rimless wheel)"] = {"compiled once": periodic_orbit_calls()}
    print(f"{'function':34s} {'way':22s} " + " ".join(f"{'call ' + str(k):>9s}" for k in (1, 2, 3))
          + f" {'call 4 (g)':>10s} {'max error':>9s}")
    for name, ways in rows.items():
        for way, cs in ways.items():
            print(f"{name:34s} {way:22s} " + " ".join(f"{c['wall_s']:8.3f}s" for c in cs[:3])
                  + (f" {cs[3]['wall_s']:9.3f}s" if len(cs) > 3 else f"{'-':>11s}")
                  + f" {max(c['max_error'] for c in cs):9.1e}")
    path = write_json("eager_calls", dict(machine=machine_info(), rows=rows))
    print("wrote", path)


if __name__ == "__main__":
    main()
