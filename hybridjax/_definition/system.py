"""Definition of a hybrid dynamical system H = (J, Gamma, D, F, G, R).

Notation follows A. M. Johnson, S. E. Burden, D. E. Koditschek, "A hybrid systems model for
simple manipulation and self-manipulation systems", IJRR 35(11), 2016: modes J, transitions
Gamma (directed edges), domains D_I = {a_I >= 0}, flows F_I, guards G_IJ = {g_IJ <= 0} and
resets R_IJ : G_IJ -> D_J.
"""

import abc
import html
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._definition.indexed import ModeIndexed
from .._definition.validation import check_function_shapes


def _identity_reset(t, x, args):
    del t, args
    return x


def _names_tuple(names):
    # A list of names is accepted as a tuple (a static field must be hashable); anything else is
    # left as given for `Mode.__check_init__` to reject with the mode's name.
    return tuple(names) if isinstance(names, list) else names


class Mode(eqx.Module):
    """A discrete mode I: its flow F_I, its state dimension n_I and optionally its domain.

    Within mode I the continuous state obeys dx/dt = F_I(t, x, args), x in R^{n_I}.

    **Arguments:**

    - `name`: a unique name; transitions and `simulate(mode0=...)` may use it.
    - `flow`: `flow(t, x, args) -> dx/dt`, diffrax's `(t, y, args)` convention, returning an
      array of shape `(dim,)`.
    - `dim`: the state dimension n_I of this mode. Modes may differ in dimension (the domains
      form a disjoint union); the solver carries a zero-padded state and every user function
      sees exactly its own mode's `dim` components.
    - `domain`: optional `domain(t, x, args) -> a` (a scalar or 1-D array), D_I = {a >= 0}.
    - `names`: optional names of the `dim` state components (a tuple of strings), used in
      plot labels; `component_names` gives `("x[0]", "x[1]", ...)` when they are not given.

    !!! Example

        ```python
        flight = hj.Mode("flight", lambda t, x, args: jnp.array([x[1], -args["g"]]), dim=2,
                         names=("h", "v"))
        flight.component_names  # ("h", "v")
        ```
    """

    name: str = eqx.field(static=True)
    flow: Callable
    dim: int = eqx.field(static=True)
    domain: Callable | None = None
    names: tuple[str, ...] | None = eqx.field(static=True, default=None, converter=_names_tuple)

    def __check_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"Mode name must be a non-empty string, got {self.name!r}.")
        if not callable(self.flow):
            raise TypeError(f"Mode '{self.name}': `flow` must be callable, got {self.flow!r}.")
        if self.domain is not None and not callable(self.domain):
            raise TypeError(f"Mode '{self.name}': `domain` must be callable or None.")
        if isinstance(self.dim, bool) or not isinstance(self.dim, (int, np.integer)) or self.dim < 1:
            raise ValueError(f"Mode '{self.name}': `dim` must be a positive int, got {self.dim!r}.")
        if self.names is not None:
            if not isinstance(self.names, tuple) or not all(
                isinstance(c, str) and c for c in self.names
            ):
                raise TypeError(
                    f"Mode '{self.name}': `names` must be a tuple of non-empty strings, one per "
                    f"state component, got {self.names!r}."
                )
            if len(self.names) != self.dim:
                raise ValueError(
                    f"Mode '{self.name}': `names` has {len(self.names)} entries but `dim` is "
                    f"{self.dim}; give one name per state component."
                )

    @property
    def component_names(self) -> tuple[str, ...]:
        """The names of the state components: `names`, or `("x[0]", "x[1]", ...)` without them."""
        return self.names if self.names is not None else tuple(f"x[{i}]" for i in range(self.dim))


class Transition(eqx.Module):
    """A discrete transition (I, J) in Gamma, with its guard g_IJ and reset R_IJ.

    The transition fires when the flow of mode I enters the guard set
    G_IJ = {x : g_IJ(t, x, args) <= 0}; the state then jumps to x+ = R_IJ(t, x-, args) in
    mode J.

    **Arguments:**

    - `source`, `target`: mode names (or indices into `HybridSystem.modes`).
    - `guard`: `guard(t, x, args) -> scalar`, evaluated on a state of `source` (shape
      `(n_I,)`).
    - `reset`: `reset(t, x, args) -> x+` mapping a state of `source` (`(n_I,)`) to one of
      `target` (`(n_J,)`). Defaults to the identity (which requires n_I == n_J).
    - `name`: optional label used in messages and plots; defaults to `"source->target"`.

    Several transitions may leave one mode; their order in `HybridSystem.transitions` is
    their priority when guards are reached at the same instant.

    !!! Example

        ```python
        bounce = hj.Transition(
            "flight", "flight",
            guard=lambda t, x, args: x[0],
            reset=lambda t, x, args: jnp.array([x[0], -args["e"] * x[1]]),
        )
        ```
    """

    source: str | int = eqx.field(static=True)
    target: str | int = eqx.field(static=True)
    guard: Callable
    reset: Callable = _identity_reset
    name: str | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        for role in ("source", "target"):
            ref = getattr(self, role)
            if isinstance(ref, bool) or not isinstance(ref, (str, int, np.integer)):
                raise TypeError(
                    f"Transition {self.label}: `{role}` must be a mode name or index, got {ref!r}."
                )
        if not callable(self.guard):
            raise TypeError(f"Transition {self.label}: `guard` must be callable.")
        if not callable(self.reset):
            raise TypeError(f"Transition {self.label}: `reset` must be callable.")

    @property
    def label(self) -> str:
        return self.name if self.name is not None else f"{self.source}->{self.target}"


