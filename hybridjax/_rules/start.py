"""The start of an epoch (execution rule 3): which transition fires at once, which guards are disarmed,
and the epoch's first step."""

import jax
import jax.numpy as jnp
from jax import lax

from .._definition.kernels import Kernels
from .._step.runge_kutta import fold
from .locate import resolve_simultaneous
from .records import EpochStart
from .tolerances import event_time_tol

sg = lax.stop_gradient


# ---------------------------------------------------------------------------- start of an epoch
def trending_negative(L1, L2, L3, scale1, eps) -> jax.Array:
    """First non-zero Lie derivative negative. L1 counts as zero below 64 eps * scale1."""
    l1_nonzero = jnp.abs(L1) > 64 * eps * scale1
    higher = jnp.where(L2 != 0, L2 < 0, L3 < 0)
    return jnp.where(l1_nonzero, L1 < 0, higher)


def strictly_inside(jets) -> jax.Array:
    """Per watched function, whether the state lies strictly inside its set, beyond the
    tolerance band: g < -band. A transition that fires at the start of an epoch for this
    reason was not reached by the flow: a reset (or the initial state) put the state inside
    its guard. Legitimate where resets chain (a plastic impact that lands inside the lift-off
    guard), and the mark of a modelling mistake elsewhere (a hopper whose apex lies below its
    touchdown height); `Solution.inside_guard` records it per event."""
    return jets.L0 < -jets.band


def unresolved_departure(jets, tol_t) -> jax.Array:
    """Per watched function, whether a guard that departs to first order (L1 > 0) comes back
    before an event could be told apart from the start: along its Taylor polynomial
    L0 + L1 s + L2 s^2 / 2 (L2 < 0) the apex lies at s* = L1 / |L2|, and the departure is
    unresolved when s* <= tol_t (the return, at 2 s*, within two event-time tolerances) or
    when the apex value L0 + L1^2 / (2 |L2|) is <= 0 (the guard never becomes positive). The
    tail of a Zeno execution reaches it: a ball whose bounces last less than the resolution of
    t would otherwise step through the floor with its guard never seen positive."""
    L1, L2 = jets.L1, jets.L2
    turns = (L1 > 0) & (L2 < 0)
    safe = jnp.where(turns, -L2, 1.0)
    apex_time = L1 / safe
    apex_value = jets.L0 + 0.5 * L1 * apex_time
    return turns & ((apex_time <= tol_t) | (apex_value <= 0))


def start_decision(jets, outgoing, eps, tol_t=0.0):
    """Which guards fire at the start of an epoch, and the guards' starting values.

    A guard fires when the state lies strictly inside it (`strictly_inside`), or within the
    band of it and trending negative (`trending_negative`) or departing unresolvably
    (`unresolved_departure`, with the event-time tolerance tol_t). Returns `(fire, g_start)`:
    `fire` (K,) bool; `g_start` (K,) the value each guard starts the epoch with, 0 for
    departing (disarmed) guards, +1 for guards not leaving the mode.
    """
    L0, band = jets.L0, jets.band
    in_band = jnp.abs(L0) <= band
    neg = trending_negative(jets.L1, jets.L2, jets.L3, jets.scale1, eps) | unresolved_departure(jets, tol_t)
    fire = outgoing & (strictly_inside(jets) | (in_band & neg))
    g_start = jnp.where(outgoing, jnp.where(L0 > band, L0, jnp.zeros_like(L0)), 1.0)
    return fire, g_start


def carries_step(dt0, explicit: bool) -> bool:
    """Whether epochs after the first start with the controller's last proposal (`first_step`):
    with an explicit solver and no `dt0` given."""
    return dt0 is None and explicit


