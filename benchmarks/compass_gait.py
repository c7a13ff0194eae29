"""The compass-gait walker's period-one gait and its return to the gait after a push.

`hj.periodic_orbit` on `hj.examples.compass_gait()` (Goswami, Thuilot and Espiau's model: m = 5,
m_H = 10, a = b = 0.5, a 3 degree slope) gives the gait and its Floquet multipliers; then a walker
pushed off the gait (the stance leg's rate after a strike raised by 0.1 rad/s) is simulated for 16
steps, and the distance of each post-strike state to the gait is set beside rho^k, rho the
multipliers' spectral radius. Plots the gait's phase portrait and that distance.

Writes results/compass_gait.json and docs/benchmarks/compass_gait.png.

    python benchmarks/compass_gait.py
"""

from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine_info, write_json  # noqa: E402

import hybridjax as hj  # noqa: E402

STEPS = 16
PUSH = 0.1


def state_before_strike(walker, x_star, period, args, ctrl):
    """The state just before the strike that closes the step from x_star."""
    sol = hj.simulate(walker, jnp.asarray(x_star), 0, 0.0, 1.5 * period, args, stepsize_controller=ctrl,
                      max_epochs=2)
    return sol.states_before[0]


def main():
    walker = hj.examples.compass_gait()
    args = {k: jnp.asarray(v) for k, v in hj.examples.COMPASS_GAIT_ARGS.items()}
    orbit = hj.periodic_orbit(walker, 0, jnp.array([0.33, -0.22, 0.38, 1.1]), args, max_epochs=4, t_max=2.0)
    x_star, period = np.asarray(orbit.state), float(orbit.period)
    dp = np.linalg.eigvals(np.asarray(orbit.poincare_jacobian))
    dp = dp[np.argsort(-np.abs(dp))]
    rho = float(np.abs(dp[0]))
    ctrl = diffrax.PIDController(rtol=1e-10, atol=1e-10)
    ts = np.linspace(0.0, period, 200, endpoint=False)
    gait = hj.simulate(walker, jnp.asarray(x_star), 0, 0.0, period * 0.999, args, stepsize_controller=ctrl,
                       saveat=jnp.asarray(ts), max_epochs=2)
    x0 = x_star + np.array([0.0, 0.0, 0.0, PUSH])
    pushed = hj.simulate(walker, jnp.asarray(x0), 0, 0.0, (STEPS + 0.5) * period, args, stepsize_controller=ctrl,
                         max_epochs=STEPS + 4)
    n = int(pushed.num_events)
    after = np.concatenate([x0[None], np.asarray(pushed.states_after[:n])])
    distance = np.linalg.norm(after - x_star, axis=1)
    payload = dict(
        machine=machine_info(), args=hj.examples.COMPASS_GAIT_ARGS, state=x_star.tolist(), period=period,
        multipliers_real=dp.real.tolist(), multipliers_imag=dp.imag.tolist(), push=PUSH, steps=n,
        distance=distance.tolist(), step_times=np.asarray(pushed.event_times[:n]).tolist(),
    )
    print(f"gait {x_star}, period {period:.10f} s, multipliers {dp}")
    print(f"pushed walker: {n} steps, distance to the gait {distance[0]:.3e} -> {distance[-1]:.3e}")
    print(write_json("compass_gait", payload))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    ys = np.concatenate([np.asarray(gait.ys), np.asarray(state_before_strike(walker, x_star, period, args, ctrl))[None]])
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.8))
    axes[0].plot(ys[:, 1], ys[:, 3], color="C0", label="stance leg")
    axes[0].plot(ys[:, 0], ys[:, 2], color="C1", label="swing leg")
    # The strike: the stance leg becomes the swing leg and the other way round, rates jumping.
    axes[0].plot([ys[-1, 1], x_star[0]], [ys[-1, 3], x_star[2]], ":", color="k", lw=1, label="heel strike")
    axes[0].plot([ys[-1, 0], x_star[1]], [ys[-1, 2], x_star[3]], ":", color="k", lw=1)
    axes[0].plot(x_star[1], x_star[3], "o", color="C0", ms=4)
    axes[0].plot(x_star[0], x_star[2], "o", color="C1", ms=4)
    axes[0].set_xlabel("leg angle from the vertical (rad)")
    axes[0].set_ylabel("angular rate (rad/s)")
    axes[0].set_title(f"the gait: one step of {period:.4f} s (dots: just after the strike)", fontsize=9)
    axes[0].legend(fontsize=8)
    k = np.arange(distance.shape[0])
    axes[1].semilogy(k, distance, "o-", ms=3, label="|x_k - x*| after strike k")
    axes[1].semilogy(k, distance[0] * rho**k, "--", color="0.4", label=f"{distance[0]:.2f} x {rho:.4f}^k")
    axes[1].set_xlabel("step k")
    axes[1].set_title(f"pushed by {PUSH} rad/s: back to the gait", fontsize=9)
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    path = Path(__file__).parent.parent / "docs" / "benchmarks" / "compass_gait.png"
    fig.savefig(path, dpi=100, metadata={"Software": None})
    print(path)


if __name__ == "__main__":
    main()
