"""Small dense linear algebra as array operations (no LAPACK call), against numpy's LAPACK."""

import jax
import jax.numpy as jnp
import numpy as np

from hybridjax._core.small_linalg import cholesky, cholesky_inverse, det, least_squares, solve, spd_solve

RNG = np.random.default_rng(0)


def test_solve_equals_lapack_and_pivots():
    for n in (1, 2, 5, 9):
        a, b, B = RNG.normal(size=(n, n)), RNG.normal(size=n), RNG.normal(size=(n, 3))
        np.testing.assert_allclose(solve(a, b), np.linalg.solve(a, b), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(solve(a, B), np.linalg.solve(a, B), rtol=1e-12, atol=1e-12)
    # a zero first pivot needs the row exchange
    np.testing.assert_allclose(solve(jnp.array([[0.0, 1.0], [1.0, 0.0]]), jnp.array([2.0, 3.0])), [3.0, 2.0])


def test_det_equals_lapack_with_its_sign():
    for n in (1, 3, 6):
        a = RNG.normal(size=(n, n))
        np.testing.assert_allclose(det(a), np.linalg.det(a), rtol=1e-12)
    assert float(det(jnp.array([[0.0, 1.0], [1.0, 0.0]]))) == -1.0  # one row exchange


def test_solve_derivative_by_the_inverse():
    # d(a^-1 b)/da_ij = -(a^-1)_ki x_j  =>  grad of sum(x) = -(a^-T 1) x^T
    a, b = jnp.asarray(RNG.normal(size=(4, 4))), jnp.asarray(RNG.normal(size=4))
    g = jax.grad(lambda a: solve(a, b).sum())(a)
    x = np.linalg.solve(a, b)
    np.testing.assert_allclose(g, -np.outer(np.linalg.solve(np.asarray(a).T, np.ones(4)), x), rtol=1e-10)


def test_cholesky_and_spd_solve_equal_lapack_and_a_dependent_gram_matrix_has_a_zero_pivot():
    J = RNG.normal(size=(3, 5))
    G = J @ J.T
    L = np.array([[float(v) if v is not None else 0.0 for v in row] for row in cholesky(jnp.asarray(G))])
    np.testing.assert_allclose(L, np.linalg.cholesky(G), rtol=1e-12)
    B = RNG.normal(size=(3, 2))
    np.testing.assert_allclose(spd_solve(jnp.asarray(G), jnp.asarray(B)), np.linalg.solve(G, B), rtol=1e-10)
    # spd_solve's derivative comes from custom_linear_solve: d(G^-1 b)/db = G^-1
    jac = jax.jacfwd(lambda b: spd_solve(jnp.asarray(G), b))(jnp.asarray(B[:, 0]))
    np.testing.assert_allclose(jac, np.linalg.inv(G), rtol=1e-9)
    Jd = np.vstack([J[:2], 2.0 * J[0] - J[1]])  # the third row a combination of the others
    last = cholesky(jnp.asarray(Jd @ Jd.T))[2][2]
    assert not np.isfinite(float(last)) or float(last) ** 2 < 1e-12 * float(np.max(np.diag(Jd @ Jd.T)))


def test_cholesky_inverse_equals_the_inverse_of_lapacks_factor():
    for n in (1, 2, 4, 7):
        J = RNG.normal(size=(n, n + 2))
        G = J @ J.T
        X = np.asarray(cholesky_inverse(jnp.asarray(G)))
        np.testing.assert_allclose(X, np.linalg.inv(np.linalg.cholesky(G)), rtol=1e-10, atol=1e-12)
        assert np.all(np.triu(X, 1) == 0.0)  # lower triangular, exact zeros above the diagonal


def test_least_squares_full_rank_and_least_norm():
    a, b = RNG.normal(size=(6, 3)), RNG.normal(size=6)
    np.testing.assert_allclose(least_squares(a, b), np.linalg.lstsq(a, b, rcond=None)[0], rtol=1e-9)
    # a repeated column: the least-norm solution splits its weight equally (numpy's SVD lstsq)
    ad = np.hstack([a, a[:, :1]])
    # the damped normal equations meet it to rounding over the damping in the direction a does
    # not see: eps / 1e-13, about 2e-3
    np.testing.assert_allclose(least_squares(ad, b), np.linalg.lstsq(ad, b, rcond=None)[0], atol=1e-3)
