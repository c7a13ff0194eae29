"""Definition-time validation: every error names the mode or transition at fault; a system written
against `hj.AbstractHybridSystem`."""

import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj


def flow2(t, x, args):
    return jnp.array([x[1], -9.8])


def test_system_keeps_modes_and_transitions_in_order():
    a = hj.Mode("a", flow2, dim=2)
    b = hj.Mode("b", lambda t, x, args: -x, dim=1)
    t0 = hj.Transition("a", "b", guard=lambda t, x, args: x[0], reset=lambda t, x, args: x[:1])
    t1 = hj.Transition(1, 0, guard=lambda t, x, args: x[0] - 1.0,
                       reset=lambda t, x, args: jnp.array([x[0], 0.0]))
    sys = hj.HybridSystem(modes=[a, b], transitions=[t0, t1])
    assert sys.modes == (a, b) and sys.transitions == (t0, t1)
    assert sys.sources == (0, 1) and sys.targets == (1, 0)
    assert sys.max_dim == 2
    assert sys.outgoing(0) == (0,) and sys.transition_index(t1) == 1
    assert sys.mode_index("b") == 1


def test_duplicate_mode_names():
    with pytest.raises(ValueError, match=r"Duplicate mode name 'a' \(modes\[0\] and modes\[1\]\)"):
        hj.HybridSystem([hj.Mode("a", flow2, 2), hj.Mode("a", flow2, 2)], [])


def test_unknown_mode_in_transition():
    m = hj.Mode("flight", flow2, 2)
    tr = hj.Transition("flight", "stance", guard=lambda t, x, a: x[0], name="touchdown")
    with pytest.raises(ValueError, match=r"Transition 0 \(touchdown\): unknown target mode 'stance'"):
        hj.HybridSystem([m], [tr])
    tr2 = hj.Transition(3, "flight", guard=lambda t, x, a: x[0])
    with pytest.raises(ValueError, match=r"Transition 0 .*source index 3 out of range"):
        hj.HybridSystem([m], [tr2])


def test_flow_output_shape():
    bad = hj.Mode("bad", lambda t, x, args: jnp.zeros(3), dim=2)
    with pytest.raises(hj.DefinitionError, match=r"Mode 0 'bad': flow returned shape \(3,\); expected \(2,\)"):
        hj.HybridSystem([bad])


def test_non_scalar_guard():
    m = hj.Mode("m", flow2, 2)
    tr = hj.Transition("m", "m", guard=lambda t, x, a: x, name="vec")
    with pytest.raises(hj.DefinitionError, match=r"Transition 0 \(vec.*guard returned shape \(2,\); a guard must return a scalar"):
        hj.HybridSystem([m], [tr])


def test_reset_dimension_mismatch_found_by_abstract_evaluation():
    calls = []

    def reset(t, x, a):
        calls.append(1)
        return x  # dim 4 into a dim-2 mode
    a = hj.Mode("flight", lambda t, x, p: x, 4)
    b = hj.Mode("slide", lambda t, x, p: x, 2)
    tr = hj.Transition("flight", "slide", guard=lambda t, x, p: x[0], reset=reset, name="stick")
    with pytest.raises(hj.DefinitionError, match=r"Transition 0 \(stick, 'flight' -> 'slide'\): reset returned shape \(4,\); expected \(2,\)"):
        hj.HybridSystem([a, b], [tr])
    # eval_shape traces the function once with abstract values; nothing is computed.
    assert len(calls) == 1


def test_identity_reset_needs_equal_dimensions():
    a = hj.Mode("a", lambda t, x, p: x, 3)
    b = hj.Mode("b", lambda t, x, p: x, 2)
    with pytest.raises(ValueError, match=r"Transition 0 \(a->b\): the default identity reset needs equal dimensions"):
        hj.HybridSystem([a, b], [hj.Transition("a", "b", guard=lambda t, x, p: x[0])])


