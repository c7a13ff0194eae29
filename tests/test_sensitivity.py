"""Global sensitivity of the bouncing ball's first impact time and bounce count: Sobol' indices
against closed forms and quadrature, Morris effects and DGSM against closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import qmc

import hybridjax as hj
from hybridjax._analysis.sensitivity import saltelli_estimates

E, T = 0.8, 1.5
BOUNDS = np.array([[0.5, 1.5], [5.0, 15.0]])  # h0, g
CHUNK = 4096
OPTIONS = hj.SensitivityOptions(chunk_size=CHUNK, confidence=0.99, n_bootstrap=300, seed=3)


def _inputs(theta):
    return jnp.stack([theta[0], jnp.zeros_like(theta[0])]), {"g": theta[1], "e": E}


def _outputs(sol):
    """(first impact time, number of impacts before T)."""
    return jnp.stack([sol.event_times[:, 0], sol.num_events.astype(sol.event_times.dtype)], axis=1)


MODEL = hj.execution_model(hj.examples.bouncing_ball(), _inputs, _outputs, t1=T)


def _closed_form(h, g):
    """t1 = sqrt(2 h / g); impact k at t1 (1 + 2 e (1 - e^(k-1)) / (1 - e)); count those <= T."""
    t1 = np.sqrt(2 * h / g)
    return t1, sum((t1 * (1 + 2 * E * (1 - E ** (k - 1)) / (1 - E)) <= T).astype(float) for k in range(1, 40))


def _t1_indices():
    """t1 = sqrt(2) u(h) w(g), u = h^(1/2), w = g^(-1/2) independent: V = 2 (E u^2 E w^2 -
    (E u E w)^2), V_h = 2 Var(u) (E w)^2, V_g = 2 Var(w) (E u)^2; S_Th = 1 - V_g / V."""
    (a, b), (c, d) = BOUNDS
    Eu, Eu2 = (2 / 3) * (b**1.5 - a**1.5) / (b - a), (a + b) / 2
    Ew, Ew2 = 2 * (d**0.5 - c**0.5) / (d - c), np.log(d / c) / (d - c)
    V = 2 * (Eu2 * Ew2 - (Eu * Ew) ** 2)
    Vh, Vg = 2 * (Eu2 - Eu**2) * Ew**2, 2 * (Ew2 - Ew**2) * Eu**2
    return np.array([Vh / V, Vg / V]), np.array([1 - Vg / V, 1 - Vh / V])


def _count_indices(grid=2000):
    """Midpoint quadrature on a grid x grid of the box: V_h = Var_h(E[N | h]), and so on."""
    h = BOUNDS[0, 0] + (np.arange(grid) + 0.5) / grid * (BOUNDS[0, 1] - BOUNDS[0, 0])
    g = BOUNDS[1, 0] + (np.arange(grid) + 0.5) / grid * (BOUNDS[1, 1] - BOUNDS[1, 0])
    _, N = _closed_form(h[:, None], g[None, :])
    V = N.var()
    Vh, Vg = N.mean(axis=1).var(), N.mean(axis=0).var()
    return np.array([Vh / V, Vg / V]), np.array([1 - Vg / V, 1 - Vh / V])


def test_sobol_indices_of_the_impact_time_and_the_bounce_count():
    res = hj.sobol_indices(MODEL, BOUNDS, 2**13, names=("h0", "g"), options=OPTIONS)
    assert res.evaluations == 4 * 2**13
    for j, (S_ref, ST_ref) in enumerate([_t1_indices(), _count_indices()]):
        lo, hi = res.first_order_interval[j].T
        assert np.all((lo <= S_ref) & (S_ref <= hi)), (j, res.first_order[j], S_ref, lo, hi)
        lo, hi = res.total_interval[j].T
        assert np.all((lo <= ST_ref) & (ST_ref <= hi)), (j, res.total[j], ST_ref, lo, hi)
        # the intervals are informative: a few hundredths wide at most
        assert np.all(res.total_interval[j, :, 1] - res.total_interval[j, :, 0] < 0.06)
    # h0 and g enter t1 only through h0 / g: a product, whose interaction is small but not zero
    assert np.all(res.total[0] > res.first_order[0])


def test_saltelli_estimators_on_an_additive_function_in_numpy():
    # f = theta_0 + 2 theta_1 on [0, 1]^2: S = (1/5, 4/5), no interaction, so S_T = S
    rng = np.random.default_rng(0)
    A, B = rng.random((200_000, 2)), rng.random((200_000, 2))
    f = lambda x: (x[:, 0] + 2 * x[:, 1])[:, None]  # noqa: E731
    AB = np.stack([np.where(np.arange(2) == i, B, A) for i in range(2)])
    S, ST = saltelli_estimates(f(A), f(B), np.stack([f(x) for x in AB]))
    np.testing.assert_allclose(S[0], [0.2, 0.8], atol=5e-3)
    np.testing.assert_allclose(ST[0], [0.2, 0.8], atol=5e-3)


def test_morris_effects_equal_the_closed_form_on_the_same_trajectories():
    res = hj.morris_effects(MODEL, BOUNDS, 200, options=OPTIONS)
    r, d = 200, 2
    f = np.stack(_closed_form(res.points[..., 0], res.points[..., 1]), axis=-1)  # (r, d + 1, k)
    u = (res.points - BOUNDS[:, 0]) / (BOUNDS[:, 1] - BOUNDS[:, 0])
    ee = np.zeros((r, 2, d))
    for s in range(d):
        step = u[:, s + 1] - u[:, s]  # one coordinate moves by +-delta
        j = np.argmax(np.abs(step), axis=1)
        np.testing.assert_allclose(np.abs(step[np.arange(r), j]), res.delta)
        ee[np.arange(r), :, j] = (f[:, s + 1] - f[:, s]) / step[np.arange(r), j][:, None]
    np.testing.assert_allclose(res.elementary_effects, ee, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(res.mu_star, np.abs(ee).mean(0), rtol=1e-7)
    np.testing.assert_allclose(res.sigma, ee.std(0, ddof=1), rtol=1e-6)
    assert res.mu_star[0, 1] > res.mu_star[0, 0] > 0  # g's range moves t1 more than h0's


def test_dgsm_from_exact_gradients_against_the_closed_form():
    n = 1024
    res = hj.dgsm(MODEL, BOUNDS, n, options=OPTIONS)
    theta = hj.sample(BOUNDS, n, "sobol", OPTIONS.seed)
    h, g = theta[:, 0], theta[:, 1]
    # d t1 / d h = 1 / sqrt(2 h g), d t1 / d g = -t1 / (2 g)
    t1 = np.sqrt(2 * h / g)
    np.testing.assert_allclose(res.gradients[:, 0, 0], 1 / np.sqrt(2 * h * g), rtol=1e-6)
    np.testing.assert_allclose(res.gradients[:, 0, 1], -t1 / (2 * g), rtol=1e-6)
    assert np.all(res.gradients[:, 1] == 0)  # the bounce count: zero derivative a.e.
    # E[(dt1/dh)^2] = E[1/h] E[1/g] / 2; E[(dt1/dg)^2] = E[h] E[g^-3] / 2
    (a, b), (c, d) = BOUNDS
    Eih, Eig = np.log(b / a) / (b - a), np.log(d / c) / (d - c)
    Eg3 = (c**-2 - d**-2) / (2 * (d - c))
    nu_ref = np.array([Eih * Eig / 2, (a + b) / 2 * Eg3 / 2])
    np.testing.assert_allclose(res.nu[0], nu_ref, rtol=3e-3)  # scrambled Sobol' points, n = 1024
    # the bound on the total index holds (Sobol' and Kucherenko 2009)
    assert np.all(res.total_bound[0] >= _t1_indices()[1])


def test_options_and_bounds_are_validated():
    with pytest.raises(ValueError, match="sampler"):
        hj.SensitivityOptions(sampler="halton")
    with pytest.raises(ValueError, match="confidence"):
        hj.SensitivityOptions(confidence=1.5)
    with pytest.raises(ValueError, match="high > low"):
        hj.sample([[1.0, 0.0]], 8)
    x = hj.sample(BOUNDS, 1000, "lhs", 0)  # one point in each of the 1000 strata of each axis
    strata = np.floor((x - BOUNDS[:, 0]) / (BOUNDS[:, 1] - BOUNDS[:, 0]) * 1000)
    assert all(len(np.unique(strata[:, i])) == 1000 for i in range(2))


def test_sample_takes_num_samples_and_a_jax_random_key():
    # num_samples (n a shorthand); an int key, or the shorthand seed, is scipy's seed itself
    named = hj.sample(BOUNDS, num_samples=64, key=3)
    for other in (hj.sample(BOUNDS, n=64, seed=3), hj.sample(BOUNDS, 64, "sobol", 3)):
        np.testing.assert_array_equal(other, named)
    u = qmc.Sobol(2, scramble=True, seed=3).random_base2(6)
    np.testing.assert_allclose(named, BOUNDS[:, 0] + u * (BOUNDS[:, 1] - BOUNDS[:, 0]), rtol=1e-15)
    # A jax.random key: 64 scrambled Sobol' points, one in each 64th of each axis' range (a
    # (0, m, 2)-net); the same key (typed or legacy) gives the same points, another key others.
    key = jax.random.key(7)
    x = hj.sample(BOUNDS, num_samples=64, key=key)
    strata = np.floor((x - BOUNDS[:, 0]) / (BOUNDS[:, 1] - BOUNDS[:, 0]) * 64)
    assert x.shape == (64, 2) and all(sorted(strata[:, i]) == list(range(64)) for i in range(2))
    np.testing.assert_array_equal(hj.sample(BOUNDS, 64, key=jax.random.PRNGKey(7)), x)
    assert not np.array_equal(hj.sample(BOUNDS, 64, key=jax.random.key(8)), x)
    options = hj.SensitivityOptions(key=key)
    assert options == hj.SensitivityOptions("sobol", options.seed)
    assert hj.SensitivityOptions(seed=3) == hj.SensitivityOptions(key=3) != options
    for call, names in ((lambda: hj.sample(BOUNDS, 64, key=key, seed=3), "key and seed"),
                        (lambda: hj.sample(BOUNDS, 64, n=64), "num_samples and n"),
                        (lambda: hj.SensitivityOptions(key=key, seed=3), "key and seed"),
                        (lambda: hj.sobol_indices(MODEL, BOUNDS, 64, n=64), "num_samples and n"),
                        (lambda: hj.dgsm(MODEL, BOUNDS, 64, n=64), "num_samples and n")):
        with pytest.raises(ValueError, match=f"{names} are the same option"):
            call()
    with pytest.raises(TypeError, match="unexpected keyword argument 'num'"):
        hj.sample(BOUNDS, num=64)

