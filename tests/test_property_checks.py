"""Property checks (A. M. Johnson, "Hybrid Dynamical Systems", section 3) against hand derivations.

Each system is checked with a few `args`; its searches compile once (array-valued `args`).
"""

import math

import diffrax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj
from hybridjax import examples
from hybridjax._analysis.properties import _start_tolerances

from helpers import compile_count, line_system

G = 9.8

# ----------------------------------------------------------------------------- practice problem 1


def point_particle() -> hj.HybridSystem:
    """The chapter's practice problem 1: a planar point particle q = (x, z) under gravity with
    constraints a_G = z >= 0 and a_H = -x sin(theta) + z cos(theta) >= 0 (frictionless).
    Modes are the sets of active constraints:

    - "free" (none), state (x, z, vx, vz), domain (a_G, a_H) >= 0;
    - "G" (on the ground z = 0), state (x, vx), domain a_H(x, 0) = -x sin(theta) >= 0;
    - "H" (on the line H at s (cos, sin)), state (s, s'), domain a_G = s sin(theta) >= 0;
    - "GH" (at the corner, at rest), a 1-D placeholder state.

    Impacts add a constraint (guard: its a <= 0); lift-offs remove one (guard: its contact force
    lambda <= 0). Contact forces per unit mass balance gravity's normal component: on G,
    lambda_G = g; on H (normal n_H = (-sin, cos)), lambda_H = g cos(theta); at the corner,
    n_G lambda_G + n_H lambda_H = (0, g) gives lambda_H = 0 (sin(theta) != 0), lambda_G = g.
    """

    def a_h(x, z, th):
        return -x * jnp.sin(th) + z * jnp.cos(th)

    free = hj.Mode(
        "free",
        lambda t, q, p: jnp.array([q[2], q[3], 0.0 * q[2], -p["g"] + 0.0 * q[3]]),
        dim=4,
        domain=lambda t, q, p: jnp.array([q[1], a_h(q[0], q[1], p["theta"])]),
    )
    ground = hj.Mode(
        "G",
        lambda t, q, p: jnp.array([q[1], 0.0 * q[1]]),
        dim=2,
        domain=lambda t, q, p: a_h(q[0], 0.0, p["theta"]),
    )
    line = hj.Mode(
        "H",
        lambda t, q, p: jnp.array([q[1], -p["g"] * jnp.sin(p["theta"]) + 0.0 * q[1]]),
        dim=2,
        domain=lambda t, q, p: q[0] * jnp.sin(p["theta"]),
    )
    corner = hj.Mode("GH", lambda t, q, p: 0.0 * q, dim=1)

    def on_line(t, q, p):  # project (x, z, vx, vz) onto the line H
        c, s = jnp.cos(p["theta"]), jnp.sin(p["theta"])
        return jnp.array([q[0] * c + q[1] * s, q[2] * c + q[3] * s])

    def off_line(t, q, p):
        c, s = jnp.cos(p["theta"]), jnp.sin(p["theta"])
        return jnp.array([q[0] * c, q[0] * s, q[1] * c, q[1] * s])

    rest1 = lambda t, q, p: 0.0 * q[:1]
    rest2 = lambda t, q, p: jnp.zeros(2) + 0.0 * q[0]
    return hj.HybridSystem(
        [free, ground, line, corner],
        [
            hj.Transition(
                "free",
                "G",
                guard=lambda t, q, p: q[1],
                reset=lambda t, q, p: q[jnp.array([0, 2])],
                name="free->G",
            ),
            hj.Transition(
                "free", "H", guard=lambda t, q, p: a_h(q[0], q[1], p["theta"]), reset=on_line, name="free->H"
            ),
            hj.Transition(
                "G",
                "free",
                guard=lambda t, q, p: p["g"] + 0.0 * q[0],
                reset=lambda t, q, p: jnp.array([q[0], 0.0, q[1], 0.0]),
                name="G->free",
            ),
            hj.Transition(
                "H",
                "free",
                guard=lambda t, q, p: p["g"] * jnp.cos(p["theta"]) + 0.0 * q[0],
                reset=off_line,
                name="H->free",
            ),
            hj.Transition(
                "G", "GH", guard=lambda t, q, p: a_h(q[0], 0.0, p["theta"]), reset=rest1, name="G->GH"
            ),
            hj.Transition(
                "H", "GH", guard=lambda t, q, p: q[0] * jnp.sin(p["theta"]), reset=rest1, name="H->GH"
            ),
            hj.Transition("GH", "G", guard=lambda t, q, p: 0.0 * q[0], reset=rest2, name="GH->G"),
            hj.Transition("GH", "H", guard=lambda t, q, p: p["g"] + 0.0 * q[0], reset=rest2, name="GH->H"),
        ],
    )


