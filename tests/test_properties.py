"""Property-based tests (hypothesis): invariants of every execution, over random initial
conditions and parameters, checked with the user's own guard and reset functions.

- event times are non-decreasing, inside [t0, t1], padded with inf after the last;
- the state before each event lies in its guard, on its boundary: -tol <= g(x(t_i^-)) <= 0
  (to a few ulps: the engine's compiled arithmetic and this re-evaluation round differently);
- the state after each event is the reset of the state before: x(t_i^+) = R(t_i, x(t_i^-));
- no saved state lies strictly inside a guard of its mode during an epoch: g > -tol.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

import hybridjax as hj

from helpers import BALL, THERMO, TIGHT

PROPERTY_SETTINGS = settings(max_examples=50, deadline=None, derandomize=True)
SAVE_TS = np.linspace(0.0, 1.0, 97)[1:]  # fractions of t1


@functools.cache
def runner(system_name: str, t1: float):
    system = {"ball": BALL, "thermostat": THERMO}[system_name]

    @jax.jit
    def run(x0, mode0, args):
        return hj.simulate(system, x0, mode0, 0.0, t1, args, stepsize_controller=TIGHT,
                           saveat=jnp.asarray(SAVE_TS * t1), max_epochs=48)

    return run


def _guard(system, k, t, x, args):
    tr = system.transitions[k]
    dim = system.modes[system.sources[k]].dim
    return float(tr.guard(t, jnp.asarray(x[:dim]), args))


def check_execution(system, sol, args, tol: float) -> None:
    n = int(sol.num_events)
    times = np.asarray(sol.event_times)
    assert np.all(np.diff(times[:n]) >= 0), "event times decrease"
    assert np.all(times[:n] >= float(sol.t0)) and np.all(times[:n] <= float(sol.final_time))
    assert np.all(np.isinf(times[n:]))
    for i in range(n):
        k, t = int(sol.transitions[i]), float(times[i])
        x_before, x_after = np.asarray(sol.states_before[i]), np.asarray(sol.states_after[i])
        g = _guard(system, k, t, x_before, args)
        # <= 0 where the engine evaluated it; re-evaluated here, rounding may differ by ulps.
        ulps = 16 * np.finfo(np.float64).eps * max(1.0, float(np.max(np.abs(x_before))))
        assert -tol <= g <= ulps, f"event {i}: guard {k} = {g:g} at the pre-event state"
        tr = system.transitions[k]
        n_src = system.modes[system.sources[k]].dim
        n_tgt = system.modes[system.targets[k]].dim
        expected = np.asarray(tr.reset(t, jnp.asarray(x_before[:n_src]), args))
        np.testing.assert_array_equal(x_after[:n_tgt], expected)
    # Saved states inside epochs (not at an event instant) are outside every guard of their mode.
    for t, y, mode in zip(np.asarray(sol.ts), np.asarray(sol.ys), np.asarray(sol.saved_modes), strict=True):
        if mode < 0 or np.any(times[:n] == t):
            continue
        for k in system.outgoing(int(mode)):
            g = _guard(system, k, float(t), y, args)
            assert g > -tol, f"saved state at t = {t} in mode {mode} is inside guard {k}: {g:g}"


@PROPERTY_SETTINGS
@given(h0=st.floats(0.05, 2.0), v0=st.floats(-3.0, 3.0), e=st.floats(0.3, 0.95), g=st.floats(1.0, 20.0))
def test_ball_execution_invariants(h0, v0, e, g):
    args = {"g": jnp.float64(g), "e": jnp.float64(e)}
    sol = runner("ball", 3.0)(jnp.array([h0, v0]), 0, args)
    assert sol.status_name in ("T1_REACHED", "ZENO")
    check_execution(BALL, sol, args, tol=1e-9)


THERMO_RANGES = {0: (16.0, 24.0), 1: (10.0, 18.0), 2: (22.0, 35.0)}  # inside each mode, off its guards


@PROPERTY_SETTINGS
@given(mode0=st.sampled_from([0, 1, 2]), u=st.floats(0.01, 0.99), a=st.floats(0.05, 0.3),
       T_amb=st.floats(5.0, 35.0))
def test_thermostat_execution_invariants(mode0, u, a, T_amb):
    lo, hi = THERMO_RANGES[mode0]
    T0 = lo + u * (hi - lo)
    args = dict(a=jnp.float64(a), T_amb=jnp.float64(T_amb), P_heat=jnp.float64(2.5),
                P_cool=jnp.float64(2.0), s=jnp.float64(20.0))
    sol = runner("thermostat", 30.0)(jnp.array([T0]), mode0, args)
    assert sol.status_name == "T1_REACHED"
    check_execution(THERMO, sol, args, tol=1e-8)
