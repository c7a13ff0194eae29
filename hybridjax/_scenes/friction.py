r"""Coulomb friction in scenes: stick and slip modes of frictional contacts.

A unilateral `Constraint` with a `tangent` $b(t, q)$ and a `friction` coefficient $\mu \ge 0$
is, while held, in one of three states, each part of the mode (named `"left:stick"`,
`"left:slip+"`, `"left:slip-"`; frictionless contacts keep their bare name):

- stick: $\dot b = 0$ held with the gap (the tangent row of the KKT system), its force
  $\lambda_t$ free, in the cone $|\lambda_t| \le \mu \lambda_n$;
- slip $s = \pm 1$ ($s \dot b > 0$): $M \ddot q = f + J_n^\top \lambda_n + J_t^\top (-\mu s
  \lambda_n)$, $J_n \ddot q = -\dot J_n \dot q$: the normal row only, its generalised force
  column $(J_n - \mu s J_t)^\top$, smooth within the mode.

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
  > 0$ on the held rows (positive without friction); where it reaches 0 (Painleve's paradox) the
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
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from .._analysis.search import box_samples
from .._core import small_linalg as small_linalg
from .._definition.system import Mode, Transition
from .mechanics import _INDEPENDENT, constraint_kinematics, impact, independence, rows
from .scene import (
    FREE,
    UNBUILT,
    UNILATERAL,
    ContactSystem,
    Scene,
    _identity,
    _range,
    _releases,
    _search,
    _terminal_domain,
    _terminal_flow,
    witness_text,
)

HELD, STICK, SLIP_POS, SLIP_NEG = "held", "stick", "slip+", "slip-"
SIGN = {SLIP_POS: 1.0, SLIP_NEG: -1.0}
INCONSISTENT = "inconsistent: "
# Sliding speeds within this fraction of 1 + max |dq| of 0 when another contact stops count as
# stopped with it (a flat body's two ends stop at one instant, up to rounding).
_SPEED_TIE = 1e-8


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
    friction = np.asarray([c.friction is not None for c in scene.constraints], dtype=float)
    unilateral = np.asarray([c.kind == UNILATERAL for c in scene.constraints], dtype=float)
    return fns, owners, tan, friction, unilateral


def friction_coefficients(scene: Scene, args, dtype) -> jax.Array:
    r"""$\mu_k$ of every constraint (0 where it has none)."""
    mus = []
    for c in scene.constraints:
        mu = 0.0 if c.friction is None else (c.friction(args) if callable(c.friction) else c.friction)
        mus.append(jnp.reshape(jnp.asarray(mu, dtype), ()))
    return jnp.stack(mus)


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
    _, owners, _, friction, _ = _layout(scene)
    K = len(scene.constraints)
    held = np.asarray([s is not None for s in state], dtype=float)
    rows_mask = np.asarray(
        [held[k] if r < K or not friction[k] else float(state[k] == STICK) for r, k in enumerate(owners)]
    )
    sign = np.asarray([SIGN.get(s, 0.0) for s in state])
    return held, rows_mask, sign


def parse_state(scene: Scene, spec) -> tuple:
    """A state from `"free"`, `"left:stick+right"` or a sequence of such tokens; bilateral
    constraints are always held; a frictional contact needs its state named."""
    if isinstance(spec, str):
        tokens = [] if spec == FREE else re.findall(r"([^+:]+(?::(?:stick|slip[+-]))?)\+?", spec)
    else:
        tokens = list(spec)
    state = [HELD if c.kind != UNILATERAL else None for c in scene.constraints]
    for token in tokens:
        name, _, status = token.partition(":")
        k = scene.index(name)
        c = scene.constraints[k]
        if c.friction is not None and status not in (STICK, SLIP_POS, SLIP_NEG):
            raise ValueError(
                f"contact_system: '{name}' has friction: name its state, '{name}:stick', "
                f"'{name}:slip+' or '{name}:slip-' (got {token!r})."
            )
        if c.friction is None and status:
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
    determine. Every solve is written as array operations (`small_linalg`), no LAPACK call."""
    fns, _, tan, _, _ = _layout(scene)
    K, n = len(scene.constraints), scene.dim
    M = jnp.asarray(scene.mass(q, args), q.dtype)
    f = jnp.asarray(scene.forces(t, q, dq, args), q.dtype)
    _, J, rate, bias = constraint_kinematics(fns, t, q, dq, args)
    slip = friction_coefficients(scene, args, q.dtype) * sign
    W = J.at[:K].add(-slip[:, None] * (jnp.asarray(tan, q.dtype) @ J))
    m = rows_mask
    lhs = jnp.block([[M, -(m[:, None] * W).T], [m[:, None] * J, jnp.diag(1.0 - m)]])
    rhs = jnp.concatenate([f, -m * bias])
    sol = _regularised_solve(lhs, rhs, m, n) if least_norm else small_linalg.solve(lhs, rhs)
    return sol[:n], sol[n:], J, rate, bias


