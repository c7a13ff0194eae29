"""Shape checks of a system's user functions by abstract evaluation (`jax.eval_shape`).

Nothing here calls a user function on real data: `jax.eval_shape` traces it with abstract
arrays, so the checks are cheap and have no side effects.
"""

import contextvars
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

# Set by `_solve.eager.compiled_when_eager` around the trace of a call whose time span it checked.
_TIME_SPAN_CHECKED = contextvars.ContextVar("hybridjax_time_span_checked", default=None)


class _Ticket:
    used: bool = False


def take_time_span_check() -> bool:
    """Whether t1 >= t0 was checked on concrete values at the call being traced, so that its
    check needs no traced copy (and no host callback). True once per compiled call, for the
    first check made in its trace: the call's own."""
    ticket = _TIME_SPAN_CHECKED.get()
    if ticket is None or ticket.used:
        return False
    ticket.used = True
    return True


class DefinitionError(ValueError):
    """A mode or transition of a `HybridSystem` is ill-defined (message names the culprit)."""


def as_state_array(x0, where: str) -> jax.Array:
    """`x0` as a JAX array, or a `TypeError` naming the argument when it is not numeric (most
    often a mode name passed first: the order is `(system, x0, mode0, t0, t1, args)`)."""
    if isinstance(x0, str) or (isinstance(x0, np.ndarray) and not np.issubdtype(x0.dtype, np.number)):
        raise TypeError(f"{where}: x0 must be an array of numbers, got {x0!r}. The arguments are "
                        f"{where}(system, x0, mode0, t0, t1, args): were x0 and mode0 swapped?")
    return jnp.asarray(x0)


def check_time_span(t0, t1, where: str, given: tuple):
    """`(t1, before)`: t1 clamped to >= t0, and where t1 < t0 (elementwise).

    `given`: (t0, t1) as the caller passed them. Known values are checked here, at the call
    (a `ValueError` naming `where`). Traced ones (inside `jax.jit`, `jax.vmap` or a derivative
    with respect to t0 or t1) cannot raise a readable error: the execution runs over the empty
    span [t0, t0] and its status is set to `T1_BEFORE_T0` where `before` holds, one status per
    execution, like every other stop. No host callback enters the program, which keeps it
    cacheable by JAX's persistent compilation cache. Inside a call compiled by
    `compiled_when_eager` the check was made at its call."""
    # "Not before" as a NumPy constant: no array to dispatch at a direct call's check.
    if take_time_span_check():
        return t1, np.zeros(np.shape(t1), bool)
    try:
        bad = bool(np.any(np.asarray(given[1]) < np.asarray(given[0])))
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        # t1 where t1 = t0, with its whole derivative (`jnp.maximum` would halve it at the tie).
        return jnp.where(t1 < t0, t0, t1), t1 < t0
    if bad:
        raise ValueError(f"{where}: t1 must be >= t0.")
    return t1, np.zeros(np.shape(t1), bool)


def _abstract_shape(fn, dim: int, args: Any, dtype) -> jax.ShapeDtypeStruct:
    t = jax.ShapeDtypeStruct((), dtype)
    x = jax.ShapeDtypeStruct((dim,), dtype)
    out = jax.eval_shape(fn, t, x, args)
    if not isinstance(out, jax.ShapeDtypeStruct):
        leaves = jax.tree_util.tree_leaves(out)
        if len(leaves) != 1:
            raise DefinitionError(f"returned a pytree {jax.tree_util.tree_structure(out)}, "
                                  "expected a single array")
        out = leaves[0]
    return out


def _check_one(what: str, fn, dim: int, args, dtype, strict: bool, want) -> None:
    try:
        out = _abstract_shape(fn, dim, args, dtype)
    except DefinitionError as err:
        raise DefinitionError(f"{what} {err}.") from None
    except Exception as err:  # noqa: BLE001 - any user error is re-raised with the culprit named
        if not strict:
            return  # most likely needs the real `args`; `simulate` repeats the check with them
        raise DefinitionError(
            f"{what} failed on a state of shape ({dim},): {type(err).__name__}: {err}"
        ) from err
    problem = want(out.shape)
    if problem is not None:
        raise DefinitionError(f"{what} {problem}")
    if not jnp.issubdtype(out.dtype, jnp.floating):
        raise DefinitionError(f"{what} returned dtype {out.dtype}; expected a real floating dtype.")


def check_function_shapes(system, args: Any, dtype, strict: bool) -> None:
    """Check flow, domain, guard and reset output shapes of every mode and transition.

    - flow of mode I: shape (n_I,)
    - domain of mode I: shape () or (m,)
    - guard of transition (I, J): shape () (a scalar guard function)
    - reset of transition (I, J): shape (n_J,)

    With `strict=False` a function that raises (typically because `args` is not known yet)
    is skipped; a function that evaluates with a wrong shape always raises.
    """
    for i, mode in enumerate(system.modes):
        n = mode.dim
        _check_one(
            f"Mode {i} '{mode.name}': flow", mode.flow, n, args, dtype, strict,
            lambda s, n=n: None if s == (n,) else f"returned shape {s}; expected ({n},) = (dim,).",
        )
        if mode.domain is not None:
            _check_one(
                f"Mode {i} '{mode.name}': domain", mode.domain, n, args, dtype, strict,
                lambda s: None if len(s) <= 1 else f"returned shape {s}; expected () or (m,).",
            )
    for k, tr in enumerate(system.transitions):
        src, tgt = system.modes[system.sources[k]], system.modes[system.targets[k]]
        _check_one(
            f"Transition {k} ({tr.label}, '{src.name}' -> '{tgt.name}'): guard",
            tr.guard, src.dim, args, dtype, strict,
            lambda s: None if s == () else f"returned shape {s}; a guard must return a scalar.",
        )
    for name, reset, i, j in system.jumps():
        src, tgt = system.modes[i], system.modes[j]
        _check_one(
            f"{name[:-1]}, '{src.name}' -> '{tgt.name}'): reset", reset, src.dim, args, dtype, strict,
            lambda s, m=tgt.dim: None
            if s == (m,)
            else f"returned shape {s}; expected ({m},), the target mode's dim.",
        )

def domain_sizes(system, args: Any, dtype) -> tuple[int, ...]:
    """Number of domain components m_I of each mode (0 without a domain), by eval_shape."""
    sizes = []
    for mode in system.modes:
        if mode.domain is None:
            sizes.append(0)
        else:
            out = _abstract_shape(mode.domain, mode.dim, args, dtype)
            sizes.append(1 if out.shape == () else int(out.shape[0]))
    return tuple(sizes)
