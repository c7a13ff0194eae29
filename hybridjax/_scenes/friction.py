r"""Friction in scenes: stick and slip modes of frictional contacts.

A unilateral `Constraint` with a `tangent` $b(t, q)$ and a stick-slip tangential law (`laws`:
Coulomb's with $\mu \ge 0$, or any law giving a slip coefficient and stick limits) is, while
held, in one of three states, each part of the mode (named `"left:stick"`,
`"left:slip+"`, `"left:slip-"`; frictionless contacts keep their bare name):

- stick: $\dot b = 0$ held with the gap (the tangent row of the KKT system), its force
  $\lambda_t$ free, in the cone $|\lambda_t| \le \mu \lambda_n$;
- slip $s = \pm 1$ ($s \dot b > 0$): $M \ddot q = f + J_n^\top \lambda_n + J_t^\top (-\mu s
  \lambda_n)$, $J_n \ddot q = -\dot J_n \dot q$: the normal row only, its generalised force
  column $(J_n - \mu s J_t)^\top$, smooth within the mode.

Below, $\mu$ is the law's: in a slipping state's force its $\mu_\text{slip}$, in the cone
$-\mu_\text{stick}(+1) \lambda_n \le \lambda_t \le \mu_\text{stick}(-1) \lambda_n$ its stick limits,
and in the stick $\to$ slip $d$ guard $\mu_\text{stick}(d)$ (`Coefficients`; Coulomb's law: all
$\mu$).

Guards (A. M. Johnson, "Hybrid Dynamical Systems", section 1.1: the modes are the contact
conditions, each boundary of a domain a guard):

- stick $\to$ slip $d$: $\mu \lambda_n + d \lambda_t \le 0$ (the force needed to stick leaves the
  cone on the side opposite to the motion it cannot prevent), identity reset;
- slip $s \to$ stick or slip $-s$: $s \dot b \le 0$; the force the contact would need to stick
  there decides: it sticks when $|\lambda_t| \le \mu \lambda_n$ (with the other slipping
  contacts stopped at the same instant, when all of theirs are in their cones; the velocity is
  projected onto the new constraints), and otherwise slips the other way (identity reset);
- lift-off $\lambda_n \le 0$ and impacts as for frictionless contacts;
- the slip mode's normal equation is consistent while $\det(J_n M^{-1} (J_n - \mu s J_t)^\top)
  > 0$ on the held rows (positive without friction); where it falls to `PAINLEVE_RATIO` times
  its frictionless value $\det(J_n M^{-1} J_n^\top)$ (Painleve's paradox, approached) the
  execution goes to a terminal mode `"inconsistent: <mode>"` and ends with `Status.BLOCKED`.

Impacts act on the normal rows only (no tangential impulse on frictional contacts; a
`tangent` without `friction` still sticks through the impact): the frictionless impact map of
`contact_system`. Each frictional contact of the new set then slips in the direction of its
post-impact tangential velocity, `slip+` where it is $\ge 0$; one left exactly at rest meets
its slip guard at once and is decided, in a zero-length epoch, by the rule above.
"""

import functools
import itertools
import re
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax import lax
from jaxtyping import PRNGKeyArray

from .._analysis.search import SearchOptions, box_samples
from .._core import small_linalg as small_linalg
from .._definition.kernels import pick_values, select_by_mode
from .._definition.system import Mode, Transition
from .graph import ContactGraph, ExploreRules, Leaving, explore
from .indexed import SceneEvaluation, _by_mode, choice_groups
from .laws import HELD, SLIP_NEG, SLIP_POS, STICK, slip_state
from .mechanics import (
    _INDEPENDENT,
    armed_values,
    constraint_gaps,
    impact,
    impact_candidate,
    impact_gaps,
    independence,
    kinematics,
    rows,
    selection_guard,
)
from .scene import (
    FREE,
    INCONSISTENT,
    UNBUILT,
    UNILATERAL,
    AbstractContactSystem,
    Assembly,
    Scene,
    _identity,
    _releases,
    _set_fields,
    point_search_key,
    run_search,
    sample_box,
    state_names,
    witness_text,
)

SIGN = {SLIP_POS: 1.0, SLIP_NEG: -1.0}
# Sliding speeds within this fraction of 1 + max |dq| of 0 when another contact stops count as
# stopped with it (a flat body's two ends stop at one instant, up to rounding).
_SPEED_TIE = 1e-8
# Where the slip equation's determinant falls to this fraction of its frictionless value, the
# execution ends (Painleve's paradox). Not at 0: the normal force and the acceleration grow as
# 1 / det there, so an integrator's steps collapse before det reaches 0 and a guard at 0 would
# never be crossed. At this ratio the normal force is about 1e6 times its frictionless value.
PAINLEVE_RATIO = 1e-6


# ----------------------------------------------------------------------------- layout and states


@functools.cache
def _layout(scene: Scene):
    """Static arrays of a scene: row functions, `tan[k, r] = 1` where row r is the tangent of
    constraint k, and masks of the frictional and the unilateral constraints."""
    K = len(scene.constraints)
    fns, owners = rows(scene, range(K))
    tan = np.zeros((K, len(fns)))
    for r in range(K, len(fns)):
        tan[owners[r], r] = 1.0
    # The contacts whose tangential law has several states (stick and slip).
    friction = np.asarray([len(c.tangential_law.states) > 1 for c in scene.constraints], dtype=float)
    unilateral = np.asarray([c.kind == UNILATERAL for c in scene.constraints], dtype=float)
    return fns, owners, tan, friction, unilateral


class Coefficients(NamedTuple):
    r"""The constraints' tangential laws under `args`, in columns for $+1$ and $-1$: `slip`
    (K, 2), $\mu_\text{slip}$ of the state slipping with sign $s$; `stick` (K, 2), the stick
    limit $\mu_\text{stick}(d)$ for the slip direction $d$ (0 where a law has none)."""

    slip: jax.Array
    stick: jax.Array


def friction_coefficients(scene: Scene, args, dtype) -> Coefficients:
    """The `Coefficients` of every constraint's tangential law under `args`."""

    def scalar(x):
        return jnp.reshape(jnp.asarray(x, dtype), ())

    slip, stick = [], []
    for c in scene.constraints:
        law = c.tangential_law
        states = [slip_state(law, s) for s in (1.0, -1.0)]
        slip.append([scalar(0.0 if st is None else law.slip_coefficient(st, args)) for st in states])
        stick.append([scalar(law.stick_limit(d, args)) for d in (1.0, -1.0)])
    return Coefficients(jnp.stack([jnp.stack(r) for r in slip]), jnp.stack([jnp.stack(r) for r in stick]))


def slip_mu(coef: Coefficients, sign) -> jax.Array:
    r"""(K,): $\mu_\text{slip}$ of each contact slipping with sign `sign` (K,)."""
    return jnp.where(sign > 0, coef.slip[:, 0], coef.slip[:, 1])


def stick_mu(coef: Coefficients, d) -> jax.Array:
    r"""(K,): the stick limit $\mu_\text{stick}(d)$ of each contact for the slip direction `d`
    (a number or (K,))."""
    return jnp.where(d > 0, coef.stick[:, 0], coef.stick[:, 1])


def cone_margin(coef: Coefficients, lam_n, lam_t) -> jax.Array:
    r"""(K,): $\min_d (\mu_\text{stick}(d) \lambda_n + d \lambda_t)$, $\ge 0$ where the sticking
    force is in the cone (Coulomb's law: $\mu \lambda_n - |\lambda_t|$)."""
    return jnp.minimum(coef.stick[:, 0] * lam_n + lam_t, coef.stick[:, 1] * lam_n - lam_t)


def in_cone(coef: Coefficients, lam_n, lam_t) -> jax.Array:
    r"""Where $-\mu_\text{stick}(+1) \lambda_n \le \lambda_t \le \mu_\text{stick}(-1) \lambda_n$
    (the last axis: the K contacts; Coulomb's law: $|\lambda_t| \le \mu \lambda_n$)."""
    shape = (1,) * (jnp.ndim(lam_n) - 1) + (-1,)
    pos, neg = coef.stick[:, 0].reshape(shape), coef.stick[:, 1].reshape(shape)
    return (-lam_t <= pos * lam_n) & (lam_t <= neg * lam_n)


