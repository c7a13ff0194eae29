r"""Scenes: rigid-body systems with unilateral and bilateral constraints, built into hybrid systems.

A scene is a Lagrangian system with generalised coordinates $q \in \mathbb{R}^n$, a mass matrix
$M(q)$, applied forces $f(t, q, \dot q)$ and named constraints $a_k(t, q)$, each unilateral
($a_k \ge 0$, a contact) or bilateral ($a_k = 0$, a joint). Its modes are contact sets $A$ (the
constraints held active), as A. M. Johnson, "Hybrid Dynamical Systems", section 1.1 describes
for rigid bodies with contact. In mode $A$ (state $x = (q, \dot q)$):

- flow: $M \ddot q = f + J_A^\top \lambda_A$, $J_A \ddot q = -\dot J_A \dot q$ (with the
  $\partial_t$ terms of time-varying constraints), $J_A = \partial a_A / \partial q$ by AD, solved
  together for $\ddot q$ and the contact forces $\lambda_A$ (one dense solve of the KKT system);
- guards: an impact $a_k \le 0$ for each unilateral $k \notin A$, a lift-off $\lambda_j \le 0$
  for each unilateral $j \in A$; the domain $D_A = \{a_k \ge 0, k \notin A;\ \lambda_A \ge 0\}$
  is bounded by exactly these guards, so the system watches the guards alone;
- resets: the impact map (below), the identity on lift-off.

**Impacts.** When $k$ hits in mode $A$, impulses $P$ act on $C = A \cup \{k\}$:
$\dot q^+ = \dot q^- + M^{-1} J_C^\top P$. A held constraint $i$ ends with
$J_i \dot q^+ = -e_i J_i \dot q^-$ (Newton's law; $e_i = 0$ is a plastic impact, and the
constraints of $A$ approach at speed 0, so only $k$'s restitution matters); a constraint whose
impulse would be negative (pulling) is released instead: $P_i = 0$ and it must separate,
$J_i \dot q^+ \ge 0$. Of the candidates (release none of $A$, then one, then two, ...) the first
that satisfies both is taken (for independent constraints this linear complementarity problem has
one solution). The new contact set is $C$ less the released constraints, and less $k$ if it
restitutes ($e_k > 0$: it leaves the contact). A constraint whose contact force right after the
impact is negative (a ball thrown at a ceiling) lifts off at once, in a zero-length epoch.
Simultaneous impacts are taken one at a time in the constraints' order (the engine's rule for
guards reached at the same instant); each later one sees the earlier ones held.

**Modelling only what the scene requires.** From the initial contact sets the builder adds only
the sets reached through *achievable* transitions: a transition is kept when the point search
(`find_point`) finds a witness state of its source mode in its guard, under the values of `args`
given. An impact needs $a_A = 0$, $\dot a_A = 0$, $a_k = 0$, the other contacts open, the flow in
$A$ ($\lambda_A \ge 0$), an approach speed $-\dot a_k \ge$ `margin`, nonnegative impulses and
separating releases, and an independent new set; a lift-off needs $\lambda_j \le -$`margin` (the
guard's interior, where a flow crossing $\lambda_j = 0$ or a reset lands). Everything else is
pruned and the system's repr says which and why. Sampling cannot prove a transition impossible:
every pruned transition still leads, with its guard, to a terminal mode named
`"unbuilt: <set>"`, whose empty domain ends the execution with `Status.BLOCKED` there, so an
execution that reaches a contact set that was not built stops and names it. So does an impact
that no release candidate solves (dependent constraints, or rounding at a tie): with the
unbuilt candidates, or in a terminal mode `"inconsistent: impact of <k> in <set>"`.
"""

import abc
import dataclasses
import functools
import itertools
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from .._analysis.search import SearchOptions
from .._analysis.search import search as point_search
from .._core import small_linalg as small_linalg
from .._core.names import one_of
from .._definition.system import AbstractHybridSystem, Mode, Transition, validate_system
from .indexed import ContactEvaluation
from .laws import (
    AbstractImpactLaw,
    AbstractTangentialLaw,
    Coulomb,
    Frictionless,
    Newton,
    Plastic,
    Sticking,
)
from .mechanics import (
    constrained_acceleration,
    rows,
)

UNILATERAL = "unilateral"
BILATERAL = "bilateral"
FREE = "free"
UNBUILT = "unbuilt: "
INCONSISTENT = "inconsistent: "


def _nested_tuple(value):
    """Lists and arrays as (nested) tuples of floats: a static field must be hashable."""
    if isinstance(value, (list, tuple, np.ndarray)):
        return tuple(_nested_tuple(v) for v in value)
    return float(value) if isinstance(value, (int, float, np.number)) else value


