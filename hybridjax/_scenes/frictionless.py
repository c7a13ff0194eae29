r"""Frictionless contact sets: the builder of scenes whose contacts have no friction.

The modes are the sets $A$ of held constraints (`scene.py` states the flow, guards and impact
map). The contact graph's transitions out of $A$: an impact of each open unilateral contact $k$
with each release candidate $R$ (none of $A$, then one, then two, ...), and a lift-off of each
held unilateral contact. Their witnesses (`contact_system`'s notes): an impact needs $a_A = 0$,
$\dot a_A = 0$, $a_k = 0$, the other contacts open, $\lambda_A \ge 0$, approach speed
$-\dot a_k \ge$ `margin`, nonnegative impulses and separating releases; a lift-off needs
$\lambda_j \le -$`margin`.
"""

import dataclasses
import functools
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, PRNGKeyArray

from .._analysis.search import SearchOptions, box_samples
from .._definition.system import Mode, Transition
from .graph import ContactGraph, ExploreRules, Leaving, explore
from .indexed import CONSTANT, FORCE, GAP, SELECTED, ContactEvaluation, ReleaseChoice, ResetSpec, SlotSpec
from .mechanics import (
    _INDEPENDENT,
    _row_mask,
    acceleration,
    armed_values,
    constrained_acceleration,
    constraint_gaps,
    impact,
    impact_gaps,
    impact_map,
    independence,
    kinematics,
    release_choice,
    rows,
    selection_guard,
)
from .scene import (
    INCONSISTENT,
    UNBUILT,
    UNILATERAL,
    Assembly,
    ContactSystem,
    Relabel,
    Scene,
    _as_set,
    _identity,
    _releases,
    _then,
    run_search,
    sample_box,
    set_name,
    state_names,
    witness_text,
)


class _Impact(eqx.Module):
    """Impact of constraint `k` in contact set `A` with release candidate `R`, on the constraint
    indices `order` (A's, then k); static description, functions of (t, x, args)."""

    # Static: a transition's reset is this object, part of the system's pytree; the scene
    # (callables) and the Python indices choose the code traced.
    scene: Scene = eqx.field(static=True)
    source: tuple = eqx.field(static=True)  # sorted indices of A
    k: int = eqx.field(static=True)
    candidates: tuple = eqx.field(static=True)  # release sets, each a sorted tuple
    least_norm: bool = eqx.field(static=True)

    @property
    def order(self):
        return self.source + (self.k,)

    def fns(self):
        return rows(self.scene, self.order)[0]

    def _e(self, args, dtype):
        e_k = self.scene.constraints[self.k].coefficient(args)
        num_rows = len(self.fns())
        return jnp.zeros(num_rows, dtype).at[len(self.order) - 1].set(jnp.asarray(e_k, dtype))

    def held(self, c, dtype):
        """The held rows of candidate `c` (the released constraints' rows are 0)."""
        release = self.candidates[c]
        return jnp.asarray([0.0 if i in release else 1.0 for i in rows(self.scene, self.order)[1]], dtype)

    def outcome(self, c, t, x, args):
        n = self.scene.dim
        q, dq = x[:n], x[n:]
        return impact(
            self.scene,
            self.fns(),
            self.held(c, x.dtype),
            self._e(args, x.dtype),
            t,
            q,
            dq,
            args,
            self.least_norm,
        )

    def select(self, t, x, args):
        """The index of the first candidate that solves the impact, -1 if none
        (`mechanics.release_choice`)."""
        n, dtype = self.scene.dim, x.dtype
        num_rows = len(self.fns())
        kin = kinematics(self.scene, self.fns(), t, x[:n], x[n:], args)
        held = jnp.stack([self.held(c, dtype) for c in range(len(self.candidates))])
        # The unilateral constraints' gap rows: a joint's impulse has either sign.
        gap_rows = jnp.asarray([r < len(self.order) and self.scene.constraints[o].kind == UNILATERAL
                                for r, o in enumerate(rows(self.scene, self.order)[1])])
        return release_choice(kin, held, self._e(args, dtype), jnp.ones(num_rows, bool), gap_rows,
                              self.least_norm)

    def choice(self) -> ReleaseChoice:
        """`select` on the rows of all the scene's constraints, for `ContactEvaluation`."""
        K = len(self.scene.constraints)
        _, owners = rows(self.scene, range(K))
        # The rows of `order` in `select`'s order (gaps of `order`, then their tangents), as
        # indices into all the rows: the independence test's pivots depend on the order.
        _, own = rows(self.scene, self.order)
        index = [o if r < len(self.order) else K + owners[K:].index(o) for r, o in enumerate(own)]
        return ReleaseChoice(
            held=tuple(tuple(float(o in self.order and o not in R) for o in owners) for R in self.candidates),
            hit=self.k,
            involved=tuple(index),
            gap_rows=tuple(
                o in self.order and r < K and self.scene.constraints[o].kind == UNILATERAL
                for r, o in enumerate(owners)
            ),
        )

    def guard(self, chosen: tuple):
        """a_k (`mechanics.impact_gaps`: max(a_k, -c_k) for an armed contact) where the selected
        candidate is in `chosen`, positive elsewhere."""
        n, k = self.scene.dim, self.k

        def gap(t, x, args):
            q = x[:n]
            return impact_gaps(self.scene, t, q, args, constraint_gaps(self.scene, t, q, args))[k]

        if set(range(len(self.candidates))) <= set(chosen):
            return gap

        def g(t, x, args):
            a = gap(t, x, args)
            # Which outcome holds is a discrete choice: no derivative flows through it.
            sel = self.select(*jax.lax.stop_gradient((t, x, args)))
            return selection_guard(a, jnp.any(jnp.stack([sel == c for c in chosen] + [False])))

        return g

    def slot(self, chosen: tuple) -> SlotSpec:
        """`guard(chosen)` as `ContactEvaluation` reads it."""
        if set(range(len(self.candidates))) <= set(chosen):
            return SlotSpec(GAP, self.k)
        return SlotSpec(SELECTED, self.k, choice=self.choice(), chosen=chosen)

    def reset(self, c):
        n = self.scene.dim

        def r(t, x, args):
            dq_plus, _, _ = self.outcome(c, t, x, args)
            return jnp.concatenate([x[:n], dq_plus])

        return r

    def target(self, c) -> frozenset:
        held = (set(self.source) | {self.k}) - set(self.candidates[c])
        if self.scene.constraints[self.k].restitutes:
            held.discard(self.k)
        return frozenset(held)