PARTICLE = point_particle()
PARTICLE_BOUNDS = {"free": (-2.0, 2.0), "G": (-2.0, 2.0), "H": (-2.0, 2.0), "GH": (-1.0, 1.0)}


def particle_achievable_by_hand(theta: float) -> set[str]:
    """Eq. (3) for each transition of `point_particle`, G_IJ meeting D_I:

    - free->G: {z <= 0} meets {z >= 0, a_H >= 0} at the corner (0, 0), for every theta;
    - free->H: {a_H <= 0} meets the domain at the corner, every theta;
    - G->free: lambda_G = g <= 0 never;
    - H->free: lambda_H = g cos(theta) <= 0 iff cos(theta) <= 0 (H overhangs, theta in
      [pi/2, 3 pi/2]; at pi/2, a wall, lambda_H = 0 on all of it);
    - G->GH: -x sin(theta) <= 0 and >= 0 at x = 0, every theta; H->GH likewise at s = 0;
    - GH->G: lambda_H = 0 <= 0 always; GH->H: lambda_G = g <= 0 never.
    """
    out = {"free->G", "free->H", "G->GH", "H->GH", "GH->G"}
    if (
        math.cos(theta) <= 1e-12
    ):  # cos(pi/2) rounds to 6e-17: lambda_H = 6e-16, zero to the search's tolerance
        out.add("H->free")
    return out


@pytest.mark.parametrize(
    "theta", [math.pi / 4, math.pi / 2, 3 * math.pi / 4, 5 * math.pi / 4, 7 * math.pi / 4]
)
def test_practice_problem_1_achievable_transitions(theta):
    args = {"g": G, "theta": theta}
    report = hj.check_properties(PARTICLE, args, bounds=PARTICLE_BOUNDS)
    assert set(report.achievable_transitions) == particle_achievable_by_hand(theta)
    # Each witness lies in its guard and in its source domain (the user's functions, evaluated here).
    for a, tr, k in zip(report.achievable, PARTICLE.transitions, range(8), strict=True):
        assert a.transition == tr.label
        if a.achievable:
            mode = PARTICLE.modes[PARTICLE.sources[k]]
            x = jnp.asarray(a.state)
            assert x.shape == (mode.dim,)
            assert float(tr.guard(0.0, x, args)) <= 1e-6
            if mode.domain is not None:
                assert np.all(np.asarray(mode.domain(0.0, x, args)) >= -1e-6)


# ----------------------------------------------------------------------------- thermostat

THERMO_ARGS = {"a": 0.5, "T_amb": 10.0, "P_heat": 15.0, "P_cool": 10.0, "s": 20.0}
THERMO_BOUNDS = {"off": (5.0, 35.0), "heat": (5.0, 35.0), "cool": (5.0, 35.0)}


THERMO = examples.thermostat()