def _regularised_solve(lhs, rhs, m, n):
    r"""A KKT solve with $-\epsilon$ on the held rows' diagonal ($\epsilon = 10^{-10}$ of the
    system's scale), so that dependent rows give nearly least-norm forces; elimination written
    as array operations (`small_linalg.solve`, no LAPACK call)."""
    eps = 1e-10 * jnp.max(jnp.abs(lhs[n:, :n])) ** 2 / jnp.max(jnp.abs(jnp.diag(lhs)[:n]))
    return small_linalg.solve(lhs.at[n:, n:].add(-eps * jnp.diag(m)), rhs)


def _search_impact(scene: Scene, held_rows, e, t, q, dq, args):
    r"""`impact` with the search's solve: $(P, J \dot q^+ + a_t)$."""
    fns = _layout(scene)[0]
    n = scene.dim
    M = jnp.asarray(scene.mass(q, args), q.dtype)
    _, J, adot, _ = constraint_kinematics(fns, t, q, dq, args)
    a_t = adot - J @ dq
    m = held_rows
    lhs = jnp.block([[M, -(m[:, None] * J).T], [m[:, None] * J, jnp.diag(1.0 - m)]])
    rhs = jnp.concatenate([M @ dq, m * (-e * adot - (1.0 + e) * a_t)])
    sol = _regularised_solve(lhs, rhs, m, n)
    return sol[n:], J @ sol[:n] + a_t


def slip_consistency(scene: Scene, rows_mask, sign, t, q, args):
    r"""$\det(J M^{-1} W^\top)$ on the held rows (1 on the others): positive without friction;
    where it reaches 0 the slip mode's contact forces are undetermined (Painleve's paradox)."""
    fns, _, tan, _, _ = _layout(scene)
    K = len(scene.constraints)
    M = jnp.asarray(scene.mass(q, args), q.dtype)
    _, J, _, _ = constraint_kinematics(fns, t, q, jnp.zeros_like(q), args)
    slip = friction_coefficients(scene, args, q.dtype) * sign
    W = J.at[:K].add(-slip[:, None] * (jnp.asarray(tan, q.dtype) @ J))
    m = rows_mask
    G = m[:, None] * m[None, :] * (J @ small_linalg.spd_solve(M, W.T)) + jnp.diag(1.0 - m)
    return small_linalg.det(G)


