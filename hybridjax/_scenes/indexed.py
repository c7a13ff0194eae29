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
one solve with all $K$ constraints, not of one per mode built. An impact's release candidates
share its gap: the engines watch the gap once (`locate_watch`) and solve the choice at the
located event (`select`).
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._definition.indexed import ModeIndexed
from .._definition.kernels import dispatch, pick_values, row_by_mode, select_slots
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


class SceneEvaluation(ModeIndexed):
    r"""What the evaluations of a scene's modes share: the kinematics of all its rows (the
    constraints' gaps, then the tangents of those that stick), the restitution on those rows,
    the flow $(\dot q, \ddot q)$ (0 in a terminal mode) and the resets (the impact map with the
    rows a transition holds, or the identity). A subclass gives its modes' accelerations
    (`_acceleration`), which modes are terminal (`_terminal`) and its resets' tables
    (`_reset_tables`)."""

    # Static: the scene's Python callables.
    scene: object = eqx.field(static=True)

    def _rows(self):
        return rows(self.scene, range(len(self.scene.constraints)))

    def _kinematics(self, t, y, args):
        n = self.scene.dim
        return kinematics(self.scene, self._rows()[0], t, y[:n], y[n:], args)

    def _restitution(self, args, dtype) -> jax.Array:
        """(rows,): each constraint's coefficient on its gap row, 0 on the tangent rows."""
        e = jnp.stack([jnp.asarray(c.coefficient(args), dtype) for c in self.scene.constraints])
        return jnp.concatenate([e, jnp.zeros(len(self._rows()[0]) - e.shape[0], dtype)])

    @abc.abstractmethod
    def _terminal(self) -> tuple:
        """Per mode, whether it is terminal (its flow is 0)."""

    @abc.abstractmethod
    def _acceleration(self, mode, kin, args, dtype):
        r"""$\ddot q$ and the row forces $\lambda$ (all rows) of `mode` at the state of `kin`."""

    @abc.abstractmethod
    def _reset_tables(self):
        """Per transition: the rows held (T, rows), whether it is an impact (T,), the rows that
        take restitution (T, rows), and the least-norm flag (a bool for all, or (T,))."""

    def flow(self, mode, t, y, args) -> jax.Array:
        return _traced_once(type(self)._flow, self, mode, t, y, args)

    def _flow(self, mode, t, y, args) -> jax.Array:
        n = self.scene.dim
        kin = self._kinematics(t, y, args)
        ddq, _ = self._acceleration(mode, kin, args, y.dtype)
        terminal = jnp.asarray(self._terminal())[mode]
        return jnp.where(terminal, 0.0, jnp.concatenate([y[n:], ddq]))

    def reset(self, k, t, y, args) -> jax.Array:  # once per event: tables read by index
        n = self.scene.dim
        held, is_impact, hit, least = self._reset_tables()
        e = jnp.asarray(hit, y.dtype)[k] * self._restitution(args, y.dtype)
        kin = self._kinematics(t, y, args)
        if isinstance(least, np.ndarray):
            least = jnp.asarray(least, y.dtype)[k] if least.any() else False
        dq_plus, _, _ = impact_map(kin, jnp.asarray(held, y.dtype)[k], e, least)
        return jnp.concatenate([y[:n], jnp.where(jnp.asarray(is_impact)[k], dq_plus, y[n:])])