def state_name(scene: Scene, state: tuple) -> str:
    """`"left:stick+right:slip+"`: the held constraints, frictional ones with their state."""
    parts = [
        c.name if s == HELD else f"{c.name}:{s}"
        for c, s in zip(scene.constraints, state, strict=True)
        if s is not None
    ]
    return "+".join(parts) if parts else FREE


def _state_arrays(scene: Scene, state: tuple):
    """(held over constraints, held rows, slip sign over constraints) of a state."""
    owners, laws = _layout(scene)[1], [c.tangential_law for c in scene.constraints]
    K = len(scene.constraints)
    held = np.asarray([s is not None for s in state], dtype=float)
    rows_mask = np.asarray(
        [held[k] if r < K else float(state[k] is not None and laws[k].holds_tangent(state[k]))
         for r, k in enumerate(owners)]
    )  # fmt: skip
    sign = np.asarray([0.0 if s is None else law.slip_sign(s) for s, law in zip(state, laws, strict=True)])
    return held, rows_mask, sign


def parse_state(scene: Scene, spec) -> tuple:
    """A state from `"free"`, `"left:stick+right"` or a sequence of such tokens; bilateral
    constraints are always held; a frictional contact needs its state named."""
    if isinstance(spec, str):
        named = sorted({s for c in scene.constraints for s in c.tangential_law.states if s != HELD}, key=len)
        alternatives = "|".join(re.escape(s) for s in reversed(named))
        tokens = [] if spec == FREE else re.findall(rf"([^+:]+(?::(?:{alternatives}))?)\+?", spec)
    else:
        tokens = list(spec)
    state = [HELD if c.kind != UNILATERAL else None for c in scene.constraints]
    for token in tokens:
        name, _, status = token.partition(":")
        k = scene.index(name)
        c = scene.constraints[k]
        states = c.tangential_law.states
        if len(states) > 1 and status not in states:
            quoted = [f"'{name}:{s}'" for s in states]
            raise ValueError(
                f"contact_system: '{name}' has friction: name its state, {', '.join(quoted[:-1])} or "
                f"{quoted[-1]} (got {token!r})."
            )
        if len(states) == 1 and status:
            raise ValueError(f"contact_system: '{name}' has no friction, so no state ({token!r}).")
        state[k] = status or HELD
    return tuple(state)


# ----------------------------------------------------------------------------- mechanics


def friction_solve(scene: Scene, rows_mask, sign, t, q, dq, args, least_norm=False):
    r"""$\ddot q$ and the row forces $\lambda$ of a state: $M \ddot q = f + W^\top \lambda$,
    $J \ddot q = -c$ on the held rows, with $W = J$ except on a slipping contact's normal row,
    $W_k = J_k - \mu_k s_k J_{t,k}$. Returns $(\ddot q, \lambda, J, \dot a, c)$.

    `least_norm`: nearly the least-norm forces (`_regularised_solve`), for more held rows than
    coordinates: two sticking contacts of one rigid body share a tangential force they do not
    determine (a traced 0/1 factor selects it per mode; `"search"`: always). Every solve is
    written as array operations (`small_linalg`), no LAPACK call."""
    kin = kinematics(scene, _layout(scene)[0], t, q, dq, args)
    ddq, lam = friction_acceleration(scene, kin, friction_coefficients(scene, args, q.dtype), rows_mask, sign,
                                     least_norm)
    return ddq, lam, kin.J, kin.adot, kin.bias


def friction_acceleration(scene: Scene, kin, mu, rows_mask, sign, least_norm=False):
    """`friction_solve` from the state's `mechanics.Kinematics` (all rows) and coefficients."""
    n, J = scene.dim, kin.J
    W = force_columns(scene, J, mu, sign)
    m = rows_mask
    lhs = jnp.block([[kin.M, -(m[:, None] * W).T], [m[:, None] * J, jnp.diag(1.0 - m)]])
    rhs = jnp.concatenate([kin.f, -m * kin.bias])
    if least_norm is False:
        sol = small_linalg.solve(lhs, rhs)
    else:
        sol = _regularised_solve(lhs, rhs, m, n, 1.0 if isinstance(least_norm, (bool, str)) else least_norm)
    return sol[:n], sol[n:]


def _regularised_solve(lhs, rhs, m, n, factor=1.0):
    r"""A KKT solve with $-\epsilon$ on the held rows' diagonal ($\epsilon = 10^{-10}$ of the
    system's scale, times `factor`), so that dependent rows give nearly least-norm forces;
    elimination written as array operations (`small_linalg.solve`, no LAPACK call)."""
    eps = 1e-10 * jnp.max(jnp.abs(lhs[n:, :n])) ** 2 / jnp.max(jnp.abs(jnp.diag(lhs)[:n])) * factor
    return small_linalg.solve(lhs.at[n:, n:].add(-eps * jnp.diag(m)), rhs)


def _search_impact(kin, held_rows, e, n):
    r"""The impact map with the search's regularised solve, from the state's `Kinematics`:
    $(P, J \dot q^+ + a_t)$."""
    J, adot, dq = kin.J, kin.adot, kin.dq
    a_t = adot - J @ dq
    m = held_rows
    lhs = jnp.block([[kin.M, -(m[:, None] * J).T], [m[:, None] * J, jnp.diag(1.0 - m)]])
    rhs = jnp.concatenate([kin.M @ dq, m * (-e * adot - (1.0 + e) * a_t)])
    sol = _regularised_solve(lhs, rhs, m, n)
    return sol[n:], J @ sol[:n] + a_t


def slip_consistency(scene: Scene, rows_mask, sign, t, q, args):
    r"""The Painleve guard of a slip state, on the held rows (identity on the others):
    $\det(J M^{-1} W^\top) - \rho \det(J M^{-1} J^\top)$, $W$ from `force_columns`, $\rho$ =
    `PAINLEVE_RATIO`. Positive without friction; where it reaches 0 the slip mode's contact
    forces are about $1/\rho$ times their frictionless values, and undetermined where the first
    determinant reaches 0 (Painleve's paradox)."""
    kin = kinematics(scene, _layout(scene)[0], t, q, jnp.zeros_like(q), args)
    return consistency(scene, kin, friction_coefficients(scene, args, q.dtype), rows_mask, sign)


def force_columns(scene: Scene, J, mu, sign):
    r"""$W$: the rows' generalised force directions, $J$ except on a slipping contact's normal
    row, $W_k = J_k - \mu_k s_k J_{t,k}$, $\mu_k$ its law's $\mu_\text{slip}$ (`mu`: the
    `Coefficients`)."""
    K, tan = len(scene.constraints), _layout(scene)[2]
    return J.at[:K].add(-(slip_mu(mu, sign) * sign)[:, None] * (jnp.asarray(tan, J.dtype) @ J))


def consistency(scene: Scene, kin, mu, rows_mask, sign):
    """`slip_consistency` from the state's `mechanics.Kinematics` (all rows)."""
    m = rows_mask
    held, free = m[:, None] * m[None, :], jnp.diag(1.0 - m)
    # W = F J (`force_columns` is linear in J), so J M^-1 W^T = G F^T with G = J M^-1 J^T.
    F = force_columns(scene, jnp.eye(kin.J.shape[0], dtype=kin.J.dtype), mu, sign)
    coupled = held * (kin.G @ F.T) + free
    frictionless = held * kin.G + free
    return small_linalg.det(coupled) - PAINLEVE_RATIO * small_linalg.det(frictionless)


def stop_ties(kin, ddq, tan, dq):
    r"""(K, K): `[j, i]` true where contacts j and i stop at one instant: their sliding speeds
    $v$ and accelerations $a$ (tangent rows) give the same time to zero, $v_i a_j = v_j a_i$
    within `_SPEED_TIE` $(1 + \max|\dot q|)(|a_i| + |a_j|)$. Time-to-zero rather than
    speed: at a state past the instant (the end of an integrator's step) two contacts that
    stop together have equal times, not speeds near 0."""
    tan = jnp.asarray(tan, kin.J.dtype)
    v, a = tan @ kin.adot, tan @ (kin.J @ ddq + kin.bias)
    cross = jnp.abs(v[None, :] * a[:, None] - v[:, None] * a[None, :])
    scale = _SPEED_TIE * (1.0 + jnp.max(jnp.abs(dq))) * (jnp.abs(a)[:, None] + jnp.abs(a)[None, :])
    return cross <= scale


