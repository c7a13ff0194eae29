"""Location of an event: the root and minimum searches on the interpolant (an event locator), the
brackets, the simultaneity rule, the first event and the implicit-function event point.

The searches are the extension point: `AbstractEventLocator` declares them, `BracketedNewton`
(the default) implements them; `event_brackets` and `first_event` take the locator to use, and
both engines hand them the one of the call's `EventOptions`.
"""

import abc
import contextlib
import contextvars
import functools
from collections.abc import Callable

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
from jax import lax

from .._core.jaxprs import closure_converted, equation_count
from .._definition.kernels import Kernels
from .._step.runge_kutta import unrolled_sum
from .records import Brackets, Detection, EventChoice

sg = lax.stop_gradient


# ---------------------------------------------------------------------------- location
# A root search whose function has more equations than this (`equation_count`) is written as
# one loop that holds the function once (`_root_search_one_copy`); below, written out, with the
# function at each place it is evaluated (`_root_search_written_out`), which runs faster. The
# watched values along a step's dense output: 65 equations for the ball, 284 for the thermostat,
# about 900 for a block sliding with friction.
ONE_COPY_ABOVE = 400


# Whether the searches traced now run across a block of lanes (`across_lanes`), where each pass
# of a `lax.map` over their few fixed points runs the kernels over the whole block once per point.
_ACROSS_LANES = contextvars.ContextVar("across_lanes", default=False)


@contextlib.contextmanager
def across_lanes():
    """Within: the searches traced here evaluate f at their few fixed points (a bracket's
    two ends, the polish's three candidates, the first event's two times) in one pass rather
    than in a `lax.map` run once per point (`at_points`). Same values, another program: for one
    execution the map's one copy of f compiles sooner and runs as fast; across a block of lanes
    (the batched engine) each of the map's passes runs the kernels over the whole block."""
    token = _ACROSS_LANES.set(True)
    try:
        yield
    finally:
        _ACROSS_LANES.reset(token)


def at_points(f, points: list, written_out: bool = True) -> list:
    """`[f(p) for p in points]` (pytrees alike). Per execution: one copy of f under `lax.map`.
    Within `across_lanes`: a copy of f per point (`written_out`), or one copy under `jax.vmap`
    over the points."""
    if _ACROSS_LANES.get() and written_out:
        return [f(p) for p in points]
    xs = jnp.stack(points)
    out = jax.vmap(f)(xs) if _ACROSS_LANES.get() else lax.map(f, xs)
    return [jax.tree_util.tree_map(lambda o, j=j: o[j], out) for j in range(len(points))]


def locate_root(f, a, b, tol, max_iter: int = 64, one_copy: bool | None = None):
    """Right end of a bracket [a, b] of a root of f, f(a) > 0 >= f(b), narrower than `tol`.

    Newton's method with the derivative of f (forward-mode AD) from the root of the cubic
    Hermite interpolant of f's values and slopes at a and b (`hermite_root`), falling back to
    bisection when a Newton step is not at most half the step before last or leaves the
    bracket by more than `tol` (Numerical Recipes' rtsafe; a step that lands within
    `tol` outside it is clamped to its end, where the next probe closes it). Each iterate x_k
    is followed by a probe at x_k + delta_k if f(x_k) > 0, else at x_k - delta_k (towards the root), delta_k =
    2 |x_k - x_{k-1}| clipped to [max(tol/1000, 4 ulp), tol/2]: once Newton converges
    quadratically the root lies well within |x_k - x_{k-1}| of x_k, so x_k and the probe
    straddle it and the bracket closes at once (a fixed tiny delta would wait for Newton to
    land within rounding noise of the root, and bisect ~40 times instead). A final
    Newton step from the right end then puts it a few ulps past the root (g <= 0 kept).
    No gradients: the caller differentiates the event time by the implicit function theorem.

    `one_copy`: the search as one loop holding f once (`_root_search_one_copy`), or written
    out (False); None: one loop where f has more than `ONE_COPY_ABOVE` equations.
    """
    return _root_search(f, a, b, tol, max_iter, True, one_copy)[1]


def root_bracket(f, a, b, tol, max_iter: int = 64, one_copy: bool | None = None):
    """`locate_root`'s bracket search: `(a, b, iterations)`, the bracket narrower than `tol`
    (or after `max_iter` iterations) and the iterations it took, each an iterate and its probe."""
    return _root_search(f, a, b, tol, max_iter, False, one_copy)


