"""Scenes: contact hybrid systems built from constraints (`hj.Scene`, `hj.contact_system`).

Checked against hand derivations (the chapter's practice problem 1, the rimless wheel's gait) and
against the hand-written examples (the two balls)."""

import functools
import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj
from hybridjax import examples

from helpers import evaluations_agree

TIGHT = diffrax.PIDController(rtol=1e-11, atol=1e-11)
G = 9.81
WEDGE = examples.wedge_particle()


def wedge_args(theta):
    return {"m": jnp.asarray(1.0), "g": jnp.asarray(G), "theta": jnp.asarray(theta)}


THETAS = (math.pi / 4, math.pi / 3, 2 * math.pi / 3, 3 * math.pi / 4)
@functools.cache
def wedge_system(theta):
    """The wedge's system for one angle, built on first use (collection compiles nothing)."""
    return hj.contact_system(WEDGE, ["free"], wedge_args(theta))


def table(system):
    """(modes built, achievable transitions as (kind, constraint, source, target))."""
    modes = {m.name for m, s in zip(system.modes, system.contact_sets, strict=True) if s is not None}
    edges = {(kind, c, src, tgt) for src, tgt, kind, c, _ in system.achievable}
    return modes, edges


def wedge_hand_table(theta):
    """Practice problem 1 by hand (m = 1, gravity -g along z, plastic impacts).

    J_G = (0, 1), J_H = (-sin th, cos th) (unit normals), M = I. A transition is achievable when
    a state of its source set lies in its guard: an impact needs the other held constraints'
    forces >= 0, approach speed > 0, impulses >= 0 and released constraints separating; a
    lift-off needs lambda_j < 0.
    - free -> G, free -> H: a fall onto either; always.
    - Held forces (no curvature): in G, lambda_G = g > 0 (no lift-off); in H, lambda_H = g cos th:
      no lift-off for th < pi/2; for th > pi/2 it is negative on all of H: H -> free (an overhang).
    - Impact of H in G (sliding into the corner at the origin, speed v > 0 along x): holding both,
      the impulse J^T P = -v e_x gives P_H = v / sin th > 0 and P_G = -v cot th: negative for
      th < pi/2, so G is released, and then H's impulse leaves dq+ = v cos th (cos th, sin th),
      z-rate v sin th cos th > 0 (G separates): G -> H. For th > pi/2, P_G > 0: G -> G+H, while
      the release fails (z-rate < 0).
    - Impact of G in H (sliding down H with speed u into the corner): holding both gives
      P_H = -u cot th... negative for th < pi/2 (u > 0 the speed), so H is released: H -> G. For
      th > pi/2, lambda_H < 0 on H: it lifts off before it can slide, so no impact from H.
    - In G+H (th > pi/2): dq = 0, J^T lambda = (0, g): lambda_G = g, lambda_H = 0: no lift-off
      (lambda_H = 0 is not < 0).
    """
    both = {("impact", "G", "free", "G"), ("impact", "H", "free", "H")}
    if theta < math.pi / 2:
        return {"free", "G", "H"}, both | {("impact", "H", "G", "H"), ("impact", "G", "H", "G")}
    return {"free", "G", "H", "G+H"}, both | {("lift-off", "H", "H", "free"), ("impact", "H", "G", "G+H")}


@pytest.mark.parametrize("theta", THETAS)
def test_practice_problem_mode_table(theta):
    assert table(wedge_system(theta)) == wedge_hand_table(theta)
    text = repr(wedge_system(theta))
    assert "contact sets built" in text and "pruned" in text
    if theta < math.pi / 2:
        assert "pruned set G+H" in text


def test_args_values_union_is_reported():
    system = hj.contact_system(WEDGE, ["free"], args_values=[wedge_args(THETAS[0]), wedge_args(THETAS[2])])
    modes, edges = table(system)
    m0, e0 = wedge_hand_table(THETAS[0])
    m2, e2 = wedge_hand_table(THETAS[2])
    assert modes == m0 | m2 and edges == e0 | e2
    assert "only for args_values [1]" in repr(system) and "built over 2 args values" in repr(system)


