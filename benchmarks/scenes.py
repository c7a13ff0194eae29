"""Scenes: what `hj.contact_system` builds and what it costs, against the number of walls K.

A point (unit mass, gravity 9.81) inside a regular polygon of K walls at distance r = 1 from
the centre (`hj.examples.polygon_particle(K)`), plastic impacts, K = 1 ... 8 (or the K given).
For each K: the contact sets built (against the 2^K subsets of walls), the transitions, the
build time (the point search), and for each way of evaluating the system, "mask" (the default:
the current mode in one solve with all K walls, those not held masked out) and "branch" (every
mode's and transition's own function, the current one selected; measured up to K = 3): the time to trace, lower and XLA-compile `jax.jit(hj.simulate_batch)`
(wall and process CPU time: on a shared machine the CPU time is the steadier) and executions per second,
N = 256 executions from the free set (positions in a disc of radius 0.4, velocities in
[-2, 2]^2), T = 1.5, Tsit5, rtol = atol = 1e-8, with the statuses reached and, where both forms ran, the largest difference between their event times.

The compass-gait walker (`hj.examples.compass_gait_scene()`, its stance foot sticking, the swing
foot armed ahead of it, legs relabelled at heel strike): its build, the compile and run of one `hj.simulate`
and of the batch, and executions per second, N = 256 executions of T = 3 s from a stance state with
the hip's angular rate in [1.0, 1.4].

A rod with Coulomb friction at one end (`hj.examples.rod_scene(friction=("left",))`): its build (the
friction states' point searches) and its first `hj.simulate`, compiled and run.

    python benchmarks/scenes.py            # K = 1 ... 8 and the walker; writes results/scenes.json
    python benchmarks/scenes.py 1 2 3      # only these K (merged into an existing results file)
    python benchmarks/scenes.py walker     # only the walker
    python benchmarks/scenes.py rod        # only the rod with friction
"""

import json
import sys
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from _common import machine_info, write_json

import hybridjax as hj

jax.config.update("jax_enable_x64", True)

N, T1 = 256, 1.5
FORMS = ("mask", "branch")
BRANCH_UP_TO = 3
ARGS = {"g": 9.81, "r": 1.0}