def _root_search(f, a, b, tol, max_iter: int, polish: bool, one_copy: bool | None):
    a, b, tol = lax.stop_gradient((a, b, tol))
    if one_copy is None:
        one_copy = equation_count(f, b) > ONE_COPY_ABOVE
    search = _root_search_one_copy if one_copy else _root_search_written_out
    return search(f, a, b, tol, max_iter, polish)


def _slope(f):
    """x -> (f(x), f'(x)) by forward-mode AD."""
    return lambda x: jax.jvp(f, (x,), (jnp.ones_like(x),))


def _probe_delta(x, dx, tol):
    """The probe's distance from the iterate x: 2 |dx| (dx the last Newton step) clipped to
    [max(tol/1000, 4 ulp), tol/2]."""
    floor = jnp.maximum(1e-3 * tol, 4 * jnp.finfo(x.dtype).eps * jnp.abs(x))
    return jnp.clip(2 * jnp.abs(dx), floor, jnp.maximum(0.5 * tol, floor))


def _narrow(a, b, points):
    """The bracket [a, b] narrowed by the points `(x, f(x))`: f(x) > 0 moves a up to x, f(x) <= 0
    moves b down to x, a non-finite f(x) neither. Written out, not stacked: elementwise code
    that XLA fuses into a few kernels (a stack and a reduction over it do not fuse under vmap)."""
    for p, fp in points:
        finite = jnp.isfinite(fp)
        a = jnp.where(finite & (fp > 0), jnp.maximum(a, p), a)
        b = jnp.where(finite & (fp <= 0), jnp.minimum(b, p), b)
    return a, b


def _newton_or_bisect(x, fx, dfx, a, b, dx_old, tol):
    """The next iterate from x in the bracket [a, b], as in rtsafe: Newton's step if it stays in
    the bracket and is at most half the step before last, `dx_old` (converging), else the
    bracket's midpoint. A converging step that lands within `tol` outside the bracket has found
    a root within rounding of the bracket's end (a probe put that end there): clamped to the
    end, the next probe closes the bracket, where a bisection of the whole bracket would take
    ~40 halvings."""
    step = fx / jnp.where(dfx != 0, dfx, 1.0)
    xn = x - step
    converging = (dfx != 0) & jnp.isfinite(xn) & (2 * jnp.abs(step) <= jnp.abs(dx_old))
    near = (xn > a - tol) & (xn < b + tol)
    return jnp.where(converging & near, jnp.clip(xn, a, b), 0.5 * (a + b))


# The polish: from the Newton point x_p = b - f(b) / f'(b) (b within tol of the root, so x_p
# within rounding of it), the first of x_p + 4, 16, 64 ulp in (a, b] where f <= 0, else b. The
# few ulps of margin keep g <= 0 when the caller re-evaluates the state there (its arithmetic
# rounds differently by an ulp or so).
_POLISH_ULPS = (64.0, 16.0, 4.0)  # in the order written: the last good one wins


def _polish_points(b, fb, dfb):
    """The candidates x_p + 64, 16, 4 ulp of the polish (see `_POLISH_ULPS`)."""
    xp = b - fb / jnp.where(dfb != 0, dfb, 1.0)
    ulp = jnp.finfo(b.dtype).eps * jnp.maximum(jnp.abs(xp), jnp.finfo(b.dtype).tiny)
    return [xp + m * ulp for m in _POLISH_ULPS]


def _polished(a, b, cands, f_cands, slope_ok):
    """The polish's result: the nearest candidate to x_p in (a, b] with f <= 0, else b."""
    out = b
    for cand, fc in zip(cands, f_cands, strict=True):
        good = (fc <= 0) & (cand > a) & (cand <= b) & jnp.isfinite(cand) & slope_ok
        out = jnp.where(good, cand, out)
    return out


