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

import jax
import jax.numpy as jnp
from jax.lax import Precision
from jaxtyping import Array, Float

HIGHEST = Precision.HIGHEST


def _eliminate(m, n: int):
    """Forward elimination with partial pivoting (the row of largest magnitude in each column)
    of the first `n` columns of `m`, unrolled over `n`: the row-echelon `m` and the sign of the
    row permutation."""
    rows = jnp.arange(n)
    sign = jnp.ones((), m.dtype)
    for k in range(n):
        p = jnp.argmax(jnp.where(rows >= k, jnp.abs(m[:, k]), -1.0))
        row_k, row_p = m[k], m[p]
        m = m.at[p].set(row_k).at[k].set(row_p)
        sign = jnp.where(p == k, sign, -sign)
        factor = jnp.where(rows > k, m[:, k] / m[k, k], 0.0)
        m = m - factor[:, None] * m[k][None, :]
    return m, sign


def solve(a: Float[Array, "n n"], b: Float[Array, "n ..."]) -> Float[Array, "n ..."]:
    """$x$ with $a x = b$, by Gaussian elimination with partial pivoting, unrolled over $n$.
    A singular `a` gives non-finite values, as `jnp.linalg.solve` does."""
    n = a.shape[-1]
    vector = b.ndim == 1
    m, _ = _eliminate(jnp.concatenate([a, b[:, None] if vector else b], axis=1), n)
    x = [None] * n
    for k in reversed(range(n)):
        acc = m[k, n:]
        for j in range(k + 1, n):
            acc = acc - m[k, j] * x[j]
        x[k] = acc / m[k, k]
    out = jnp.stack(x)
    return out[:, 0] if vector else out


def det(a: Float[Array, "n n"]) -> Float[Array, ""]:
    r"""$\det a$: the product of the pivots of `solve`'s elimination, signed by its row
    exchanges."""
    a = jnp.asarray(a)
    n = a.shape[-1]
    m, sign = _eliminate(a, n)
    return sign * jnp.prod(jnp.diagonal(m))


def cholesky(A) -> list:
    """The lower Cholesky factor of a small symmetric positive definite matrix, as rows of
    scalars, unrolled into elementwise operations.

    A contact system's matrices are a few rows wide and solved once per lane and flow stage:
    as elementwise operations they fuse across the lanes of a batch, where a LAPACK call per
    lane (`jnp.linalg.solve`) costs far more than the arithmetic and, with OpenBLAS's threads
    on a busy machine, can stall a batch a hundredfold. A matrix that is not positive definite
    (dependent constraints) gives a non-finite factor."""
    s = A.shape[0]
    L = [[None] * s for _ in range(s)]
    for j in range(s):
        d = A[j, j] - sum((L[j][k] ** 2 for k in range(j)), jnp.zeros((), A.dtype))
        L[j][j] = jnp.sqrt(d)
        for i in range(j + 1, s):
            off = A[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), jnp.zeros((), A.dtype))
            L[i][j] = off / L[j][j]
    return L


def spd_solve(A, B):
    """Solve $A X = B$, $A$ small symmetric positive definite, $B$ of shape (s,) or (s, r).

    The factor $A = L L^\top$ and the inverse $L^{-1}$ are computed without gradients, and the
    solution is $X = L^{-\top} (L^{-1} B)$, two matrix products. Its derivatives come from
    `custom_linear_solve` (as `jnp.linalg.solve`'s do from its LU factors): a derivative of the
    solution is the same two products applied to one more right-hand side, so the nested
    derivatives of a contact flow (the start test's Lie derivatives) neither differentiate the
    factorisation nor repeat a substitution unrolled over $s$ (in a contact scene such copies
    would be most of the program)."""
    A = 0.5 * (A + A.T)
    Linv = cholesky_inverse(jax.lax.stop_gradient(A))

    def solve(_, b):
        return jnp.matmul(Linv.T, jnp.matmul(Linv, b, precision=HIGHEST), precision=HIGHEST)

    return jax.lax.custom_linear_solve(lambda x: jnp.matmul(A, x, precision=HIGHEST), B, solve=solve,
                                       symmetric=True)


def cholesky_inverse(A: Float[Array, "s s"]) -> Float[Array, "s s"]:
    r"""$L^{-1}$ of the lower Cholesky factor $A = L L^\top$, by columns of $L$ and rows of
    $L^{-1}$ (forward substitution on the identity): each step is a few elementwise operations on
    a vector, $O(s^2)$ operations in all where an element-by-element form has $O(s^3)$, so a
    program that solves such systems at many places (a contact flow, at every stage of a step) is
    smaller to trace and compile.

    Column j of $L$: $v = A_{j:, j} - \sum_{k<j} L_{j:, k} L_{jk}$, $L_{jj} = \sqrt{v_0}$,
    $L_{j+1:, j} = v_{1:} / L_{jj}$. Row i of $X = L^{-1}$: $X_{i, :i} = -\sum_{k<i} L_{ik}
    X_{k, :i} / L_{ii}$, $X_{ii} = 1 / L_{ii}$, zero above the diagonal."""
    s = A.shape[0]
    if s == 0:
        return jnp.zeros_like(A)
    cols, diag = [], []
    for j in range(s):
        acc = None
        for k in range(j):
            term = cols[k][j - k:] * cols[k][j - k]
            acc = term if acc is None else acc + term
        v = A[j:, j] if acc is None else A[j:, j] - acc
        d = jnp.sqrt(v[0])
        diag.append(d)
        cols.append(jnp.concatenate([d[None], v[1:] / d]))  # L[j:, j]
    rows = []
    for i in range(s):
        inv = 1.0 / diag[i]
        if i == 0:
            rows.append(jnp.concatenate([inv[None], jnp.zeros((s - 1,), A.dtype)]))
            continue
        acc = None
        for k in range(i):
            term = cols[k][i - k] * rows[k][:i]  # L[i, k] X[k, :i]
            acc = term if acc is None else acc + term
        rows.append(jnp.concatenate([-acc / diag[i], inv[None], jnp.zeros((s - i - 1,), A.dtype)]))
    return jnp.stack(rows)


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
