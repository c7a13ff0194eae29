r"""Checks of a hybrid system's properties before running it, by sampling and local search.

The properties are those of A. M. Johnson, "Hybrid Dynamical Systems", section 3:

- achievable transitions, eq. (3): $G_{IJ} \cap D_I \neq \emptyset$;
- disjoint guards, eq. (6): $G_{IJ} \cap G_{IK} = \emptyset$; where two guards of one mode
  meet, the system is not deterministic (section 3.5) and hybridjax resolves the overlap by
  priority (the transition listed first wins, execution rule 4);
- guards covering the boundary where the flow leaves the domain, eq. (7): a point with
  $a_j = 0$, $a_j$ trending negative and no guard firing is where an execution blocks
  (section 3.4);
- resets into the target domain ($R_{IJ}(G_{IJ}) \subseteq D_J$, section 3.4), resets into
  another guard (allowed, section 3.7: reported as chains of zero-length epochs), and cycles
  of such zero-time transitions (chattering).

Each question is put to `find_point` (sampling, then local least squares) as equalities and
inequalities on the system's own functions; a point found is then judged by the simulator's
own rule for the start of an epoch (`start_decision` on the guard jets: what fires, what
blocks), so that a reported counterexample is one a simulation would meet. Sampling finds
counterexamples; it does not prove that there are none.
"""

import dataclasses
import html
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._analysis.search import SearchOptions, box_samples, search, search_options
from .._core.names import one_of
from .._definition.kernels import Kernels
from .._definition.system import HybridSystem
from .._definition.validation import domain_sizes
from .._rules.start import start_decision
from .._solve.simulator import Simulator

# Relations a query imposes on each watched function (guards, then domain components) of the
# mode it is about, or of the target mode after a reset. `STRICT` relations keep a `margin`
# away from zero, so that a point found satisfies the strict inequality it stands for.
_NONE, _EQ, _GE, _LE, _GT, _LT = 0, 1, 2, 3, 4, 5

CAVEAT = (
    "Sampling finds counterexamples; it does not prove their absence: a property reported as "
    "holding had no counterexample among the samples and their local refinements."
)


# ----------------------------------------------------------------------------- findings
@dataclasses.dataclass(frozen=True)
class Achievable:
    """Transition `transition` (I -> J): whether a point of $G_{IJ} \\cap D_I$ was found (eq. (3))."""

    transition: str
    source: str
    achievable: bool
    t: float
    state: np.ndarray | None


@dataclasses.dataclass(frozen=True)
class Overlap:
    """Guards of two transitions leaving `mode` meet at `state` (eq. (6) fails); `winner`, the one
    listed first in `HybridSystem.transitions`, fires there."""

    mode: str
    transitions: tuple[str, str]
    winner: str
    t: float
    state: np.ndarray


@dataclasses.dataclass(frozen=True)
class Gap:
    """A point of the boundary $a_j = 0$ of `mode`'s domain where the flow leaves it and no guard
    fires (eq. (7) fails): an execution reaching it ends `BLOCKED`."""

    mode: str
    component: int
    t: float
    state: np.ndarray


@dataclasses.dataclass(frozen=True)
class ResetOutside:
    """A state where `transition` fires whose reset `image` lies outside the target domain
    (component `component` of $a_J$ negative); `outcome` says what a simulation does there."""

    transition: str
    component: int
    t: float
    state: np.ndarray
    image: np.ndarray
    outcome: str


@dataclasses.dataclass(frozen=True)
class Chain:
    """Transitions firing one after another at one instant, from `state` where the first
    fires: `transitions` in order, `images` the state after each. `cyclic`: the chain
    returned to a (transition, state) it had already passed (chattering)."""

    transitions: tuple[str, ...]
    t: float
    state: np.ndarray
    images: tuple[np.ndarray, ...]
    cyclic: bool

    @property
    def length(self) -> int:
        return len(self.transitions)


