r"""The mechanics of a scene: constraint kinematics, the contact (KKT) solve and the impact map.

Pure functions of a scene's mass matrix, forces and constraint functions, shared by the
per-mode functions of a built system, its mode-indexed evaluation and the point search.
The solves are elementwise (`_core.small_linalg`): no LAPACK call per lane.
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._core import small_linalg as small_linalg


def rows(scene, members) -> tuple[tuple, tuple]:
    """The rows of the constraints `members` (indices, in order): their gaps, then the
    tangential coordinates of those that stick. Returns (functions, owners): row r belongs to
    constraint owners[r]; row i < len(members) is the gap of members[i]."""
    sticky = [k for k in members if scene.constraints[k].tangent is not None]
    fns = tuple(scene.constraints[k].fn for k in members) + tuple(
        scene.constraints[k].tangent for k in sticky
    )
    return fns, tuple(members) + tuple(sticky)


def _row_mask(owners, members_mask, dtype):
    """A mask over rows from one over constraints (indexed by constraint)."""
    return jnp.asarray(members_mask, dtype)[np.asarray(owners, dtype=int)]



def _gaps(fns, t, q, args):
    return jnp.stack([jnp.reshape(jnp.asarray(f(t, q, args), q.dtype), ()) for f in fns])


def constraint_kinematics(fns, t, q, dq, args):
    r"""Gaps $a$, Jacobian $J = \partial a / \partial q$, rates $\dot a$ and the bias
    $c = \ddot a - J \ddot q$ (so that $\ddot a = 0$ is $J \ddot q = -c$), all by AD."""
    t = jnp.asarray(t, q.dtype)
    gap = lambda t_, q_: _gaps(fns, t_, q_, args)
    J = jax.jacfwd(gap, argnums=1)(t, q)
    # (a, a') and its derivative along (1, dq), (a', a''): one nested jvp gives all three.
    rate = lambda t_, q_: jax.jvp(gap, (t_, q_), (jnp.ones_like(t_), dq))
    (a, adot), (_, bias) = jax.jvp(rate, (t, q), (jnp.ones_like(t), dq))
    return a, J, adot, bias


def schur_solve(v, W, G, J, bottom, mask, least_norm=False):
    r"""The KKT system $M u - J_m^\top \mu = $ top, $J_m u = m \odot$ `bottom` (rows with mask
    $m_i = 0$ drop out: $\mu_i = 0$), from $v = M^{-1}$ top, $W = M^{-1} J^\top$ and the Gram
    matrix $G = J W$ (shared by every mask): $u = v + W \mu$ with
    $((m m^\top) \odot G + \mathrm{diag}(1 - m) + \varepsilon\, \mathrm{diag}(m)) \mu
    = m \odot (\text{bottom} - J v)$, solved by `small_linalg.spd_solve`. The rows dropped are
    masked by selection, so a non-finite value in one of them does not reach the others.

    $\varepsilon = 0$; with `least_norm` (True, or a 0/1 factor), $\varepsilon = 10^{-10}
    \operatorname{tr}(G_m) / \sum_i m_i$: the held rates are then met to $\varepsilon |\mu|$
    and, as $\varepsilon \to 0$, $\mu$ tends to the least-norm solution of dependent rows."""
    held = mask > 0
    both = held[:, None] & held[None, :]
    eps = 0.0
    if least_norm is not False:
        trace = jnp.sum(jnp.where(held, jnp.diag(G), 0.0))
        eps = 1e-10 * trace / jnp.maximum(jnp.sum(mask), 1.0) * least_norm
    S = jnp.where(both, G, 0.0) + jnp.diag(1.0 - mask + eps * mask)
    mu = small_linalg.spd_solve(S, jnp.where(held, bottom - J @ v, 0.0))
    return v + jnp.where(held[None, :], W, 0.0) @ mu, mu


def kkt_solve(M, top, J, bottom, mask, least_norm=False):
    r"""Solve $M u - J^\top \mathrm{diag}(m) \mu = $ `top`, $m_i (J u)_i + (1 - m_i) \mu_i = m_i$
    `bottom`$_i$ ($M$ symmetric positive definite): `schur_solve` with $M^{-1}$ top and
    $M^{-1} J^\top$ from one `small_linalg.spd_solve`."""
    if J.shape[0] == 0:
        return small_linalg.spd_solve(M, top), jnp.zeros((0,), top.dtype)
    X = small_linalg.spd_solve(M, jnp.concatenate([top[:, None], J.T], axis=1))
    v, W = X[:, 0], X[:, 1:]
    return schur_solve(v, W, J @ W, J, bottom, mask, least_norm)


class Kinematics(NamedTuple):
    r"""What every solve of a scene at one state shares: the mass matrix $M$, the applied forces
    $f$, and the rows' gaps $a$, Jacobian $J$, rates $\dot a$ and bias $c$
    (`constraint_kinematics`), with the velocity $\dot q$."""

    M: jax.Array
    f: jax.Array
    gap: jax.Array
    J: jax.Array
    adot: jax.Array
    bias: jax.Array
    dq: jax.Array
    Minv_f: jax.Array  # M^-1 f
    W: jax.Array  # M^-1 J^T
    G: jax.Array  # J M^-1 J^T


def velocity_forces(mass, q, dq, args):
    r"""The Coriolis and centrifugal forces of the mass matrix $M(q)$ = `mass(q, args)`:
    $h(q, \dot q) = -\dot M \dot q + \tfrac12 \partial_q (\dot q^\top M(q) \dot q)$, so that the
    Euler-Lagrange equations of $T = \tfrac12 \dot q^\top M(q) \dot q$ read
    $M \ddot q = f + h$; componentwise $h_j = -\sum_{i,k} (\partial_i M_{jk} -
    \tfrac12 \partial_j M_{ik}) \dot q_i \dot q_k$ (the Christoffel symbols of the first kind).
    $\partial M$ by forward-mode AD ($n$ tangents); zero for a constant $M$."""
    dM = jax.jacfwd(lambda q_: jnp.asarray(mass(q_, args), q.dtype))(q)  # dM[j, k, i] = d M_jk / d q_i
    Mdot_dq = jnp.einsum("jki,i,k->j", dM, dq, dq)
    grad_T = jnp.einsum("abj,a,b->j", dM, dq, dq)
    return -Mdot_dq + 0.5 * grad_T


def kinematics(scene, fns, t, q, dq, args) -> Kinematics:
    r"""The `Kinematics` of the rows `fns` at (t, q, dq), with $M^{-1} f$, $W = M^{-1} J^\top$
    and $G = J W$ from one `small_linalg.spd_solve`: every solve at this state reuses them.
    $f$ is the scene's `forces` plus, unless `scene.velocity_terms` is False, the velocity
    forces of $M(q)$ (`velocity_forces`)."""
    M = jnp.asarray(scene.mass(q, args), q.dtype)
    f = jnp.asarray(scene.forces(t, q, dq, args), q.dtype)
    if scene.velocity_terms:
        f = f + velocity_forces(scene.mass, q, dq, args)
    if not fns:
        z, J = jnp.zeros((0,), q.dtype), jnp.zeros((0, q.shape[0]), q.dtype)
        return Kinematics(M, f, z, J, z, z, dq, small_linalg.spd_solve(M, f), J.T, jnp.zeros((0, 0), q.dtype))
    gap, J, adot, bias = constraint_kinematics(fns, t, q, dq, args)
    X = small_linalg.spd_solve(M, jnp.concatenate([f[:, None], J.T], axis=1))
    W = X[:, 1:]
    return Kinematics(M, f, gap, J, adot, bias, dq, X[:, 0], W, J @ W)


def restrict(kin: Kinematics, idx) -> Kinematics:
    """The `Kinematics` of the rows `idx` (static indices) alone: a solve that holds only some
    rows needs only theirs, and its size is theirs."""
    idx = list(idx)

    def pick(a):
        return jnp.stack([a[r] for r in idx])

    W = jnp.stack([kin.W[:, r] for r in idx], axis=1)
    G = jnp.stack([jnp.stack([kin.G[r, c] for c in idx]) for r in idx])
    return kin._replace(gap=pick(kin.gap), J=pick(kin.J), adot=pick(kin.adot), bias=pick(kin.bias), W=W, G=G)


def acceleration(kin: Kinematics, mask, least_norm=False):
    r"""$\ddot q$ and $\lambda$ with the rows held where `mask` is 1:
    $M \ddot q = f + J^\top \lambda$, $J \ddot q = -c$ on the held rows (`kkt_solve`)."""
    if kin.J.shape[0] == 0:
        return kin.Minv_f, jnp.zeros((0,), kin.f.dtype)
    return schur_solve(kin.Minv_f, kin.W, kin.G, kin.J, -kin.bias, mask, least_norm)


def impact_map(kin: Kinematics, held, e, least_norm=False):
    r"""The impact with the rows held where `held` is 1: $\dot q^+ = \dot q^- + M^{-1} J^\top P$
    with $J_i \dot q^+ + \partial_t a_i = -e_i \dot a_i^-$ on the held rows (Newton's law, the
    rates with their explicit time dependence) and $P_i = 0$ on the others.
    Returns $\dot q^+$, $P$ and the rates $\dot a^+$."""
    a_t = kin.adot - kin.J @ kin.dq
    # M u - J^T P = M dq-: v = M^-1 (M dq-) = dq-.
    dq_plus, P = schur_solve(kin.dq, kin.W, kin.G, kin.J, -e * kin.adot - (1.0 + e) * a_t, held, least_norm)
    return dq_plus, P, kin.J @ dq_plus + a_t


def gram_independence(G, held):
    r"""$\min_j d_j / \max_j G_{jj}$ over the held rows $j$, $d_j$ the pivots ($L_{jj}^2$) of
    the Cholesky factor of the Gram matrix $G = J M^{-1} J^\top$ on the held rows (1 where
    none): 0 up to rounding, or NaN, for dependent constraints, and never below
    $\lambda_{\min}(G) / \lambda_{\max}(G)$ (a pivot is at least the least eigenvalue, a
    diagonal entry at most the greatest). Elementwise, as `kkt_solve` (no LAPACK call per lane)."""
    G = jnp.where((held[:, None] > 0) & (held[None, :] > 0), G, 0.0) + jnp.diag(1.0 - held)
    L = small_linalg.cholesky(0.5 * (G + G.T))
    pivots = jnp.stack([L[j][j] ** 2 for j in range(len(L))])
    on = held > 0
    # Over the held rows alone: the rows not held (pivot 1) do not change the ratio.
    ratio = jnp.min(jnp.where(on, pivots, jnp.inf)) / jnp.max(jnp.where(on, jnp.diag(G), 0.0))
    return jnp.where(jnp.any(on), ratio, 1.0)


_INDEPENDENT = 1e-9  # `gram_independence` below this: dependent


def impact_candidate(kin: Kinematics, held, e, involved, gap_rows, least_norm=False):
    r"""Whether the impact with the rows `held` held solves it, and its rates $\dot a^+$: on the
    gap rows of the constraints involved (`gap_rows`: the source set's and the impacting
    one's) the held impulses are >= 0 and the released rates >= 0 (each to 1e-9 of its scale
    over the rows `involved`), and the held rows are independent (`gram_independence`; not
    asked with `least_norm`, a Python bool here)."""
    _, P, rates = impact_map(kin, held, e, least_norm)
    scale = 1.0 + jnp.max(jnp.abs(P))
    ok_P = jnp.all(jnp.where((held > 0) & gap_rows, P >= -1e-9 * scale, True))
    tol_v = 1e-9 * (1.0 + jnp.max(jnp.where(involved, jnp.abs(rates), 0.0)))
    ok_v = jnp.all(jnp.where((held > 0) | ~gap_rows, True, rates >= -tol_v))
    ok = ok_P & ok_v
    if least_norm is False:
        ok = ok & (gram_independence(kin.G, held) > _INDEPENDENT)
    return ok, rates


def release_choice(kin: Kinematics, held_masks, e, involved, gap_rows, least_norm=False, present=None):
    """The first of an impact's release candidates that solves it (`impact_candidate`), -1 if
    none: candidate c holds the rows `held_masks[c]` ((C, rows); none, then one, then two
    released contacts...; `present` (C,) marks the candidates of a padded table). For
    independent constraints this linear complementarity problem has one solution. The
    candidates are one vmapped solve."""
    ok, _ = jax.vmap(lambda held: impact_candidate(kin, held, e, involved, gap_rows, least_norm))(held_masks)
    if present is not None:
        ok = ok & present
    return jnp.where(jnp.any(ok), jnp.argmax(ok), -1).astype(jnp.int32)


def selection_guard(a, taken):
    r"""The guard of one of the impacts that share the gap $a$ and differ in the release
    candidate they take: $a$ where $a > 0$ and where the impact takes this candidate
    (`taken`), $|a| + 1$ elsewhere. The builders give every outcome, "no candidate solves it"
    included, one such guard, so exactly one of them crosses zero where $a$ does; while $a > 0$
    none depends on the choice, so the choice is needed only where some $a \le 0$."""
    return jnp.where((a > 0) | taken, a, jnp.abs(a) + 1.0)


def constraint_gaps(scene, t, q, args):
    """(K,): the gaps $a_k(t, q)$ of the scene's constraints."""
    return _gaps(tuple(c.fn for c in scene.constraints), jnp.asarray(t, q.dtype), q, args)