class _ModeFunctions(eqx.Module):
    """Flow and contact forces of contact set `held` (sorted indices), solved with the held
    constraints only (the mode's own functions; `ContactEvaluation` solves with all rows,
    masked, for a traced mode)."""

    # Static: a mode's flow is this object, part of the system's pytree; callables and indices.
    scene: Scene = eqx.field(static=True)
    held: tuple = eqx.field(static=True)
    least_norm: bool = eqx.field(static=True)

    def solve(self, t, x, args):
        n = self.scene.dim
        fns, _ = rows(self.scene, self.held)
        mask = jnp.ones(len(fns), x.dtype)
        return constrained_acceleration(self.scene, fns, mask, t, x[:n], x[n:], args, self.least_norm)

    def flow(self, t, x, args):
        ddq, _ = self.solve(t, x, args)
        return jnp.concatenate([x[self.scene.dim :], ddq])

    def force(self, j, offset=0.0):
        """lambda_j + offset, the force of held constraint j (a lift-off guard)."""
        pos = self.held.index(j)
        return lambda t, x, args: self.solve(t, x, args)[1][pos] + offset


# ----------------------------------------------------------------------------- search queries


class _Query(eqx.Module):
    """The conditions of one search as masks over the K constraints (all arrays, so that one
    compiled search checks every query of a level under `vmap`)."""

    held: Array  # source set A
    lift: Array  # one-hot lift-off constraint (or zeros)
    hit: Array  # one-hot impacting constraint (or zeros)
    impact_held: Array  # C less the released constraints (zeros for a lift-off)
    released: Array  # the released constraints
    flowing: Array  # scalar 1: lambda_A >= 0 required (impacts)