def stop_decision(scene: Scene, state: tuple, j: int, kin, mu, dq):
    """Where slipping contact j of `state` stops: (the index in `stop_subsets(state, j)` of the
    other slipping contacts stopped with it (`stop_ties`); whether all of those and j, stuck,
    have their forces in their cones)."""
    tan = _layout(scene)[2]
    row = [int(np.argmax(tan[i])) for i in range(len(state))]
    others = others_slipping(state, j)
    _, rows_now, sign_now = _state_arrays(scene, state)
    ddq = friction_acceleration(scene, kin, mu, jnp.asarray(rows_now, kin.J.dtype),
                                jnp.asarray(sign_now, kin.J.dtype), bool(rows_now.sum() > scene.dim))[0]
    ties = stop_ties(kin, ddq, tan, dq)
    stopped = [ties[j, i] for i in others]
    which, inside = jnp.array(-1), jnp.array(False)
    for c, members in enumerate(stop_subsets(state, j)):
        match = jnp.all(jnp.stack([stopped[others.index(i)] == (i in members) for i in others] + [True]))
        stuck = tuple(STICK if i in (j, *members) else st for i, st in enumerate(state))
        _, rows_mask, sign = _state_arrays(scene, stuck)
        lam = friction_acceleration(scene, kin, mu, jnp.asarray(rows_mask, kin.J.dtype),
                                    jnp.asarray(sign, kin.J.dtype), bool(rows_mask.sum() > scene.dim))[1]
        inside_all = in_cone(mu, lam[:len(state)], jnp.stack([lam[r] for r in row]))
        ok = jnp.all(jnp.stack([inside_all[i] for i in (j, *members)]))
        which, inside = jnp.where(match, c, which), jnp.where(match, ok, inside)
    return which, inside


def others_slipping(state: tuple, j: int) -> tuple:
    return tuple(i for i, st in enumerate(state) if st in SIGN and i != j)


def stop_subsets(state: tuple, j: int) -> list:
    """The sets of other slipping contacts that can stop with j: none, then one, then two..."""
    others = others_slipping(state, j)
    return [c for size in range(len(others) + 1) for c in itertools.combinations(others, size)]


def stop_goes(which, inside, subsets, to_stick: bool, tied: tuple):
    """Whether the stop transition (to stick with the contacts `tied`, or to reverse) is taken."""
    return (inside & (which == subsets.index(tied))) if to_stick else ~inside


class _StateFunctions(eqx.Module):
    """Flow, forces and guards of one friction state (static descriptors)."""

    # Static: a mode's flow and guards are these objects, leaves of the system's pytree; the
    # scene (callables) and the state (Python indices) choose the code traced.
    scene: Scene = eqx.field(static=True)
    state: tuple = eqx.field(static=True)

    def _arrays(self, dtype):
        _, rows_mask, sign = _state_arrays(self.scene, self.state)
        return jnp.asarray(rows_mask, dtype), jnp.asarray(sign, dtype)

    def solve(self, t, x, args):
        n = self.scene.dim
        rows_mask, sign = self._arrays(x.dtype)
        least_norm = int(_state_arrays(self.scene, self.state)[1].sum()) > n
        ddq, lam, J, rate, bias = friction_solve(
            self.scene, rows_mask, sign, t, x[:n], x[n:], args, least_norm
        )
        return ddq, lam, rate

    def flow(self, t, x, args):
        return jnp.concatenate([x[self.scene.dim :], self.solve(t, x, args)[0]])

    def normal(self, j, offset=0.0):
        """lambda_n of held contact j (+ offset): its lift-off guard."""
        return lambda t, x, args: self.solve(t, x, args)[1][j] + offset

    def cone(self, j, d, offset=0.0):
        """mu_stick(d) lambda_n + d lambda_t of sticking contact j (+ offset): its guard into slip d."""
        tan = _layout(self.scene)[2]
        r = int(np.argmax(tan[j]))

        def g(t, x, args):
            lam = self.solve(t, x, args)[1]
            mu = friction_coefficients(self.scene, args, x.dtype).stick[j, 0 if d > 0 else 1]
            return mu * lam[j] + d * lam[r] + offset

        return g

    def others_slipping(self, j) -> tuple:
        return others_slipping(self.state, j)

    def stop(self, j, to_stick: bool, tied: tuple = ()):
        """s v_t of slipping contact j where the stop rule sends it (`to_stick`: it sticks with
        the other slipping contacts `tied`, those stopped at the same instant; otherwise it
        slips back; `stop_decision`), positive elsewhere (`mechanics.selection_guard`)."""
        s = SIGN[self.state[j]]
        tan = _layout(self.scene)[2]
        r = int(np.argmax(tan[j]))
        subsets = stop_subsets(self.state, j)
        n = self.scene.dim

        def g(t, x, args):
            v = s * self.solve(t, x, args)[2][r]
            # Which way it goes is a discrete choice: no derivative flows through it.
            t_, x_, a_ = jax.lax.stop_gradient((t, x, args))
            kin = kinematics(self.scene, _layout(self.scene)[0], t_, x_[:n], x_[n:], a_)
            mu = friction_coefficients(self.scene, a_, x.dtype)
            which, inside = stop_decision(self.scene, self.state, j, kin, mu, x_[n:])
            return selection_guard(v, stop_goes(which, inside, subsets, to_stick, tied))

        return g

    def project(self, t, x, args):
        """The velocity projected through M onto this state's held rows (a plastic impulse):
        the reset into a stick state, so that its tangential speed is exactly 0."""
        n = self.scene.dim
        _, rows_mask, _ = _state_arrays(self.scene, self.state)
        fns = _layout(self.scene)[0]
        zeros = jnp.zeros(len(fns), x.dtype)
        least_norm = int(rows_mask.sum()) > n
        dq = impact(
            self.scene, fns, jnp.asarray(rows_mask, x.dtype), zeros, t, x[:n], x[n:], args, least_norm
        )[0]
        return jnp.concatenate([x[:n], dq])

    def consistency(self, t, x, args):
        rows_mask, sign = self._arrays(x.dtype)
        return slip_consistency(self.scene, rows_mask, sign, t, x[: self.scene.dim], args)

    def forces(self, t, x, args):
        """Row forces: normal forces, then tangential ones (a slipping contact's friction
        force -mu_slip s lambda_n), 0 on rows not held."""
        rows_mask, sign = self._arrays(x.dtype)
        lam = self.solve(t, x, args)[1]
        K = len(self.scene.constraints)
        friction = -slip_mu(friction_coefficients(self.scene, args, x.dtype), sign) * sign * lam[:K]
        return lam * rows_mask + jnp.asarray(_layout(self.scene)[2], x.dtype).T @ friction