def _root_search_written_out(f, a, b, tol, max_iter: int, polish: bool):
    """The search with f at each place it is evaluated: the ends' values and slopes (`at_points`:
    one copy of f under `lax.map`, or under `jax.vmap` within `across_lanes`; for one execution
    a `jax.vmap` over them makes a small matrix product of an interpolant a batched one,
    slower), then a loop whose iterations evaluate the iterate (value and slope) and its probe
    (value), then the polish's Newton point and its candidates (`at_points`)."""
    # The ends' values and slopes under one `vmap` across lanes: written out, the two copies of
    # the slope's forward-mode program make XLA's legacy CPU emitters
    # (`--xla_cpu_use_fusion_emitters=false`) take over 6 GB compiling the thermostat.
    (fa, da), (fb, db) = at_points(_slope(f), [a, b], written_out=False)
    x0 = hermite_root(a, b, fa, fb, da, db)

    def cond(c):
        a, b, *_, i = c
        return (b - a > tol) & (i < max_iter)

    def body(c):
        a, b, x, dx, dx_old, i = c
        fx, dfx = _slope(f)(x)
        # One probe, on the side of x where the root lies (a probe on the other side moves the
        # bracket only if f changes sign twice within delta).
        delta = _probe_delta(x, dx, tol)
        probe = jnp.clip(jnp.where(fx > 0, x + delta, x - delta), a, b)
        a_new, b_new = _narrow(a, b, ((x, fx), (probe, f(probe))))
        xn = _newton_or_bisect(x, fx, dfx, a_new, b_new, dx_old, tol)
        return a_new, b_new, xn, jnp.abs(xn - x), dx, i + 1

    a, b, *_, i = lax.while_loop(cond, body, (a, b, x0, b - a, 2 * (b - a), jnp.array(0)))
    if not polish:
        return a, b, i
    fb, dfb = _slope(f)(b)
    cands = _polish_points(b, fb, dfb)
    return a, _polished(a, b, cands, at_points(f, cands), dfb != 0), i


# The phases of `_root_search_one_copy`'s loop, in order: what its next iteration evaluates.
_ENDS, _ITERATE, _NEWTON_AT_B, _CANDIDATES, _DONE = range(5)


def _phase(k: int) -> jax.Array:
    return jnp.asarray(k, jnp.int32)


def _root_search_one_copy(f, a, b, tol, max_iter: int, polish: bool):
    """The search as one loop whose iterations each evaluate f and f' at three points (one
    `jax.vmap` of the JVP: f appears once in the program), moving through the phases:

    - `_ENDS`: a and b (the third point repeats b), for the Hermite start (`hermite_root`);
    - `_ITERATE` (while b - a > tol, at most `max_iter` times): the iterate x and x +- delta, of
      which the probe on the side of the root (by the sign of f(x)) narrows the bracket, as in
      the written-out search (the other point is not used); then the next iterate;
    - `_NEWTON_AT_B` (`polish`): b, for the polish's Newton point;
    - `_CANDIDATES`: the polish's candidates.

    Each iteration evaluates f at more points than the written-out search does there, and
    every phase is an iteration: it runs slower, and compiles once where that one compiles f
    five times."""
    after_iterating = _NEWTON_AT_B if polish else _DONE

    def points(c):
        phase, a, b, x = c["phase"], c["a"], c["b"], c["x"]
        delta = _probe_delta(x, c["dx"], tol)
        by_phase = [(a, b, b), (x, jnp.clip(x + delta, a, b), jnp.clip(x - delta, a, b)), (b, b, b),
                    tuple(c["cands"][j] for j in range(3))]
        return [jnp.select([phase == k for k in range(4)], [pts[j] for pts in by_phase], b) for j in range(3)]

    def body(c):
        phase, a, b = c["phase"], c["a"], c["b"]
        pts = points(c)
        vals, slopes = jax.vmap(_slope(f))(jnp.stack(pts))
        at_ends, iterating, at_b = phase == _ENDS, phase == _ITERATE, phase == _NEWTON_AT_B
        start = hermite_root(a, b, vals[0], vals[1], slopes[0], slopes[1])
        x, fx, dfx = pts[0], vals[0], slopes[0]
        probe, f_probe = jnp.where(fx > 0, pts[1], pts[2]), jnp.where(fx > 0, vals[1], vals[2])
        a_it, b_it = _narrow(a, b, ((x, fx), (probe, f_probe)))
        xn = _newton_or_bisect(x, fx, dfx, a_it, b_it, c["dx_old"], tol)
        i = c["i"] + iterating.astype(c["i"].dtype)
        result = _polished(a, b, pts, [vals[j] for j in range(3)], c["slope_ok"])
        a_new = jnp.where(iterating, a_it, a)
        b_new = jnp.where(iterating, b_it, jnp.where(phase == _CANDIDATES, result, b))
        more = (b_new - a_new > tol) & (i < max_iter)
        nxt = jnp.where(iterating | at_ends, jnp.where(more, _phase(_ITERATE), _phase(after_iterating)),
                        phase + 1)
        return dict(
            phase=nxt, a=a_new, b=b_new, i=i,
            x=jnp.where(at_ends, start, jnp.where(iterating, xn, c["x"])),
            dx=jnp.where(at_ends, b - a, jnp.where(iterating, jnp.abs(xn - x), c["dx"])),
            dx_old=jnp.where(at_ends, 2 * (b - a), jnp.where(iterating, c["dx"], c["dx_old"])),
            # at b (pts[0] = b): the polish's candidates from b's value and slope
            cands=jnp.where(at_b, jnp.stack(_polish_points(b, fx, dfx)), c["cands"]),
            slope_ok=jnp.where(at_b, dfx != 0, c["slope_ok"]),
        )

    zero = jnp.zeros_like(b)
    init = dict(phase=_phase(_ENDS), a=a, b=b, x=zero, dx=zero, dx_old=zero, i=jnp.array(0),
                cands=jnp.stack([zero] * 3), slope_ok=jnp.array(False))
    c = lax.while_loop(lambda c: c["phase"] != _DONE, body, init)
    return c["a"], c["b"], c["i"]


