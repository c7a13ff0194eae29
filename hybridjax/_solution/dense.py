"""Dense output of one execution at many times: one pass over its epochs.

Each epoch's flow is integrated once from its initial state x(t_i^+) through the sorted query
times inside it, saving there (`diffrax.SaveAt(ts=...)`). The compiled program takes the mode,
the start and the times as arrays, with the times padded to a fixed length `CHUNK`; so one
program serves every epoch and every mode of a system (for a given solver, step-size controller
and dtype), and a later call with other times compiles nothing. An epoch with more than `CHUNK`
query times is integrated in consecutive segments, each starting where the previous one ended.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._definition.kernels import Kernels

CHUNK = 128
MAX_STEPS = 16384


@eqx.filter_jit
def _segment(system, solver, stepsize_controller, args, mode, t_start, x_start, ts):
    """x at `ts` (sorted, in [t_start, ts[-1]], ts[-1] > t_start) along mode `mode`'s flow."""
    kern = Kernels(system, args, x_start.dtype)
    term = diffrax.ODETerm(lambda t, y, a: kern.flow(mode, t, y, a))
    sol = diffrax.diffeqsolve(
        term, solver, t_start, ts[-1], None, x_start, args=args,
        saveat=diffrax.SaveAt(ts=ts), stepsize_controller=stepsize_controller,
        max_steps=MAX_STEPS, throw=False,
    )
    # A query at the segment's start is its initial state exactly (no interpolation).
    return jnp.where((ts == t_start)[:, None], x_start[None, :], sol.ys)


def evaluate_many(sol, t, solver, stepsize_controller):
    """(states (N, n), modes (N,)) of the single, concrete execution `sol` at the times `t` (N,)."""
    dtype = np.dtype(sol.final_time.dtype)
    t = np.asarray(t, dtype)
    n_events = int(sol.num_events)
    event_times = np.asarray(sol.event_times)[:n_events]
    states_after = np.asarray(sol.states_after)[:n_events]
    modes = np.asarray(sol.epoch_modes)[: n_events + 1]
    transitions = np.asarray(sol.transitions)[:n_events]
    t0, t_final = np.asarray(sol.t0, dtype), np.asarray(sol.final_time, dtype)
    x0 = np.asarray(sol.x0)

    # Right-continuous: epoch i holds t_i <= t < t_{i+1}; at an instant with several events,
    # the last one's epoch (as the scalar `evaluate`).
    epoch = np.minimum(np.searchsorted(event_times, t, side="right"), n_events)
    # The epoch that ends in a Zeno completion stands for infinitely many unsimulated epochs.
    tail = np.zeros(t.shape, bool)
    before_last = epoch < n_events
    tail[before_last] = transitions[epoch[before_last]] >= sol.system.num_transitions
    inside = (t >= t0) & (t <= t_final) & ~tail

    xs = np.full((t.shape[0], x0.shape[-1]), np.inf, x0.dtype)
    out_modes = np.where(inside, modes[epoch], -1).astype(np.int32)
    starts_t = np.concatenate([t0[None], event_times])
    starts_x = np.concatenate([x0[None], states_after]) if n_events else x0[None]
    order = np.argsort(t, kind="stable")
    order = order[inside[order]]
    for i in np.unique(epoch[order]):
        idx = order[epoch[order] == i]  # sorted by time
        s, x = starts_t[i], starts_x[i]
        at_start = t[idx] == s
        xs[idx[at_start]] = x
        idx = idx[~at_start]
        for k in range(0, idx.shape[0], CHUNK):
            part = idx[k : k + CHUNK]
            ts = np.full(CHUNK, t[part[-1]], dtype)
            ts[: part.shape[0]] = t[part]
            ys = np.asarray(_segment(sol.system, solver, stepsize_controller, sol.args,
                                     np.asarray(modes[i], np.int32), np.asarray(s, dtype),
                                     np.asarray(x), ts))
            xs[part] = ys[: part.shape[0]]
            # The next segment continues from this one's last time (a saved time, never before it).
            s, x = t[part[-1]], ys[part.shape[0] - 1]
    # device_put, not jnp.asarray, which compiles a small conversion program per shape.
    return jax.device_put(xs), jax.device_put(out_modes)


def is_concrete(*trees) -> bool:
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(trees))
