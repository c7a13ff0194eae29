"""XLA:CPU work-arounds of the batched engine, each kept for a measured reason.

None of them changes a rule: they change how a value is computed, not which. Their invariants:

- `_rows_all`, `_rows_any`: reductions over a small leading axis written out (`fold`); XLA:CPU
  runs small reductions slowly, or calls a library that does not fuse with its inputs.
- `running_count`, `first_lanes`: prefix counts by a log-depth scan; `cumsum` is lowered to a
  slow reduce-window. `first_lanes` pads with N (past the last lane): its users drop or clip
  those slots.
- `_materialize`, `_computed_once`: values computed once inside a conditional, because XLA:CPU
  recomputes a shared elementwise computation in each consumer's fusion. Where the predicate
  is False the values are zeros, so the predicate must hold wherever the values are used, and
  it must be data-dependent (a constant one is folded and the conditional inlined).
"""

import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jax import lax

from .._step.runge_kutta import fold as _fold


def _rows_all(x):
    return _fold(jnp.logical_and, x)


def _rows_any(x):
    return _fold(jnp.logical_or, x)


def running_count(mask):
    """Inclusive prefix count of `mask` (int32): `jnp.cumsum`'s value by a log-depth scan.

    XLA:CPU lowers `cumsum` to a reduce-window, which is slow on wide vectors; the scan's
    log2(N) elementwise levels are not."""
    return lax.associative_scan(jnp.add, mask.astype(jnp.int32))


def first_lanes(mask, size: int, count=None):
    """Indices of the first `size` lanes where `mask` holds, in order, padded with N:
    `jnp.nonzero(mask, size=size, fill_value=N)[0]` (two cumsums and a scatter-add there)
    as one prefix count and one scatter. `count`:
    `running_count(mask)`, where the caller has it."""
    N = mask.shape[0]
    count = running_count(mask) if count is None else count
    slot = jnp.where(mask, count - 1, size)  # size: dropped
    return jnp.full((size,), N, jnp.int32).at[slot].set(jnp.arange(N, dtype=jnp.int32), mode="drop")


def _materialize(tree, pred):
    """`tree`, computed once into buffers: XLA:CPU gives each consumer of a shared elementwise
    computation its own fusion and recomputes the shared part in each (the guard samples and
    crossing tests, ~490 operations per lane, four times over), and it removes
    `lax.optimization_barrier`; a conditional's operands are materialised. `pred` must be
    data-dependent (a constant one is folded and the conditional inlined); where it is False
    the values are zeros, so it must hold whenever they are used (here: some lane steps).
    One process, N = 10,000, the guard samples and the crossing tests: -7 to -19 % run time
    (oscillator with a guard, ball, thermostat, Van der Pol), identical results. The
    conditional copies each array into its output: where the inputs of a computation are at
    hand, `_computed_once` writes it there directly (the guard samples and the error norm now)."""
    return _computed_once(lambda x: x, tree, pred)


def _computed_once(fn, operands, pred):
    """`fn(operands)` computed inside a conditional taken where `pred` holds (zeros where not;
    `pred` as `_materialize`'s): its outputs are written once, by the fusions that compute them,
    where `_materialize` copies values computed outside (one copy per array per iteration)."""
    return lax.cond(pred, fn, lambda ops: jtu.tree_map(jnp.zeros_like, jax.eval_shape(fn, ops)), operands)
