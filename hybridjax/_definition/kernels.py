"""A system's user functions, evaluated on the padded state with the mode chosen at run time.

The solver carries one state of length n = max_I n_I. Mode I's functions see its first n_I
components; their outputs are padded back with zeros. The current mode is a traced integer,
so under `jax.vmap` every mode's branch is evaluated and one is selected. An inactive branch
may see a state of another mode, on which a user function can return NaN or inf; its inputs
are therefore passed through `stop_gradient` (the "double where" idiom), so that a NaN in a
branch that was not taken never reaches a gradient. A system that implements `ModeIndexed`
(`HybridSystem.mode_indexed`) is instead evaluated once per call for the traced mode
(`Kernels.indexed`).
"""

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax import lax

from .._definition.system import HybridSystem
from .._definition.validation import domain_sizes


def mask_inputs(active, tree):
    """`tree` with gradients cut where `active` is False (values unchanged)."""

    def mask(a):
        if isinstance(a, jax.Array) and jnp.issubdtype(a.dtype, jnp.inexact):
            return jnp.where(active, a, lax.stop_gradient(a))
        return a

    return jtu.tree_map(mask, tree)


def _pad(v: jax.Array, n: int) -> jax.Array:
    v = jnp.asarray(v)
    return v if v.shape[0] == n else jnp.concatenate([v, jnp.zeros((n - v.shape[0],), v.dtype)])


def select_by_mode(mode, rows, size: int, fill, dtype) -> jax.Array:
    """(size,): entry s is `rows[mode][s]`, `fill` where `mode`'s row is shorter; `rows[m]` the
    scalars of mode m. Selected elementwise by `mode` (under `jax.vmap`, selects that fuse; a
    gather by a traced index is slow on XLA:CPU)."""
    out = []
    for s in range(size):
        v = jnp.full((), fill, dtype)
        for m, row in enumerate(rows):
            if s < len(row):
                v = jnp.where(mode == m, row[s], v)
        out.append(v)
    return jnp.stack(out) if out else jnp.zeros((0,), dtype)


def row_by_mode(mode, table, dtype) -> jax.Array:
    """Row `mode` of the constant (modes, m) `table`: $\sum_I [I = \text{mode}]\,T_I$ as one
    select over the table and one sum, whatever the number of modes (a chain of one select per
    mode would grow a scene's program with its modes). No gather by a traced index (slow on
    XLA:CPU under `jax.vmap`); exact, the sum adding zeros to one entry."""
    table = jnp.asarray(table, dtype)
    if table.shape[0] == 1:
        return table[0]
    hit = (mode == jnp.arange(table.shape[0]))[:, None]
    return jnp.sum(jnp.where(hit, table, jnp.zeros((), dtype)), axis=0)


def pick_values(values, index, fill) -> jax.Array:
    """(S,): entry s is `values[index[s]]`, `fill` where `index[s] < 0`; `values` (V,) traced,
    `index` (S,) an integer array (traced or constant). One select of the (S, V) one-hot pattern
    and one sum: a NaN or inf in an entry not picked does not reach the result or its gradient."""
    V = values.shape[0]
    if index.shape[0] == 0 or V == 0:
        return jnp.full(index.shape, fill, values.dtype)
    hit = jnp.asarray(index)[:, None] == jnp.arange(V)[None, :]
    picked = jnp.sum(jnp.where(hit, values[None, :], jnp.zeros((), values.dtype)), axis=1)
    return jnp.where(jnp.asarray(index) >= 0, picked, jnp.asarray(fill, values.dtype))


def select_slots(mode, values, index, offset, fill) -> jax.Array:
    """(S,): slot s of `mode` is `values[index[mode, s]] + offset[mode, s]`, `fill` where
    `index[mode, s] < 0` (an unused slot); `index`, `offset` constant (modes, S) tables. The
    program has a fixed number of operations, not one per mode and slot."""
    index = np.asarray(index, dtype=np.int64).reshape(len(index), -1)
    if index.shape[1] == 0:
        return jnp.zeros((0,), values.dtype)
    idx = row_by_mode(mode, index, jnp.int32)
    off = row_by_mode(mode, np.asarray(offset, dtype=float).reshape(index.shape), values.dtype)
    picked = pick_values(values, idx, fill)
    return jnp.where(idx >= 0, picked + off, picked)


def dispatch(index, branches: list[Callable], *operands):
    """`lax.switch(index, branches, *operands)` with inactive branches' gradients cut."""
    if len(branches) == 1:
        return branches[0](*operands)

    def wrap(i, fn):
        def branch(index, *ops):
            return fn(*mask_inputs(index == i, ops))

        return branch

    return lax.switch(index, [wrap(i, f) for i, f in enumerate(branches)], index, *operands)


