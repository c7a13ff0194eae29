"""The benchmark problems, each as a HybridSystem, numpy callbacks for scipy, and a truth.

A. bouncing ball, e = 0.8, h0 ~ U(0.5, 1.5), v0 ~ U(-1, 1), to T = 2.5 (before any Zeno point);
   truth: closed form.
B. Van der Pol (mu = 5) with relay feedback: x' = y, y' = mu (1 - x^2) y - x + q, q = +-1
   switching when q x crosses 0.5 upward (guard 0.5 - q x), x0 ~ U(-2, 0.5), y0 ~ U(-2, 2),
   q0 = +1, to T = 20; truth: a reference run at rtol = atol = 1e-13 (Dopri8), itself checked
   against scipy's DOP853 at 1e-13 on a few executions.
C. thermostat (the chapter's practice problem 2), T0 ~ U(16.5, 23.5) in "off", ambient 30,
   60 min (heating and cooling cycles; guards and domains watched); truth: closed form.
D. stiff relay: slow s' = u, fast y' = -1e6 (y - s), u = +-1 switching when u y crosses 1, to
   T = 20 (stiffness ratio 1e6); truth: closed form (switches at (1 + 1e-6)(1 + 2k)).
"""

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

import hybridjax as hj
from hybridjax import examples


@dataclass
class Problem:
    name: str
    system: hj.HybridSystem
    t1: float
    args: dict
    sample: Callable  # (rng, n) -> (x0 (n, dim), mode0 (n,))
    truth: Callable | None  # (x0 row, mode0) -> dict(final_state, num_events); None: reference run
    numpy_flows: list = field(default_factory=list)
    numpy_guards: list = field(default_factory=list)
    numpy_resets: list = field(default_factory=list)
    max_epochs: int = 64


def ball() -> Problem:
    args = {"g": 9.8, "e": 0.8}

    def sample(rng, n):
        return np.stack([rng.uniform(0.5, 1.5, n), rng.uniform(-1, 1, n)], 1), np.zeros(n, int)

    def truth(x0, mode0):
        ref = examples.bouncing_ball_closed_form(x0[0], x0[1], 9.8, 0.8, 2.5)
        return dict(final_state=ref["final_state"], num_events=len(ref["event_times"]))

    return Problem("A: bouncing ball", examples.bouncing_ball(), 2.5, args, sample, truth,
                   [lambda t, x: np.array([x[1], -9.8])], [lambda t, x: x[0]],
                   [lambda t, x: np.array([x[0], -0.8 * x[1]])], max_epochs=32)


MU = 5.0


def vdp_relay() -> Problem:
    def sample(rng, n):
        return np.stack([rng.uniform(-2, 0.5, n), rng.uniform(-2, 2, n)], 1), np.zeros(n, int)

    def f(q):
        return lambda t, x: np.array([x[1], MU * (1 - x[0] ** 2) * x[1] - x[0] + q])

    return Problem("B: Van der Pol relay", examples.van_der_pol_relay(), 20.0, MU, sample, None,
                   [f(1.0), f(-1.0)], [lambda t, x: 0.5 - x[0], lambda t, x: 0.5 + x[0]],
                   [lambda t, x: x, lambda t, x: x], max_epochs=64)


THERMO_P = dict(a=0.1, T_amb=30.0, P_heat=2.5, P_cool=2.0, s=20.0)


def thermostat() -> Problem:
    def sample(rng, n):
        return rng.uniform(16.5, 23.5, (n, 1)), np.zeros(n, int)

    def truth(x0, mode0):
        ref = examples.thermostat_closed_form(float(x0[0]), "off", THERMO_P, 60.0)
        return dict(final_state=ref["final_state"], num_events=len(ref["event_times"]))

    p = THERMO_P

    def flow(power):
        return lambda t, x: np.array([p["a"] * (p["T_amb"] - x[0]) + power])

    return Problem("C: thermostat", examples.thermostat(), 60.0, THERMO_P, sample, truth,
                   [flow(0.0), flow(p["P_heat"]), flow(-p["P_cool"])],
                   [lambda t, x: x[0] - (p["s"] - 4), lambda t, x: (p["s"] - 2) - x[0],
                    lambda t, x: (p["s"] + 4) - x[0], lambda t, x: x[0] - (p["s"] + 2)],
                   [lambda t, x: x] * 4, max_epochs=64)


LAM = 1e6


def stiff_relay() -> Problem:
    def sample(rng, n):
        s0 = rng.uniform(-0.5, 0.5, n)
        return np.stack([s0, s0], 1), np.zeros(n, int)

    def truth(x0, mode0):
        ref = examples.stiff_relay_closed_form(float(x0[0]), LAM, 20.0)
        return dict(final_state=ref["final_state"], num_events=len(ref["event_times"]))

    return Problem("D: stiff relay", examples.stiff_relay(), 20.0, LAM, sample, truth, max_epochs=32)
