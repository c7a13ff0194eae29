"""Hybrid iLQR against gradient descent through `simulate` (optax) on the same problems.

Both minimise the same cost of the same discrete problem: controls held constant on the
intervals of a time grid, each interval one hybrid execution (`simulate`), a quadratic cost on
the states at the grid times. Hybrid iLQR: `hj.hybrid_ilqr` (saltation matrices in the
backward pass, reference extension). Gradient descent: `optax.adam` on `jax.grad` of the
rolled-out cost (reverse mode through every interval's `simulate`), one jitted step, at three
learning rates.

- ball: the bouncing ball with a vertical thrust tracks the passive ball (one impact) on 20
  intervals over [0, 1], from u = 2.5 (impact one interval late); the optimum is u = 0, cost 0.
- hopper: a vertical hopper (leg spring, thrust in stance in [0, 60]) dropped from an apex at 1.2
  must be at an apex of 1.5 at t = 0.9 (18 intervals).

For each: the cost after each iteration, the iterations and wall time (compile excluded: every
method runs once before it is timed) to reach 1e-4 of the initial cost, the final cost, and how
many gradient-descent iterates had an interval whose execution stopped before its end time
(MAX_EPOCHS with more than two events in one interval, ZENO, ...): their cost is not that of the
discrete problem. Hybrid iLQR discards such trial rollouts.

    python benchmarks/trajopt.py          # prints a table, writes results/trajopt.json
"""

import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from _common import machine_info, write_json

import hybridjax as hj
from hybridjax._optimise.ilqr import _initial, _rollout

jax.config.update("jax_enable_x64", True)
G = 9.8


def ball_problem():
    ball = hj.HybridSystem(
        [hj.Mode("flight", lambda t, x, a: jnp.stack([x[1], -a["g"] + a["u"][0]]), dim=2)],
        [hj.Transition("flight", "flight", guard=lambda t, x, a: x[0],
                       reset=lambda t, x, a: x.at[1].multiply(-a["e"]), name="bounce")])
    n, ts = 20, jnp.linspace(0.0, 1.0, 21)
    cargs = lambda u: {"g": G, "e": 0.8, "u": u}
    Q = jnp.diag(jnp.array([10.0, 1.0]))
    x0 = jnp.array([1.0, 0.0])
    ref = _initial(hj.HybridILQR(ball, cargs, x0, "flight", ts, jnp.zeros((n + 1, 2)), Q, 1e-3, 10 * Q),
                   jnp.zeros((n, 1))).xs
    problem = hj.HybridILQR(ball, cargs, x0, "flight", ts, ref, Q, 1e-3, 10 * Q)
    return problem, jnp.full((n, 1), 2.5), (0.03, 0.1, 0.3)


def hopper_problem():
    hopper = hj.HybridSystem(
        [hj.Mode("flight", lambda t, x, a: jnp.stack([x[1], -a["g"] + 0.0 * x[1]]), dim=2),
         hj.Mode("stance", lambda t, x, a: jnp.stack([x[1], a["k"] * (a["l0"] - x[0]) - a["g"] + a["u"][0]]),
                 dim=2)],
        [hj.Transition("flight", "stance", guard=lambda t, x, a: x[0] - a["l0"], name="touchdown"),
         hj.Transition("stance", "flight", guard=lambda t, x, a: a["l0"] - x[0], name="liftoff")])
    n, ts = 18, jnp.linspace(0.0, 0.9, 19)
    target = jnp.zeros((n + 1, 2)).at[-1].set(jnp.array([1.5, 0.0]))
    problem = hj.HybridILQR(hopper, lambda u: {"g": G, "k": 100.0, "l0": 1.0, "u": u}, jnp.array([1.2, 0.0]),
                                  "flight", ts, target, jnp.zeros((2, 2)), 1e-4, 1e3 * jnp.eye(2),
                                  bounds=(0.0, 60.0))
    return problem, jnp.zeros((n, 1)), (0.3, 1.0, 3.0)


def run_ilqr(problem, u0, iterations):
    hj.hybrid_ilqr(problem, u0, iterations=iterations)  # compiles
    t = time.perf_counter()
    res = hj.hybrid_ilqr(problem, u0, iterations=iterations)
    wall = time.perf_counter() - t
    costs = np.asarray(res.costs)
    return costs, wall / max(len(costs) - 1, 1), 0  # its rollouts keep only complete trials


def run_gd(problem, u0, lr, steps):
    opt = optax.adam(lr)

    def rollout(u):
        roll = _rollout(problem, lambda k, x, c: u[k])
        # every interval must reach its end time (no MAX_EPOCHS, ZENO, ... inside one)
        return roll.cost, jnp.all(roll.status == 0)

    @jax.jit
    def step(u, state):
        (cost, complete), g = jax.value_and_grad(rollout, has_aux=True)(u)
        updates, state = opt.update(g, state, u)
        return problem.clip(optax.apply_updates(u, updates)), state, cost, complete

    # compiles: the arguments' weak types change over the first calls (`init`'s state, then
    # `update`'s), each change a new program: a few untimed steps compile them all
    u, state = u0, opt.init(u0)
    for _ in range(5):
        u, state = step(u, state)[:2]
    jax.block_until_ready(u)
    u, state, costs, incomplete = u0, opt.init(u0), [], 0
    t = time.perf_counter()
    for _ in range(steps):
        u, state, cost, complete = step(u, state)
        costs.append(float(cost))
        incomplete += not bool(complete)
    wall = time.perf_counter() - t
    costs.append(float(jax.jit(rollout)(u)[0]))
    return np.asarray(costs), wall / steps, incomplete


def reach(costs, target, per_iteration):
    hit = np.flatnonzero(costs <= target)
    return (int(hit[0]), float(hit[0] * per_iteration)) if hit.size else (None, None)


def main():
    out = dict(machine=machine_info(), target_fraction=1e-4, problems=[])
    for name, make, ilqr_iters, gd_steps in (("ball", ball_problem, 10, 300), ("hopper", hopper_problem, 10, 300)):
        problem, u0, lrs = make()
        rows = {}
        runs = [("hybrid iLQR", run_ilqr(problem, u0, ilqr_iters))]
        runs += [(f"adam (lr {lr:g})", run_gd(problem, u0, lr, gd_steps)) for lr in lrs]
        for method, (costs, per, incomplete) in runs:
            target = out["target_fraction"] * costs[0]
            its, secs = reach(costs, target, per)
            rows[method] = dict(costs=costs.tolist(), per_iteration_s=per, iterations_to_target=its,
                                seconds_to_target=secs, final_cost=float(costs[-1]), iterations=len(costs) - 1,
                                incomplete_iterates=incomplete)
            print(f"{name:7s} {method:16s} to 1e-4: {its} it, {secs} s; final {costs[-1]:.3e} "
                  f"after {len(costs) - 1} it ({per * 1e3:.1f} ms/it), {incomplete} incomplete")
        out["problems"].append(dict(name=name, initial_cost=float(rows["hybrid iLQR"]["costs"][0]), methods=rows))
    write_json("trajopt", out)


if __name__ == "__main__":
    main()
