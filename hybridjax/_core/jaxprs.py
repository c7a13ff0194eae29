"""A function as a program of its closure's arrays and its arguments."""

from collections.abc import Callable

import jax
import jax.tree_util as jtu


def closure_converted(fn: Callable, *example_args):
    """`fn` traced once into a jaxpr: `(fn_c, consts, out_shape)` with
    `fn_c(consts, *args) == fn(*args)` for arguments shaped as `example_args` (arrays or
    `jax.ShapeDtypeStruct`s, in pytrees).

    Every array `fn` reads from its closure, traced or not, becomes one of `consts`: an explicit
    input that a custom derivative can differentiate, and that a rule traced after the caller's
    trace has ended can still be given (`jax.closure_convert` hoists only the values that may
    carry a tangent). Calling `fn_c` evaluates the jaxpr, which costs less than tracing `fn`
    again. `out_shape`: `fn`'s output as `jax.ShapeDtypeStruct`s."""
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*example_args)
    out_tree = jtu.tree_structure(out_shape)

    def fn_c(consts, *args):
        return jtu.tree_unflatten(out_tree, jax.core.eval_jaxpr(closed.jaxpr, consts, *jtu.tree_leaves(args)))

    return fn_c, list(closed.consts), out_shape


def equation_count(fn: Callable, *example_args) -> int:
    """The number of equations of `fn`'s jaxpr for arguments shaped as `example_args`, those of
    the jaxprs nested in its equations (calls, loops, conditionals, custom derivatives) included:
    a measure of the program `fn` adds at each place it is traced."""
    def count(jaxpr) -> int:
        total = 0
        for eqn in jaxpr.eqns:
            total += 1
            for param in eqn.params.values():
                for sub in param if isinstance(param, (tuple, list)) else (param,):
                    inner = getattr(sub, "jaxpr", sub)  # a ClosedJaxpr holds its Jaxpr
                    if hasattr(inner, "eqns"):
                        total += count(inner)
        return total

    return count(jax.make_jaxpr(fn)(*example_args).jaxpr)
