"""Derivatives of `hj.periodic_orbit` with respect to the system's parameters, against closed
forms: McGeer's rimless wheel (g / l = 1) has the gait omega*^2 = 4 c^2 sin(alpha) sin(gamma) /
(1 - c^2) just after heel strike at theta = gamma - alpha, c = cos(2 alpha), and the return-map
multiplier c^2, independent of the slope gamma."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj

WHEEL = hj.examples.rimless_wheel()
ALPHA, GAMMA = 0.3, 0.08
GUESS = jnp.asarray(hj.examples.rimless_wheel_closed_form(ALPHA, GAMMA)["state"] * np.array([1.0, 1.2]))


def orbit_outputs(p):
    """(the nontrivial multiplier from the monodromy matrix, the one from DP, the gait's state)
    for p = (alpha, gamma)."""
    orbit = hj.periodic_orbit(WHEEL, 0, GUESS, {"alpha": p[0], "gamma": p[1]}, max_epochs=4, t_max=20.0)
    # DP's eigenvalues are 0 (along the flow) and the multiplier: the multiplier is its trace.
    return jnp.concatenate([orbit.multipliers_ad[1:2].real, jnp.trace(orbit.poincare_jacobian)[None], orbit.state])


def closed_outputs(p):
    alpha, gamma = p
    c = jnp.cos(2 * alpha)
    w = jnp.sqrt(4 * c * c * jnp.sin(alpha) * jnp.sin(gamma) / (1 - c * c))
    return jnp.stack([c * c, c * c, gamma - alpha, w])


# One compiled program for the values and the Jacobian (reverse mode through the orbit).
VALUE_AND_JACOBIAN = jax.jit(lambda p: (orbit_outputs(p), jax.jacrev(orbit_outputs)(p)))


def test_multiplier_and_gait_derivatives_of_the_rimless_wheel():
    p = jnp.array([ALPHA, GAMMA])
    value, J = map(np.asarray, VALUE_AND_JACOBIAN(p))
    np.testing.assert_allclose(value, closed_outputs(p), rtol=0, atol=1e-9)
    exact = np.asarray(jax.jacfwd(closed_outputs)(p))
    # d(multiplier)/d(alpha) = -2 sin(4 alpha); d(multiplier)/d(gamma) = 0
    np.testing.assert_allclose(exact[0], [-2 * np.sin(4 * ALPHA), 0.0], atol=1e-15)
    np.testing.assert_allclose(J, exact, rtol=0, atol=1e-7)


@pytest.mark.costly  # the orbit's forward mode; its reverse mode: the test above
def test_forward_mode_through_the_orbit():
    p = jnp.array([ALPHA, GAMMA])
    J = np.asarray(jax.jit(jax.jacfwd(orbit_outputs))(p))
    np.testing.assert_allclose(J, np.asarray(jax.jacfwd(closed_outputs)(p)), rtol=0, atol=1e-7)


def test_spoke_angle_for_a_target_multiplier_by_gradient_descent():
    # Minimise (m(alpha) - m_target)^2 over alpha on a fixed slope: the closed form's optimum is
    # alpha* = arccos(sqrt(m_target)) / 2. Newton-free: plain gradient steps, the gradient of
    # the multiplier through periodic_orbit.
    target = 0.5
    alpha_star = 0.5 * np.arccos(np.sqrt(target))
    alpha = ALPHA
    losses = []
    for _ in range(6):
        value, J = VALUE_AND_JACOBIAN(jnp.array([alpha, GAMMA]))
        m, dm = float(value[0]), float(J[0, 0])
        losses.append((m - target) ** 2)
        alpha -= 0.12 * 2 * (m - target) * dm
    np.testing.assert_allclose(alpha, alpha_star, atol=1e-6)
    assert losses[-1] < 1e-10 * losses[0]
