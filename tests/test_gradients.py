"""Derivatives through the epoch loop, against closed forms and finite differences."""

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj

from helpers import BALL, BALL_ARGS, CEILING, TIGHT, ball_reference, ball_runner, central_difference


def test_event_time_gradient_matches_the_implicit_function_theorem():
    # t1 = (v0 + sqrt(v0^2 + 2 g h0)) / g; the second impact t2 = t1 + 2 e w / g.
    def times(h0, v0, g, e):
        sol = ball_runner(3.0)(jnp.stack([h0, v0]), {"g": g, "e": e})
        return sol.event_times[:2]

    point = (1.0, 0.5, 9.8, 0.8)
    J = jax.jit(jax.jacrev(times, argnums=(0, 1, 2, 3)))(*map(jnp.asarray, point))

    def closed(h0, v0, g, e):
        w = math.sqrt(v0 * v0 + 2 * g * h0)
        t1 = (v0 + w) / g
        return np.array([t1, t1 + 2 * e * w / g])

    fd = central_difference(lambda p: closed(*p), np.array(point))
    np.testing.assert_allclose(np.stack(J, axis=-1), fd, rtol=1e-6)


def test_final_state_jacobian_reverse_forward_and_finite_differences():
    # d x(T) / d (h0, v0, e) after several bounces: jacrev, jacfwd, and central differences
    # of the closed form agree.
    p0 = jnp.array([1.0, 0.3, 0.8])

    def final(p, adjoint):
        return ball_runner(2.0, adjoint=adjoint)(p[:2], {"g": 9.8, "e": p[2]}).final_state

    J_rev = jax.jit(jax.jacrev(lambda p: final(p, "checkpointed")))(p0)
    J_fwd = jax.jit(jax.jacfwd(lambda p: final(p, "forward")))(p0)
    fd = central_difference(lambda p: ball_reference(p[0], p[1], 9.8, p[2], 2.0)["final_state"],
                            np.asarray(p0))
    assert int(ball_runner(2.0)(p0[:2], BALL_ARGS).num_events) >= 3
    np.testing.assert_allclose(J_rev, fd, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(J_fwd, J_rev, rtol=1e-9, atol=1e-12)


def test_gradient_with_respect_to_t0_and_t1():
    def final(t0, t1):
        return hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", t0, t1, BALL_ARGS,
                           stepsize_controller=TIGHT).final_state

    d0, d1 = jax.jit(jax.jacrev(final, argnums=(0, 1)))(jnp.asarray(0.0), jnp.asarray(1.0))
    # autonomous: shifting t0 shifts the execution, d x(t1)/d t0 = -d x(t1)/d t1 = -F(x(t1))
    x1 = ball_reference(1.0, 0.0, 9.8, 0.8, 1.0)["final_state"]
    np.testing.assert_allclose(d1, [x1[1], -9.8], rtol=1e-8)
    np.testing.assert_allclose(d0, [-x1[1], 9.8], rtol=1e-8)


