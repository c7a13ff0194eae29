"""`Kernels.guard_jets`: the watched functions' Lie derivatives along the flow, against a hand
derivation."""

import jax.numpy as jnp
import numpy as np

import hybridjax as hj
from hybridjax._definition.kernels import Kernels


def test_lie_derivatives_by_hand():
    # Flow x0' = x1, x1' = -x0 and the time-varying guard g = x0^2 + t x1. By hand, along the flow:
    # L1 = 2 x0 x1 + x1 - t x0,
    # L2 = 2 x1^2 - 2 x0^2 - 2 x0 - t x1,
    # L3 = -8 x0 x1 - 3 x1 + t x0.
    system = hj.HybridSystem(
        [hj.Mode("m", lambda t, x, args: jnp.stack([x[1], -x[0]]), dim=2)],
        [hj.Transition("m", "m", guard=lambda t, x, args: x[0] ** 2 + t * x[1])],
    )
    kern = Kernels(system, None, jnp.float64)
    t, (x0, x1) = 0.7, (0.3, -1.1)
    jets = kern.guard_jets(jnp.asarray(0), jnp.asarray(t), jnp.asarray([x0, x1]), None, 0.0, 0.0, 0.0)
    hand = [
        x0**2 + t * x1,
        2 * x0 * x1 + x1 - t * x0,
        2 * x1**2 - 2 * x0**2 - 2 * x0 - t * x1,
        -8 * x0 * x1 - 3 * x1 + t * x0,
    ]
    got = [float(v[0]) for v in (jets.L0, jets.L1, jets.L2, jets.L3)]
    np.testing.assert_allclose(got, hand, rtol=1e-14, atol=1e-14)