def _wedge_run(x0, mode0, theta, saveat):
    # mode0 as an array: a Python int is a constant of the compiled program (one compile per value).
    return hj.simulate(
        wedge_system(math.pi / 4),
        jnp.asarray(x0),
        jnp.asarray(mode0),
        0.0,
        1.0,
        wedge_args(theta),
        stepsize_controller=TIGHT,
        saveat=jnp.asarray(saveat),
        max_epochs=8,
    )


def test_wedge_execution_and_contact_forces_by_hand():
    th = math.pi / 4
    sol = _wedge_run([-0.5, 0.2, 1.0, 0.0], 0, th, [0.1, 0.3, 0.6])
    system = wedge_system(th)
    names = [system.modes[int(m)].name for m in sol.epoch_modes[: int(sol.num_events) + 1]]
    assert names == ["free", "G", "H", "G"]
    # Fall of 0.2 onto the floor; slide at speed 1 to the corner at x = 0 (t = 0.5); up the ramp at
    # speed cos th, back at the corner 2 cos th / (g sin th) later; then along the floor at -cos^2 th.
    t1 = math.sqrt(2 * 0.2 / G)
    t3 = 0.5 + 2 * math.cos(th) / (G * math.sin(th))
    np.testing.assert_allclose(sol.event_times[:3], [t1, 0.5, t3], rtol=0, atol=1e-9)
    v = math.cos(th) ** 2
    np.testing.assert_allclose(sol.final_state, [-v * (1.0 - t3), 0.0, -v, 0.0], atol=1e-9)
    assert sol.status == hj.Status.T1_REACHED
    forces = np.asarray(system.contact_forces(sol))  # columns G, H
    np.testing.assert_allclose(forces, [[0.0, 0.0], [G, 0.0], [0.0, G * math.cos(th)]], atol=1e-9)


def test_unbuilt_contact_set_ends_with_a_status_naming_it():
    # Built for theta = pi/4, run at 2 pi/3: sliding into the corner now holds both G and H, a
    # contact set this system does not have.
    sol = _wedge_run([-0.5, 0.0, 1.0, 0.0], 1, 2 * math.pi / 3, [0.1, 0.3, 0.6])
    assert sol.status == hj.Status.BLOCKED
    assert wedge_system(math.pi / 4).modes[int(sol.final_mode)].name == "unbuilt: G+H"
    np.testing.assert_allclose(sol.final_time, 0.5, atol=1e-9)


# ----------------------------------------------------------------------------- the balls

BALL_ARGS = {"g": jnp.asarray(9.8), "e": jnp.asarray(0.8)}
CEILING_ARGS = {"g": jnp.asarray(9.8), "H": jnp.asarray(1.0)}


def test_ball_scene_equals_bouncing_ball():
    system = hj.contact_system(examples.ball_scene(), ["free"], BALL_ARGS)
    assert [m.name for m in system.modes] == ["free"] and len(system.transitions) == 1
    x0 = jnp.array([1.0, 0.5])
    a = hj.simulate(system, x0, "free", 0.0, 2.5, BALL_ARGS, stepsize_controller=TIGHT)
    b = hj.simulate(examples.bouncing_ball(), x0, "flight", 0.0, 2.5, BALL_ARGS, stepsize_controller=TIGHT)
    n = int(b.num_events)
    assert int(a.num_events) == n > 3
    np.testing.assert_allclose(a.event_times[:n], b.event_times[:n], rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.states_after[:n], b.states_after[:n], rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.final_state, b.final_state, rtol=0, atol=1e-10)


def test_ceiling_scene_equals_ceiling_ball():
    system = hj.contact_system(examples.ceiling_scene(), ["free"], CEILING_ARGS)
    assert [m.name for m in system.modes] == ["free", "ceiling"]
    x0 = jnp.array([0.0, 6.0])
    a = hj.simulate(system, x0, "free", 0.0, 1.0, CEILING_ARGS, stepsize_controller=TIGHT)
    b = hj.simulate(examples.ceiling_ball(), x0, "flight", 0.0, 1.0, CEILING_ARGS, stepsize_controller=TIGHT)
    assert int(a.num_events) == int(b.num_events) == 2
    np.testing.assert_array_equal(a.epoch_modes[:3], b.epoch_modes[:3])  # free, ceiling (0 s), free
    np.testing.assert_allclose(a.event_times[:2], b.event_times[:2], rtol=0, atol=1e-10)
    np.testing.assert_allclose(a.final_state, b.final_state, rtol=0, atol=1e-10)


