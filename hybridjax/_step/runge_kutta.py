"""A fast explicit Runge-Kutta step with diffrax's interface, for the epoch loop.

diffrax's `AbstractRungeKutta.step` is general (pytrees of terms and tableaus, implicit stages,
SDEs) and runs its stages in a (checkpointed) scan. Inside the epoch loop under `vmap`, that
generality is paid every iteration for every execution. `UnrolledERK` computes the same step
for an ODE with a flat state, from the same Butcher tableau (diffrax's, not retyped):

    k_i = h F(t0 + c_i h, y0 + sum_{j<i} a_ij k_j),   y1 = y0 + sum_i b_i k_i,
    err = sum_i b^err_i k_i,

with the stages unrolled in Python, so that XLA fuses each stage's arithmetic into a few
kernels over the whole batch; zero tableau entries are skipped at trace time. FSAL methods
(Tsit5, Dopri5, Bosh3) reuse the last stage as the next step's first, as diffrax does. The
dense output is diffrax's own interpolation class for the solver, fed the same `k`.

`FastIController` is diffrax's `PIDController` step-size rule for its default coefficients
(an I controller: pcoeff = dcoeff = 0, icoeff = 1) without the bookkeeping its general form
carries (dtmin/dtmax clipping, previous errors; step_ts and jump_ts, which diffrax wraps
around it, are the loops' own rule, `_rules.clip_to_times`, see `split_clip`):

    e = RMS_i( err_i / (atol + rtol max(|y0_i|, |y1_i|)) ),   keep = e < 1,
    factor = clip(safety e^(-1/q), [1 if keep else factormin, factormax if keep else safety]),

q the solver's error order (its order + 1 for an ODE, as diffrax counts it). `engine="auto"`
uses both where they give diffrax's steps exactly.

The step (`explicit_rk_step`, `rk_error_estimate`) and the step-size rule (`scaled_error`,
`pid_controller`) are written once, for one execution, over the leading (component) axis of the
state: the per-execution engine calls them through `UnrolledERK` and `FastIController`, the
batched engine on its lanes-last (n, lanes) arrays, where they broadcast over the lanes.
"""

from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax import lax

# Explicit RK solvers whose `tableau` the unrolled step reproduces; a solver is recognised by
# its tableau (`can_unroll`), so a subclass of one of them that keeps it qualifies too.
UNROLLED_SOLVERS = (diffrax.Heun, diffrax.Midpoint, diffrax.Ralston, diffrax.Bosh3,
                    diffrax.Tsit5, diffrax.Dopri5, diffrax.Dopri8)


def weighted_sum(weights, ks, like):
    """sum_i w_i k_i over the nonzero weights (zeros skipped at trace time); zeros like `like`
    when every weight is zero."""
    out = None
    for w, k in zip(weights, ks, strict=True):
        if w != 0.0:
            term = jnp.asarray(w, like.dtype) * k
            out = term if out is None else out + term
    return jnp.zeros_like(like) if out is None else out


def fold(op, x):
    """Reduce over the leading axis by a Python loop of elementwise ops (above 64 entries, the
    `jnp` reduction: `sum`, `min`, `all`, `any`). XLA:CPU runs a reduction over a small axis
    slowly: over the outer axis of a (small, N) array several times slower than the same sum
    written out, and over the minor axis of a vmapped (lanes, small) array it calls YNNPACK
    (jaxlib 0.10), which does not fuse with its inputs. Written out, the reduction is
    elementwise and fuses. The order is x_0 op x_1 op ..., left to right."""
    if x.shape[0] > 64:
        reduce = {jnp.add: jnp.sum, jnp.minimum: jnp.min, jnp.logical_and: jnp.all, jnp.logical_or: jnp.any}
        return reduce[op](x, axis=0)
    out = x[0]
    for i in range(1, x.shape[0]):
        out = op(out, x[i])
    return out


def unrolled_sum(x):
    """sum_i x_i of a small 1-D array, written out (`fold`)."""
    return fold(jnp.add, x) if x.shape[0] else jnp.zeros((), x.dtype)


def unrolled_rms_norm(x):
    """sqrt(sum_i x_i^2 / n) of a flat array, written out: `optimistix.rms_norm`'s value (a
    dot product there; under vmap a YNNPACK call, see `fold`), without gradients (diffrax
    stops them through the initial step it is used for; sqrt has none at 0)."""
    x = lax.stop_gradient(jnp.ravel(x))
    if x.shape[0] == 0:
        return jnp.zeros((), x.dtype)
    return jnp.sqrt(unrolled_sum(jnp.square(x)) / x.shape[0])


