"""Contact laws: the impact and tangential laws a `Constraint` derives from its fields, and the
friction states' rows and signs they give (nothing compiles here).

Checked against the definitions (Newton's law of restitution, Coulomb's stick and slip) written
out by hand for the rod with friction at its left end."""

import numpy as np
import pytest

import hybridjax as hj
from hybridjax._scenes.friction import _state_arrays, parse_state
from hybridjax._scenes.laws import Coulomb, Frictionless, Newton, Plastic, Sticking


def gap(t, q, args):
    return q[0]


def test_impact_laws_from_restitution():
    plastic = hj.Constraint("a", gap)
    assert isinstance(plastic.impact_law, Plastic)
    assert plastic.coefficient({}) == 0.0 and not plastic.restitutes
    # Newton's law: e given as a number or a function of args; e = 0 holds the contact.
    assert isinstance(hj.Constraint("a", gap, restitution=0.8).impact_law, Newton)
    assert hj.Constraint("a", gap, restitution=0.8).coefficient({}) == 0.8
    assert hj.Constraint("a", gap, restitution=0.8).restitutes
    assert not hj.Constraint("a", gap, restitution=0.0).restitutes
    by_args = hj.Constraint("a", gap, restitution=lambda args: args["e"])
    assert by_args.coefficient({"e": 0.25}) == 0.25 and by_args.restitutes


def test_tangential_laws_from_tangent_and_friction():
    assert isinstance(hj.Constraint("a", gap).tangential_law, Frictionless)
    assert isinstance(hj.Constraint("a", gap, tangent=gap).tangential_law, Sticking)
    coulomb = hj.Constraint("a", gap, tangent=gap, friction=lambda args: args["mu"]).tangential_law
    assert isinstance(coulomb, Coulomb) and coulomb.coefficient({"mu": 0.3}) == 0.3
    assert coulomb.states == ("stick", "slip+", "slip-")
    # Stick holds the tangent row; slip s moves with s b' > 0; stick leaves to slip in either
    # direction, a slip stops (and sticks) or reverses.
    assert [coulomb.holds_tangent(s) for s in coulomb.states] == [True, False, False]
    assert [coulomb.slip_sign(s) for s in coulomb.states] == [0.0, 1.0, -1.0]
    assert [c[2] for c in coulomb.changes("stick")] == ["slip+", "slip-"]
    assert [c[2] for c in coulomb.changes("slip+")] == ["stick", "slip-"]


# The rod's rows: the gaps of `left`, `right`, then the tangent of `left` (the one with friction).
@pytest.mark.parametrize(
    "spec, rows, sign",
    [
        ("left:stick+right", [1, 1, 1], [0, 0]),
        ("left:slip-+right", [1, 1, 0], [-1, 0]),
        ("left:slip+", [1, 0, 0], [1, 0]),
        ("right", [0, 1, 0], [0, 0]),
        ("free", [0, 0, 0], [0, 0]),
    ],
)
def test_friction_state_rows_and_signs_by_hand(spec, rows, sign):
    scene = hj.examples.rod_scene(friction=("left",))
    held, rows_mask, signs = _state_arrays(scene, parse_state(scene, spec))
    np.testing.assert_array_equal(rows_mask, rows)
    np.testing.assert_array_equal(signs, sign)
    np.testing.assert_array_equal(held, rows[:2])


def test_a_frictional_contact_needs_its_state_named():
    scene = hj.examples.rod_scene(friction=("left",))
    with pytest.raises(ValueError, match="'left:stick', 'left:slip\\+' or 'left:slip-'"):
        parse_state(scene, "left+right")
    with pytest.raises(ValueError, match="'right' has no friction"):
        parse_state(scene, ["right:stick"])
