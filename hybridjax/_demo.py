"""`python -m hybridjax demo`: batches of bouncing balls and thermostats, timed and checked.

Runs `jax.jit(simulate_batch)` (the batched engine) over N executions of each example,
compares every execution with its closed form, prints a table and writes a PNG of a few
executions coloured by mode.
"""

import argparse
import os
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from . import examples
from ._core.status import STATUS_NAMES
from ._solve.simulate_batch import simulate_batch


def _timed(fn, *inputs, repeat: int = 3):
    """(output, compile seconds, run seconds): the first call less the best of `repeat` more
    (single runs on a shared machine vary)."""
    t = time.perf_counter()
    out = jax.block_until_ready(fn(*inputs))
    first = time.perf_counter() - t
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        out = jax.block_until_ready(fn(*inputs))
        best = min(best, time.perf_counter() - t)
    return out, max(first - best, 0.0), best


def _status_tally(sol) -> str:
    codes, counts = np.unique(np.asarray(sol.status_code), return_counts=True)
    return ", ".join(f"{STATUS_NAMES[c]} {k}" for c, k in zip(codes, counts, strict=True))


def run_demo(n: int = 10_000, t1_ball: float = 2.5, t1_thermo: float = 60.0,
             plot_path: str | None = "hybridjax_demo.png", seed: int = 0) -> dict:
    """Simulate `n` bouncing balls and `n` thermostats; return the summary rows."""
    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(seed)
    ctrl = diffrax.PIDController(rtol=1e-9, atol=1e-9)
    saves = np.linspace(0.0, 1.0, 201)
    rows = []

    # Bouncing balls: h0 ~ U(0.5, 1.5), v0 ~ U(-1, 1), e = 0.8, to t1 (before any Zeno point).
    ball = examples.bouncing_ball()
    bargs = {"g": 9.8, "e": 0.8}
    x0 = np.stack([rng.uniform(0.5, 1.5, n), rng.uniform(-1.0, 1.0, n)], axis=1)
    run_ball = jax.jit(lambda x, ts: simulate_batch(
        ball, x, "flight", 0.0, t1_ball, bargs, stepsize_controller=ctrl, saveat=ts, max_epochs=32))
    sol_b, compile_b, run_b = _timed(run_ball, jnp.asarray(x0), jnp.asarray(saves * t1_ball))
    ref = np.array([examples.bouncing_ball_closed_form(h, v, 9.8, 0.8, t1_ball)["final_state"]
                    for h, v in x0])
    err_b = float(np.max(np.abs(np.asarray(sol_b.final_state) - ref)))
    n_ref = np.array([len(examples.bouncing_ball_closed_form(h, v, 9.8, 0.8, t1_ball)["event_times"])
                      for h, v in x0])
    missed = int(np.sum(np.asarray(sol_b.num_events) != n_ref))
    rows.append(("bouncing ball", n, compile_b, run_b, _status_tally(sol_b),
                 float(np.mean(sol_b.num_events)), err_b, missed))

    # Thermostats: T0 ~ U(14, 26) in "off", ambient ~ U(0, 40).
    thermo = examples.thermostat()
    T0 = rng.uniform(14.5, 25.5, n)
    T_amb = rng.uniform(0.0, 40.0, n)
    base = dict(a=0.1, P_heat=2.5, P_cool=2.0, s=20.0)
    run_thermo = jax.jit(lambda x, amb, ts: simulate_batch(
        thermo, x, "off", 0.0, t1_thermo,
        {**{k: jnp.full_like(amb, v) for k, v in base.items()}, "T_amb": amb}, args_batched=True,
        stepsize_controller=ctrl, saveat=ts, max_epochs=64))
    sol_t, compile_t, run_t = _timed(run_thermo, jnp.asarray(T0)[:, None], jnp.asarray(T_amb),
                                     jnp.asarray(saves * t1_thermo))
    cf = [examples.thermostat_closed_form(T, "off", {**base, "T_amb": amb}, t1_thermo)
          for T, amb in zip(T0, T_amb, strict=True)]
    err_t = float(np.max(np.abs(np.asarray(sol_t.final_state[:, 0]) -
                                np.array([c["final_state"][0] for c in cf]))))
    missed_t = int(np.sum(np.asarray(sol_t.num_events) != np.array([len(c["event_times"]) for c in cf])))
    rows.append(("thermostat", n, compile_t, run_t, _status_tally(sol_t),
                 float(np.mean(sol_t.num_events)), err_t, missed_t))

    header = (f"{'system':<14} {'N':>7} {'compile s':>10} {'run s':>8} {'exec/s':>10} "
              f"{'mean events':>12} {'max |err|':>10} {'wrong #events':>14}  status")
    print(f"hybridjax demo on {len(jax.devices())} {jax.devices()[0].platform} device(s), float64, Tsit5, "
          "rtol = atol = 1e-9")
    print(header)
    print("-" * len(header))
    for name, nn, c, r, tally, ev, err, miss in rows:
        print(f"{name:<14} {nn:>7} {c:>10.2f} {r:>8.3f} {nn / r:>10.0f} {ev:>12.2f} "
              f"{err:>10.1e} {miss:>14}  {tally}")
    print("max |err|: final state against the closed form; wrong #events: executions whose "
          "number of transitions differs from the closed form's.")

    if plot_path:
        _plot(sol_b, sol_t, thermo, plot_path)
        print(f"wrote {plot_path}")
    return dict(rows=rows)


def _plot(sol_b, sol_t, thermo, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.2))
    for i in range(6):
        ts, ys = np.asarray(sol_b.ts[i]), np.asarray(sol_b.ys[i, :, 0])
        ax1.plot(ts, ys, lw=1.2, color=f"C{i}")
        k = int(sol_b.num_events[i])
        ax1.plot(np.asarray(sol_b.event_times[i, :k]), np.zeros(k), "x", color=f"C{i}", ms=4)
    ax1.set(title="bouncing balls (x: impacts)", xlabel="t [s]", ylabel="height [m]")
    colours = {0: "0.5", 1: "tab:red", 2: "tab:blue"}
    for i in range(8):
        ts, ys, ms = (np.asarray(a[i]) for a in (sol_t.ts, sol_t.ys[..., 0], sol_t.saved_modes))
        for j in range(len(ts) - 1):
            ax2.plot(ts[j:j + 2], ys[j:j + 2], color=colours[int(ms[j])], lw=1.2)
    for m, c in colours.items():
        ax2.plot([], [], color=c, label=thermo.mode_names[m])
    for level in (16, 18, 22, 24):
        ax2.axhline(level, color="k", lw=0.5, ls=":")
    ax2.legend(loc="upper right")
    ax2.set(title="thermostats, coloured by mode", xlabel="t [min]", ylabel="T [deg]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def one_device_per_core() -> None:
    """Give JAX's CPU backend one device per core (`simulate_batch` splits the executions
    between them); only possible before JAX has started its backends, else nothing happens."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        jax.config.update("jax_num_cpu_devices", cores)
    except RuntimeError:  # backends already started: keep what they have
        pass


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m hybridjax")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="simulate batches of the built-in examples")
    demo.add_argument("-n", type=int, default=10_000, help="executions per example")
    demo.add_argument("--plot", default="hybridjax_demo.png", help="PNG path ('' for none)")
    ns = parser.parse_args(argv)
    if ns.command == "demo":
        if ns.n < 8:
            parser.error("-n must be at least 8")
        one_device_per_core()
        run_demo(n=ns.n, plot_path=ns.plot or None)


if __name__ == "__main__":  # pragma: no cover
    main()