def test_derivatives_when_the_last_step_lands_on_t1_to_the_last_bit():
    # Constant steps of 0.25 from 0 end at t1 = 1 exactly (0.75 + 0.25 = 1.0): the final state
    # is x(t1), whose derivatives are the closed form's in full, with t1's tangent (not half of
    # t's, as min(t + h, t1) would give at the tie). No impact before t1:
    # h(t1) = h0 + v0 T - g T^2 / 2, T = t1 - t0; v(t1) = v0 - g T.
    steps = dict(stepsize_controller=diffrax.ConstantStepSize(), dt0=0.25)

    def one(p):  # p = (h0, v0, g, t0, t1)
        return hj.simulate(BALL, p[:2], "flight", p[3], p[4], {"g": p[2], "e": 0.8}, **steps).final_state

    def batch(p):  # two executions on the per-execution engine under jax.vmap, called directly
        x0 = jnp.stack([p[:2], p[:2] + jnp.array([1.0, 0.0])])
        return hj.simulate_batch(BALL, x0, "flight", p[3], p[4], {"g": p[2], "e": 0.8}, engine="vmap",
                                 **steps).final_state

    p = jnp.array([10.0, 0.5, 9.8, 0.0, 1.0])
    v1 = 0.5 - 9.8
    exact = np.array([[1.0, 1.0, -0.5, -v1, v1], [0.0, 1.0, -1.0, 9.8, -9.8]])
    np.testing.assert_allclose(jax.jacfwd(one)(p), exact, rtol=1e-12, atol=1e-12)
    J = jax.jacrev(batch)(p)
    np.testing.assert_allclose(J, np.stack([exact, exact]), rtol=1e-12, atol=1e-12)
    # Adaptive steps made to end at a step time equal to t1 (diffrax's `step_ts`): the same
    # tie, d (h, v)(t1) / d t1 = (v(t1), -g) and d final_time / d t1 = 1.
    to_knots = diffrax.PIDController(rtol=1e-10, atol=1e-10, step_ts=jnp.array([0.5, 1.0]))

    def ends(t1):
        sol = hj.simulate(BALL, p[:2], "flight", 0.0, t1, {"g": 9.8, "e": 0.8}, stepsize_controller=to_knots)
        return jnp.concatenate([sol.final_state, sol.final_time[None]])

    np.testing.assert_allclose(jax.jacfwd(ends)(jnp.asarray(1.0)), [v1, -9.8, 1.0], rtol=1e-9)