@functools.cache
def _query_functions(scene: Scene, margin: float, least_norm: bool):
    """The constraints of every query, one function `(t, x, (args, query)) -> (equalities,
    inequalities)` (cached: later builds of one scene, with other `args`, reuse the compiled
    search)."""
    K, n = len(scene.constraints), scene.dim
    fns, owners = rows(scene, range(K))
    unilateral = np.asarray([c.kind == UNILATERAL for c in scene.constraints], dtype=float)

    def parts(t, x, p):
        args, Q = p
        q, dq = x[:n], x[n:]
        held_rows = _row_mask(owners, Q.held, x.dtype)
        kin = kinematics(scene, fns, t, q, dq, args)
        a, adot = kin.gap, kin.adot
        open_gap = impact_gaps(scene, t, q, args, a)
        armed = armed_values(scene, t, q, args)
        _, lam = acceleration(kin, held_rows, least_norm)
        e = jnp.stack([jnp.asarray(c.coefficient(args), x.dtype) for c in scene.constraints]) * Q.hit
        e = jnp.concatenate([e, jnp.zeros(len(fns) - K, x.dtype)])
        impact_rows = _row_mask(owners, Q.impact_held, x.dtype)
        _, P, rates = impact_map(kin, impact_rows, e, least_norm)
        a, adot_gap, lam, P, rates = a[:K], adot[:K], lam[:K], P[:K], rates[:K]
        uni = jnp.asarray(unilateral, x.dtype)
        eq = jnp.concatenate([Q.held * a, held_rows * adot, Q.hit * a])
        adot = adot_gap
        one = jnp.ones_like(a)
        ineq = [
            jnp.where((uni * (1 - Q.held) * (1 - Q.hit)) > 0, open_gap, one),
            jnp.where(Q.hit > 0, armed, one),
            jnp.where((uni * Q.held * Q.flowing) > 0, lam, one),
            jnp.where(Q.lift > 0, -lam - margin, one),
            jnp.where(Q.hit > 0, -adot - margin, one),
            jnp.where(Q.impact_held * uni > 0, P, one),
            jnp.where(Q.released > 0, rates, one),
        ]
        ineq = jnp.concatenate(ineq)
        # A singular contact system (dependent constraints at a sample) gives non-finite values:
        # they count as violated, and finite.
        eq = jnp.where(jnp.isfinite(eq), eq, 1e6)
        return eq, jnp.where(jnp.isfinite(ineq), ineq, -1e6)

    return parts


def _run_queries(scene, queries, args_batch, samples, margin, least_norm, search):
    """The point search for every (query, args value): Witness with leading axes (Q, V)."""
    return run_search(_query_functions(scene, margin, least_norm), queries, args_batch, samples, search)


# ----------------------------------------------------------------------------- the contact graph


def _impact(scene: Scene, A: frozenset, k: int, least_norm: bool) -> _Impact:
    """The impact of `k` in `A` with its release candidates. A candidate with more rows than
    coordinates is dependent wherever it is: it can hold only with least-norm impulses."""
    releases = tuple(
        tuple(sorted(r))
        for r in _releases(A & {i for i, c in enumerate(scene.constraints) if c.kind == UNILATERAL})
        if least_norm or len(rows(scene, sorted((A | {k}) - r))[0]) <= scene.dim
    )
    return _Impact(scene, tuple(sorted(A)), k, releases, least_norm)