class _FrictionImpact(eqx.Module):
    """Impact of constraint `k` in state `source`: release candidates as in `contact_system`,
    then the frictional contacts of the new set slip by the sign of their tangential velocity.
    Outcomes are (candidate, signs), numbered by `outcome_id`."""

    # Static: a reset of the system's pytree; callables and Python indices.
    scene: Scene = eqx.field(static=True)
    source: tuple = eqx.field(static=True)
    k: int = eqx.field(static=True)
    candidates: tuple = eqx.field(static=True)

    def new_set(self, c) -> tuple:
        held = {i for i, s in enumerate(self.source) if s is not None} | {self.k}
        held -= set(self.candidates[c])
        if self.scene.constraints[self.k].restitutes:
            held.discard(self.k)
        return tuple(sorted(held))

    def frictional(self, c) -> tuple:
        """The contacts of the new set whose tangential law has several states."""
        friction = _layout(self.scene)[3]
        return tuple(i for i in self.new_set(c) if friction[i])

    @property
    def outcomes(self) -> tuple:
        return tuple(
            (c, signs)
            for c in range(len(self.candidates))
            for signs in itertools.product((1.0, -1.0), repeat=len(self.frictional(c)))
        )

    def target(self, outcome) -> tuple:
        c, signs = outcome
        held = set(self.new_set(c))
        slip = dict(zip(self.frictional(c), signs, strict=True))
        laws = [c.tangential_law for c in self.scene.constraints]
        return tuple(
            None if i not in held else (slip_state(laws[i], slip[i]) if i in slip else HELD)
            for i in range(len(self.scene.constraints))
        )

    def held_rows(self, c, dtype=None):
        """The rows the impact holds (a numpy array): the new set's gaps (and k's), and the
        tangents of contacts that stick without a friction limit."""
        _, owners, _, friction, _ = _layout(self.scene)
        keep = set(self.new_set(c)) | {self.k}
        K = len(self.scene.constraints)
        held = [float(i in keep and (r < K or not friction[i])) for r, i in enumerate(owners)]
        return np.asarray(held, dtype)

    def outcome(self, c, t, x, args):
        n = self.scene.dim
        fns = _layout(self.scene)[0]
        e = self.restitution(args, x.dtype)
        return impact(self.scene, fns, jnp.asarray(self.held_rows(c), x.dtype), e, t, x[:n], x[n:], args)

    def outcome_tables(self):
        """Per candidate: the rows held, the bit of each frictional contact of the new set in
        the outcome's code, and the index of its first outcome; the gap rows involved."""
        _, owners, _, _, _ = _layout(self.scene)
        K, C = len(self.scene.constraints), len(self.candidates)
        held = np.stack([self.held_rows(c) for c in range(C)])
        bits, offsets, offset = np.zeros((C, K)), np.zeros(C, int), 0
        for c in range(C):
            fr = self.frictional(c)
            # In the order of `itertools.product((1, -1), ...)`: the first contact most
            # significant, 1 for slip-.
            for b, i in enumerate(fr):
                bits[c, i] = 2 ** (len(fr) - 1 - b)
            offsets[c] = offset
            offset += 2 ** len(fr)
        source = {i for i, st in enumerate(self.source) if st is not None} | {self.k}
        # The unilateral constraints' gap rows: a joint's impulse has either sign.
        uni = _layout(self.scene)[4]
        gap_rows = np.asarray([r < K and o in source and uni[o] > 0 for r, o in enumerate(owners)])
        return held, bits, offsets, gap_rows

    def outcome_from(self, kin, e):
        """The index in `outcomes` of what happens at the state of `kin` (all rows; `e` the
        restitution on k's gap row), -1 if no candidate solves the impact
        (`mechanics.impact_candidate`): the first that does, and the signs of the new set's
        frictional contacts' tangential velocities after it."""
        held, bits, offsets, gap_rows = self.outcome_tables()
        tan = jnp.asarray(_layout(self.scene)[2], kin.J.dtype)
        every = jnp.ones(held.shape[1], bool)
        ok, rates = jax.vmap(lambda h: impact_candidate(kin, h, e, every, jnp.asarray(gap_rows)))(
            jnp.asarray(held, kin.J.dtype)
        )
        code = jnp.sum(jnp.asarray(bits, kin.J.dtype) * ((rates @ tan.T) < 0), axis=1).astype(jnp.int32)
        c = jnp.argmax(ok)
        return jnp.where(jnp.any(ok), jnp.asarray(offsets, jnp.int32)[c] + code[c], -1).astype(jnp.int32)

    def restitution(self, args, dtype):
        """(rows,): k's coefficient on its gap row."""
        R = len(_layout(self.scene)[0])
        e_k = jnp.asarray(self.scene.constraints[self.k].coefficient(args), dtype)
        return jnp.zeros(R, dtype).at[self.k].set(e_k)

    def outcome_id(self, t, x, args):
        """`outcome_from` at (t, x)."""
        n = self.scene.dim
        kin = kinematics(self.scene, _layout(self.scene)[0], t, x[:n], x[n:], args)
        return self.outcome_from(kin, self.restitution(args, x.dtype))

    def guard(self, ids: tuple):
        """a_k where the outcome is one of `ids` (-1: none valid), positive elsewhere."""
        n = self.scene.dim

        def g(t, x, args):
            gaps = constraint_gaps(self.scene, t, x[:n], args)
            a = impact_gaps(self.scene, t, x[:n], args, gaps)[self.k]
            got = self.outcome_id(*jax.lax.stop_gradient((t, x, args)))
            return selection_guard(a, jnp.any(jnp.stack([got == i for i in ids])))

        return g

    def reset(self, c):
        n = self.scene.dim

        def r(t, x, args):
            return jnp.concatenate([x[:n], self.outcome(c, t, x, args)[0]])

        return r


# ----------------------------------------------------------------------------- search queries


class _FQuery(eqx.Module):
    """One witness search, as arrays (K: constraints, R: rows) so one compiled search checks a
    level's queries under vmap."""

    held: jax.Array  # (K) source's held constraints
    rows: jax.Array  # (R) source's held rows
    sign: jax.Array  # (K) source's slip signs
    flowing: jax.Array  # () source's domain required (held forces >= 0, sticking forces in the cone)
    lift: jax.Array  # (K) one-hot lift-off
    unstick: jax.Array  # (K) one-hot stick -> slip
    direction: jax.Array  # () the slip direction d of `unstick`
    stop: jax.Array  # (K) one-hot slip -> stick or reverse
    tied: jax.Array  # (K) slipping contacts stopped at the same instant (they stick with it)
    to_stick: jax.Array  # () 1: the stop sticks, 0: it reverses
    hit: jax.Array  # (K) one-hot impact
    impact_rows: jax.Array  # (R) rows the impact holds
    released: jax.Array  # (K) released constraints
    post: jax.Array  # (K) required sign of the tangential velocity after the impact (0: any)


@functools.cache
def _friction_queries(scene: Scene, margin: float):
    fns, owners, tan_np, friction_np, unilateral_np = _layout(scene)
    K, n = len(scene.constraints), scene.dim

    def parts(t, x, p):
        args, Q = p
        q, dq = x[:n], x[n:]
        dt = x.dtype
        tan, fr, uni = (jnp.asarray(a, dt) for a in (tan_np, friction_np, unilateral_np))
        mu = friction_coefficients(scene, args, dt)
        kin = kinematics(scene, fns, t, q, dq, args)
        a, J, rate, bias = kin.gap[:K], kin.J, kin.adot, kin.bias
        open_gap = impact_gaps(scene, t, q, args, kin.gap)
        armed = armed_values(scene, t, q, args)
        ddq, lam = friction_acceleration(scene, kin, mu, Q.rows, Q.sign, "search")
        lam_n, lam_t, v_t = lam[:K], tan @ lam, tan @ rate
        acc_t = tan @ (J @ ddq + bias)
        # The stopping contacts' forces were they to stick here.
        stopping = Q.stop + Q.tied
        stuck_rows, stuck_sign = Q.rows + tan.T @ stopping, Q.sign * (1 - stopping)
        lam2 = friction_acceleration(scene, kin, mu, stuck_rows, stuck_sign, "search")[1]
        lam2_n, lam2_t = lam2[:K], tan @ lam2
        e = jnp.stack([jnp.asarray(c.coefficient(args), dt) for c in scene.constraints]) * Q.hit
        e = jnp.concatenate([e, jnp.zeros(len(fns) - K, dt)])
        P, rates_plus = _search_impact(kin, Q.impact_rows, e, n)
        stuck = fr * (tan @ Q.rows)
        slipping = jnp.abs(Q.sign)
        s = Q.sign
        one = jnp.ones_like(a)
        eq = jnp.concatenate([Q.held * a, Q.rows * rate, Q.hit * a, stopping * v_t])

        def where(mask, value):
            return jnp.where(mask > 0, value, one)

        ineq = jnp.concatenate(
            [
                where(uni * (1 - Q.held) * (1 - Q.hit), open_gap),
                where(Q.hit, armed),
                where(slipping * (1 - stopping), s * v_t),
                where(uni * Q.held * Q.flowing * (1 - Q.lift), lam_n),
                where(stuck * Q.flowing * (1 - Q.unstick), cone_margin(mu, lam_n, lam_t)),
                where(Q.lift, -lam_n - margin),
                where(Q.unstick, -(stick_mu(mu, Q.direction) * lam_n + Q.direction * lam_t) - margin),
                where(Q.stop, -s * acc_t - margin),
                where(stopping * Q.to_stick, cone_margin(mu, lam2_n, lam2_t)),
                # It slips back (direction -s) where the sticking force leaves the cone on that side.
                where(Q.stop * (1 - Q.to_stick), s * lam2_t - stick_mu(mu, -s) * lam2_n - margin),
                where(Q.hit, -rate[:K] - margin),
                where(Q.impact_rows[:K] * uni, P[:K]),
                where(Q.released, rates_plus[:K]),
                where(jnp.abs(Q.post), Q.post * (tan @ rates_plus)),
            ]
        )
        # Non-finite values (a singular system at a sample) count as violated, finite, so no NaN
        # reaches the least-squares solve.
        eq = jnp.where(jnp.isfinite(eq), eq, 1e6)
        return eq, jnp.where(jnp.isfinite(ineq), ineq, -1e6)

    return parts


