r"""A contact system evaluated for the traced mode index: one masked solve, whatever the modes.

Every mode of a contact system is the same constrained dynamics with the mask of its contact
set $A$ over the scene's rows $r$ (the constraints' gaps, then the tangents of those that
stick): the KKT system $M \ddot q = f + J^\top \lambda$, $m_r (J \ddot q + c)_r = 0$,
$(1 - m_r) \lambda_r = 0$ with $m = \mathbb{1}_A$ (`mechanics.kkt_solve`). So is every guard
(a gap $a_k$, or a contact force $\lambda_j$ of the same solve) and every reset (the impact
map with the mask of the new set, or the identity). `ContactEvaluation` looks the mask,
the guard of each slot and the reset of each transition up in tables by the traced index
and solves once, where the engines would otherwise evaluate every mode's and every
transition's function and select one: the cost of a step, and of compiling it, is that of
one solve with all $K$ constraints, not of one per mode built.
"""

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._definition.indexed import ModeIndexed
from .._definition.kernels import dispatch, select_by_mode
from .mechanics import (
    impact_gaps,
    impact_map,
    kinematics,
    release_choice,
    rows,
    schur_solve,
    selection_guard,
)

# Where a slot's value comes from: a gap, a contact force, a constant, or a selection guard.
GAP, FORCE, CONSTANT, SELECTED = "gap", "force", "constant", "selected"

# The records below (`ReleaseChoice`, `SlotSpec`, `ResetSpec`) are plain Python data read while a
# step is traced; they live in the static fields of `ContactEvaluation`, so their own fields are
# ordinary ones.


class ReleaseChoice(eqx.Module):
    """An impact's release candidates on the rows of all the scene's constraints, as
    `mechanics.release_choice` takes them: per candidate the rows held, the impacting
    constraint `hit` (its restitution on its gap row), the rows of the constraints involved
    (`involved`: their indices, in the order of the impact's own rows) and the gap rows of the
    unilateral constraints involved (impulses >= 0 and released rates >= 0 are asked there)."""

    held: tuple
    hit: int
    involved: tuple
    gap_rows: tuple


class SlotSpec(eqx.Module):
    r"""One watched function of a mode: `kind` GAP (constraint `index`'s gap), FORCE (row
    `index`'s contact force plus `offset`), CONSTANT (`offset`), or SELECTED (constraint
    `index`'s gap where the impact's `choice`, a candidate index, is in `chosen`, and
    |gap| + 1 elsewhere: the impacts that share one guard $a_k \le 0$ and differ in which
    contacts the impact releases)."""

    kind: str
    index: int = 0
    offset: float = 0.0
    choice: ReleaseChoice | None = None
    chosen: tuple = ()


class ResetSpec(eqx.Module):
    """The reset of one transition: the impact of constraint `hit` with the rows of the
    constraints `held` held (None: the identity), then relabelling map `relabel` (an index
    into `ContactEvaluation.relabel_maps`, -1 for none)."""

    held: tuple | None = None
    hit: int = 0
    relabel: int = -1


