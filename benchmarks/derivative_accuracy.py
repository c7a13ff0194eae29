"""How accurate event-time derivatives are over long event sequences.

The leaky integrate-and-fire neuron V' = (I - V) / tau, spike at V = 1, reset to V = 0
(I = 1.5, tau = 0.02, V(0) = 0) spikes at t_k = k T, T = tau ln(I / (I - 1)), so
d t_k / d I = k tau (1 / I - 1 / (I - 1)) and d t_k / d tau = k ln(I / (I - 1)) in closed
form. (The flow is linear in I, and so is every explicit Runge-Kutta solution of it: the
derivative in I carries no discretisation error and shows what the composition across events
adds; the one in tau carries the solver's.) For each solver tolerance (rtol = atol) this
measures, for the first 100 spikes, the error against the closed form of

- reverse-mode AD (`jax.jacrev`, default adjoint) and forward-mode AD (`jax.jacfwd` with
  `diffrax.ForwardMode()`) through `hj.simulate`;
- the same through `hj.simulate_batch` (reverse mode);
- a central finite difference of the simulated spike times (relative step 1e-4), the
  simulation's own derivative including its step-size choices;
- the spike times themselves;

and the growth exponent of each error (least-squares slope of log of its running maximum
against log k over k = 10 ... 100: 1 for linear growth, 2 for quadratic).

    python benchmarks/derivative_accuracy.py    # writes benchmarks/results/derivative_accuracy.json

`python benchmarks/report.py` turns the JSON into the documentation's table and plot.
"""

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine_info, write_json  # noqa: E402

import hybridjax as hj  # noqa: E402

TOLERANCES = (1e-6, 1e-8, 1e-10, 1e-12)
SPIKES = 100
I0, TAU = 1.5, 0.02
FD_STEP = 1e-4


def closed_form(current: float, tau: float) -> tuple[np.ndarray, dict]:
    """Spike times (`hj.examples.integrate_and_fire_closed_form`) and their exact derivatives
    in I and tau (forward-mode AD of that formula)."""
    def times(p):
        return hj.examples.integrate_and_fire_closed_form(p[0], p[1], 0.0, SPIKES)

    p = jnp.asarray([current, tau])
    J = np.asarray(jax.jacfwd(times)(p))
    return np.asarray(times(p)), {"I": J[:, 0], "tau": J[:, 1]}


def growth_exponent(err: np.ndarray, k_from: int = 10) -> float:
    k = np.arange(1, err.shape[0] + 1)
    env = np.maximum.accumulate(np.abs(err)) + np.finfo(np.float64).tiny
    sel = k >= k_from
    return float(np.polyfit(np.log(k[sel]), np.log(env[sel]), 1)[0])


def measure(tol: float) -> dict:
    system = hj.examples.integrate_and_fire()
    t1 = (SPIKES + 0.5) * TAU * np.log(I0 / (I0 - 1))
    opts = dict(stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol), max_epochs=SPIKES + 8,
                zeno=False, max_steps=64 * 4096)

    def times(p, adjoint, engine="simulate"):
        args = {"I": p[0], "tau": p[1]}
        if engine == "simulate":
            return hj.simulate(system, jnp.zeros(1), "subthreshold", 0.0, t1, args, adjoint=adjoint, **opts).event_times[:SPIKES]
        return hj.simulate_batch(system, jnp.zeros((1, 1)), "subthreshold", 0.0, t1, args, adjoint=adjoint,
                                 **opts).event_times[0, :SPIKES]

    rev, fwd = diffrax.RecursiveCheckpointAdjoint(), diffrax.ForwardMode()
    value = jax.jit(lambda p: times(p, rev))
    p = jnp.asarray([I0, TAU])
    t_sim = np.asarray(value(p))
    jac = {"reverse": jax.jit(jax.jacrev(lambda p: times(p, rev)))(p),
           "forward": jax.jit(jax.jacfwd(lambda p: times(p, fwd)))(p),
           "batch_reverse": jax.jit(jax.jacrev(lambda p: times(p, rev, "simulate_batch")))(p)}
    steps = FD_STEP * np.asarray(p)
    jac["finite_difference"] = np.stack(
        [(np.asarray(value(p + e)) - np.asarray(value(p - e))) / (2 * h)
         for e, h in ((jnp.array([steps[0], 0.0]), steps[0]), (jnp.array([0.0, steps[1]]), steps[1]))], axis=-1)
    t_exact, d_exact = closed_form(I0, TAU)
    k = np.arange(1, SPIKES + 1)
    errors = {"times": t_sim - t_exact}
    for method, J in jac.items():
        J = np.asarray(J)
        for i, name in enumerate(("I", "tau")):
            errors[f"{method} d/d{name}"] = J[:, i] - d_exact[name]
    return dict(tol=tol, errors={m: v.tolist() for m, v in errors.items()},
                growth={m: growth_exponent(v) for m, v in errors.items()},
                max_error_per_event={m: float(np.max(np.abs(v) / k)) for m, v in errors.items()})


def main() -> None:
    rows = []
    for tol in TOLERANCES:
        row = measure(tol)
        rows.append(row)
        for m, v in row["max_error_per_event"].items():
            print(f"tol {tol:.0e}  {m:28s} max |error| / k {v:.2e}  growth k^{row['growth'][m]:.2f}")
    path = write_json("derivative_accuracy", dict(
        machine=machine_info(), problem=dict(system="leaky integrate-and-fire", I=I0, tau=TAU, V0=0.0,
                                             spikes=SPIKES, fd_relative_step=FD_STEP, solver="Tsit5"),
        results=rows))
    print("wrote", path)


if __name__ == "__main__":
    main()