class ContactEvaluation(SceneEvaluation):
    r"""The flows, watched functions and resets of a contact system for a traced index.

    - `mode_sets`: per mode, its held constraints (indices), None for a terminal mode (flow 0);
    - `slots`: per mode, its watched functions in the engine's order (`SlotSpec`);
    - `resets`: per transition, `ResetSpec`;
    - `least_norm`: least-norm contact forces (regularised solve) in every mode.
    """

    # Static: the index tables that choose the code traced.
    mode_sets: tuple = eqx.field(static=True)
    slots: tuple = eqx.field(static=True)
    resets: tuple = eqx.field(static=True)
    relabel_maps: tuple = eqx.field(static=True)
    least_norm: bool = eqx.field(static=True)

    # ------------------------------------------------------------------ tables
    def _mode_mask(self, mode, dtype) -> jax.Array:
        """(rows,): 1 on the rows of `mode`'s held constraints (a terminal mode holds none)."""
        K = len(self.scene.constraints)
        _, owners = self._rows()
        table = np.asarray([[float(s is not None and i in s) for i in range(K)] for s in self.mode_sets])
        return _by_mode(mode, table[:, np.asarray(owners, dtype=int)], dtype)

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
        S = _by_mode(mode, table, dtype)
        return S, jnp.sum(S, axis=1)

    def _terminal(self) -> tuple:
        return tuple(s is None for s in self.mode_sets)

    def _acceleration(self, mode, kin, args, dtype):
        r"""$\ddot q$ and the row forces $\lambda$ (all rows, 0 where not held) of `mode`
        (`mechanics.acceleration` on the mode's rows, `_selection`)."""
        S, m = self._selection(mode, dtype)
        if S.shape[0] == 0:
            return kin.Minv_f, jnp.zeros(kin.J.shape[0], dtype)
        ddq, mu = schur_solve(kin.Minv_f, kin.W @ S.T, S @ kin.G @ S.T, S @ kin.J, -(S @ kin.bias), m,
                              self.least_norm)
        return ddq, S.T @ mu

    # ------------------------------------------------------------------ ModeIndexed
    def _values(self, mode, t, y, args):
        """The kinematics at (t, y), the impacts' gaps (K,) and what a slot picks from:
        [gaps (K), row forces of `mode`, 0]."""
        kin = self._kinematics(t, y, args)
        _, lam = self._acceleration(mode, kin, args, y.dtype)
        gaps = impact_gaps(self.scene, t, y[: self.scene.dim], args, kin.gap)
        return kin, gaps, jnp.concatenate([gaps, lam, jnp.zeros((1,), y.dtype)])

    def watch(self, mode, t, y, args) -> jax.Array:
        K = len(self.scene.constraints)
        kin, gaps, values = self._values(mode, t, y, args)
        # The impacts' choices of the current mode, only of the constraints whose selection
        # guards are read, those at or below zero (`selection_guard`).
        held, present, gap_rows, involved = self._choice_tables()
        picks = jnp.full((K,), -1, jnp.int32)
        if present.any():
            has = _by_mode(mode, present.any(axis=2).astype(float), y.dtype) > 0
            kin_sg, args_sg = lax.stop_gradient((kin, args))
            picks = self._choices(mode, kin_sg, args_sg, has & (gaps <= 0), y.dtype)
        # Slot s of `mode` from constant tables (`_slot_tables`): one pick from
        # [gaps, forces, 0], plus an offset; a selection guard on its picked gap.
        index, offset, selected, hit, chosen = self._slot_tables()
        if index.shape[1] == 0:
            return jnp.zeros((0,), y.dtype)
        out = select_slots(mode, values, index, offset, 1.0)
        if not selected.any():
            return out
        # The impact's choice `picks[hit]` (-1: none solves it) against the candidates the slot
        # takes, a (S, C + 1) pattern whose column c + 1 is candidate c.
        pick = pick_values(picks, row_by_mode(mode, hit, jnp.int32), -1)
        takes = _by_mode(mode, chosen, y.dtype) > 0
        taken = jnp.any(takes & (pick[:, None] + 1 == jnp.arange(chosen.shape[2])[None, :]), axis=1)
        return jnp.where(row_by_mode(mode, selected, y.dtype) > 0, selection_guard(out, taken), out)

    def locate_watch(self, mode, t, y, args) -> jax.Array:
        r"""`watch` with each impact's selection guards located on its gap $a_k$ alone: the
        first selection guard of an impact reads $a_k$, the others $+1$ (`_located_tables`);
        `select` takes the release choice at the event. No choice is solved while locating."""
        return _traced_once(ContactEvaluation._locate_watch, self, mode, t, y, args)

    def _locate_watch(self, mode, t, y, args) -> jax.Array:
        index, offset = self._located_tables()
        if index.shape[1] == 0:
            return jnp.zeros((0,), y.dtype)
        _, _, values = self._values(mode, t, y, args)
        return select_slots(mode, values, index, offset, 1.0)

    def select(self, mode, slot, t, y, args) -> jax.Array:
        """The selection guard of the impact located on `slot` that holds at (t, y): the one
        whose candidates include the impact's `release_choice` there (exactly one does, "no
        candidate solves it" included); `slot` where it is not a selection guard."""
        _, _, selected, hit, _ = self._slot_tables()
        if not selected.any():
            return slot
        redirect = self._redirect_table()  # (modes, S, C + 1)
        M, S, C1 = redirect.shape
        k = pick_values(row_by_mode(mode, hit, jnp.int32), slot[None], 0)[0]
        kin = self._kinematics(t, y, args)
        e = self._restitution(args, y.dtype)
        tables = tuple(_by_mode(mode, tab, y.dtype) for tab in self._choice_tables())
        pick = self._choice(k, kin, e, *tables)
        row = row_by_mode(mode, redirect.reshape(M, -1), jnp.int32)
        taken = pick_values(row, (slot * C1 + pick + 1)[None], 0)[0]
        is_selected = pick_values(row_by_mode(mode, selected, y.dtype), slot[None], 0.0)[0] > 0
        return jnp.where(is_selected, taken, slot)

    def _groups(self) -> list:
        """Per mode, `choice_groups` of its slots: a selection guard's choice is its impact's."""
        return [choice_groups([sp.choice.hit if sp.kind == SELECTED else None for sp in specs])
                for specs in self.slots]

    def _located_tables(self):
        """`_slot_tables`' index and offset with every selection guard but the first of each
        impact reading the constant +1 (the zero entry plus an offset of 1)."""
        index, offset, *_ = self._slot_tables()
        index, offset = index.copy(), offset.copy()
        zero = len(self.scene.constraints) + len(self._rows()[0])
        for m, groups in enumerate(self._groups()):
            for s, (_, first) in enumerate(groups):
                if not first:
                    index[m, s], offset[m, s] = zero, 1.0
        return index, offset

    def _redirect_table(self):
        """(modes, S, C + 1): for a selection guard, the slot of its impact that takes each
        outcome (column 0: none solves it; column c + 1: candidate c); the slot itself
        elsewhere."""
        *_, chosen = self._slot_tables()
        M, S, C1 = chosen.shape
        redirect = np.broadcast_to(np.arange(S)[None, :, None], (M, S, C1)).copy()
        for m, groups in enumerate(self._groups()):
            for s, (members, _) in enumerate(groups):
                for s2 in members:  # a slot of its own takes no candidate
                    redirect[m, s, chosen[m, s2] > 0] = s2
        return redirect

    def _slot_tables(self):
        """Constant (modes, S) tables of the slots: the index into [gaps (K), row forces, 0]
        (-1 unused), the offset, whether the slot is a selection guard, the impacting constraint
        it reads the choice of, and (modes, S, C + 1) the candidates it takes (column c + 1 for
        candidate c, column 0 for "none solves it")."""
        K, R = len(self.scene.constraints), len(self._rows()[0])
        M, S = len(self.slots), max(map(len, self.slots), default=0)
        C = max((len(sp.choice.held) for specs in self.slots for sp in specs if sp.kind == SELECTED),
                default=0)
        index, offset = np.full((M, S), -1), np.zeros((M, S))
        selected, hit, chosen = np.zeros((M, S)), np.zeros((M, S), int), np.zeros((M, S, C + 1))
        for m, specs in enumerate(self.slots):
            for s, spec in enumerate(specs):
                offset[m, s] = spec.offset
                if spec.kind in (GAP, SELECTED):
                    index[m, s] = spec.index
                elif spec.kind == FORCE:
                    index[m, s] = K + spec.index
                else:  # CONSTANT: `offset` on the zero at the end
                    index[m, s] = K + R
                if spec.kind == SELECTED:
                    selected[m, s], hit[m, s] = 1.0, spec.choice.hit
                    chosen[m, s, [c + 1 for c in spec.chosen]] = 1.0
        return index, offset, selected, hit, chosen

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

    def _choices(self, mode, kin, args, need, dtype):
        """`release_choice` of the impact of each constraint k in `mode` with `need[k]`, at the
        state of `kin` (given without gradients): (K,) candidate indices (-1 where none solves it,
        or it is not needed). One constraint at a time, its candidates one vmapped solve: at an
        impact one gap or two are closed, so a loop over those needed costs one or two solves
        where a solve of every constraint costs K (under `jax.vmap`, the loop runs as often as
        the execution that needs the most)."""
        K = len(self.scene.constraints)
        tables = tuple(_by_mode(mode, tab, dtype) for tab in self._choice_tables())
        e = self._restitution(args, dtype)

        def body(carry):
            picks, left = carry
            k = jnp.argmax(left)
            pick = self._choice(k, kin, e, *tables)
            mine = jnp.arange(K) == k
            return jnp.where(mine, pick, picks), left & ~mine

        return lax.while_loop(lambda c: jnp.any(c[1]), body, (jnp.full((K,), -1, jnp.int32), need))[0]

    def _choice(self, k, kin, e, held, present, gap_rows, involved) -> jax.Array:
        """`release_choice` of the impact of constraint `k` (traced) at the state of `kin`, from
        the current mode's choice tables (`_choice_tables`' rows: held (K, C, rows), present
        (K, C), gap rows and rows involved (K, rows)); -1 where no candidate solves it."""
        K, C, R = held.shape
        dtype = kin.gap.dtype
        h, p, g, i = (row_by_mode(k, table.reshape(K, -1), dtype)
                      for table in (held, present, gap_rows, involved))
        hit = (jnp.arange(R) == k).astype(dtype)  # constraint k's restitution on its gap row alone
        return release_choice(kin, h.reshape(C, R), hit * e, i > 0, g > 0, self.least_norm, present=p > 0)

    def _reset_tables(self):
        _, owners = self._rows()
        specs = self.resets
        held = np.asarray([[float(r.held is not None and o in r.held) for o in owners] for r in specs])
        is_impact = np.asarray([r.held is not None for r in specs])
        hit = np.asarray([[float(r.held is not None and i == r.hit) for i in range(len(owners))]
                          for r in specs])
        return held, is_impact, hit, self.least_norm

    def reset(self, k, t, y, args) -> jax.Array:  # once per event: tables read by index
        x = super().reset(k, t, y, args)
        if not self.relabel_maps:
            return x
        which = jnp.asarray([r.relabel + 1 for r in self.resets], jnp.int32)[k]
        return dispatch(which, [lambda t, x, args: x, *self.relabel_maps], t, x, args)