def _query(scene: Scene, state: tuple, **kw) -> _FQuery:
    K = len(scene.constraints)
    R = len(_layout(scene)[0])
    held, rows_mask, sign = _state_arrays(scene, state)
    dt = jnp.result_type(float)
    fields = dict(
        held=held,
        rows=rows_mask,
        sign=sign,
        flowing=1.0,
        lift=np.zeros(K),
        unstick=np.zeros(K),
        direction=0.0,
        stop=np.zeros(K),
        tied=np.zeros(K),
        to_stick=0.0,
        hit=np.zeros(K),
        impact_rows=np.zeros(R),
        released=np.zeros(K),
        post=np.zeros(K),
    )
    for key, value in kw.items():
        if isinstance(value, tuple):  # (index, value) for a one-hot
            arr = np.zeros(K)
            arr[value[0]] = value[1]
            value = arr
        fields[key] = value
    return _FQuery(**{k: jnp.asarray(v, dt) for k, v in fields.items()})


def _run(scene, queries, args_batch, samples, margin, search):
    return run_search(_friction_queries(scene, margin), queries, args_batch, samples, search)


# ----------------------------------------------------------------------------- the system


class FrictionSystem(AbstractContactSystem):
    r"""The contact system of a scene with friction (as `ContactSystem`, with the same fields and
    methods): `states` gives, for each mode, the state of
    every constraint (`None` open, `"held"`, `"stick"`, `"slip+"`, `"slip-"`; `None` for the
    whole entry of a terminal mode). `contact_forces` reports a slipping contact's tangential
    column as its friction force $-\mu s \lambda_n$."""

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
    evaluation: "FrictionEvaluation | None" = eqx.field(static=True)
    states: tuple = eqx.field(static=True)

    def __init__(self, modes, transitions, *, states, evaluation=None, **fields):
        self.states = states
        _set_fields(self, modes, transitions, evaluation=evaluation, **fields)

    def _force_function(self) -> Callable:
        built = [(m, s) for m, s in enumerate(self.states) if s is not None]
        fns = [_StateFunctions(self.scene, s).forces for _, s in built]
        index = np.full(self.num_modes, -1)
        for b, (m, _) in enumerate(built):
            index[m] = b

        def one(t, y, mode, args):
            b = jnp.asarray(index)[jnp.maximum(mode, 0)]
            ok = (mode >= 0) & jnp.isfinite(t) & (b >= 0)
            y = jnp.where(ok, y, 0.0)
            t = jnp.where(ok, t, 0.0)
            lam = jax.lax.switch(jnp.maximum(b, 0), fns, t, y, args)
            return jnp.where(ok, lam, jnp.nan)

        return one


def _friction_impact(scene: Scene, S: tuple, k: int) -> _FrictionImpact:
    """The impact of `k` in state `S`, with the release candidates of its held unilateral contacts."""
    unilateral = _layout(scene)[4]
    held = {i for i, s in enumerate(S) if s is not None and unilateral[i]}
    return _FrictionImpact(scene, S, k, tuple(tuple(sorted(r)) for r in _releases(held)))


class _Rules(ExploreRules):
    """The explorer's rules for friction states (per constraint: None, held, stick, slip+, slip-)."""

    noun = "states"

    def __init__(self, scene: Scene, values: list, key, num_samples: int, margin: float,
                 search: SearchOptions):  # fmt: skip
        dtype = jnp.result_type(float)
        self.scene, self.margin, self.options, self.dtype = scene, margin, search, dtype
        self.args_batch = (
            jnp.arange(len(values)),
            jtu.tree_map(lambda *v: jnp.stack([jnp.asarray(x, dtype) for x in v]), *values),
        )
        pts = box_samples(point_search_key(key, None), tuple(sample_box(scene, dtype)), num_samples)
        self.samples = (pts[:, -1], pts[:, :-1])

    def search(self, queries):
        return _run(self.scene, queries, self.args_batch, self.samples, self.margin, self.options)

    def outcome(self, w, i):
        found_v = w.found[i]
        if found_v.any():
            return tuple(int(a) for a in np.flatnonzero(found_v)), witness_text(w, i, self.scene.dim)
        least = np.nanmin(w.violation[i])
        return (), f"no state of the source found in the guard (least violation {least:.2g})"

    def leaving(self, S):
        scene, K = self.scene, len(self.scene.constraints)
        unilateral = _layout(scene)[4]
        for k in sorted(i for i in range(K) if unilateral[i] and S[i] is None):
            imp = _friction_impact(scene, S, k)
            for o, (c, signs) in enumerate(imp.outcomes):
                post, released = np.zeros(K), np.zeros(K)
                post[list(imp.frictional(c))] = signs
                released[list(imp.candidates[c])] = 1.0
                query = _query(scene, S, hit=(k, 1.0), impact_rows=np.asarray(imp.held_rows(c, self.dtype)),
                               released=released, post=post)  # fmt: skip
                yield Leaving("impact", k, o, imp.target((c, signs)), query)
        for j in sorted(i for i, s in enumerate(S) if s is not None and unilateral[i]):
            query = _query(scene, S, lift=(j, 1.0), flowing=0.0)
            yield Leaving("lift-off", j, None, S[:j] + (None,) + S[j + 1 :], query)
            for kind, detail, status in scene.constraints[j].tangential_law.changes(S[j]):
                if kind == "slip":  # a sticking contact starts slipping in direction `detail`
                    query = _query(scene, S, unstick=(j, 1.0), direction=detail)
                    yield Leaving("slip", j, detail, S[:j] + (status,) + S[j + 1 :], query)
                elif detail is not None:  # a slipping one stops and sticks, with those `tied` to it
                    for tied in stop_subsets(S, j):
                        mask = np.zeros(K)
                        mask[list(tied)] = 1.0
                        T = tuple(status if i in (j, *tied) else st for i, st in enumerate(S))
                        query = _query(scene, S, stop=(j, 1.0), tied=mask, to_stick=1.0)
                        yield Leaving("stop", j, tied, T, query)
                else:  # it stops and slips back
                    query = _query(scene, S, stop=(j, 1.0), to_stick=0.0)
                    yield Leaving("stop", j, None, S[:j] + (status,) + S[j + 1 :], query)


def _check_values(scene: Scene, values: list) -> None:
    """The scene's shapes, and the tangential laws' coefficients (>= 0, and the law's own
    `check`) at every `args` value."""
    if not values:
        raise ValueError("contact_system: `args_values` is empty.")
    dtype = jnp.result_type(float)
    for v in values:
        scene.check(v)
        coef = friction_coefficients(scene, v, dtype)
        mus = np.concatenate([np.asarray(coef.slip), np.asarray(coef.stick)], axis=1)
        for c, mu in zip(scene.constraints, mus, strict=True):
            bad = next((m for m in mu if not m >= 0), None)
            if bad is not None:
                raise ValueError(
                    f"Constraint '{c.name}': the friction coefficient must be >= 0, got {bad} for args {v!r}."
                )
            problem = c.tangential_law.check(v)
            if problem is not None:
                raise ValueError(f"Constraint '{c.name}': {problem} for args {v!r}.")


def _initial_states(scene: Scene, rules: _Rules, initial: Sequence, values: list) -> list:
    """The initial states: each with a consistent state in the scene's ranges, its held
    constraints independent."""
    n, fns = scene.dim, _layout(scene)[0]
    initial_states = list(dict.fromkeys(parse_state(scene, s) for s in initial))
    if not initial_states:
        raise ValueError("contact_system: give at least one initial contact set.")
    w = rules.search([_query(scene, S, flowing=0.0) for S in initial_states])
    for i, S in enumerate(initial_states):
        if not w.found[i].any():
            raise ValueError(
                f"contact_system: the initial state {state_name(scene, S)} has no consistent state in "
                f"the scene's ranges (least violation {np.nanmin(w.violation[i]):.2g})."
            )
        v = int(np.argmax(w.found[i]))
        rows_mask = jnp.asarray(_state_arrays(scene, S)[1], rules.dtype)
        if (
            independence(scene, fns, rows_mask, w.t[i, v], jnp.asarray(w.x[i, v, :n]), values[v])
            <= _INDEPENDENT
        ):
            names = [scene.constraints[j].name for j, s in enumerate(S) if s is not None]
            raise ValueError(
                f"contact_system: the initial state {state_name(scene, S)} has dependent constraints "
                f"{names} (redundant contacts); remove one of them."
            )
    return initial_states