@dataclasses.dataclass(frozen=True)
class PropertyReport:
    """The result of `check_properties`: one list per property, summaries as booleans, a table
    as its `repr` and as HTML in a notebook.

    A property "holds" here when no counterexample was found; sampling finds counterexamples,
    it does not prove their absence.
    """

    achievable: tuple[Achievable, ...]
    overlaps: tuple[Overlap, ...]
    gaps: tuple[Gap, ...]
    resets_outside: tuple[ResetOutside, ...]
    chains: tuple[Chain, ...]
    cycles: tuple[tuple[str, ...], ...]
    modes: tuple[str, ...]
    transitions: tuple[str, ...]
    num_samples: int
    t_bounds: tuple[float, float]

    @property
    def t_window(self) -> tuple[float, float]:
        """`t_bounds` under its other name."""
        return self.t_bounds

    @property
    def disjoint_guards(self) -> bool:
        """No two guards of one mode were found to meet (eq. (6))."""
        return not self.overlaps

    @property
    def deterministic(self) -> bool:
        """Disjoint guards: no state was found where two transitions could fire (section 3.5)."""
        return self.disjoint_guards

    @property
    def nonblocking(self) -> bool:
        """No boundary gap (eq. (7)) and no reset outside its target domain was found."""
        return not self.gaps and not self.resets_outside

    @property
    def achievable_transitions(self) -> tuple[str, ...]:
        """The transitions of the achievable set (eq. (3)) found, in the system's order."""
        return tuple(a.transition for a in self.achievable if a.achievable)

    @property
    def max_chain_length(self) -> int:
        """The longest chain of transitions at one instant found (1 when resets land in no guard)."""
        return max((c.length for c in self.chains), default=1)

    def _rows(self) -> list[tuple[str, str, str, str]]:
        rows = []
        for a in self.achievable:
            rows.append(
                (
                    "achievable (eq. 3)",
                    f"{a.transition} (from {a.source})",
                    "achievable" if a.achievable else "no point found",
                    _point(a.t, a.state),
                )
            )
        for o in self.overlaps:
            rows.append(
                (
                    "disjoint guards (eq. 6)",
                    f"{o.transitions[0]} & {o.transitions[1]}",
                    f"overlap; {o.winner} wins (listed first)",
                    _point(o.t, o.state),
                )
            )
        for g in self.gaps:
            rows.append(
                (
                    "guards cover boundary (eq. 7)",
                    f"{g.mode}, a[{g.component}] = 0",
                    "gap: leaves the domain in no guard (BLOCKED)",
                    _point(g.t, g.state),
                )
            )
        for r in self.resets_outside:
            rows.append(
                (
                    "reset into target domain",
                    r.transition,
                    f"image outside (a[{r.component}] < 0); {r.outcome}",
                    f"{_point(r.t, r.state)} -> {_fmt(r.image)}",
                )
            )
        for c in self.chains:
            verdict = "zero-time cycle (chattering)" if c.cyclic else f"reset into guard: chain of {c.length}"
            rows.append(
                (
                    "resets into guards (sec. 3.7)",
                    " -> ".join(c.transitions),
                    verdict,
                    f"{_point(c.t, c.state)} -> {_fmt(c.images[0])}",
                )
            )
        for cyc in self.cycles:
            rows.append(("zero-time cycles", " -> ".join(cyc + cyc[:1]), "cycle in the transition graph", ""))
        return rows

    def _summary(self) -> list[tuple[str, str]]:
        def yes(b):
            return "yes" if b else "NO"

        return [
            ("achievable transitions", f"{len(self.achievable_transitions)} of {len(self.transitions)}"),
            ("disjoint guards / deterministic", yes(self.disjoint_guards)),
            ("nonblocking", yes(self.nonblocking)),
            ("longest reset chain", str(self.max_chain_length)),
            ("zero-time cycles", str(len(self.cycles)) if self.cycles else "none"),
        ]

    def _header(self) -> str:
        lo, hi = self.t_bounds
        return (
            f"Property checks: {len(self.modes)} modes, {len(self.transitions)} transitions, "
            f"{self.num_samples} samples per mode, t in [{lo:g}, {hi:g}]."
        )

    def __repr__(self) -> str:
        lines = [self._header(), CAVEAT, ""]
        lines += [f"  {k:<32} {v}" for k, v in self._summary()]
        rows = self._rows()
        head = ("check", "where", "verdict", "witness (t, x)")
        widths = [max(len(r[i]) for r in rows + [head]) for i in range(4)]
        lines.append("")
        for r in [head, tuple("-" * w for w in widths)] + rows:
            lines.append("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip())
        return "\n".join(lines)

    def _repr_html_(self) -> str:
        esc = html.escape
        summary = "".join(f"<tr><td>{esc(k)}</td><td>{esc(v)}</td></tr>" for k, v in self._summary())
        rows = "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>" for r in self._rows())
        return (
            f"<div><p>{esc(self._header())}</p><p><em>{esc(CAVEAT)}</em></p>"
            f"<table><tbody>{summary}</tbody></table>"
            "<table><thead><tr><th>check</th><th>where</th><th>verdict</th><th>witness (t, x)</th>"
            f"</tr></thead><tbody>{rows}</tbody></table></div>"
        )