def hermite_root(a, b, fa, fb, da, db, newton_steps: int = 4):
    r"""A starting point for the root search on [a, b], f(a) > 0 >= f(b): the root of the cubic
    Hermite interpolant of f from its values and slopes at the ends,

        p(s) = (2s^3 - 3s^2 + 1) f_a + (s^3 - 2s^2 + s) L f'_a + (3s^2 - 2s^3) f_b + (s^3 - s^2) L f'_b,

    L = b - a, x = a + L s (p evaluated in powers of s), found by `newton_steps` Newton steps on
    p from the regula-falsi point s_0 = f_a / (f_a - f_b), kept inside the bracket [s_lo, s_hi]
    of p's sign change (p(0) = f_a > 0 >= f_b = p(1)), bisecting it where a step would leave it.
    Its error is O(L^4 f^(4)) where the regula-falsi point's is O(L^2 f''): the search's Newton
    iteration starts two orders closer. Where the steps end farther from zero than s_0
    (|p(s)| > |p(s_0)|, or a non-finite value), s_0 is kept. No evaluation of f: arithmetic on the
    four numbers."""
    L = b - a
    denom = fa - fb
    s0 = jnp.clip(jnp.where(denom > 0, fa / jnp.where(denom > 0, denom, 1.0), 0.5), 0.0, 1.0)
    ta, tb = L * da, L * db
    # p in powers of s, f_a + t_a s + c_2 s^2 + c_3 s^3, by Horner's rule: a third of the
    # arithmetic of the basis form above, in a fusion a batch of searches runs on every lane.
    c2 = 3 * (fb - fa) - 2 * ta - tb
    c3 = 2 * (fa - fb) + ta + tb

    def p_dp(s):
        return fa + s * (ta + s * (c2 + s * c3)), ta + s * (2 * c2 + s * (3 * c3))

    p0 = p_dp(s0)[0]
    s, lo, hi = s0, jnp.zeros_like(s0), jnp.ones_like(s0)
    for _ in range(newton_steps):
        p, dp = p_dp(s)
        lo, hi = jnp.where(p > 0, s, lo), jnp.where(p <= 0, s, hi)
        sn = s - p / jnp.where(dp != 0, dp, 1.0)
        s = jnp.where((sn >= lo) & (sn <= hi), sn, 0.5 * (lo + hi))
    p1 = p_dp(s)[0]
    s = jnp.where(jnp.isfinite(p1) & (jnp.abs(p1) <= jnp.abs(p0)), s, s0)
    return jnp.clip(a + L * s, a, b)


def locate_minimum(f, a, b, x0, tol, max_iter: int = 32):
    """The minimum of f on [a, b] (f' < 0 at a, > 0 at b), or the first point found with f < 0.

    Newton's method on f' (f' and f'' by nested forward-mode AD), kept inside a shrinking
    bracket [a, b] with f'(a) < 0 < f'(b), bisecting when a Newton step would leave it; stops
    as soon as some f(x) < 0 (a crossing is proven), when the step or bracket is below
    `tol`, or after `max_iter` iterations. Returns `(x, f(x))` at the lowest point seen.
    """
    a, b, x0, tol = lax.stop_gradient((a, b, x0, tol))
    one = jnp.ones_like(x0)

    def value_and_slope(x):
        return jax.jvp(f, (x,), (one,))

    def evaluate(x):
        """f, f' and f'' at x from one nested JVP. Read by every output of the iteration: computed
        once behind a barrier (else XLA copies the evaluation into each output's fusion)."""
        (fx, d1), (_, d2) = jax.jvp(value_and_slope, (x,), (one,))
        return lax.optimization_barrier((fx, d1, d2))

    def cond(c):
        a, b, _, step, f_best, _, i = c
        return (f_best >= 0) & (b - a > tol) & (jnp.abs(step) > 0.5 * tol) & (i < max_iter)

    def body(c):
        # The iterate is evaluated here, at the start of the iteration, not carried from the
        # previous one: f's second-order evaluation appears once in the program.
        a, b, x, _, f_best, x_best, i = c
        fx, d1, d2 = evaluate(x)
        better = fx < f_best
        f_best, x_best = jnp.where(better, fx, f_best), jnp.where(better, x, x_best)
        a = jnp.where(d1 < 0, x, a)
        b = jnp.where(d1 > 0, x, b)
        xn = x - d1 / jnp.where(d2 > 0, d2, 1.0)
        ok = (d2 > 0) & jnp.isfinite(xn) & (xn > a) & (xn < b)
        xn = jnp.where(ok, xn, 0.5 * (a + b))
        step = jnp.where(d1 == 0, 0.0, xn - x)
        return a, b, xn, step, f_best, x_best, i + 1

    init = (a, b, jnp.clip(x0, a, b), jnp.asarray(jnp.inf, x0.dtype), jnp.asarray(jnp.inf, x0.dtype), x0,
            jnp.array(0))
    _, _, _, _, f_best, x_best, _ = lax.while_loop(cond, body, init)
    return x_best, f_best