def test_thermostat_is_nonblocking_with_disjoint_guards():
    report = hj.check_properties(THERMO, THERMO_ARGS, bounds=THERMO_BOUNDS)
    assert report.nonblocking and report.disjoint_guards and report.deterministic
    assert report.gaps == () and report.overlaps == () and report.resets_outside == ()
    assert report.chains == () and report.cycles == ()
    # Each guard meets its domain at one threshold only (the guards lie on the domains'
    # boundaries): heat on at s - 4, heat off at s - 2, cool on at s + 4, cool off at s + 2.
    s = THERMO_ARGS["s"]
    np.testing.assert_allclose(
        [float(a.state[0]) for a in report.achievable], [s - 4, s - 2, s + 4, s + 2], atol=1e-6
    )
    assert "nonblocking" in repr(report) and "<table>" in report._repr_html_()


def test_new_args_reuse_the_compiled_searches():
    hj.check_properties(THERMO, THERMO_ARGS, bounds=THERMO_BOUNDS)
    before = compile_count()
    report = hj.check_properties(THERMO, {**THERMO_ARGS, "s": 21.0}, bounds=THERMO_BOUNDS)
    assert compile_count() == before
    np.testing.assert_allclose(report.achievable[0].state, [21.0 - 4], atol=1e-6)


def test_check_properties_takes_a_simulator_and_search_options():
    # The band of the start rule comes from the simulator's step-size controller; rtol, atol are
    # shorthands for a PIDController with them. The thresholds are those of the closed form.
    controller = diffrax.PIDController(rtol=1e-8, atol=1e-8)
    by_simulator = hj.check_properties(THERMO, THERMO_ARGS, bounds=THERMO_BOUNDS,
                                       simulator=hj.Simulator(stepsize_controller=controller))
    by_tolerances = hj.check_properties(THERMO, THERMO_ARGS, bounds=THERMO_BOUNDS, rtol=1e-8, atol=1e-8)
    # search=hj.SearchOptions(...): the refinement's settings, its fields' keywords shorthands
    by_search = hj.check_properties(THERMO, THERMO_ARGS, bounds=THERMO_BOUNDS, rtol=1e-8,
                                    search=hj.SearchOptions(num_starts=8, iterations=64, tol=1e-14))
    by_keywords = hj.check_properties(THERMO, THERMO_ARGS, bounds=THERMO_BOUNDS, atol=1e-8, num_starts=8,
                                      max_steps=64, tol=1e-14)
    assert repr(by_simulator) == repr(by_tolerances) == repr(by_search) == repr(by_keywords)
    s = THERMO_ARGS["s"]
    np.testing.assert_allclose(
        [float(a.state[0]) for a in by_simulator.achievable], [s - 4, s - 2, s + 4, s + 2], atol=1e-6
    )
    # the band's tolerances: the controller's, or sqrt(eps) for one without (as the simulation loop)
    loose = hj.Simulator(stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-9))
    constant = hj.Simulator(stepsize_controller=diffrax.ConstantStepSize(), dt0=0.01)
    assert _start_tolerances(loose, None, None, jnp.float64) == (1e-6, 1e-9)
    assert _start_tolerances(constant, None, None, jnp.float64) == (math.sqrt(np.finfo(np.float64).eps),) * 2
    with pytest.raises(ValueError, match="simulator and rtol are the same option"):
        hj.check_properties(THERMO, THERMO_ARGS, bounds=THERMO_BOUNDS, simulator=hj.Simulator(), rtol=1e-8)
    with pytest.raises(ValueError, match="search and num_starts are the same option"):
        hj.check_properties(THERMO, THERMO_ARGS, bounds=THERMO_BOUNDS, search=hj.SearchOptions(), num_starts=8)
    with pytest.raises(TypeError, match="unexpected keyword argument 'max_epochs'"):
        hj.check_properties(THERMO, THERMO_ARGS, bounds=THERMO_BOUNDS, max_epochs=8)


def thermostat_variant() -> hj.HybridSystem:
    """The thermostat with three knobs in `args`: heat off fires at T >= s - 2 + d (d > 0 leaves
    a gap above the heat domain T <= s - 2), its reset adds `shift`, and an extra transition
    "pre-cool" off -> cool, listed last, fires at T >= s + o."""
    base = examples.thermostat()
    trs = list(base.transitions)
    trs[1] = hj.Transition(
        "heat",
        "off",
        guard=lambda t, x, p: (p["s"] - 2 + p["d"]) - x[0],
        reset=lambda t, x, p: x + p["shift"],
        name="heat off",
    )
    trs.append(hj.Transition("off", "cool", guard=lambda t, x, p: (p["s"] + p["o"]) - x[0], name="pre-cool"))
    return hj.HybridSystem(base.modes, trs)


