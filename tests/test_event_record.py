"""The event record stored by dtype (`_engines.event_record`): the `Solution`'s arrays read back
from it are the values written, in their places, untouched entries keep the padding, and the
scratch slot is left out."""

import jax.numpy as jnp
import numpy as np

from hybridjax._engines.event_record import empty_events, event_field, event_rows, with_scratch

NAMES = ("event_times", "states_before", "states_after", "transitions", "epoch_modes", "simultaneous", "grazing",
         "inside_guard")


def solution_arrays(real, index, flag, first_modes):
    """Every event array of the `Solution`, as it reads them (`event_field`)."""
    return {name: event_field(name, real, index, flag, first_modes) for name in NAMES}


def test_events_written_by_rows_read_back_as_the_solution_arrays():
    E, n = 4, 3
    rng = np.random.default_rng(0)
    t = rng.uniform(size=2)
    before, after = rng.normal(size=(2, n)), rng.normal(size=(2, n))
    k, target = np.array([1, 0]), np.array([2, 5])
    sim, graz, inside = np.array([True, False]), np.array([False, True]), np.array([True, True])
    real, index, flag = empty_events((E + 1,), n, jnp.float64)  # E events and the scratch slot
    rows = np.array([0, 2])  # events 0 and 2 written, 1 and 3 left empty
    values = event_rows(t, before, after, k, target, sim, graz, inside, jnp.float64)
    real, index, flag = (a.at[rows].set(v) for a, v in zip((real, index, flag), values, strict=True))
    real, index, flag = (a.at[E].set(v[0]) for a, v in zip((real, index, flag), values, strict=True))  # scratch
    out = solution_arrays(real, index, flag, jnp.int32(7))

    np.testing.assert_array_equal(out["event_times"][rows], t)
    np.testing.assert_array_equal(out["states_before"][rows], before)
    np.testing.assert_array_equal(out["states_after"][rows], after)
    np.testing.assert_array_equal(out["transitions"][rows], k)
    # epoch i + 1 starts after event i; epoch 0 in the initial mode
    np.testing.assert_array_equal(out["epoch_modes"], [7, 2, -1, 5, -1])
    np.testing.assert_array_equal(out["simultaneous"][rows], sim)
    np.testing.assert_array_equal(out["grazing"][rows], graz)
    np.testing.assert_array_equal(out["inside_guard"][rows], inside)
    empty = np.array([1, 3])
    assert np.all(np.isinf(out["event_times"][empty])) and np.all(np.isinf(out["states_after"][empty]))
    assert np.all(out["transitions"][empty] == -1) and not np.any(out["grazing"][empty])
    assert out["states_before"].shape == (E, n) and out["epoch_modes"].shape == (E + 1,)


def test_a_record_of_executions_and_of_no_events_keeps_the_solution_shapes():
    N, n = 3, 2
    real, index, flag = with_scratch(*empty_events((N, 0), n, jnp.float32))
    assert real.shape == (N, 1, 1 + 2 * n) and np.all(np.isinf(real))
    out = solution_arrays(real, index, flag, jnp.arange(N, dtype=jnp.int32))
    assert out["event_times"].shape == (N, 0) and out["event_times"].dtype == jnp.float32
    assert out["states_before"].shape == (N, 0, n)
    np.testing.assert_array_equal(out["epoch_modes"], [[0], [1], [2]])
