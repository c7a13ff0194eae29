"""The per-mode table lookups of the mode-indexed evaluation (`row_by_mode`, `pick_values`,
`select_slots`) against numpy's indexing, under `jax.vmap` and with a NaN in an entry not
picked."""

import jax
import jax.numpy as jnp
import numpy as np

from hybridjax._definition.kernels import pick_values, row_by_mode, select_slots

RNG = np.random.default_rng(3)
TABLE = RNG.normal(size=(5, 7))
INDEX = np.array([[0, 3, -1], [2, 2, 4], [-1, -1, -1], [5, 1, 0], [4, -1, 3]])
OFFSET = RNG.normal(size=INDEX.shape)


def test_row_by_mode_is_the_tables_row_for_each_mode_under_vmap():
    modes = jnp.arange(5)
    got = jax.vmap(lambda m: row_by_mode(m, TABLE, jnp.float64))(modes)
    np.testing.assert_array_equal(np.asarray(got), TABLE)  # exact: zeros added to one entry
    ints = jax.vmap(lambda m: row_by_mode(m, INDEX, jnp.int32))(modes)
    np.testing.assert_array_equal(np.asarray(ints), INDEX)


def test_select_slots_reads_values_at_the_modes_indices_plus_offsets():
    values = jnp.asarray(RNG.normal(size=6))
    for m in range(INDEX.shape[0]):
        got = np.asarray(select_slots(jnp.asarray(m), values, INDEX, OFFSET, 1.0))
        want = np.where(INDEX[m] >= 0, np.asarray(values)[INDEX[m]] + OFFSET[m], 1.0)
        np.testing.assert_array_equal(got, want)


def test_a_nan_not_picked_reaches_neither_the_value_nor_the_gradient():
    values = jnp.asarray([1.5, jnp.nan, -2.0])
    index = jnp.asarray([2, 0, -1])

    def f(v):
        return jnp.sum(pick_values(v, index, 7.0) * jnp.asarray([1.0, 10.0, 100.0]))

    np.testing.assert_array_equal(np.asarray(pick_values(values, index, 7.0)), [-2.0, 1.5, 7.0])
    np.testing.assert_array_equal(np.asarray(jax.grad(f)(values)), [10.0, 0.0, 1.0])
