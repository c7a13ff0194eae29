"""The engines' loops started with the derivatives their bodies give them
(`perturbed_like_the_body`): each engine lists the carried fields its body differentiates."""

import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
from jax import lax


def _zero_from(xs):
    """0.0 (+0.0, exactly), with a (zero) derivative wherever one of `xs` has one: each leaf
    selected away (`lax.select` on an all-False predicate, whose tangent is the tangent
    selected away: a zero that depends on it), and the zeros summed. Batched under `jax.vmap`
    wherever a leaf is (a `jax.custom_jvp` returning an unbatched zero with a batched tangent
    fails JAX's batching once staged: `jax.grad` of a direct `simulate_batch` call on the
    per-execution engine)."""
    dtype = jnp.result_type(*xs)
    away = (lax.select(jnp.zeros(jnp.shape(x), bool), x, jnp.zeros_like(x)) for x in xs)
    return sum(jnp.sum(a).astype(dtype) for a in away)


def perturbed_like_the_body(carry, inputs, fields):
    """`carry` with each of its `fields` (float leaves) minus a zero that carries a derivative
    wherever one of `inputs` does: the same values bit for bit (x - 0 is x, -0 and inf
    included), differentiated as the body will differentiate them.

    Under differentiation, equinox's while loops (and JAX's) find which carried values carry
    a derivative by differentiating the body, growing the set from the initial values' until
    it stops growing: one trace of the body's derivative per round. A loop's record (and the
    per-execution loop's held step) starts as constants and is reached a round or two later;
    started where the body takes it, the first round confirms the set. The derivatives are
    unchanged (the added tangents are zero); only tracing is saved."""
    leaves = [x for x in jtu.tree_leaves(inputs) if eqx.is_inexact_array(x)]
    if not leaves:
        return carry
    z = _zero_from(leaves)

    def seeded(obj):
        names = [n for n in fields if getattr(obj, n, None) is not None]
        return eqx.tree_at(
            lambda o: [getattr(o, n) for n in names], obj,
            [jtu.tree_map(lambda a: a - z.astype(a.dtype) if eqx.is_inexact_array(a) else a, getattr(obj, n))
             for n in names])

    return tuple(seeded(c) for c in carry)
