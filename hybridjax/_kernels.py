"""A system's user functions, evaluated on the padded state with the mode chosen at run time.

The solver carries one state of length n = max_I n_I. Mode I's functions see its first n_I
components; their outputs are padded back with zeros. The current mode is a traced integer,
so under `jax.vmap` every mode's branch is evaluated and one is selected. An inactive branch
may see a state of another mode, on which a user function can return NaN or inf; its inputs
are therefore passed through `stop_gradient` (the "double where" idiom), so that a NaN in a
branch that was not taken never reaches a gradient.
"""

from collections.abc import Callable

import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jax import lax

from ._system import HybridSystem


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


def dispatch(index, branches: list[Callable], *operands):
    """`lax.switch(index, branches, *operands)` with inactive branches' gradients cut."""
    if len(branches) == 1:
        return branches[0](*operands)

    def wrap(i, fn):
        def branch(index, *ops):
            return fn(*mask_inputs(index == i, ops))

        return branch

    return lax.switch(index, [wrap(i, f) for i, f in enumerate(branches)], index, *operands)


class Kernels:
    """Padded, mode-dispatched flows, guards, resets and guard Lie derivatives of a system."""

    def __init__(self, system: HybridSystem):
        self.system = system
        self.n = system.max_dim
        self.num_transitions = system.num_transitions
        self.sources = jnp.asarray(system.sources, dtype=jnp.int32)
        self.targets = jnp.asarray(system.targets, dtype=jnp.int32)

    # ---------------------------------------------------------------- per-mode pieces
    def mode_flow(self, i: int) -> Callable:
        mode, n = self.system.modes[i], self.n
        return lambda t, y, args: _pad(mode.flow(t, y[: mode.dim], args), n)

    def flow(self, mode, t, y, args) -> jax.Array:
        """F_mode(t, y) on the padded state (zeros beyond the mode's dim)."""
        branches = [self.mode_flow(i) for i in range(self.system.num_modes)]
        return dispatch(mode, branches, t, y, args)

    def _guard_fn(self, k: int) -> Callable:
        tr = self.system.transitions[k]
        n_src = self.system.modes[self.system.sources[k]].dim
        return lambda t, y, args: jnp.asarray(tr.guard(t, y[:n_src], args))

    def outgoing_mask(self, mode) -> jax.Array:
        """(K,) bool: which transitions leave `mode`."""
        if self.num_transitions == 0:
            return jnp.zeros((0,), dtype=bool)
        return self.sources == mode

    def guards(self, mode, t, y, args) -> jax.Array:
        """(K,) guard values g_k(t, y); transitions not leaving `mode` read +1 (never fire)."""
        if self.num_transitions == 0:
            return jnp.zeros((0,), dtype=y.dtype)
        values = []
        for k in range(self.num_transitions):
            active = mode == self.system.sources[k]
            tt, yy, aa = mask_inputs(active, (t, y, args))
            values.append(self._guard_fn(k)(tt, yy, aa).astype(y.dtype))
        g = jnp.stack(values)
        return jnp.where(self.outgoing_mask(mode), g, jnp.ones_like(g))

    def reset(self, k, t, y, args) -> jax.Array:
        """R_k(t, y) on the padded state, transition index `k` traced."""

        def branch(kk):
            tr = self.system.transitions[kk]
            n_src = self.system.modes[self.system.sources[kk]].dim
            return lambda t, y, args: _pad(tr.reset(t, y[:n_src], args), self.n).astype(y.dtype)

        return dispatch(k, [branch(kk) for kk in range(self.num_transitions)], t, y, args)

    # ---------------------------------------------------------------- guard jets
    def guard_jets(self, mode, t, y, args, rtol, atol, tol_t) -> dict[str, jax.Array]:
        """Lie derivatives of every guard along the current flow, and a tolerance band.

        L0 = g, L_{j+1} = d/dt L_j along (t, x) -> (1, F_I(t, x)), so L1 = D_t g + D_x g F_I.
        `band` = sum_i |d g/d x_i| (atol + rtol |x_i|) + |D_t g| tol_t: the change in g that
        the solver's own tolerances cannot resolve. `scale1` = |D_t g| + sum_i |D_x g_i F_i|,
        against which L1 is judged zero (cancellation) or not.
        """
        K = self.num_transitions
        if K == 0:
            z = jnp.zeros((0,), dtype=y.dtype)
            return dict(L0=z, L1=z, L2=z, L3=z, band=z, scale1=z)
        out: dict[str, list] = {key: [] for key in ("L0", "L1", "L2", "L3", "band", "scale1")}
        for k in range(K):
            src = self.system.sources[k]
            active = mode == src
            tt, yy, aa = mask_inputs(active, (t, y, args))
            g = lambda t_, y_: self._guard_fn(k)(t_, y_, aa).astype(y.dtype)  # noqa: E731
            f = lambda t_, y_: self.mode_flow(src)(t_, y_, aa)  # noqa: E731

            def lie(h):
                return lambda t_, y_: jax.jvp(h, (t_, y_), (jnp.ones_like(t_), f(t_, y_)))[1]

            L1f = lie(g)
            L2f = lie(L1f)
            L3f = lie(L2f)
            gt, gx = jax.grad(g, argnums=(0, 1))(tt, yy)
            F = f(tt, yy)
            out["L0"].append(g(tt, yy))
            out["L1"].append(L1f(tt, yy))
            out["L2"].append(L2f(tt, yy))
            out["L3"].append(L3f(tt, yy))
            out["band"].append(jnp.sum(jnp.abs(gx) * (atol + rtol * jnp.abs(yy))) + jnp.abs(gt) * tol_t)
            out["scale1"].append(jnp.abs(gt) + jnp.sum(jnp.abs(gx * F)))
        return {key: jnp.stack(v) for key, v in out.items()}