def _fmt(x) -> str:
    return "[" + ", ".join(f"{v:.6g}" for v in np.asarray(x)) + "]"


def _point(t, x) -> str:
    return "" if x is None else f"t={t:.6g}, x={_fmt(x)}"


# ----------------------------------------------------------------------------- queries
class _Queries:
    """A batch of point searches, each as relations on the watched functions of a mode (the
    "pre" frame) and optionally of the target mode after a transition's reset ("post")."""

    def __init__(self, num_watch: int):
        self.num_watch = num_watch
        self.rows: list[tuple] = []
        self.tags: list[tuple] = []

    def add(self, tag, mode, trans=-1, pre=(), pre_lie=(), post=(), post_lie=()):
        def codes(pairs):
            c = np.zeros(self.num_watch, np.int32)
            for w, rel in pairs:
                c[w] = rel
            return c

        self.rows.append((mode, trans, codes(pre), codes(pre_lie), codes(post), codes(post_lie)))
        self.tags.append(tag)

    def arrays(self):
        cols = list(zip(*self.rows, strict=True))
        return tuple(
            jnp.asarray(np.stack(c) if i >= 2 else np.array(c, np.int32)) for i, c in enumerate(cols)
        )


def _relations(codes, values, margin):
    """(equalities, inequalities) that the codes impose on the values; unused entries read 0
    (an equality met) and 1 (an inequality met)."""
    eq = jnp.where(codes == _EQ, values, 0.0)
    ineq = jnp.select(
        [codes == _GE, codes == _LE, codes == _GT, codes == _LT],
        [values, -values, values - margin, -values - margin],
        jnp.ones_like(values),
    )
    return eq, ineq


def _frame(kern: Kernels, mode, t, y, args):
    """The watched values of `mode` at (t, y) and their Lie derivatives along its flow,
    L1 = D_t w + D_x w F (as `Kernels.guard_jets`)."""
    F = kern.flow(mode, t, y, args)
    return jax.jvp(lambda t_, y_: kern.guards(mode, t_, y_, args), (t, y), (jnp.ones_like(t), F))


@eqx.filter_jit
def _search_batch(system, queries, ts, xs, args, margin, t_bounds, tol, num_starts, iterations):
    """Every query's `find_point`, vmapped; `ts` (M, N), `xs` (M, N, max_dim) per mode."""
    kern = Kernels(system, args)
    has_reset = system.num_transitions > 0

    def constraints(t, y, q):
        mode, trans, pre, pre_lie, post, post_lie = q
        W, L1 = _frame(kern, mode, t, y, args)
        eqs, ineqs = _relations(pre, W, margin)
        parts_eq, parts_in = [eqs], [ineqs, _relations(pre_lie, L1, margin)[1]]
        if has_reset:
            k = jnp.maximum(trans, 0)
            yp = kern.reset(k, t, y, args)
            Wp, L1p = _frame(kern, kern.targets[k], t, yp, args)
            eqs, ineqs = _relations(post, Wp, margin)
            parts_eq.append(eqs)
            parts_in += [ineqs, _relations(post_lie, L1p, margin)[1]]
        return jnp.concatenate(parts_eq), jnp.concatenate(parts_in)

    def one(q):
        mode = q[0]
        return search(
            constraints,
            ts[mode],
            xs[mode],
            q,
            t_bounds=t_bounds,
            tol=tol,
            num_starts=num_starts,
            iterations=iterations,
        )

    return jax.vmap(one)(queries)