class _StateFunctions(eqx.Module):
    """Flow, forces and guards of one friction state (static descriptors)."""

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
        """mu lambda_n + d lambda_t of sticking contact j (+ offset): its guard into slip d."""
        tan = _layout(self.scene)[2]
        r = int(np.argmax(tan[j]))

        def g(t, x, args):
            lam = self.solve(t, x, args)[1]
            mu = friction_coefficients(self.scene, args, x.dtype)[j]
            return mu * lam[j] + d * lam[r] + offset

        return g

    def others_slipping(self, j) -> tuple:
        return tuple(i for i, st in enumerate(self.state) if st in SIGN and i != j)

    def stuck(self, members) -> "_StateFunctions":
        """This state with the contacts `members` sticking."""
        return _StateFunctions(
            self.scene, tuple(STICK if i in members else st for i, st in enumerate(self.state))
        )

    def stop(self, j, to_stick: bool, tied: tuple = ()):
        """s v_t of slipping contact j where the stop rule sends it (`to_stick`: it sticks with
        the other slipping contacts `tied`, those stopped at the same instant; otherwise it
        slips back), positive elsewhere."""
        s = SIGN[self.state[j]]
        tan = _layout(self.scene)[2]
        row = [int(np.argmax(tan[i])) for i in range(len(self.state))]
        others = self.others_slipping(j)
        subsets = [c for size in range(len(others) + 1) for c in itertools.combinations(others, size)]

        def decide(t, x, args):
            """(index in `subsets` of the contacts stopped with j, whether all of them stick)."""
            rate = self.solve(t, x, args)[2]
            scale = 1.0 + jnp.max(jnp.abs(x[self.scene.dim :]))
            stopped = [jnp.abs(rate[row[i]]) <= _SPEED_TIE * scale for i in others]
            mu = friction_coefficients(self.scene, args, x.dtype)
            which, inside = jnp.array(-1), jnp.array(False)
            for c, members in enumerate(subsets):
                match = jnp.all(
                    jnp.stack([stopped[others.index(i)] == (i in members) for i in others] + [True])
                )
                lam = self.stuck((j, *members)).solve(t, x, args)[1]
                ok = jnp.all(jnp.stack([jnp.abs(lam[row[i]]) <= mu[i] * lam[i] for i in (j, *members)]))
                which, inside = jnp.where(match, c, which), jnp.where(match, ok, inside)
            return which, inside

        def g(t, x, args):
            v = s * self.solve(t, x, args)[2][row[j]]
            # Which way it goes is a discrete choice: no derivative flows through it.
            which, inside = decide(*jax.lax.stop_gradient((t, x, args)))
            go = (inside & (which == subsets.index(tied))) if to_stick else ~inside
            return jnp.where(go, v, jnp.abs(v) + 1.0)

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
        force -mu s lambda_n), 0 on rows not held."""
        rows_mask, sign = self._arrays(x.dtype)
        lam = self.solve(t, x, args)[1]
        K = len(self.scene.constraints)
        friction = -friction_coefficients(self.scene, args, x.dtype) * sign * lam[:K]
        return lam * rows_mask + jnp.asarray(_layout(self.scene)[2], x.dtype).T @ friction


class _FrictionImpact(eqx.Module):
    """Impact of constraint `k` in state `source`: release candidates as in `contact_system`,
    then the frictional contacts of the new set slip by the sign of their tangential velocity.
    Outcomes are (candidate, signs), numbered by `outcome_id`."""

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
        return tuple(i for i in self.new_set(c) if self.scene.constraints[i].friction is not None)

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
        return tuple(
            None if i not in held else ({1.0: SLIP_POS, -1.0: SLIP_NEG}[slip[i]] if i in slip else HELD)
            for i in range(len(self.scene.constraints))
        )

    def held_rows(self, c, dtype):
        """The rows the impact holds: the new set's gaps (and k's), and the tangents of
        contacts that stick without a friction limit."""
        _, owners, _, friction, _ = _layout(self.scene)
        keep = set(self.new_set(c)) | {self.k}
        K = len(self.scene.constraints)
        return jnp.asarray(
            [float(i in keep and (r < K or not friction[i])) for r, i in enumerate(owners)], dtype
        )

    def outcome(self, c, t, x, args):
        n = self.scene.dim
        fns = _layout(self.scene)[0]
        e_k = jnp.asarray(self.scene.constraints[self.k].coefficient(args), x.dtype)
        e = jnp.zeros(len(fns), x.dtype).at[self.k].set(e_k)
        return impact(self.scene, fns, self.held_rows(c, x.dtype), e, t, x[:n], x[n:], args)

    def valid(self, c, t, x, args):
        """Held impulses >= 0, released constraints separating, held rows independent."""
        _, P, rates = self.outcome(c, t, x, args)
        K = len(self.scene.constraints)
        held = self.held_rows(c, x.dtype)
        ok_P = jnp.all(jnp.where(held[:K] > 0, P[:K] >= -1e-9 * (1.0 + jnp.max(jnp.abs(P))), True))
        released = jnp.asarray([float(i in self.candidates[c]) for i in range(K)], x.dtype)
        tol_v = 1e-9 * (1.0 + jnp.max(jnp.abs(rates)))
        ok_v = jnp.all(jnp.where(released > 0, rates[:K] >= -tol_v, True))
        fns = _layout(self.scene)[0]
        ok_i = independence(self.scene, fns, held, t, x[: self.scene.dim], args) > _INDEPENDENT
        return ok_P & ok_v & ok_i

    def outcome_id(self, t, x, args):
        """The index in `outcomes` of what happens at (t, x), -1 if no candidate is valid."""
        tan = jnp.asarray(_layout(self.scene)[2], x.dtype)
        result = jnp.array(-1, jnp.int32)
        offset = 0
        for c in range(len(self.candidates)):
            fr = self.frictional(c)
            vt = tan @ self.outcome(c, t, x, args)[2]
            # Bits in the order of `itertools.product((1, -1), ...)`: the first contact most
            # significant, 1 for slip-.
            code = sum((vt[i] < 0).astype(jnp.int32) * 2 ** (len(fr) - 1 - b) for b, i in enumerate(fr))
            ok = self.valid(c, t, x, args) & (result < 0)
            result = jnp.where(ok, offset + code, result)
            offset += 2 ** len(fr)
        return result

    def guard(self, ids: tuple):
        """a_k where the outcome is one of `ids` (-1: none valid), positive elsewhere."""
        k_fn = self.scene.constraints[self.k].fn

        def g(t, x, args):
            a = jnp.reshape(jnp.asarray(k_fn(t, x[: self.scene.dim], args), x.dtype), ())
            got = self.outcome_id(*jax.lax.stop_gradient((t, x, args)))
            hit = jnp.any(jnp.stack([got == i for i in ids]))
            return jnp.where(hit, a, jnp.abs(a) + 1.0)

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
        a = constraint_kinematics(fns, t, q, dq, args)[0][:K]
        ddq, lam, J, rate, bias = friction_solve(scene, Q.rows, Q.sign, t, q, dq, args, "search")
        lam_n, lam_t, v_t = lam[:K], tan @ lam, tan @ rate
        acc_t = tan @ (J @ ddq + bias)
        # The stopping contacts' forces were they to stick here.
        stopping = Q.stop + Q.tied
        lam2 = friction_solve(
            scene, Q.rows + tan.T @ stopping, Q.sign * (1 - stopping), t, q, dq, args, "search"
        )[1]
        lam2_n, lam2_t = lam2[:K], tan @ lam2
        e = jnp.stack([jnp.asarray(c.coefficient(args), dt) for c in scene.constraints]) * Q.hit
        e = jnp.concatenate([e, jnp.zeros(len(fns) - K, dt)])
        P, rates_plus = _search_impact(scene, Q.impact_rows, e, t, q, dq, args)
        stuck = fr * (tan @ Q.rows)
        slipping = jnp.abs(Q.sign)
        s = Q.sign
        one = jnp.ones_like(a)
        eq = jnp.concatenate([Q.held * a, Q.rows * rate, Q.hit * a, stopping * v_t])

        def where(mask, value):
            return jnp.where(mask > 0, value, one)

        ineq = jnp.concatenate(
            [
                where(uni * (1 - Q.held) * (1 - Q.hit), a),
                where(slipping * (1 - stopping), s * v_t),
                where(uni * Q.held * Q.flowing * (1 - Q.lift), lam_n),
                where(stuck * Q.flowing * (1 - Q.unstick), mu * lam_n - jnp.abs(lam_t)),
                where(Q.lift, -lam_n - margin),
                where(Q.unstick, -(mu * lam_n + Q.direction * lam_t) - margin),
                where(Q.stop, -s * acc_t - margin),
                where(stopping * Q.to_stick, mu * lam2_n - jnp.abs(lam2_t)),
                where(Q.stop * (1 - Q.to_stick), s * lam2_t - mu * lam2_n - margin),
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

    return (lambda t, x, p: parts(t, x, p)[0]), (lambda t, x, p: parts(t, x, p)[1])


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


def _run(scene, queries, args_batch, samples, margin, tol, num_starts):
    eq, ineq = _friction_queries(scene, margin)
    count = len(queries)
    padded = max(8, 1 << max(count - 1, 0).bit_length())  # powers of two: few compiled sizes
    queries = list(queries) + [queries[0]] * (padded - count)
    stacked = jtu.tree_map(lambda *xs: jnp.stack(xs), *queries)
    out = _search(eq, ineq, samples[0], samples[1], stacked, args_batch, tol, num_starts)
    return jtu.tree_map(lambda a: np.asarray(a)[:count], out)


# ----------------------------------------------------------------------------- the system


class FrictionSystem(ContactSystem):
    """The `ContactSystem` of a scene with friction: `states` gives, for each mode, the state of
    every constraint (`None` open, `"held"`, `"stick"`, `"slip+"`, `"slip-"`; `None` for the
    whole entry of a terminal mode). `contact_forces` reports a slipping contact's tangential
    column as its friction force $-\\mu s \\lambda_n$."""

    states: tuple = eqx.field(static=True)

    def __init__(self, modes, transitions, *, states, **kwargs):
        super().__init__(modes, transitions, **kwargs)
        self.states = states

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


def friction_system(
    scene: Scene,
    initial: Sequence,
    args: Any = None,
    *,
    args_values: Sequence | None = None,
    num_samples: int = 512,
    num_starts: int = 8,
    margin: float = 1e-3,
    tol: float = 1e-14,
    seed: int = 0,
    redundant: str = "error",
    max_modes: int = 64,
    relabels: Sequence = (),
) -> FrictionSystem:
    """`contact_system` for a scene with frictional contacts (see the module notes)."""
    if relabels:
        raise ValueError("contact_system: `relabels` are not available for scenes with friction.")
    if redundant != "error":
        raise ValueError(
            "contact_system: scenes with friction need independent contacts (redundant='error')."
        )
    values = list(args_values) if args_values is not None else [args]
    if not values:
        raise ValueError("contact_system: `args_values` is empty.")
    dtype = jnp.result_type(float)
    for v in values:
        scene.check(v)
        mus = np.asarray(friction_coefficients(scene, v, dtype))
        for c, mu in zip(scene.constraints, mus, strict=True):
            if c.friction is not None and not mu >= 0:
                raise ValueError(
                    f"Constraint '{c.name}': the friction coefficient must be >= 0, got {mu} for args {v!r}."
                )
    K, n = len(scene.constraints), scene.dim
    fns, owners, tan, friction, unilateral = _layout(scene)
    args_batch = (
        jnp.arange(len(values)),
        jtu.tree_map(lambda *v: jnp.stack([jnp.asarray(x, dtype) for x in v]), *values),
    )
    (qlo, qhi), (vlo, vhi) = _range(scene.q_range, n, "q_range"), _range(scene.dq_range, n, "dq_range")
    lo = jnp.asarray(qlo + vlo + (scene.t_range[0],), dtype)
    hi = jnp.asarray(qhi + vhi + (scene.t_range[1],), dtype)
    pts = box_samples(jax.random.key(seed), lo, hi, num_samples)
    samples = (pts[:, -1], pts[:, :-1])

    def search(qs):
        return _run(scene, qs, args_batch, samples, margin, tol, num_starts)

    initial_states = list(dict.fromkeys(parse_state(scene, s) for s in initial))
    if not initial_states:
        raise ValueError("contact_system: give at least one initial contact set.")
    w = search([_query(scene, S, flowing=0.0) for S in initial_states])
    for i, S in enumerate(initial_states):
        if not w.found[i].any():
            raise ValueError(
                f"contact_system: the initial state {state_name(scene, S)} has no consistent state in "
                f"the scene's ranges (least violation {np.nanmin(w.violation[i]):.2g})."
            )
        v = int(np.argmax(w.found[i]))
        rows_mask = jnp.asarray(_state_arrays(scene, S)[1], dtype)
        if (
            independence(scene, fns, rows_mask, w.t[i, v], jnp.asarray(w.x[i, v, :n]), values[v])
            <= _INDEPENDENT
        ):
            names = [scene.constraints[j].name for j, s in enumerate(S) if s is not None]
            raise ValueError(
                f"contact_system: the initial state {state_name(scene, S)} has dependent constraints "
                f"{names} (redundant contacts); remove one of them."
            )

    built = list(initial_states)
    impacts: dict[tuple, _FrictionImpact] = {}
    outcomes: dict[tuple, list] = {}  # (S, kind, j) -> [(detail, target, found, text)]
    frontier = list(built)
    while frontier:
        qs, keys = [], []
        for S in frontier:
            held = {i for i, s in enumerate(S) if s is not None}
            for k in sorted(i for i in range(K) if unilateral[i] and S[i] is None):
                imp = _FrictionImpact(
                    scene,
                    S,
                    k,
                    tuple(tuple(sorted(r)) for r in _releases({i for i in held if unilateral[i]})),
                )
                impacts[(S, k)] = imp
                for o, (c, signs) in enumerate(imp.outcomes):
                    post = np.zeros(K)
                    post[list(imp.frictional(c))] = signs
                    released = np.zeros(K)
                    released[list(imp.candidates[c])] = 1.0
                    qs.append(
                        _query(
                            scene,
                            S,
                            hit=(k, 1.0),
                            impact_rows=np.asarray(imp.held_rows(c, dtype)),
                            released=released,
                            post=post,
                        )  # fmt: skip
                    )
                    keys.append((S, "impact", k, o, imp.target((c, signs))))
            for j in sorted(held):
                if not unilateral[j]:
                    continue
                qs.append(_query(scene, S, lift=(j, 1.0), flowing=0.0))
                keys.append((S, "lift-off", j, None, S[:j] + (None,) + S[j + 1 :]))
                if S[j] == STICK:
                    for d, status in ((1.0, SLIP_POS), (-1.0, SLIP_NEG)):
                        qs.append(_query(scene, S, unstick=(j, 1.0), direction=d))
                        keys.append((S, "slip", j, d, S[:j] + (status,) + S[j + 1 :]))
                elif S[j] in SIGN:
                    others = _StateFunctions(scene, S).others_slipping(j)
                    for size in range(len(others) + 1):
                        for tied in itertools.combinations(others, size):
                            mask = np.zeros(K)
                            mask[list(tied)] = 1.0
                            T = tuple(STICK if i in (j, *tied) else st for i, st in enumerate(S))
                            qs.append(_query(scene, S, stop=(j, 1.0), tied=mask, to_stick=1.0))
                            keys.append((S, "stop", j, tied, T))
                    other = SLIP_NEG if S[j] == SLIP_POS else SLIP_POS
                    qs.append(_query(scene, S, stop=(j, 1.0), to_stick=0.0))
                    keys.append((S, "stop", j, None, S[:j] + (other,) + S[j + 1 :]))
        frontier = []
        if not qs:
            break
        w = search(qs)
        for i, (S, kind, j, detail, T) in enumerate(keys):
            found_v = w.found[i]
            if found_v.any():
                text = witness_text(w, i, n)
                if T not in built:
                    if len(built) >= max_modes:
                        raise ValueError(f"contact_system: more than max_modes={max_modes} states reached.")
                    built.append(T)
                    frontier.append(T)
            else:
                least = np.nanmin(w.violation[i])
                text = f"no state of the source found in the guard (least violation {least:.2g})"
            outcomes.setdefault((S, kind, j), []).append((detail, T, bool(found_v.any()), text))

    return _assemble(scene, built, outcomes, impacts, margin, len(values))


def _assemble(scene, built, outcomes, impacts, margin, num_values) -> FrictionSystem:
    """Modes, transitions (in each mode: consistency, impacts, lift-offs, stick/slip) and the
    report of a friction build."""
    n = scene.dim
    funcs = {S: _StateFunctions(scene, S) for S in built}
    names = scene.names or tuple(f"q[{i}]" for i in range(n))
    comp = tuple(names) + tuple(f"d{s}" for s in names)
    modes = [Mode(state_name(scene, S), funcs[S].flow, dim=2 * n, names=comp) for S in built]
    transitions, achievable, pruned, terminals = [], [], [], {}

    def add(src, T, guard, reset, label, text, ok):
        tgt = state_name(scene, T)
        if not ok:
            tgt = UNBUILT + tgt
            terminals[tgt] = None
            pruned.append(f"  pruned: {label} in {src} -> {state_name(scene, T)}: {text}")
        else:
            achievable.append((src, tgt, label.split(" ")[0], label.split(" ")[-1], text))
        transitions.append(
            Transition(src, tgt, guard=guard, reset=reset or _identity, name=f"{label}: {src} -> {tgt}")
        )

    for S in built:
        src = state_name(scene, S)
        if any(s in SIGN for s in S):
            term = INCONSISTENT + src
            terminals[term] = None
            transitions.append(
                Transition(src, term, guard=funcs[S].consistency, name=f"painleve: {src} -> {term}")
            )
        for (S_, kind, j), items in outcomes.items():
            if S_ != S:
                continue
            cname = scene.constraints[j].name
            if kind == "impact":
                imp = impacts[(S, j)]
                missing = tuple(o for o, _, ok, _ in items if not ok) + (-1,)
                for o, T, ok, text in items:
                    if ok:
                        add(
                            src,
                            T,
                            imp.guard((o,)),
                            imp.reset(imp.outcomes[o][0]),
                            f"impact {cname}",
                            text,
                            True,
                        )
                first = next((T for _, T, ok, _ in items if not ok), None)
                if first is not None:
                    texts = "; ".join(t for _, _, ok, t in items if not ok)
                    add(src, first, imp.guard(missing), None, f"impact {cname}", texts, False)
                else:  # no valid candidate: an impact that cannot be resolved stops the execution
                    term = f"{INCONSISTENT}impact of {cname} in {src}"
                    terminals[term] = None
                    transitions.append(
                        Transition(src, term, guard=imp.guard((-1,)), name=f"impact {cname}: {term}")
                    )
            for detail, T, ok, text in items if kind != "impact" else ():
                off = 0.0 if ok else margin
                if kind == "lift-off":
                    guard = funcs[S].normal(j, off)
                elif kind == "slip":
                    guard = funcs[S].cone(j, detail, off)
                else:
                    guard = funcs[S].stop(j, detail is not None, detail or ())
                stick = kind == "stop" and detail is not None
                reset = _StateFunctions(scene, T).project if stick else None
                label = {"lift-off": "lift-off", "slip": "slip", "stop": "stick" if stick else "reverse"}[
                    kind
                ]
                add(src, T, guard, reset, f"{label} {cname}", text, ok)
    for term in terminals:
        modes.append(Mode(term, _terminal_flow, dim=2 * n, domain=_terminal_domain, names=comp))

    report = [f"states built: {len(built)} ({', '.join(state_name(scene, S) for S in built)})"]
    report += [f"  achievable: {kind} of {c}: {s} -> {t}; {text}" for s, t, kind, c, text in achievable]
    report += pruned
    if num_values > 1:
        report.append(
            f"  built over {num_values} args values: a batch or a derivative across values "
            "that change the transitions found needs a system built over all of them"
        )
    states = tuple(built) + (None,) * len(terminals)
    contact_sets = tuple(
        tuple(c.name for c, s in zip(scene.constraints, S, strict=True) if s is not None) for S in built
    )
    return FrictionSystem(
        modes,
        transitions,
        states=states,
        scene=scene,
        contact_sets=contact_sets + (None,) * len(terminals),
        least_norm_modes=(False,) * len(modes),
        report=tuple(report),
        achievable=tuple(achievable),
        form="branch",
    )
