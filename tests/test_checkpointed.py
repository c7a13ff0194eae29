"""The per-execution loop's checkpointed while loop against reverse mode through the same
iterations written as a `lax.scan` (an independent route: JAX's own transpose of the unrolled
loop), for several numbers of checkpoints, under `jax.vmap`, and through a closed-over parameter."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hybridjax._engines.checkpointed import checkpointed_while_loop, segment_length

MAX_STEPS = 40


def _body(a):
    def body(c):
        x, v, i, stop = c
        # A data-dependent end: the loop stops once x passes 3 (its iteration count depends on
        # the inputs); `v` rides along without derivatives.
        x_new = x + 0.1 * jnp.sin(a * x) + 0.05 * a
        return x_new, v + 1.0, i + 1, stop | (x_new > 3.0)
    return body


def _loop(x0, a, checkpoints, keep="residuals"):
    c = checkpointed_while_loop(lambda c: ~c[3], _body(a), (x0, jnp.zeros(()), jnp.array(0), jnp.array(False)),
                                max_steps=MAX_STEPS, checkpoints=checkpoints,
                                differentiated=lambda carry: [True, False, False, False], keep=keep)
    return c[0] * c[0] + c[1]


def _scan(x0, a):
    def step(c, _):
        nxt = _body(a)(c)
        return jax.tree_util.tree_map(lambda new, old: jnp.where(c[3], old, new), nxt, c), None

    c = jax.lax.scan(step, (x0, jnp.zeros(()), jnp.array(0), jnp.array(False)), None, length=MAX_STEPS)[0]
    return c[0] * c[0] + c[1]


@pytest.mark.parametrize("keep", ["residuals", "carries"])
@pytest.mark.parametrize("checkpoints", [None, 1, 3, MAX_STEPS])
def test_gradient_equals_reverse_mode_through_the_unrolled_loop(checkpoints, keep):
    x0, a = jnp.asarray(0.2), jnp.asarray(1.3)
    got = jax.jit(jax.grad(_loop, argnums=(0, 1)), static_argnums=(2, 3))(x0, a, checkpoints, keep)
    want = jax.jit(jax.grad(_scan, argnums=(0, 1)))(x0, a)
    np.testing.assert_allclose(got, want, rtol=1e-13)
    assert float(_loop(x0, a, checkpoints)) == pytest.approx(float(_scan(x0, a)), rel=1e-15)


@pytest.mark.parametrize("keep", ["residuals", "carries"])
def test_gradient_under_vmap_and_of_a_closed_over_parameter(keep):
    x0 = jnp.linspace(-0.5, 2.5, 7)
    a = jnp.asarray(0.9)
    got = jax.jit(jax.grad(lambda a: jnp.sum(jax.vmap(lambda x: _loop(x, a, None, keep))(x0))))(a)
    want = jax.jit(jax.grad(lambda a: jnp.sum(jax.vmap(lambda x: _scan(x, a))(x0))))(a)
    np.testing.assert_allclose(got, want, rtol=1e-13)


def test_an_unknown_keep_is_refused():
    with pytest.raises(ValueError, match="keep must be 'residuals' or 'carries'"):
        _loop(jnp.asarray(0.2), jnp.asarray(1.3), None, keep="states")


def test_segment_length():
    assert segment_length(100, None) == 10 and segment_length(101, None) == 11
    assert segment_length(100, 3) == 34 and segment_length(5, 10) == 1


def test_the_default_and_a_checkpoint_budget_give_the_same_gradient():
    # The default runs the loop above; a number of checkpoints given runs equinox's
    # checkpointed loop (a memory budget, diffrax's meaning): two reverse modes, one gradient.
    import diffrax

    import hybridjax as hj

    ball = hj.examples.bouncing_ball()

    def height(x0, e, adjoint):
        return hj.simulate(ball, x0, "flight", 0.0, 2.5, {"g": 9.8, "e": e}, adjoint=adjoint,
                           max_epochs=16).final_state[0]

    x0, e = jnp.array([1.0, 0.3]), jnp.asarray(0.8)
    grad = jax.jit(jax.grad(height, argnums=(0, 1)), static_argnums=2)
    own = grad(x0, e, diffrax.RecursiveCheckpointAdjoint())
    budget = grad(x0, e, diffrax.RecursiveCheckpointAdjoint(checkpoints=16))
    # The truth: the closed form's height at t = 2.5 after its n impacts, differentiated.
    n = len(hj.examples.bouncing_ball_closed_form(1.0, 0.3, 9.8, 0.8, 2.5)["event_times"])

    def closed(x0, e, g=9.8):
        w = jnp.sqrt(x0[1] ** 2 + 2 * g * x0[0])  # the first impact's speed
        t = (x0[1] + w) / g
        for _ in range(n - 1):
            w = e * w
            t = t + 2 * w / g
        s = 2.5 - t
        return e * w * s - 0.5 * g * s * s

    truth = jax.grad(closed, argnums=(0, 1))(x0, e)
    for got in (own, budget):  # the event times' derivatives are exact to ~tol per event
        np.testing.assert_allclose(got[0], truth[0], rtol=1e-10)
        np.testing.assert_allclose(got[1], truth[1], rtol=1e-10)
    # two programs of one gradient: they differ by their roundings alone
    np.testing.assert_allclose(own[0], budget[0], rtol=1e-11)
    np.testing.assert_allclose(own[1], budget[1], rtol=1e-11)


@jax.custom_jvp
def _step_size(x):
    """0.3, and 0.24 where the body is linearised: a recomputation that rounds otherwise than
    the forward pass, exaggerated (its steps differ from the forward pass's)."""
    return 0.3 + 0.0 * x


@_step_size.defjvp
def _step_size_jvp(primals, tangents):
    return 0.24 + 0.0 * primals[0], 0.0 * tangents[0]


def _decay_to_one(a, max_steps, step_size=_step_size):
    """x' = a x from x(0) = 1 in steps of `step_size` up to t = 1: x(1) = e^a however it steps."""
    def body(c):
        t, x, done = c
        t_next = jnp.minimum(t + jax.lax.stop_gradient(step_size(x)), 1.0)
        return t_next, x * jnp.exp(a * (t_next - t)), t_next >= 1.0

    c = checkpointed_while_loop(lambda c: ~c[2], body, (jnp.zeros(()), jnp.ones(()), jnp.array(False)),
                                max_steps=max_steps, checkpoints=None,
                                differentiated=lambda carry: [False, True, False])
    return c[1]


def test_a_recomputed_last_segment_runs_on_to_the_loops_end():
    # The forward pass ends at t = 1 after 4 steps of 0.3; recomputed in steps of 0.24, 4 steps
    # end at t = 0.96 and the gradient would be 0.96 e^(0.96 a): the recomputation goes on to
    # t = 1 (5 steps), where d x(1) / da = e^a.
    a = jnp.asarray(0.7)
    assert float(_decay_to_one(a, 40)) == pytest.approx(np.exp(0.7), rel=1e-14)
    assert float(jax.grad(_decay_to_one)(a, 40)) == pytest.approx(np.exp(0.7), rel=1e-13)


def test_a_loop_stopped_at_max_steps_is_recomputed_to_the_same_step():
    # Two steps of 0.3 where max_steps = 2: x(0.6) = e^(0.6 a). The loop's condition still holds
    # at its end, which is not the end of the run: the recomputation stops where it stopped.
    a = jnp.asarray(0.7)
    grad = jax.grad(_decay_to_one)(a, 2, lambda x: 0.3 + 0.0 * x)
    assert float(grad) == pytest.approx(0.6 * np.exp(0.42), rel=1e-13)


def test_recomputed_length():
    from hybridjax._engines.checkpointed import recomputed_length

    def running():
        return jnp.array(True)

    # every forward iteration, whether the loop's condition holds or not
    assert bool(recomputed_length(2, 3, 3, lambda: jnp.array(False)))
    # past them only while the condition holds, and only up to `extended_to`
    assert bool(recomputed_length(4, 3, 5, running)) and not bool(recomputed_length(5, 3, 5, running))
    assert not bool(recomputed_length(3, 3, 5, lambda: jnp.array(False)))
    assert not bool(recomputed_length(3, 3, 3, running))  # not the last segment