def _same_tableau(t: diffrax.ButcherTableau, u: diffrax.ButcherTableau) -> bool:
    def same(x, y):
        return np.shape(x) == np.shape(y) and bool(np.array_equal(np.asarray(x), np.asarray(y)))

    return (t.fsal == u.fsal and t.ssal == u.ssal and same(t.c, u.c) and same(t.b_sol, u.b_sol)
            and same(t.b_error, u.b_error) and len(t.a_lower) == len(u.a_lower)
            and all(same(x, y) for x, y in zip(t.a_lower, u.a_lower, strict=True)))


def can_unroll(solver) -> bool:
    """Whether `UnrolledERK` reproduces `solver`'s step: an explicit Runge-Kutta solver whose
    Butcher tableau (compared entry by entry) and dense output are those of one of
    `UNROLLED_SOLVERS`, and whose `step` is diffrax's own (a subclass that overrides it is
    stepped by diffrax, through its own `step`)."""
    cls = type(solver)
    if not isinstance(solver, diffrax.AbstractERK) or cls.step is not diffrax.AbstractRungeKutta.step:
        return False
    tab = getattr(cls, "tableau", None)
    if not isinstance(tab, diffrax.ButcherTableau):
        return False
    if cls in UNROLLED_SOLVERS:
        return True
    # A method is its tableau and its dense output: both as one of the known solvers'.
    return any(_same_tableau(tab, known.tableau) and cls.interpolation_cls is known.interpolation_cls
               for known in UNROLLED_SOLVERS)


def can_use_fast_controller(controller) -> bool:
    """Whether `FastIController` reproduces `controller`'s steps (a default-coefficient PID)."""
    if not can_batch_controller(controller):
        return False
    c = controller
    return bool(c.pcoeff == 0 and c.icoeff == 1 and c.dcoeff == 0 and c.dtmin is None and c.dtmax is None)


def can_batch_controller(controller) -> bool:
    """Whether `pid_controller` reproduces `controller`'s steps: a `PIDController` with the rms
    norm, Python-number coefficients and bounds, and no step_ts / jump_ts."""
    if type(controller) is not diffrax.PIDController or controller.norm is not optx.rms_norm:
        return False
    c = controller
    try:
        return bool(getattr(c, "step_ts", None) is None and getattr(c, "jump_ts", None) is None
                    and all(isinstance(v, (int, float)) for v in (c.pcoeff, c.icoeff, c.dcoeff, c.safety,
                                                                 c.factormin, c.factormax))
                    and all(v is None or isinstance(v, (int, float)) for v in (c.dtmin, c.dtmax)))
    except jax.errors.ConcretizationTypeError:  # traced coefficients: the general controller
        return False


def split_clip(controller, dtype) -> tuple[Any, Any, Any]:
    """diffrax's `PIDController(step_ts=..., jump_ts=...)` is a `ClipStepSizeController` around
    the `PIDController`: returns the controller inside and the times (sorted arrays of `dtype`,
    None where not given), for `_rules.clip_to_times`; any other controller (a
    `ClipStepSizeController` that stores rejected steps, too) as it is, with (None, None)."""
    c = controller
    if type(c) is not diffrax.ClipStepSizeController or c.store_rejected_steps is not None \
            or c.callback_on_reject is not None:
        return controller, None, None

    def times(ts):
        return None if ts is None else jnp.sort(jnp.asarray(ts, dtype).reshape(-1))

    return c.controller, times(c.step_ts), times(c.jump_ts)


def explicit_rk_step(tab, field, t0, y0, h, f0):
    """One explicit Runge-Kutta step of size h from (t0, y0) with the tableau `tab` (its `c`,
    `a` rows, `b_sol`, `ssal`), the first stage's field value f0 given:

        k_1 = h f0,   k_i = h F(t0 + c_i h, y0 + sum_{j<i} a_ij k_j),   y1 = y0 + sum_i b_i k_i

    (y1 the last stage's state for an SSAL tableau). `field(t, y, scale)` is F(t, y) times
    `scale` (h for every stage but the last), or F(t, y) for `scale` None (the last, whose value
    an FSAL tableau reuses as the next step's f0). Returns `(y1, ks, f_last)`.
    """
    ks, z, f_last = [f0 * h], y0, f0
    last = len(tab.c) - 1
    for i, (c_i, a_i) in enumerate(zip(tab.c, tab.a, strict=True)):
        z = y0 + weighted_sum(a_i, ks, y0)
        if i < last:
            ks.append(field(t0 + c_i * h, z, h))
        else:
            f_last = field(t0 + c_i * h, z, None)
            ks.append(f_last * h)
    y1 = z if tab.ssal else y0 + weighted_sum(tab.b_sol, ks, y0)
    return y1, ks, f_last