def initial_states(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rad = 0.4 * np.sqrt(rng.uniform(0, 1, n))
    ang = rng.uniform(0, 2 * np.pi, n)
    return np.stack([rad * np.cos(ang), rad * np.sin(ang), rng.uniform(-2, 2, n), rng.uniform(-2, 2, n)], 1)


def compile_and_time(fn, x0):
    """(result, compile wall s, compile CPU s, best of 3 runs in s) of the jitted `fn` at `x0`."""
    t, cpu = time.perf_counter(), time.process_time()
    compiled = fn.trace(x0).lower().compile()
    compile_s, compile_cpu_s = time.perf_counter() - t, time.process_time() - cpu
    out, best = None, float("inf")
    for _ in range(3):
        t = time.perf_counter()
        out = jax.block_until_ready(compiled(x0))
        best = min(best, time.perf_counter() - t)
    return out, compile_s, compile_cpu_s, best


def one_k(k: int, forms) -> dict:
    scene = hj.examples.polygon_particle(k)
    args = {key: jnp.asarray(v) for key, v in ARGS.items()}
    x0 = jnp.asarray(initial_states(N))
    ctrl = diffrax.PIDController(rtol=1e-8, atol=1e-8)
    row = {"K": k, "subsets": 2**k}
    events = {}
    for form in forms:
        t, cpu = time.perf_counter(), time.process_time()
        system = hj.contact_system(scene, ["free"], args, form=form)
        build_s, build_cpu_s = time.perf_counter() - t, time.process_time() - cpu
        fn = jax.jit(
            lambda x, s=system: hj.simulate_batch(
                s, x, "free", 0.0, T1, args, stepsize_controller=ctrl, max_epochs=48
            )
        )
        sol, compile_s, compile_cpu_s, best = compile_and_time(fn, x0)
        codes = np.asarray(sol.status)
        events[form] = np.asarray(sol.event_times)
        statuses = {hj.STATUS_NAMES[c]: int(np.sum(codes == c)) for c in np.unique(codes)}
        row.update(
            {
                "modes_built": len(system.built_sets),
                "modes": system.num_modes,
                "transitions": system.num_transitions,
                f"{form}_build_s": build_s,
                f"{form}_build_cpu_s": build_cpu_s,
                f"{form}_compile_s": compile_s,
                f"{form}_compile_cpu_s": compile_cpu_s,
                f"{form}_run_s": best,
                f"{form}_exec_per_s": N / best,
                f"{form}_statuses": statuses,
                f"{form}_mean_events": float(np.mean(np.asarray(sol.num_events))),
            }
        )
        print(
            f"K={k} {form}: {len(system.built_sets)} sets of {2**k}, {system.num_transitions} transitions, "
            f"build {build_s:.1f} s ({build_cpu_s:.1f} s CPU), compile {compile_s:.1f} s ({compile_cpu_s:.1f} s CPU), {N / best:.0f} executions/s, {statuses}",
            flush=True,
        )
    if len(events) == 2:
        a, b = events["mask"], events["branch"]
        same = bool(np.array_equal(np.isfinite(a), np.isfinite(b)))
        fin = np.isfinite(a) & np.isfinite(b)
        row["max_event_time_difference"] = float(np.max(np.abs(a[fin] - b[fin]), initial=0.0)) if same else float("inf")
    return row


def walker_state(alpha: float, w: float) -> np.ndarray:
    """A stance state of the walker: feet at x = 0 (stance) and -2 l sin(alpha), everything
    rotating at rate w about the stance foot (consistent with the legs and the pinned foot)."""
    p = hj.examples.COMPASS_GAIT_ARGS
    leg, b = p["a"] + p["b"], p["b"]
    hip = np.array([-leg * np.sin(alpha), leg * np.cos(alpha)])
    feet = (np.zeros(2), np.array([-2 * leg * np.sin(alpha), 0.0]))
    points = [hip] + [hip + b / leg * (f - hip) for f in feet]
    return np.concatenate([*points, *(w * np.array([r[1], -r[0]]) for r in points)])


def walker() -> dict:
    scene, relabel = hj.examples.compass_gait_scene()
    args = {key: jnp.asarray(v) for key, v in hj.examples.COMPASS_GAIT_ARGS.items()}
    ctrl = diffrax.PIDController(rtol=1e-8, atol=1e-8)
    t, cpu = time.perf_counter(), time.process_time()
    system = hj.contact_system(scene, ["foot0"], args, relabels=[relabel])
    build_s, build_cpu_s = time.perf_counter() - t, time.process_time() - cpu
    x1 = jnp.asarray(walker_state(0.2, 1.2))
    one = jax.jit(lambda x: hj.simulate(system, x, 0, 0.0, 3.0, args, stepsize_controller=ctrl, max_epochs=16))
    t, cpu = time.perf_counter(), time.process_time()
    sol = jax.block_until_ready(one(x1))
    first_s, first_cpu_s = time.perf_counter() - t, time.process_time() - cpu
    rng = np.random.default_rng(0)
    x0 = jnp.asarray(np.stack([walker_state(0.2, w) for w in rng.uniform(1.0, 1.4, N)]))
    fn = jax.jit(
        lambda x: hj.simulate_batch(system, x, 0, 0.0, 3.0, args, stepsize_controller=ctrl, max_epochs=16)
    )
    batch, compile_s, compile_cpu_s, best = compile_and_time(fn, x0)
    codes = np.asarray(batch.status)
    statuses = {hj.STATUS_NAMES[c]: int(np.sum(codes == c)) for c in np.unique(codes)}
    row = {
        "modes": system.num_modes,
        "transitions": system.num_transitions,
        "mask_build_s": build_s,
        "mask_build_cpu_s": build_cpu_s,
        "walker_first_simulate_s": first_s,
        "walker_first_simulate_cpu_s": first_cpu_s,
        "mask_compile_s": compile_s,
        "mask_compile_cpu_s": compile_cpu_s,
        "mask_run_s": best,
        "mask_exec_per_s": N / best,
        "mask_statuses": statuses,
        "steps_in_3_s": int(sol.num_events),
    }
    print(
        f"walker: {system.num_modes} modes, build {build_s:.1f} s ({build_cpu_s:.1f} s CPU), first simulate "
        f"{first_s:.1f} s ({first_cpu_s:.1f} s CPU), batch compile "
        f"{compile_s:.1f} s ({compile_cpu_s:.1f} s CPU), {N / best:.0f} executions/s, {statuses}",
        flush=True,
    )
    return row


ROD_ARGS = {"m": 1.0, "g": 9.81, "L": 1.0, "mu": 0.3}


def friction_rod() -> dict:
    """The rod with Coulomb friction at its left end (`hj.examples.rod_scene(friction=("left",))`,
    mu = 0.3): its build from the free state and the first `hj.simulate` (compiled and run),
    dropped at x = 0.1, z = 0.5, phi = 0.3 from rest for T = 1 s (rtol = atol = 1e-11)."""
    args = {key: jnp.asarray(v) for key, v in ROD_ARGS.items()}
    t, cpu = time.perf_counter(), time.process_time()
    system = hj.contact_system(hj.examples.rod_scene(friction=("left",)), ["free"], args)
    build_s, build_cpu_s = time.perf_counter() - t, time.process_time() - cpu
    ctrl = diffrax.PIDController(rtol=1e-11, atol=1e-11)
    one = jax.jit(lambda x: hj.simulate(system, x, system.mode_index("free"), 0.0, 1.0, args,
                                        stepsize_controller=ctrl, max_epochs=16))
    t, cpu = time.perf_counter(), time.process_time()
    sol = jax.block_until_ready(one(jnp.asarray([0.1, 0.5, 0.3, 0.0, 0.0, 0.0])))
    first_s, first_cpu_s = time.perf_counter() - t, time.process_time() - cpu
    row = {"modes": system.num_modes, "transitions": system.num_transitions, "build_s": build_s,
           "build_cpu_s": build_cpu_s, "first_simulate_s": first_s, "first_simulate_cpu_s": first_cpu_s,
           "events": int(sol.num_events), "status": hj.STATUS_NAMES[int(sol.status)]}
    print(f"friction rod: {system.num_modes} modes, build {build_s:.1f} s ({build_cpu_s:.1f} s CPU), first "
          f"simulate {first_s:.1f} s ({first_cpu_s:.1f} s CPU), {row['events']} events, {row['status']}",
          flush=True)
    return row


def main():
    from pathlib import Path

    args = sys.argv[1:]
    path = Path(__file__).parent / "results" / "scenes.json"
    old = json.loads(path.read_text()) if path.exists() and args else {}
    rows = {r["K"]: r for r in old.get("rows", [])}
    walker_row = old.get("walker")
    rod_row = old.get("friction_rod")

    def write():
        write_json(
            "scenes",
            {
                "machine": machine_info(),
                "n": N,
                "t1": T1,
                "forms": FORMS,
                "rows": [rows[k] for k in sorted(rows)],
                **({"walker": walker_row} if walker_row else {}),
                **({"friction_rod": rod_row} if rod_row else {}),
            },
        )

    if not args or "walker" in args:
        walker_row = walker()
        write()
    if not args or "rod" in args:
        rod_row = friction_rod()
        write()
    for k in [int(a) for a in args if a.isdigit()] or ([] if args else list(range(1, 9))):
        # The branch form compiles in minutes from K = 4 on (its program grows with the modes built).
        rows[k] = one_k(k, FORMS if k <= BRANCH_UP_TO else FORMS[:1])
        write()


if __name__ == "__main__":
    main()
