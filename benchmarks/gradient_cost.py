"""Cost of a gradient through the epoch loop relative to the forward solve, and memory.

Bouncing ball (e = 0.8, h0 ~ U(0.5, 1.5), v0 ~ U(-1, 1), T = 2.5, Tsit5, rtol = atol = 1e-9,
float64). For batch sizes 1 and 1,000, with `jax.vmap(hj.simulate)` and with the batched engine
(`hj.simulate_batch`; also 10,000): forward solve; reverse mode (jax.grad of the summed final
state w.r.t. x0 and e, checkpointed loop); forward mode (every execution's 2 x 3 Jacobian w.r.t.
(x0, e) by jax.jacfwd, ForwardMode loop). The batched engine's reverse pass takes all lanes as
its block by default; rows "block = forward default" give it the forward solve's default block
(passes over blocks, a checkpointed loop nested in the main one) for comparison. Then the
compiled temporary memory of reverse mode against the number of epochs.

    python benchmarks/gradient_cost.py          # prints tables, writes results/gradient_cost.json
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
from _common import machine_info, timed, write_json

import hybridjax as hj
from hybridjax._engines.lanes import default_block

jax.config.update("jax_enable_x64", True)
BALL = hj.examples.bouncing_ball()
CTRL = diffrax.PIDController(rtol=1e-9, atol=1e-9)


def make(t1, max_epochs, adjoint):
    def final(x0, e):
        return hj.simulate(BALL, x0, "flight", 0.0, t1, {"g": 9.8, "e": e}, stepsize_controller=CTRL,
                           max_epochs=max_epochs, adjoint=adjoint).final_state
    return final


def make_batch(adjoint, block=None):
    def final(x0, e):
        return hj.simulate_batch(BALL, x0, "flight", 0.0, 2.5, {"g": jnp.full_like(e, 9.8), "e": e},
                                 args_batched=True, stepsize_controller=CTRL, max_epochs=32,
                                 adjoint=adjoint, block=block).final_state
    return final


def batched_jacobians(x0, e):
    """(N, 2, 3): each execution's Jacobian of its final state w.r.t. (h0, v0, e). Executions are
    independent, so three forward-mode tangents (the same direction in every execution) give
    every execution's Jacobian at once."""
    final = make_batch(diffrax.ForwardMode())
    return jax.jacfwd(lambda c: final(x0 + c[:2], e + c[2]))(jnp.zeros(3))


def batched_jvp(x0, e):
    """Every execution's final state and its derivative along one direction of (h0, v0, e)."""
    final = make_batch(diffrax.ForwardMode())
    return jax.jvp(final, (x0, e), (jnp.ones_like(x0), jnp.ones_like(e)))


