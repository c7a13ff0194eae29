"""`Solution.inside_guard`: events fired at the start of an epoch because a reset put the state
strictly inside a guard, in both engines, on the ceiling ball (a plastic impact whose reset
lands inside the lift-off guard: lambda = -g < 0), against its closed-form impact time."""

import jax
import jax.numpy as jnp
import numpy as np

import hybridjax as hj
from hybridjax import examples

from helpers import CEILING, TIGHT

ARGS = {"g": 9.8, "H": 2.0}
X0 = jnp.array([0.0, 7.0])
_run = jax.jit(lambda x0: hj.simulate(CEILING, x0, "flight", 0.0, 1.0, ARGS, stepsize_controller=TIGHT))
_run_batch = jax.jit(lambda x0: hj.simulate_batch(CEILING, x0, "flight", 0.0, 1.0, ARGS,
                                                  stepsize_controller=TIGHT))


def _check(times, transitions, inside, num_events):
    ref = examples.ceiling_ball_closed_form(0.0, 7.0, ARGS, 1.0)
    assert int(num_events) == 2
    names = [CEILING.transitions[int(k)].name for k in np.asarray(transitions)[:2]]
    assert names == ["impact", "lift-off"]
    np.testing.assert_allclose(np.asarray(times)[:2], ref["event_time"], rtol=1e-9)
    # The impact is a crossing; the lift-off fires at once, from strictly inside its guard.
    assert np.asarray(inside)[:2].tolist() == [False, True]
    assert not np.any(np.asarray(inside)[2:])


def test_a_reset_into_a_guard_is_flagged_per_event():
    sol = _run(X0)
    _check(sol.event_times, sol.transitions, sol.inside_guard, sol.num_events)
    assert "inside_guard=1 events" in repr(sol)
    # The repr names the final state's components (the mode's `names`, x[i] by default).
    z, v = examples.ceiling_ball_closed_form(0.0, 7.0, ARGS, 1.0)["final_state"]
    assert f"final_state=(x[0]={z:.6g}, x[1]={v:.6g})" in repr(sol)
    assert "inside guard" in sol._repr_html_()


def test_the_batched_engine_flags_it_too_and_the_repr_counts_executions():
    sol = _run_batch(jnp.stack([X0, jnp.array([0.0, 1.0])]))  # the second never reaches the ceiling
    _check(sol.event_times[0], sol.transitions[0], sol.inside_guard[0], sol.num_events[0])
    assert int(sol.num_events[1]) == 0 and not np.any(np.asarray(sol.inside_guard[1]))
    assert "1 with events fired from inside a guard" in repr(sol)


def test_plots_mark_events_fired_inside_a_guard():
    import matplotlib

    matplotlib.use("Agg")
    import hybridjax.plot as hjp

    ax = hjp.trajectory(_run(X0), 0)
    assert "1 fired inside a guard" in ax.get_title()
    assert "fired" not in hjp.trajectory(_run(jnp.array([0.0, 1.0])), 0).get_title()