def rk_error_estimate(tab, ks, y0):
    """The embedded error estimate of a step, err = sum_i b^err_i k_i."""
    return weighted_sum(tab.b_err, ks, y0)


def scaled_error(y0, y1, y_err, rtol, atol):
    """The step's error relative to the tolerances, an RMS over the components (leading axis):

        e = sqrt( sum_i (err_i / (atol + rtol max(|y0_i|, |y1_i|)))^2 / n ),

    with y1 read as y0 where it has a NaN (diffrax's rule). No gradient is taken through it."""
    y0, y1, y_err = lax.stop_gradient((y0, y1, y_err))
    y1 = jnp.where(fold(jnp.logical_or, jnp.isnan(y1)), y0, y1)
    scale = atol + rtol * jnp.maximum(jnp.abs(y0), jnp.abs(y1))
    return jnp.sqrt(fold(jnp.add, jnp.square(y_err / scale)) / y0.shape[0])


class PIDState(NamedTuple):
    """The step-size history of diffrax's `PIDController`: 1/e of the last accepted step and of
    the one before, and whether the step is at `dtmin`."""

    inv_error: jax.Array
    prev_inv_error: jax.Array
    at_dtmin: jax.Array


def has_history(c) -> bool:
    """Whether the rule reads `PIDState` (P or D terms, or dtmin); the I controller does not."""
    return not (c.pcoeff == 0 and c.dcoeff == 0 and c.dtmin is None)


def pow_root(e, q):
    """e^(-1/q) as diffrax computes it, `(1 / e) ** (1 / q)`."""
    return (1 / e) ** (1 / q)


def pid_controller(e, state: PIDState, order, h, c, root=None):
    """diffrax's `PIDController` rule for the next step size from the scaled error e of a step of
    size h (`scaled_error`), with the controller `c`'s coefficients, q the error order:

        keep = e < 1 (or at dtmin),   h_next = h clip(safety (1/e)^b1 r1^b2 r2^b3, bounds),
        b1 = (i + p + d) / q,  b2 = -(p + 2 d) / q,  b3 = d / q,

    r1, r2 the 1/e of the last two accepted steps (`PIDState`), bounds [1, factormax] for a kept
    step and [factormin, safety] otherwise (p = d = 0: the I controller); then
    h_next <= dtmax and h_next >= dtmin. Elementwise: lanes broadcast. `root(e, q)` computes
    e^(-1/q): `inverse_root` (elementwise arithmetic, which XLA:CPU vectorises) in the batched
    engine (the default), `pow_root` (diffrax's own `pow`, so that the steps are diffrax's to the last bit) in
    the per-execution one; the two agree to a few ulps. Returns `(keep, h_next, state)`, the
    state `state` itself where the rule reads none (`has_history`).
    """
    i_sum = c.icoeff + c.pcoeff + c.dcoeff
    b2, b3 = -(c.pcoeff + 2 * c.dcoeff) / order, c.dcoeff / order
    history = 1.0
    if b2 != 0:
        history = history * state.inv_error**b2
    if b3 != 0:
        history = history * state.prev_inv_error**b3
    keep = e < 1
    if c.dtmin is not None:
        keep = keep | state.at_dtmin
    # the I term, e^(-1/q') with q' = q / (i + p + d)
    root = inverse_root if root is None else root
    term = root(e, order / i_sum) if i_sum != 0 else jnp.ones_like(e)
    lo = jnp.where(keep, 1.0, c.factormin)
    hi = jnp.where(keep, c.factormax, c.safety)
    factor = lax.stop_gradient(jnp.clip(c.safety * term * history, lo, hi))
    h_next = h * factor.astype(jnp.result_type(h))
    if c.dtmax is not None:
        h_next = jnp.minimum(h_next, c.dtmax)
    at_dtmin = state.at_dtmin
    if c.dtmin is not None:
        h_next = jnp.where(state.at_dtmin & (factor == 1), c.dtmin, h_next)
        at_dtmin = h_next <= c.dtmin
        h_next = jnp.maximum(h_next, c.dtmin)
    if not has_history(c):
        return keep, h_next, state
    inv = lax.stop_gradient(1 / e)
    inv = jnp.where((inv == 0) | jnp.isinf(inv), 1.0, inv)
    new = PIDState(jnp.where(keep, inv, state.inv_error),
                   jnp.where(keep, state.inv_error, state.prev_inv_error), at_dtmin)
    return keep, h_next, new