def _range(value, dim, what):
    try:
        lo, hi = value
    except (TypeError, ValueError):
        raise ValueError(f"Scene: `{what}` must be (lower, upper), got {value!r}.") from None
    lo = np.broadcast_to(np.asarray(lo, dtype=float), (dim,))
    hi = np.broadcast_to(np.asarray(hi, dtype=float), (dim,))
    if not np.all(hi >= lo):
        raise ValueError(f"Scene: `{what}` needs lower <= upper componentwise, got {lo} and {hi}.")
    return tuple(map(float, lo)), tuple(map(float, hi))


def _state_bounds(bounds, q_range, dq_range, dim):
    """The sampling box of x = (q, dq) as two length-2n tuples, from `bounds` (lower, upper:
    scalars or length 2n) or from its shorthands `q_range`, `dq_range` (each over length n)."""
    if bounds is not None and (q_range is not None or dq_range is not None):
        given = " and ".join(k for k, v in (("bounds", bounds), ("q_range", q_range), ("dq_range", dq_range))
                             if v is not None)
        raise ValueError(
            f"Scene: {given} are the same option under two names; pass `bounds` (the box of "
            "x = (q, dq)) or its shorthands `q_range`, `dq_range`, not both."
        )
    if bounds is None:
        (qlo, qhi) = _range((-1.0, 1.0) if q_range is None else q_range, dim, "q_range")
        (vlo, vhi) = _range((-1.0, 1.0) if dq_range is None else dq_range, dim, "dq_range")
        return qlo + vlo, qhi + vhi
    try:
        lo, hi = bounds
        lo = np.broadcast_to(np.asarray(lo, dtype=float), (2 * dim,))
        hi = np.broadcast_to(np.asarray(hi, dtype=float), (2 * dim,))
    except (TypeError, ValueError):
        raise ValueError(
            f"Scene: `bounds` must be (lower, upper) over x = (q, dq), each a scalar or of length "
            f"{2 * dim}, got {bounds!r}."
        ) from None
    if not np.all(hi >= lo):
        raise ValueError(f"Scene: `bounds` needs lower <= upper componentwise, got {lo} and {hi}.")
    return tuple(map(float, lo)), tuple(map(float, hi))


def point_search_key(key, seed) -> PRNGKeyArray:
    """The point search's `jax.random` key: `key`, or `jax.random.key(seed)` from the shorthand
    `seed`, or `jax.random.key(0)`; passing both is a ValueError naming them."""
    one_of("contact_system", key=key, seed=seed, default=None)  # both passed: a ValueError
    if seed is not None:
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise TypeError(f"contact_system: `seed` must be an int, got {seed!r}.")
        return jax.random.key(int(seed))
    return jax.random.key(0) if key is None else key


def sample_box(scene: "Scene", dtype) -> tuple[Array, Array]:
    """The lower and upper corners of the builder's sampling box of (q, dq, t), (2n + 1,) each."""
    (lo, hi), (t_lo, t_hi) = scene.bounds, scene.t_bounds
    return jnp.asarray(lo + (t_lo,), dtype), jnp.asarray(hi + (t_hi,), dtype)