class ZenoCompletion(eqx.Module):
    """A completion of Zeno executions in mode `source` (Ames et al., "Is there life after Zeno?").

    When event times accumulate in `source` (a Zeno execution, detected by `simulate`), the
    execution jumps to the extrapolated Zeno limit (t_inf, x_inf) and continues in `target`
    from `reset(t_inf, x_inf, args)`. A bouncing ball, for example, comes to rest:

    ```python
    rest = hj.ZenoCompletion("flight", "rest", reset=lambda t, x, args: x[:1] * 0.0)
    ```
    """

    source: str | int = eqx.field(static=True)
    target: str | int = eqx.field(static=True)
    reset: Callable = _identity_reset

    @property
    def label(self) -> str:
        return f"zeno:{self.source}->{self.target}"


def _indices(system, edges, role: str) -> tuple[int, ...]:
    """The mode index of each edge's `role` ("source" or "target"), given by name or index."""
    index = {m.name: i for i, m in enumerate(system.modes)}
    return tuple(index[e_ref] if isinstance(e_ref := getattr(e, role), str) else int(e_ref) for e in edges)


class AbstractHybridSystem(eqx.Module):
    r"""The interface of a hybrid system H = (J, Gamma, D, F, G, R) that the engines and every
    tool read (A. M. Johnson, "Hybrid Dynamical Systems", eq. (1)): its modes $J$ with their
    flows $F_I$ and domains $D_I$ (`Mode`), its edges $\Gamma$ with guards $G_{IJ}$ and resets
    $R_{IJ}$ (`Transition`), and optional Zeno completions.

    A subclass gives three attributes and one method; everything else (mode and transition
    lookups, the source and target indices of each edge, the shape checks) is derived here:

    - `modes`: a tuple of `Mode`, names unique;
    - `transitions`: a tuple of `Transition` (a transition's index is its position, also its
      priority among those leaving one mode); sources and targets by mode name or index;
    - `completions`: a tuple of `ZenoCompletion` (often `()`);
    - `mode_indexed()`: the system's evaluation for a traced mode index (a `ModeIndexed`), or
      `None` to have the engines evaluate each mode's and transition's own functions.

    `HybridSystem` is the general implementation (it validates everything at construction);
    `ContactSystem` the one `contact_system` builds from a `Scene`. A subclass of this class
    is simulated by `simulate` like either; `simulate` runs the shape checks with the real `args`.

    !!! Example

        ```python
        class Ball(hj.AbstractHybridSystem):
            modes: tuple = (hj.Mode("flight", lambda t, x, a: jnp.stack([x[1], -a["g"] + 0 * x[0]]), 2),)
            transitions: tuple = (
                hj.Transition("flight", "flight", guard=lambda t, x, a: x[0],
                              reset=lambda t, x, a: jnp.stack([x[0], -a["e"] * x[1]])),
            )
            completions: tuple = ()

            def mode_indexed(self):
                return None
        ```
    """

    modes: eqx.AbstractVar[tuple[Mode, ...]]
    transitions: eqx.AbstractVar[tuple[Transition, ...]]
    completions: eqx.AbstractVar[tuple[ZenoCompletion, ...]]

    @abc.abstractmethod
    def mode_indexed(self) -> "ModeIndexed | None":
        """The system's evaluation for a traced mode index (`ModeIndexed`), or None: the engines
        then evaluate the modes' and transitions' own functions branch by branch."""

    # ------------------------------------------------------------------ edges by index
    @property
    def sources(self) -> tuple[int, ...]:
        """The source mode index of each transition."""
        return _indices(self, self.transitions, "source")

    @property
    def targets(self) -> tuple[int, ...]:
        """The target mode index of each transition."""
        return _indices(self, self.transitions, "target")

    @property
    def completion_sources(self) -> tuple[int, ...]:
        return _indices(self, self.completions, "source")

    @property
    def completion_targets(self) -> tuple[int, ...]:
        return _indices(self, self.completions, "target")

    # ------------------------------------------------------------------ lookups
    @property
    def num_modes(self) -> int:
        return len(self.modes)

    @property
    def num_transitions(self) -> int:
        return len(self.transitions)

    @property
    def max_dim(self) -> int:
        """The padded state dimension max_I n_I that the solver carries."""
        return max(m.dim for m in self.modes)

    @property
    def mode_names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.modes)

    def mode_index(self, mode: str | int) -> int:
        """The index of a mode given by name or index (a Python value, not a tracer)."""
        if isinstance(mode, str):
            try:
                return self.mode_names.index(mode)
            except ValueError:
                raise ValueError(
                    f"Unknown mode '{mode}'; known modes: {list(self.mode_names)}."
                ) from None
        i = int(mode)
        if not 0 <= i < self.num_modes:
            raise ValueError(f"Mode index {i} out of range for {self.num_modes} modes.")
        return i

    def transition_index(self, transition: "Transition | int") -> int:
        """The index of a transition given as the object or its index."""
        if isinstance(transition, Transition):
            for k, tr in enumerate(self.transitions):
                if tr is transition:
                    return k
            for k, tr in enumerate(self.transitions):
                if tr == transition:
                    return k
            raise ValueError(f"Transition {transition.label} is not part of this system.")
        k = int(transition)
        if not 0 <= k < self.num_transitions:
            raise ValueError(
                f"Transition index {k} out of range for {self.num_transitions} transitions."
            )
        return k

    def jumps(self):
        """(name, reset, source, target) of every transition, then every Zeno completion."""
        for k, tr in enumerate(self.transitions):
            yield f"Transition {k} ({tr.label})", tr.reset, self.sources[k], self.targets[k]
        for c, comp in enumerate(self.completions):
            yield (f"Completion {c} ({comp.label})", comp.reset, self.completion_sources[c],
                   self.completion_targets[c])

    def completion_of(self, mode: int) -> int:
        """Index of the ZenoCompletion leaving `mode`, or -1."""
        return self.completion_sources.index(mode) if mode in self.completion_sources else -1

    def outgoing(self, mode: int) -> tuple[int, ...]:
        """Indices of the transitions leaving `mode`, in priority order."""
        return tuple(k for k, s in enumerate(self.sources) if s == mode)

    def check(self, args: Any = None, dtype: Any = None) -> None:
        """Run the shape checks with these `args` (raises ValueError naming the culprit).

        Shapes only: `hj.check_properties` searches for blocking, overlapping guards and resets
        into guards."""
        check_function_shapes(
            self, args, dtype=jnp.result_type(float) if dtype is None else dtype, strict=True
        )

    def _repr_html_(self) -> str:
        esc = html.escape
        modes = "".join(
            f"<tr><td>{i}</td><td>{esc(m.name)}</td><td>{m.dim}</td>"
            f"<td>{'yes' if m.domain is not None else ''}</td>"
            f"<td>{', '.join(esc(self.transitions[k].label) for k in self.outgoing(i))}</td></tr>"
            for i, m in enumerate(self.modes)
        )
        trans = "".join(
            f"<tr><td>{k}</td><td>{esc(tr.label)}</td><td>{esc(self.modes[self.sources[k]].name)}</td>"
            f"<td>{esc(self.modes[self.targets[k]].name)}</td></tr>"
            for k, tr in enumerate(self.transitions)
        )
        comps = "".join(
            f"<tr><td>zeno {c}</td><td>{esc(comp.label)}</td>"
            f"<td>{esc(self.modes[self.completion_sources[c]].name)}</td>"
            f"<td>{esc(self.modes[self.completion_targets[c]].name)}</td></tr>"
            for c, comp in enumerate(self.completions)
        )
        return (
            f"<div><b>HybridSystem</b>: {self.num_modes} modes, {self.num_transitions} transitions"
            "<table><tr><th>mode</th><th>name</th><th>dim</th><th>domain</th><th>leaving</th></tr>"
            f"{modes}</table><table><tr><th>transition</th><th>name</th><th>source</th>"
            f"<th>target</th></tr>{trans}{comps}</table></div>"
        )

    def __repr__(self) -> str:
        lines = [f"HybridSystem({self.num_modes} modes, {self.num_transitions} transitions)"]
        for i, m in enumerate(self.modes):
            dom = ", domain" if m.domain is not None else ""
            lines.append(f"  mode {i} '{m.name}': dim {m.dim}{dom}")
        for k, tr in enumerate(self.transitions):
            src, tgt = self.modes[self.sources[k]].name, self.modes[self.targets[k]].name
            lines.append(f"  transition {k} '{tr.label}': {src} -> {tgt}")
        return "\n".join(lines)


