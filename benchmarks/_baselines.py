"""What a user would write without hybridjax, for the same problems, measured in the same run.

- `scipy_loop`: `scipy.integrate.solve_ivp` with terminal events (direction -1), numpy
  callbacks, a Python loop over epochs, one execution at a time.
- `diffrax_lockstep`: a jitted `vmap` of a bounded while loop over epochs, each epoch one
  `diffrax.diffeqsolve` ended by a `diffrax.Event` (all guards of the system as `cond_fn`s, those
  of other modes, and those not moving into their guard, held positive), `dt0=None`, the
  step-size controller given. This is the "plain
  diffrax lock-step loop" of the benchmarks' ratios.

`diffrax_lockstep` takes the problem's `HybridSystem` and uses its user functions, so the
engines solve the same model; `scipy_loop` uses the problem's numpy twins of them.
"""

import diffrax
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


def diffrax_lockstep(system, *, solver, controller, t1, max_epochs=64, max_steps=4096):
    """jit(vmap(...)) of a bounded epoch loop of diffeqsolve + Event. Returns a function
    `(x0 (N, n), mode0 (N,), args) -> (event_times (N, E), num_events, final_state, final_mode)`."""
    K, n = system.num_transitions, system.max_dim
    sources = jnp.asarray(system.sources)
    targets = jnp.asarray(system.targets)

    def flow(t, y, a):
        mode, args = a
        return lax.switch(mode, [lambda t, y, m=m: m.flow(t, y, args) for m in system.modes], t, y)

    def cond_fn(k):
        tr = system.transitions[k]

        def fn(t, y, args, **kwargs):
            mode, args = args
            # Only a guard moving into {g <= 0} may fire (scipy's direction = -1); otherwise the
            # solve right after a reset stops at once on the guard it just left.
            g, gdot = jax.jvp(lambda t, y: tr.guard(t, y, args), (t, y), (jnp.ones_like(t), flow(t, y, (mode, args))))
            return jnp.where((sources[k] == mode) & (gdot < 0), g, jnp.abs(g) + 1.0)

        return fn

    event = diffrax.Event([cond_fn(k) for k in range(K)], root_finder=optx.Newton(rtol=1e-12, atol=1e-12))
    term = diffrax.ODETerm(flow)

    def one(x0, mode0, args):
        def body(c):
            t, y, mode, i, times, done = c
            sol = diffrax.diffeqsolve(term, solver, t, t1, None, y, (mode, args), stepsize_controller=controller,
                                      event=event, max_steps=max_steps, saveat=diffrax.SaveAt(t1=True),
                                      throw=False)
            mask = jnp.stack(sol.event_mask) if K > 1 else jnp.atleast_1d(sol.event_mask[0])
            fired = jnp.any(mask) & (sol.result == diffrax.RESULTS.event_occurred)
            k = jnp.argmax(mask)
            te, ye = sol.ts[-1], sol.ys[-1]
            y_new = lax.switch(k, [lambda t, y, tr=tr: tr.reset(t, y, args) for tr in system.transitions], te, ye)
            times = times.at[i].set(jnp.where(fired, te, jnp.inf))
            return (te, jnp.where(fired, y_new, ye), jnp.where(fired, targets[k], mode), i + fired,
                    times, ~fired)

        init = (jnp.zeros(()), x0, mode0, jnp.array(0), jnp.full((max_epochs,), jnp.inf), jnp.array(False))
        t, y, mode, i, times, _ = lax.while_loop(lambda c: ~c[5] & (c[3] < max_epochs), body, init)
        return times, i, y, mode

    del n
    return jax.jit(jax.vmap(one, in_axes=(0, 0, None)))
