"""The JAX transformations a call is made under, read from JAX's current trace.

A call of `simulate` or `simulate_batch` sees its transformations as a chain of traces, the
innermost first: `jax.jvp` and `jax.jacfwd` add a JVP trace, `jax.grad`, `jax.vjp` and
`jax.jacrev` a linearize trace, `jax.vmap` a batching trace, and `jax.jit` (as `lax.scan`,
`lax.cond`, `jax.checkpoint`) a staging trace that records a program. What lies beneath a
staging trace says nothing about the program it records: JAX keeps that program and reuses it
under other transformations, so only the traces above the nearest staging trace are read here.

Three uses:

- a call whose chain reaches JAX's eager evaluation with only JVP, linearize and batching
  traces on the way ("eager at the top") can run as a compiled program that JAX transforms,
  and reuses across calls (`hybridjax._eager`);
- a forward-mode derivative needs a loop that JAX can differentiate forwards: the default
  `RecursiveCheckpointAdjoint`'s checkpointed loop is a `jax.custom_vjp`, which only reverse
  mode can go through, so under a JVP trace (and no linearize trace) it is replaced by
  `ForwardMode()` (`adjoint_for`);
- the per-execution loop's reverse mode keeps each iteration's residuals for one execution and
  its carries for a batch, which runs faster under `jax.vmap` (`runs_batched`).

The current trace is read from `jax._src.core.trace_ctx` (private: JAX's "stackless" tracing,
where each trace knows its parent). Without it every call counts as staged, with no derivative
seen: calls are made as plain calls, and a forward-mode derivative with the default adjoint
fails with the error of `FORWARD_MODE_HINT`.
"""

import contextlib
import contextvars
import warnings

import diffrax

_DERIVATIVE = {"JVPTrace": "forward", "LinearizeTrace": "reverse", "BatchTrace": None}

# The derivative modes of the call that `hybridjax._eager` is running compiled: inside it, the
# call's own traces lie beneath the staging trace of its compiled program.
_CALL_MODES: contextvars.ContextVar[frozenset | None] = contextvars.ContextVar("hybridjax_call_modes",
                                                                              default=None)
# Whether that call runs under a batching trace (`jax.vmap`).
_CALL_BATCHED: contextvars.ContextVar[bool] = contextvars.ContextVar("hybridjax_call_batched", default=False)

FORWARD_MODE_HINT = (
    "Forward-mode differentiation (jax.jvp, jax.jacfwd) of hybridjax.simulate / simulate_batch "
    "needs adjoint=diffrax.ForwardMode(): the default RecursiveCheckpointAdjoint is a "
    "jax.custom_vjp, which only reverse mode goes through. hybridjax makes this choice itself "
    "where it sees the JVP at the call; it cannot where the JVP is taken outside a jax.jit (or "
    "lax.scan, ...) inside which the call is made."
)


def _traces() -> list[str]:
    """The class names of the current trace and its parents, innermost first (empty where JAX
    does not say)."""
    try:
        from jax._src.core import trace_ctx
        trace = trace_ctx.trace
    except (ImportError, AttributeError):
        return []
    names = []
    while trace is not None and len(names) < 256:
        names.append(type(trace).__name__)
        trace = getattr(trace, "parent_trace", None)
    return names


def _chain() -> tuple[tuple[str, ...], str | None]:
    """The JVP, linearize and batching traces above the nearest other trace (class names,
    innermost first), and that other trace's class name (None where JAX does not say)."""
    names = _traces()
    top = 0
    while top < len(names) and names[top] in _DERIVATIVE:
        top += 1
    return tuple(names[:top]), names[top] if top < len(names) else None


def eager_at_top() -> bool:
    """Whether the call is made outside every staging trace (`jax.jit`, `lax.scan`, ...), under
    JVP, linearize and batching traces only (`jax.grad`, `jax.jvp`, `jax.vmap`, ...) or none."""
    return _chain()[1] == "EvalTrace"