class GuardJets(NamedTuple):
    """Lie derivatives of the watched functions at one point, and their tolerance band
    (`Kernels.guard_jets`); each field (K + W,)."""

    L0: jax.Array
    L1: jax.Array
    L2: jax.Array
    L3: jax.Array
    band: jax.Array
    scale1: jax.Array


class Kernels:
    """Padded, mode-dispatched flows, resets and *watched functions* of a system.

    The watched functions are, in priority order, the K guards g_k (a transition fires when
    one reaches <= 0) and then the W domain components a_Ij of every mode (the execution is
    blocked when one of the current mode's reaches <= 0 before any guard does).
    """

    def __init__(self, system: HybridSystem, args=None, dtype=None, located: bool = False):
        self.system = system
        # The engines' view of a `ModeIndexed` system (`located=True`): guards that share one
        # function are watched through it alone and the transition taken is chosen at the event
        # (`ModeIndexed.locate_watch`, `select`). Tools that ask where each guard holds (the
        # property checks) keep every guard as it is (`watch`).
        self.located = located
        self.n = system.max_dim
        self.num_transitions = system.num_transitions
        self.sources = jnp.asarray(system.sources, dtype=jnp.int32)
        self.targets = jnp.asarray(system.targets, dtype=jnp.int32)
        self.completion_targets = jnp.asarray(system.completion_targets, dtype=jnp.int32)
        comp = [system.completion_of(i) for i in range(system.num_modes)]
        self.completion_of_mode = jnp.asarray(comp, dtype=jnp.int32)
        watch: list[tuple[int, Callable]] = [
            (system.sources[k], self._guard_fn(k)) for k in range(self.num_transitions)
        ]
        if any(m.domain is not None for m in system.modes):
            sizes = domain_sizes(system, args, jnp.result_type(float) if dtype is None else dtype)
            for i, m_i in enumerate(sizes):
                for j in range(m_i):
                    watch.append((i, self._domain_fn(i, j)))
        self.watch = watch
        self.num_watch = len(watch)
        self.watch_sources = jnp.asarray([w[0] for w in watch], dtype=jnp.int32)
        # Slot s of mode m: its s-th own watched function (`to_slots`).
        self.mode_watch = [[w for w, (src, _) in enumerate(watch) if src == m]
                           for m in range(system.num_modes)]
        self.num_slots = max(map(len, self.mode_watch), default=0)
        # (modes, slots): the watched function in each mode's slot (0 where the slot is unused), a
        # NumPy table: read under a traced mode through `row_by_mode` or `jnp.asarray`.
        slot_watch = np.asarray([[own[s] if s < len(own) else 0 for s in range(self.num_slots)]
                                 for own in self.mode_watch], dtype=np.int32)
        self.slot_watch = slot_watch.reshape(system.num_modes, self.num_slots)
        # Each watched function's slot in its own mode (`from_slots`).
        self.watch_slot = [self.mode_watch[src].index(w) for w, (src, _) in enumerate(watch)]
        # One evaluation for the traced mode, where the system has it (`ModeIndexed`).
        self.indexed = system.mode_indexed()

    def _indexed_watch(self, mode, t, y, args) -> jax.Array:
        """The `ModeIndexed` watched values of `mode`, in slot order (`located`: `locate_watch`)."""
        fn = self.indexed.locate_watch if self.located else self.indexed.watch
        return fn(mode, t, y, args).astype(y.dtype)

    def select(self, mode, k, t, y, args) -> jax.Array:
        """The transition taken at an event of watched function `k` located at (t, y):
        `ModeIndexed.select` where the engines locate on shared guards (`located`), else `k`.
        A discrete choice: no gradient flows through it."""
        if self.indexed is None or not self.located or self.num_transitions == 0:
            return k
        t, y, args = lax.stop_gradient((t, y, args))
        watch_slot = np.asarray(self.watch_slot, np.int32)
        slot = pick_values(jnp.asarray(watch_slot), jnp.clip(k, 0, self.num_watch - 1)[None], 0)[0]
        chosen = self.indexed.select(mode, slot, t, y, args)
        k_new = pick_values(row_by_mode(mode, self.slot_watch, jnp.int32), chosen[None], 0)[0]
        return jnp.where(k < self.num_transitions, k_new, k).astype(jnp.asarray(k).dtype)

    # ---------------------------------------------------------------- per-mode pieces
    def mode_flow(self, i: int) -> Callable:
        mode, n = self.system.modes[i], self.n
        return lambda t, y, args: _pad(mode.flow(t, y[: mode.dim], args), n)

    def flow(self, mode, t, y, args) -> jax.Array:
        """F_mode(t, y) on the padded state (zeros beyond the mode's dim)."""
        if self.indexed is not None:
            return self.indexed.flow(mode, t, y, args)
        branches = [self.mode_flow(i) for i in range(self.system.num_modes)]
        return dispatch(mode, branches, t, y, args)

    def flow_component(self, mode, t, y, args, i: int) -> jax.Array:
        """Component i of `flow`, each mode's branch cut to it before the modes' selection (under
        `jax.vmap` the selection is elementwise; selecting whole vectors and then slicing left
        XLA a lanes-first (N, n) intermediate that it transposed at every stage)."""
        if self.indexed is not None:
            return self.indexed.flow(mode, t, y, args)[i]
        branches = [lambda t, y, args, b=b: self.mode_flow(b)(t, y, args)[i]
                    for b in range(self.system.num_modes)]
        return dispatch(mode, branches, t, y, args)

    def _guard_fn(self, k: int) -> Callable:
        tr = self.system.transitions[k]
        n_src = self.system.modes[self.system.sources[k]].dim
        return lambda t, y, args: jnp.asarray(tr.guard(t, y[:n_src], args))

    def _domain_fn(self, i: int, j: int) -> Callable:
        mode = self.system.modes[i]
        return lambda t, y, args: jnp.reshape(jnp.asarray(mode.domain(t, y[: mode.dim], args)), (-1,))[j]

    def outgoing_mask(self, mode) -> jax.Array:
        """(K + W,) bool: which watched functions belong to `mode`."""
        if self.num_watch == 0:
            return jnp.zeros((0,), dtype=bool)
        return self.watch_sources == mode

    def _watched_values(self, mode, t, y, args) -> list:
        """Every watched function (guards, then domain components) at (t, y), each with its
        inputs' gradients cut where it does not belong to `mode`; a list of scalars."""
        values = []
        for src, fn in self.watch:
            tt, yy, aa = mask_inputs(mode == src, (t, y, args))
            values.append(fn(tt, yy, aa).astype(y.dtype))
        return values

    def guards(self, mode, t, y, args) -> jax.Array:
        """(K + W,) watched values (guards, then domain components) of `mode` at (t, y).

        Those not belonging to `mode` read +1 (never cross).
        """
        if self.num_watch == 0:
            return jnp.zeros((0,), dtype=y.dtype)
        if self.indexed is not None:
            return self.from_slots(mode, self._indexed_watch(mode, t, y, args), 1.0)
        g = jnp.stack(self._watched_values(mode, t, y, args))
        return jnp.where(self.outgoing_mask(mode), g, jnp.ones_like(g))

    def slot_guards(self, mode, t, y, args) -> jax.Array:
        """`to_slots(mode, guards(mode, t, y, args))`, assembled from the watched functions'
        values one by one: the (K + W,) vector is never formed, so that under `vmap` no
        (lanes, K + W) array is built, transposed and indexed (XLA:CPU did that for every guard
        sample of every step)."""
        if self.indexed is not None:
            return self._indexed_watch(mode, t, y, args)
        return self._slots(mode, self._watched_values(mode, t, y, args), 1.0, y.dtype)

    def to_slots(self, mode, values, fill=1.0) -> jax.Array:
        """(num_slots,): the watched `values` (K + W,) of `mode`'s own functions, in order, padded
        with `fill`. A mode watches only its own guards and domain components (the others read
        +1), so the engine that samples them at every step carries max_I (own of mode I) slots,
        not all K + W (Van der Pol with relay: 1 against 2, the thermostat: 4 against 8)."""
        return self._slots(mode, values, fill, values.dtype)

    def from_slots(self, mode, slots, fill) -> jax.Array:
        """(K + W,): the inverse of `to_slots`, watched function w reading its slot of `slots`
        where it belongs to `mode` and `fill` elsewhere."""
        if self.num_watch == 0:
            return jnp.zeros((0,), slots.dtype)
        mine = pick_values(slots, np.asarray(self.watch_slot), fill)
        return jnp.where(self.outgoing_mask(mode), mine, jnp.asarray(fill, slots.dtype))

    def _slots(self, mode, values, fill, dtype) -> jax.Array:
        """Slot s of `mode`: values[mode_watch[mode][s]], `fill` where `mode` has fewer;
        `values` indexable by watched function (an array or a list)."""
        rows = [[values[w] for w in own] for own in self.mode_watch]
        return select_by_mode(mode, rows, self.num_slots, fill, dtype)

    def reset(self, k, t, y, args) -> jax.Array:
        """R_k(t, y) on the padded state, transition index `k` traced."""
        if self.indexed is not None:
            return self.indexed.reset(k, t, y, args).astype(y.dtype)

        def branch(kk):
            tr = self.system.transitions[kk]
            n_src = self.system.modes[self.system.sources[kk]].dim
            return lambda t, y, args: _pad(tr.reset(t, y[:n_src], args), self.n).astype(y.dtype)

        return dispatch(k, [branch(kk) for kk in range(self.num_transitions)], t, y, args)

    def completion_reset(self, c, t, y, args) -> jax.Array:
        """The reset of ZenoCompletion `c` (traced index) on the padded state."""

        def branch(cc):
            comp = self.system.completions[cc]
            n_src = self.system.modes[self.system.completion_sources[cc]].dim
            return lambda t, y, args: _pad(comp.reset(t, y[:n_src], args), self.n).astype(y.dtype)

        return dispatch(c, [branch(cc) for cc in range(len(self.system.completions))], t, y, args)

    # ---------------------------------------------------------------- guard jets
    def guard_jets(self, mode, t, y, args, rtol, atol, tol_t) -> GuardJets:
        """Lie derivatives of every watched function along the current flow, and a tolerance band.

        L0 = g, L_{j+1} = d/dt L_j along (t, x) -> (1, F_I(t, x)), so L1 = D_t g + D_x g F_I.
        `band` = sum_i |d g/d x_i| (atol + rtol |x_i|) + scale1 tol_t: the change in g that
        the solver's tolerances and the event-time tolerance cannot resolve (a located event
        state lies up to |dg/dt| tol_t inside its guard). `scale1` = |D_t g| + sum_i |D_x g_i F_i|,
        against which L1 is judged zero (cancellation) or not.
        """
        K = self.num_watch
        if K == 0:
            z = jnp.zeros((0,), dtype=y.dtype)
            return GuardJets(z, z, z, z, z, z)
        if self.indexed is not None:
            return self._indexed_jets(mode, t, y, args, rtol, atol, tol_t)
        out: dict[str, list] = {key: [] for key in GuardJets._fields}
        for src, fn in self.watch:
            active = mode == src
            tt, yy, aa = mask_inputs(active, (t, y, args))
            g = lambda t_, y_: fn(t_, y_, aa).astype(y.dtype)  # noqa: E731
            f = lambda t_, y_: self.mode_flow(src)(t_, y_, aa)  # noqa: E731
            L0, L1, L2, L3 = lie_derivatives(g, f, tt, yy)
            gt, gx = jax.grad(g, argnums=(0, 1))(tt, yy)
            F = f(tt, yy)
            out["L0"].append(L0)
            out["L1"].append(L1)
            out["L2"].append(L2)
            out["L3"].append(L3)
            scale1 = jnp.abs(gt) + jnp.sum(jnp.abs(gx * F))
            out["band"].append(jnp.sum(jnp.abs(gx) * (atol + rtol * jnp.abs(yy))) + scale1 * tol_t)
            out["scale1"].append(scale1)
        return GuardJets(**{key: jnp.stack(v) for key, v in out.items()})

    def _indexed_jets(self, mode, t, y, args, rtol, atol, tol_t) -> GuardJets:
        """`guard_jets` of a `ModeIndexed` system: the current mode's watched values and flow in
        one evaluation each, their Lie derivatives by one nested jvp, mapped from slots to the
        watched functions (`from_slots`; those of other modes read L0 = 1, the rest 0)."""
        g = lambda t_, y_: self._indexed_watch(mode, t_, y_, args)  # noqa: E731
        f = lambda t_, y_: self.indexed.flow(mode, t_, y_, args)  # noqa: E731
        L0, L1, L2, L3 = lie_derivatives(g, f, t, y)
        gt, gx = jax.jacfwd(g, argnums=(0, 1))(t, y)  # (S,), (S, n)
        F = f(t, y)
        scale1 = jnp.abs(gt) + jnp.sum(jnp.abs(gx * F[None, :]), axis=-1)
        band = jnp.sum(jnp.abs(gx) * (atol + rtol * jnp.abs(y))[None, :], axis=-1) + scale1 * tol_t
        slots = GuardJets(L0, L1, L2, L3, band, scale1)
        return GuardJets(*(self.from_slots(mode, v, 1.0 if i == 0 else 0.0) for i, v in enumerate(slots)))


def lie_derivatives(g, f, t, y):
    """L0..L3 of `g(t, y)` along the flow (t, y) -> (1, f(t, y)): L0 = g, L_{j+1} = d/dt L_j.

    L_{j+1} is the derivative of L_j along the flow; the lower orders ride along as jvp's aux,
    undifferentiated, so that L0..L3 come from one nested jvp (three separate ones, for L1, L2
    and L3, would trace and compile the nested flow derivatives three times)."""

    def lie(h):
        def up(t_, y_):
            top, dtop, lower = jax.jvp(h, (t_, y_), (jnp.ones_like(t_), f(t_, y_)), has_aux=True)
            return dtop, (*lower, top)

        return up

    L3, (L0, L1, L2) = lie(lie(lie(lambda t_, y_: (g(t_, y_), ()))))(t, y)
    return L0, L1, L2, L3
