"""`simulate_batch(devices=...)`: executions split over several devices.

The test process has one CPU device (JAX's default), so the split itself runs in a subprocess
started with `jax_num_cpu_devices = 2`, its results checked there against closed forms and
finite differences and printed as JSON.
"""

import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hybridjax as hj

from helpers import BALL, BALL_ARGS

SPLIT_SCRIPT = r"""
import json, jax
jax.config.update("jax_num_cpu_devices", 2)
jax.config.update("jax_enable_x64", True)
import diffrax, jax.numpy as jnp, numpy as np
import hybridjax as hj
from hybridjax import examples

out = {"devices": len(jax.devices())}
ball, ctrl = examples.bouncing_ball(), diffrax.PIDController(rtol=1e-10, atol=1e-10)
rng = np.random.default_rng(1)
x0 = np.stack([rng.uniform(0.5, 1.5, 9), rng.uniform(-1, 1, 9)], 1)  # 9: the last device padded


def run_ball(x, e, devices, adjoint=diffrax.RecursiveCheckpointAdjoint()):
    return hj.simulate_batch(ball, x, "flight", 0.0, 2.5, {"g": 9.8, "e": e}, stepsize_controller=ctrl,
                             max_epochs=32, devices=devices, adjoint=adjoint)


ref = [examples.bouncing_ball_closed_form(h, v, 9.8, 0.8, 2.5) for h, v in x0]
runs = {d: jax.jit(lambda x, d=d: run_ball(x, 0.8, d))(jnp.asarray(x0)) for d in (None, 1)}
split, one = runs[None], runs[1]
out["final_error"] = float(np.max(np.abs(np.asarray(split.final_state) - np.array([r["final_state"] for r in ref]))))
out["event_error"] = max(float(np.max(np.abs(np.asarray(split.event_times[i, :len(r["event_times"])])
                                             - np.array(r["event_times"])))) for i, r in enumerate(ref))
out["wrong_counts"] = int(np.sum(np.asarray(split.num_events) != np.array([len(r["event_times"]) for r in ref])))
out["shapes_equal"] = all(np.shape(a) == np.shape(b) for a, b in zip(jax.tree_util.tree_leaves(split),
                                                                     jax.tree_util.tree_leaves(one)))
out["split_vs_one"] = float(np.max(np.abs(np.asarray(split.final_state) - np.asarray(one.final_state))))
out["steps_equal"] = bool(np.array_equal(split.num_steps, one.num_steps))

# Forward mode on two devices: d final state / d e against central differences of the closed form.
jac = jax.jit(jax.jacfwd(lambda e: run_ball(jnp.asarray(x0), e, None, diffrax.ForwardMode()).final_state))(0.8)
h = 1e-6
fd = (np.array([examples.bouncing_ball_closed_form(a, b, 9.8, 0.8 + h, 2.5)["final_state"] for a, b in x0])
      - np.array([examples.bouncing_ball_closed_form(a, b, 9.8, 0.8 - h, 2.5)["final_state"] for a, b in x0])) / (2 * h)
out["jacfwd_error"] = float(np.max(np.abs(np.asarray(jac) - fd)))

# Reverse mode (run on one device): d sum(final heights) / d e against the same differences.
grad = jax.jit(jax.grad(lambda e: jnp.sum(run_ball(jnp.asarray(x0), e, None).final_state[:, 0])))(0.8)
out["grad_error"] = float(abs(float(grad) - fd[:, 0].sum()))

# Per-execution args and save times, outside jit (the split is compiled on its own); 2 lanes
# per device for 3 executions each (5 padded to 6): lanes take the next execution as theirs ends.
thermo, p = examples.thermostat(), dict(a=0.1, P_heat=2.5, P_cool=2.0, s=20.0)
T0, amb = np.linspace(15.0, 25.0, 5), np.linspace(5.0, 35.0, 5)
args = {**{k: jnp.full((5,), v) for k, v in p.items()}, "T_amb": jnp.asarray(amb)}
sol = hj.simulate_batch(thermo, jnp.asarray(T0)[:, None], "off", 0.0, 60.0, args, args_batched=True,
                        stepsize_controller=ctrl, saveat=jnp.linspace(0.0, 60.0, 7), lanes=4)
cf = [examples.thermostat_closed_form(T, "off", {**p, "T_amb": a}, 60.0) for T, a in zip(T0, amb)]
out["thermo_error"] = float(np.max(np.abs(np.asarray(sol.final_state[:, 0]) - np.array([c["final_state"][0] for c in cf]))))
out["thermo_wrong_counts"] = int(np.sum(np.asarray(sol.num_events) != np.array([len(c["event_times"]) for c in cf])))
out["thermo_saved_last"] = float(np.max(np.abs(np.asarray(sol.ys[:, -1, 0]) - np.asarray(sol.final_state[:, 0]))))
print("RESULT" + json.dumps(out))
"""


@pytest.fixture(scope="module")
def split_results():
    # The environment is inherited, with it the suite's compile settings (`XLA_FLAGS`, conftest.py).
    proc = subprocess.run([sys.executable, "-c", SPLIT_SCRIPT], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT")][-1]
    return json.loads(line[len("RESULT"):])


def test_split_over_two_devices_matches_closed_form(split_results):
    r = split_results
    assert r["devices"] == 2
    assert r["final_error"] < 1e-9 and r["event_error"] < 1e-9
    assert r["wrong_counts"] == 0
    # The same executions on one device: the same steps, results within the tolerance (the
    # halves round differently in places: 2e-11 seen, with the test suite's compile flags).
    assert r["shapes_equal"] and r["steps_equal"]
    assert r["split_vs_one"] < 1e-9


def test_split_with_batched_args_saves_and_refill(split_results):
    assert split_results["thermo_error"] < 1e-7
    assert split_results["thermo_wrong_counts"] == 0
    assert split_results["thermo_saved_last"] < 1e-7  # the last save time is t1


def test_derivatives_with_several_devices(split_results):
    assert split_results["jacfwd_error"] < 1e-5
    assert split_results["grad_error"] < 1e-5


@pytest.mark.parametrize("devices", [0, 2, -1, "cpu", [], True])
def test_devices_argument_is_checked(devices):
    x0 = jnp.array([[1.0, 0.0], [1.2, 0.0]])
    with pytest.raises(ValueError, match="devices"):
        hj.simulate_batch(BALL, x0, "flight", 0.0, 1.0, BALL_ARGS, devices=devices)


def test_one_device_given_as_a_list():
    x0 = jnp.array([[1.0, 0.0], [1.2, 0.0]])
    sol = hj.simulate_batch(BALL, x0, "flight", 0.0, 0.3, BALL_ARGS, devices=jax.devices()[:1])
    # Free fall, no bounce before t = 0.3: h = h0 - g t^2 / 2.
    np.testing.assert_allclose(np.asarray(sol.final_state[:, 0]), [1.0 - 4.9 * 0.09, 1.2 - 4.9 * 0.09], atol=1e-9)