class AbstractEventLocator(eqx.Module):
    r"""How an event is located on a step's dense output: the two searches the engines call.

    Subclass it and implement both methods to add a strategy (Illinois, Brent, ...); pass an
    instance as `hj.EventOptions(locator=...)`. Each method sees one watched function `f` of the
    time on the step's interpolant (a guard, or a domain component), traced inside the loop: use
    JAX control flow (`lax.while_loop`), and return arrays of `a`'s dtype. The event time's
    derivative is taken by the implicit function theorem after the search, so a locator needs no
    gradient of its own (its inputs arrive with `lax.stop_gradient`).
    """

    @abc.abstractmethod
    def root(self, f: Callable, a, b, tol):
        """A point x in (a, b] with f(x) <= 0 and x - r <= tol, r the first root of f in the
        bracket [a, b] with f(a) > 0 >= f(b): the right end of a bracket narrower than `tol`,
        so that the pre-event state lies in the guard set."""

    @abc.abstractmethod
    def minimum(self, f: Callable, a, b, x0, tol):
        """`(x, f(x))` at the lowest point found of f on [a, b] (f' < 0 at a, > 0 at b), starting
        from `x0`; it may stop at the first x with f(x) < 0 (a crossing proven), or when the
        bracket is narrower than `tol`. A dip below zero that this misses is not an event.
        The engines call it for every watched function at once: one without a dip candidate
        gets the empty bracket `a == b`, and its result is not used."""


class BracketedNewton(AbstractEventLocator):
    r"""The default locator: Newton's method kept inside a shrinking bracket.

    `root`: Newton with the derivative of f by forward-mode AD, from the root of the cubic
    Hermite interpolant of the bracket's ends (`hermite_root`), bisecting where a Newton step
    leaves the bracket or does not halve the step before last (Numerical Recipes' `rtsafe`;
    W. H. Press et al., *Numerical Recipes*, 3rd ed., Sec. 9.4), each iterate followed by a
    probe towards the root so that the bracket closes once Newton converges, then one Newton
    step from the right end put a few ulps past the root
    (`locate_root`; for an f of more than `ONE_COPY_ABOVE` equations one loop that holds f
    once, else written out). `minimum`: Newton on f' (f'' by nested forward-mode AD) inside the
    bracket of f' changing sign, stopping at the first f < 0 (`locate_minimum`; f'' appears once
    in its loop). `max_iter` and `max_iter_minimum` bound the iterations of each.
    """

    max_iter: int = 64
    max_iter_minimum: int = 32

    def __check_init__(self):
        for name in ("max_iter", "max_iter_minimum"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"BracketedNewton: {name} must be an int >= 1, got {v!r}.")

    def root(self, f, a, b, tol):
        return locate_root(f, a, b, tol, self.max_iter)

    def minimum(self, f, a, b, x0, tol):
        return locate_minimum(f, a, b, x0, tol, self.max_iter_minimum)


DEFAULT_LOCATOR = BracketedNewton()


