"""Status codes of an execution (a results enumeration, as diffrax's `RESULTS`)."""

import equinox as eqx


class Status(eqx.Enumeration):
    """Why an execution stopped.

    One value per execution; under `jax.vmap` a batch of them. Compare with `==`
    (`sol.status == hj.Status.T1_REACHED`) or read the integer code with
    `hj.status_code(sol.status)`. Precedence when two apply at the same iteration: the
    first condition met in loop order wins (non-finite values, then the step limit,
    then the epoch limit), and everything computed before the stop is kept.
    """

    T1_REACHED = "The execution reached t1."
    MAX_EPOCHS = "The execution needed more than `max_epochs` transitions."
    BLOCKED = "The flow left the domain outside every guard, or a reset left the target domain."
    ZENO = "Event times accumulate (Zeno execution)."
    CHATTERING = "Too many zero-length epochs in a row (chattering / zero-time Zeno)."
    MAX_STEPS = "The execution needed more than `max_steps` solver steps."
    NONFINITE = "A flow, guard or reset produced a non-finite value."


STATUS_NAMES: tuple[str, ...] = (
    "T1_REACHED",
    "MAX_EPOCHS",
    "BLOCKED",
    "ZENO",
    "CHATTERING",
    "MAX_STEPS",
    "NONFINITE",
)
