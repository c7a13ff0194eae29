"""Status codes of an execution (a results enumeration, as diffrax's `RESULTS`)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class Status(eqx.Enumeration):
    """Why an execution stopped.

    One value per execution; under `jax.vmap` or `simulate_batch` a batch of them.
    Precedence when two apply at the same iteration: the first condition met in loop order
    wins (non-finite values, then a collapsed step size, then the step limit, then the epoch
    limit), and everything computed before the stop is kept.

    A status is also its integer code, the index of its name in `hj.STATUS_NAMES` (codes are
    only ever appended, so stored codes keep their meaning): `int(...)` of one status, or of
    a member, gives the code; `np.asarray(...)` of a batch gives the array of codes (as does
    `sol.status_code`, which also works on traced values); a status compares with `==` to
    another status, to a member, or to integer codes such as those of a Monte Carlo table
    (an array of booleans, traced inside `jax.jit`).

    !!! Example

        ```python
        import hybridjax as hj, jax.numpy as jnp, numpy as np
        ball = hj.examples.bouncing_ball()
        sol = hj.simulate(ball, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0,
                          {"g": 9.8, "e": 0.8}, max_epochs=3)
        sol.status == hj.Status.MAX_EPOCHS        # Array(True)
        int(sol.status), int(hj.Status.MAX_EPOCHS)  # (1, 1)
        hj.STATUS_NAMES[sol.status]               # 'MAX_EPOCHS'
        sols = hj.simulate_batch(ball, jnp.array([[1.0, 0.0], [5.0, 0.0]]), "flight",
                                 0.0, 3.0, {"g": 9.8, "e": 0.8}, max_epochs=3)
        np.asarray(sols.status)                   # array([1, 0], dtype=int32)
        mc = hj.monte_carlo(ball, x0=np.array([[1.0, 0.0], [5.0, 0.0]]), t1=3.0,
                            args={"g": np.full(2, 9.8), "e": np.full(2, 0.8)}, max_epochs=3)
        mc.per_execution["status"] == hj.Status.MAX_EPOCHS  # array([ True, False])
        ```
    """

    T1_REACHED = "The execution reached t1."
    MAX_EPOCHS = "The execution needed more than `max_epochs` transitions."
    BLOCKED = "The flow left the domain outside every guard, or a reset left the target domain."
    ZENO = "Event times accumulate (Zeno execution)."
    CHATTERING = "Too many zero-length epochs in a row (chattering / zero-time Zeno)."
    MAX_STEPS = "The execution needed more than `max_steps` solver steps."
    NONFINITE = "A flow, guard or reset produced a non-finite value."
    STEP_COLLAPSE = ("The step size fell to the resolution of t with every value finite: the flow "
                     "blows up in finite time at `final_time`, or the tolerance cannot be met there.")
    T1_BEFORE_T0 = ("t1 < t0: nothing was run. Known values of t0 and t1 raise a ValueError at the "
                    "call; values traced inside `jax.jit` or `jax.vmap` end here instead.")


STATUS_NAMES: tuple[str, ...] = (
    "T1_REACHED",
    "MAX_EPOCHS",
    "BLOCKED",
    "ZENO",
    "CHATTERING",
    "MAX_STEPS",
    "NONFINITE",
    "STEP_COLLAPSE",
    "T1_BEFORE_T0",
)


_Item = type(Status.T1_REACHED)  # equinox's enumeration item class


def _code(other):
    """`other` as an array of integer codes, or a ValueError (as equinox's for a non-status)."""
    if not isinstance(other, bool):
        code = other if isinstance(other, jax.Array) else np.asarray(other)
        if jnp.issubdtype(code.dtype, jnp.integer):
            return code
    raise ValueError("A status compares with an hj.Status member or with integer status codes "
                     f"(see hj.STATUS_NAMES), not with {other!r}.")


class StatusCode(_Item):
    """An `hj.Status` value that is also its integer code (see `Status`)."""

    def __int__(self) -> int:
        return int(self._value)

    def __index__(self) -> int:
        return int(self._value)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        return np.asarray(self._value, dtype=dtype)

    def __eq__(self, other):
        if isinstance(other, _Item):
            return super().__eq__(other)
        with jax.ensure_compile_time_eval():
            return jnp.asarray(self._value == _code(other))

    def __ne__(self, other):
        if isinstance(other, _Item):
            return super().__ne__(other)
        with jax.ensure_compile_time_eval():
            return jnp.asarray(self._value != _code(other))


def _where(cls, pred, a, b):
    item = eqx.Enumeration.__dict__["where"].__func__(cls, pred, a, b)
    return item if isinstance(item, StatusCode) else StatusCode(item._value, cls)


# Every status the package makes is a `StatusCode`: the members, and `Status.where`'s results
# (equinox's builds plain items; one class throughout keeps loop carries of one pytree type).
for _name, _member in list(Status._name_to_item.items()):
    Status._name_to_item[_name] = StatusCode(_member._value, Status)
Status.where = classmethod(_where)