@eqx.filter_jit
def _start_fire(system, mode, t, y, args, rtol, atol):
    """Which watched functions fire at (t, y) in `mode` by the simulator's start-of-epoch rule
    (execution rule 3: strictly inside, or within the tolerance band and trending negative)."""
    kern = Kernels(system, args)
    jets = kern.guard_jets(mode, t, y, args, rtol, atol, jnp.zeros_like(t))
    fire, _ = start_decision(jets, kern.outgoing_mask(mode), jnp.finfo(y.dtype).eps)
    return fire


@eqx.filter_jit
def _reset(system, k, t, y, args):
    return Kernels(system, args).reset(k, t, y, args)


# ----------------------------------------------------------------------------- samples
def _mode_samples(system, bounds, key, num, dtype):
    """(M, N, max_dim) samples per mode, zero-padded, from `bounds[mode]`: a (lower, upper)
    box or a sampler `(key, num) -> (num, dim)`."""
    if not isinstance(bounds, Mapping):
        raise TypeError(
            "check_properties: `bounds` must map each mode name to (lower, upper) or a "
            "sampler (key, num) -> (num, dim)."
        )
    unknown = set(bounds) - set(system.mode_names) - set(range(system.num_modes))
    if unknown:
        raise ValueError(
            f"check_properties: `bounds` names unknown modes {sorted(map(str, unknown))}; "
            f"known modes: {list(system.mode_names)}."
        )
    out = []
    for i, (m, k) in enumerate(zip(system.modes, jax.random.split(key, system.num_modes), strict=True)):
        spec = bounds.get(m.name, bounds.get(i))
        if spec is None:
            raise ValueError(
                f"check_properties: no sampling bounds for mode '{m.name}'; give "
                f"bounds['{m.name}'] = (lower, upper) or a sampler."
            )
        if callable(spec):
            xs = jnp.asarray(spec(k, num), dtype)
        else:
            lo, hi = (jnp.broadcast_to(jnp.asarray(v, dtype), (m.dim,)) for v in spec)
            xs = box_samples(k, (lo, hi), num)
        if xs.shape != (num, m.dim):
            raise ValueError(
                f"check_properties: samples of mode '{m.name}' have shape {xs.shape}; "
                f"expected ({num}, {m.dim})."
            )
        out.append(jnp.pad(xs, ((0, 0), (0, system.max_dim - m.dim))))
    return jnp.stack(out)


# ----------------------------------------------------------------------------- the checks
def _watch_index(system, args, dtype):
    """Index of domain component (mode, j) among the watched functions (after the K guards)."""
    sizes = domain_sizes(system, args, dtype)
    index, w = {}, system.num_transitions
    for i, m_i in enumerate(sizes):
        for j in range(m_i):
            index[i, j] = w
            w += 1
    return sizes, index, w


def _domain(sizes, index, mode, rel=_GE, skip=None):
    return [(index[mode, j], rel) for j in range(sizes[mode]) if j != skip]


def _entry(system, sizes, index, k):
    """The states where the flow of the source mode enters guard k: g_k = 0, dg_k/dt < 0, in D_I."""
    src = system.sources[k]
    return dict(pre=[(k, _EQ)] + _domain(sizes, index, src), pre_lie=[(k, _LT)])


def _build_queries(system, sizes, index, num_watch) -> _Queries:
    Q = _Queries(num_watch)
    K = system.num_transitions
    for k in range(K):
        i = system.sources[k]
        Q.add(("achievable", k), i, pre=[(k, _LE)] + _domain(sizes, index, i))
    for i in range(system.num_modes):
        out = system.outgoing(i)
        for a, k in enumerate(out):
            for k2 in out[a + 1 :]:
                Q.add(("overlap", k, k2), i, pre=[(k, _LE), (k2, _LE)] + _domain(sizes, index, i))
        for j in range(sizes[i]):
            pre = [(index[i, j], _EQ)] + _domain(sizes, index, i, skip=j) + [(k, _GT) for k in out]
            Q.add(("gap", i, j), i, pre=pre, pre_lie=[(index[i, j], _LT)])
    for k in range(K):
        J = system.targets[k]
        entry = _entry(system, sizes, index, k)
        for j in range(sizes[J]):
            Q.add(("outside", k, j), system.sources[k], k, post=[(index[J, j], _LT)], **entry)
        for k2 in system.outgoing(J):
            Q.add(("into", k, k2), system.sources[k], k, post=[(k2, _LT)], **entry)
            Q.add(("into", k, k2), system.sources[k], k, post=[(k2, _EQ)], post_lie=[(k2, _LT)], **entry)
    return Q