class ContactEvaluation(ModeIndexed):
    r"""The flows, watched functions and resets of a contact system for a traced index.

    - `mode_sets`: per mode, its held constraints (indices), None for a terminal mode (flow 0);
    - `slots`: per mode, its watched functions in the engine's order (`SlotSpec`);
    - `resets`: per transition, `ResetSpec`;
    - `least_norm`: least-norm contact forces (regularised solve) in every mode.
    """

    # Static: the scene's Python callables and the index tables that choose the code traced.
    scene: object = eqx.field(static=True)
    mode_sets: tuple = eqx.field(static=True)
    slots: tuple = eqx.field(static=True)
    resets: tuple = eqx.field(static=True)
    relabel_maps: tuple = eqx.field(static=True)
    least_norm: bool = eqx.field(static=True)

    # ------------------------------------------------------------------ tables
    def _rows(self):
        return rows(self.scene, range(len(self.scene.constraints)))

    def _mode_mask(self, mode, dtype) -> jax.Array:
        """(rows,): 1 on the rows of `mode`'s held constraints (a terminal mode holds none)."""
        K = len(self.scene.constraints)
        _, owners = self._rows()
        table = np.asarray([[float(s is not None and i in s) for i in range(K)] for s in self.mode_sets])
        return _by_mode(mode, table[:, np.asarray(owners, dtype=int)], dtype)

    def _kinematics(self, t, y, args):
        n = self.scene.dim
        return kinematics(self.scene, self._rows()[0], t, y[:n], y[n:], args)

    def _selection(self, mode, dtype):
        """(S, m): S (P, rows) picks the rows `mode` holds (P: the most rows any mode holds),
        m (P,) marks the entries in use. A mode's solve is on its own rows: its size is P,
        not the scene's number of rows."""
        _, owners = self._rows()
        held = [[r for r, o in enumerate(owners) if s is not None and o in s] for s in self.mode_sets]
        P = max(map(len, held), default=0)
        table = np.zeros((len(held), P, len(owners)))
        for m, rs in enumerate(held):
            table[m, np.arange(len(rs)), rs] = 1.0
        S = _by_mode(mode, table.reshape(len(held), -1), dtype).reshape(P, len(owners))
        return S, jnp.sum(S, axis=1)

    def _acceleration(self, mode, kin, dtype):
        r"""$\ddot q$ and the row forces $\lambda$ (all rows, 0 where not held) of `mode`
        (`mechanics.acceleration` on the mode's rows, `_selection`)."""
        S, m = self._selection(mode, dtype)
        if S.shape[0] == 0:
            return kin.Minv_f, jnp.zeros(kin.J.shape[0], dtype)
        ddq, mu = schur_solve(kin.Minv_f, kin.W @ S.T, S @ kin.G @ S.T, S @ kin.J, -(S @ kin.bias), m,
                              self.least_norm)
        return ddq, S.T @ mu

    def _restitution(self, args, dtype) -> jax.Array:
        """(rows,): each constraint's coefficient on its gap row, 0 on the tangent rows."""
        e = jnp.stack([jnp.asarray(c.coefficient(args), dtype) for c in self.scene.constraints])
        return jnp.concatenate([e, jnp.zeros(len(self._rows()[0]) - e.shape[0], dtype)])

    # ------------------------------------------------------------------ ModeIndexed
    def flow(self, mode, t, y, args) -> jax.Array:
        n = self.scene.dim
        kin = self._kinematics(t, y, args)
        ddq, _ = self._acceleration(mode, kin, y.dtype)
        terminal = jnp.asarray([s is None for s in self.mode_sets])[mode]
        return jnp.where(terminal, 0.0, jnp.concatenate([y[n:], ddq]))

    def watch(self, mode, t, y, args) -> jax.Array:
        K = len(self.scene.constraints)
        kin = self._kinematics(t, y, args)
        _, lam = self._acceleration(mode, kin, y.dtype)
        gaps = impact_gaps(self.scene, t, y[: self.scene.dim], args, kin.gap)
        # Every impact's choice of the current mode in one vmapped solve, and only where one of
        # its selection guards is at or below zero, where it is read (`selection_guard`):
        # under `jax.vmap`, where one execution needs it.
        held, present, gap_rows, involved = self._choice_tables()
        if present.any():
            has = _by_mode(mode, present.any(axis=2).astype(float), y.dtype) > 0
            need = jnp.any(has & (gaps <= 0))
            kin_sg, args_sg = lax.stop_gradient((kin, args))
            picks = lax.cond(eqxi.unvmap_any(need), lambda: self._choices(mode, kin_sg, args_sg, y.dtype),
                             lambda: jnp.full((K,), -1, jnp.int32))
        values = [gaps, lam]
        base = K + lam.shape[0]
        source, offset = [], []
        for specs in self.slots:
            src_row, off_row = [], []
            for spec in specs:
                if spec.kind == GAP:
                    src_row.append(spec.index)
                elif spec.kind == FORCE:
                    src_row.append(K + spec.index)
                elif spec.kind == SELECTED:
                    pick = picks[spec.choice.hit]
                    taken = jnp.any(jnp.stack([pick == c for c in spec.chosen] + [False]))
                    values.append(selection_guard(gaps[spec.index], taken)[None])
                    src_row.append(base)
                    base += 1
                else:  # CONSTANT: `offset` on the zero at the end of `values`
                    src_row.append(-1)
                off_row.append(spec.offset)
            source.append(src_row)
            offset.append(off_row)
        values = jnp.concatenate([*values, jnp.zeros((1,), y.dtype)])
        # Slot s of `mode`: values[source] + offset; an unused slot reads 1.
        rows = [[values[i] + o for i, o in zip(src, off, strict=True)]
                for src, off in zip(source, offset, strict=True)]
        return select_by_mode(mode, rows, max(map(len, self.slots), default=0), 1.0, y.dtype)

    def _choice_tables(self):
        """The release candidates of every (mode, impacting constraint) that a selection guard
        reads, padded to C candidates: held rows (modes, K, C, rows), present (modes, K, C), and
        the gap rows and rows involved (modes, K, rows) (`ReleaseChoice`)."""
        K, R = len(self.scene.constraints), len(self._rows()[0])
        choices = {(m, sp.choice.hit): sp.choice for m, specs in enumerate(self.slots) for sp in specs
                   if sp.kind == SELECTED}
        C = max((len(ch.held) for ch in choices.values()), default=0)
        M = len(self.slots)
        held, present = np.zeros((M, K, C, R)), np.zeros((M, K, C), bool)
        gap_rows, involved = np.zeros((M, K, R), bool), np.zeros((M, K, R), bool)
        for (m, k), ch in choices.items():
            held[m, k, : len(ch.held)] = ch.held
            present[m, k, : len(ch.held)] = True
            gap_rows[m, k] = ch.gap_rows
            involved[m, k, list(ch.involved)] = True
        return held, present, gap_rows, involved

    def _choices(self, mode, kin, args, dtype):
        """`release_choice` of the impact of each constraint k in `mode` at the state of `kin`
        (given without gradients): (K,) candidate indices (-1 where none solves it, or none is read).
        The K impacts and their candidates are one vmapped solve on the scene's rows."""
        K, R = len(self.scene.constraints), len(self._rows()[0])
        held, present, gap_rows, involved = self._choice_tables()
        C = held.shape[2]
        held = _by_mode(mode, held.reshape(held.shape[0], -1), dtype).reshape(K, C, R)
        present = _by_mode(mode, present.reshape(present.shape[0], -1), dtype).reshape(K, C) > 0
        gap_rows = _by_mode(mode, gap_rows.reshape(gap_rows.shape[0], -1), dtype).reshape(K, R) > 0
        involved = _by_mode(mode, involved.reshape(involved.shape[0], -1), dtype).reshape(K, R) > 0
        e = self._restitution(args, dtype)
        hit = jnp.eye(K, R, dtype=dtype)  # constraint k's restitution acts on its gap row alone

        def one(k_hit, h, p, g, i):
            return release_choice(kin, h, k_hit * e, i, g, self.least_norm, present=p)

        return jax.vmap(one)(hit, held, present, gap_rows, involved)

    def reset(self, k, t, y, args) -> jax.Array:  # once per event: tables read by index
        n = self.scene.dim
        _, owners = self._rows()
        specs = self.resets
        held = np.asarray([[float(r.held is not None and o in r.held) for o in owners] for r in specs])
        is_impact = np.asarray([r.held is not None for r in specs])
        hit = np.asarray([[float(r.held is not None and i == r.hit) for i in range(len(owners))]
                          for r in specs])
        e = jnp.asarray(hit, y.dtype)[k] * self._restitution(args, y.dtype)
        kin = self._kinematics(t, y, args)
        dq_plus, _, _ = impact_map(kin, jnp.asarray(held, y.dtype)[k], e, self.least_norm)
        x = jnp.concatenate([y[:n], jnp.where(jnp.asarray(is_impact)[k], dq_plus, y[n:])])
        if not self.relabel_maps:
            return x
        which = jnp.asarray([r.relabel + 1 for r in specs], jnp.int32)[k]
        return dispatch(which, [lambda t, x, args: x, *self.relabel_maps], t, x, args)


def _by_mode(mode, table, dtype) -> jax.Array:
    """Row `mode` of the constant (modes, m) `table`, each entry selected elementwise by `mode`
    (no gather by a traced index)."""
    row = jnp.zeros(table.shape[1], dtype)
    for m in range(table.shape[0]):
        row = jnp.where(mode == m, jnp.asarray(table[m], dtype), row)
    return row