class _Rules(ExploreRules):
    """The explorer's rules for frictionless contact sets (frozensets of constraint indices)."""

    noun = "contact sets"

    def __init__(self, scene: Scene, values: list, key: PRNGKeyArray, num_samples: int, margin: float,
                 least_norm: bool, search: SearchOptions):  # fmt: skip
        dtype = jnp.result_type(float)
        self.scene, self.margin, self.least_norm, self.options, self.dtype = (
            scene, margin, least_norm, search, dtype
        )  # fmt: skip
        self.unilateral = {i for i, c in enumerate(scene.constraints) if c.kind == UNILATERAL}
        self.args_batch = (
            jnp.arange(len(values)),
            jtu.tree_map(lambda *v: jnp.stack([jnp.asarray(x, dtype) for x in v]), *values),
        )
        pts = box_samples(key, tuple(sample_box(scene, dtype)), num_samples)
        self.samples = (pts[:, -1], pts[:, :-1])
        self.relabel_of: dict = {}  # source set -> (target set, state map)

    def onehot(self, idx) -> Array:
        return jnp.asarray([1.0 if i in idx else 0.0 for i in range(len(self.scene.constraints))], self.dtype)

    def query(self, A, lift=(), hit=(), impact_held=(), released=(), flowing=0.0) -> _Query:
        h = self.onehot
        return _Query(h(A), h(lift), h(hit), h(impact_held), h(released), jnp.asarray(flowing, self.dtype))

    def leaving(self, A):
        for k in sorted(self.unilateral - A):
            imp = _impact(self.scene, A, k, self.least_norm)
            for c, R in enumerate(imp.candidates):
                held = (A | {k}) - set(R)
                query = self.query(A, hit={k}, impact_held=held, released=set(R), flowing=1.0)
                yield Leaving("impact", k, c, imp.target(c), query)
        for j in sorted(A & self.unilateral):
            yield Leaving("lift-off", j, 0, A - {j}, self.query(A, lift={j}))

    def search(self, queries):
        return _run_queries(self.scene, queries, self.args_batch, self.samples, self.margin, self.least_norm,
                            self.options)  # fmt: skip

    def outcome(self, w, i):
        found_v = w.found[i]
        if found_v.any():
            return tuple(int(a) for a in np.flatnonzero(found_v)), witness_text(w, i, self.scene.dim)
        finite = np.where(np.isfinite(w.violation[i]), w.violation[i], np.nan)
        least = float(np.nanmin(finite, initial=np.inf))
        why = (
            f"no state of the source set found in the guard (least violation {least:.2g})"
            if np.isfinite(least)
            else "the contact equations are singular (dependent constraints) at every state tried"
        )
        return (), why

    def canonical(self, T):
        return self.relabel_of.get(T, (T, None))[0]


def _initial_sets(scene: Scene, rules: _Rules, initial: Sequence, values: list) -> list:
    """The initial contact sets: each with a consistent state (held gaps and rates 0, the others
    open) where the held constraints are independent (or `redundant="least_norm"`)."""
    initial_sets = list(dict.fromkeys(_as_set(scene, s) for s in initial))
    if not initial_sets:
        raise ValueError("contact_system: give at least one initial contact set.")
    w = rules.search([rules.query(A) for A in initial_sets])
    K, n = len(scene.constraints), scene.dim
    for i, A in enumerate(initial_sets):
        if not w.found[i].any():
            raise ValueError(
                f"contact_system: the initial contact set {set_name(scene, A)} has no consistent state "
                "in the scene's ranges (held gaps and rates 0, the other contacts open; least violation "
                f"{np.nanmin(w.violation[i]):.2g}, infinite where the held constraints are dependent)."
            )
        v = int(np.argmax(w.found[i]))
        fns, owners = rows(scene, range(K))
        held_rows = _row_mask(owners, rules.onehot(A), rules.dtype)
        ratio = independence(scene, fns, held_rows, w.t[i, v], jnp.asarray(w.x[i, v, :n]), values[v])
        if ratio <= _INDEPENDENT and not rules.least_norm:
            names = [scene.constraints[j].name for j in sorted(A)]
            raise ValueError(
                f"contact_system: the initial contact set {set_name(scene, A)} has dependent constraints "
                f"{names} (redundant contacts); pass redundant='least_norm' for least-norm contact "
                "forces, or remove one of them."
            )
    return initial_sets


def _relabel_table(scene: Scene, relabels: Sequence[Relabel]) -> dict:
    """source set -> (target set, state map) of each `Relabel`."""
    relabel_of = {}
    for r in relabels:
        if not isinstance(r, Relabel):
            raise TypeError(f"contact_system: relabels must be hybridjax.Relabel, got {type(r).__name__}.")
        relabel_of[_as_set(scene, r.source)] = (_as_set(scene, r.target), r.state_map(scene.dim))
    return relabel_of


def frictionless_system(
    scene: Scene,
    initial: Sequence,
    args: Any,
    *,
    args_values: Sequence | None,
    num_samples: int,
    margin: float,
    key: PRNGKeyArray,
    redundant: str,
    form: str,
    max_modes: int,
    relabels: Sequence[Relabel],
    search: SearchOptions,
) -> ContactSystem:
    """`contact_system` for a scene without friction: its contact graph, assembled."""
    values = list(args_values) if args_values is not None else [args]
    if not values:
        raise ValueError("contact_system: `args_values` is empty.")
    for v in values:
        scene.check(v)
    least_norm = redundant == "least_norm"
    rules = _Rules(scene, values, key, num_samples, margin, least_norm, search)
    initial_sets = _initial_sets(scene, rules, initial, values)
    rules.relabel_of = _relabel_table(scene, relabels)
    graph = explore(rules, initial_sets, max_modes)
    return _assemble(scene, graph, rules.relabel_of, least_norm, margin, len(values), form)


