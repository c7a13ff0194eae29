"""The precedence of statuses: which stop rule decides."""

import jax.numpy as jnp


# ---------------------------------------------------------------------------- statuses
def stop_first(done, code, *rules):
    """The precedence of statuses: `(done, code)` after the stop rules `(pred, Status)` in
    order; an execution already done keeps its status, and of two rules that hold at once the
    first wins. `code`: the integer status codes (a `Status` item's `_value`)."""
    for pred, status in rules:
        pred = pred & ~done
        done, code = done | pred, jnp.where(pred, status._value, code)
    return done, code
