"""`ZenoOptions`: the four Zeno settings in one object, the keywords still accepted."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj
from hybridjax import examples

from helpers import BALL, TIGHT

E = 1 / math.sqrt(2)
ARGS = {"g": 9.8, "e": E}
X0 = jnp.array([1.0, 0.0])


def _run(**kw):
    return hj.simulate(BALL, X0, "flight", 0.0, 5.0, ARGS, stepsize_controller=TIGHT, **kw)


def test_options_object_and_keywords_detect_the_same_zeno_time():
    t_inf = examples.zeno_time(1.0, 9.8, E)  # sqrt(2 h0 / g) (1 + e) / (1 - e)
    by_object = _run(zeno=hj.ZenoOptions(window=4, ratio_tol=0.01, max_ratio=0.9))
    by_keywords = _run(zeno_window=4, zeno_ratio_tol=0.01, zeno_max_ratio=0.9)
    for sol in (by_object, by_keywords):
        assert sol.status == hj.Status.ZENO
        np.testing.assert_allclose(sol.zeno_time, t_inf, atol=1e-6)
    # the same settings: the same events
    assert int(by_object.num_events) == int(by_keywords.num_events)
    # a wider window needs more events before it decides (window + 2 event times)
    assert int(by_object.num_events) > int(_run(zeno=hj.ZenoOptions(window=2)).num_events)


def test_zeno_options_in_simulate_batch_and_off():
    sols = hj.simulate_batch(
        BALL,
        jnp.stack([X0, X0]),
        "flight",
        0.0,
        5.0,
        ARGS,
        stepsize_controller=TIGHT,
        zeno=hj.ZenoOptions(window=4, ratio_tol=0.01, max_ratio=0.9),
    )
    np.testing.assert_allclose(sols.zeno_time, examples.zeno_time(1.0, 9.8, E), atol=1e-6)
    assert _run(zeno=False, max_epochs=8).status == hj.Status.MAX_EPOCHS


def test_bad_zeno_options():
    with pytest.raises(ValueError, match="window must be an int >= 1"):
        hj.ZenoOptions(window=0)
    with pytest.raises(ValueError, match="max_ratio must be in"):
        hj.ZenoOptions(max_ratio=1.0)
    with pytest.raises(ValueError, match="ratio_tol must be >= 0"):
        hj.ZenoOptions(ratio_tol=-0.1)
    with pytest.raises(ValueError, match="not beside it"):
        _run(zeno=hj.ZenoOptions(), zeno_window=5)
