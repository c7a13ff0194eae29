"""What a user would write without hybridjax, for the same problems, measured in the same run.

- `scipy_loop`: `scipy.integrate.solve_ivp` with terminal events (direction -1), numpy
  callbacks, a Python loop over epochs, one execution at a time.
- `diffrax_lockstep`: a jitted `vmap` of a bounded while loop over epochs (equinox's
  `while_loop(kind="bounded")`, the loop reverse mode can pass through), each epoch one `diffrax.diffeqsolve` ended by a `diffrax.Event` (all guards of the
  system as `cond_fn`s, those of other modes, and those not moving into their guard, held
  positive), `dt0=None`, the step-size controller given. This is the "plain diffrax lock-step
  loop" of the benchmarks' ratios. `loop="lax"`: the epochs in a `lax.while_loop` instead
  (forward only, no reverse mode), also measured and reported beside it.

- `diffrax_epoch_scan`: one execution as a `lax.scan` over `max_epochs` epochs, each one
  `diffrax.diffeqsolve` ended by a `diffrax.Event` (as `diffrax_lockstep`); a scan is what
  reverse mode differentiates without a bounded loop. The first-call benchmark compiles it
  beside `hj.simulate`.

- `ball_bare_loop`: problem A only, on a bare hand-written lanes-last loop
  (hand-written Tsit5 step, one crossing test, Newton on the dense output under a `lax.cond`,
  no record, saves or status checks): what such a loop reaches with nothing
  general, against which a general engine's cost is read.

`diffrax_lockstep` takes the problem's `HybridSystem` and uses its user functions, so the
engines solve the same model; `scipy_loop` uses the problem's numpy twins of them.
"""

import diffrax
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax import lax
from scipy.integrate import solve_ivp


def scipy_loop(problem, x0, mode0, *, method="RK45", rtol=1e-9, atol=1e-9):
    """One execution with solve_ivp and numpy callbacks; returns (num_events, final_state)."""
    system = problem.system
    t, x, mode, count = 0.0, np.asarray(x0, float), int(mode0), 0
    while count < problem.max_epochs:
        out = system.outgoing(mode)
        events = []
        for k in out:
            def ev(tt, xx, k=k):
                return problem.numpy_guards[k](tt, xx)
            ev.terminal, ev.direction = True, -1
            events.append(ev)
        sol = solve_ivp(problem.numpy_flows[mode], (t, problem.t1), x, method=method, rtol=rtol, atol=atol,
                        events=events)
        hit = [i for i, te in enumerate(sol.t_events) if len(te)]
        if sol.status != 1 or not hit:
            return count, sol.y[:, -1]
        i = min(hit, key=lambda i: sol.t_events[i][0])
        k = out[i]
        t = float(sol.t_events[i][0])
        x = np.asarray(problem.numpy_resets[k](t, sol.y_events[i][0]), float)
        mode = system.targets[k]
        count += 1
    return count, x


def diffrax_lockstep(system, *, solver, controller, t1, max_epochs=64, max_steps=4096, loop="bounded"):
    """jit(vmap(...)) of an epoch loop of diffeqsolve + Event: `loop="bounded"` (equinox's bounded
    while loop, reverse-mode differentiable) or `"lax"` (`lax.while_loop`, forward only). Returns
    a function `(x0 (N, n), mode0 (N,), args) -> (event_times (N, E), num_events, final_state,
    final_mode)`."""
    if loop not in ("bounded", "lax"):
        raise ValueError(f"loop={loop!r}: 'bounded' or 'lax'")
    targets = jnp.asarray(system.targets)
    term, event = _epoch_parts(system)

    def one(x0, mode0, args):
        def body(c):
            t, y, mode, i, times, done = c
            fired, k, te, ye, y_new = _epoch(system, term, event, solver, controller, t1, max_steps,
                                             diffrax.RecursiveCheckpointAdjoint(), t, y, mode, args)
            times = times.at[i].set(jnp.where(fired, te, jnp.inf))
            return (te, jnp.where(fired, y_new, ye), jnp.where(fired, targets[k], mode), i + fired,
                    times, ~fired)

        init = (jnp.zeros(()), x0, mode0, jnp.array(0), jnp.full((max_epochs,), jnp.inf), jnp.array(False))
        def cond(c):
            return ~c[5] & (c[3] < max_epochs)

        if loop == "bounded":
            t, y, mode, i, times, _ = eqxi.while_loop(cond, body, init, max_steps=max_epochs, kind="bounded")
        else:
            t, y, mode, i, times, _ = lax.while_loop(cond, body, init)
        return times, i, y, mode

    return jax.jit(jax.vmap(one, in_axes=(0, 0, None)))