# ----------------------------------------------------------------------------- the rimless wheel

WHEEL_ARGS = {"alpha": 0.3, "gamma": 0.08, "g": 1.0, "l": 1.0, "m": 1.0}
INERTIA = 0.1


@functools.cache
def wheel():
    """The rimless wheel's system (built once for the tests that use it), its args, the index of
    its step transition and the hand-derived gait."""
    scene, relabel = examples.rimless_wheel_scene(INERTIA)
    # Speeds up to 0.7: the foot's force m (g cos - l omega^2) stays positive, so the wheel never
    # leaves the ground and the build keeps the stance set alone.
    scene = type(scene)(
        scene.dim,
        scene.mass,
        scene.forces,
        scene.constraints,
        bounds=(scene.q_range[0] + (-0.7,) * scene.dim, scene.q_range[1] + (0.7,) * scene.dim),
        names=scene.names,
    )
    args = {k: jnp.asarray(v) for k, v in WHEEL_ARGS.items()}
    system = hj.contact_system(scene, ["spoke0"], args, relabels=[relabel])
    step = [k for k, tr in enumerate(system.transitions) if tr.name == "impact spoke1: spoke0 -> spoke0"]
    ref = examples.rimless_wheel_scene_closed_form(0.3, 0.08, 1.0, 1.0, INERTIA)
    return system, args, step, ref


def test_rimless_wheel_gait_by_hand():
    system, args, step, ref = wheel()
    assert [m.name for m in system.modes][:1] == ["spoke0"]
    assert len(step) == 1

    @jax.jit
    def P(x):
        sol = hj.simulate(system, x, 0, 0.0, 10.0, args, stepsize_controller=TIGHT, max_epochs=2)
        return sol.states_after[0], sol.transitions[0]

    x_star = jnp.asarray(ref["state"])
    after, k = P(x_star)
    assert int(k) == step[0]
    np.testing.assert_allclose(after, x_star, atol=1e-9)  # the hand fixed point is a fixed point
    # The return map's multipliers by central differences: c^2 and zeros (the plastic, sticking
    # impact removes every direction off the stance manifold, the section the flow's direction).
    h = 1e-5
    cols = [(P(x_star + h * e)[0] - P(x_star - h * e)[0]) / (2 * h) for e in jnp.eye(6)]
    mult = np.sort(np.abs(np.linalg.eigvals(np.stack(cols, axis=1))))[::-1]
    # Central differences of a map with event times: O(h^2) plus rounding / h, about 1e-8.
    np.testing.assert_allclose(mult[0], ref["multiplier"], atol=1e-6)
    # The zero multipliers form a Jordan block (nilpotent): an error d in the matrix moves them by
    # about sqrt(d), 1e-4.
    np.testing.assert_allclose(mult[1:], 0.0, atol=1e-3)


@pytest.mark.costly  # periodic_orbit on the example wheel: test_periodic_gradients.py, test_saltation.py
def test_rimless_wheel_gait_by_periodic_orbit():
    system, args, step, ref = wheel()
    orbit = hj.periodic_orbit(system, step[0], ref["state"] * 1.02, args, max_epochs=4)
    np.testing.assert_allclose(orbit.state, ref["state"], rtol=0, atol=1e-10)
    # The monodromy matrix's multipliers, by AD and by saltation matrices: 1 (the flow's
    # direction), c^2 (the hand return map's) and zeros (the plastic, sticking impact).
    for mult in (orbit.multipliers_ad, orbit.multipliers_saltation):
        mult = np.abs(mult)
        np.testing.assert_allclose(mult[:2], [1.0, ref["multiplier"]], rtol=0, atol=1e-9)
        # The zeros form a Jordan block: a rounding error d in the matrix moves them by about
        # sqrt(d) (1e-8 at d = 1e-16).
        np.testing.assert_allclose(mult[2:], 0.0, atol=1e-6)