def event_brackets(values_at: Callable, det: Detection, s_ext, tol,
                   locator: AbstractEventLocator = DEFAULT_LOCATOR) -> Brackets:
    """Per watched function, a bracket of its first event in the step: of a dip where the
    minimum search on a dip candidate (`locator.minimum`, run only when some execution has a
    candidate) finds g < 0 (from the interval's start to that point), else of the first
    crossing (samples j - 1 to j).

    `values_at(x)`: the watched values on the step's dense output at time x; `det`: the step's
    `Detection` (`suspect` already `dip_filter`ed); `s_ext` the sample times.
    """
    has, j, suspect, i_d, x0_d = det
    s = s_ext[1:]

    def refine(_):
        def lowest(k, a_k, b_k, x_k):
            return locator.minimum(lambda x: values_at(x)[k], a_k, b_k, x_k, tol)

        # A function without a candidate gets the empty bracket [a, a]: its search stops at
        # once, where on its sample interval it would run to `max_iter` (f' need not change
        # sign there) and hold every other search's loop open that long (under `jax.vmap`, a
        # while loop runs until its last element is done).
        a_d = s_ext[i_d]
        b_d = jnp.where(suspect, s_ext[i_d + 1], a_d)
        if has.shape[0] == 1:
            # One watched function: its search alone. A vmap over one function would batch the
            # search's loop ([1]-shaped values), a larger program for the same work.
            return tuple(v[None] for v in lowest(0, a_d[0], b_d[0], x0_d[0]))
        return jax.vmap(lowest)(jnp.arange(has.shape[0]), a_d, b_d, x0_d)

    x_min, g_min = lax.cond(
        eqxi.unvmap_any(jnp.any(suspect)), refine, lambda _: (x0_d, jnp.ones_like(x0_d)), None
    )
    dip = suspect & (g_min < 0)
    a = jnp.where(dip, s_ext[i_d], jnp.where(has, s_ext[j], s[j]))
    b = jnp.where(dip, x_min, s[j])
    return Brackets(has | dip, a, b)


def simultaneous_set(has, tk, t_min, tol, g_at, g_from):
    """Which watched functions are reached at the same instant as the first event, at t_min.

    Those with an event located within the event-time tolerance of t_min, tk <= t_min + tol,
    and those that are <= 0 at t_min but were > 0 at the start of the earliest bracket (their
    own bracket may be narrower than the samples): g(t_min) <= 0 < g(a_first). Which of them
    fires: `resolve_simultaneous`.
    """
    any_event = jnp.any(has)
    return has & (tk <= t_min + tol) | ((g_at <= 0) & (g_from > 0) & any_event)


def resolve_simultaneous(reached, num_counted: int | None = None):
    """The simultaneity rule: of the watched functions reached at one instant (`reached`, in
    listing order: guards in the order of the system's transitions, then domain components),
    the first fires; the event is *simultaneous* when more than one of the first `num_counted`
    (all: None) was reached. Used at the start of an epoch (`epoch_start`, counting the
    guards) and within a step (`first_event`). Returns `(index, simultaneous)`; index 0 when
    none was reached."""
    if reached.shape[0] == 0:
        return jnp.array(0, jnp.int32), jnp.array(False)
    counted = reached if num_counted is None else reached[:num_counted]
    return jnp.argmax(reached).astype(jnp.int32), jnp.sum(counted) > 1


def first_event(values_at: Callable, br: Brackets, tol, t_end,
                locator: AbstractEventLocator = DEFAULT_LOCATOR) -> EventChoice:
    """The step's first event: the bracketed roots located on the dense output (`locator.root`),
    the earliest time t_min, and of the watched functions reached then (`simultaneous_set`) the
    first in listing order. Located only when some execution has an event in the step (under
    `jax.vmap`, `eqxi.unvmap_any`); none: `t_end`, index 0.

    The roots are located one bracket at a time in the order of the brackets' starts $a_k$,
    while $a_k \le t_{min} + $ `tol` ($t_{min}$ the earliest root so far): a root lies in its
    bracket, so a function whose bracket starts later is neither first nor reached at
    $t_{min}$ (`simultaneous_set`). One search runs where one function crosses in the step, not
    one per watched function (a contact scene watches a hundred).
    """
    has, a, b = br
    any_event = jnp.any(has)
    n = has.shape[0]

    def root(k, a_k, b_k):
        return locator.root(lambda x: values_at(x)[k], a_k, b_k, tol)

    def roots_in_order():
        order = jnp.argsort(jnp.where(has, a, jnp.inf))

        def more(carry):
            i, t_min, _ = carry
            k = order[jnp.minimum(i, n - 1)]
            return (i < n) & has[k] & (a[k] <= t_min + tol)

        def next_root(carry):
            i, t_min, tk = carry
            k = order[i]
            t_k = root(k, a[k], b[k])
            return i + 1, jnp.minimum(t_min, t_k), jnp.where(jnp.arange(n) == k, t_k, tk)

        inf = jnp.full((), jnp.inf, a.dtype)
        return lax.while_loop(more, next_root, (jnp.array(0), inf, jnp.full((n,), inf)))[2]

    def locate(_):
        if n == 1:
            # One watched function: its search, with no loop or batch of one around it. It is
            # the only one reached at its root (`simultaneous_set` gives `has` itself), so the
            # simultaneity rule needs no values there.
            return EventChoice(jnp.where(any_event, root(0, a[0], b[0]), t_end),
                               jnp.array(0, jnp.int32), jnp.array(False))
        tk = roots_in_order()
        first = jnp.argmin(tk)
        t_min = tk[first]
        t_at = jnp.where(any_event, t_min, b[first])
        g_at, g_from = at_points(values_at, [t_at, a[first]])
        cand = simultaneous_set(has, tk, t_min, tol, g_at, g_from)
        i, simultaneous = resolve_simultaneous(cand)
        tk = jnp.where(cand & ~has, t_min, tk)
        return EventChoice(jnp.where(any_event, tk[i], t_end), i, simultaneous)

    def none(_):
        return EventChoice(t_end, jnp.array(0, jnp.int32), jnp.array(False))

    return lax.cond(eqxi.unvmap_any(any_event), locate, none, None)