# ----------------------------------------------------------------------------- assembly


@dataclasses.dataclass(frozen=True)
class _Links:
    """What the transitions of one build share: the relabellings and their state maps' order."""

    scene: Scene
    relabel_of: dict
    relabel_maps: tuple
    least_norm: bool

    def into(self, T: frozenset) -> tuple[frozenset, Any]:
        """(the set a transition into T goes to, the relabelling's state map or None)."""
        return self.relabel_of.get(T, (T, None))

    def reset_spec(self, held=None, hit=0, relabel_map=None) -> ResetSpec:
        r = -1 if relabel_map is None else self.relabel_maps.index(relabel_map)
        return ResetSpec(None if held is None else tuple(sorted(held)), hit, r)


def _add_impacts(asm: Assembly, links: _Links, A: frozenset, j: int, edges: list) -> None:
    """The transitions of an impact of `j` in `A`: one per candidate found, and one into a
    terminal mode for the candidates not found (or for an impact no candidate solves)."""
    scene = links.scene
    src, cname = set_name(scene, A), scene.constraints[j].name
    imp = _impact(scene, A, j, links.least_norm)
    chosen = tuple(e.detail for e in edges if e.found)
    for e in edges:
        c = e.detail
        if not e.found:
            released = [scene.constraints[i].name for i in imp.candidates[c]]
            rel = f" releasing {'+'.join(released)}" if released else ""
            tname = set_name(scene, e.target)
            asm.pruned.append(f"  pruned: impact of {cname} in {src}{rel} -> {tname}: {e.text}")
            continue
        tgt, relabel_map = links.into(imp.target(c))
        via = "" if relabel_map is None else f" (relabelled from {set_name(scene, imp.target(c))})"
        tname = set_name(scene, tgt)
        held = (set(imp.source) | {j}) - set(imp.candidates[c])
        asm.add(
            Transition(src, tname, guard=imp.guard((c,)), reset=_then(imp.reset(c), relabel_map),
                       name=f"impact {cname}: {src} -> {tname}"),
            imp.slot((c,)),
            links.reset_spec(held=held, hit=j, relabel_map=relabel_map),
        )  # fmt: skip
        asm.achievable.append((src, tname + via, "impact", cname, e.text))
    if len(chosen) < len(edges):
        term = asm.terminal(UNBUILT + set_name(scene, imp.target(0)))
        # With the candidates not found, the impact that no candidate solves (-1).
        others = tuple(c for c in range(len(imp.candidates)) if c not in chosen) + (-1,)
        asm.add(Transition(src, term, guard=imp.guard(others), name=f"impact {cname}: {src} -> {term}"),
                imp.slot(others), links.reset_spec())  # fmt: skip
    elif len(chosen) > 1:
        # Every candidate was found, so each transition reads the choice: an impact that no
        # candidate solves (dependent constraints, or rounding at a tie) stops the execution
        # there, naming it, rather than pass through the constraint.
        term = asm.terminal(f"{INCONSISTENT}impact of {cname} in {src}")
        asm.add(Transition(src, term, guard=imp.guard((-1,)), name=f"impact {cname}: {term}"),
                imp.slot((-1,)), links.reset_spec())  # fmt: skip


