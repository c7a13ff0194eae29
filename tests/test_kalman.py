"""The salted Kalman filter against a textbook Kalman filter, the ball's closed-form saltation
matrix, chi-square bounds on the normalised estimation error, and finite differences."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.stats

import hybridjax as hj

TIGHT = diffrax.PIDController(rtol=1e-12, atol=1e-12)
G, E = 9.81, 0.8
BALL_ARGS = {"g": G, "e": E}


def _height(t, x, args):
    return x[:1]


# ---------------------------------------------------------------- one mode, linear: textbook KF
A_LIN = np.array([[0.0, 1.0], [-2.0, -0.3]])
H_LIN = np.array([[1.0, 0.5]])


def _textbook_kalman(x0, P0, t0, ts, ys, Q, R):
    """x_k^- = F x, P^- = F P F^T + Q with F = expm(A dt); K = P^- H^T S^-1; the standard update."""
    x, P, t = x0.copy(), P0.copy(), t0
    means, covs, ll = [], [], 0.0
    for tk, yk in zip(ts, ys, strict=True):
        F = scipy.linalg.expm(A_LIN * (tk - t))
        x, P = F @ x, F @ P @ F.T + Q
        S = H_LIN @ P @ H_LIN.T + R
        K = P @ H_LIN.T @ np.linalg.inv(S)
        nu = yk - H_LIN @ x
        ll += -0.5 * (nu @ np.linalg.solve(S, nu) + np.log(np.linalg.det(2 * np.pi * S)))
        x, P = x + K @ nu, (np.eye(2) - K @ H_LIN) @ P
        means.append(x), covs.append(P)
        t = tk
    return np.array(means), np.array(covs), ll


def test_one_linear_mode_equals_the_textbook_kalman_filter():
    linear = hj.HybridSystem([hj.Mode("m", lambda t, x, args: jnp.asarray(A_LIN) @ x, dim=2)])
    kf = hj.SaltedKalmanFilter(linear, lambda t, x, args: jnp.asarray(H_LIN) @ x, stepsize_controller=TIGHT)
    rng = np.random.default_rng(1)
    ts = np.cumsum(rng.uniform(0.05, 0.2, 12))
    ys = rng.normal(size=(12, 1))
    x0, P0 = np.array([1.0, -0.5]), np.array([[0.3, 0.05], [0.05, 0.2]])
    Q, R = np.array([[1e-3, 2e-4], [2e-4, 5e-3]]), np.array([[0.04]])
    res = kf(x0, P0, ts, ys, Q, R, t0=0.0)
    means, covs, ll = _textbook_kalman(x0, P0, 0.0, ts, ys, Q, R)
    np.testing.assert_allclose(res.means, means, rtol=0, atol=1e-10)
    np.testing.assert_allclose(res.covariances, covs, rtol=0, atol=1e-10)
    np.testing.assert_allclose(res.log_likelihood, ll, rtol=0, atol=1e-10)
    assert np.all(np.asarray(res.status) == hj.Status.T1_REACHED)


# ---------------------------------------------------------------- the ball across one impact
def _flow_stm(dt):
    return np.array([[1.0, dt], [0.0, 1.0]])


def _ball_saltation(v_minus):
    """Xi = D_x R + (F_J(R x) - D_x R F_I(x)) D_x g / (D_x g F_I(x)) at h = 0, for the guard
    g = h, reset (h, v) -> (h, -e v), flow (v, -g): D_x R = diag(1, -e),
    F_J - D_x R F_I = (-e v - v, -g - e g), D_x g = (1, 0), D_x g F_I = v."""
    return np.array([[-E, 0.0], [-(1 + E) * G / v_minus, -E]])


@pytest.mark.parametrize("update", ["saltation", "reset"])
def test_covariance_across_an_impact_is_salted(update):
    ball = hj.examples.bouncing_ball()
    kf = hj.SaltedKalmanFilter(ball, _height, update=update, stepsize_controller=TIGHT)
    h0, v0, t_meas = 0.6, 1.0, 0.7
    t_hit = (v0 + np.sqrt(v0**2 + 2 * G * h0)) / G
    v_minus = v0 - G * t_hit
    assert t_hit < t_meas
    P0 = np.array([[2e-3, 5e-4], [5e-4, 1e-3]])
    Q = np.diag([1e-6, 2e-6])
    res = kf(np.array([h0, v0]), P0, np.array([t_meas]), np.array([[0.3]]), Q, np.array([[1e-2]]),
             t0=0.0, args=BALL_ARGS)
    M = _ball_saltation(v_minus) if update == "saltation" else np.diag([1.0, -E])
    J = _flow_stm(t_meas - t_hit) @ M @ _flow_stm(t_hit)
    assert int(res.num_events[0]) == 1
    np.testing.assert_allclose(res.predicted_covariances[0], J @ P0 @ J.T + Q, rtol=1e-8, atol=1e-12)
    w = np.sqrt(v0**2 + 2 * G * h0) * E  # the mean: the closed-form ball
    dt = t_meas - t_hit
    np.testing.assert_allclose(res.predicted_means[0], [w * dt - G * dt**2 / 2, w - G * dt], rtol=1e-9)


# ---------------------------------------------------------------- a batch of filters: NEES
N_TRIALS = 400
TS = 0.03 + 0.04 * np.arange(38)  # no measurement within 15 ms of the nominal impacts
X0 = np.array([1.0, 0.0])
P0_BALL = np.diag([0.01**2, 0.01**2])
R_BALL = np.array([[0.01**2]])


def _ball_truths():
    rng = np.random.default_rng(7)
    x0s = X0 + rng.normal(size=(N_TRIALS, 2)) @ np.linalg.cholesky(P0_BALL).T
    ball = hj.examples.bouncing_ball()
    truth = jax.jit(jax.vmap(lambda x: hj.simulate(ball, x, 0, 0.0, TS[-1], BALL_ARGS, saveat=jnp.asarray(TS)).ys))
    xs = np.asarray(truth(jnp.asarray(x0s)))
    ys = xs[:, :, :1] + 0.01 * rng.normal(size=(N_TRIALS, len(TS), 1))
    return xs, ys


def _nees_and_error(update, xs, ys):
    kf = hj.SaltedKalmanFilter(hj.examples.bouncing_ball(), _height, update=update)
    run = jax.jit(jax.vmap(lambda y: kf(X0, P0_BALL, TS, y, jnp.zeros((2, 2)), R_BALL, t0=0.0, args=BALL_ARGS)))
    res = run(jnp.asarray(ys))
    err = xs - np.asarray(res.means)
    nees = np.einsum("nki,nkij,nkj->nk", err, np.linalg.inv(np.asarray(res.covariances)), err)
    return nees, err, res


def test_batch_of_filters_on_a_noisy_ball_is_consistent_and_beats_the_reset_update():
    xs, ys = _ball_truths()
    impacts = hj.examples.bouncing_ball_closed_form(1.0, 0.0, G, E, TS[-1])["event_times"]
    assert len(impacts) == 2 and np.min(np.abs(TS[:, None] - impacts[None, :])) > 0.015
    nees_s, err_s, res_s = _nees_and_error("saltation", xs, ys)
    nees_r, err_r, _ = _nees_and_error("reset", xs, ys)
    assert np.all(np.asarray(res_s.status) == hj.Status.T1_REACHED)
    # N * (average NEES at a time) ~ chi2(2 N) for a consistent filter (Bar-Shalom, Li,
    # Kirubarajan, "Estimation with Applications to Tracking and Navigation", Sec. 5.4).
    lo, hi = scipy.stats.chi2.ppf([0.005, 0.995], 2 * N_TRIALS) / N_TRIALS
    anees_s, anees_r = nees_s.mean(axis=0), nees_r.mean(axis=0)
    inside = np.mean((anees_s >= lo) & (anees_s <= hi))
    assert inside >= 0.9, (inside, anees_s)
    after = TS > impacts[0]
    # the reset-Jacobian update is inconsistent after the first impact, and its errors larger
    assert np.mean((anees_r[after] >= lo) & (anees_r[after] <= hi)) < 0.5, anees_r
    rms_s = np.sqrt(np.mean(err_s[:, after] ** 2, axis=(0, 1)))
    rms_r = np.sqrt(np.mean(err_r[:, after] ** 2, axis=(0, 1)))
    assert np.all(rms_s < rms_r), (rms_s, rms_r)


def test_log_likelihood_gradient_in_noise_and_model_parameters_matches_finite_differences():
    kf = hj.SaltedKalmanFilter(hj.examples.bouncing_ball(), _height, stepsize_controller=TIGHT)
    ts = np.array([0.2, 0.42, 0.5, 0.6, 0.75])
    ys = np.array([[0.81], [0.14], [0.15], [0.42], [0.6]])

    def loglik(theta):
        log_r, e = theta[0], theta[1]
        R = jnp.exp(log_r) * jnp.eye(1)
        res = kf(X0, P0_BALL, ts, ys, 1e-6 * jnp.eye(2), R, t0=0.0, args={"g": G, "e": e})
        return res.log_likelihood

    theta = jnp.array([np.log(1e-3), 0.75])
    grad = jax.grad(loglik)(theta)
    f = jax.jit(loglik)
    eps = 1e-6
    fd = [(f(theta.at[i].add(eps)) - f(theta.at[i].add(-eps))) / (2 * eps) for i in range(2)]
    # central differences of a function computed to ~1e-12: error ~ eps^2 f''' + 1e-12 / eps
    assert np.all(np.abs(np.asarray(fd)) > 1e-3)
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


def test_a_transition_to_a_mode_of_smaller_dimension_with_its_own_measurement():
    # Mode "fall" (p, v): flow (v, -1); at p = 0 the state becomes q = v in mode "decay" (dim 1),
    # flow -q. Xi (1 x 2) = D_x R + (F_J - D_x R F_I) D_x g / (D_x g F_I) with D_x R = (0, 1),
    # F_J = -v, D_x R F_I = -1, D_x g = (1, 0), D_x g F_I = v: Xi = ((1 - v) / v, 1).
    fall = hj.Mode("fall", lambda t, x, args: jnp.stack([x[1], -jnp.ones_like(x[1])]), dim=2)
    decay = hj.Mode("decay", lambda t, x, args: -x, dim=1)
    land = hj.Transition("fall", "decay", guard=lambda t, x, args: x[0], reset=lambda t, x, args: x[1:])
    system = hj.HybridSystem([fall, decay], [land])
    kf = hj.SaltedKalmanFilter(system, [lambda t, x, args: x[:1], lambda t, x, args: 2.0 * x],
                               stepsize_controller=TIGHT)
    p0, v0, t1 = 0.5, 0.5, 2.0
    t_hit = v0 + np.sqrt(v0**2 + 2 * p0)  # p0 + v0 t - t^2 / 2 = 0
    v_minus = v0 - t_hit
    P0, Q, R = np.array([[0.02, 0.004], [0.004, 0.01]]), np.diag([3e-4, 7e-4]), np.array([[0.05]])
    y = 0.1
    res = kf(np.array([p0, v0]), P0, np.array([t1]), np.array([[y]]), Q, R, mode0="fall", t0=0.0)
    J = np.exp(-(t1 - t_hit)) * np.array([[(1 - v_minus) / v_minus, 1.0]]) @ _flow_stm(t_hit)
    P_pred = (J @ P0 @ J.T)[0, 0] + Q[0, 0]  # decay uses Q's leading block
    q_pred = v_minus * np.exp(-(t1 - t_hit))
    assert int(res.modes[0]) == 1
    np.testing.assert_allclose(res.predicted_means[0], [q_pred, 0.0], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res.predicted_covariances[0], [[P_pred, 0.0], [0.0, 0.0]], rtol=1e-8, atol=1e-14)
    # the update with decay's measurement h = 2 q, H = 2
    S = 4 * P_pred + R[0, 0]
    K = 2 * P_pred / S
    np.testing.assert_allclose(res.means[0, 0], q_pred + K * (y - 2 * q_pred), rtol=1e-9)
    np.testing.assert_allclose(res.covariances[0, 0, 0], (1 - 2 * K) * P_pred, rtol=1e-8)
