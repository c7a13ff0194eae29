"""Small dense linear algebra written as array operations, with no LAPACK call.

XLA:CPU runs LAPACK's factorisations (LU, SVD, symmetric eigenvalues) as custom calls that
split a batch over the intra-op thread pool and then wait for it. Where two such calls run at
once in one program (a vmapped search or flow evaluates several), each can hold a pool thread
while it waits for work queued behind the other, and the program never ends: on a 2-core
machine, two batched LU factorisations were seen waiting on each other for good. The systems
solved here are small (a contact system's n + K unknowns, a search's few), so elimination
unrolled over their static size is cheap, fuses with the work around it, and is
differentiable like any other array code.
"""

import jax.numpy as jnp
from jaxtyping import Array, Float


def solve(a: Float[Array, "n n"], b: Float[Array, "n ..."]) -> Float[Array, "n ..."]:
    """$x$ with $a x = b$, by Gaussian elimination with partial pivoting (the row of largest
    magnitude in each column), unrolled over $n$. A singular `a` gives non-finite values, as
    `jnp.linalg.solve` does."""
    n = a.shape[-1]
    vector = b.ndim == 1
    m = jnp.concatenate([a, b[:, None] if vector else b], axis=1)
    rows = jnp.arange(n)
    for k in range(n):
        p = jnp.argmax(jnp.where(rows >= k, jnp.abs(m[:, k]), -1.0))
        row_k, row_p = m[k], m[p]
        m = m.at[p].set(row_k).at[k].set(row_p)
        factor = jnp.where(rows > k, m[:, k] / m[k, k], 0.0)
        m = m - factor[:, None] * m[k][None, :]
    x = [None] * n
    for k in reversed(range(n)):
        acc = m[k, n:]
        for j in range(k + 1, n):
            acc = acc - m[k, j] * x[j]
        x[k] = acc / m[k, k]
    out = jnp.stack(x)
    return out[:, 0] if vector else out


def rank_ratio(g: Float[Array, "n n"]) -> Float[Array, ""]:
    """For a symmetric positive semi-definite `g`: the smallest pivot of its Cholesky
    factorisation with diagonal pivoting (the largest remaining diagonal first) over the largest
    diagonal entry. 1 for a multiple of the identity, 0 (to rounding) where `g` is singular:
    every pivot after the first `rank(g)` is the rounding of a zero Schur complement."""
    n = g.shape[-1]
    scale = jnp.max(jnp.diagonal(g))
    used = jnp.zeros((n,), bool)
    smallest = scale
    for _ in range(n):
        d = jnp.where(used, -jnp.inf, jnp.diagonal(g))
        p = jnp.argmax(d)
        pivot = d[p]
        smallest = jnp.minimum(smallest, pivot)
        col = g[:, p]
        safe = jnp.where(pivot > 0, pivot, 1.0)
        g = g - jnp.where(pivot > 0, jnp.outer(col, col) / safe, 0.0)
        used = used.at[p].set(True)
    return jnp.maximum(smallest, 0.0) / jnp.where(scale > 0, scale, 1.0)


def least_squares(
    a: Float[Array, "m n"], b: Float[Array, " m"], damping: float = 1e-13
) -> Float[Array, " n"]:
    r"""$\arg\min_x \lVert a x - b \rVert^2 + \mu \lVert x \rVert^2$ with
    $\mu = $ `damping` $\cdot \operatorname{tr}(a^\top a) / n$, by the normal equations: for a
    rank-deficient `a`, close to the least-norm solution (the directions `a` does not see get
    no step)."""
    n = a.shape[-1]
    ata = a.T @ a
    mu = damping * jnp.trace(ata) / n + jnp.finfo(a.dtype).tiny
    return solve(ata + mu * jnp.eye(n, dtype=a.dtype), a.T @ b)