def event_point(kern: Kernels, eps, mode, k, t_star, interp, args, tol):
    r"""The event time and pre-event state, differentiable to every order by the implicit
    function theorem.

    The event lies at the elapsed time u* = t* - t_s after the start t_s of its step. Near it
    the flow is written as its Taylor polynomial in the time w past u*, about the dense
    output's state x* at the fixed elapsed time u*:

        X(w; p) = x* + F w + [D_t F + D_x F F] w^2 / 2,   F = F(t_s + u*, x*),

    p = (t_s, x*, args) (x* carries the dependence on the epoch's start state and parameters
    through the dense output's coefficients). The event is the root w(p) of
    G(w; p) = g(t_s + u* + w, X(w; p)): w = w0 in value (0, or `onto_the_guard`'s step of a
    few ulps where x* rounds outside the guard, at most the event-time tolerance `tol` and the
    step's end), with the derivative

        dw = -(D_p G dp) / D_w G,     D_w G = D_t g + D_x g F   (the guard's rate along the flow),

    and the returned time and state are t* + (t_s - [t_s]) + w and X(w; p) ([.]: stop-gradient).
    `_located` gives w(p) and X(w(p); p) a JVP rule that calls `_located` itself, so its own
    derivatives follow the same rule: every derivative of the event time is the implicit
    function theorem's, and those up to the second are exact for the flow through x*(p) (a
    third derivative would need the third time derivative of the flow, and the derivative of
    the second, held here so that first derivatives never differentiate the flow twice: a
    contact scene's flow is a KKT solve). X uses the true vector
    field and its time derivative, not the dense output's slope and curvature, which are one
    and two orders less accurate than the tolerance. Holding u* fixed, rather than t*, makes a
    shift of the epoch's start time reach the event time directly: for an autonomous flow and
    guard the event time moves one-for-one with it, exactly, whatever the solver's local error
    (through t* it would arrive as D_x g xdot / D_x g F, with xdot the dense output's slope:
    1 + O(tol) at every epoch, an error of every later event's derivative that grows with the
    square of the event count).

    Also returns whether the crossing is grazing: |D_w G| <= eps^(1/3) (|D_t g| + |D_x g| |F|)
    (6e-6 in float64), the flow nearly tangent to the guard, where the derivative is
    ill-conditioned.
    """
    t_s = interp.t0
    u_star = sg(t_star - t_s)
    # The dense output at the fixed elapsed time u* for the derivative ((t_at - t_s) / h has
    # none), and at t* itself for the value: t_s + (t* - t_s) can round to a neighbour of t*.
    x_at = interp.evaluate(t_s + u_star)
    x_star = sg(interp.evaluate(t_star)) + (x_at - sg(x_at))
    diff_args, rest = eqx.partition(args, eqx.is_inexact_array)

    def local(w, p):
        """(G, X, D_w G, D_w X) at (w; p), p = (t_s, x*, the args' inexact arrays)."""
        ts, x0, da = p
        a = eqx.combine(da, rest)
        tt = ts + u_star

        def flow(t_, x_):
            return kern.flow(mode, t_, x_, a)

        def guard(t_, x_):
            return kern.guards(mode, t_, x_, a)[k]

        F = flow(tt, x0)
        F_dot = sg(jax.jvp(flow, (tt, x0), (jnp.ones_like(tt), F))[1])
        X = x0 + w * F + (0.5 * w * w) * F_dot
        X_w = F + w * F_dot
        G, G_w = jax.jvp(guard, (tt + w, X), (jnp.ones_like(tt), X_w))
        return G, X, G_w, X_w

    # The guard, its rate along the true vector field and the grazing test, on values alone.
    t_v, x_v, a_v = sg((t_star, x_star, args))
    F_v = kern.flow(mode, t_v, x_v, a_v)
    g_v, (gt, gx) = jax.value_and_grad(lambda tt, xx: kern.guards(mode, tt, xx, a_v)[k],
                                       argnums=(0, 1))(t_v, x_v)
    gdot = gt + unrolled_sum(gx * F_v)  # dg/dt along the true vector field (see `fold`)
    size = jnp.abs(gt) + jnp.sqrt(unrolled_sum(gx * gx)) * jnp.sqrt(unrolled_sum(F_v**2))
    grazing = jnp.abs(gdot) <= jnp.cbrt(eps) * size

    # Within the step: where the held step has no event (t* its end, g > 0) the shift is 0.
    # Within the event-time tolerance: near tangency (gdot -> 0-) -g / gdot is a rounding error
    # divided by a vanishing rate, and the time may move no further than the search's accuracy.
    w0 = jnp.minimum(onto_the_guard(g_v, gdot), jnp.minimum(sg(interp.t1) - t_v, sg(tol)))
    p = (t_s, x_star, diff_args)
    # The closure's arrays (the loop's tracers among them: the engine's tables are built inside
    # the traced call) become inputs of the custom derivative, whose JVP rule may be traced
    # after the loop's trace has ended.
    local_c, consts, _ = closure_converted(local, w0, p)
    w, y_ev = _located(local_c, w0, p, consts)
    # X(w0; p) to first order in w0 (`onto_the_guard`); x* itself where w0 = 0 (F may be inf).
    y_ev = y_ev + jnp.where(w0 != 0, w0 * F_v, jnp.zeros_like(F_v))
    t_ev = t_star + (t_s - sg(t_s)) + w
    return t_ev, y_ev, grazing