def friction_system(
    scene: Scene,
    initial: Sequence,
    args: Any = None,
    *,
    args_values: Sequence | None = None,
    num_samples: int = 512,
    margin: float = 1e-3,
    key: PRNGKeyArray | None = None,
    redundant: str = "error",
    max_modes: int = 64,
    relabels: Sequence = (),
    form: str = "mask",
    search: SearchOptions = SearchOptions(),
) -> FrictionSystem:
    """`contact_system` for a scene with frictional contacts (see the module notes): its graph
    of friction states, assembled."""
    if relabels:
        raise ValueError("contact_system: `relabels` are not available for scenes with friction.")
    if redundant != "error":
        raise ValueError(
            "contact_system: scenes with friction need independent contacts (redundant='error')."
        )
    values = list(args_values) if args_values is not None else [args]
    _check_values(scene, values)
    rules = _Rules(scene, values, key, num_samples, margin, search)
    graph = explore(rules, _initial_states(scene, rules, initial, values), max_modes)
    return _assemble(scene, graph, margin, len(values), form)


# ----------------------------------------------------------------------------- mode-indexed evaluation


# `FrictionSlot` and `FrictionReset` are plain Python data read while a step is traced; they live
# in the static fields of `FrictionEvaluation`, so their own fields are ordinary ones.
class FrictionSlot(eqx.Module):
    """One watched function of a friction mode, as `FrictionEvaluation` reads it: `kind`
    "painleve" (the slip consistency), "impact" (constraint `j`'s gap where the impact's
    outcome is one of `ids`), "lift" (normal force of `j` + `offset`), "cone" (mu lambda_n +
    `d` lambda_t of `j` + `offset`), "stop" (s v_t of slipping `j` of `state` where the stop
    goes to stick with `tied` (`to_stick`) or to reverse), or "constant" (`offset`)."""

    kind: str
    j: int = 0
    offset: float = 0.0
    d: float = 0.0
    ids: tuple = ()
    impact: Any = None
    state: tuple | None = None
    to_stick: bool = False
    tied: tuple = ()


class FrictionReset(eqx.Module):
    """The reset of one transition: the identity (`rows` None), or the impact map with the rows
    `rows` held (restitution of constraint `hit`, when `restitute`) and least-norm impulses
    when `least_norm` (a projection onto a stick state's rows is a plastic impact)."""

    rows: tuple | None = None
    hit: int = 0
    restitute: bool = False
    least_norm: bool = False


class _Parts(NamedTuple):
    """What a friction mode's watched values read (`FrictionEvaluation._parts`): the
    kinematics, the friction coefficients, the mode's solve (accelerations `ddq`, row forces
    `lam`) and its rows and slip signs, the impacts' gaps, the rows' rates, and the slip
    consistency where a mode watches it (else None)."""

    kin: Any
    mu: Coefficients
    ddq: jax.Array
    lam: jax.Array
    rows_mask: jax.Array
    sign: jax.Array
    gaps: jax.Array
    rate: jax.Array
    consistency: jax.Array | None