def _add_lift_off(asm: Assembly, links: _Links, fns: _ModeFunctions, A, j: int, edge, margin: float) -> None:
    """The lift-off of `j` in `A`: to its target if found, else to a terminal mode."""
    scene = links.scene
    src, cname = set_name(scene, A), scene.constraints[j].name
    T = edge.target
    if edge.found:
        tgt, relabel_map = links.into(T)
        via = "" if relabel_map is None else f" (relabelled from {set_name(scene, T)})"
        tname = set_name(scene, tgt)
        asm.add(
            Transition(src, tname, guard=fns.force(j), reset=_then(_identity, relabel_map),
                       name=f"lift-off {cname}: {src} -> {tname}"),
            SlotSpec(FORCE, j),
            links.reset_spec(relabel_map=relabel_map),
        )  # fmt: skip
        asm.achievable.append((src, tname + via, "lift-off", cname, edge.text))
        return
    term = asm.terminal(UNBUILT + set_name(scene, T))
    # The search found no state with lambda_j <= -margin; a force between that and 0 (a contact
    # that carries none, such as a wall beside a resting point, whose force is 0 up to rounding)
    # stays held.
    asm.add(Transition(src, term, guard=fns.force(j, margin), name=f"lift-off {cname}: {src} -> {term}"),
            SlotSpec(FORCE, j, margin), links.reset_spec())  # fmt: skip
    asm.pruned.append(f"  pruned: lift-off of {cname} in {src} -> {set_name(scene, T)}: {edge.text}")


def _report(scene: Scene, graph: ContactGraph, asm: Assembly, num_values: int, least_norm: bool) -> list:
    """The build report: the sets built, the achievable and pruned transitions, the sets never
    reached or never adjacent."""
    num_unilateral = sum(c.kind == UNILATERAL for c in scene.constraints)
    report = [
        f"contact sets built: {len(graph.states)} of 2^{num_unilateral} = {2**num_unilateral} "
        f"({', '.join(set_name(scene, A) for A in graph.states)})"
    ]
    for src, tgt, kind, cname, text in asm.achievable:
        report.append(f"  achievable: {kind} of {cname}: {src} -> {tgt}; {text}")
    report.extend(asm.pruned)
    for T in sorted(graph.unreached, key=lambda s: (len(s), sorted(s))):
        report.append(f"  pruned set {set_name(scene, T)}: no achievable transition into it was found")
    never = 2**num_unilateral - len(graph.states) - len(graph.unreached)
    if never > 0:
        report.append(
            f"  {never} other contact sets: not adjacent to a built set (no transition leads there)"
        )
    if num_values > 1:
        report.append(
            f"  built over {num_values} args values: a batch or a derivative across values "
            "that change the transitions found needs a system built over all of them"
        )
    if least_norm and graph.states:
        names = ", ".join(set_name(scene, A) for A in graph.states)
        report.append("  least-norm contact forces in: " + names)
    return report


def _assemble(scene: Scene, graph: ContactGraph, relabel_of: dict, least_norm: bool, margin: float,
              num_values: int, form: str) -> ContactSystem:  # fmt: skip
    """The system of a contact graph: a mode per set built, its transitions (in each mode, by
    constraint: impacts, then lift-offs), terminal modes, the report and the evaluation."""
    n, order = scene.dim, graph.states
    mode_fns = {A: _ModeFunctions(scene, tuple(sorted(A)), least_norm) for A in order}
    asm = Assembly(scene, [Mode(set_name(scene, A), mode_fns[A].flow, dim=2 * n, names=state_names(scene))
                           for A in order])  # fmt: skip
    relabel_maps = tuple(dict.fromkeys(m for _, m in relabel_of.values()))
    links = _Links(scene, relabel_of, relabel_maps, least_norm)
    for A in order:
        for (kind, j), edges in graph.leaving(A):
            if kind == "impact":
                _add_impacts(asm, links, A, j, edges)
            else:
                _add_lift_off(asm, links, mode_fns[A], A, j, edges[0], margin)
    asm.close()
    num_terminal = len(asm.terminals)
    evaluation = None
    if form == "mask":
        evaluation = ContactEvaluation(
            scene=scene,
            mode_sets=tuple(tuple(sorted(A)) for A in order) + (None,) * num_terminal,
            slots=asm.mode_slots(SlotSpec(CONSTANT, offset=-1.0)),
            resets=tuple(asm.resets),
            relabel_maps=relabel_maps,
            least_norm=least_norm,
        )
    return ContactSystem(
        asm.modes,
        asm.transitions,
        scene=scene,
        contact_sets=tuple(tuple(scene.constraints[i].name for i in sorted(A)) for A in order)
        + (None,) * num_terminal,
        least_norm_modes=(least_norm,) * len(order) + (False,) * num_terminal,
        report=tuple(_report(scene, graph, asm, num_values, least_norm)),
        achievable=tuple(asm.achievable),
        form=form,
        evaluation=evaluation,
    )
