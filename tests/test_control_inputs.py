"""A control input passed through `args`: the ball with a vertical thrust u(t) added to gravity.

The gradient of the second impact time with respect to the control values, by
`jax.jit(jax.value_and_grad(...))` through `hj.simulate`, is checked against central differences
of a closed form: between grid points the thrust is constant (a table) or linear (a
`diffrax.LinearInterpolation`), so the height is a piecewise quadratic or cubic in t, whose
roots numpy finds segment by segment.
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import hybridjax as hj

from helpers import TIGHT, central_difference

G, E, H0 = 9.8, 0.8, 1.0
T, N = 1.6, 8                    # the control's horizon and number of values
DT = T / N
T1 = 1.5                         # two impacts, near t = 0.47 and 1.28, before t1
U = np.array([2.0, -1.5, 1.0, 3.0, -2.0, 0.5, 2.5, -1.0])
KNOTS = np.linspace(0.0, T, N)   # LinearInterpolation knots of the same values


def _bounce():
    return hj.Transition("flight", "flight", guard=lambda t, x, a: x[0],
                         reset=lambda t, x, a: x.at[1].multiply(-a["e"]), name="bounce")


# The table: state (h, v, k), k the index of the value in force, advanced by a transition at
# each grid time t = (k + 1) DT, so that every switch of the thrust is an event.
TABLE_BALL = hj.HybridSystem(
    [hj.Mode("flight", lambda t, x, a: jnp.stack(
        [x[1], -a["g"] + a["u"][jnp.clip(x[2].astype(jnp.int32), 0, N - 1)], jnp.zeros_like(x[2])]),
        dim=3)],
    [_bounce(), hj.Transition("flight", "flight", guard=lambda t, x, a: (x[2] + 1) * DT - t,
                              reset=lambda t, x, a: x.at[2].add(1.0), name="switch")])

# The interpolation: state (h, v), the thrust evaluated at t.
LINEAR_BALL = hj.HybridSystem(
    [hj.Mode("flight", lambda t, x, a: jnp.stack([x[1], -a["g"] + a["u"].evaluate(t)]), dim=2)],
    [_bounce()])


def _second_impact(system, x0, control, controller=TIGHT):
    args = {"g": jnp.asarray(G), "e": jnp.asarray(E), "u": control}
    sol = hj.simulate(system, x0, "flight", 0.0, T1, args, stepsize_controller=controller)
    second = jnp.nonzero(sol.transitions == 0, size=2)[0][1]   # transition 0 is the bounce
    return sol.event_times[second]


table_cost = jax.jit(jax.value_and_grad(
    lambda u: _second_impact(TABLE_BALL, jnp.array([H0, 0.0, 0.0]), u)))
# The linear thrust has kinks at its knots: steps end there (`step_ts`), so that every step
# integrates a smooth field and the derivative's error stays at the solver's tolerance.
KNOT_STEPS = diffrax.PIDController(rtol=TIGHT.rtol, atol=TIGHT.atol, step_ts=jnp.asarray(KNOTS))
linear_cost = jax.jit(jax.value_and_grad(
    lambda u: _second_impact(LINEAR_BALL, jnp.array([H0, 0.0]),
                             diffrax.LinearInterpolation(jnp.asarray(KNOTS), u), KNOT_STEPS)))


# ----------------------------------------------------------------------------- closed form


def _first_root(h, v, acc, jerk, length):
    """Smallest s in (0, length] with h + v s + acc s^2 / 2 + jerk s^3 / 6 = 0, or None."""
    poly = np.array([jerk / 6, acc / 2, v, h])
    roots = np.roots(poly[:-1] if h == 0.0 else poly)  # just after an impact s = 0 is a root: divide it out
    found = sorted(r.real for r in roots if abs(r.imag) < 1e-9 and 0.0 < r.real <= length)
    if not found:
        return None
    s = found[0]
    for _ in range(3):                                  # Newton steps polish it to rounding level
        s -= np.polyval(poly, s) / np.polyval(np.polyder(poly), s)
    return s


def impact_times(knots, values, linear, n):
    """The first n impact times of the ball under a thrust constant on [knots[j], knots[j+1])
    (value values[j]) or linear between knots (values at the knots)."""
    t, h, v, times = 0.0, H0, 0.0, []
    for j in range(len(knots) - 1):
        a, b = knots[j], knots[j + 1]
        jerk = (values[j + 1] - values[j]) / (b - a) if linear else 0.0
        while True:
            acc = values[j] + jerk * (t - a) - G
            s = _first_root(h, v, acc, jerk, b - t)
            if s is None:                               # no impact left in this segment
                s = b - t
                h, v, t = h + v * s + acc * s * s / 2 + jerk * s ** 3 / 6, v + acc * s + jerk * s * s / 2, b
                break
            t += s
            times.append(t)
            if len(times) == n:
                return np.array(times)
            h, v = 0.0, -E * (v + acc * s + jerk * s * s / 2)
    raise ValueError("fewer impacts than asked for")


def _table_truth(u):
    return impact_times(np.linspace(0.0, T, N + 1), u, linear=False, n=2)[1]


def _linear_truth(u):
    return impact_times(KNOTS, u, linear=True, n=2)[1]


# ----------------------------------------------------------------------------- tests


def test_piecewise_constant_thrust_gradient_matches_the_closed_form():
    value, grad = table_cost(jnp.asarray(U))
    np.testing.assert_allclose(value, _table_truth(U), rtol=1e-12)
    fd = central_difference(lambda u: np.array([_table_truth(u)]), U, eps=1e-6)[0]
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-9)
    # the last value acts after the second impact: exactly no effect on its time
    assert grad[-1] == 0.0 and np.all(grad[:-1] != 0.0)


def test_linearly_interpolated_thrust_gradient_matches_the_closed_form():
    value, grad = linear_cost(jnp.asarray(U))
    np.testing.assert_allclose(value, _linear_truth(U), rtol=1e-12)
    fd = central_difference(lambda u: np.array([_linear_truth(u)]), U, eps=1e-6)[0]
    np.testing.assert_allclose(grad, fd, rtol=0, atol=1e-7 * np.abs(fd).max())
    # the last knot (t = 1.6) shapes the thrust only after t = 1.37, past the second impact
    assert grad[-1] == 0.0 and np.all(grad[:-1] != 0.0)
    # other control values reuse the compiled program
    value2, _ = linear_cost(jnp.asarray(U + 0.25))
    np.testing.assert_allclose(value2, _linear_truth(U + 0.25), rtol=1e-8)


def test_batched_engine_keeps_the_table_index_exact():
    # The batched engine reads event states from each step's Chebyshev series: the table index
    # x[2] is constant between switches and must read as exactly the integer it is (2 read as
    # 1.999... truncates to the previous table entry). Three thrust tables, against the closed form.
    us = np.stack([U, U[::-1], U + 0.5])
    args = {"g": jnp.full(3, G), "e": jnp.full(3, E), "u": jnp.asarray(us)}
    x0 = jnp.broadcast_to(jnp.array([H0, 0.0, 0.0]), (3, 3))
    sol = hj.simulate_batch(TABLE_BALL, x0, "flight", 0.0, T1, args, stepsize_controller=TIGHT,
                            args_batched=True, engine="batched")
    for i, u in enumerate(us):
        bounces = np.asarray(sol.event_times[i])[np.asarray(sol.transitions[i]) == 0]
        np.testing.assert_allclose(bounces[1], _table_truth(u), rtol=1e-10)
