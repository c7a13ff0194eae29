"""Calls made outside `jax.jit`, compiled once per configuration and reused.

`simulate` and `simulate_batch` build their loop (closures over the system, the solver and
the options) on every call. Under the caller's own `jax.jit` that is traced once; called as
a plain function, as in a notebook, each call would trace and compile its loops anew (under
`jax.grad` too), however often the same problem was run. `compiled_when_eager` runs such a
call under `eqx.filter_jit` instead: arrays (`jax.Array`, NumPy arrays and scalars, and the
tracers of `jax.grad`, `jax.jvp`, `jax.vmap`, ...) are its inputs, everything else (the
system's functions, Python numbers and strings, the solver, the options) is part of the cache
key, compared by equality. A second call with arrays of the same shapes and dtypes and equal other arguments
runs the compiled program at once; a changed Python number compiles a new one, as a changed
constant must. Compiled programs stay in memory until `jax.clear_caches()`, as with
`jax.jit`: each configuration adds one (~600 memory mappings for the ball, in a process whose
limit is 65,530 by default).

This holds under `jax.grad`, `jax.vjp`, `jax.jacrev`, `jax.jvp`, `jax.jacfwd`, `jax.vmap` and
their compositions, made outside `jax.jit` (`hybridjax._core.transforms.eager_at_top`): JAX
differentiates and batches the compiled call (`jit` composes with them), and keeps what it
compiles for the derivative or the batch, so a repeated `jax.grad` with new values compiles
nothing. The derivatives taken at the call (forward, reverse) and whether it runs under
`jax.vmap` are part of the cache key, and the program is traced knowing them: under forward mode
the default adjoint is replaced by one forward mode can go through
(`hybridjax._core.transforms.adjoint_for`), `simulate_batch` picks its defaults for a
differentiated call, and the per-execution loop's reverse mode what it keeps for a batch
(`hybridjax._core.transforms.runs_batched`).

A call that runs one execution (`simulate`, not under `jax.vmap`), on the CPU, is compiled
with XLA:CPU's own fusion emitters instead of its MLIR fusion emitters
(`eager_compiler_options`, `ONE_EXECUTION_CPU`): most of such a program's compile time is
spent compiling its kernels one by one, which these emitters do in one half to two thirds of
the time, and a single execution runs as fast (its reverse-mode derivative up to a tenth
slower, against the seconds its first call saves). A batch keeps the MLIR emitters, which run
it faster, and lets LLVM vectorize its loops over the executions 512 bits wide
(`BATCH_CPU`), except under reverse mode, whose programs run slower so. Both let XLA's copy
insertion analyse the loops' and conditionals' regions (`FEWER_COPIES_CPU`), which keeps fewer
copies of the arrays they carry. JAX accepts
a program's own options only on a program it compiles as called, not on one it records while
differentiating, so under one reverse-mode derivative (`jax.grad`, `jax.vjp`, `jax.jacrev`)
the call is a custom VJP whose forward pass (the solve with `jax.vjp`'s residuals) and
backward pass are two such programs (`_reverse_with_options`); under forward mode JAX
differentiates the compiled call itself, and a reverse-mode derivative nested in another
derivative (`jax.hessian`, `jax.grad` of `jax.grad`) keeps the defaults. The results are
the same to rounding. A jaxlib whose XLA does not know the option runs the call with the
defaults (`with_default_options_if_refused`).

Left to the plain call: calls inside `jax.jit` (or `lax.scan`, `jax.checkpoint`, ...), which
compile with their caller; arguments with an unhashable non-array leaf; and calls that need a
concrete value of an array argument (a 0-d NumPy array `mode0` of `simulate_batch` with an
`x0` to pad, read as a Python integer): tracing them raises a concretization error, and the
call is made as a plain call.
"""

import functools
import inspect
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from .._core.transforms import (
    adjoint_for,
    batched_at_call,
    compiled_call,
    derivative_modes,
    eager_at_top,
    naming_the_forward_mode_fix,
    reverse_only_at_call,
)
from .._core.xla_options import BATCH_CPU as BATCH_CPU
from .._core.xla_options import FAST_COMPILE_CPU as FAST_COMPILE_CPU
from .._core.xla_options import ONE_EXECUTION_CPU as ONE_EXECUTION_CPU
from .._definition.validation import _TIME_SPAN_CHECKED, _Ticket
from .prepare import SHORTHANDS, solve_options

# The errors of code that needs a concrete value where the compiled call gives it a tracer.
_NEEDS_CONCRETE = (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
                   jax.errors.TracerBoolConversionError, jax.errors.TracerIntegerConversionError)


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


def _traced(tree) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jtu.tree_leaves(tree))


def _hashable_leaves(tree) -> bool:
    """Every non-array leaf hashable (a cache key)."""
    for leaf in jtu.tree_leaves(tree):
        if not eqx.is_array(leaf):
            try:
                hash(leaf)
            except TypeError:
                return False
    return True