class Constraint(eqx.Module):
    r"""A named constraint $a(t, q, \text{args})$ of a `Scene`.

    **Arguments:**

    - `name`: a unique name (mode names are built from these).
    - `fn`: `fn(t, q, args) -> scalar`, the gap $a$.
    - `kind`: `"unilateral"` ($a \ge 0$, a contact that can open and close) or `"bilateral"`
      ($a = 0$ always, a joint or a pinned foot, held in every mode).
    - `restitution`: the impact law of a unilateral constraint: `None` (plastic, the default),
      a number $e \in [0, 1]$, `restitution(args) -> e` (Newton's law with that $e$), or an
      `AbstractImpactLaw` (`hj.Plastic()`, `hj.Newton(e)`). With $e > 0$ the contact separates
      after its impact (Newton's law $\dot a^+ = -e \dot a^-$) and is not added to the contact
      set.
    - `tangent`: optional `tangent(t, q, args) -> scalar`, the contact point's coordinate along
      the surface, for a contact that sticks while it is held (a foot that does not slip,
      unlimited friction): its rate $\dot b$ is held at 0 with the gap (the impact stops it
      too), its force $\lambda_t$ is free in sign, and it is released with the gap.
    - `friction`: optional tangential law of a unilateral contact with a `tangent`: a Coulomb
      coefficient $\mu \ge 0$ (a number or `friction(args) -> mu`, `hj.Coulomb(mu)`), or an
      `AbstractTangentialLaw` (`hj.Coulomb`, `hj.StaticKineticCoulomb`, one of the user's). With
      Coulomb's law the contact sticks ($\dot b = 0$ held, $|\lambda_t| \le \mu \lambda_n$) or
      slips ($\lambda_t = -\mu\, \mathrm{sign}(\dot b) \lambda_n$), each a mode (`"name:stick"`,
      `"name:slip+"`, `"name:slip-"`); see `contact_system`. `hj.Sticking()` is a `tangent`
      alone; `hj.Frictionless()`, a contact without a `tangent`.
    - `armed`: optional `armed(t, q, args) -> scalar` $c$ of a unilateral contact: it can be hit
      only where $c \ge 0$. Its impact guard is $\max(a, -c) \le 0$ (the gap closed while the
      contact is armed); where $c < 0$ the gap may be negative (a walker's swing foot passing
      through the ground at mid-stance) and the contact is not watched. The point search asks
      an impact's witness for $c \ge 0$, and the other open contacts for $\max(a, -c) \ge 0$.
      Choose $c$ so that the gap is open where $c$ turns positive (the swing foot ahead of the
      stance foot by a little): a contact armed with its gap closed is hit at once.

    !!! Example

        ```python
        floor = hj.Constraint("floor", lambda t, q, args: q[0], restitution=lambda args: args["e"])
        ```
    """

    name: str = eqx.field(static=True)
    fn: Callable = eqx.field(static=True)
    kind: str = eqx.field(static=True, default=UNILATERAL)
    restitution: float | Callable | AbstractImpactLaw | None = None
    tangent: Callable | None = eqx.field(static=True, default=None)
    friction: float | Callable | AbstractTangentialLaw | None = None
    armed: Callable | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if not isinstance(self.name, str) or not self.name or "+" in self.name:
            raise ValueError(f"Constraint name must be a non-empty string without '+', got {self.name!r}.")
        if not callable(self.fn):
            raise TypeError(f"Constraint '{self.name}': `fn` must be callable, got {self.fn!r}.")
        if self.kind not in (UNILATERAL, BILATERAL):
            raise ValueError(
                f"Constraint '{self.name}': `kind` must be 'unilateral' or 'bilateral', got {self.kind!r}."
            )
        if self.tangent is not None and not callable(self.tangent):
            raise TypeError(f"Constraint '{self.name}': `tangent` must be callable or None.")
        _check_friction(self)
        if self.armed is not None and (self.kind != UNILATERAL or not callable(self.armed)):
            raise ValueError(
                f"Constraint '{self.name}': `armed` must be a callable of a unilateral constraint."
            )
        e = self.restitution
        if e is not None and self.kind == BILATERAL:
            raise ValueError(f"Constraint '{self.name}': a bilateral constraint has no restitution.")
        if e is not None and not callable(e) and not isinstance(e, AbstractImpactLaw):
            if isinstance(e, bool) or not isinstance(e, (int, float)) or not 0.0 <= e <= 1.0:
                raise ValueError(
                    f"Constraint '{self.name}': `restitution` must be None, a number in [0, 1], a "
                    f"function of args or an AbstractImpactLaw, got {e!r}."
                )

    @property
    def impact_law(self) -> AbstractImpactLaw:
        """The impact law the builders read: `restitution` where it is a law, plastic ($e = 0$)
        where it is None, Newton's law with $e$ = `restitution` otherwise."""
        if isinstance(self.restitution, AbstractImpactLaw):
            return self.restitution
        return Plastic() if self.restitution is None else Newton(self.restitution)

    @property
    def tangential_law(self) -> AbstractTangentialLaw:
        r"""The tangential law the builders read: `friction` where it is a law, Coulomb's with
        $\mu$ = `friction` where it is a number or a function (stick, slip+, slip-), sticking
        where a `tangent` is given alone, frictionless otherwise."""
        if isinstance(self.friction, AbstractTangentialLaw):
            return self.friction
        if self.friction is not None:
            return Coulomb(self.friction)
        return Sticking() if self.tangent is not None else Frictionless()

    @property
    def restitutes(self) -> bool:
        """True when an impact on this constraint separates it (restitution given and not 0)."""
        return self.impact_law.separates

    def coefficient(self, args) -> Any:
        """The coefficient of restitution under `args` (0 for a plastic impact)."""
        return self.impact_law.coefficient(args)