def test_checks_needing_args_run_in_simulate():
    # The flow reads args["g"]; at construction args are unknown, so the check is deferred.
    m = hj.Mode("m", lambda t, x, args: jnp.array([x[1], -args["g"], 0.0]), dim=2)
    sys = hj.HybridSystem([m])
    with pytest.raises(hj.DefinitionError, match=r"Mode 0 'm': flow returned shape \(3,\)"):
        hj.simulate(sys, jnp.array([1.0, 0.0]), "m", 0.0, 1.0, {"g": 9.8})
    with pytest.raises(hj.DefinitionError, match=r"Mode 0 'm': flow returned shape \(3,\)"):
        hj.HybridSystem([m], example_args={"g": 9.8})
    with pytest.raises(hj.DefinitionError, match=r"Mode 0 'm': flow failed .*KeyError"):
        hj.simulate(sys, jnp.array([1.0, 0.0]), "m", 0.0, 1.0, {"gravity": 9.8})


def test_bad_constructor_arguments():
    with pytest.raises(ValueError, match="dim"):
        hj.Mode("m", flow2, dim=0)
    with pytest.raises(TypeError, match="flow"):
        hj.Mode("m", 3.0, dim=1)
    with pytest.raises(TypeError, match="expected hybridjax.Mode"):
        hj.HybridSystem(["m"])
    with pytest.raises(ValueError, match="at least one Mode"):
        hj.HybridSystem([])


def test_bad_simulate_arguments():
    sys = hj.examples.bouncing_ball()
    args = {"g": 9.8, "e": 0.5}
    with pytest.raises(ValueError, match="Unknown mode 'air'"):
        hj.simulate(sys, jnp.array([1.0, 0.0]), "air", 0.0, 1.0, args)
    with pytest.raises(ValueError, match="x0 has 3 components but mode 'flight' has dim 2"):
        hj.simulate(sys, jnp.array([1.0, 0.0, 0.0]), "flight", 0.0, 1.0, args)
    with pytest.raises(ValueError, match="max_epochs must be an int >= 1"):
        hj.simulate(sys, jnp.array([1.0, 0.0]), "flight", 0.0, 1.0, args, max_epochs=0)
    with pytest.raises(TypeError, match="adjoint"):
        hj.simulate(sys, jnp.array([1.0, 0.0]), "flight", 0.0, 1.0, args,
                    adjoint=__import__("diffrax").BacksolveAdjoint())


# ---------------------------------------------------------------------------- the interface
class _InterfaceBall(hj.AbstractHybridSystem):
    """The bouncing ball written directly against the interface: three attributes, one method."""

    modes: tuple = (hj.Mode("flight", lambda t, x, a: jnp.stack([x[1], -a["g"] + 0.0 * x[0]]), dim=2),)
    transitions: tuple = (
        hj.Transition("flight", "flight", guard=lambda t, x, a: x[0],
                      reset=lambda t, x, a: jnp.stack([x[0], -a["e"] * x[1]])),
    )
    completions: tuple = ()

    def mode_indexed(self):
        return None


def test_a_subclass_of_the_interface_is_simulated():
    # First impact from height h0 at rest: h0 - g t^2 / 2 = 0, t = sqrt(2 h0 / g) (closed form);
    # the second 2 e sqrt(2 h0 / g) later (the rebound speed e sqrt(2 g h0) up and down).
    h0, g, e = 1.5, 9.81, 0.7
    ball = _InterfaceBall()
    assert ball.sources == ball.targets == (0,) and ball.mode_names == ("flight",)
    sol = hj.simulate(ball, jnp.array([h0, 0.0]), "flight", 0.0, 1.5, {"g": g, "e": e}, max_epochs=4)
    t_hit = (2.0 * h0 / g) ** 0.5
    assert int(sol.status) == hj.Status.T1_REACHED and int(sol.num_events) == 2
    np.testing.assert_allclose(sol.event_times[:2], [t_hit, t_hit * (1.0 + 2.0 * e)], rtol=0, atol=1e-9)
    for system in (hj.examples.bouncing_ball(), ball):
        assert isinstance(system, hj.AbstractHybridSystem)
    with pytest.raises(TypeError):
        hj.AbstractHybridSystem()  # abstract: modes, transitions, completions, mode_indexed

    class NoModeIndexed(hj.AbstractHybridSystem):
        modes: tuple = ()
        transitions: tuple = ()
        completions: tuple = ()

    with pytest.raises(TypeError, match="mode_indexed"):
        NoModeIndexed()
