"""Numerical limits: accuracy at the extremes (grazing, scales, long runs, stiffness, float32).

Each case is measured against an independent truth (a closed form, in 50-digit decimal
arithmetic where float64 itself would be the limit; or a conserved quantity):

1. near-grazing: a ball thrown up under a ceiling its apex passes by `depth`;
2. time and state scales: the ball with first impact at T from height L;
3. long runs: 10,000 elastic bounces; an elastic impact oscillator;
4. stiffness: a relay watching a fast lag (stiffness ratio 1e6), Kvaerno5 vs Tsit5;
5. float32: the ball to its Zeno point at several tolerances.

    python benchmarks/numerical_limits.py     # prints tables, writes results/numerical_limits.json
"""

import decimal
import math
import time
import warnings

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from _common import machine_info, write_json

import hybridjax as hj
from hybridjax import examples

jax.config.update("jax_enable_x64", True)
G, V0 = 9.8, 3.0
BALL = examples.bouncing_ball()
TIGHT = diffrax.PIDController(rtol=1e-10, atol=1e-10)


def grazing():
    fly = hj.Mode("fly", lambda t, x, c: jnp.array([x[1], -G + 0.0 * x[0]]), 2)
    stuck = hj.Mode("stuck", lambda t, x, c: jnp.zeros_like(x), 2)
    sys = hj.HybridSystem([fly, stuck], [hj.Transition("fly", "stuck", guard=lambda t, x, c: c - x[0])])
    run = jax.jit(lambda c: hj.simulate(sys, jnp.array([0.0, V0]), "fly", 0.0, 2.0, c, stepsize_controller=TIGHT))
    grad = jax.jit(jax.grad(lambda c: run(c).event_times[0]))
    ctx, D = decimal.Context(prec=50), decimal.Decimal
    rows = []
    for depth in (1e-3, 1e-6, 1e-9, 1e-10, 1e-11, 1e-12, -1e-12):
        c = V0 * V0 / (2 * G) - depth
        sol = run(c)
        row = dict(depth=depth, events=int(sol.num_events), steps=int(sol.num_steps))
        if depth > 0:
            w = ctx.sqrt(D(V0) * D(V0) - 2 * D(G) * D(c))
            t_ref, dtdc_ref = float(ctx.divide(D(V0) - w, D(G))), float(ctx.divide(1, w))
            row.update(time_error=abs(float(sol.event_times[0]) - t_ref), grazing=bool(sol.grazing[0]),
                       dtdc_rel_error=abs(float(grad(c)) / dtdc_ref - 1), slope=float(w))
        rows.append(row)
    print("1. near-grazing crossing of a ceiling (Tsit5, rtol = atol = 1e-10; polynomial flow: steps are long)")
    print(f"{'depth':>8} {'events':>6} {'|dg/dt|':>9} {'t* error':>9} {'dt*/dc rel err':>14} {'grazing':>7} {'steps':>5}")
    for r in rows:
        if r["depth"] > 0:
            print(f"{r['depth']:>8.0e} {r['events']:>6} {r['slope']:>9.1e} {r['time_error']:>9.1e}"
                  f" {r['dtdc_rel_error']:>14.1e} {r['grazing']!s:>7} {r['steps']:>5}")
        else:
            print(f"{r['depth']:>8.0e} {r['events']:>6} {'(misses the ceiling)':>44} {r['steps']:>5}")
    return rows


def scales():
    @jax.jit
    def run(T, L):
        ctrl = diffrax.PIDController(rtol=1e-10, atol=1e-10 * jnp.stack([L, L / T]))
        return hj.simulate(BALL, jnp.stack([L, 0.0 * L]), "flight", 0.0 * T, 3.5 * T,
                           {"g": 2 * L / T**2, "e": 0.5}, stepsize_controller=ctrl)

    rows = []
    for T in (1e-9, 1e-3, 1.0, 1e3, 1e6):
        for L in (1e-8, 1.0, 1e8):
            sol = run(T, L)
            ref = examples.bouncing_ball_closed_form(L, 0.0, 2 * L / T**2, 0.5, 3.0 * T, max_events=64)
            n = int(sol.num_events)
            err = np.max(np.abs(np.asarray(sol.event_times[:n]) - ref["event_times"][:n])) / T
            zt = abs(float(sol.zeno_time) / examples.zeno_time(L, 2 * L / T**2, 0.5) - 1)
            rows.append(dict(T=T, L=L, status=str(sol.status_name), events=n, time_rel_error=err,
                             zeno_rel_error=zt, steps=int(sol.num_steps)))
    print("\n2. time and state scales: ball from height L, first impact at T, e = 0.5 (Zeno at 3T);"
          " rtol = 1e-10, atol = 1e-10 x (L, L/T)")
    print(f"{'T':>6} {'L':>6} {'status':>6} {'events':>6} {'max |t_i - ref| / T':>20} {'Zeno time rel err':>18} {'steps':>5}")
    for r in rows:
        print(f"{r['T']:>6.0e} {r['L']:>6.0e} {r['status']:>6} {r['events']:>6} {r['time_rel_error']:>20.1e}"
              f" {r['zeno_rel_error']:>18.1e} {r['steps']:>5}")
    return rows