def _epoch_parts(system):
    """The lock-step loops' vector field over modes and their Event (each transition's guard,
    held positive outside its source mode and where it is not moving into {g <= 0})."""
    sources = jnp.asarray(system.sources)

    def flow(t, y, a):
        mode, args = a
        return lax.switch(mode, [lambda t, y, m=m: m.flow(t, y, args) for m in system.modes], t, y)

    def cond_fn(k):
        tr = system.transitions[k]

        def fn(t, y, args, **kwargs):
            mode, args = args
            g, gdot = jax.jvp(lambda t, y: tr.guard(t, y, args), (t, y), (jnp.ones_like(t), flow(t, y, (mode, args))))
            return jnp.where((sources[k] == mode) & (gdot < 0), g, jnp.abs(g) + 1.0)

        return fn

    K = system.num_transitions
    event = diffrax.Event([cond_fn(k) for k in range(K)], root_finder=optx.Newton(rtol=1e-12, atol=1e-12))
    return diffrax.ODETerm(flow), event


def _epoch(system, term, event, solver, controller, t1, max_steps, adjoint, t, y, mode, args):
    """One epoch of the lock-step loops: `diffeqsolve` from (t, y) in `mode` until t1 or an event.
    Returns (an event fired, its transition k, the end time and state, the state after k's reset)."""
    sol = diffrax.diffeqsolve(term, solver, t, t1, None, y, (mode, args), stepsize_controller=controller,
                              event=event, max_steps=max_steps, saveat=diffrax.SaveAt(t1=True), throw=False,
                              adjoint=adjoint)
    mask = jnp.stack(sol.event_mask) if system.num_transitions > 1 else jnp.atleast_1d(sol.event_mask[0])
    fired = jnp.any(mask) & (sol.result == diffrax.RESULTS.event_occurred)
    k = jnp.argmax(mask)
    te, ye = sol.ts[-1], sol.ys[-1]
    y_new = lax.switch(k, [lambda t, y, tr=tr: tr.reset(t, y, args) for tr in system.transitions], te, ye)
    return fired, k, te, ye, y_new


def diffrax_epoch_scan(system, *, solver, controller, t1, max_epochs=64, max_steps=4096, adjoint=None):
    """One execution, `(x0, mode0, args) -> final_state`, as a `lax.scan` over `max_epochs`
    epochs of `diffeqsolve` + `Event` (epochs after the run has ended integrate nothing)."""
    targets = jnp.asarray(system.targets)
    term, event = _epoch_parts(system)
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint

    def one(x0, mode0, args):
        def epoch(c, _):
            t, y, mode, done = c
            fired, k, te, ye, y_new = _epoch(system, term, event, solver, controller, t1, max_steps, adjoint,
                                             t, y, mode, args)
            fired = fired & ~done
            y_out = jnp.where(done, y, jnp.where(fired, y_new, ye))
            return (jnp.where(done, t, te), y_out, jnp.where(fired, targets[k], mode), done | ~fired), None

        init = (jnp.zeros((), x0.dtype), x0, jnp.asarray(mode0), jnp.array(False))
        (_, y, _, _), _ = lax.scan(epoch, init, None, length=max_epochs)
        return y

    return one