VARIANT = thermostat_variant()


def variant(d=0.0, shift=0.0, o=10.0):
    # o = 10: pre-cool's guard T >= s + 10 misses the off domain T <= s + 4.
    return hj.check_properties(VARIANT, {**THERMO_ARGS, "d": d, "shift": shift, "o": o}, bounds=THERMO_BOUNDS)


def test_thermostat_with_a_gap_blocks_at_a_witness_in_the_gap():
    # Heat's domain T <= s - 2 has the boundary T = s - 2, where the flow a (T_amb - T) + P_heat
    # = 0.5 (10 - 18) + 15 = 11 > 0 leaves it; heat off needs T >= s - 1: the point T = s - 2 is
    # in no guard. No other boundary is uncovered.
    report = variant(d=1.0)
    assert not report.nonblocking
    assert report.disjoint_guards
    (gap,) = report.gaps
    assert gap.mode == "heat" and gap.component == 0
    np.testing.assert_allclose(gap.state, [THERMO_ARGS["s"] - 2], atol=1e-8)
    assert "heat off" not in report.achievable_transitions  # {T >= 19} misses {T <= 18}


DISC = hj.HybridSystem(
    [
        hj.Mode(
            "disc",
            lambda t, x, p: jnp.array([1.0 + 0.0 * x[0], 0.0 * x[1]]),
            dim=2,
            domain=lambda t, x, p: 1.0 - x[0] ** 2 - x[1] ** 2,
        ),
        hj.Mode("out", lambda t, x, p: 0.0 * x, dim=2),
    ],
    [hj.Transition("disc", "out", guard=lambda t, x, p: p["c"] - x[0], name="exit")],
)


@pytest.mark.parametrize("c", [0.0, 0.5])
def test_gap_on_a_curved_boundary(c):
    # The unit disc a = 1 - x^2 - y^2 >= 0 under the flow (1, 0): da/dt = -2x, so the flow leaves
    # through the arc x > 0 (at x = 0 it is tangent, and there the guard c - x = 0 fires for c = 0,
    # trending negative). The guard covers x >= c: for c = 0 the whole arc, for c = 0.5 not the
    # arc 0 < x < 0.5.
    report = hj.check_properties(DISC, {"c": c}, bounds={"disc": (-1.5, 1.5), "out": (-1.5, 1.5)})
    if c == 0.0:
        assert report.nonblocking and report.gaps == ()
        return
    (gap,) = report.gaps
    x, y = gap.state
    assert x * x + y * y == pytest.approx(1.0, abs=1e-8)
    assert 0.0 < x < c


def test_thermostat_with_an_overlapping_guard_reports_witness_and_winner():
    # pre-cool {T >= s + 3} and cool on {T >= s + 4} within off's domain s - 4 <= T <= s + 4
    # meet at T = s + 4 only; cool on is listed first and wins there.
    report = variant(o=3.0)
    assert report.nonblocking
    assert not report.disjoint_guards and not report.deterministic
    (ov,) = report.overlaps
    assert ov.mode == "off" and set(ov.transitions) == {"cool on", "pre-cool"} and ov.winner == "cool on"
    np.testing.assert_allclose(ov.state, [THERMO_ARGS["s"] + 4], atol=1e-6)