@jax.jit(static_argnums=(0, 1))
def _traced_once(method, evaluation, mode, t, y, args):
    """`method(evaluation, mode, t, y, args)` as one jitted call, `evaluation` static (its
    fields are static tables): an engine evaluates a flow or a guard at many places of a step
    (every Runge-Kutta stage, every root-finding iteration, their derivatives), and each place
    then reuses one trace of it, where a plain call would trace the scene's kinematics and
    solves again. XLA inlines the calls, so the compiled program and its numbers are those of
    plain calls."""
    return method(evaluation, mode, t, y, args)


def choice_groups(keys: list) -> list:
    """Per slot of one mode, from each slot's choice (`keys[s]`, None for a slot of its own):
    the slots of the same choice, and whether the slot is the first of them (the one located
    on the value they share, `ModeIndexed.locate_watch`)."""
    keys = [("own", s) if key is None else key for s, key in enumerate(keys)]
    return [([s2 for s2, k2 in enumerate(keys) if k2 == key], keys.index(key) == s)
            for s, key in enumerate(keys)]


def _by_mode(mode, table, dtype) -> jax.Array:
    """Entry `mode` of the constant (modes, ...) `table` (`kernels.row_by_mode` of its rows)."""
    table = np.asarray(table)
    return row_by_mode(mode, table.reshape(len(table), -1), dtype).reshape(table.shape[1:])