class FrictionEvaluation(SceneEvaluation):
    """A friction system evaluated for the traced mode: every state is one friction solve
    (`friction_acceleration`) with the state's held rows, slip signs and least-norm flag, looked
    up in tables by the mode; the guards read its forces and the kinematics' rates, and the
    discrete choices (an impact's outcome, where a stopping contact goes) are computed, in `watch`,
    only where one of the current mode's guards that reads them is at or below zero, and for the
    engines (`locate_watch`, `select`) once, at the located event."""

    # Static: the tables that choose the code traced.
    states: tuple = eqx.field(static=True)
    slots: tuple = eqx.field(static=True)
    resets: tuple = eqx.field(static=True)

    def _tables(self):
        R = len(_layout(self.scene)[0])
        K = len(self.scene.constraints)
        rows_t, sign_t, least_t = [], [], []
        for S in self.states:
            if S is None:
                rows_t.append(np.zeros(R)), sign_t.append(np.zeros(K)), least_t.append(0.0)
                continue
            _, rows_mask, sign = _state_arrays(self.scene, S)
            rows_t.append(rows_mask), sign_t.append(sign)
            least_t.append(float(rows_mask.sum() > self.scene.dim))
        return np.stack(rows_t), np.stack(sign_t), np.asarray(least_t)[:, None]

    def _solve(self, mode, kin, mu, dtype):
        rows_t, sign_t, least_t = self._tables()
        least = _by_mode(mode, least_t, dtype)[0] if least_t.any() else False
        rows_mask, sign = _by_mode(mode, rows_t, dtype), _by_mode(mode, sign_t, dtype)
        return friction_acceleration(self.scene, kin, mu, rows_mask, sign, least), rows_mask, sign

    def _terminal(self) -> tuple:
        return tuple(S is None for S in self.states)

    def _acceleration(self, mode, kin, args, dtype):
        return self._solve(mode, kin, friction_coefficients(self.scene, args, dtype), dtype)[0]

    def _solved(self, mode, t, y, args):
        """The kinematics at (t, y), the friction coefficients and `mode`'s solve."""
        kin = self._kinematics(t, y, args)
        mu = friction_coefficients(self.scene, args, y.dtype)
        (ddq, lam), rows_mask, sign = self._solve(mode, kin, mu, y.dtype)
        return kin, mu, ddq, lam, rows_mask, sign

    def _parts(self, mode, t, y, args) -> _Parts:
        """Everything `mode`'s watched values read at (t, y) (`_Parts`)."""
        kin, mu, ddq, lam, rows_mask, sign = self._solved(mode, t, y, args)
        gaps = impact_gaps(self.scene, t, y[: self.scene.dim], args, kin.gap)
        value = None
        if any(sp.kind == "painleve" for specs in self.slots for sp in specs):
            value = consistency(self.scene, kin, mu, rows_mask, sign)
        return _Parts(kin, mu, ddq, lam, rows_mask, sign, gaps, kin.adot, value)

    def _slot_value(self, sp: FrictionSlot, parts: _Parts, taken=None) -> jax.Array:
        """The watched value of slot `sp`: for a choice's slot (an impact's, a stop's) the value
        the choice's slots share (the gap, the slip speed), as the selection guard of the
        outcomes the slot takes where `taken` is given."""
        row = int(np.argmax(_layout(self.scene)[2][sp.j])) if sp.kind in ("cone", "stop") else 0
        if sp.kind == "painleve":
            return parts.consistency
        if sp.kind == "lift":
            return parts.lam[sp.j] + sp.offset
        if sp.kind == "cone":
            mu = parts.mu.stick[sp.j, 0 if sp.d > 0 else 1]
            return mu * parts.lam[sp.j] + sp.d * parts.lam[row] + sp.offset
        if sp.kind not in ("impact", "stop"):
            return jnp.asarray(sp.offset, parts.kin.dq.dtype)
        value = parts.gaps[sp.j] if sp.kind == "impact" else SIGN[sp.state[sp.j]] * parts.rate[row]
        return value if taken is None else selection_guard(value, taken)

    @staticmethod
    def _taken(sp: FrictionSlot, got, which, inside) -> jax.Array:
        """Whether slot `sp` takes its choice's outcome: the impacts' outcomes `got` (K,), the
        stops' decisions `which`, `inside` (K,) (`_impact_outcomes`, `_stop_decisions`)."""
        if sp.kind == "impact":
            return jnp.any(jnp.stack([got[sp.j] == i for i in sp.ids]))
        if sp.kind == "stop":
            return stop_goes(which[sp.j], inside[sp.j], stop_subsets(sp.state, sp.j), sp.to_stick, sp.tied)
        return jnp.array(True)

    def _by_slots(self, mode, value, dtype) -> jax.Array:
        """`value(sp, s, m)` of every slot `s` of every mode `m`, that of `mode` selected."""
        rows = [[value(sp, s, m) for s, sp in enumerate(specs)] for m, specs in enumerate(self.slots)]
        return select_by_mode(mode, rows, max(map(len, self.slots), default=0), 1.0, dtype)

    def watch(self, mode, t, y, args) -> jax.Array:
        n, K = self.scene.dim, len(self.scene.constraints)
        parts = self._parts(mode, t, y, args)
        # The discrete choices of the current mode (an impact's outcome per constraint, a stop's
        # decision per slipping contact), each one vmapped solve without gradients, computed
        # only where a guard of the current mode that reads one is at or below zero.
        imp_t, stop_t = self._impact_tables(), self._stop_tables()
        has_impact = _by_mode(mode, imp_t["present"].any(axis=2).astype(float), y.dtype) > 0
        has_stop = _by_mode(mode, stop_t["present"].any(axis=2).astype(float), y.dtype) > 0
        slipping = parts.sign != 0
        speeds = parts.sign * (jnp.asarray(_layout(self.scene)[2], y.dtype) @ parts.rate)
        need = jnp.any(has_impact & (parts.gaps <= 0)) | jnp.any(has_stop & slipping & (speeds <= 0))
        kin_sg, mu_sg, y_sg, args_sg, ddq_sg = lax.stop_gradient((parts.kin, parts.mu, y, args, parts.ddq))

        def choices():
            got = self._impact_outcomes(mode, kin_sg, args_sg, imp_t, y.dtype)
            which, inside = self._stop_decisions(mode, kin_sg, mu_sg, y_sg[n:], ddq_sg, stop_t, y.dtype)
            return got, which, inside

        none = (jnp.full(K, -1, jnp.int32), jnp.full(K, -1, jnp.int32), jnp.zeros(K, bool))
        got, which, inside = lax.cond(eqxi.unvmap_any(need), choices, lambda: none)

        def value(sp, s, m):
            choice = sp.kind in ("impact", "stop")
            return self._slot_value(sp, parts, self._taken(sp, got, which, inside) if choice else None)

        return self._by_slots(mode, value, y.dtype)

    def _groups(self) -> list:
        """Per mode, `choice_groups` of its slots: an impact's outcomes of one constraint, a
        stop's outcomes of one slipping contact."""
        return [choice_groups([(sp.kind, sp.j) if sp.kind in ("impact", "stop") else None for sp in specs])
                for specs in self.slots]

    def locate_watch(self, mode, t, y, args) -> jax.Array:
        """`watch` with each choice's selection guards located on the value they share (an
        impact's gap, a stop's slip speed): the first reads it, the others +1; `select` takes
        the choice at the event. No choice is solved while locating."""
        parts = self._parts(mode, t, y, args)
        groups = self._groups()

        def value(sp, s, m):
            if sp.kind in ("impact", "stop") and not groups[m][s][1]:
                return jnp.ones((), y.dtype)
            return self._slot_value(sp, parts)

        return self._by_slots(mode, value, y.dtype)

    def select(self, mode, slot, t, y, args) -> jax.Array:
        """The slot of the choice located on `slot` whose outcome holds at (t, y) (exactly one
        of a choice's slots takes each outcome, "none solves it" included); `slot` elsewhere."""
        groups = self._groups()
        if not any(len(g) > 1 for gs in groups for g, _ in gs):
            return slot
        n = self.scene.dim
        kin, mu, ddq, _, _, _ = self._solved(mode, t, y, args)
        got = self._impact_outcomes(mode, kin, args, self._impact_tables(), y.dtype)
        which, inside = self._stop_decisions(mode, kin, mu, y[n:], ddq, self._stop_tables(), y.dtype)
        S = max(map(len, self.slots), default=0)
        # Per mode, (S,) the slot each slot's choice goes to.
        rows = []
        for specs, gs in zip(self.slots, groups, strict=True):
            takes = [self._taken(sp, got, which, inside) for sp in specs]
            rows.append([jnp.asarray(members[0], jnp.int32) if len(members) == 1 else
                         jnp.asarray(members, jnp.int32)[jnp.argmax(jnp.stack([takes[m] for m in members]))]
                         for members, _ in gs])
        target = select_by_mode(mode, rows, S, 0, jnp.int32)
        return pick_values(target, slot[None], 0)[0]

    def _impact_tables(self) -> dict:
        """Per (mode, impacting constraint k) with an impact slot, its candidates padded to C
        (`_FrictionImpact.outcome_tables`): held rows (M, K, C, R), present (M, K, C), the
        outcome code's bits (M, K, C, K) and offsets (M, K, C), the gap rows (M, K, R)."""
        K, R, M = len(self.scene.constraints), len(_layout(self.scene)[0]), len(self.slots)
        impacts = {(m, sp.j): sp.impact for m, specs in enumerate(self.slots) for sp in specs
                   if sp.kind == "impact"}
        C = max((len(imp.candidates) for imp in impacts.values()), default=0)
        t = dict(held=np.zeros((M, K, C, R)), present=np.zeros((M, K, C), bool), bits=np.zeros((M, K, C, K)),
                 offsets=np.zeros((M, K, C)), gap_rows=np.zeros((M, K, R), bool))
        for (m, k), imp in impacts.items():
            held, bits, offsets, gap_rows = imp.outcome_tables()
            c = len(imp.candidates)
            t["held"][m, k, :c], t["present"][m, k, :c] = held, True
            t["bits"][m, k, :c], t["offsets"][m, k, :c], t["gap_rows"][m, k] = bits, offsets, gap_rows
        return t

    def _impact_outcomes(self, mode, kin, args, t, dtype):
        """(K,): the outcome (`_FrictionImpact.outcome_from`) of an impact of each constraint in
        `mode`, -1 where none solves it or none is built; one vmapped solve."""
        K, R = len(self.scene.constraints), len(_layout(self.scene)[0])
        if t["held"].shape[2] == 0:
            return jnp.full(K, -1, jnp.int32)
        pick = {key: _by_mode(mode, v.astype(float), dtype) for key, v in t.items()}
        held, bits, present, offsets = pick["held"], pick["bits"], pick["present"] > 0, pick["offsets"]
        gap_rows = pick["gap_rows"] > 0
        e_all = jnp.stack([jnp.asarray(c.coefficient(args), dtype) for c in self.scene.constraints])
        tan = jnp.asarray(_layout(self.scene)[2], dtype)
        every = jnp.ones(R, bool)

        def one(k_hit, h, p, b, off, g):
            e = jnp.concatenate([k_hit * e_all, jnp.zeros(R - K, dtype)])
            ok, rates = jax.vmap(lambda hc: impact_candidate(kin, hc, e, every, g))(h)
            ok = ok & p
            code = jnp.sum(b * ((rates @ tan.T) < 0), axis=1)
            c = jnp.argmax(ok)
            return jnp.where(jnp.any(ok), off[c] + code[c], -1).astype(jnp.int32)

        return jax.vmap(one)(jnp.eye(K, dtype=dtype), held, present, bits, offsets, gap_rows)

    def _stop_tables(self) -> dict:
        """Per (mode, slipping contact j) with a stop slot, the candidate sets of other contacts
        stopped with it (`stop_subsets`), padded to C: present (M, K, C), members (M, K, C, K),
        others (M, K, K), and the stuck state's rows, signs and least-norm flag."""
        K, R, M = len(self.scene.constraints), len(_layout(self.scene)[0]), len(self.slots)
        stops = {(m, sp.j): sp.state for m, specs in enumerate(self.slots) for sp in specs
                 if sp.kind == "stop"}
        C = max((len(stop_subsets(S, j)) for (_, j), S in stops.items()), default=0)
        t = dict(present=np.zeros((M, K, C), bool), members=np.zeros((M, K, C, K)),
                 others=np.zeros((M, K, K)), rows=np.zeros((M, K, C, R)), sign=np.zeros((M, K, C, K)),
                 least=np.zeros((M, K, C)))
        for (m, j), S in stops.items():
            t["others"][m, j, list(others_slipping(S, j))] = 1.0
            for c, members in enumerate(stop_subsets(S, j)):
                stuck = tuple(STICK if i in (j, *members) else st for i, st in enumerate(S))
                _, rows_mask, sign = _state_arrays(self.scene, stuck)
                t["present"][m, j, c] = True
                t["members"][m, j, c, [j, *members]] = 1.0
                t["rows"][m, j, c], t["sign"][m, j, c] = rows_mask, sign
                t["least"][m, j, c] = float(rows_mask.sum() > self.scene.dim)
        return t

    def _stop_decisions(self, mode, kin, mu, dq, ddq, t, dtype):
        """(K,) each: `stop_decision` of each slipping contact j of `mode` (the index of the set
        of other contacts stopped with it, and whether all of those and j, stuck, are in their
        cones); one vmapped friction solve."""
        K = len(self.scene.constraints)
        if t["present"].shape[2] == 0:
            return jnp.full(K, -1, jnp.int32), jnp.zeros(K, bool)
        pick = {key: _by_mode(mode, v.astype(float), dtype) for key, v in t.items()}
        present, members, others = pick["present"] > 0, pick["members"] > 0, pick["others"] > 0
        rows_t, sign_t, least_t = pick["rows"], pick["sign"], pick["least"]
        tan = jnp.asarray(_layout(self.scene)[2], dtype)
        stopped = stop_ties(kin, ddq, tan, dq)  # (j, i)
        lam = jax.vmap(jax.vmap(lambda r, s, f: friction_acceleration(self.scene, kin, mu, r, s, f)[1]))(
            rows_t, sign_t, least_t
        )
        lam_n, lam_t = lam[..., :K], lam @ tan.T
        ok = jnp.all(~members | in_cone(mu, lam_n, lam_t), axis=-1)
        # A candidate matches where exactly its other members are stopped (j itself is a member).
        match = jnp.all(~others[:, None, :] | (stopped[:, None, :] == members), axis=-1) & present
        which = jnp.where(jnp.any(match, axis=1), jnp.argmax(match, axis=1), -1)
        inside = jnp.take_along_axis(ok, jnp.maximum(which, 0)[:, None], axis=1)[:, 0] & (which >= 0)
        return which.astype(jnp.int32), inside

    def _reset_tables(self):
        R = len(_layout(self.scene)[1])
        specs = self.resets
        held = np.asarray([np.zeros(R) if r.rows is None else r.rows for r in specs])
        moves = np.asarray([r.rows is not None for r in specs])
        hit = np.asarray([[float(r.restitute and i == r.hit) for i in range(R)] for r in specs])
        return held, moves, hit, np.asarray([float(r.least_norm) for r in specs])