def onto_the_guard(g, rate):
    r"""The elapsed time $w$ past a located event at which its state lies in the guard,
    $g \le 0$: 0 where the state at the located time does (always, but for rounding),
    else one Newton step along the flow, $w = -g / \dot g$ ($\dot g < 0$ the guard's rate
    along the vector field), the state moving by $w F$.

    The root search keeps $g \le 0$ on its own evaluations of the dense output; the state
    reported is evaluated again (it carries the derivatives), and that evaluation can round
    $g$ above zero by ulps of the dense output's terms, which scale with the step's change
    $|y_1 - y_0|$, not with the state. After the step, $g$ is rounded on $x^* + w F$, at the
    scale of the state near the guard: the accuracy an execution promises at a pre-event
    state. $w$ is a few ulps of $t$ where the guard is crossed transversally; `event_point`
    keeps it within the step."""
    return sg(jnp.where((g > 0) & (rate < 0), -g / jnp.where(rate < 0, rate, -1.0), 0.0))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _located(local, w0, p, consts):
    """The root w(p) of G(w; p) and the state X(w(p); p) (`event_point`): in value (w0, x*)
    (the caller adds w0 F to the state); derivatives by `_located_jvp`.

    Each output is selected against a sum over every input (never taken: XLA removes it), so
    that under `jax.vmap` the outputs are batched wherever their tangents are: JAX's batching
    of a custom JVP staged in a loop fails where a primal output is unbatched and its tangent
    batched."""
    leaves = jax.tree_util.tree_leaves((w0, p, consts))
    every = sum(jnp.sum(leaf).astype(w0.dtype) for leaf in leaves if jnp.issubdtype(leaf.dtype, jnp.number))
    never = jnp.zeros((), bool)
    return jnp.where(never, every, w0), jnp.where(never, every.astype(p[1].dtype), p[1])


@_located.defjvp
def _located_jvp(local, primals, tangents):
    """dw = -(D_p G dp) / D_w G and dX = D_p X dp + D_w X dw, both evaluated at (w(p), p) with
    w(p) from `_located` itself, so that differentiating this rule applies it again."""
    w0, p, consts = primals
    _, dp, dconsts = tangents
    w, x = _located(local, w0, p, consts)
    # One JVP in p: the partial derivatives in w are outputs of `local` (the tangents of those
    # outputs are not used, and XLA drops them).
    (_, _, G_w, X_w), (G_p, X_p, _, _) = jax.jvp(lambda p_, c_: local(c_, w, p_), (p, consts), (dp, dconsts))
    dw = (-G_p / jnp.where(G_w != 0, G_w, 1.0)).astype(w.dtype)  # tangency: 1, not 0 (`grazing`)
    return (w, x), (dw, (X_p + X_w * dw).astype(x.dtype))
