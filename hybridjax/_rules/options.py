"""The options of a run, as validated objects: event location (`EventOptions`) and everything
else the loops read (`SolveOptions`, which holds the `EventOptions` and the `ZenoOptions`).

`simulate` and `simulate_batch` build one `SolveOptions` (from `options=` or from their keyword
shorthands, `hybridjax._solve.prepare.solve_options`) and hand the same object to whichever
loop runs the executions.
"""

import equinox as eqx
import numpy as np

from .._core.checks import check_int
from .locate import DEFAULT_LOCATOR, AbstractEventLocator
from .zeno import ZenoOptions


class EventOptions(eqx.Module):
    r"""How events are detected and located within a step (`hj.SolveOptions(events=...)`).

    Each guard (and domain component) is sampled on the step's dense output at
    `interior_points` equally spaced interior points and at the step's end; a crossing is the
    first sample with g <= 0 after one with g > 0. Between two positive samples a local minimum
    of g that may reach zero is searched for (`locator.minimum`); one below zero is a crossing
    too. The event time is then located on the dense output (`locator.root`) to

    $$|t^* - t_{\text{root}}| \le \max(\text{tol}\, h,\ 8\,\text{ulp}(t)),$$

    $h$ the step in which the event lies, $t^*$ on the guard side ($g(t^*) \le 0$).

    **Fields:**

    - `locator`: an `hj.AbstractEventLocator` (default `hj.BracketedNewton()`).
    - `tol`: the event-time tolerance relative to the step; None (default): 1e-12 in float64,
      1e-6 in float32 (the run's dtype decides). `simulate`'s `event_tol` sets it.
    - `interior_points`: samples inside each step (default 4); more catch a guard entered and
      left within one step at a smaller dip. `simulate`'s `interior_points` sets it.

    !!! Example

        ```python
        import hybridjax as hj, jax.numpy as jnp
        ball = hj.examples.bouncing_ball()
        opts = hj.SolveOptions(events=hj.EventOptions(tol=1e-10, interior_points=8))
        sol = hj.simulate(ball, jnp.array([1.0, 0.0]), "flight", 0.0, 1.0, {"g": 9.8, "e": 0.8},
                          options=opts)
        ```
    """

    locator: AbstractEventLocator = DEFAULT_LOCATOR
    # tol: a traced value is allowed (it enters the bracket width arithmetic only).
    tol: float | None = None
    interior_points: int = eqx.field(static=True, default=4)  # static: the number of samples (a shape)

    def __check_init__(self):
        if not isinstance(self.locator, AbstractEventLocator):
            raise TypeError(f"EventOptions: locator must be an hj.AbstractEventLocator, got "
                            f"{type(self.locator).__name__}.")
        if self.tol is not None and eqx.is_array_like(self.tol) and not eqx.is_array(self.tol):
            if not 0 < self.tol < 1:
                raise ValueError(f"EventOptions: tol must be in (0, 1) (relative to the step), "
                                 f"got {self.tol!r}.")
        check_int("EventOptions", "interior_points", self.interior_points, 0)


class SolveOptions(eqx.Module):
    r"""The options of `simulate` and `simulate_batch` besides the diffrax objects, in one object
    (`hj.simulate(..., options=hj.SolveOptions(...))`).

    **Fields:**

    - `dt0`: first step size of every epoch; None (default): from the tolerances (Hairer's rule)
      for the first epoch and, with an explicit Runge-Kutta solver, the step-size controller's
      last proposal for the later ones.
    - `max_epochs`: the most transitions recorded (the length of the `Solution`'s event
      arrays); one more ends with `MAX_EPOCHS`. Default 64.
    - `max_steps`: the most solver steps, accepted and rejected, all epochs together; more end
      with `MAX_STEPS`. Default 4096.
    - `max_zero_epochs`: more zero-length epochs in a row end with `CHATTERING`. Default 16.
    - `events`: an `hj.EventOptions` (event detection and location).
    - `zeno`: an `hj.ZenoOptions`, or None to switch Zeno detection off.
    - `throw`: raise (`eqx.error_if`) when the status is not `T1_REACHED`. Default False.

    The keywords `dt0`, `max_epochs`, `max_steps`, `max_zero_epochs`, `event_tol`,
    `interior_points`, `zeno`, `zeno_window`, `zeno_ratio_tol`, `zeno_max_ratio` and `throw` of
    `simulate` are shorthands that build this object; pass either them or `options`.

    !!! Example

        ```python
        import hybridjax as hj, jax.numpy as jnp
        ball = hj.examples.bouncing_ball()
        opts = hj.SolveOptions(max_epochs=16, zeno=hj.ZenoOptions(window=4))
        sol = hj.simulate(ball, jnp.array([1.0, 0.0]), "flight", 0.0, 5.0, {"g": 9.8, "e": 0.7},
                          options=opts)
        sol.event_times.shape  # (16,)
        ```
    """

    # dt0: a traced value is allowed (the step size's arithmetic); None selects the rule above.
    dt0: float | None = None
    # static: the record's length (a shape) and the while loop's bound.
    max_epochs: int = eqx.field(static=True, default=64)
    max_steps: int = eqx.field(static=True, default=4096)
    max_zero_epochs: int = 16  # compared with a counter in the loop: may be traced
    events: EventOptions = EventOptions()
    zeno: ZenoOptions | None = ZenoOptions()
    throw: bool = eqx.field(static=True, default=False)  # static: decides whether a check is traced

    def __check_init__(self):
        check_int("SolveOptions", "max_epochs", self.max_epochs, 1)
        check_int("SolveOptions", "max_steps", self.max_steps, 1)
        check_int("SolveOptions", "max_zero_epochs", self.max_zero_epochs, 0)
        if not isinstance(self.events, EventOptions):
            raise TypeError(f"SolveOptions: events must be an hj.EventOptions, "
                            f"got {type(self.events).__name__}.")
        if self.zeno is not None and not isinstance(self.zeno, ZenoOptions):
            raise TypeError(f"SolveOptions: zeno must be an hj.ZenoOptions or None, "
                            f"got {type(self.zeno).__name__}.")
        if not isinstance(self.throw, (bool, np.bool_)):
            raise TypeError(f"SolveOptions: throw must be a bool, got {self.throw!r}.")
        if self.dt0 is not None and eqx.is_array_like(self.dt0) and not eqx.is_array(self.dt0):
            if not self.dt0 > 0:
                raise ValueError(f"SolveOptions: dt0 must be > 0 (or None), got {self.dt0!r}.")