def test_derivatives_of_a_save_at_t1():
    # The state saved at t1 is x(t1): d/dt1 = F(x(t1)) = (v(t1), -g), with v(t1) = -g t1 for a
    # ball dropped from h0 = 10 (no impact before t1 = 1); the save at 0.5 does not move with t1.
    # Both engines: the per-execution loop and the batched one.
    def saved(engine):
        def ys(t1):
            saveat = diffrax.SaveAt(ts=jnp.stack([jnp.asarray(0.5), t1]))
            kw = dict(saveat=saveat, stepsize_controller=TIGHT)
            if engine == "simulate":
                return hj.simulate(BALL, jnp.array([10.0, 0.0]), "flight", 0.0, t1, BALL_ARGS, **kw).ys
            return hj.simulate_batch(BALL, jnp.array([[10.0, 0.0]]), "flight", 0.0, t1, BALL_ARGS, engine="batched",
                                     **kw).ys[0]
        return ys

    exact = np.array([[0.0, 0.0], [-9.8, -9.8]])
    np.testing.assert_allclose(jax.jacfwd(saved("simulate"))(jnp.asarray(1.0)), exact, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(jax.jacrev(saved("simulate_batch"))(jnp.asarray(1.0)), exact, rtol=1e-9, atol=1e-12)


def test_derivatives_when_the_run_reaches_t1_at_an_epochs_start():
    # t1 = t0: the final state and the save at t1 are x0, and their derivatives those of the
    # flow continued past t0: d/dt1 = F(x0) = (v0, -g), d/dt0 = -F(x0). A ball on the floor
    # moving down bounces at t0 (a zero-length epoch) and ends at its reset state (0, e |v0|):
    # d/dt1 = (e |v0|, -g). Both engines.
    def run(engine):
        def out(x0, t0, t1):
            kw = dict(saveat=diffrax.SaveAt(t1=True), stepsize_controller=TIGHT)
            if engine == "simulate":
                sol = hj.simulate(BALL, x0, "flight", t0, t1, BALL_ARGS, **kw)
                return jnp.stack([sol.final_state, sol.ys[-1]])
            sol = hj.simulate_batch(BALL, x0[None], "flight", t0, t1, BALL_ARGS, engine="batched", **kw)
            return jnp.stack([sol.final_state[0], sol.ys[0, -1]])
        return jax.jit(jax.jacrev(out, argnums=(1, 2)))

    zero = jnp.asarray(0.0)
    F = np.array([0.5, -9.8])
    for engine in ("simulate", "batched"):
        d0, d1 = run(engine)(jnp.array([1.0, 0.5]), zero, zero)
        np.testing.assert_allclose(d1, np.stack([F, F]), rtol=1e-12)
        np.testing.assert_allclose(d0, -np.stack([F, F]), rtol=1e-12)
    _, d1 = run("simulate")(jnp.array([0.0, -1.0]), zero, zero)
    np.testing.assert_allclose(d1[0], [0.8, -9.8], rtol=1e-12)


def test_zero_length_epoch_chain_sensitivity_ceiling():
    # d v(T) / d v0 = g dt*/dv0 = -g t*/v* = 1 - sqrt(5) for z0 = 0, v0 = 7, H = 2, g = 9.8, T = 1.
    p = {"g": 9.8, "H": 2.0}
    J = jax.jacrev(lambda x0: hj.simulate(CEILING, x0, "flight", 0.0, 1.0, p,
                                          stepsize_controller=TIGHT).final_state)(jnp.array([0.0, 7.0]))
    np.testing.assert_allclose(J[1, 1], 1 - math.sqrt(5), rtol=1e-8)
    assert np.all(np.isfinite(np.asarray(J)))


def test_padding_never_poisons_gradients():
    # 2 events recorded of 16 slots; the sum over all slots (padding masked) has a finite
    # gradient, and the padded slots contribute nothing.
    def loss(h0):
        sol = ball_runner(1.5, max_epochs=16)(jnp.stack([h0, 0.0]), BALL_ARGS)
        valid = jnp.arange(16) < sol.num_events
        return jnp.sum(jnp.where(valid, sol.event_times, 0.0))

    g = jax.grad(loss)(jnp.asarray(1.0))
    ref = ball_reference(1.0, 0.0, 9.8, 0.8, 1.5)
    n = len(ref["event_times"])
    # each impact time scales with sqrt(h0): d/dh0 sum t_i = sum t_i / (2 h0)
    np.testing.assert_allclose(g, np.sum(ref["event_times"][:n]) / 2, rtol=1e-8)


def test_vmap_of_grad_over_initial_heights():
    h0 = jnp.linspace(0.5, 1.5, 32)
    f = lambda h: ball_runner(1.2)(jnp.stack([h, 0.0 * h]), BALL_ARGS).final_state[0]  # noqa: E731
    g = jax.jit(jax.vmap(jax.grad(f)))(h0)
    fd = np.array([central_difference(
        lambda x: ball_reference(x[0], 0.0, 9.8, 0.8, 1.2)["final_state"][:1], np.array([h]))[0, 0]
        for h in np.asarray(h0)])
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7)


def test_solver_options_are_diffrax_objects():
    sol = hj.simulate(BALL, jnp.array([1.0, 0.0]), "flight", 0.0, 1.0, BALL_ARGS,
                      solver=diffrax.Dopri8(), stepsize_controller=TIGHT)
    np.testing.assert_allclose(sol.event_times[0], math.sqrt(2 / 9.8), atol=1e-12)