def main():
    rng = np.random.default_rng(0)
    rows = []
    for n in (1, 1000, 10_000):
        x0 = jnp.asarray(np.stack([rng.uniform(0.5, 1.5, n), rng.uniform(-1, 1, n)], axis=1))
        e = jnp.full((n,), 0.8)
        if n > 1:
            # The batched engine's reverse pass with the forward solve's default block.
            block = default_block(n)
            p_solve = jax.jit(make_batch(diffrax.RecursiveCheckpointAdjoint(), block))
            p_rev = jax.jit(jax.grad(lambda x, e: jnp.sum(
                make_batch(diffrax.RecursiveCheckpointAdjoint(), block)(x, e)), argnums=(0, 1)))
            c0, t0, _ = timed(p_solve, x0, e)
            c1, t1, _ = timed(p_rev, x0, e)
            rows.append(dict(engine=f"simulate_batch, block = forward default ({block})", batch=n,
                             forward_s=t0, reverse_s=t1, reverse_ratio=t1 / t0, compile_forward_s=c0,
                             compile_reverse_s=c1))
        fwd_solve = jax.jit(jax.vmap(make(2.5, 32, diffrax.RecursiveCheckpointAdjoint())))
        rev = jax.jit(jax.vmap(jax.grad(lambda x, e: jnp.sum(make(2.5, 32, diffrax.RecursiveCheckpointAdjoint())(x, e)),
                                        argnums=(0, 1))))
        fwd = jax.jit(jax.vmap(jax.jacfwd(make(2.5, 32, diffrax.ForwardMode()), argnums=(0, 1))))
        one = make(2.5, 32, diffrax.ForwardMode())
        jvp = jax.jit(jax.vmap(lambda x, e: jax.jvp(one, (x, e), (jnp.ones_like(x), jnp.ones_like(e)))))
        b_solve = jax.jit(make_batch(diffrax.RecursiveCheckpointAdjoint()))
        b_rev = jax.jit(jax.grad(lambda x, e: jnp.sum(make_batch(diffrax.RecursiveCheckpointAdjoint())(x, e)),
                                 argnums=(0, 1)))
        b_fwd = jax.jit(batched_jacobians)
        b_jvp = jax.jit(batched_jvp)
        engines = [("simulate_batch", (b_solve, b_rev, b_fwd, b_jvp))]
        if n <= 1000:  # vmap(simulate)'s reverse pass at 10,000: minutes, to no new end
            engines.insert(0, ("vmap(simulate)", (fwd_solve, rev, fwd, jvp)))
        for engine, (f0, f1, f2, f3) in engines:
            c0, t0, _ = timed(f0, x0, e)
            c1, t1, _ = timed(f1, x0, e)
            c2, t2, _ = timed(f2, x0, e)
            c3, t3, _ = timed(f3, x0, e)
            rows.append(dict(engine=engine, batch=n, forward_s=t0, reverse_s=t1, jacfwd_s=t2, jvp_s=t3,
                             reverse_ratio=t1 / t0, jacfwd_ratio=t2 / t0, jvp_ratio=t3 / t0,
                             compile_forward_s=c0, compile_reverse_s=c1, compile_jacfwd_s=c2, compile_jvp_s=c3))
    print("gradient cost relative to the forward solve (bouncing ball, T = 2.5, ~5 events)")
    print(f"{'engine':>15} {'batch':>6} {'forward s':>10} {'grad (rev) s':>13} {'ratio':>6} {'jvp s':>8} {'ratio':>6}"
          f" {'jacfwd s':>9} {'ratio':>6} {'compile f/r/jvp/fwd s':>22}")
    for r in rows:
        fwd_mode = (f" {r['jvp_s']:>8.4f} {r['jvp_ratio']:>6.1f} {r['jacfwd_s']:>9.4f} {r['jacfwd_ratio']:>6.1f}"
                    if "jvp_s" in r else f" {'-':>8} {'-':>6} {'-':>9} {'-':>6}")
        compiles = "/".join(f"{r[k]:.1f}" if k in r else "-" for k in
                            ("compile_forward_s", "compile_reverse_s", "compile_jvp_s", "compile_jacfwd_s"))
        print(f"{r['engine']:>15} {r['batch']:>6} {r['forward_s']:>10.4f} {r['reverse_s']:>13.4f} {r['reverse_ratio']:>6.1f}"
              f"{fwd_mode}   {compiles}")

    mem = []
    x = jnp.array([1.0, 0.0])
    for epochs in (4, 16, 64):
        # e close to 1 keeps the bounces long, so `epochs` of them fit before T.
        t1 = 0.9 * epochs * 2 * np.sqrt(2 / 9.8)
        g = jax.jit(jax.grad(lambda x: jnp.sum(make(t1, epochs, diffrax.RecursiveCheckpointAdjoint())(x, 0.999))))
        compiled = g.lower(x).compile()
        ma = compiled.memory_analysis()
        n_ev = int(hj.simulate(BALL, x, "flight", 0.0, t1, {"g": 9.8, "e": 0.999}, stepsize_controller=CTRL,
                               max_epochs=epochs).num_events)
        mem.append(dict(max_epochs=epochs, events=n_ev, temp_bytes=int(ma.temp_size_in_bytes)))
    print("\nreverse-mode compiled temporary memory against the number of epochs (one execution)")
    print(f"{'max_epochs':>10} {'events':>7} {'temp MiB':>9}")
    for m in mem:
        print(f"{m['max_epochs']:>10} {m['events']:>7} {m['temp_bytes'] / 2**20:>9.2f}")
    path = write_json("gradient_cost", dict(machine=machine_info(), cost=rows, memory=mem))
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