def _check_friction(c: "Constraint") -> None:
    """`friction` needs a unilateral contact with a tangent, and a coefficient is >= 0; a law
    with one state that holds no tangent row (`Frictionless`) needs no tangent."""
    mu = c.friction
    if mu is None:
        return
    law = mu if isinstance(mu, AbstractTangentialLaw) else None
    rowless = law is not None and len(law.states) == 1 and not law.holds_tangent(law.states[0])
    if c.kind != UNILATERAL or (c.tangent is None and not rowless):
        raise ValueError(f"Constraint '{c.name}': `friction` needs a unilateral constraint with a `tangent`.")
    if rowless and c.tangent is not None:
        raise ValueError(
            f"Constraint '{c.name}': `friction={law!r}` holds no tangent row: leave `tangent` None."
        )
    if law is None and not callable(mu) and (
        isinstance(mu, bool) or not isinstance(mu, (int, float)) or not mu >= 0.0
    ):
        raise ValueError(
            f"Constraint '{c.name}': the friction coefficient must be a number >= 0, a function of "
            f"args or an AbstractTangentialLaw, got {mu!r}."
        )


class Scene(eqx.Module):
    r"""A rigid-body scene: coordinates, mass matrix, applied forces and named constraints.

    $M(q) \ddot q = f(t, q, \dot q) + J^\top \lambda$ with the constraints' forces $\lambda$;
    `contact_system` builds its hybrid system.

    **Arguments:**

    - `dim`: the number $n$ of generalised coordinates $q$; the state is $x = (q, \dot q)$.
    - `mass`: `mass(q, args) -> (n, n)`, symmetric positive definite.
    - `forces`: `forces(t, q, dq, args) -> (n,)`, gravity, springs, controls.
    - `constraints`: a sequence of `Constraint`, names unique.
    - `bounds`: `(lower, upper)`, the box of states $x = (q, \dot q)$ the builder samples when
      it searches for achievable transitions, each a scalar or a length-$2n$ sequence (the form of
      `check_properties`' per-mode `bounds`); default $[-1, 1]^{2n}$. Shorthands: `q_range`,
      `dq_range`, each `(lower, upper)` (scalars or length-$n$) for $q$ and $\dot q$ alone.
    - `t_bounds`: `(t_lo, t_hi)`, the times sampled (for time-varying constraints or forces), as
      `find_point`'s `t_bounds`; default `(0, 0)`. Shorthand: `t_range`.
    - `names`: optional names of the coordinates (plot labels of $q$; $\dot q$'s get a `d`).
    - `velocity_terms`: add the Coriolis and centrifugal forces of $M(q)$,
      $-\dot M \dot q + \tfrac12 \partial_q(\dot q^\top M \dot q)$ (the Euler-Lagrange
      equations; derived by AD), to `forces`; `False` where `forces` already holds them.

    Errors at definition name the constraint at fault.

    !!! Example

        ```python
        ball = hj.Scene(
            dim=1, mass=lambda q, args: jnp.eye(1), forces=lambda t, q, dq, args: -args["g"] + 0 * q,
            constraints=[hj.Constraint("floor", lambda t, q, args: q[0], restitution=0.8)],
            bounds=((0.0, -5.0), (2.0, 5.0)),   # q in [0, 2], dq in [-5, 5]
        )
        ```
    """

    dim: int = eqx.field(static=True)
    mass: Callable = eqx.field(static=True)
    forces: Callable = eqx.field(static=True)
    constraints: tuple[Constraint, ...] = eqx.field(static=True, converter=tuple)
    # The sampling boxes: Python floats read by the builder (numpy), ordinary fields.
    bounds: tuple[tuple[float, ...], tuple[float, ...]]
    t_bounds: tuple[float, float]
    names: tuple[str, ...] | None = eqx.field(static=True)
    velocity_terms: bool = eqx.field(static=True)  # chooses the code traced

    def __init__(
        self,
        dim: int,
        mass: Callable,
        forces: Callable,
        constraints: Sequence[Constraint],
        bounds: tuple | None = None,
        t_bounds: tuple | None = None,
        names: Sequence[str] | None = None,
        velocity_terms: bool = True,
        *,
        q_range: tuple | None = None,
        dq_range: tuple | None = None,
        t_range: tuple | None = None,
    ):
        if isinstance(dim, bool) or not isinstance(dim, (int, np.integer)) or dim < 1:
            raise ValueError(f"Scene: `dim` must be a positive int, got {dim!r}.")
        self.dim, self.mass, self.forces = int(dim), mass, forces
        self.constraints = tuple(constraints)
        self.bounds = _state_bounds(bounds, q_range, dq_range, self.dim)
        t_bounds = one_of("Scene", t_bounds=t_bounds, t_range=t_range, default=(0.0, 0.0))
        try:
            t_lo, t_hi = map(float, t_bounds)
        except (TypeError, ValueError):
            raise ValueError(f"Scene: `t_bounds` must be (t_lo, t_hi), got {t_bounds!r}.") from None
        if not t_lo <= t_hi:
            raise ValueError(f"Scene: `t_bounds` must be (t_lo, t_hi) with t_lo <= t_hi, got {t_bounds!r}.")
        self.t_bounds = (t_lo, t_hi)
        self.names = _nested_tuple(names)
        self.velocity_terms = velocity_terms

    @property
    def q_range(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """The $q$ part of `bounds`, `(lower, upper)` of length $n$ each."""
        n = self.dim
        return self.bounds[0][:n], self.bounds[1][:n]

    @property
    def dq_range(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        r"""The $\dot q$ part of `bounds`, `(lower, upper)` of length $n$ each."""
        n = self.dim
        return self.bounds[0][n:], self.bounds[1][n:]

    @property
    def t_range(self) -> tuple[float, float]:
        """`t_bounds` under its other name."""
        return self.t_bounds

    def __check_init__(self):
        if not callable(self.mass) or not callable(self.forces):
            raise TypeError("Scene: `mass` and `forces` must be callable.")
        seen = set()
        for i, c in enumerate(self.constraints):
            if not isinstance(c, Constraint):
                raise TypeError(
                    f"Scene: constraints[{i}] is {type(c).__name__}, expected hybridjax.Constraint."
                )
            if c.name in seen:
                raise ValueError(f"Scene: duplicate constraint name '{c.name}'.")
            seen.add(c.name)
        if not self.constraints:
            raise ValueError("Scene: give at least one Constraint.")
        if self.names is not None and len(self.names) != self.dim:
            raise ValueError(f"Scene: `names` needs {self.dim} entries, got {len(self.names)}.")
        if not isinstance(self.velocity_terms, bool):
            raise TypeError(f"Scene: `velocity_terms` must be a bool, got {self.velocity_terms!r}.")

    @property
    def constraint_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.constraints)

    def index(self, name: str) -> int:
        try:
            return self.constraint_names.index(name)
        except ValueError:
            raise ValueError(
                f"Unknown constraint '{name}'; the scene's constraints: {list(self.constraint_names)}."
            ) from None

    def check(self, args: Any = None) -> None:
        """Check the shapes of `mass`, `forces` and every constraint with these `args` (by
        abstract evaluation), raising a ValueError that names the function at fault."""
        n, dt = self.dim, jnp.result_type(float)
        t, q = jax.ShapeDtypeStruct((), dt), jax.ShapeDtypeStruct((n,), dt)

        def shape(fn, *xs):
            return jax.eval_shape(lambda *ys: jnp.asarray(fn(*ys, args)), *xs).shape

        if (s := shape(self.mass, q)) != (n, n):
            raise ValueError(f"Scene: `mass` returns shape {s}, expected {(n, n)}.")
        if (s := shape(self.forces, t, q, q)) != (n,):
            raise ValueError(f"Scene: `forces` returns shape {s}, expected {(n,)}.")
        for c in self.constraints:
            for role, fn in (("fn", c.fn), ("tangent", c.tangent), ("armed", c.armed)):
                if fn is not None and (s := shape(fn, t, q)) not in ((), (1,)):
                    raise ValueError(f"Constraint '{c.name}': `{role}` returns shape {s}, expected a scalar.")


class Relabel(eqx.Module):
    r"""Identify contact set `source` with contact set `target` through a change of coordinates.

    A body with symmetric parts (the spokes of a wheel, the legs of a walker) reaches sets that
    are the same physical situation with the parts renamed. A transition into `source` goes to
    `target` instead, with $q' = $ `q_map(t, q, args)` and $\dot q' = \partial_q$`q_map`$\,\dot q$
    applied after its reset; `source` is never built. `q_map` must carry the constraints of
    `source` onto those of `target` (a rotation by the spoke angle, a shift of the origin to the
    new stance foot), so that the periodic gait of a walker is a periodic orbit of the system.

    !!! Example

        ```python
        # spoke 1 becomes spoke 0: rotate back by 2 alpha, put the new foot at x = 0
        hj.Relabel(("spoke1",), ("spoke0",), q_map=lambda t, q, args: ...)
        ```
    """

    source: tuple[str, ...] = eqx.field(static=True, converter=tuple)
    target: tuple[str, ...] = eqx.field(static=True, converter=tuple)
    q_map: Callable = eqx.field(static=True)

    def __check_init__(self):
        if not callable(self.q_map):
            raise TypeError(f"Relabel {self.source} -> {self.target}: `q_map` must be callable.")

    def state_map(self, n: int) -> Callable:
        """(t, x, args) -> (q_map(q), D q_map dq)."""

        def m(t, x, args):
            q2, dq2 = jax.jvp(lambda q_: jnp.asarray(self.q_map(t, q_, args), x.dtype), (x[:n],), (x[n:],))
            return jnp.concatenate([q2, dq2])

        return m


def _then(reset: Callable, relabel_map: Callable | None) -> Callable:
    if relabel_map is None:
        return reset
    return lambda t, x, args: relabel_map(t, reset(t, x, args), args)


def _identity(t, x, args):
    return x


# ----------------------------------------------------------------------------- contact sets


def set_name(scene: Scene, contact_set) -> str:
    """The mode name of a contact set: its constraints' names joined by '+', or 'free'."""
    if not contact_set:
        return FREE
    return "+".join(scene.constraints[i].name for i in sorted(contact_set))


def _releases(held_unilateral):
    """Release candidates R of the held unilateral constraints: none, then one, then two..."""
    return [
        frozenset(r)
        for size in range(len(held_unilateral) + 1)
        for r in itertools.combinations(sorted(held_unilateral), size)
    ]


def _terminal_flow(t, x, args):
    return jnp.zeros_like(x)


def _terminal_domain(t, x, args):
    return -jnp.ones((), x.dtype)


# Queries per call of the compiled search: every call has this many (the last one padded), so a
# scene's search compiles once, whatever the number of queries of a level.
SEARCH_CHUNK = 8
# The search runs a few times per build and its program is large (the contact equations, their
# derivatives, the trust-region solve): XLA:CPU's own fusion emitters compile it in less time
# than its MLIR ones. XLA's backend optimisation stays on: at level 0, jaxlib 0.10.2 has run
# programs with results that depend on its threads, and with the concurrency-optimised schedule
# also off it has computed a batched program wrong on one core (docs: FAQ, "Compile time"); a
# scene's build runs in the user's process, on every core. At level 0 a friction rod would build
# about a tenth faster, the compass-gait walker about a quarter.
_SEARCH_COMPILE = {"xla_cpu_use_fusion_emitters": False}


def run_search(constraints, queries, args_batch, samples, search: SearchOptions):
    """`_search` over `queries` in chunks of `SEARCH_CHUNK`: Witness with leading axes (Q, V).
    `constraints(t, x, (args, query)) -> (equalities, inequalities)`, one function, so that the
    work the two share (the scene's kinematics and solves) is traced once."""
    ts, xs = samples
    count = len(queries)
    padded = -(-count // SEARCH_CHUNK) * SEARCH_CHUNK
    queries = list(queries) + [queries[0]] * (padded - count)
    outs = []
    for start in range(0, padded, SEARCH_CHUNK):
        stacked = jtu.tree_map(lambda *xs_: jnp.stack(xs_), *queries[start : start + SEARCH_CHUNK])
        operands = (ts, xs, stacked, args_batch)
        shapes = tuple((a.shape, a.dtype) for a in jtu.tree_leaves(operands))
        run = _compiled_search(constraints, search, jtu.tree_structure(operands), shapes, operands)
        outs.append(run(*operands))
    return jtu.tree_map(lambda *a: np.concatenate([np.asarray(b) for b in a])[:count], *outs)


def _compiled_search(constraints, search, structure, shapes, operands):
    """The search's executable for these constraint functions and operand shapes: compiled on
    first use (`_SEARCH_COMPILE`), then reused for every level and `args` value of the scene."""
    key = (constraints, search, structure, shapes)
    if key not in _SEARCHES:
        if len(_SEARCHES) >= 8:
            _SEARCHES.pop(next(iter(_SEARCHES)))
        fn = jax.jit(functools.partial(_search, constraints, search=search))
        _SEARCHES[key] = fn.trace(*operands).lower().compile(_SEARCH_COMPILE)
    return _SEARCHES[key]


_SEARCHES: dict = {}


def _search(constraints, ts, xs, queries, args_batch, *, search):
    """`analysis.search.search` for every (query, `args` value) pair, under one `jax.vmap` over
    the Q * V pairs (a nested vmap would batch the least-squares solve's program twice)."""
    # The index makes the vmap well defined for `args` without arrays (None).
    index, args_batch = args_batch
    num_q, num_v = jtu.tree_leaves(queries)[0].shape[0], index.shape[0]
    pair_q = jtu.tree_map(lambda a: jnp.repeat(a, num_v, axis=0), queries)
    pair_a = jtu.tree_map(lambda a: jnp.tile(a, (num_q,) + (1,) * (a.ndim - 1)), (index, args_batch))

    def one(Q, indexed):
        _, args = indexed
        return point_search(constraints, ts, xs, (args, Q), tol=search.tol, num_starts=search.num_starts,
                            iterations=search.iterations)

    out = jax.vmap(one)(pair_q, pair_a)
    return jtu.tree_map(lambda a: a.reshape((num_q, num_v) + a.shape[1:]), out)


# ----------------------------------------------------------------------------- the system


class AbstractContactSystem(AbstractHybridSystem):
    """A hybrid system built from a `Scene`, whose modes are contact sets: what `ContactSystem`
    and `FrictionSystem` share (the build report, the evaluation for a traced mode, the contact
    forces along a solution). Each gives its fields and `_force_function`."""

    scene: eqx.AbstractVar[Scene]
    contact_sets: eqx.AbstractVar[tuple]
    least_norm_modes: eqx.AbstractVar[tuple]
    report: eqx.AbstractVar[tuple]
    achievable: eqx.AbstractVar[tuple]
    form: eqx.AbstractVar[str]
    evaluation: eqx.AbstractVar[Any]

    @abc.abstractmethod
    def _force_function(self) -> Callable:
        """`(t, y, mode, args) -> forces` at one saved state (NaN where `mode` < 0 or t is not finite)."""

    def mode_indexed(self) -> ContactEvaluation | None:
        """The one masked evaluation for a traced mode (`form="mask"`), or None (`"branch"`)."""
        return self.evaluation

    @property
    def force_names(self) -> tuple[str, ...]:
        """The columns of `contact_forces`: the constraints' names, then `"<name>.t"` for the
        tangential force of each sticking contact."""
        _, owners = rows(self.scene, range(len(self.scene.constraints)))
        K = len(self.scene.constraints)
        return tuple(self.scene.constraints[k].name + (".t" if r >= K else "") for r, k in enumerate(owners))

    @property
    def built_sets(self) -> tuple[frozenset, ...]:
        """The contact sets built as modes (sets of constraint names)."""
        return tuple(frozenset(s) for s in self.contact_sets if s is not None)

    def contact_forces(self, sol, args: Any = None) -> Float[Array, "*batch saves K"]:
        r"""The contact forces $\lambda$ (one column per constraint, in the scene's order, then one
        per sticking contact's tangential force, as `force_names`; 0 for a constraint not held) at
        the saved states `sol.ts`, `sol.ys` of a solution of this system
        (NaN at save times the execution did not reach). `args` defaults to `sol.args` (for a
        batch, one value per execution)."""
        args = sol.args if args is None else args
        one = self._force_function()

        def execution(ts, ys, modes, args):
            return jax.vmap(lambda t, y, m: one(t, y, m, args))(ts, ys, modes)

        if sol.ts.ndim == 1:
            return execution(sol.ts, sol.ys, sol.saved_modes, args)
        # A batch: `sol.args` holds one value per execution (leaves with the batch's leading axis).
        size = sol.ts.shape[0]
        axes = jtu.tree_map(lambda a: 0 if jnp.ndim(a) >= 1 and jnp.shape(a)[0] == size else None, args)
        return jax.vmap(execution, in_axes=(0, 0, 0, axes))(sol.ts, sol.ys, sol.saved_modes, args)

    def __repr__(self) -> str:
        return "\n".join([f"Contact{super().__repr__()}", *self.report])

    def _repr_html_(self) -> str:
        import html

        lines = "<br>".join(html.escape(line) for line in self.report)
        return super()._repr_html_() + f"<div><pre>{lines}</pre></div>"


def _set_fields(system, modes, transitions, **fields) -> None:
    """Set a contact system's fields in its `__init__` (no Zeno completions), then validate it as
    `HybridSystem` does."""
    system.modes, system.transitions, system.completions = tuple(modes), tuple(transitions), ()
    for name, value in fields.items():
        setattr(system, name, value)
    validate_system(system)


def state_names(scene: Scene) -> tuple[str, ...]:
    """The names of the state's components: the coordinates' names (or `q[i]`), then `d<name>`."""
    names = scene.names or tuple(f"q[{i}]" for i in range(scene.dim))
    return tuple(names) + tuple(f"d{s}" for s in names)


@dataclasses.dataclass
class Assembly:
    """A build's modes and transitions as a builder adds them: per transition its slot and
    reset (as the builder's mode-indexed evaluation reads them), the report's achievable and
    pruned lines, and the terminal modes named so far (added after the built ones)."""

    scene: Scene
    modes: list
    transitions: list = dataclasses.field(default_factory=list)
    slots: list = dataclasses.field(default_factory=list)
    resets: list = dataclasses.field(default_factory=list)
    achievable: list = dataclasses.field(default_factory=list)
    pruned: list = dataclasses.field(default_factory=list)
    terminals: dict = dataclasses.field(default_factory=dict)

    def add(self, transition: Transition, slot: Any, reset: Any) -> None:
        self.transitions.append(transition)
        self.slots.append(slot)
        self.resets.append(reset)

    def terminal(self, name: str) -> str:
        """`name` as a terminal mode (each added once)."""
        self.terminals[name] = None
        return name

    def close(self) -> None:
        """Add the terminal modes: no flow, an empty domain (the execution ends `BLOCKED`)."""
        comp = state_names(self.scene)
        for term in self.terminals:
            self.modes.append(Mode(term, _terminal_flow, dim=2 * self.scene.dim, domain=_terminal_domain,
                                   names=comp))  # fmt: skip

    def mode_slots(self, constant: Any) -> tuple:
        """The slots in the engines' order: each mode's transitions in index order, then a
        terminal mode's one domain component (`constant`)."""
        names = [m.name for m in self.modes]
        sources = [names.index(tr.source) for tr in self.transitions]
        num_built = len(self.modes) - len(self.terminals)
        return tuple(
            tuple(self.slots[i] for i, m_ in enumerate(sources) if m_ == m)
            + ((constant,) if m >= num_built else ())
            for m in range(len(self.modes))
        )


class ContactSystem(AbstractContactSystem):
    """The hybrid system of a `Scene`, built by `contact_system`: an `AbstractHybridSystem`
    (every tool works on it, as on a `HybridSystem`) whose modes are contact sets, with what the
    builder found. It is validated at construction as a `HybridSystem` is.

    - `scene`: the scene.
    - `contact_sets`: for each mode, the names of its held constraints (`None` for the terminal
      `"unbuilt: <set>"` modes).
    - `report`: the lines of the build report (built transitions with a witness state, pruned
      transitions and sets with the reason); the repr prints them.
    - `contact_forces(sol)`: the contact forces at the solution's saved states.
    """

    modes: tuple[Mode, ...]
    transitions: tuple[Transition, ...]
    completions: tuple[()]
    # Static: the scene (callables), names, report lines and the evaluation's tables.
    scene: Scene = eqx.field(static=True)
    contact_sets: tuple = eqx.field(static=True)
    least_norm_modes: tuple = eqx.field(static=True)
    report: tuple = eqx.field(static=True)
    achievable: tuple = eqx.field(static=True)
    form: str = eqx.field(static=True)
    evaluation: ContactEvaluation | None = eqx.field(static=True)

    def __init__(
        self, modes, transitions, *, scene, contact_sets, least_norm_modes, report, achievable, form,
        evaluation=None,
    ):  # fmt: skip
        _set_fields(self, modes, transitions, scene=scene, contact_sets=contact_sets,
                    least_norm_modes=least_norm_modes, report=report, achievable=achievable, form=form,
                    evaluation=evaluation)  # fmt: skip

    def _force_function(self) -> Callable:
        """`(t, y, mode, args) -> forces` at one saved state (NaN where `mode` < 0 or t is not finite)."""
        scene, K = self.scene, len(self.scene.constraints)
        fns, owners = rows(scene, range(K))
        table = np.zeros((self.num_modes, K))
        for m, s in enumerate(self.contact_sets):
            for name in s or ():
                table[m, scene.index(name)] = 1.0
        table = table[:, np.asarray(owners, dtype=int)]
        least_norm = any(self.least_norm_modes)
        n = scene.dim

        def one(t, y, mode, args):
            ok = (mode >= 0) & jnp.isfinite(t)
            mask = jnp.asarray(table, y.dtype)[jnp.maximum(mode, 0)]
            y = jnp.where(ok, y, 0.0)
            t = jnp.where(ok, t, 0.0)
            _, lam = constrained_acceleration(scene, fns, mask, t, y[:n], y[n : 2 * n], args, least_norm)
            return jnp.where(ok, lam * mask, jnp.nan)

        return one


def _as_set(scene: Scene, contact_set) -> frozenset:
    if isinstance(contact_set, str):
        contact_set = () if contact_set == FREE else contact_set.split("+")
    idx = frozenset(scene.index(name) for name in contact_set)
    bilateral = {i for i, c in enumerate(scene.constraints) if c.kind == BILATERAL}
    return idx | bilateral


def _fmt(x) -> str:
    return "(" + ", ".join(f"{v:.3g}" for v in np.ravel(x)) + ")"


def witness_text(w, i: int, n: int) -> str:
    """The report line of query `i`'s witness (found for some `args` value): its time, q and
    dq, and the `args` values it was found for where not all."""
    found_v = w.found[i]
    v = int(np.argmax(found_v))
    where = "" if found_v.all() else f", only for args_values {[int(a) for a in np.flatnonzero(found_v)]}"
    return f"witness t={w.t[i, v]:.3g}, q={_fmt(w.x[i, v, :n])}, dq={_fmt(w.x[i, v, n:])}{where}"