def reverse_only_at_call() -> bool:
    """Whether exactly one linearize trace (`jax.grad`, `jax.vjp`, `jax.jacrev`), and no other
    JVP, linearize or batching trace, lies between the call and the nearest other trace."""
    return _chain()[0] == ("LinearizeTrace",)


def batched_at_call() -> bool:
    """Whether a batching trace (`jax.vmap`, and the batches of `jax.jacfwd` and `jax.jacrev`)
    lies between the call and the nearest other trace: for a call made outside `jax.jit`
    (`eager_at_top`), whether it runs a batch."""
    return "BatchTrace" in _chain()[0]


def runs_batched() -> bool:
    """Whether the call runs as part of a batch: a batching trace at the call
    (`batched_at_call`), or at the call whose compiled program is being traced. (A batch taken
    outside a `jax.jit` inside which the call is made is not seen.)"""
    return batched_at_call() or _CALL_BATCHED.get()


def derivative_modes() -> frozenset:
    """The derivatives taken through the call: "forward" (`jax.jvp`, `jax.jacfwd`), "reverse"
    (`jax.grad`, `jax.vjp`, `jax.jacrev`), both (`jax.hessian`) or none."""
    names, _ = _chain()
    return compiled_call_modes() | frozenset(_DERIVATIVE[n] for n in names if _DERIVATIVE[n])


@contextlib.contextmanager
def compiled_call(modes: frozenset, batched: bool = False):
    """Within: tracing the compiled program of a call made under the derivative traces `modes`
    (`derivative_modes()` and `compiled_call_modes()` say so), and under a batching trace
    where `batched` (`runs_batched()` says so)."""
    token, token_b = _CALL_MODES.set(modes), _CALL_BATCHED.set(batched)
    try:
        yield
    finally:
        _CALL_MODES.reset(token)
        _CALL_BATCHED.reset(token_b)


def compiled_call_modes() -> frozenset:
    """The derivative modes at the call whose compiled program is being traced (empty outside
    one): what a leaf of that call, a tracer of the program, no longer shows."""
    modes = _CALL_MODES.get()
    return frozenset() if modes is None else modes


def adjoint_for(adjoint, modes: frozenset):
    """`ForwardMode()` in place of the default `RecursiveCheckpointAdjoint` under forward mode
    alone; otherwise `adjoint` as given (an explicit choice, or what reverse mode needs). Forward
    over reverse (`jax.hessian`) keeps the default: the outer JVP differentiates the reverse
    pass's forward and backward computations, which are ordinary code, not the custom_vjp."""
    if isinstance(adjoint, diffrax.RecursiveCheckpointAdjoint) and modes == {"forward"}:
        return diffrax.ForwardMode()
    return adjoint


def warn_if_forward_mode_beneath(adjoint, where: str) -> None:
    """Warn where the default adjoint is traced inside a staging trace (`jax.jit`, ...) made
    under a JVP trace: if that JVP differentiates through the staged program, JAX fails with
    its bare custom_vjp error, which does not name the fix; the warning does. (The program
    cannot be given another loop: JAX reuses it under other transformations.) Not inside the
    program compiled for a call by `hybridjax._eager`, which names the fix itself."""
    if not isinstance(adjoint, diffrax.RecursiveCheckpointAdjoint) or _CALL_MODES.get() is not None:
        return
    names = _traces()
    top = len(_chain()[0])
    if "JVPTrace" in names[top + 1:]:
        warnings.warn(f"{where} is traced inside a jax.jit (or lax.scan, ...) that is itself under "
                      f"jax.jvp / jax.jacfwd. {FORWARD_MODE_HINT}", stacklevel=5)


@contextlib.contextmanager
def naming_the_forward_mode_fix():
    """JAX's error for a JVP of the checkpointed loop, re-raised naming the fix."""
    try:
        yield
    except TypeError as err:
        if "forward-mode" in str(err) and "custom_vjp" in str(err):
            raise TypeError(FORWARD_MODE_HINT) from err
        raise