class UnrolledERK:
    """`solver`'s step with its stages unrolled; otherwise the diffrax solver (init, interpolation,
    error order are delegated to it)."""

    def __init__(self, solver: diffrax.AbstractERK):
        if not can_unroll(solver):
            raise TypeError(f"UnrolledERK: {type(solver).__name__} is not a plain explicit RK solver.")
        self.solver = solver
        tab = type(solver).tableau
        self.c = [float(x) for x in tab.c]
        self.a = [[float(x) for x in row] for row in tab.a_lower]
        self.b_sol = [float(x) for x in tab.b_sol]
        self.b_err = [float(x) for x in tab.b_error]
        self.fsal = bool(tab.fsal)
        self.ssal = bool(tab.ssal)

    def __getattr__(self, name):  # init, func, error_order, interpolation_cls, ...
        return getattr(self.solver, name)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        h = t1 - t0

        def field(t, y, scale):
            F = terms.vf(t, y, args)
            return F if scale is None else F * scale

        if self.fsal:
            _, f_prev = solver_state
            # After a jump (or at the start) the stored last stage is stale: evaluate f0.
            f0 = jnp.where(made_jump, terms.vf(t0, y0, args), f_prev)
        else:
            f0 = terms.vf(t0, y0, args)
        y1, ks, f_last = explicit_rk_step(self, field, t0, y0, h, f0)
        y_err = rk_error_estimate(self, ks, y0)
        dense_info = dict(y0=y0, y1=y1, k=jnp.stack(ks))
        new_state = (jnp.array(False), f_last) if self.fsal else None
        return y1, y_err, dense_info, new_state, diffrax.RESULTS.successful


def inverse_root(e, q):
    """e^(-1/q) for e >= 0, as `(1 / e) ** (1 / q)` within a few ulps (0 -> inf, inf -> 0).

    For an integer q <= 9 (every unrolled solver's error order) by Newton's method on
    y^(-q) = e, which needs no division, y <- y (q + 1 - e y^q) / q (quadratic: the error
    eps -> (q + 1) eps^2 / 2), from a first guess read off the exponent bits (the bits of a
    float are a piecewise-linear log2: error < 10 %, so five iterations reach rounding, six
    for q > 6). XLA:CPU computes `pow` one element at a time; this is
    elementwise arithmetic it vectorises. Other q: `pow`.
    """
    q_int = int(q) if isinstance(q, (int, float)) and float(q).is_integer() else 0
    if not 1 <= q_int <= 9 or e.dtype not in (jnp.float32, jnp.float64):
        return (1 / e) ** (1 / q)
    ints = jnp.int64 if e.dtype == jnp.float64 else jnp.int32
    one = lax.bitcast_convert_type(jnp.ones((), e.dtype), ints).astype(e.dtype)  # the bits of 1.0
    bits = lax.bitcast_convert_type(e, ints).astype(e.dtype)
    guess = jnp.clip(one - (bits - one) / q_int, 0, 2 * one - 1)  # within the finite positives
    y = lax.bitcast_convert_type(guess.astype(ints), e.dtype)
    for _ in range((5 if q_int <= 6 else 6) if e.dtype == jnp.float64 else 4):
        y_q = y
        for _ in range(q_int - 1):
            y_q = y_q * y
        y = y * ((q_int + 1) - e * y_q) * (1 / q_int)
    y = jnp.where(e == 0, jnp.inf, jnp.where(jnp.isinf(e), 0.0, y))
    return jnp.where(jnp.isnan(e), e, y)


class FastIController:
    """diffrax's `PIDController` step rule (`pid_controller`; for the default coefficients, an
    I controller) without its general machinery; `init` is diffrax's (Hairer's initial step),
    delegated."""

    def __init__(self, controller: diffrax.PIDController):
        if not can_batch_controller(controller):
            raise TypeError("FastIController: only a PIDController with the rms norm, Python-number "
                            "coefficients and no step_ts / jump_ts.")
        self.controller = controller

    def __getattr__(self, name):  # rtol, atol, ...
        return getattr(self.controller, name)

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        """diffrax's `init` (Hairer's initial step when dt0 is None), its rms norm written out
        (`unrolled_rms_norm`): the same value up to the summation's rounding order."""
        plain = eqx.tree_at(lambda c: c.norm, self.controller, unrolled_rms_norm)
        return plain.init(terms, t0, t1, y0, dt0, args, func, error_order)

    def adapt_step_size(self, t0, t1, y0, y1, args, y_err, error_order, controller_state) -> Any:
        c = self.controller
        e = scaled_error(y0, y1, y_err, c.rtol, c.atol)
        state = PIDState(*controller_state)
        keep, h_next, state = pid_controller(e, state, c._get_error_order(error_order), t1 - t0, c, pow_root)
        next_t0 = jnp.where(keep, t1, t0)
        next_t1 = next_t0 + h_next
        return keep, next_t0, next_t1, jnp.array(False), tuple(state), diffrax.RESULTS.successful