def long_runs():
    out = {}
    n = 10_000
    T = math.sqrt(2 / G)
    t = time.perf_counter()
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 2 * n * T, {"g": G, "e": 1.0},
                      stepsize_controller=TIGHT, max_epochs=n + 2, max_steps=8 * n)
    wall = time.perf_counter() - t
    k = int(sol.num_events)
    ref = T * (1 + 2 * np.arange(k))
    x = np.asarray(sol.states_after[:k])
    energy = G * x[:, 0] + 0.5 * x[:, 1] ** 2
    out["elastic_ball"] = dict(bounces=k, status=str(sol.status_name), steps=int(sol.num_steps),
                               time_rel_error=float(np.max(np.abs(np.asarray(sol.event_times[:k]) - ref) / ref)),
                               energy_rel_drift=float(np.max(np.abs(energy / G - 1))), wall_s=wall)
    a, n_osc = 0.5, 1000
    osc = hj.HybridSystem([hj.Mode("free", lambda t, x, a: jnp.array([x[1], -x[0]]), 2)], [
        hj.Transition("free", "free", guard=lambda t, x, a: x[0] + a, reset=lambda t, x, a: jnp.array([x[0], -x[1]]))])
    phi = math.acos(a)
    period = 2 * math.pi - 2 * phi
    sol = hj.simulate(osc, jnp.array([1.0, 0.0]), "free", 0.0, math.pi - phi + (n_osc - 0.5) * period, a,
                      stepsize_controller=TIGHT, max_epochs=n_osc + 2, max_steps=120 * n_osc)
    k = int(sol.num_events)
    e_osc = 0.5 * np.sum(np.asarray(sol.states_after[:k]) ** 2, axis=1)
    ref = math.pi - phi + period * np.arange(k)
    out["impact_oscillator"] = dict(bounces=k, status=str(sol.status_name), steps=int(sol.num_steps),
                                    energy_drift=float(np.max(np.abs(e_osc - 0.5))),
                                    energy_drift_per_bounce=float(np.max(np.abs(e_osc - 0.5))) / k,
                                    time_rel_error=float(np.max(np.abs(np.asarray(sol.event_times[:k]) - ref) / ref)))
    print("\n3. long runs (Tsit5, rtol = atol = 1e-10)")
    b, o = out["elastic_ball"], out["impact_oscillator"]
    print(f"elastic ball (e = 1): {b['bounces']} bounces, {b['steps']} steps, {b['wall_s']:.1f} s;"
          f" max relative event-time error {b['time_rel_error']:.1e}, energy drift {b['energy_rel_drift']:.1e} (relative)")
    print(f"elastic impact oscillator x'' = -x, wall at x = -{a}: {o['bounces']} bounces, {o['steps']} steps;"
          f" energy drift {o['energy_drift']:.1e} ({o['energy_drift_per_bounce']:.1e} per bounce),"
          f" max relative event-time error {o['time_rel_error']:.1e}")
    return out


def stiff():
    lam = 1e6
    sys = examples.stiff_relay()
    rows = []
    for solver in (diffrax.Kvaerno5(), diffrax.Tsit5()):
        t = time.perf_counter()
        sol = hj.simulate(sys, jnp.zeros(2), "up", 0.0, 20.0, lam, solver=solver,
                          stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8), max_steps=20_000)
        wall = time.perf_counter() - t
        n = int(sol.num_events)
        ref = examples.stiff_relay_closed_form(0.0, lam, 20.0)["event_times"][:n]
        rows.append(dict(solver=type(solver).__name__, status=str(sol.status_name), events=n,
                         steps=int(sol.num_steps), final_time=float(sol.final_time),
                         time_error=float(np.max(np.abs(np.asarray(sol.event_times[:n]) - ref))) if n else None,
                         wall_s_incl_compile=wall))
    print("\n4. stiff relay (slow s' = u, fast y' = -1e6 (y - s), switch when u y = 1), to t = 20, rtol = atol = 1e-8")
    print(f"{'solver':>9} {'status':>10} {'events':>6} {'steps':>6} {'reached t':>9} {'max t_i error':>13}")
    for r in rows:
        err = "-" if r["time_error"] is None else f"{r['time_error']:.1e}"
        print(f"{r['solver']:>9} {r['status']:>10} {r['events']:>6} {r['steps']:>6} {r['final_time']:>9.4g} {err:>13}")
    return rows


def float32():
    rows = []
    ref = examples.bouncing_ball_closed_form(1.0, 0.0, 9.8, 0.8, 5.0)
    zt = examples.zeno_time(1.0, 9.8, 0.8)
    for tol in (1e-3, 1e-4, 1e-5, 1e-6, 1e-7):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            sol = hj.simulate(BALL, jnp.array([1.0, 0.0], jnp.float32), "flight", 0.0, 5.0,
                              {"g": np.float32(9.8), "e": np.float32(0.8)},
                              stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol), max_steps=4096)
        n = int(sol.num_events)
        err = np.max(np.abs(np.asarray(sol.event_times[:n], np.float64) - ref["event_times"][:n]))
        rows.append(dict(tol=tol, status=str(sol.status_name), events=n, steps=int(sol.num_steps),
                         time_error=float(err), zeno_rel_error=abs(float(sol.zeno_time) / zt - 1),
                         warned=bool(caught)))
    print("\n5. float32: ball (e = 0.8, h0 = 1) to t = 5, past its Zeno point 4.0658")
    print(f"{'rtol=atol':>9} {'status':>8} {'events':>6} {'steps':>5} {'max t_i error':>13} {'Zeno time rel err':>17} {'warned':>6}")
    for r in rows:
        print(f"{r['tol']:>9.0e} {r['status']:>8} {r['events']:>6} {r['steps']:>5} {r['time_error']:>13.1e}"
              f" {r['zeno_rel_error']:>17.1e} {r['warned']!s:>6}")
    return rows


def main():
    payload = dict(machine=machine_info(), grazing=grazing(), scales=scales(), long_runs=long_runs(),
                   stiff=stiff(), float32=float32())
    print(f"\nwrote {write_json('numerical_limits', payload)}")


if __name__ == "__main__":
    main()
