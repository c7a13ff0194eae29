"""The per-execution loop's reverse mode: a while loop with checkpoints and its own VJP.

The loop's caller knows which carried leaves can carry a derivative (`Loop`'s
`DIFFERENTIABLE_FIELDS`), so this loop takes them as given: tracing its reverse mode costs one
trace of the body and one of its VJP, where a loop that works out which leaves are perturbed and
which cotangents are symbolic zeros traces the body's JVP and VJP again for each question.

Checkpoints every k iterations: the forward pass stores the carry at iterations 0, k, 2k, ...
(S = ceil(max_steps / k) stores, one flat buffer per dtype); the backward pass takes the
segments from the last to the first, recomputes a segment's at most k iterations from its
checkpoint, and pulls the cotangent back through them one at a time. Every iteration is
recomputed once; the memory is S + k carries (or residuals), k = ceil(sqrt(max_steps)) unless a
number of checkpoints S is given; the last segment is recomputed until the loop's condition
ends it (`recomputed_length`). The loop's own condition is one decision for a whole
`jax.vmap` batch (the caller's), so the iteration count and the segments are too.

What the recomputation keeps (`keep`):

- `"residuals"`: each iteration's linearisation, `jax.vjp` of the body, keeping the pullback's
  residuals; the backward pass applies the pullbacks. The body's code appears twice in the
  program (the forward pass, the linearisation) and its transpose once: the ball's reverse
  program has a tenth fewer fusions (836 against 927) and compiles in about a tenth less time.
- `"carries"`: each carry; the backward pass linearises the body again at each iteration and
  transposes it (the body three times). Under `jax.vmap` it runs faster, measured:
  `jax.vmap(jax.grad(...))` over 1,000 balls takes about 1.15 times as long keeping residuals
  (164 arrays per iteration against the carry's 59).
"""

import math
from collections.abc import Callable
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax import lax

from .._core.jaxprs import closure_converted


def segment_length(max_steps: int, checkpoints: int | None) -> int:
    """k, the iterations between two checkpoints: ceil(sqrt(max_steps)), or with `checkpoints`
    given, ceil(max_steps / checkpoints)."""
    if checkpoints is None:
        return max(1, math.ceil(math.sqrt(max_steps)))
    return max(1, math.ceil(max_steps / checkpoints))


# Iterations the backward pass may add to the forward pass's last segment (`recomputed_length`).
FINISH = 4


def recomputed_length(t, length, extended_to, running: Callable) -> jax.Array:
    """Whether the backward pass recomputes iteration t of a segment of `length` forward
    iterations: every one of them, and while the loop's condition still holds (`running()`),
    the iterations up to `extended_to` (> `length` only in the last segment: at most `FINISH`
    more, never past `max_steps`).

    A recomputation is the body's program compiled again (under the linearisation, or inside a
    derivative of the derivative); where XLA rounds it otherwise, an adaptive solve recomputed
    from a checkpoint takes steps that differ at rounding level, and its last step may stop
    short of where the forward pass's ended (a run recomputed one step short of its end time
    t1 pulls the final state's cotangent back from a state before t1). Running the last segment
    to the loop's end linearises a run that ends where the forward pass's did; a recomputation
    that ends sooner than the forward pass is unchanged by its remaining iterations (the body
    leaves a finished run as it is). A forward pass stopped by `max_steps` is recomputed to the
    same iteration."""
    return (t < length) | ((t < extended_to) & running())


def _split(leaves, mask):
    pairs = list(zip(leaves, mask, strict=True))
    return [x for x, m in pairs if m], [x for x, m in pairs if not m]


def _join(on, off, mask):
    on, off = iter(on), iter(off)
    return [next(on) if m else next(off) for m in mask]


class _Packing:
    """The carried arrays laid out as one flat vector per dtype, so that storing a checkpoint
    is one indexed write per dtype rather than one per leaf (three against some sixty for the
    loop's state, each a kernel of its own for XLA). The backward pass keeps what it recomputes
    of a segment (carries or residuals, `keep`) leaf by leaf: packed there, every iteration
    would copy all of it once more (`jax.vmap(jax.grad(...))` over 1,000 balls took 1.5 times
    as long with packed carries, 2.2 times with packed residuals)."""

    def __init__(self, arrays):
        self.dtypes = list(dict.fromkeys(jnp.result_type(x) for x in arrays))
        self.layout = []  # per array: (group, start, size, shape)
        used = dict.fromkeys(self.dtypes, 0)
        for x in arrays:
            d, shape = jnp.result_type(x), jnp.shape(x)
            size = math.prod(shape)
            self.layout.append((self.dtypes.index(d), used[d], size, shape))
            used[d] += size
        self.sizes = [used[d] for d in self.dtypes]

    def pack(self, arrays):
        parts = [[] for _ in self.dtypes]
        for x, (g, _, _, _) in zip(arrays, self.layout, strict=True):
            parts[g].append(jnp.reshape(x, (-1,)))
        return [jnp.concatenate(p) for p in parts]

    def unpack(self, packed):
        return [jnp.reshape(packed[g][a:a + n], shape) for g, a, n, shape in self.layout]

    def buffers(self, length: int):
        return [jnp.zeros((length, n), d) for n, d in zip(self.sizes, self.dtypes, strict=True)]