class HybridSystem(AbstractHybridSystem):
    """A hybrid dynamical system H = (J, Gamma, D, F, G, R): modes and the transitions between them.

    Validation happens here, at construction: unknown or duplicate mode names, and, by
    abstract evaluation (`jax.eval_shape`, no real call), the flow output shape, scalar
    guards, scalar-or-vector domains and reset output dimensions. Errors name the mode or
    transition at fault. Shape checks that need `args` (a flow reading `args["g"]`, say) are
    repeated by `simulate` with the real `args`; pass `example_args` to run them here.

    **Arguments:**

    - `modes`: a sequence of `Mode`, names unique.
    - `transitions`: a sequence of `Transition`; a transition's index is its position here,
      which is also its priority among transitions leaving the same mode.
    - `completions`: optional `ZenoCompletion`s, at most one per source mode: what a Zeno
      execution in that mode does at its accumulation point (otherwise it stops with `ZENO`).
    - `example_args`: optional `args` pytree used only for the shape checks.

    `system.modes` and `system.transitions` are the tuples given, in order.
    """

    modes: tuple[Mode, ...]
    transitions: tuple[Transition, ...]
    completions: tuple[ZenoCompletion, ...]

    def __init__(
        self,
        modes: Sequence[Mode],
        transitions: Sequence[Transition] = (),
        *,
        completions: Sequence[ZenoCompletion] = (),
        example_args: Any = None,
    ):
        self.modes = tuple(modes)
        self.transitions = tuple(transitions)
        self.completions = tuple(completions)
        validate_system(self, example_args)

    def mode_indexed(self) -> None:
        """None: the engines evaluate each mode's and transition's own functions."""
        return None


