"""The point search: a witness where the constraints are feasible, none where they are not."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import hybridjax as hj

N = 64
XS = hj.box_samples(jax.random.key(0), -2.0 * jnp.ones(2), 2.0 * jnp.ones(2), N)


def circle(t, x, a):
    return jnp.array([x[0] ** 2 + x[1] ** 2 - 1.0])


def half_plane(t, x, a):
    return jnp.array([x[0] - a])


# The unit circle against the half-plane x[0] >= a, for several a at once (one compile).
CIRCLE_IN_HALF_PLANE = jax.jit(jax.vmap(lambda a: hj.find_point(circle, half_plane, jnp.zeros(N), XS, a)))
A = jnp.array([0.0, 0.5, 0.999999, 1.0, 1.5])


def test_box_samples_lie_in_the_box():
    lo, hi = jnp.array([-1.0, 2.0, 0.0]), jnp.array([1.0, 3.0, 0.0])
    xs = hj.box_samples(jax.random.key(1), lo, hi, 100)
    assert xs.shape == (100, 3)
    assert np.all(np.asarray(xs) >= np.asarray(lo)) and np.all(np.asarray(xs) <= np.asarray(hi))


def test_box_samples_take_bounds_and_the_lower_upper_shorthands():
    lo, hi = jnp.array([-1.0, 2.0]), jnp.array([1.0, 6.0])
    key = jax.random.key(2)
    xs = hj.box_samples(key, (lo, hi), 4000)
    for same in (hj.box_samples(key, lo, hi, 4000), hj.box_samples(key, lower=lo, upper=hi, num=4000)):
        np.testing.assert_array_equal(same, xs)
    # uniform on [lo, hi]: in the box, mean (lo + hi) / 2 and variance (hi - lo)^2 / 12, each
    # within 4 standard errors for 4000 samples
    x = np.asarray(xs)
    assert np.all(x >= np.asarray(lo)) and np.all(x <= np.asarray(hi))
    width = np.asarray(hi - lo)
    assert np.all(np.abs(x.mean(0) - np.asarray(lo + hi) / 2) < 4 * width / np.sqrt(12 * 4000))
    assert np.all(np.abs(x.var(0) - width**2 / 12) < 4 * width**2 / np.sqrt(180 * 4000))
    with pytest.raises(ValueError, match="bounds and lower"):
        hj.box_samples(key, (lo, hi), 8, lower=lo)
    with pytest.raises(TypeError, match="'lowr'"):
        hj.box_samples(key, (lo, hi), 8, lowr=lo)


def test_point_on_a_circle_inside_a_half_plane():
    w = CIRCLE_IN_HALF_PLANE(A)
    found = np.asarray(w.found)
    np.testing.assert_array_equal(found, [True, True, True, True, False])
    x = np.asarray(w.x)[found]
    # Found means violation <= 1e-10, i.e. each residual within 1e-5; these converge to rounding.
    np.testing.assert_allclose(np.sum(x**2, axis=1), 1.0, atol=1e-12)
    assert np.all(x[:, 0] >= np.asarray(A)[found] - 1e-12)
    # a = 1: the half-plane touches the circle at the single point (1, 0).
    np.testing.assert_allclose(np.asarray(w.x)[3], [1.0, 0.0], atol=1e-6)


def test_infeasible_pair_reported_not_found_with_its_least_violation():
    w = CIRCLE_IN_HALF_PLANE(A)
    # a = 1.5: no point. The least violation, min over x of (|x|^2 - 1)^2 + min(x0 - 1.5, 0)^2,
    # by scipy from the side where it lies (x1 = 0, 1 <= x0 <= 1.5).
    res = scipy.optimize.minimize_scalar(
        lambda u: (u * u - 1) ** 2 + (u - 1.5) ** 2,
        bounds=(1.0, 1.5),
        method="bounded",
        options={"xatol": 1e-12},
    )
    assert not bool(w.found[4])
    np.testing.assert_allclose(float(w.violation[4]), res.fun, rtol=1e-8)
    np.testing.assert_allclose(float(w.x[4, 0]), res.x, rtol=1e-6)


SEGMENT = jax.jit(
    lambda c: hj.find_point(
        lambda t, x, c: x[:1] - t,  # x[0] = t ...
        lambda t, x, c: x[:1] - c,  # ... >= c, with t in [1, 2]
        jnp.zeros(4),
        jnp.zeros((4, 2)),
        c,
        t_bounds=(1.0, 2.0),
    )
)


@pytest.mark.parametrize("c, feasible", [(1.5, True), (2.5, False)])
def test_time_is_searched_within_its_bounds(c, feasible):
    w = SEGMENT(c)
    assert bool(w.found) == feasible
    assert 1.0 <= float(w.t) <= 2.0
    if feasible:
        assert float(w.t) >= c - 1e-9
        np.testing.assert_allclose(float(w.x[0]), float(w.t), atol=1e-9)
    else:
        # min over t in [1, 2] and x0 of (x0 - t)^2 + min(x0 - c, 0)^2: at t = 2, x0 = (2 + c) / 2.
        np.testing.assert_allclose(float(w.violation), (c - 2.0) ** 2 / 2, rtol=1e-8)
        np.testing.assert_allclose([float(w.t), float(w.x[0])], [2.0, (2.0 + c) / 2], rtol=1e-8)


def test_samples_where_a_constraint_is_not_finite_are_skipped():
    # sqrt(x0) - 0.5 >= 0 is NaN for x0 < 0: those samples score inf, the others are refined.
    xs = jnp.array([[-1.0], [-2.0], [0.1], [-3.0]])
    w = jax.jit(
        lambda xs: hj.find_point(None, lambda t, x, a: jnp.sqrt(x) - 0.5, jnp.zeros(4), xs, num_starts=2)
    )(xs)
    assert bool(w.found)
    assert float(w.x[0]) >= 0.25 - 1e-12


def test_refinement_from_points_where_every_derivative_is_not_finite_ends():
    # sqrt(x0) = 1 and x0 + x1 = 3 (the point (1, 2)), refined from starts where sqrt is NaN
    # (x0 < 0) or its derivative infinite (x0 = 0): every step stays finite (a NaN in the
    # least-squares SVD can stall it), and the search ends at the point.
    xs = jnp.array([[-1.0, 0.0], [0.0, 0.0], [-2.0, 1.0]])

    def eq(t, x, a):
        return jnp.array([jnp.sqrt(x[0]) - 1.0, x[0] + x[1] - 3.0])

    w = jax.jit(lambda xs: hj.find_point(eq, None, jnp.zeros(3), xs, num_starts=3))(xs)
    assert bool(w.found)
    np.testing.assert_allclose(np.asarray(w.x), [1.0, 2.0], atol=1e-6)


def test_the_refinement_differentiates_the_residuals_through_their_jacobian_with_non_finite_entries_zero():
    # r(y) = (sqrt(y0), y0 y1): at y = (0, 2) the Jacobian is [[inf, 0], [2, 0]]; the tangent
    # along v = (3, 5) is J v with the infinite entry set to 0: (0, 6), by hand.
    from hybridjax._analysis.search import _with_jacobian

    r = _with_jacobian(lambda y: jnp.stack([jnp.sqrt(y[0]), y[0] * y[1]]))
    value, tangent = jax.jvp(lambda y: r(y, None), (jnp.array([0.0, 2.0]),), (jnp.array([3.0, 5.0]),))
    np.testing.assert_array_equal(np.asarray(value), [0.0, 0.0])
    np.testing.assert_array_equal(np.asarray(tangent), [0.0, 6.0])
    # Where every entry is finite, the tangent is the residuals' own (y = (4, 2): [[1/4, 0], [2, 4]]).
    _, tangent = jax.jvp(lambda y: r(y, None), (jnp.array([4.0, 2.0]),), (jnp.array([3.0, 5.0]),))
    np.testing.assert_allclose(np.asarray(tangent), [0.75, 26.0], rtol=1e-15)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="both are None"):
        hj.find_point(None, None, jnp.zeros(2), jnp.zeros((2, 1)))
    with pytest.raises(ValueError, match=r"\(N,\)"):
        hj.find_point(circle, None, jnp.zeros(3), jnp.zeros((2, 2)))


def test_box_samples_takes_num_samples():
    # num_samples (num a shorthand): N points of the box [-2, 2]^2, the same from one key
    lo, hi = -2.0 * jnp.ones(2), 2.0 * jnp.ones(2)
    named = hj.box_samples(jax.random.key(0), (lo, hi), num_samples=N)
    np.testing.assert_array_equal(hj.box_samples(jax.random.key(0), (lo, hi), num=N), named)
    np.testing.assert_array_equal(XS, named)
    assert named.shape == (N, 2) and bool(jnp.all((named >= -2.0) & (named <= 2.0)))
    with pytest.raises(ValueError, match="num_samples and num are the same option"):
        hj.box_samples(jax.random.key(0), (lo, hi), N, num=N)