def test_reset_outside_its_target_domain_is_reported_with_the_state():
    # Heat off fires where the flow reaches T = s - 2 = 18 (the only point of its guard in the
    # heat domain); shifted by 7 it lands at 25, outside off's domain T <= s + 4 = 24 (its
    # component a[1] = (s + 4) - T = -1), strictly inside cool on's guard, which fires next.
    report = variant(shift=7.0)
    assert not report.nonblocking
    (out,) = report.resets_outside
    assert out.transition == "heat off" and out.component == 1
    np.testing.assert_allclose(out.state, [18.0], atol=1e-8)
    np.testing.assert_allclose(out.image, [25.0], atol=1e-8)
    assert out.outcome == "cool on fires first"
    (chain,) = report.chains
    assert chain.transitions == ("heat off", "cool on") and not chain.cyclic


# ----------------------------------------------------------------------------- reset chains


def test_ceiling_chain_of_length_two_and_no_cycle():
    # Impact where the flow reaches z = H moving up (v > 0) resets to (H, 0) in contact, inside
    # the lift-off guard -g <= 0, which fires at once back to flight at (H, 0); there the impact
    # guard H - z = 0 has dz/dt = v = 0 and d2/dt2 (H - z) = g > 0: not trending negative.
    H = 2.0
    report = hj.check_properties(
        examples.ceiling_ball(), {"g": G, "H": H}, bounds={"flight": (-5.0, 5.0), "contact": (-5.0, 5.0)}
    )
    (chain,) = report.chains
    assert chain.transitions == ("impact", "lift-off") and chain.length == 2 and not chain.cyclic
    assert report.max_chain_length == 2 and report.cycles == ()
    assert float(chain.state[0]) == pytest.approx(H, abs=1e-8) and float(chain.state[1]) > 0
    for image in chain.images:
        np.testing.assert_allclose(image, [H, 0.0], atol=1e-8)


def test_two_mode_reset_loop_is_a_cycle():
    # x' = -1 in both modes, identity resets. A -> B fires at x = 0 (entering x <= 0); x = 0 is
    # inside B's guard x - 1 <= 0, so B -> A fires at once, back to x = 0 in A, where A's guard
    # is 0 and trending negative: fires again, forever in zero time.
    flow = lambda t, x, p: -jnp.ones_like(x)
    loop = hj.HybridSystem(
        [hj.Mode("A", flow, dim=1), hj.Mode("B", flow, dim=1)],
        [
            hj.Transition("A", "B", guard=lambda t, x, p: x[0], name="A->B"),
            hj.Transition("B", "A", guard=lambda t, x, p: x[0] - 1.0, name="B->A"),
        ],
    )
    report = hj.check_properties(loop, None, bounds={"A": (-2.0, 2.0), "B": (-2.0, 2.0)})
    assert report.cycles == (("A->B", "B->A"),)
    assert any(c.cyclic for c in report.chains)
    assert "cycle" in repr(report)


H_TD, H_LO, K_SPRING = 1.0, 0.9, 50.0


def hopper() -> hj.HybridSystem:
    """A 1-D hopper, state (h, v). Flight: (v, -g), touchdown when h <= h_td. Stance: a spring
    of rest length h_td, (v, k (h_td - h) - g); lift-off when the body rises through h_lo <
    h_td (guard max(h_lo - h, -v): h >= h_lo while moving up). The lift-off reset goes to the
    apex of the flight, (h + v^2 / (2 g), 0). An apex below h_td is inside the touchdown guard."""
    flight = hj.Mode("flight", lambda t, x, p: jnp.array([x[1], -G + 0.0 * x[1]]), dim=2)
    stance = hj.Mode("stance", lambda t, x, p: jnp.array([x[1], K_SPRING * (H_TD - x[0]) - G]), dim=2)
    return hj.HybridSystem(
        [flight, stance],
        [
            hj.Transition("flight", "stance", guard=lambda t, x, p: x[0] - H_TD, name="touchdown"),
            hj.Transition(
                "stance",
                "flight",
                guard=lambda t, x, p: jnp.maximum(H_LO - x[0], -x[1]),
                reset=lambda t, x, p: jnp.array([x[0] + x[1] ** 2 / (2 * G), 0.0 * x[1]]),
                name="lift-off",
            ),
        ],
    )