def _first_firing(fire: np.ndarray) -> int | None:
    """The simulator's choice at a start of epoch (as `Loop.start_stage`): the first firing
    watched function, a transition if < K, else a domain component (BLOCKED); None if none."""
    return int(np.argmax(fire)) if fire.any() else None


def _follow(system, k, t, y, args, rtol, atol, max_chain):
    """From a state where transition k fires, apply resets while the simulator's start rule
    fires another transition at once. Returns (transitions, images, cyclic)."""
    K = system.num_transitions
    trans, images, seen = [], [], []
    while True:
        y = _reset(system, jnp.int32(k), t, y, args)
        trans.append(k)
        images.append(np.asarray(y)[: system.modes[system.targets[k]].dim])
        key = (k, tuple(np.round(np.asarray(y), 9)))
        if key in seen or len(trans) > max_chain:
            return trans, images, True
        seen.append(key)
        fire = np.asarray(_start_fire(system, jnp.int32(system.targets[k]), t, y, args, rtol, atol))
        nxt = _first_firing(fire)
        if nxt is None or nxt >= K:
            return trans, images, False
        k = nxt


def _simple_cycles(edges: dict[int, set[int]]) -> list[tuple[int, ...]]:
    """Elementary cycles of a small directed graph, each once, starting at its least node."""
    cycles = []

    def walk(start, node, path, on_path):
        for nxt in sorted(edges.get(node, ())):
            if nxt == start:
                cycles.append(tuple(path))
            elif nxt > start and nxt not in on_path:
                walk(start, nxt, path + [nxt], on_path | {nxt})

    for s in sorted(edges):
        walk(s, s, [s], {s})
    return cycles


def _start_tolerances(simulator, rtol, atol, dtype) -> tuple[Any, Any]:
    """The `rtol`, `atol` of the start rule's band: those of `simulator`'s step-size controller
    (a controller without them: sqrt(eps), as the simulation loop takes), or the shorthands
    `rtol`, `atol` (1e-8 each where not given)."""
    given = [name for name, value in (("rtol", rtol), ("atol", atol)) if value is not None]
    if simulator is None:
        return (1e-8 if rtol is None else rtol), (1e-8 if atol is None else atol)
    if not isinstance(simulator, Simulator):
        raise TypeError("check_properties: simulator must be an hj.Simulator, got "
                        f"{type(simulator).__name__}.")
    if given:
        raise ValueError(f"check_properties: simulator and {' and '.join(given)} are the same option (the "
                         "tolerances of the simulator's step-size controller); pass one of them.")
    controller = simulator.stepsize_controller
    if controller is None:  # simulate's default controller for `dtype`
        tol = 1e-8 if dtype == jnp.float64 else 1e-5
        return tol, tol
    eps = float(jnp.finfo(dtype).eps) ** 0.5
    rtol, atol = getattr(controller, "rtol", None), getattr(controller, "atol", None)
    return (eps if rtol is None else rtol), (eps if atol is None else atol)


