r"""Contact graphs: the contact states a scene reaches, as plain data, and the explorer that finds them.

A contact state is the discrete part of a scene's mode (a set of held constraints; with friction,
the stick or slip state of each held frictional contact). From the initial states the explorer
tests every transition out of each state built: the point search looks for a witness state of
the source in the transition's guard (A. M. Johnson, "Hybrid Dynamical Systems", eq. (3): a guard
that meets its source's domain). A transition with a witness is kept and its target built; one
without is kept as pruned, with the reason. The graph is plain Python data (states, edges,
witness texts); the builders turn it into modes and transitions.

The law-specific part (which transitions leave a state, the search that tests them, how a
target is renamed) comes in as an `ExploreRules`.
"""

import abc
import dataclasses
from collections.abc import Hashable, Iterable, Sequence
from typing import Any, NamedTuple


class Leaving(NamedTuple):
    """A transition out of a contact state, to be tested: its `kind` (`"impact"`, `"lift-off"`,
    ...), the constraint `j` it concerns, a law-specific `detail` (a release candidate, a slip
    direction), the `target` state, and the `query` the point search tests."""

    kind: str
    j: int
    detail: Any
    target: Hashable
    query: Any


@dataclasses.dataclass(frozen=True)
class Edge:
    """A tested transition: `source` to `target` (the state built, after renaming, where
    `found`; the state proposed otherwise), `args_values` the indices of the `args` values a
    witness was found for (empty: pruned), `text` the witness or the reason it was pruned."""

    source: Hashable
    kind: str
    j: int
    detail: Any
    target: Hashable
    args_values: tuple[int, ...]
    text: str

    @property
    def found(self) -> bool:
        return bool(self.args_values)


@dataclasses.dataclass(frozen=True)
class ContactGraph:
    """What the explorer found: the `states` built (initial ones first, then in the order
    reached), every tested transition (`edges`, in the order tested), and the `unreached`
    states (targets of pruned transitions that were never built nor renamed)."""

    states: tuple[Hashable, ...]
    edges: tuple[Edge, ...]
    unreached: tuple[Hashable, ...]

    def leaving(self, state: Hashable) -> list[tuple[tuple[str, int], list[Edge]]]:
        """The edges out of `state`, grouped by (kind, constraint) in the order first tested."""
        groups: dict[tuple[str, int], list[Edge]] = {}
        for e in self.edges:
            if e.source == state:
                groups.setdefault((e.kind, e.j), []).append(e)
        return list(groups.items())


class ExploreRules(abc.ABC):
    """The law-specific part of the explorer."""

    # The states' name in the error of a build that exceeds `max_modes`.
    noun: str = "states"

    @abc.abstractmethod
    def leaving(self, state: Hashable) -> Iterable[Leaving]:
        """The transitions out of `state` to test, in order."""

    @abc.abstractmethod
    def search(self, queries: Sequence) -> Any:
        """The witnesses of `queries` (one batch, leading axis over the queries)."""

    @abc.abstractmethod
    def outcome(self, witnesses: Any, i: int) -> tuple[tuple[int, ...], str]:
        """Query `i`'s result: the indices of the `args` values with a witness (empty: none), and
        the witness's text or the reason none was found."""

    def canonical(self, state: Hashable) -> Hashable:
        """The state a transition into `state` leads to (a renamed symmetric state); itself by
        default."""
        return state


def explore(rules: ExploreRules, initial: Sequence[Hashable], max_modes: int) -> ContactGraph:
    """The contact graph reached from `initial`: one batched search per level of new states."""
    built = list(initial)
    edges = []
    frontier = list(built)
    while frontier:
        tests = [(S, leave) for S in frontier for leave in rules.leaving(S)]
        frontier = []
        if not tests:
            break
        w = rules.search([leave.query for _, leave in tests])
        for i, (S, leave) in enumerate(tests):
            values, text = rules.outcome(w, i)
            T = leave.target
            if values:
                T = rules.canonical(T)
                if T not in built:
                    if len(built) >= max_modes:
                        raise ValueError(
                            f"contact_system: more than max_modes={max_modes} {rules.noun} reached."
                        )
                    built.append(T)
                    frontier.append(T)
            edges.append(Edge(S, leave.kind, leave.j, leave.detail, T, values, text))
    unreached = dict.fromkeys(
        e.target
        for e in edges
        if not e.found and e.target not in built and rules.canonical(e.target) == e.target
    )
    return ContactGraph(tuple(built), tuple(edges), tuple(unreached))