def impact_gaps(scene, t, q, args, gaps):
    r"""The values of the impact guards: the gaps $a_k$ of the scene's constraints (`gaps`, the
    first K rows), with $\max(a_k, -c_k)$ for a contact armed only where $c_k(t, q) \ge 0$
    (`Constraint.armed`): $\le 0$ exactly where the gap is closed and the contact armed."""
    out = []
    for k, c in enumerate(scene.constraints):
        if c.armed is None:
            out.append(gaps[k])
        else:
            out.append(jnp.maximum(gaps[k], -_armed_value(c, t, q, args)))
    return jnp.stack(out) if out else gaps[:0]


def _armed_value(c, t, q, args):
    """$c_k(t, q)$ of the armed contact `c`, a scalar of q's dtype."""
    return jnp.reshape(jnp.asarray(c.armed(jnp.asarray(t, q.dtype), q, args), q.dtype), ())


def armed_values(scene, t, q, args):
    """(K,): $c_k(t, q)$ of each armed contact, 1 for the others."""
    return jnp.stack([
        jnp.ones((), q.dtype) if c.armed is None else _armed_value(c, t, q, args)
        for c in scene.constraints
    ])


def constrained_acceleration(scene, fns, mask, t, q, dq, args, least_norm=False):
    r"""$\ddot q$ and $\lambda$ of the constraints `fns` held where `mask` is 1 (`acceleration`)."""
    return acceleration(kinematics(scene, fns, t, q, dq, args), mask, least_norm)


def impact(scene, fns, held, e, t, q, dq, args, least_norm=False):
    r"""`impact_map` on the constraints `fns` at (t, q, dq)."""
    return impact_map(kinematics(scene, fns, t, q, dq, args), held, e, least_norm)


def independence(scene, fns, held, t, q, args):
    r"""`gram_independence` of the constraints `fns` at (t, q) (no velocity needed), as one
    compiled computation (the builder calls it outside any trace: op by op, each of its
    operations would be compiled on its own)."""
    return jax.jit(functools.partial(_independence, scene, fns))(held, t, q, args)


def _independence(scene, fns, held, t, q, args):
    M = jnp.asarray(scene.mass(q, args), q.dtype)
    J = jax.jacfwd(lambda q_: _gaps(fns, jnp.asarray(t, q.dtype), q_, args))(q)
    G = J @ small_linalg.spd_solve(M, J.T)
    return gram_independence(G, held)
