"""Calls made outside any JAX transformation, compiled once per configuration and reused.

`simulate` and `simulate_batch` build their loop (closures over the system, the solver and
the options) on every call. Under the caller's own `jax.jit` that is traced once; called
directly, as in a notebook, each call traced and compiled its loops anew: 2.7-3.5 s per call
for the bouncing ball on a 2-core CPU, however often the same problem was run.
`compiled_when_eager` runs such a call under `eqx.filter_jit` instead: arrays (`jax.Array`,
NumPy arrays and scalars) are its inputs, everything else (the system's functions, Python
numbers and strings, the solver, the options) is part of the cache key, compared by
equality. A second call with arrays of the same shapes and dtypes and equal other arguments
runs the compiled program at once; a changed Python number compiles a new one, as a changed
constant must. Compiled programs stay in memory until `jax.clear_caches()`, as with
`jax.jit`; before, every direct call added one (~600 memory mappings each for the ball, in a
process whose limit is 65,530 by default), now each configuration adds one.

Left to the plain call (what happened before): calls inside a transformation (`jax.jit`,
`jax.grad`, `jax.vmap`, ...), which compile with their caller; arguments with an unhashable
non-array leaf; and calls that need a concrete value of an array argument (a 0-d NumPy array
`mode0` of `simulate_batch` with an `x0` to pad, read as a Python integer): tracing them
raises a concretization error, and the call is run as before.
"""

import contextvars
import functools
import inspect
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

_TIME_SPAN_CHECKED = contextvars.ContextVar("hybridjax_time_span_checked", default=None)


class _Ticket:
    used: bool = False


# The errors of code that needs a concrete value where the compiled call gives it a tracer.
_NEEDS_CONCRETE = (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
                   jax.errors.TracerBoolConversionError, jax.errors.TracerIntegerConversionError)


def take_time_span_check() -> bool:
    """Whether t1 >= t0 was checked on concrete values at the call being traced, so that its
    check needs no traced copy (and no host callback). True once per compiled call, for the
    first check made in its trace: the call's own."""
    ticket = _TIME_SPAN_CHECKED.get()
    if ticket is None or ticket.used:
        return False
    ticket.used = True
    return True


def _inside_transformation() -> bool:
    try:
        from jax._src.core import trace_state_clean
    except ImportError:  # a JAX without it: treat every call as transformed (the plain call)
        return True
    return not trace_state_clean()


class _StaticScalar:
    """A NumPy scalar kept static (part of the cache key), as the plain call saw it: code that
    checks `isinstance(mode0, np.integer)` or calls `int(max_epochs)` gets the scalar back."""

    __slots__ = ("value",)

    def __init__(self, value):
        self.value = value

    def __eq__(self, other):
        return (isinstance(other, _StaticScalar) and type(other.value) is type(self.value)
                and bool(other.value == self.value))

    def __hash__(self):
        return hash((type(self.value), self.value.item()))


def _wrap_scalars(tree):
    return jtu.tree_map(lambda x: _StaticScalar(x) if isinstance(x, np.generic) else x, tree)


def _unwrap_scalars(tree):
    return jtu.tree_map(lambda x: x.value if isinstance(x, _StaticScalar) else x, tree)


def _eager_leaves(tree) -> bool:
    """Every leaf concrete (no tracer) and every non-array leaf hashable (a cache key)."""
    for leaf in jtu.tree_leaves(tree):
        if isinstance(leaf, jax.core.Tracer):
            return False
        if not eqx.is_array(leaf):
            try:
                hash(leaf)
            except TypeError:
                return False
    return True


def compiled_when_eager(check_time_span: Callable) -> Callable:
    """Decorator: `fn` called outside any transformation runs as `eqx.filter_jit(fn)`.

    `check_time_span(t0, t1, where, given)` is called at the call on the concrete t0 and t1
    first (a `ValueError` there, as before); inside the compiled call `take_time_span_check()`
    then says so, and the traced check adds no host callback (which would keep the program out
    of JAX's persistent compilation cache)."""

    def wrap(fn: Callable) -> Callable:
        compiled = eqx.filter_jit(lambda args, kwargs: fn(*_unwrap_scalars(args), **_unwrap_scalars(kwargs)))
        signature = inspect.signature(fn)

        @functools.wraps(fn)
        def call(*args, **kwargs):
            if _inside_transformation():
                return fn(*args, **kwargs)
            bound = signature.bind(*args, **kwargs)
            # The state is an array whatever the caller wrote (a list of floats would otherwise
            # be part of the key, and compile again for every initial state).
            if isinstance(bound.arguments["x0"], (list, tuple)):
                bound.arguments["x0"] = jnp.asarray(bound.arguments["x0"])
            call_args, call_kwargs = _wrap_scalars((bound.args, bound.kwargs))
            if not _eager_leaves((call_args, call_kwargs)):
                return fn(*args, **kwargs)
            bound.apply_defaults()
            t0, t1 = bound.arguments["t0"], bound.arguments["t1"]
            check_time_span(t0, t1, fn.__name__, given=(t0, t1))
            token = _TIME_SPAN_CHECKED.set(_Ticket())
            try:
                return compiled(call_args, call_kwargs)
            except _NEEDS_CONCRETE:
                pass
            finally:
                _TIME_SPAN_CHECKED.reset(token)
            return fn(*args, **kwargs)

        return call

    return wrap
