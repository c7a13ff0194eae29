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

from .._analysis.search import SearchOptions, box_samples, find_point, search_options
from .._core import small_linalg as small_linalg
from .._core.names import one_of
from .._definition.system import AbstractHybridSystem, Mode, Transition, validate_system
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
      a number $e \in [0, 1]$, or `restitution(args) -> e`. With $e > 0$ the contact separates
      after its impact (Newton's law $\dot a^+ = -e \dot a^-$) and is not added to the contact
      set.
    - `tangent`: optional `tangent(t, q, args) -> scalar`, the contact point's coordinate along
      the surface, for a contact that sticks while it is held (a foot that does not slip,
      unlimited friction): its rate $\dot b$ is held at 0 with the gap (the impact stops it
      too), its force $\lambda_t$ is free in sign, and it is released with the gap.
    - `friction`: optional Coulomb coefficient $\mu \ge 0$ (a number or `friction(args) -> mu`)
      of a unilateral contact with a `tangent`: the contact then sticks ($\dot b = 0$ held,
      $|\lambda_t| \le \mu \lambda_n$) or slips ($\lambda_t = -\mu\, \mathrm{sign}(\dot b)
      \lambda_n$), each a mode (`"name:stick"`, `"name:slip+"`, `"name:slip-"`); see `contact_system`.
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
    restitution: float | Callable | None = None
    tangent: Callable | None = eqx.field(static=True, default=None)
    friction: float | Callable | None = None
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
        if e is not None and not callable(e):
            if isinstance(e, bool) or not isinstance(e, (int, float)) or not 0.0 <= e <= 1.0:
                raise ValueError(
                    f"Constraint '{self.name}': `restitution` must be None, a number in [0, 1] or "
                    f"a function of args, got {e!r}."
                )

    @property
    def restitutes(self) -> bool:
        """True when an impact on this constraint separates it (restitution given and not 0)."""
        return self.restitution is not None and (callable(self.restitution) or self.restitution > 0)

    def coefficient(self, args) -> Any:
        e = self.restitution
        if e is None:
            return 0.0
        return e(args) if callable(e) else e


def _check_friction(c: "Constraint") -> None:
    """A friction coefficient needs a unilateral contact with a tangent, and is >= 0."""
    mu = c.friction
    if mu is None:
        return
    if c.kind != UNILATERAL or c.tangent is None:
        raise ValueError(f"Constraint '{c.name}': `friction` needs a unilateral constraint with a `tangent`.")
    if not callable(mu) and (isinstance(mu, bool) or not isinstance(mu, (int, float)) or not mu >= 0.0):
        raise ValueError(
            f"Constraint '{c.name}': the friction coefficient must be a number >= 0 or a function of "
            f"args, got {mu!r}."
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


def _terminal_flow(t, x, args):
    return jnp.zeros_like(x)


def _terminal_domain(t, x, args):
    return -jnp.ones((), x.dtype)


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
    """The equalities and inequalities of every query (cached: later builds of one scene, with
    other `args`, reuse the compiled search)."""
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

    return (lambda t, x, p: parts(t, x, p)[0]), (lambda t, x, p: parts(t, x, p)[1])


def _run_queries(scene, queries, args_batch, samples, margin, least_norm, search):
    """find_point for every (query, args value): Witness with leading axes (Q, V)."""
    eq, ineq = _query_functions(scene, margin, least_norm)
    return run_search(eq, ineq, queries, args_batch, samples, search)


# Queries per call of the compiled search: every call has this many (the last one padded), so a
# scene's search compiles once, whatever the number of queries of a level.
SEARCH_CHUNK = 8
# The search runs a few times per build and its program is large (the contact equations, their
# derivatives, the trust-region solve): XLA's backend optimisation would take most of its
# compile time and save little of its run time.
_SEARCH_COMPILE = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}


def run_search(eq, ineq, queries, args_batch, samples, search: SearchOptions):
    """`_search` over `queries` in chunks of `SEARCH_CHUNK`: Witness with leading axes (Q, V)."""
    ts, xs = samples
    count = len(queries)
    padded = -(-count // SEARCH_CHUNK) * SEARCH_CHUNK
    queries = list(queries) + [queries[0]] * (padded - count)
    outs = []
    for start in range(0, padded, SEARCH_CHUNK):
        stacked = jtu.tree_map(lambda *xs_: jnp.stack(xs_), *queries[start : start + SEARCH_CHUNK])
        operands = (ts, xs, stacked, args_batch)
        shapes = tuple((a.shape, a.dtype) for a in jtu.tree_leaves(operands))
        run = _compiled_search(eq, ineq, search, jtu.tree_structure(operands), shapes, operands)
        outs.append(run(*operands))
    return jtu.tree_map(lambda *a: np.concatenate([np.asarray(b) for b in a])[:count], *outs)


def _compiled_search(eq, ineq, search, structure, shapes, operands):
    """The search's executable for these constraint functions and operand shapes: compiled on
    first use (`_SEARCH_COMPILE`), then reused for every level and `args` value of the scene."""
    key = (eq, ineq, search, structure, shapes)
    if key not in _SEARCHES:
        if len(_SEARCHES) >= 8:
            _SEARCHES.pop(next(iter(_SEARCHES)))
        fn = jax.jit(functools.partial(_search, eq, ineq, search=search))
        _SEARCHES[key] = fn.trace(*operands).lower().compile(_SEARCH_COMPILE)
    return _SEARCHES[key]


_SEARCHES: dict = {}


def _search(eq, ineq, ts, xs, queries, args_batch, *, search):
    def one(Q, args):
        return find_point(eq, ineq, ts, xs, (args, Q), tol=search.tol, num_starts=search.num_starts,
                          iterations=search.iterations)

    # The index makes the inner vmap well defined for `args` without arrays (None).
    index, args_batch = args_batch
    return jax.vmap(lambda Q: jax.vmap(lambda i, a: one(Q, a))(index, args_batch))(queries)


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


def contact_system(
    scene: Scene,
    initial: Sequence,
    args: Any = None,
    *,
    args_values: Sequence | None = None,
    num_samples: int = 512,
    margin: float = 1e-3,
    key: PRNGKeyArray | None = None,
    redundant: str = "error",
    form: str = "mask",
    max_modes: int = 64,
    relabels: Sequence[Relabel] = (),
    search: SearchOptions | None = None,
    **shorthands,
) -> AbstractContactSystem:
    r"""Build the hybrid system of `scene`, with only the contact sets it reaches.

    Starting from the `initial` contact sets, each transition out of a built set (an impact of
    each open contact with each release candidate, a lift-off of each held contact) is kept
    when the point search finds a witness state in its guard for one of the `args` values
    (see the module notes for the conditions); its target set is then built too. What is
    never found is pruned and listed, with the reason, in the repr; a pruned transition still
    fires into a terminal mode `"unbuilt: <set>"` that ends the execution with `BLOCKED`.

    **Arguments:**

    - `scene`: the `Scene`.
    - `initial`: the initial contact sets, each a sequence of constraint names or a mode name
      (`"free"`, `"G+H"`); bilateral constraints are always held.
    - `args`: the scene's `args`; or `args_values`: a sequence of them (a slope angle's values,
      or samples of its range) to build over: a transition found for any of them is kept, and
      the repr says for which. A batch or a derivative across values that change the modes
      built needs a system built over all of them.
    - `num_samples`, `key`: the point search's samples, drawn in the scene's `bounds` x
      `t_bounds` (`key` a `jax.random` key, default `jax.random.key(0)`).
    - `margin`: the least approach speed of an impact and the least pulling force of a
      lift-off that a witness must show, in the scene's units.
    - `redundant`: `"error"` (a reachable contact set with dependent constraints raises,
      naming them) or `"least_norm"` (its contact forces are the least-norm solution).
    - `form`: `"mask"` (the default: the engines evaluate the system for the current mode in
      one solve with all constraints, those not held masked out, `ContactEvaluation`; the
      cost of a step and of its compile does not grow with the modes built) or `"branch"`
      (each mode's and each transition's own function, evaluated and selected under
      `jax.vmap`: every mode's solve in every step). Both give the same executions to
      rounding; the mask is faster to compile and to run (docs: Scenes, "What it costs").
      Scenes with friction too (`FrictionEvaluation`).
    - `max_modes`: a build that would exceed this many modes stops with an error.
    - `relabels`: `Relabel`s identifying symmetric contact sets (a transition into a `source`
      set goes to its `target` set, the state relabelled).
    - `search`: an `hj.SearchOptions` (`num_starts`, `iterations`, `tol`: how the best samples
      are refined, the violation accepted as zero), as in `find_point`.

    **Keyword shorthands** (passing one with the name it stands for is a `ValueError`):
    `seed=s` for `key=jax.random.key(s)`; `num_starts`, `iterations` (or `max_steps`), `tol`
    for `search=hj.SearchOptions(...)` with them.

    !!! Example

        ```python
        system = hj.contact_system(scene, initial=["free"], args={"g": 9.81})
        system              # modes, transitions, witnesses, and what was pruned and why
        sol = hj.simulate(system, x0, "free", 0.0, 2.0, {"g": 9.81})
        system.contact_forces(sol)
        ```
    """
    search = search_options("contact_system", search, shorthands)
    unknown = sorted(set(shorthands) - {"seed"})
    if unknown:
        raise TypeError(f"contact_system() got an unexpected keyword argument {unknown[0]!r}.")
    key = point_search_key(key, shorthands.get("seed"))
    if redundant not in ("error", "least_norm"):
        raise ValueError(f"contact_system: `redundant` must be 'error' or 'least_norm', got {redundant!r}.")
    if form not in ("branch", "mask"):
        raise ValueError(f"contact_system: `form` must be 'branch' or 'mask', got {form!r}.")
    if any(c.friction is not None for c in scene.constraints):
        from .._scenes.friction import friction_system

        return friction_system(
            scene, initial, args, args_values=args_values, num_samples=num_samples, search=search,
            margin=margin, key=key, redundant=redundant, max_modes=max_modes, relabels=relabels,
            form=form,
        )  # fmt: skip
    values = list(args_values) if args_values is not None else [args]
    if not values:
        raise ValueError("contact_system: `args_values` is empty.")
    for v in values:
        scene.check(v)
    least_norm = redundant == "least_norm"
    K, n = len(scene.constraints), scene.dim
    dtype = jnp.result_type(float)
    unilateral = {i for i, c in enumerate(scene.constraints) if c.kind == UNILATERAL}
    args_batch = (
        jnp.arange(len(values)),
        jtu.tree_map(lambda *v: jnp.stack([jnp.asarray(x, dtype) for x in v]), *values),
    )

    pts = box_samples(key, tuple(sample_box(scene, dtype)), num_samples)
    samples = (pts[:, -1], pts[:, :-1])

    def onehot(idx):
        return jnp.asarray([1.0 if i in idx else 0.0 for i in range(K)], dtype)

    def query(A, lift=(), hit=(), impact_held=(), released=(), flowing=0.0):
        return _Query(
            onehot(A),
            onehot(lift),
            onehot(hit),
            onehot(impact_held),
            onehot(released),
            jnp.asarray(flowing, dtype),
        )

    def witnesses(qs):
        return _run_queries(scene, qs, args_batch, samples, margin, least_norm, search)

    # Initial sets: a consistent state (held gaps and rates 0, the others open), where the held
    # constraints are independent (or `redundant="least_norm"`).
    initial_sets = list(dict.fromkeys(_as_set(scene, s) for s in initial))
    if not initial_sets:
        raise ValueError("contact_system: give at least one initial contact set.")
    w = witnesses([query(A) for A in initial_sets])
    built: dict[frozenset, bool] = {}  # set -> least-norm
    report: list[str] = []
    for i, A in enumerate(initial_sets):
        if not w.found[i].any():
            raise ValueError(
                f"contact_system: the initial contact set {set_name(scene, A)} has no consistent state "
                "in the scene's ranges (held gaps and rates 0, the other contacts open; least violation "
                f"{np.nanmin(w.violation[i]):.2g}, infinite where the held constraints are dependent)."
            )
        v = int(np.argmax(w.found[i]))
        fns, owners = rows(scene, range(K))
        held_rows = _row_mask(owners, onehot(A), dtype)
        ratio = independence(scene, fns, held_rows, w.t[i, v], jnp.asarray(w.x[i, v, :n]), values[v])
        if ratio <= _INDEPENDENT and not least_norm:
            names = [scene.constraints[j].name for j in sorted(A)]
            raise ValueError(
                f"contact_system: the initial contact set {set_name(scene, A)} has dependent constraints "
                f"{names} (redundant contacts); pass redundant='least_norm' for least-norm contact "
                "forces, or remove one of them."
            )
        built[A] = least_norm

    relabel_of = {}
    for r in relabels:
        if not isinstance(r, Relabel):
            raise TypeError(f"contact_system: relabels must be hybridjax.Relabel, got {type(r).__name__}.")
        relabel_of[_as_set(scene, r.source)] = (_as_set(scene, r.target), r.state_map(n))

    def canonical(T):
        return relabel_of.get(T, (T, None))

    impacts: dict[tuple, _Impact] = {}
    outcomes: dict[tuple, list] = {}  # (A, kind, j) -> per candidate: (c, target, found, text)
    frontier = list(built)
    while frontier:
        qs, keys = [], []
        for A in frontier:
            for k in sorted(unilateral - A):
                # A candidate with more rows than coordinates is dependent wherever it is: it
                # can hold only with least-norm impulses.
                releases = tuple(
                    tuple(sorted(r))
                    for r in _releases(A & unilateral)
                    if least_norm or len(rows(scene, sorted((A | {k}) - r))[0]) <= n
                )
                imp = _Impact(scene, tuple(sorted(A)), k, releases, least_norm)
                impacts[(A, k)] = imp
                for c, R in enumerate(imp.candidates):
                    held = (A | {k}) - set(R)
                    qs.append(query(A, hit={k}, impact_held=held, released=set(R), flowing=1.0))
                    keys.append((A, "impact", k, c, imp.target(c)))
            for j in sorted(A & unilateral):
                qs.append(query(A, lift={j}))
                keys.append((A, "lift-off", j, 0, A - {j}))
        frontier = []
        if not qs:
            break
        w = witnesses(qs)
        for i, (A, kind, j, c, T) in enumerate(keys):
            found_v = w.found[i]
            if found_v.any():
                text = witness_text(w, i, n)
                T = canonical(T)[0]
                if T not in built:
                    if len(built) >= max_modes:
                        raise ValueError(
                            f"contact_system: more than max_modes={max_modes} contact sets reached."
                        )
                    built[T] = least_norm
                    frontier.append(T)
                outcomes.setdefault((A, kind, j), []).append((c, T, True, text))
            else:
                least = float(
                    np.nanmin(np.where(np.isfinite(w.violation[i]), w.violation[i], np.nan), initial=np.inf)
                )
                why = (
                    f"no state of the source set found in the guard (least violation {least:.2g})"
                    if np.isfinite(least)
                    else "the contact equations are singular (dependent constraints) at every state tried"
                )
                outcomes.setdefault((A, kind, j), []).append((c, T, False, why))

    # Assemble: built modes, then terminal modes for unbuilt targets.
    order = list(built)
    modes, transitions, achievable = [], [], []
    mode_fns = {A: _ModeFunctions(scene, tuple(sorted(A)), built[A]) for A in order}
    # Per transition, in order: its watched function and reset as `ContactEvaluation` reads them.
    slot_specs, reset_specs = [], []
    relabel_maps = list(dict.fromkeys(m for _, m in relabel_of.values()))

    def spec(slot, held=None, hit=0, relabel_map=None):
        slot_specs.append(slot)
        r = -1 if relabel_map is None else relabel_maps.index(relabel_map)
        reset_specs.append(ResetSpec(None if held is None else tuple(sorted(held)), hit, r))

    names = scene.names or tuple(f"q[{i}]" for i in range(n))
    comp = tuple(names) + tuple(f"d{s}" for s in names)
    for A in order:
        modes.append(Mode(set_name(scene, A), mode_fns[A].flow, dim=2 * n, names=comp))
    terminals: dict[str, None] = {}
    pruned_lines = []
    for A in order:
        src = set_name(scene, A)
        for (A_, kind, j), items in outcomes.items():
            if A_ != A:
                continue
            cname = scene.constraints[j].name
            if kind == "impact":
                imp = impacts[(A, j)]
                chosen = tuple(c for c, _, ok, _ in items if ok)
                for c, T, ok, text in items:
                    if ok:
                        tgt, relabel_map = canonical(imp.target(c))
                        via = (
                            ""
                            if relabel_map is None
                            else f" (relabelled from {set_name(scene, imp.target(c))})"
                        )
                        transitions.append(
                            Transition(
                                src,
                                set_name(scene, tgt),
                                guard=imp.guard((c,)),
                                reset=_then(imp.reset(c), relabel_map),
                                name=f"impact {cname}: {src} -> {set_name(scene, tgt)}",
                            )
                        )
                        held = (set(imp.source) | {j}) - set(imp.candidates[c])
                        spec(imp.slot((c,)), held=held, hit=j, relabel_map=relabel_map)
                        achievable.append((src, set_name(scene, tgt) + via, kind, cname, text))
                    else:
                        released = [scene.constraints[i].name for i in imp.candidates[c]]
                        rel = f" releasing {'+'.join(released)}" if released else ""
                        pruned_lines.append(
                            f"  pruned: impact of {cname} in {src}{rel} -> {set_name(scene, T)}: {text}"
                        )
                if len(chosen) < len(items):
                    T0 = imp.target(0)
                    term = UNBUILT + set_name(scene, T0)
                    terminals[term] = None
                    # With the candidates not found, the impact that no candidate solves (-1).
                    others = tuple(c for c in range(len(imp.candidates)) if c not in chosen) + (-1,)
                    transitions.append(
                        Transition(
                            src, term, guard=imp.guard(others), name=f"impact {cname}: {src} -> {term}"
                        )
                    )
                    spec(imp.slot(others))
                elif len(chosen) > 1:
                    # Every candidate was found, so each transition reads the choice: an impact that
                    # no candidate solves (dependent constraints, or rounding at a tie) stops the
                    # execution there, naming it, rather than pass through the constraint.
                    term = f"{INCONSISTENT}impact of {cname} in {src}"
                    terminals[term] = None
                    transitions.append(
                        Transition(src, term, guard=imp.guard((-1,)), name=f"impact {cname}: {term}")
                    )
                    spec(imp.slot((-1,)))
            else:
                c, T, ok, text = items[0]
                if ok:
                    tgt, relabel_map = canonical(T)
                    via = "" if relabel_map is None else f" (relabelled from {set_name(scene, T)})"
                    transitions.append(
                        Transition(
                            src,
                            set_name(scene, tgt),
                            guard=mode_fns[A].force(j),
                            reset=_then(_identity, relabel_map),
                            name=f"lift-off {cname}: {src} -> {set_name(scene, tgt)}",
                        )
                    )
                    spec(SlotSpec(FORCE, j), relabel_map=relabel_map)
                    achievable.append((src, set_name(scene, tgt) + via, kind, cname, text))
                else:
                    term = UNBUILT + set_name(scene, T)
                    terminals[term] = None
                    transitions.append(
                        Transition(
                            src,
                            term,
                            # The search found no state with lambda_j <= -margin; a force between
                            # that and 0 (a contact that carries none, such as a wall beside a
                            # resting point, whose force is 0 up to rounding) stays held.
                            guard=mode_fns[A].force(j, margin),
                            name=f"lift-off {cname}: {src} -> {term}",
                        )
                    )
                    spec(SlotSpec(FORCE, j, margin))
                    pruned_lines.append(
                        f"  pruned: lift-off of {cname} in {src} -> {set_name(scene, T)}: {text}"
                    )
    for term in terminals:
        modes.append(Mode(term, _terminal_flow, dim=2 * n, domain=_terminal_domain, names=comp))

    candidates = {T for items in outcomes.values() for _, T, _, _ in items} | set(built)
    candidates -= set(relabel_of) - set(built)
    unreached = sorted(candidates - set(built), key=lambda s: (len(s), sorted(s)))
    report.append(
        f"contact sets built: {len(built)} of 2^{len(unilateral)} = {2 ** len(unilateral)} "
        f"({', '.join(set_name(scene, A) for A in order)})"
    )
    for src, tgt, kind, cname, text in achievable:
        report.append(f"  achievable: {kind} of {cname}: {src} -> {tgt}; {text}")
    report.extend(pruned_lines)
    for T in unreached:
        report.append(f"  pruned set {set_name(scene, T)}: no achievable transition into it was found")
    never = 2 ** len(unilateral) - len(candidates)
    if never > 0:
        report.append(
            f"  {never} other contact sets: not adjacent to a built set (no transition leads there)"
        )
    if len(values) > 1:
        report.append(
            f"  built over {len(values)} args values: a batch or a derivative across values "
            "that change the transitions found needs a system built over all of them"
        )
    if any(built[A] for A in order):
        report.append(
            "  least-norm contact forces in: " + ", ".join(set_name(scene, A) for A in order if built[A])
        )

    contact_sets = tuple(tuple(scene.constraints[i].name for i in sorted(A)) for A in order)
    contact_sets = contact_sets + (None,) * len(terminals)
    evaluation = None
    if form == "mask":
        # Slots in the engine's order: each mode's transitions in index order, then a terminal
        # mode's one domain component (-1).
        names = [m.name for m in modes]
        sources = [names.index(tr.source) for tr in transitions]
        slots = [
            tuple(slot_specs[i] for i, m_ in enumerate(sources) if m_ == m)
            + ((SlotSpec(CONSTANT, offset=-1.0),) if m >= len(order) else ())
            for m in range(len(modes))
        ]
        evaluation = ContactEvaluation(
            scene=scene,
            mode_sets=tuple(tuple(sorted(A)) for A in order) + (None,) * len(terminals),
            slots=tuple(slots),
            resets=tuple(reset_specs),
            relabel_maps=tuple(relabel_maps),
            least_norm=least_norm,
        )
    return ContactSystem(
        modes,
        transitions,
        scene=scene,
        contact_sets=contact_sets,
        least_norm_modes=tuple(built[A] for A in order) + (False,) * len(terminals),
        report=tuple(report),
        achievable=tuple(achievable),
        form=form,
        evaluation=evaluation,
    )