def _zero_cotangents(xs):
    """Cotangents of inputs that get none: zeros, `float0` for integer and boolean arrays."""
    return [jnp.zeros_like(x) if eqx.is_inexact_array(x) else np.zeros(np.shape(x), jax.dtypes.float0)
            for x in xs]


def checkpointed_while_loop(cond_fun: Callable, body_fun: Callable, init, *, max_steps: int,
                            checkpoints: int | None, differentiated: Callable,
                            keep: Literal["residuals", "carries"] = "residuals"):
    """`lax.while_loop(cond_fun, body_fun, init)`, at most `max_steps` iterations, reverse-mode
    differentiable through checkpoints (module docstring).

    `differentiated(init)`: a bool per leaf of the carry (`jax.tree_util.tree_leaves` order),
    True for the inexact leaves that may carry a derivative; the body's outputs at the other
    leaves must not depend differentiably on the inputs (their cotangents are dropped). Arrays
    that `body_fun` closes over (the system's parameters) are differentiated as inputs. `keep`:
    what the backward pass's recomputation keeps of each iteration (module docstring).
    `cond_fun` is called in the backward pass too (`recomputed_length`): it must close over no
    traced value."""
    if keep not in ("residuals", "carries"):
        raise ValueError(f"checkpointed_while_loop: keep must be 'residuals' or 'carries', not {keep!r}.")
    numbers = bool | int | float | np.generic | np.ndarray
    init = jtu.tree_map(lambda x: jnp.asarray(x) if isinstance(x, numbers) else x, init)
    leaves, tree = jtu.tree_flatten(init)
    mask = list(differentiated(init))
    if len(mask) != len(leaves):
        raise ValueError(f"checkpointed_while_loop: {len(mask)} flags for {len(leaves)} leaves.")
    is_array = [eqx.is_array(x) for x in leaves]
    statics = [x for x, a in zip(leaves, is_array, strict=True) if not a]

    def arrays(ls):
        return [x for x, a in zip(ls, is_array, strict=True) if a]

    def with_statics(arrs):
        return _join(arrs, statics, is_array)

    # The body as a jaxpr whose constants (every array it closes over: the system's parameters,
    # traced or not) are explicit inputs, differentiated where inexact.
    body_c, consts, _ = closure_converted(lambda *arrs: arrays(jtu.tree_leaves(body_fun(jtu.tree_unflatten(
        tree, with_statics(list(arrs)))))), *arrays(leaves))
    kmask = [eqx.is_inexact_array(x) for x in consts]
    k = segment_length(max_steps, checkpoints)
    num_stores = -(-max_steps // k)
    packing = _Packing(arrays(leaves))

    def step(ls, ks):
        return with_statics(body_c(ks, *arrays(ls)))

    def forward(ls, ks, store: bool):
        buf = packing.buffers(num_stores) if store else []

        def cond(s):
            return cond_fun(jtu.tree_unflatten(tree, s[0])) & (s[1] < max_steps)

        def body(s):
            ls, i, buf = s
            if store:
                def write(b, cur):
                    return [lax.dynamic_update_index_in_dim(bb, x, i // k, 0)
                            for bb, x in zip(b, packing.pack(cur), strict=True)]

                buf = lax.cond(i % k == 0, write, lambda b, cur: b, buf, arrays(ls))
            return step(ls, ks), i + 1, buf

        return lax.while_loop(cond, body, (ls, jnp.array(0), buf))

    # Which of the inexact constants carry a derivative (known when the forward pass is traced):
    # the others are not differentiated (a tangent there could reach a loop of the body that
    # reverse mode cannot go through, such as a root search on values without derivatives).
    perturbed: list[bool] = []

    @jax.custom_vjp
    def run(d, nd, kd, knd):
        return arrays(forward(_join(d, nd, mask), _join(kd, knd, kmask), False)[0])

    def run_fwd(d, nd, kd, knd):
        perturbed[:] = [x.perturbed for x in kd]
        d, nd, kd, knd = ([x.value for x in xs] for xs in (d, nd, kd, knd))
        out, n, buf = forward(_join(d, nd, mask), _join(kd, knd, kmask), True)
        return arrays(out), (buf, n, kd, knd, nd)

    def run_bwd(res, ct):
        buf, n, kd, knd, nd = res
        ks = _join(kd, knd, kmask)
        ct = [jnp.zeros(c.aval.shape, c.aval.dtype) if isinstance(c, jax.custom_derivatives.SymbolicZero)
              else c for c in ct]
        ct_d = _split(with_statics(ct), mask)[0]
        kd_p, kd_u = _split(kd, perturbed)

        amask = _split(mask, is_array)[0]  # `mask` on the carry's arrays
        shapes = [jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)) for x in arrays(leaves)]

        def one(ld_, kp_, lnd_):
            """The body on the carry's arrays: (differentiated next carry, the rest)."""
            ks_ = _join(_join(kp_, kd_u, perturbed), knd, kmask)
            return _split(arrays(step(with_statics(_join(ld_, lnd_, amask)), ks_)), amask)

        if keep == "residuals":
            # The body's linearisation, traced once: the next carry and the pullback's residuals.
            pullback_tree = []

            def linearised(ld_, kp_, lnd_):
                out, pullback, aux = jax.vjp(lambda a, b: one(a, b, lnd_), ld_, kp_, has_aux=True)
                residuals, tree_ = jtu.tree_flatten(pullback)
                pullback_tree.append(tree_)
                return _join(out, aux, amask), residuals

            ld_shapes, lnd_shapes = _split(shapes, amask)
            lin_c, lin_consts, (_, kept_avals) = closure_converted(linearised, ld_shapes, kd_p, lnd_shapes)

            def advance(ls):
                ld_, lnd_ = _split(ls, amask)
                return lin_c(lin_consts, ld_, kd_p, lnd_)

            def pull_back(kept_, ct_d):
                return jtu.tree_unflatten(pullback_tree[0], kept_)(ct_d)
        else:
            kept_avals = shapes

            def advance(ls):
                return arrays(step(with_statics(ls), ks)), ls

            def pull_back(kept_, ct_d):
                ld_, lnd_ = _split(kept_, amask)
                return jax.vjp(lambda a, b: one(a, b, lnd_)[0], ld_, kd_p)[1](ct_d)

        def segment(s):
            j, ct_d, ct_k = s
            start = packing.unpack([lax.dynamic_index_in_dim(b, j, keepdims=False) for b in buf])
            # The last segment runs on to the loop's end (`recomputed_length`).
            length = jnp.minimum(k, n - j * k)
            # never past max_steps: a forward pass stopped there is recomputed to the same iteration
            extended_to = jnp.where(j == first, jnp.minimum(length + FINISH, max_steps - j * k), length)

            def recompute(r):
                t, ls, kept = r
                ls, item = advance(ls)
                kept = [lax.dynamic_update_index_in_dim(b, x, t, 0) for b, x in zip(kept, item, strict=True)]
                return t + 1, ls, kept

            def more(r):
                return recomputed_length(r[0], length, extended_to, lambda: cond_fun(jtu.tree_unflatten(
                    tree, with_statics(r[1]))))

            kept = [jnp.zeros((k + FINISH,) + a.shape, a.dtype) for a in kept_avals]
            recomputed, _, kept = lax.while_loop(more, recompute, (jnp.array(0), start, kept))

            def back(r):
                t, ct_d, ct_k = r
                item = [lax.dynamic_index_in_dim(b, recomputed - 1 - t, keepdims=False) for b in kept]
                g_d, g_k = pull_back(item, ct_d)
                return t + 1, g_d, [a + b for a, b in zip(g_k, ct_k, strict=True)]

            _, ct_d, ct_k = lax.while_loop(lambda r: r[0] < recomputed, back, (jnp.array(0), ct_d, ct_k))
            return j - 1, ct_d, ct_k

        first = (n + k - 1) // k - 1
        zeros_k = [jnp.zeros_like(x) for x in kd_p]
        _, ct_d, ct_k = lax.while_loop(lambda s: s[0] >= 0, segment, (first, ct_d, zeros_k))
        ct_k = _join(ct_k, [jnp.zeros_like(x) for x in kd_u], perturbed)
        return ct_d, _zero_cotangents(nd), ct_k, _zero_cotangents(knd)

    run.defvjp(run_fwd, run_bwd, symbolic_zeros=True)
    d, nd = _split(leaves, mask)
    kd, knd = _split(consts, kmask)
    return jtu.tree_unflatten(tree, with_statics(run(d, nd, kd, knd)))