def first_step(initial, proposed, carry: bool):
    """The first step of an epoch, before `departure_step_bound` caps it.

    The first epoch starts with `initial`, the controller's initial step (Hairer's rule, or
    `dt0`). With an explicit solver and no `dt0` (`carry`, from `carries_step`), a later
    epoch (`proposed` > 0: the step size the controller proposed after the step that ended
    the previous epoch) starts with that proposal, as DifferentialEquations.jl keeps its step
    size across a callback: Hairer's rule does not know the scale the solve has already
    found and at tight tolerances starts far below it, which costs several more steps per
    epoch. If the reset has changed the scale, the controller rejects and shrinks the step as
    it would anywhere:
    an explicit step across a transient faster than itself is unstable, its error estimate
    large. An implicit step across one is stable and can be accepted while its dense output
    (Hermite, where events are located) is far off: the stiff relay with Kvaerno3/5, a
    1e-6 s lag restarted at each switch, located every switch after the first wrongly.
    Implicit solvers therefore start every epoch with Hairer's rule, which sees the
    transient. A `dt0` given by the user starts every epoch.

    The epochs' first steps are then taken at the tolerance rather than far inside it: at a
    given tolerance the error can be larger (the thermostat at 1e-8: 1.8e-6 against 1.9e-7),
    at a given error the run is as fast or faster (`benchmarks/work_precision.py`).
    """
    return jnp.where(proposed > 0, proposed, initial) if carry else initial


def departure_step_bound(jets, outgoing, fire) -> jax.Array:
    """A first step short enough to see a departing guard positive before it returns.

    Along the Taylor polynomial g(s) = L0 + L1 s + L2 s^2 / 2 of a departing guard (L0 ~ 0,
    L1 > 0, L2 < 0) the flow comes back into the guard at s = 2 L1 / |L2|; half of that,
    so that an interior sample sees g > 0 (e.g. a ball bouncing with tiny velocity).
    """
    L0, L1, L2, band = jets.L0, jets.L1, jets.L2, jets.band
    departing = outgoing & (jnp.abs(L0) <= band) & ~fire & (L1 > 0) & (L2 < 0)
    safe_L2 = jnp.where(departing, L2, -1.0)
    tau = jnp.where(departing, L1 / (-safe_L2), jnp.inf)
    return fold(jnp.minimum, tau) if tau.shape[0] else jnp.asarray(jnp.inf, tau.dtype)


def epoch_start(
    kern: Kernels, mode, t, y, args, h_prev, initial, *, carry: bool, rtol, atol, event_tol, eps
) -> EpochStart:
    """The start test of an epoch at (t, y) in `mode`: which watched function fires at once, and
    otherwise the epoch's first step.

    The watched functions' Lie derivatives L0..L3 and band (`Kernels.guard_jets`, with the
    event-time tolerance of the previous step h_prev) decide which fire (`start_decision`);
    the first that fires is k (listing order: guards, then domain components; where guards are
    located through a shared function, the transition taken at (t, y), `Kernels.select`). The first step
    is `first_step(initial, h_prev, carry)`, `initial` the controller's initial step, capped by
    `departure_step_bound`. The values are taken without gradients; F, the vector field at
    (t, y), keeps those of (t, y, args) (the next step's first stage).
    """
    ts, ys, a_sg = sg(t), sg(y), sg(args)
    tol_t = event_time_tol(event_tol, ts, h_prev, eps)
    jets = kern.guard_jets(mode, ts, ys, a_sg, rtol, atol, tol_t)
    outgoing = kern.outgoing_mask(mode)
    fire, g_start = start_decision(jets, outgoing, eps, tol_t)
    F = kern.flow(mode, t, y, args)
    finite = jnp.all(jnp.isfinite(F)) & jnp.all(jnp.isfinite(jnp.where(outgoing, jets.L0, 0.0)))
    k, simultaneous = resolve_simultaneous(fire, kern.num_transitions)
    inside = strictly_inside(jets)[k] if kern.num_watch else jnp.array(False)
    k = kern.select(mode, k, ts, ys, a_sg)
    h = jnp.minimum(first_step(initial, h_prev, carry), departure_step_bound(jets, outgoing, fire))
    return EpochStart(
        fire=jnp.any(fire),
        k=k,
        g_start=g_start,
        F=F,
        finite=finite,
        h=sg(h),
        simultaneous=simultaneous,
        inside=inside,
    )