# ----------------------------------------------------------------------------- definitions


def test_definition_errors_name_the_constraint():
    floor = hj.Constraint("floor", lambda t, q, a: q[0])
    with pytest.raises(ValueError, match="duplicate constraint name 'floor'"):
        hj.Scene(1, lambda q, a: jnp.eye(1), lambda t, q, dq, a: q, [floor, floor])
    with pytest.raises(ValueError, match="'pin'.*no restitution"):
        hj.Constraint("pin", lambda t, q, a: q[0], kind="bilateral", restitution=0.5)
    with pytest.raises(ValueError, match="'floor'.*restitution"):
        hj.Constraint("floor", lambda t, q, a: q[0], restitution=1.5)
    with pytest.raises(ValueError, match="'floor'.*kind"):
        hj.Constraint("floor", lambda t, q, a: q[0], kind="sometimes")
    bad = hj.Scene(
        2, lambda q, a: jnp.eye(2), lambda t, q, dq, a: q, [hj.Constraint("wall", lambda t, q, a: q)]
    )
    with pytest.raises(ValueError, match="Constraint 'wall'.*shape"):
        hj.contact_system(bad, ["free"])
    with pytest.raises(ValueError, match="Unknown constraint 'roof'"):
        hj.contact_system(examples.ball_scene(), [["roof"]], BALL_ARGS)


def test_redundant_contacts_error_names_them():
    scene = hj.Scene(
        1,
        lambda q, a: jnp.eye(1),
        lambda t, q, dq, a: -9.8 + 0 * q,
        [hj.Constraint("left", lambda t, q, a: q[0]), hj.Constraint("right", lambda t, q, a: q[0])],
        bounds=((0.0, -1.0), (1.0, 1.0)),
    )
    with pytest.raises(ValueError, match=r"dependent constraints \['left', 'right'\]"):
        hj.contact_system(scene, [["left", "right"]])


# ----------------------------------------------------------------------------- a rod, two contacts

ROD_ARGS = {"m": jnp.asarray(1.0), "g": jnp.asarray(G), "L": jnp.asarray(1.0)}


def rod_by_hand(x0, z0, phi0, L=1.0, g=G):
    """The rod dropped from rest, computed without hybridjax: free fall; the plastic impact of
    the left end, by hand; pivoting and sliding on it (frictionless: x stays), the reduced
    equation of phi integrated by scipy until the right end lands (phi = 0); there, holding both
    ends stops z and phi, and both impulses are positive (checked), so it rests."""
    from scipy.integrate import solve_ivp

    m, I, h = 1.0, L**2 / 12, L / 2
    t1 = math.sqrt(2 * (z0 - h * math.sin(phi0)) / g)
    vz = -g * t1
    # Left end: J = (0, 1, -h cos phi); P = -J dq / (J M^-1 J^T).
    c = h * math.cos(phi0)
    P = -vz / (1 / m + c * c / I)
    vz, w = vz + P / m, -c * P / I

    # Pivoting on the left end: z = h sin phi; Lagrange's equation in phi.
    def rhs(t, y):
        phi, w = y
        a = m * h * h * math.cos(phi) ** 2 + I
        return [w, (m * h * h * math.cos(phi) * math.sin(phi) * w * w - m * g * h * math.cos(phi)) / a]

    def lands(t, y):
        return y[0]

    lands.terminal, lands.direction = True, -1

    def force(y):  # lambda_left = m (z'' + g), z'' = h (cos phi phi'' - sin phi phi'^2)
        phi, w = y
        return m * (h * (math.cos(phi) * rhs(0, y)[1] - math.sin(phi) * w * w) + g)

    sol = solve_ivp(rhs, (0, 5), [phi0, w], events=lands, rtol=1e-12, atol=1e-12, dense_output=True)
    t2 = t1 + sol.t_events[0][0]
    w2 = sol.y_events[0][0][1]
    forces = [force(sol.sol(t)) for t in np.linspace(0, sol.t[-1], 50)]
    # Both ends held at phi = 0: P_left + P_right = -m h w2, h (P_right - P_left) = -I w2.
    P_left = 0.5 * (-m * h * w2 + I * w2 / h)
    P_right = 0.5 * (-m * h * w2 - I * w2 / h)
    return dict(t=(t1, t2), w_before=w2, min_force=min(forces), impulses=(P_left, P_right))