def ball_bare_loop(*, rtol=1e-9, atol=1e-9, max_iters=4096):
    """The bouncing ball on a bare hand-written lanes-last loop, written for
    this one problem (it knows the flow, the single guard h = 0 and the reset): a reference for
    what a general engine could reach, not a proven bound.

    One `lax.while_loop`; every lane holds its own t, h, step size and its state as one vector
    per component (lanes last); each iteration every running lane takes one Tsit5 step
    (diffrax's tableau), with diffrax's I controller (safety 0.9, factors 0.2 / 10) and its
    first step (Hairer's rule, once at t0). A crossing (h > 0 at the step's start, <= 0 at its
    end: for a parabola that is every crossing) is located under a `lax.cond` taken only when
    some lane has one: a bracketed Newton iteration on the step's dense output (diffrax's
    interpolant in the engines' Chebyshev form) until the bracket or the Newton step is below
    1e-13 of the step (~7 iterations; Newton approaches a root from one side, so waiting for
    the bracket alone bisected ~45 times per call: 2x the whole run). The reset
    v -> -e v is applied there, and the next step is the controller's proposal capped at half
    the next flight's duration (e |v| / g). No record of events, no saves, no status checks.
    Returns `f(x0 (N, 2), g, e, t1) -> (num_events (N,), final_state (N, 2))`.
    """
    # The dense output's Chebyshev weights as the engines read them off diffrax's
    # interpolation (not retyped), and its trace-time weighted sum.
    from hybridjax._engines.dense_weights import chebyshev_weights
    from hybridjax._step.runge_kutta import weighted_sum

    solver = diffrax.Tsit5()
    tab = type(solver).tableau
    a_ = [[float(x) for x in row] for row in tab.a_lower]
    b_err = [float(x) for x in tab.b_error]
    cheb = chebyshev_weights(solver.interpolation_cls, len(a_) + 1, jnp.float64)

    def clenshaw(coeffs, x):
        b1 = jnp.zeros_like(coeffs[0])
        b2 = b1
        for c in coeffs[:0:-1]:
            b1, b2 = 2 * x * b1 - b2 + c, b1
        return x * b1 - b2 + coeffs[0]

    def dense(y0, y1, ks):
        """The step's dense output of one component at the fraction s (`ChebyshevDense`'s form)."""
        dy = y1 - y0
        coeffs = [r[1] * dy + weighted_sum(r[2:], ks, y0) for r in cheb]
        return lambda s: y0 + s * (dy + (1 - s) * clenshaw(coeffs, 2 * s - 1))

    def rms(v):  # over the two components, written out: a reduction over them would not fuse
        return jnp.sqrt(0.5 * (v[0] * v[0] + v[1] * v[1]))

    @jax.jit
    def run(x0, g, e, t1):
        N = x0.shape[0]

        def F(y):
            return jnp.stack([y[1], jnp.full_like(y[1], -g)])

        y = x0.T
        f0 = F(y)
        # Hairer's first step (as diffrax's PIDController.init), per lane.
        scale = atol + rtol * jnp.abs(y)
        d0 = rms(y / scale)
        d1 = rms(f0 / scale)
        small = (d0 < 1e-5) | (d1 < 1e-5)
        h0 = jnp.where(small, 1e-6, 0.01 * d0 / jnp.where(small, 1.0, d1))
        d2 = rms((F(y + h0 * f0) - f0) / scale) / h0
        md = jnp.maximum(d1, d2)
        h1 = jnp.where(md <= 1e-15, jnp.maximum(1e-6, 1e-3 * h0), (0.01 / md) ** (1 / 5))
        dt = jnp.minimum(100 * h0, h1)

        def body(c):
            t, y, dt, f0, done, count, it = c
            tn = jnp.minimum(t + dt, t1)
            hh = tn - t
            ks = [f0 * hh]
            z, fl = y, f0
            for ai in a_:  # the field is autonomous: the nodes c_i do not enter
                z = y + weighted_sum(ai, ks, y)
                fl = F(z)
                ks.append(fl * hh)
            y1, err = z, weighted_sum(b_err, ks, y)  # Tsit5: y1 is the last stage's point
            sc = atol + rtol * jnp.maximum(jnp.abs(y), jnp.abs(y1))
            en = rms(err / sc)
            keep = en < 1
            fac = jnp.clip(0.9 * en ** (-1 / 5), jnp.where(keep, 1.0, 0.2), jnp.where(keep, 10.0, 0.9))
            acc = ~done & keep
            cross = acc & (y1[0] <= 0) & (y[0] > 0)

            def locate(_):
                height = dense(y[0], y1[0], [k[0] for k in ks])

                def newton(c):
                    a, b, x, _, i = c
                    fx, dfx = jax.jvp(height, (x,), (jnp.ones_like(x),))
                    a, b = jnp.where(fx > 0, x, a), jnp.where(fx <= 0, x, b)
                    step = fx / jnp.where(dfx != 0, dfx, 1.0)
                    xn = jnp.where((x - step >= a) & (x - step <= b), x - step, 0.5 * (a + b))
                    return a, b, xn, jnp.abs(step), i + 1

                def unconverged(c):
                    a, b, _, step, i = c
                    # Newton closes the bracket from one side only: stop on a small step too.
                    return jnp.any(cross & (b - a > 1e-13) & (step > 1e-13)) & (i < 64)

                den = y[0] - y1[0]
                x = jnp.clip(jnp.where(cross, y[0] / jnp.where(cross, den, 1.0), 0.5), 0.0, 1.0)
                *_, x, _, _ = lax.while_loop(unconverged, newton, (jnp.zeros(N), jnp.ones(N), x, jnp.ones(N), 0))
                return jnp.where(cross, x, 1.0)

            th = lax.cond(jnp.any(cross), locate, lambda _: jnp.ones(N), None)
            v_ev = dense(y[1], y1[1], [k[1] for k in ks])(th)
            y_reset = jnp.stack([jnp.zeros_like(v_ev), -e * v_ev])
            t_new = jnp.where(cross, t + th * hh, jnp.where(acc, tn, t))
            y_new = jnp.where(cross, y_reset, jnp.where(acc, y1, y))
            f_new = jnp.where(cross, F(y_reset), jnp.where(acc, fl, f0))
            # After a bounce the next flight lasts 2 e |v| / g: the first step stays within it.
            dt_new = jnp.where(cross, jnp.minimum(hh * fac, e * jnp.abs(v_ev) / g), hh * fac)
            done = done | (acc & ~cross & (tn >= t1))
            return t_new, y_new, jnp.where(done, dt, dt_new), f_new, done, count + cross, it + 1

        init = (jnp.zeros(N), y, dt, f0, jnp.zeros(N, bool), jnp.zeros(N, jnp.int32), 0)
        out = lax.while_loop(lambda c: jnp.any(~c[4]) & (c[6] < max_iters), body, init)
        return out[5], out[1].T

    return run