def _add(asm: Assembly, src: str, T: tuple, guard, reset, label: str, edge_text: str, ok: bool, slot,
         reset_spec=None) -> None:  # fmt: skip
    """A transition of `src` labelled `label` (`"<kind> <constraint>"`): to state `T` if `ok`,
    else to the terminal mode `"unbuilt: <T>"`, listed as pruned."""
    tgt = state_name(asm.scene, T)
    if not ok:
        tgt = asm.terminal(UNBUILT + tgt)
        asm.pruned.append(f"  pruned: {label} in {src} -> {state_name(asm.scene, T)}: {edge_text}")
    else:
        asm.achievable.append((src, tgt, label.split(" ")[0], label.split(" ")[-1], edge_text))
    transition = Transition(src, tgt, guard=guard, reset=reset or _identity, name=f"{label}: {src} -> {tgt}")
    asm.add(transition, slot, reset_spec or FrictionReset())


def _add_impacts(asm: Assembly, S: tuple, j: int, edges: list) -> None:
    """An impact of `j` in `S`: a transition per outcome found, one into a terminal mode for the
    outcomes not found (or for an impact no candidate solves)."""
    scene = asm.scene
    src, cname = state_name(scene, S), scene.constraints[j].name
    imp = _friction_impact(scene, S, j)
    missing = tuple(e.detail for e in edges if not e.found) + (-1,)
    for e in edges:
        if e.found:
            c = imp.outcomes[e.detail][0]
            rows_c = tuple(map(float, imp.held_rows(c)))
            slot = FrictionSlot("impact", j, ids=(e.detail,), impact=imp)
            _add(asm, src, e.target, imp.guard((e.detail,)), imp.reset(c), f"impact {cname}", e.text, True,
                 slot, FrictionReset(rows_c, j, restitute=True))  # fmt: skip
    first = next((e.target for e in edges if not e.found), None)
    if first is not None:
        texts = "; ".join(e.text for e in edges if not e.found)
        _add(asm, src, first, imp.guard(missing), None, f"impact {cname}", texts, False,
             FrictionSlot("impact", j, ids=missing, impact=imp))  # fmt: skip
    else:  # no valid candidate: an impact that cannot be resolved stops the execution
        term = asm.terminal(f"{INCONSISTENT}impact of {cname} in {src}")
        asm.add(Transition(src, term, guard=imp.guard((-1,)), name=f"impact {cname}: {term}"),
                FrictionSlot("impact", j, ids=(-1,), impact=imp), FrictionReset())  # fmt: skip


def _add_state_change(asm: Assembly, fns: _StateFunctions, kind: str, j: int, edge, margin: float) -> None:
    """A lift-off, a stick to slip (`slip`) or a slip's stop (to stick, or reversing) of `j`."""
    scene, S, n = asm.scene, fns.state, asm.scene.dim
    detail, T = edge.detail, edge.target
    off = 0.0 if edge.found else margin
    if kind == "lift-off":
        guard, slot = fns.normal(j, off), FrictionSlot("lift", j, off)
    elif kind == "slip":
        guard, slot = fns.cone(j, detail, off), FrictionSlot("cone", j, off, d=detail)
    else:
        guard = fns.stop(j, detail is not None, detail or ())
        slot = FrictionSlot("stop", j, state=S, to_stick=detail is not None, tied=detail or ())
    stick = kind == "stop" and detail is not None
    reset = _StateFunctions(scene, T).project if stick else None
    reset_spec = None
    if stick:
        _, rows_T, _ = _state_arrays(scene, T)
        reset_spec = FrictionReset(tuple(map(float, rows_T)), least_norm=bool(rows_T.sum() > n))
    label = {"lift-off": "lift-off", "slip": "slip", "stop": "stick" if stick else "reverse"}[kind]
    _add(asm, state_name(scene, S), T, guard, reset, f"{label} {scene.constraints[j].name}", edge.text,
         edge.found, slot, reset_spec)  # fmt: skip


def _assemble(scene: Scene, graph: ContactGraph, margin: float, num_values: int, form: str) -> FrictionSystem:
    """Modes, transitions (in each mode: consistency, impacts, lift-offs, stick/slip) and the
    report of a friction build."""
    n, built = scene.dim, graph.states
    funcs = {S: _StateFunctions(scene, S) for S in built}
    asm = Assembly(scene, [Mode(state_name(scene, S), funcs[S].flow, dim=2 * n, names=state_names(scene))
                           for S in built])  # fmt: skip
    for S in built:
        src = state_name(scene, S)
        if any(s in SIGN for s in S):
            term = asm.terminal(INCONSISTENT + src)
            asm.add(Transition(src, term, guard=funcs[S].consistency, name=f"painleve: {src} -> {term}"),
                    FrictionSlot("painleve"), FrictionReset())  # fmt: skip
        for (kind, j), edges in graph.leaving(S):
            if kind == "impact":
                _add_impacts(asm, S, j, edges)
            else:
                for edge in edges:
                    _add_state_change(asm, funcs[S], kind, j, edge, margin)
    asm.close()
    num_terminal = len(asm.terminals)
    evaluation = FrictionEvaluation(
        scene=scene,
        states=tuple(built) + (None,) * num_terminal,
        slots=asm.mode_slots(FrictionSlot("constant", offset=-1.0)),
        resets=tuple(asm.resets),
    )
    report = [f"states built: {len(built)} ({', '.join(state_name(scene, S) for S in built)})"]
    report += [f"  achievable: {kind} of {c}: {s} -> {t}; {text}" for s, t, kind, c, text in asm.achievable]
    report += asm.pruned
    if num_values > 1:
        report.append(
            f"  built over {num_values} args values: a batch or a derivative across values "
            "that change the transitions found needs a system built over all of them"
        )
    contact_sets = tuple(
        tuple(c.name for c, s in zip(scene.constraints, S, strict=True) if s is not None) for S in built
    )
    return FrictionSystem(
        asm.modes,
        asm.transitions,
        states=tuple(built) + (None,) * num_terminal,
        scene=scene,
        contact_sets=contact_sets + (None,) * num_terminal,
        least_norm_modes=(False,) * len(asm.modes),
        report=tuple(report),
        achievable=tuple(asm.achievable),
        form=form,
        evaluation=evaluation if form == "mask" else None,
    )