def test_rod_lands_on_one_end_then_the_other_and_rests():
    system = hj.contact_system(examples.rod_scene(), ["free"], ROD_ARGS)
    ref = rod_by_hand(0.1, 0.5, 0.3)
    assert ref["min_force"] > 0 and min(ref["impulses"]) > 0  # no lift-off, no release
    sol = hj.simulate(
        system,
        jnp.array([0.1, 0.5, 0.3, 0.0, 0.0, 0.0]),
        "free",
        0.0,
        1.0,
        ROD_ARGS,
        stepsize_controller=TIGHT,
        saveat=jnp.array([0.9]),
        max_epochs=8,
    )
    names = [system.modes[int(m)].name for m in sol.epoch_modes[: int(sol.num_events) + 1]]
    assert names == ["free", "left", "left+right"]
    np.testing.assert_allclose(sol.event_times[:2], ref["t"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(sol.states_before[1, 5], ref["w_before"], rtol=0, atol=1e-8)
    np.testing.assert_allclose(sol.final_state, [0.1, 0, 0, 0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(system.contact_forces(sol), [[G / 2, G / 2]], atol=1e-9)


# ----------------------------------------------------------------------------- the small solves


def test_kkt_solve_against_the_dense_system():
    from hybridjax._scenes.mechanics import kkt_solve

    rng = np.random.default_rng(0)
    n, m = 4, 3
    A = rng.normal(size=(n, n))
    M = A @ A.T + n * np.eye(n)
    J, top, bottom = rng.normal(size=(m, n)), rng.normal(size=n), rng.normal(size=m)
    mask = np.array([1.0, 0.0, 1.0])
    # The KKT system as one dense matrix, solved by numpy: the released row has mu = 0.
    Jm = mask[:, None] * J
    dense = np.block([[M, -Jm.T], [Jm, np.diag(1.0 - mask)]])
    ref = np.linalg.solve(dense, np.concatenate([top, mask * bottom]))
    u, mu = kkt_solve(*map(jnp.asarray, (M, top, J, bottom, mask)))
    np.testing.assert_allclose(np.concatenate([u, mu]), ref, rtol=0, atol=1e-13)
    assert mu[1] == 0.0
    # Dependent held rows: no solution, and the solve says so with non-finite values.
    J2 = jnp.asarray([[1.0, 0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.0]])
    u, mu = kkt_solve(jnp.asarray(M), jnp.asarray(top), J2, jnp.zeros(2), jnp.ones(2))
    assert not np.all(np.isfinite(np.concatenate([u, mu])))


def test_independence_bounds_the_gram_eigenvalue_ratio():
    from hybridjax._scenes.mechanics import independence

    scene = examples.polygon_particle(3)
    fns = tuple(c.fn for c in scene.constraints)
    q, args = jnp.asarray([0.1, -0.2]), {"r": jnp.asarray(1.0)}
    # Walls 0 and 1, unit normals 120 degrees apart, M = I: G = [[1, c], [c, 1]], c = cos(120),
    # eigenvalues 1 -+ c; the Cholesky pivots 1 and 1 - c^2, so the ratio is 1 - c^2 = 3/4.
    held = jnp.asarray([1.0, 1.0, 0.0])
    np.testing.assert_allclose(independence(scene, fns, held, 0.0, q, args), 0.75, rtol=1e-14)
    assert 0.75 >= (1 - 0.5) / (1 + 0.5)  # not below lambda_min / lambda_max
    # One wall twice: dependent.
    same = (fns[0], fns[0])
    ratio = independence(scene, same, jnp.ones(2), 0.0, q, args)
    assert not ratio > 1e-9


def test_release_choice_and_impact_map_by_hand():
    """A point sliding along the floor at speed 1 into the 45-degree wall of an octagon.

    Rows: the floor a_0 = r + z (gradient (0, 1)) and wall 1, gradient (-s, s), s = 1/sqrt 2;
    M = I. Holding both stops the point, J^T P = -(1, 0): P_1 = sqrt 2, P_0 = -1 < 0 (pulling),
    so the floor is released; the wall alone gives P_1 = s, dq+ = (1, 0) + s (-s, s) = (1/2, 1/2),
    whose floor rate 1/2 >= 0 separates: candidate 1 of (hold both, release the floor)."""
    from hybridjax._scenes.mechanics import impact_map, kinematics, release_choice, rows, selection_guard

    scene = examples.polygon_particle(8)
    fns, _ = rows(scene, (0, 1))
    args = {"g": jnp.asarray(G), "r": jnp.asarray(1.0)}
    q = jnp.asarray([math.tan(math.pi / 8), -1.0])  # the corner of walls 0 and 1
    kin = kinematics(scene, fns, 0.0, q, jnp.asarray([1.0, 0.0]), args)
    np.testing.assert_allclose(kin.gap, [0.0, 0.0], atol=1e-15)
    held = jnp.asarray([[1.0, 1.0], [0.0, 1.0]])
    e, every = jnp.zeros(2), jnp.ones(2, bool)
    assert int(release_choice(kin, held, e, every, every)) == 1
    dq, P, rates = impact_map(kin, held[0], e)
    np.testing.assert_allclose(P, [-1.0, math.sqrt(2)], rtol=1e-14)
    dq, P, rates = impact_map(kin, held[1], e)
    np.testing.assert_allclose(dq, [0.5, 0.5], rtol=1e-14)
    np.testing.assert_allclose(rates, [0.5, 0.0], atol=1e-15)
    # Restitution 1 on the wall: the wall's rate is reversed, -(-s) = s, and the floor's is 1:
    # both separate with nothing held but the wall, so the release is still the one taken.
    dq, _, rates = impact_map(kin, held[1], jnp.asarray([0.0, 1.0]))
    np.testing.assert_allclose(dq, [0.0, 1.0], atol=1e-15)
    # The selection guards: the gap while positive, and beyond zero only where taken.
    a = jnp.asarray([0.5, -0.5, -0.5])
    np.testing.assert_array_equal(selection_guard(a, jnp.asarray([False, True, False])), [0.5, -0.5, 1.5])


@functools.cache
def _triangle_system():
    """A point in a triangle (3 walls): free, single walls and corners, with selection guards."""
    return hj.contact_system(examples.polygon_particle(3), ["free"], {"g": jnp.asarray(G), "r": jnp.asarray(1.0)})


# the triangle (three faces, the largest build) with the costly cases
@pytest.mark.parametrize("name", [pytest.param("triangle", marks=pytest.mark.costly), "wedge", "wheel"])
def test_mask_evaluation_equals_the_modes_own_functions(name):
    """The one masked evaluation of every mode (`ContactEvaluation`) against each mode's and
    transition's own function, as the engines see them (`Kernels` with and without it): flows,
    every watched value (selection guards included), resets, and the start test's Lie
    derivatives, at states drawn across the scene's ranges."""
    from hybridjax._scenes.indexed import SELECTED

    if name == "triangle":
        system, args = _triangle_system(), {"g": jnp.asarray(G), "r": jnp.asarray(1.0)}
        assert any(sp.kind == SELECTED for slots in system.evaluation.slots for sp in slots)
    elif name == "wedge":
        system, args = wedge_system(3 * math.pi / 4), wedge_args(3 * math.pi / 4)
    else:  # relabelled spokes, a sticking foot (a tangent without friction)
        system, args, _, _ = wheel()
        assert system.evaluation.relabel_maps
    assert system.form == "mask" and system.mode_indexed() is system.evaluation
    rng = np.random.default_rng(1)
    n = system.scene.dim
    lo = np.asarray([-1.2] * n + [-3.0] * n)
    xs = rng.uniform(lo, -lo, size=(64, 2 * n))
    # States on the walls and at rest too: where the selection guards read their choice.
    xs[:16, n:] = 0.0
    xs[16:32, 1] = -1.0
    assert evaluations_agree(system, args, jnp.asarray(xs)) > 500