def test_hopper_apex_below_touchdown_resets_into_the_touchdown_guard():
    # Lift-off states the flow reaches: h = h_lo, v > 0 (guard h_lo - h = 0, d/dt = -v < 0);
    # the other branch, v = 0 with h > h_lo, would need d/dt(-v) = g - k (h_td - h) < 0, i.e.
    # k (h_td - h_lo) > g, false for k = 50 (5 < 9.8). The apex h_lo + v^2 / (2 g) is below
    # h_td iff v < sqrt(2 g (h_td - h_lo)) = 1.4: then touchdown fires at once. In stance at
    # (apex, 0): lift-off's guard max(h_lo - apex, 0) = 0 with d/dt = g - k (h_td - apex) > 0
    # (as above): it does not fire, and the chain has length two.
    report = hj.check_properties(hopper(), None, bounds={"flight": (-2.0, 2.0), "stance": (-2.0, 2.0)})
    (chain,) = report.chains
    assert chain.transitions == ("lift-off", "touchdown") and not chain.cyclic
    h, v = (float(c) for c in chain.state)
    assert h == pytest.approx(H_LO, abs=1e-8)
    assert 0 < v < math.sqrt(2 * G * (H_TD - H_LO))
    np.testing.assert_allclose(chain.images[0], [H_LO + v * v / (2 * G), 0.0], rtol=1e-12, atol=1e-12)
    assert chain.images[0][0] < H_TD
    assert report.cycles == ()


def test_time_varying_guard_is_searched_over_the_window():
    # A clock: guard 1 - t (fires from t = 1 on). Over t in [0, 0.5] the guard set is empty;
    # over [0, 2] it is met at t >= 1.
    clock = hj.HybridSystem(
        [hj.Mode("wait", lambda t, x, p: 0.0 * x, dim=1), hj.Mode("go", lambda t, x, p: 0.0 * x, dim=1)],
        [hj.Transition("wait", "go", guard=lambda t, x, p: 1.0 - t + 0.0 * x[0], name="ring")],
    )
    bounds = {"wait": (-1.0, 1.0), "go": (-1.0, 1.0)}
    early = hj.check_properties(clock, None, bounds=bounds, t_bounds=(0.0, 0.5))
    late = hj.check_properties(clock, None, bounds=bounds, t_window=(0.0, 2.0))
    assert early.achievable_transitions == () and late.achievable_transitions == ("ring",)
    assert 1.0 - 1e-8 <= late.achievable[0].t <= 2.0
    # t_window: a shorthand for t_bounds (the name find_point and Scene use); both at once refused
    assert late.t_bounds == late.t_window == (0.0, 2.0)
    assert repr(hj.check_properties(clock, None, bounds=bounds, t_bounds=(0.0, 2.0))) == repr(late)
    with pytest.raises(ValueError, match="t_bounds and t_window are the same option"):
        hj.check_properties(clock, None, bounds=bounds, t_bounds=(0.0, 2.0), t_window=(0.0, 2.0))


def test_a_domain_with_no_transition_out_blocks_at_its_boundary():
    # x' = 1 on x <= 1 and no transitions: the flow leaves through x = 1, which no guard covers.
    report = hj.check_properties(
        line_system(domain=lambda t, x, p: 1.0 - x[0]), None, bounds={"m": (-2.0, 2.0), "done": (-2.0, 2.0)}
    )
    (gap,) = report.gaps
    assert gap.mode == "m" and not report.nonblocking
    np.testing.assert_allclose(gap.state, [1.0], atol=1e-10)
    assert report.achievable == () and report.chains == ()


def test_missing_bounds_name_the_mode():
    with pytest.raises(ValueError, match="'heat'"):
        hj.check_properties(
            examples.thermostat(), THERMO_ARGS, bounds={"off": (5.0, 35.0), "cool": (5.0, 35.0)}
        )
    with pytest.raises(ValueError, match="unknown modes"):
        hj.check_properties(examples.thermostat(), THERMO_ARGS, bounds={**THERMO_BOUNDS, "fan": (0.0, 1.0)})