def test_gradient_wrt_a_guard_parameter_and_of_saved_states():
    # Mode I (p, q) flows at (a, r) until p = c t; then x = p + q + b t in mode J, flowing at d.
    # t* = p0 / (c - a); a saved state after the event: x(s) = p0 + q0 + (a + r + b) t* + d (s - t*).
    I = hj.Mode("I", lambda t, x, k: jnp.array([k["a"] + 0.0 * x[0], k["r"] + 0.0 * x[1]]), dim=2)
    J = hj.Mode("J", lambda t, x, k: jnp.array([k["d"] + 0.0 * x[0]]), dim=1)
    sys = hj.HybridSystem([I, J], [hj.Transition(
        "I", "J", guard=lambda t, x, k: x[0] - k["c"] * t,
        reset=lambda t, x, k: jnp.array([x[0] + x[1] + k["b"] * t]))])
    k0 = dict(a=-1.0, r=0.5, c=0.75, b=2.0, d=-0.3)
    x0 = jnp.array([1.75, -0.3])

    def outs(k):
        sol = hj.simulate(sys, x0, "I", 0.0, 2.0, k, stepsize_controller=TIGHT, saveat=jnp.array([1.5]))
        return sol.event_times[0], sol.ys[0, 0]

    (dt_dk, dys_dk) = jax.jit(jax.jacrev(outs))(k0)
    a, r, c, b, d = (k0[n] for n in "arcbd")
    p0, s = 1.75, 1.5
    t_star = p0 / (c - a)
    np.testing.assert_allclose(dt_dk["c"], -p0 / (c - a) ** 2, rtol=1e-9)
    np.testing.assert_allclose(dt_dk["a"], p0 / (c - a) ** 2, rtol=1e-9)
    np.testing.assert_allclose(dys_dk["c"], (a + r + b - d) * (-p0 / (c - a) ** 2), rtol=1e-9)
    np.testing.assert_allclose(dys_dk["b"], t_star, rtol=1e-9)
    np.testing.assert_allclose(dys_dk["d"], s - t_star, rtol=1e-9)


@pytest.mark.parametrize("engine", ["per-execution", "batched"])
def test_the_loop_starts_with_the_derivatives_its_body_gives(engine):
    # equinox's checkpointed loop finds which carried values carry a derivative by
    # differentiating the body until the set stops growing (`_resolve_perturb_val`): the oracle
    # here. Each engine's loop starts from that set (`perturbed_like_the_body`): the search's
    # first round must find it unchanged, whether x0 or args is differentiated. The
    # per-execution loop's own checkpointed loop differentiates exactly the leaves its list
    # names (`differentiated_leaves`), so the list must be that set: run here through equinox's
    # loop, the list's leaves are compared with what equinox finds. A field added to the state
    # and missing from the engine's list (`DIFFERENTIABLE_FIELDS`, `LANE_DIFFERENTIABLE_FIELDS`)
    # shows here as a difference.
    import equinox.internal as eqxi
    from equinox.internal._loop import checkpointed

    from hybridjax._engines import loop as loop_module

    found, listed = [], []
    resolve = checkpointed._resolve_perturb_val

    def recording(final_val, body_fun, perturb_val, perturb_body_fun):
        out = resolve(final_val, body_fun, perturb_val, perturb_body_fun)
        found.append((jax.tree_util.tree_leaves(perturb_val), jax.tree_util.tree_leaves(out)))
        return out

    def through_equinox(cond, body, carry, *, max_steps, checkpoints, differentiated, keep):
        listed.append(differentiated(carry))
        return eqxi.while_loop(cond, body, carry, max_steps=max_steps, kind="checkpointed")

    def height(x0, args):
        if engine == "batched":
            return hj.simulate_batch(BALL, x0[None], "flight", 0.0, 2.0, args, engine="batched").final_state[0, 0]
        return hj.simulate(BALL, x0, "flight", 0.0, 2.0, args).final_state[0]

    x0, args = jnp.array([1.0, 0.3]), {"g": jnp.asarray(9.8), "e": jnp.asarray(0.8)}
    own_loop = loop_module.checkpointed_while_loop
    checkpointed._resolve_perturb_val = recording
    loop_module.checkpointed_while_loop = through_equinox
    try:
        jax.make_jaxpr(jax.grad(height, argnums=0))(x0, args)
        jax.make_jaxpr(jax.grad(height, argnums=1))(x0, args)
    finally:
        checkpointed._resolve_perturb_val = resolve
        loop_module.checkpointed_while_loop = own_loop
    assert len(found) == 2
    for start, fixed in found:
        assert sum(fixed) > 2  # the record carries derivatives
        assert start == fixed
    if engine == "per-execution":
        # equinox's carry holds its own counters before the loop's (no derivatives)
        assert [fixed[-len(mine):] for mine, (_, fixed) in zip(listed, found, strict=True)] == listed
        assert not any(any(fixed[:-len(mine)]) for mine, (_, fixed) in zip(listed, found, strict=True))
