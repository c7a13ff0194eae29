"""Calls outside `jax.jit` (also under `jax.grad`, `jax.jvp`, `jax.vmap`, ...): compiled once per
configuration and reused (`hybridjax._eager`), with the same results and the same errors as the
plain call.

A flow that counts its traced calls (`helpers.with_trace_counter`) tells whether a call traced
the problem again; every result is checked against the ball's closed form."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj

from helpers import TIGHT, ball_reference, central_difference, compile_count, with_trace_counter


def counting_ball():
    """The bouncing ball, with a flow that records each time it is traced."""
    return with_trace_counter(hj.examples.bouncing_ball())


def final_states(sol):
    return np.atleast_2d(np.asarray(sol.final_state))


def expected(x0s, g, e, t1):
    return np.array([ball_reference(h, v, g, e, t1)["final_state"] for h, v in np.atleast_2d(x0s)])


def run(name, system, x0, args, t1=1.5):
    fn = hj.simulate if name == "simulate" else hj.simulate_batch
    return fn(system, x0, "flight", 0.0, t1, args, stepsize_controller=TIGHT, max_epochs=16)


STATES = {"simulate": (np.array([1.0, 0.0]), np.array([0.7, 0.4])),
          "simulate_batch": (np.array([[1.0, 0.0], [0.6, -0.5]]), np.array([[0.7, 0.4], [1.2, 0.9]]))}


@pytest.mark.parametrize("name", STATES)
def test_a_second_call_reuses_the_compiled_program(name):
    system, calls = counting_ball()
    args = {"g": jnp.asarray(9.8), "e": jnp.asarray(0.8)}
    first, second = STATES[name]
    sol = run(name, system, first, args)
    traced = len(calls)
    assert traced > 0
    np.testing.assert_allclose(final_states(sol), expected(first, 9.8, 0.8, 1.5), rtol=1e-7, atol=1e-7)
    # New initial states and new parameter values, same shapes: no new trace.
    sol = run(name, system, second, {"g": jnp.asarray(9.0), "e": jnp.asarray(0.6)})
    assert len(calls) == traced
    np.testing.assert_allclose(final_states(sol), expected(second, 9.0, 0.6, 1.5), rtol=1e-7, atol=1e-7)
    assert np.all(np.asarray(sol.status == hj.Status.T1_REACHED))


def test_a_changed_python_number_is_compiled_anew_not_reused():
    # Python numbers are part of the program (constants): a changed one must not reuse it.
    system, calls = counting_ball()
    x0 = STATES["simulate"][0]
    sols = {e: run("simulate", system, x0, {"g": 9.8, "e": e}) for e in (0.8, 0.6)}
    for e, sol in sols.items():
        np.testing.assert_allclose(final_states(sol), expected(x0, 9.8, e, 1.5), rtol=1e-7, atol=1e-7)
    traced = len(calls)
    sol = run("simulate", system, x0, {"g": 9.8, "e": np.float64(0.6)}, t1=1.2)  # a NumPy scalar too
    np.testing.assert_allclose(final_states(sol), expected(x0, 9.8, 0.6, 1.2), rtol=1e-7, atol=1e-7)
    assert len(calls) > traced


def test_a_list_initial_state_is_an_input_not_a_constant():
    system, calls = counting_ball()
    args = {"g": jnp.asarray(9.8), "e": jnp.asarray(0.8)}
    run("simulate", system, [1.0, 0.0], args)
    traced = len(calls)
    sol = run("simulate", system, [0.7, 0.4], args)
    assert len(calls) == traced
    np.testing.assert_allclose(final_states(sol), expected([0.7, 0.4], 9.8, 0.8, 1.5), rtol=1e-7, atol=1e-7)


def test_an_input_needed_concrete_falls_back_to_the_plain_call():
    # simulate_batch reads a scalar mode0 as a Python integer to pad a short x0 (a wall
    # particle of 1 component in a system of 2): as a traced NumPy array it cannot, and the
    # plain call runs instead, with the same result.
    sys2 = hj.HybridSystem([hj.Mode("short", lambda t, x, p: jnp.ones_like(x), dim=1),
                            hj.Mode("long", lambda t, x, p: jnp.zeros_like(x), dim=2)], [])
    sol = hj.simulate_batch(sys2, np.array([[0.5], [1.0]]), np.array(0), 0.0, 2.0)
    np.testing.assert_allclose(np.asarray(sol.final_state), [[2.5, 0.0], [3.0, 0.0]], rtol=1e-9)


@pytest.mark.parametrize("name", STATES)
def test_t1_before_t0_as_arrays_is_still_refused_at_the_call(name):
    system, _ = counting_ball()
    fn = hj.simulate if name == "simulate" else hj.simulate_batch
    with pytest.raises(ValueError, match=f"{name}: t1 must be >= t0"):
        fn(system, STATES[name][0], "flight", np.asarray(1.0), jnp.asarray(0.5), {"g": 9.8, "e": 0.8})


def test_calls_inside_jit_compile_with_their_caller():
    # Inside jax.jit the call is traced with its caller's program; the derivative of the final
    # height with respect to h0 before the first impact is 1 (free fall).
    system, _ = counting_ball()

    def height(h0):
        return hj.simulate(system, jnp.array([h0, 0.0]), "flight", 0.0, 0.2, {"g": 9.8, "e": 0.8},
                           stepsize_controller=TIGHT, max_epochs=4).final_state[0]

    assert abs(float(jax.jit(jax.grad(height))(1.0)) - 1.0) < 1e-9


# Calls under jax.grad, jax.jvp, jax.jacfwd and jax.vmap made outside jax.jit: one counted ball,
# g and e as arrays, t1 = 1.5 (three impacts from h0 = 1, two from (0.7, 0.4)).
COUNTED, COUNTED_TRACES = counting_ball()
ARRAY_ARGS = {"g": jnp.asarray(9.8), "e": jnp.asarray(0.8)}
TANGENT = jnp.array([0.3, -1.0])


def final_state(x0, adjoint=diffrax.RecursiveCheckpointAdjoint()):
    return hj.simulate(COUNTED, x0, "flight", 0.0, 1.5, ARRAY_ARGS, stepsize_controller=TIGHT,
                       max_epochs=16, adjoint=adjoint).final_state


def closed_form_jacobian(x0):
    """d final_state / d x0 by central differences of the closed form."""
    return central_difference(lambda x: ball_reference(x[0], x[1], 9.8, 0.8, 1.5)["final_state"], x0)


TRANSFORMED = {
    # name: (the call, its value from the closed form)
    "grad": (lambda x0: jax.grad(lambda x: final_state(x)[0])(x0), lambda x0: closed_form_jacobian(x0)[0]),
    "jvp, ForwardMode": (
        lambda x0: jax.jvp(lambda x: final_state(x, diffrax.ForwardMode()), (x0,), (TANGENT,))[1],
        lambda x0: closed_form_jacobian(x0) @ np.asarray(TANGENT)),
    "jacfwd, default adjoint": (jax.jacfwd(final_state), closed_form_jacobian),
    # Reverse mode alone runs its own forward and backward programs (compiled with XLA options
    # of their own); jax.jacrev batches the backward one.
    "jacrev": (jax.jacrev(final_state), closed_form_jacobian),
    "vmap": (lambda x0: jax.vmap(final_state)(jnp.stack([x0, x0 + 0.2])),
             lambda x0: expected(np.stack([x0, x0 + 0.2]), 9.8, 0.8, 1.5)),
}


@pytest.mark.parametrize("name", TRANSFORMED)
def test_a_repeated_call_under_a_transformation_compiles_nothing(name):
    # JAX transforms the compiled call and keeps what it compiles: a second call with new
    # values neither traces the problem again nor compiles anything.
    run, truth = TRANSFORMED[name]
    first, second = jnp.array([1.0, 0.0]), jnp.array([0.7, 0.4])
    # 1e-6: central differences of the closed form are accurate to ~1e-8, the runs to ~1e-9
    np.testing.assert_allclose(run(first), truth(np.asarray(first)), rtol=1e-6, atol=1e-6)
    compiled, traced = compile_count(), len(COUNTED_TRACES)
    got = run(second)
    assert (compile_count() - compiled, len(COUNTED_TRACES) - traced) == (0, 0)
    np.testing.assert_allclose(got, truth(np.asarray(second)), rtol=1e-6, atol=1e-6)


def test_forward_mode_with_the_default_adjoint_runs_the_forward_mode_program():
    # Under jax.jvp the default adjoint (a jax.custom_vjp loop, reverse mode only) is replaced
    # by diffrax.ForwardMode(): the same compiled program as with that adjoint passed.
    x0, x1 = jnp.array([0.9, 0.1]), jnp.array([1.0, 0.2])  # x1 not computed: no program of its own
    explicit = jax.jvp(lambda x: final_state(x, diffrax.ForwardMode()), (x0,), (TANGENT,))[1]
    compiled = compile_count()
    default = jax.jvp(final_state, (x1,), (TANGENT,))[1]
    assert compile_count() == compiled
    for x, got in ((x0, explicit), (x1, default)):
        np.testing.assert_allclose(got, closed_form_jacobian(np.asarray(x)) @ np.asarray(TANGENT),
                                   rtol=1e-6, atol=1e-6)


def test_forward_mode_through_a_jit_of_the_default_adjoint_names_the_fix():
    # jax.jvp of a jax.jit made around the call: the program the jit records is reused by JAX
    # under any transformation, so it keeps the reverse-mode loop, and JAX's jvp of it fails;
    # a warning at the call names the fix.
    with pytest.warns(UserWarning, match=r"adjoint=diffrax\.ForwardMode\(\)"):
        with pytest.raises(TypeError, match="custom_vjp"):
            jax.jvp(jax.jit(final_state), (jnp.array([1.0, 0.0]),), (TANGENT,))


def test_the_compiler_options_of_a_direct_call_follow_its_executions_derivatives_and_backend():
    # On the CPU: XLA:CPU's own fusion emitters for one execution, undifferentiated, in forward
    # mode, or in reverse mode alone; wide vectors for a batch without reverse mode; both with
    # copy insertion's region analysis; XLA's defaults for a batch under reverse mode, a
    # reverse-mode derivative inside another derivative, or another backend.
    from hybridjax._solve.eager import eager_compiler_options

    one_execution = {"xla_cpu_use_fusion_emitters": False, "xla_cpu_copy_insertion_use_region_analysis": True}
    batch = {"xla_cpu_prefer_vector_width": 512, "xla_cpu_copy_insertion_use_region_analysis": True}
    for modes in (frozenset(), frozenset({"forward"})):
        assert eager_compiler_options(True, modes, False, "cpu") == one_execution
        for one, batched in [(False, False), (True, True), (False, True)]:
            assert eager_compiler_options(one, modes, batched, "cpu") == batch
    assert eager_compiler_options(True, frozenset({"reverse"}), False, "cpu", reverse_only=True) == one_execution
    for one, modes, batched, backend in [(False, frozenset({"reverse"}), False, "cpu"),
                                         (True, frozenset({"reverse"}), True, "cpu"),
                                         (True, frozenset({"reverse"}), False, "cpu"),
                                         (True, frozenset({"forward", "reverse"}), False, "cpu"),
                                         (True, frozenset(), False, "gpu"),
                                         (False, frozenset(), False, "gpu")]:
        assert eager_compiler_options(one, modes, batched, backend) == {}


def test_reverse_mode_alone_is_one_linearize_trace_at_the_call():
    from hybridjax._core.transforms import reverse_only_at_call

    seen = []

    def f(x):
        seen.append(reverse_only_at_call())
        return jnp.sum(jnp.sin(x))

    x = jnp.ones(2)
    jax.grad(f)(x)
    jax.vjp(f, x)
    jax.jacrev(f)(x)
    jax.jit(jax.grad(f))(x)  # the traces above the jit's (the call is not eager there)
    jax.vmap(jax.grad(f))(jnp.ones((3, 2)))
    jax.grad(lambda y: jax.grad(f)(y).sum())(x)  # f traced once, under two linearize traces
    jax.hessian(f)(x)
    jax.jvp(f, (x,), (x,))
    assert seen == [True, True, True, True, False, False, False, False]


def test_a_batch_is_seen_at_the_call_only_above_the_nearest_jit():
    from hybridjax._core.transforms import batched_at_call

    seen = []

    def f(x):
        seen.append(batched_at_call())
        return x

    xs = jnp.ones(3)
    f(xs[0])
    jax.vmap(f)(xs)
    jax.jit(jax.vmap(f))(xs)  # traced inside the jit, under the batch
    jax.vmap(jax.jit(f))(xs)  # the jit's own trace is nearer than the batch
    assert seen == [False, True, True, False]


def test_a_batch_at_a_direct_call_is_seen_inside_its_compiled_program():
    # The per-execution loop chooses what its reverse mode keeps by it (`runs_batched`); inside
    # the compiled program the call's own batching trace is no longer visible.
    from hybridjax._core.transforms import runs_batched
    from hybridjax._solve.eager import compiled_when_eager

    @compiled_when_eager(lambda *args, **kwargs: None)
    def call(x0, t0, t1, adjoint=diffrax.RecursiveCheckpointAdjoint(), options=None):
        return x0 * (1.0 + runs_batched())  # the slope says what the program saw

    slope = jax.grad(lambda x: call(x, 0.0, 1.0))
    assert float(slope(jnp.asarray(0.5))) == 1.0
    np.testing.assert_array_equal(jax.vmap(slope)(jnp.ones(3)), 2.0)
    np.testing.assert_array_equal(jax.vmap(lambda x: call(x, 0.0, 1.0))(jnp.ones(3)), 2.0)
    assert float(call(jnp.asarray(1.0), 0.0, 1.0)) == 1.0


def test_an_option_xla_does_not_know_falls_back_to_the_defaults(monkeypatch):
    # A jaxlib whose XLA lacks the option: the direct call runs with XLA's defaults instead.
    from hybridjax._solve import eager

    monkeypatch.setattr(eager, "_REFUSED", set())
    f = lambda x: 2.0 * x + 1.0  # noqa: E731
    unknown_options = {"xla_cpu_no_such_option": False}
    unknown = jax.jit(f, compiler_options=unknown_options)
    got = eager.with_default_options_if_refused(unknown_options, unknown, jax.jit(f), jnp.arange(3.0))
    np.testing.assert_array_equal(got, [1.0, 3.0, 5.0])
    assert eager._REFUSED == {(("xla_cpu_no_such_option", False),)}
    # A known option is used (also after another set was refused), and an error of the call
    # itself is not taken for a refusal.
    known = jax.jit(f, compiler_options=eager.FAST_COMPILE_CPU)
    np.testing.assert_array_equal(eager.with_default_options_if_refused(eager.FAST_COMPILE_CPU, known, None,
                                                                        jnp.arange(3.0)), [1.0, 3.0, 5.0])
    assert len(eager._REFUSED) == 1
    with pytest.raises(TypeError):
        eager.with_default_options_if_refused(eager.FAST_COMPILE_CPU, known, jax.jit(f), "not an array")


def test_a_repeated_direct_call_reuses_its_options_object_and_types_keep_them_apart():
    # The SolveOptions built from the keyword shorthands are kept by the values and their types.
    import inspect

    from hybridjax._solve.eager import _options_as_object

    def built(**shorthands):
        bound = inspect.signature(lambda options=None, **shorthands: None).bind(**shorthands)
        _options_as_object(bound, "simulate")
        return bound.arguments["options"]

    first, again = built(max_epochs=8, zeno=True), built(max_epochs=8, zeno=True)
    assert first is again and first.max_epochs == 8
    assert built(max_epochs=8, zeno=False) is not first
    assert built(max_epochs=8, event_tol=1e-9) is not built(max_epochs=8, event_tol=np.float64(1e-9))
    assert built(max_epochs=8, event_tol=jnp.asarray(1e-9)).max_epochs == 8  # an array: built anew