def check_properties(
    system: HybridSystem,
    args: Any = None,
    *,
    bounds: Mapping,
    t_bounds: tuple[float, float] | None = None,
    num_samples: int = 256,
    key: Any = None,
    margin: float = 1e-6,
    max_chain: int = 16,
    simulator: Simulator | None = None,
    search: SearchOptions | None = None,
    **shorthands,
) -> PropertyReport:
    r"""Check a hybrid system's properties (A. M. Johnson, "Hybrid Dynamical Systems", section 3)
    by sampling each mode's states and searching locally for counterexamples.

    For every transition $k = (I, J)$ and mode $I$, with guards $G_k = \{g_k \le 0\}$ and
    domains $D_I = \{a_I \ge 0\}$:

    - **achievable** (eq. (3)): a point of $G_k \cap D_I$;
    - **disjoint guards** (eq. (6)), **deterministic** (section 3.5): a point of
      $G_k \cap G_l \cap D_I$ for two transitions leaving $I$; the one listed first wins there
      (execution rule 4);
    - **guards cover the boundary** (eq. (7)): a point with $a_{I,j} = 0$, $\dot a_{I,j} < 0$
      (the flow leaves), every other $a_I \ge 0$ and every guard of $I$ at least `margin`
      above 0; kept only where the simulator's start rule would block there;
    - **reset into the target domain** (section 3.4): a state where the flow enters $G_k$
      ($g_k = 0$, $\dot g_k < 0$, in $D_I$) whose image $R_k$ has some $a_{J,j} < 0$;
    - **resets into guards** (section 3.7): from such a state, an image inside a guard of $J$
      (strictly, or on it and trending negative); the chain of transitions that then fire at
      the same instant is followed with the simulator's start rule, and the transition graph
      of these zero-time steps is searched for **cycles** (chattering).

    Every search is batched with `jax.vmap` and compiled once per system (repeated calls with
    new `args`, bounds or samples reuse it).

    **What it can and cannot prove.** Sampling finds counterexamples; it does not prove their
    absence. A transition reported achievable, an overlap, a gap, a reset outside its
    domain, a chain or a cycle comes with a witness state that shows it. A property reported
    as holding only means that no sample, and no local refinement of the best samples, was a
    counterexample: a small or distant counterexample can be missed. The samples cover only
    the `bounds` given and `t_bounds`; tangential exits (first derivative zero, a higher one
    negative) are not searched.

    **Arguments:**

    - `system`, `args`: the system and the `args` its functions take.
    - `bounds`: per mode (name or index), `(lower, upper)` (scalars or `(dim,)` arrays) for
      uniform samples in that box, or a sampler `(key, num) -> (num, dim)`.
    - `t_bounds`: `(t0, t1)`: times are sampled and searched in it (time-varying guards,
      domains and flows), as in `find_point`; the default `(0, 0)` fixes t = 0.
    - `num_samples`: samples per mode; `key`: a `jax.random` key (default `key(0)`).
    - `margin`: how far a strict inequality must hold (a guard "not containing" a point has
      $g \ge$ `margin`; a flow "leaving" has $\dot a \le -$`margin`).
    - `max_chain`: chains longer than this are reported as cycles.
    - `simulator`: the `hj.Simulator` whose executions the report is about: the `rtol`, `atol`
      of its step-size controller set the band within which the simulator's start rule treats
      a guard as touched (as in `simulate`; a controller without tolerances: $\sqrt{\epsilon}$).
      Default: a `PIDController(rtol=1e-8, atol=1e-8)`.
    - `search`: an `hj.SearchOptions` (`num_starts`, `iterations`, `tol`), how each search
      refines its best samples, as in `find_point`. The defaults of its `tol` and of `margin`
      assume float64 (`jax_enable_x64`).

    **Keyword shorthands** (passing one with the name it stands for is a `ValueError`):

    - `rtol`, `atol`: `simulator=hj.Simulator(stepsize_controller=diffrax.PIDController(rtol=rtol,
      atol=atol))` (each 1e-8 where not given).
    - `num_starts`, `iterations` (or `max_steps`, optimistix's name), `tol`:
      `search=hj.SearchOptions(...)` with them.
    - `t_window`: `t_bounds`.

    Returns a `PropertyReport` (a table as its `repr`, HTML in a notebook).

    !!! Example

        ```python
        args = {"a": 0.5, "T_amb": 10.0, "P_heat": 15.0, "P_cool": 10.0, "s": 20.0}
        bounds = {"off": (5.0, 35.0), "heat": (5.0, 35.0), "cool": (5.0, 35.0)}
        report = hj.check_properties(hj.examples.thermostat(), args, bounds=bounds)
        report.nonblocking, report.disjoint_guards  # True, True
        report  # a table: each transition achievable at its threshold
        ```
    """
    search = search_options("check_properties", search, shorthands)
    unknown = sorted(set(shorthands) - {"rtol", "atol", "t_window"})
    if unknown:
        raise TypeError(f"check_properties() got an unexpected keyword argument {unknown[0]!r}.")
    dtype = jnp.result_type(float)
    rtol, atol = _start_tolerances(simulator, shorthands.get("rtol"), shorthands.get("atol"), dtype)
    key = jax.random.key(0) if key is None else key
    # Python floats in `args` become arrays, so that new values reuse the compiled searches.
    args = jax.tree.map(lambda v: jnp.asarray(v, dtype) if isinstance(v, float) else v, args)
    sizes, index, num_watch = _watch_index(system, args, dtype)
    K = system.num_transitions
    k_t, k_x = jax.random.split(key)
    xs = _mode_samples(system, bounds, k_x, num_samples, dtype)
    t_bounds = one_of("check_properties", t_bounds=t_bounds, t_window=shorthands.get("t_window"),
                      default=(0.0, 0.0))
    lo, hi = float(t_bounds[0]), float(t_bounds[1])
    if hi < lo:
        raise ValueError(f"check_properties: t_bounds {t_bounds} must have t0 <= t1.")
    ts = (
        jax.random.uniform(k_t, xs.shape[:2], dtype, lo, hi) if hi > lo else jnp.full(xs.shape[:2], lo, dtype)
    )
    t_bounds = (jnp.asarray(lo, dtype), jnp.asarray(hi, dtype)) if hi > lo else None
    Q = _build_queries(system, sizes, index, num_watch)
    labels = tuple(tr.label for tr in system.transitions)
    names = system.mode_names
    if Q.rows:
        w = _search_batch(
            system, Q.arrays(), ts, xs, args, jnp.asarray(margin, dtype), t_bounds, search.tol,
            search.num_starts, search.iterations,
        )
        found, wt, wx = np.asarray(w.found), np.asarray(w.t), np.asarray(w.x)
    else:
        found = np.zeros(0, bool)

    def state(q, mode):
        return wx[q][: system.modes[mode].dim]

    def fire_at(mode, t, y):
        return np.asarray(
            _start_fire(system, jnp.int32(mode), jnp.asarray(t), jnp.asarray(y), args, rtol, atol)
        )

    achievable, overlaps, gaps, outside, chains = [], [], [], [], []
    edges: dict[int, set[int]] = {}
    chain_seen = set()
    for q, tag in enumerate(Q.tags):
        kind = tag[0]
        if kind == "achievable":
            k = tag[1]
            i = system.sources[k]
            achievable.append(
                Achievable(
                    labels[k], names[i], bool(found[q]), float(wt[q]), state(q, i) if found[q] else None
                )
            )
        elif not found[q]:
            continue
        elif kind == "overlap":
            _, k, k2 = tag
            i = system.sources[k]
            overlaps.append(
                Overlap(names[i], (labels[k], labels[k2]), labels[min(k, k2)], float(wt[q]), state(q, i))
            )
        elif kind == "gap":
            _, i, j = tag
            first = _first_firing(fire_at(i, wt[q], wx[q]))
            if first is not None and first >= K:
                gaps.append(Gap(names[i], j, float(wt[q]), state(q, i)))
        else:
            k = tag[1]
            J = system.targets[k]
            y = _reset(system, jnp.int32(k), jnp.asarray(wt[q]), jnp.asarray(wx[q]), args)
            image = np.asarray(y)[: system.modes[J].dim]
            first = _first_firing(fire_at(J, wt[q], y))
            if kind == "outside":
                outcome = "BLOCKED" if first is None or first >= K else f"{labels[first]} fires first"
                outside.append(
                    ResetOutside(labels[k], tag[2], float(wt[q]), state(q, system.sources[k]), image, outcome)
                )
            elif first is not None and first < K:
                edges.setdefault(k, set()).add(first)
                trans, images, cyclic = _follow(
                    system, k, jnp.asarray(wt[q]), jnp.asarray(wx[q]), args, rtol, atol, max_chain
                )
                for a, b in zip(trans, trans[1:], strict=False):
                    edges.setdefault(a, set()).add(b)
                if tuple(trans) in chain_seen:
                    continue
                chain_seen.add(tuple(trans))
                chains.append(
                    Chain(
                        tuple(labels[c] for c in trans),
                        float(wt[q]),
                        state(q, system.sources[k]),
                        tuple(images),
                        cyclic,
                    )
                )
    cycles = tuple(tuple(labels[c] for c in cyc) for cyc in _simple_cycles(edges))
    return PropertyReport(
        achievable=tuple(achievable),
        overlaps=tuple(overlaps),
        gaps=tuple(gaps),
        resets_outside=tuple(outside),
        chains=tuple(chains),
        cycles=cycles,
        modes=names,
        transitions=labels,
        num_samples=num_samples,
        t_bounds=(lo, hi),
    )