def validate_system(system: AbstractHybridSystem, example_args: Any = None) -> None:
    """The construction-time checks of a system: modes and transitions of the right types,
    unique mode names, sources and targets that exist, at most one Zeno completion per mode,
    and (by abstract evaluation) the functions' shapes; errors name the mode or transition."""
    modes, transitions, completions = system.modes, system.transitions, system.completions
    if len(modes) == 0:
        raise ValueError("A HybridSystem needs at least one Mode.")
    for i, m in enumerate(modes):
        if not isinstance(m, Mode):
            raise TypeError(f"modes[{i}] is {type(m).__name__}, expected hybridjax.Mode.")
    for k, tr in enumerate(transitions):
        if not isinstance(tr, Transition):
            raise TypeError(
                f"transitions[{k}] is {type(tr).__name__}, expected hybridjax.Transition."
            )
    index: dict[str, int] = {}
    for i, m in enumerate(modes):
        if m.name in index:
            raise ValueError(
                f"Duplicate mode name '{m.name}' (modes[{index[m.name]}] and modes[{i}])."
            )
        index[m.name] = i

    def resolve(k: int, tr, role: str, kind: str = "Transition") -> int:
        ref = getattr(tr, role)
        if isinstance(ref, str):
            if ref not in index:
                raise ValueError(
                    f"{kind} {k} ({tr.label}): unknown {role} mode '{ref}'; "
                    f"known modes: {sorted(index)}."
                )
            return index[ref]
        if not 0 <= int(ref) < len(modes):
            raise ValueError(
                f"{kind} {k} ({tr.label}): {role} index {ref} out of range "
                f"for {len(modes)} modes."
            )
        return int(ref)

    for k, tr in enumerate(transitions):
        resolve(k, tr, "source")
        resolve(k, tr, "target")
    for c, comp in enumerate(completions):
        if not isinstance(comp, ZenoCompletion):
            raise TypeError(
                f"completions[{c}] is {type(comp).__name__}, expected hybridjax.ZenoCompletion."
            )
    completion_sources = [resolve(c, comp, "source", "Completion") for c, comp in enumerate(completions)]
    for c, comp in enumerate(completions):
        resolve(c, comp, "target", "Completion")
    if len(set(completion_sources)) != len(completions):
        raise ValueError("At most one ZenoCompletion per source mode.")
    for name, reset, i, j in system.jumps():
        n_i, n_j = modes[i].dim, modes[j].dim
        if reset is _identity_reset and n_i != n_j:
            raise ValueError(
                f"{name}: the default identity reset needs equal dimensions, but source "
                f"has dim {n_i} and target dim {n_j}; give a `reset`."
            )
    check_function_shapes(system, example_args, dtype=jnp.result_type(float), strict=False)


def as_mode_index(system: HybridSystem, mode0) -> jax.Array:
    """`mode0` as an int32 array: a name is resolved now, an integer (array) is kept."""
    if isinstance(mode0, str):
        return jnp.asarray(system.mode_index(mode0), dtype=jnp.int32)
    if isinstance(mode0, (int, np.integer)):
        return jnp.asarray(system.mode_index(mode0), dtype=jnp.int32)
    return jnp.asarray(mode0, dtype=jnp.int32)