# `_options_as_object`'s `SolveOptions` by the arguments that built them: a repeated direct call
# reuses the object instead of building and checking it again (a few tenths of a millisecond).
_OPTIONS_BUILT: dict = {}


def _options_as_object(bound: inspect.BoundArguments, where: str) -> None:
    """`options` and its keyword shorthands replaced by the one `SolveOptions` they build, so that
    `max_epochs=8` and `options=hj.SolveOptions(max_epochs=8)` (or an `hj.Simulator` holding it)
    are one cache entry. Both given is left to the call, whose error names them."""
    given = bound.arguments.get("shorthands", {})
    mine = {name: value for name, value in given.items() if name in SHORTHANDS}
    options = bound.arguments.get("options")
    if options is not None and mine:
        return
    # Each value with its type: 1 and True, or 1e-9 and np.float64(1e-9), build different objects.
    key = (where, options, tuple((name, type(value), value) for name, value in sorted(mine.items())))
    try:
        built = _OPTIONS_BUILT.get(key)
    except TypeError:  # an unhashable value (an array): built every time
        key = built = None
    if built is None:
        built = solve_options(options, mine, where)
        if key is not None:
            if len(_OPTIONS_BUILT) >= 256:
                _OPTIONS_BUILT.clear()
            _OPTIONS_BUILT[key] = built
    bound.arguments["options"] = built
    bound.arguments["shorthands"] = {name: value for name, value in given.items() if name not in mine}


def _options_key(options: dict) -> tuple:
    """A set of XLA options as a hashable key."""
    return tuple(sorted(options.items()))


def eager_compiler_options(one_execution: bool, modes: frozenset, batched: bool, backend: str,
                           reverse_only: bool = False) -> dict:
    """The XLA compiler options of the program compiled for a call made outside `jax.jit`, on the
    `"cpu"` backend (elsewhere none: XLA's defaults); the sets named are
    `hybridjax._core.xla_options`'s:

    - `ONE_EXECUTION_CPU` (`FAST_COMPILE_CPU` and `FEWER_COPIES_CPU`) for a call that runs one
      execution (`one_execution`, and not `batched` under `jax.vmap`) with no reverse-mode
      derivative in `modes` or with reverse mode alone (`reverse_only`: one linearize trace at
      the call). One execution's programs compile in one half to two thirds of the XLA time with
      them (docs: First call); forward and forward-mode programs run as fast, reverse-mode ones
      up to a tenth slower.
    - `BATCH_CPU` (`WIDE_VECTORS_CPU` and `FEWER_COPIES_CPU`) for a batch (`simulate_batch`, or
      a call under `jax.vmap`) without a reverse-mode derivative, which runs faster with them.
    - None otherwise (a reverse-mode derivative of a batch, or one nested in another derivative).
    """
    if backend != "cpu":
        return {}
    if one_execution and not batched:
        return dict(ONE_EXECUTION_CPU) if "reverse" not in modes or reverse_only else {}
    return dict(BATCH_CPU) if "reverse" not in modes else {}


def _reverse_with_options(traced: Callable, primal: Callable, options: dict) -> Callable:
    """`traced(args, kwargs, context)` under one reverse-mode derivative, as a custom VJP whose
    two passes are programs compiled with the XLA `options`: the forward pass runs `traced`
    under `jax.vjp` with respect to the perturbed arrays and returns the result and the
    pullback (its residuals are arrays of the program's output); the backward pass applies the
    pullback to the cotangent. JAX calls both on concrete values, outside any staging trace,
    where a program may have options of its own (it refuses them on the program it records
    while differentiating a compiled call). `primal`: the call's compiled program, for JAX's
    undifferentiated evaluation."""

    def forward(diff, nondiff, context):
        def split(d):
            return eqx.partition(traced(*eqx.combine(d, nondiff), context), eqx.is_inexact_array)

        out_diff, pullback, out_rest = jax.vjp(split, diff, has_aux=True)
        return eqx.combine(out_diff, out_rest), pullback, out_diff

    forward = eqx.filter_jit(forward, compiler_options=options)
    backward = eqx.filter_jit(lambda pullback, ct: pullback(ct)[0], compiler_options=options)

    @eqx.filter_custom_vjp
    def run(inputs, context):
        return primal(*inputs, context)

    @run.def_fwd
    def _(perturbed, inputs, context):
        out, pullback, out_diff = forward(*eqx.partition(inputs, perturbed), context)
        return out, (pullback, out_diff)

    @run.def_bwd
    def _(residuals, grad_obj, perturbed, inputs, context):
        pullback, out_diff = residuals
        # A cotangent for every differentiable output: zeros where the caller's is symbolic.
        ct = jtu.tree_map(lambda o, g: None if o is None else (jnp.zeros_like(o) if g is None else g),
                          out_diff, grad_obj, is_leaf=lambda x: x is None)
        return backward(pullback, ct)

    return lambda args, kwargs, context: run((args, kwargs), context)


