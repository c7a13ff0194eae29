"""The salted Kalman filter on a bouncing ball: saltation update against the reset's Jacobian.

400 balls dropped from h0 ~ N(1, 0.01^2), v0 ~ N(0, 0.01^2) (g = 9.81, e = 0.8), height
measured every 0.04 s with noise of standard deviation 0.01 (no measurement within 15 ms of
the nominal impacts); a batch of 400 filters for each update (one compiled function each).
Reports the average normalised estimation error squared (NEES, chi-square with 2 degrees of
freedom per trial for a consistent filter) before and after the first impact, the RMS errors
after it, and the run time; plots one trial (estimate, truth, 2-sigma band).

Writes results/kalman_ball.json and docs/benchmarks/kalman_ball.png.

    python benchmarks/kalman_ball.py
"""

import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats
from _common import machine_info, write_json

import hybridjax as hj

jax.config.update("jax_enable_x64", True)

N, G, E = 400, 9.81, 0.8
ARGS = {"g": G, "e": E}
TS = 0.03 + 0.04 * np.arange(38)
X0, P0, R = np.array([1.0, 0.0]), np.diag([0.01**2, 0.01**2]), np.array([[0.01**2]])


def main():
    ball = hj.examples.bouncing_ball()
    rng = np.random.default_rng(7)
    x0s = X0 + rng.normal(size=(N, 2)) * 0.01
    truth = jax.jit(jax.vmap(lambda x: hj.simulate(ball, x, 0, 0.0, TS[-1], ARGS, saveat=jnp.asarray(TS)).ys))
    xs = np.asarray(truth(jnp.asarray(x0s)))
    ys = xs[:, :, :1] + 0.01 * rng.normal(size=(N, len(TS), 1))
    t_hit = np.sqrt(2 / G)
    after = TS > t_hit
    out, runs, nees_by_time = {}, {}, {}
    for update in ("saltation", "reset"):
        kf = hj.SaltedKalmanFilter(ball, lambda t, x, args: x[:1], update=update)
        run = jax.jit(jax.vmap(lambda y: kf(X0, P0, TS, y, jnp.zeros((2, 2)), R, t0=0.0, args=ARGS)))
        t = time.perf_counter()
        res = jax.block_until_ready(run(jnp.asarray(ys)))
        first = time.perf_counter() - t
        t = time.perf_counter()
        res = jax.block_until_ready(run(jnp.asarray(ys)))
        run_s = time.perf_counter() - t
        err = xs - np.asarray(res.means)
        nees = np.einsum("nki,nkij,nkj->nk", err, np.linalg.inv(np.asarray(res.covariances)), err).mean(0)
        out[update] = dict(
            anees_before_impact=float(nees[~after].mean()), anees_after_impact=float(nees[after].mean()),
            rms_after_impact=np.sqrt(np.mean(err[:, after] ** 2, axis=(0, 1))).tolist(),
            run_s=run_s, compile_s=first - run_s, filters_per_s=N / run_s,
        )
        runs[update] = res
        nees_by_time[update] = nees
        print(update, out[update])
    lo, hi = scipy.stats.chi2.ppf([0.005, 0.995], 2 * N) / N
    payload = dict(machine=machine_info(), trials=N, measurements=len(TS), anees_99_bounds=[lo, hi], **out,
                   anees_by_time={k: v.tolist() for k, v in nees_by_time.items()})
    print(write_json("kalman_ball", payload))
    try:
        import matplotlib

        matplotlib.use("Agg")
        print(f"99% bounds of the average NEES: [{lo:.3f}, {hi:.3f}]")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, axes = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True)
    for update, color in (("saltation", "C0"), ("reset", "C3")):
        axes[0].plot(TS, nees_by_time[update], "o-", ms=3, color=color, label=f"{update} update")
        err = xs[0, :, 1] - np.asarray(runs[update].means[0, :, 1])
        s = np.sqrt(np.asarray(runs[update].covariances[0, :, 1, 1]))
        axes[1].plot(TS, err, "o", ms=3, color=color, label=f"{update} update: error")
        axes[1].fill_between(TS, -2 * s, 2 * s, color=color, alpha=0.2, label=f"{update} update: 2 sigma")
    axes[0].axhspan(lo, hi, color="0.85", label="99% chi-square bounds")
    for ax in axes:
        for t_hit in hj.examples.bouncing_ball_closed_form(1.0, 0.0, G, E, TS[-1])["event_times"]:
            ax.axvline(t_hit, color="k", lw=0.5, ls=":")
    axes[0].set_ylabel(f"NEES, average of {N} trials")
    axes[1].set_ylabel("velocity error, trial 0")
    axes[0].legend(fontsize=7)
    axes[1].legend(fontsize=7, ncol=2)
    axes[1].set_xlabel("t (dotted: impacts)")
    fig.tight_layout()
    path = Path(__file__).parent.parent / "docs" / "benchmarks" / "kalman_ball.png"
    fig.savefig(path, dpi=110)
    print(path)


if __name__ == "__main__":
    main()