# The option sets this process's XLA refused (a jaxlib without one of their options).
_REFUSED: set[tuple] = set()


def with_default_options_if_refused(options: dict, with_options: Callable, default: Callable, *args):
    """`with_options(*args)`, a function compiled with the extra XLA `options`; `default(*args)`
    where XLA does not know one of them ("No such compile option": a jaxlib older or newer than
    the option), and from then on in the process for that set, so that a direct call never fails
    for it."""
    key = _options_key(options)
    if key not in _REFUSED:
        try:
            return with_options(*args)
        except jax.errors.JaxRuntimeError as err:
            if "No such compile option" not in str(err):
                raise
            _REFUSED.add(key)
    return default(*args)


def compiled_when_eager(check_time_span: Callable, *, one_execution: bool = False) -> Callable:
    """Decorator: `fn` called outside `jax.jit` (also under `jax.grad`, `jax.vmap`, ...) runs as
    `eqx.filter_jit(fn)`.

    `check_time_span(t0, t1, where, given)` is called at the call where t0 and t1 are known
    (a `ValueError` there); inside the compiled call `take_time_span_check()` then says so, and
    the program needs no check of its own. Traced t0 or t1 (a derivative or a batch over them)
    are checked inside the program (a `T1_BEFORE_T0` status where t1 < t0). Whether they were
    checked at the call is part of the cache key, so that a program without the check never
    serves a call that needs it. `one_execution`: `fn` runs one execution, so that its
    program may be compiled with `eager_compiler_options`."""

    def wrap(fn: Callable) -> Callable:
        signature = inspect.signature(fn)

        def traced(args, kwargs, context):
            modes, checked, batched = context
            token = _TIME_SPAN_CHECKED.set(_Ticket() if checked else None)
            try:
                with compiled_call(modes, batched):
                    return fn(*_unwrap_scalars(args), **_unwrap_scalars(kwargs))
            finally:
                _TIME_SPAN_CHECKED.reset(token)

        # One compiled wrapper per set of compiler options (a jit's options are fixed).
        compiled = {(): eqx.filter_jit(traced)}

        def program(options: dict) -> Callable:
            key = _options_key(options)
            if key not in compiled:
                compiled[key] = eqx.filter_jit(traced, compiler_options=options)
            return compiled[key]

        reverse_compiled = _reverse_with_options(traced, program(ONE_EXECUTION_CPU), ONE_EXECUTION_CPU)

        @functools.wraps(fn)
        def call(*args, **kwargs):
            if not eager_at_top():
                return fn(*args, **kwargs)
            bound = signature.bind(*args, **kwargs)
            # Defaults written out: a keyword passed at its default is the same cache entry.
            bound.apply_defaults()
            # The state is an array whatever the caller wrote (a list of floats would otherwise
            # be part of the key, and compile again for every initial state).
            if isinstance(bound.arguments["x0"], (list, tuple)):
                bound.arguments["x0"] = jnp.asarray(bound.arguments["x0"])
            # The adjoint the derivatives at the call need, chosen here: inside the compiled
            # program the call's own derivative traces are no longer visible.
            modes = derivative_modes()
            adjoint = bound.arguments.get("adjoint", signature.parameters["adjoint"].default)
            if adjoint_for(adjoint, modes) is not adjoint:
                bound.arguments["adjoint"] = adjoint_for(adjoint, modes)
            _options_as_object(bound, fn.__name__)
            call_args, call_kwargs = _wrap_scalars((bound.args, bound.kwargs))
            if not _hashable_leaves((call_args, call_kwargs)):
                return fn(*bound.args, **bound.kwargs)
            t0, t1 = bound.arguments["t0"], bound.arguments["t1"]
            checked = not _traced((t0, t1))
            if checked:
                check_time_span(t0, t1, fn.__name__, given=(t0, t1))
            try:
                reverse_only, batched = reverse_only_at_call(), batched_at_call()
                options = eager_compiler_options(one_execution, modes, batched, jax.default_backend(),
                                                 reverse_only)
                context = (modes, checked, batched)
                # JAX differentiates the compiled call here, where a forward-mode derivative
                # of the reverse-mode loop (under jax.hessian) fails: the error names the fix.
                with naming_the_forward_mode_fix():
                    if options:
                        # Reverse mode with options: one execution's (`ONE_EXECUTION_CPU`) alone.
                        with_options = reverse_compiled if "reverse" in modes else program(options)
                        return with_default_options_if_refused(options, with_options, program({}),
                                                               call_args, call_kwargs, context)
                    return program({})(call_args, call_kwargs, context)
            except _NEEDS_CONCRETE:
                pass
            return fn(*bound.args, **bound.kwargs)

        return call

    return wrap
