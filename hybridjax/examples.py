"""Built-in example systems, each with a closed-form solution it is tested against.

- `bouncing_ball`: one mode, one self-transition (A. M. Johnson, "Hybrid Dynamical Systems", Sec. 3.6).
- `thermostat`: the chapter's practice problem 2, heat / off / cool with hysteresis.
- `wall_particle`: a 4-D flight mode and a 2-D sliding mode (modes of different dimension).
- `ceiling_ball`: a ball thrown at a ceiling with plastic impact; the reset lands in the
  interior of the lift-off guard (the chapter's "reset into guards", Sec. 3.7: a zero-length epoch).
- `rimless_wheel`, `pendulum_wall`, `truncated_ball`: periodic orbits, a nonlinear impact,
  Zeno truncation.
- `compass_gait`: Goswami, Thuilot and Espiau's passive walker, a periodic gait without closed form.
- `stiff_relay`: a relay watching a fast lag (stiff); `van_der_pol_relay`: a relay oscillator.
- `integrate_and_fire`: a leaky integrate-and-fire neuron, a long spike train in closed form.
- Scenes for `contact_system`: `wedge_particle` (the chapter's practice problem 1), `ball_scene`,
  `ceiling_scene`, `polygon_particle` (a point inside K walls), `rimless_wheel_scene`, `rod_scene`.

The `*_closed_form` functions are plain numpy derivations, independent of the simulator.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import jax.numpy as jnp
import numpy as np

from ._definition.system import HybridSystem, Mode, Transition

if TYPE_CHECKING:  # imported by the scene examples when called: `import hybridjax` needs it not
    from ._scenes.scene import Relabel, Scene

# ----------------------------------------------------------------------------- ball


def bouncing_ball() -> HybridSystem:
    r"""A ball bouncing on the floor with restitution e.

    State x = (h, v); flow (v, -g); guard g(x) = h (fires when h <= 0, falling); reset
    (h, v) -> (h, -e v). `args = {"g": ..., "e": ...}`.
    """
    flight = Mode("flight", flow=lambda t, x, args: jnp.array([x[1], -args["g"]]), dim=2)
    bounce = Transition(
        "flight",
        "flight",
        guard=lambda t, x, args: x[0],
        reset=lambda t, x, args: jnp.array([x[0], -args["e"] * x[1]]),
        name="bounce",
    )
    return HybridSystem([flight], [bounce])


def bouncing_ball_closed_form(h0: float, v0: float, g: float, e: float, t1: float,
                              max_events: int = 10_000) -> dict:
    """Impact times, post-impact velocities and the state at t1 of the bouncing ball.

    First impact at t_1 = (v0 + sqrt(v0^2 + 2 g h0)) / g with speed w_1 = sqrt(v0^2 + 2 g h0);
    then w_{k+1} = e w_k and flights of length 2 e w_k / g.
    """
    w = math.sqrt(v0 * v0 + 2 * g * h0)
    t = (v0 + w) / g
    times, v_after = [], []
    t_last, v_last, h_last = 0.0, v0, h0
    while t <= t1 and len(times) < max_events:
        times.append(t)
        v_after.append(e * w)
        t_last, v_last, h_last = t, e * w, 0.0
        w = e * w
        t = t + 2 * w / g
    dt = t1 - t_last
    final = (h_last + v_last * dt - 0.5 * g * dt * dt, v_last - g * dt)
    return dict(event_times=np.array(times), post_velocities=np.array(v_after),
                final_state=np.array(final))


def zeno_time(h0: float, g: float, e: float) -> float:
    """Accumulation time of the ball dropped from rest: sqrt(2 h0 / g) (1 + e) / (1 - e)."""
    return math.sqrt(2 * h0 / g) * (1 + e) / (1 - e)


# ----------------------------------------------------------------------------- thermostat


def thermostat() -> HybridSystem:
    r"""An HVAC thermostat with linear thermal dynamics.

    A. M. Johnson, "Hybrid Dynamical Systems", practice problem 2.

    Room temperature T obeys dT/dt = a (T_amb - T) + P_mode with P = 0 (off), +P_heat
    (heat), -P_cool (cool). With setpoint s: off -> heat when T <= s - 4, heat -> off when
    T >= s - 2, off -> cool when T >= s + 4, cool -> off when T <= s + 2. Domains:
    off |T - s| <= 4, heat T <= s - 2, cool T >= s + 2.
    `args = {"a", "T_amb", "P_heat", "P_cool", "s"}`.
    """

    def flow(power):
        return lambda t, x, p: jnp.array([p["a"] * (p["T_amb"] - x[0]) + power(p)])

    off = Mode("off", flow(lambda p: 0.0), dim=1,
               domain=lambda t, x, p: jnp.array([x[0] - (p["s"] - 4), (p["s"] + 4) - x[0]]))
    heat = Mode("heat", flow(lambda p: p["P_heat"]), dim=1,
                domain=lambda t, x, p: (p["s"] - 2) - x[0])
    cool = Mode("cool", flow(lambda p: -p["P_cool"]), dim=1,
                domain=lambda t, x, p: x[0] - (p["s"] + 2))
    return HybridSystem(
        [off, heat, cool],
        [
            Transition("off", "heat", guard=lambda t, x, p: x[0] - (p["s"] - 4), name="heat on"),
            Transition("heat", "off", guard=lambda t, x, p: (p["s"] - 2) - x[0], name="heat off"),
            Transition("off", "cool", guard=lambda t, x, p: (p["s"] + 4) - x[0], name="cool on"),
            Transition("cool", "off", guard=lambda t, x, p: x[0] - (p["s"] + 2), name="cool off"),
        ],
    )


def thermostat_closed_form(T0: float, mode0: str, p: dict, t1: float) -> dict:
    """Switching times and modes of the thermostat: T(t) = T_eq + (T0 - T_eq) e^{-a t}.

    In each mode T relaxes to T_eq = T_amb + P / a; the time to reach a threshold T* is
    ln((T0 - T_eq) / (T* - T_eq)) / a (infinite when T* is not between T0 and T_eq).
    """
    a, s = p["a"], p["s"]
    power = {"off": 0.0, "heat": p["P_heat"], "cool": -p["P_cool"]}
    # (target, threshold, sign): the guard sign * (T - threshold) <= 0 fires.
    exits = {"off": [("heat", s - 4, 1.0), ("cool", s + 4, -1.0)], "heat": [("off", s - 2, -1.0)],
             "cool": [("off", s + 2, 1.0)]}
    t, T, mode = 0.0, T0, mode0
    times, modes = [], [mode0]
    while True:
        T_eq = p["T_amb"] + power[mode] / a
        best = (math.inf, None, None)
        for target, thr, sign in exits[mode]:
            if sign * (T - thr) <= 0:  # already in the guard: fires at once
                cand = (0.0, target, T)
            else:
                r = (T - T_eq) / (thr - T_eq) if thr != T_eq else -1.0
                cand = (math.log(r) / a, target, thr) if r >= 1.0 else (math.inf, None, None)
            best = min(best, cand, key=lambda b: b[0])
        dt, target, thr = best
        if t + dt > t1:
            T = T_eq + (T - T_eq) * math.exp(-a * (t1 - t))
            return dict(event_times=np.array(times), modes=modes, final_state=np.array([T]),
                        final_mode=mode)
        t, T, mode = t + dt, thr, target
        times.append(t)
        modes.append(mode)


# ----------------------------------------------------------------------------- wall


def wall_particle() -> HybridSystem:
    r"""A particle flying in a vertical plane that hits a wall at x = w and sticks to it.

    Flight (4-D): x = (x, z, v_x, v_z), flow (v_x, v_z, 0, -g). Guard w - x (the wall).
    Reset (x, z, v_x, v_z) -> (z, v_z): the normal velocity is absorbed (plastic contact).
    Slide (2-D): (z, v_z), flow (v_z, -g - c v_z), viscous friction c along the wall.
    `args = {"g", "w", "c"}`.
    """
    flight = Mode("flight", lambda t, x, p: jnp.array([x[2], x[3], 0.0 * x[2], -p["g"] + 0.0 * x[3]]),
                  dim=4)
    slide = Mode("slide", lambda t, x, p: jnp.array([x[1], -p["g"] - p["c"] * x[1]]), dim=2)
    hit = Transition("flight", "slide", guard=lambda t, x, p: p["w"] - x[0],
                     reset=lambda t, x, p: jnp.array([x[1], x[3]]), name="stick")
    return HybridSystem([flight, slide], [hit])


def wall_particle_closed_form(x0, p: dict, t1: float) -> dict:
    """Impact at t* = (w - x) / v_x; then v(tau) = -g/c + (v* + g/c) e^{-c tau} on the wall."""
    x, z, vx, vz = (float(v) for v in x0)
    g, w, c = p["g"], p["w"], p["c"]
    ts = (w - x) / vx
    zs, vzs = z + vz * ts - 0.5 * g * ts * ts, vz - g * ts
    tau = t1 - ts
    v_inf = -g / c
    v = v_inf + (vzs - v_inf) * math.exp(-c * tau)
    zf = zs + v_inf * tau + (vzs - v_inf) * (1 - math.exp(-c * tau)) / c
    return dict(event_time=ts, state_before=np.array([w, zs, vx, vzs]),
                state_after=np.array([zs, vzs]), final_state=np.array([zf, v]))


# ----------------------------------------------------------------------------- ceiling


def ceiling_ball() -> HybridSystem:
    r"""A ball thrown up at a ceiling at height H, with plastic impact.

    Flight: (z, v), flow (v, -g); guard H - z; reset (z, v) -> (z, 0) into "contact".
    Contact: flow 0; the ceiling's normal force per unit mass needed to hold the ball is
    lambda = -g < 0, so the lift-off guard lambda <= 0 holds at once: the reset lands in
    the interior of the lift-off guard and the contact epoch has zero length.
    `args = {"g", "H"}`.
    """
    flight = Mode("flight", lambda t, x, p: jnp.array([x[1], -p["g"] + 0.0 * x[1]]), dim=2)
    contact = Mode("contact", lambda t, x, p: jnp.zeros_like(x), dim=2)
    return HybridSystem(
        [flight, contact],
        [
            Transition("flight", "contact", guard=lambda t, x, p: p["H"] - x[0],
                       reset=lambda t, x, p: jnp.array([x[0], 0.0 * x[1]]), name="impact"),
            Transition("contact", "flight", guard=lambda t, x, p: -p["g"] + 0.0 * x[0],
                       name="lift-off"),
        ],
    )


def ceiling_ball_closed_form(z0: float, v0: float, p: dict, t1: float) -> dict:
    """Impact at the smaller root of z0 + v0 t - g t^2 / 2 = H, then free fall from rest."""
    g, H = p["g"], p["H"]
    disc = v0 * v0 - 2 * g * (H - z0)
    ts = (v0 - math.sqrt(disc)) / g
    dt = t1 - ts
    return dict(event_time=ts, impact_velocity=v0 - g * ts,
                final_state=np.array([H - 0.5 * g * dt * dt, -g * dt]))


# ----------------------------------------------------------------------------- rimless wheel


def rimless_wheel() -> HybridSystem:
    r"""McGeer's rimless wheel rolling down a slope of angle gamma, spokes 2 alpha apart.

    Stance (theta, omega), theta the stance spoke's angle from vertical, g/l = 1:
    flow (omega, sin theta). Heel strike when theta reaches gamma + alpha: guard
    (gamma + alpha) - theta; reset (theta - 2 alpha, cos(2 alpha) omega) (angular momentum
    about the new contact). `args = {"alpha", "gamma"}`.
    """
    stance = Mode("stance", lambda t, x, p: jnp.array([x[1], jnp.sin(x[0])]), dim=2)
    strike = Transition(
        "stance", "stance",
        guard=lambda t, x, p: (p["gamma"] + p["alpha"]) - x[0],
        reset=lambda t, x, p: jnp.array([x[0] - 2 * p["alpha"], jnp.cos(2 * p["alpha"]) * x[1]]),
        name="heel strike",
    )
    return HybridSystem([stance], [strike])


def rimless_wheel_closed_form(alpha: float, gamma: float) -> dict:
    """The rolling gait's post-strike speed and return-map multiplier.

    Energy: omega_-^2 = omega_+^2 + 4 sin(alpha) sin(gamma); strike: omega_+' = cos(2 alpha)
    omega_-. Fixed point omega*^2 = 4 c^2 sin(alpha) sin(gamma) / (1 - c^2), c = cos(2 alpha);
    multiplier d omega_+' / d omega_+ = c^2.
    """
    c = math.cos(2 * alpha)
    w2 = 4 * c * c * math.sin(alpha) * math.sin(gamma) / (1 - c * c)
    return dict(state=np.array([gamma - alpha, math.sqrt(w2)]), multiplier=c * c)


# ----------------------------------------------------------------------------- compass gait


def compass_gait() -> HybridSystem:
    r"""Goswami, Thuilot and Espiau's compass-gait walker on a slope, in its two leg angles.

    Two rigid massless legs of length l = a + b, each with a point mass m at distance a from its
    foot, and a point mass m_H at the hip; the stance foot is a pin, the slope goes down at angle
    gamma. State x = (theta_ns, theta_s, theta_ns', theta_s'): the swing and stance legs' angles
    from the vertical, each the direction from the leg's foot to the hip, positive when the hip is
    downhill of the foot. Flow $M(q) q'' + C(q, q') q' + G(q) = 0$, q = (theta_ns, theta_s),
    c = cos(theta_s - theta_ns), s = sin(theta_s - theta_ns):

    $$M = \begin{pmatrix} m b^2 & -m l b c \\ -m l b c & m a^2 + (m_H + m) l^2 \end{pmatrix},\quad
    C = m l b s \begin{pmatrix} 0 & \theta_s' \\ -\theta_{ns}' & 0 \end{pmatrix},\quad
    G = g \begin{pmatrix} m b \sin\theta_{ns} \\ -(m a + (m_H + m) l) \sin\theta_s \end{pmatrix}.$$

    Heel strike: the swing foot's height above the slope, l (cos(theta_s - gamma) -
    cos(theta_ns - gamma)), reaches 0 while the foot is ahead of the stance foot along the slope,
    d = l (sin(theta_s - gamma) - sin(theta_ns - gamma)), by at least `args["ahead"]`: guard
    max(height, ahead - d) (the swing foot passes through the ground at mid-stance, as in the
    classical model, without an impact). Reset: the legs swap, theta^+ = (theta_s, theta_ns), and
    the impulse at the new foot conserves the angular momentum of the whole walker about the new
    foot and that of the old stance leg about the hip: $Q^+ \omega^+ = Q^- \omega^-$, with
    c_2 = cos(theta_s - theta_ns) at the strike,

    $$Q^- = \begin{pmatrix} -m a b & -m a b + (m_H l^2 + 2 m a l) c_2 \\ 0 & -m a b \end{pmatrix},\quad
    Q^+ = \begin{pmatrix} m b (b - l c_2) & m l (l - b c_2) + m a^2 + m_H l^2 \\
    m b^2 & -m b l c_2 \end{pmatrix}.$$

    `args = {"m", "m_H", "a", "b", "g", "gamma", "ahead"}` (`COMPASS_GAIT_ARGS`, shared with
    `compass_gait_scene`). A. Goswami, B. Thuilot, B. Espiau, "A study of the passive gait of a
    compass-like biped robot", IJRR 17(12), 1998.

    !!! Example

        ```python
        args = {k: jnp.asarray(v) for k, v in hj.examples.COMPASS_GAIT_ARGS.items()}
        orbit = hj.periodic_orbit(hj.examples.compass_gait(), 0, jnp.array([0.33, -0.22, 0.38, 1.1]),
                                  args, max_epochs=4, t_max=2.0)
        orbit.period  # 0.7343 s: the stable period-one gait on the 3 degree slope
        ```
    """

    def two_by_two(a11, a12, a21, a22):
        return jnp.stack([jnp.stack([a11, a12]), jnp.stack([a21, a22])])

    def flow(t, x, p):
        q, w = x[:2], x[2:]
        m, m_H, a, b = p["m"], p["m_H"], p["a"], p["b"]
        leg = a + b
        c, s = jnp.cos(q[1] - q[0]), jnp.sin(q[1] - q[0])
        M = two_by_two(m * b**2 + 0.0 * c, -m * leg * b * c, -m * leg * b * c,
                       m * a**2 + (m_H + m) * leg**2 + 0.0 * c)
        velocity = m * leg * b * s * jnp.stack([w[1] ** 2, -(w[0] ** 2)])
        gravity = p["g"] * jnp.stack([m * b * jnp.sin(q[0]), -(m * a + (m_H + m) * leg) * jnp.sin(q[1])])
        return jnp.concatenate([w, jnp.linalg.solve(M, -velocity - gravity)])

    def strike_guard(t, x, p):
        leg = p["a"] + p["b"]
        height = leg * (jnp.cos(x[1] - p["gamma"]) - jnp.cos(x[0] - p["gamma"]))
        ahead = leg * (jnp.sin(x[1] - p["gamma"]) - jnp.sin(x[0] - p["gamma"]))
        return jnp.maximum(height, p["ahead"] - ahead)

    def strike_reset(t, x, p):
        m, m_H, a, b = p["m"], p["m_H"], p["a"], p["b"]
        leg = a + b
        c = jnp.cos(x[1] - x[0])
        mab = m * a * b + 0.0 * c
        Q_minus = two_by_two(-mab, -mab + (m_H * leg**2 + 2 * m * a * leg) * c, 0.0 * c, -mab)
        Q_plus = two_by_two(m * b * (b - leg * c), m * leg * (leg - b * c) + m * a**2 + m_H * leg**2,
                            m * b**2 + 0.0 * c, -m * b * leg * c)
        w_plus = jnp.linalg.solve(Q_plus, Q_minus @ x[2:])
        return jnp.concatenate([jnp.stack([x[1], x[0]]), w_plus])

    stance = Mode("stance", flow, dim=4)
    strike = Transition("stance", "stance", guard=strike_guard, reset=strike_reset, name="heel strike")
    return HybridSystem([stance], [strike])


# ----------------------------------------------------------------------------- pendulum


def pendulum_wall() -> HybridSystem:
    r"""A pendulum (g/l = 1) swinging against a wall at theta = theta_w with restitution e.

    Flow (omega, -sin theta); guard theta_w - theta; reset (theta, -e omega).
    `args = {"theta_w", "e"}`. A nonlinear example for saltation and variational checks.
    """
    swing = Mode("swing", lambda t, x, p: jnp.array([x[1], -jnp.sin(x[0])]), dim=2)
    hit = Transition("swing", "swing", guard=lambda t, x, p: p["theta_w"] - x[0],
                     reset=lambda t, x, p: jnp.array([x[0], -p["e"] * x[1]]), name="wall")
    return HybridSystem([swing], [hit])


# ----------------------------------------------------------------------------- truncation


def truncated_ball() -> HybridSystem:
    r"""The bouncing ball with Zeno truncated (the chapter's second remedy): it stops rebounding
    when it lands slower than `v_min`.

    Flight (h, v) as `bouncing_ball`; "settle" (listed first, so it wins a tie) fires on landing
    slower than v_min: guard max(h, -v - v_min) <= 0 iff h <= 0 and |v| <= v_min; it resets to
    the 1-D "rest" mode (height, flow 0). Otherwise "bounce" (guard h) rebounds with -e v.
    Finitely many transitions: impact speeds e^k w fall below v_min after
    ceil(log(v_min / w) / log(e)) bounces. `args = {"g", "e", "v_min"}`. Simulate it with
    `zeno=False`: until the truncation acts its epochs shrink geometrically, which the Zeno
    detector would (rightly, by its test) extrapolate.
    """
    ball = bouncing_ball()
    rest = Mode("rest", lambda t, x, p: jnp.zeros_like(x), dim=1)
    settle = Transition(
        "flight", "rest",
        guard=lambda t, x, p: jnp.maximum(x[0], -x[1] - p["v_min"]),
        reset=lambda t, x, p: jnp.array([0.0 * x[0]]),
        name="settle",
    )
    return HybridSystem([ball.modes[0], rest], [settle, ball.transitions[0]])


def truncated_ball_closed_form(h0: float, g: float, e: float, v_min: float) -> dict:
    """Bounce times and the settling time of `truncated_ball` dropped from rest at h0."""
    w = math.sqrt(2 * g * h0)
    t = math.sqrt(2 * h0 / g)
    bounces = []
    while w > v_min:
        bounces.append(t)
        w *= e
        t += 2 * w / g
    return dict(bounce_times=np.array(bounces), settle_time=t)


# ----------------------------------------------------------------------------- relays


def stiff_relay() -> HybridSystem:
    r"""A relay watching a fast first-order lag: stiffness ratio `args` (e.g. 1e6).

    State (s, y): slow s' = u, fast y' = -lam (y - s), with u = +1 in mode "up" and -1 in
    "down"; "up" -> "down" when y >= 1 (guard 1 - y), "down" -> "up" when y <= -1 (guard 1 + y).
    `args = lam`. Explicit solvers need ~ lam steps per unit time; use `diffrax.Kvaerno5()`.
    """

    def mode(u):
        return Mode("up" if u > 0 else "down",
                    lambda t, x, lam: jnp.array([u + 0.0 * x[0], -lam * (x[1] - x[0])]), dim=2)

    return HybridSystem([mode(1.0), mode(-1.0)], [
        Transition("up", "down", guard=lambda t, x, lam: 1.0 - x[1], name="switch down"),
        Transition("down", "up", guard=lambda t, x, lam: 1.0 + x[1], name="switch up"),
    ])


def stiff_relay_closed_form(s0: float, lam: float, t1: float) -> dict:
    """Switching times and final state of `stiff_relay` from (s0, s0) in "up", |s0| < 1.

    After its 1/lam transient y = s - u/lam, so u y = 1 when u s = a = 1 + 1/lam: switches at
    t_1 = a - s0 and every 2a after (the transients left at a switch are e^{-2 lam a}, i.e. 0).
    """
    a = 1 + 1 / lam
    times = []
    t = a - s0
    while t <= t1:
        times.append(t)
        t += 2 * a
    n = len(times)
    u = 1.0 if n % 2 == 0 else -1.0
    s_end = s0 + t1 if n == 0 else -u * a + u * (t1 - times[-1])
    return dict(event_times=np.array(times), final_state=np.array([s_end, s_end - u / lam]),
                final_mode="up" if u > 0 else "down")


def van_der_pol_relay() -> HybridSystem:
    r"""Van der Pol oscillator with relay feedback and hysteresis.

    x' = y, y' = mu (1 - x^2) y - x + q with q = +1 in mode "q+" and -1 in "q-"; q switches
    when q x crosses 0.5 upward (guard 0.5 - q x). `args = mu`. No closed form: a benchmark
    problem (`benchmarks/problems.py`) compared with a reference at tight tolerance.
    """

    def mode(q):
        return Mode("q+" if q > 0 else "q-",
                    lambda t, x, mu: jnp.array([x[1], mu * (1 - x[0] ** 2) * x[1] - x[0] + q]), dim=2)

    return HybridSystem([mode(1.0), mode(-1.0)], [
        Transition("q+", "q-", guard=lambda t, x, mu: 0.5 - x[0], name="relay off"),
        Transition("q-", "q+", guard=lambda t, x, mu: 0.5 + x[0], name="relay on"),
    ])


# ----------------------------------------------------------------------------- neuron


def integrate_and_fire() -> HybridSystem:
    r"""A leaky integrate-and-fire neuron driven by a constant current.

    Membrane potential x = (V,); flow V' = (I - V) / tau; a spike when V reaches 1 (guard
    1 - V), which resets V to 0. `args = {"I": ..., "tau": ...}`; it spikes periodically when
    I > 1 (`integrate_and_fire_closed_form`).
    """
    sub = Mode("subthreshold", lambda t, x, p: (p["I"] - x) / p["tau"], dim=1)
    spike = Transition("subthreshold", "subthreshold", guard=lambda t, x, p: 1.0 - x[0],
                       reset=lambda t, x, p: jnp.zeros_like(x), name="spike")
    return HybridSystem([sub], [spike])


def integrate_and_fire_closed_form(current, tau, V0, num_spikes: int):
    """The first `num_spikes` spike times of `integrate_and_fire` from V(0) = V0 < 1, with
    current I > 1.

    V(t) = I + (V0 - I) e^{-t / tau} reaches 1 at t_1 = tau ln((I - V0) / (I - 1)); from the
    reset, every period is T = tau ln(I / (I - 1)), so t_k = t_1 + (k - 1) T. Written with
    `jax.numpy`, so that differentiating it gives the exact derivatives of the spike times.
    """
    first = tau * jnp.log((current - V0) / (current - 1.0))
    return first + jnp.arange(num_spikes) * tau * jnp.log(current / (current - 1.0))


# ----------------------------------------------------------------------------- scenes
# Scenes (`hj.Scene`) whose hybrid systems `hj.contact_system` builds: modes are contact sets.


def wedge_particle() -> Scene:
    r"""A planar point particle of mass m above a floor and a line through the origin.

    A. M. Johnson, "Hybrid Dynamical Systems", practice problem 1: q = (x, z), constraints
    a_G = z >= 0 and a_H = -x sin(theta) + z cos(theta) >= 0, gravity -m g along z, plastic
    impacts. `args = {"m", "g", "theta"}`; theta in (0, pi) sets which transitions are
    achievable (see the scenes guide).
    """
    from ._scenes.scene import Constraint, Scene

    def a_H(t, q, p):
        return -q[0] * jnp.sin(p["theta"]) + q[1] * jnp.cos(p["theta"])

    return Scene(
        dim=2,
        mass=lambda q, p: p["m"] * jnp.eye(2),
        forces=lambda t, q, dq, p: jnp.stack([0.0 * q[0], -p["m"] * p["g"] + 0.0 * q[1]]),
        constraints=[Constraint("G", lambda t, q, p: q[1]), Constraint("H", a_H)],
        bounds=((-1.0, -1.0, -2.0, -2.0), (1.0, 1.0, 2.0, 2.0)),  # x = (q, dq)
        names=("x", "z"),
    )


def ball_scene() -> Scene:
    r"""The bouncing ball as a scene: q = (h,), unit mass, gravity -g, a floor h >= 0 with
    restitution `args["e"]`. Its system equals `bouncing_ball` (one mode, "free")."""
    from ._scenes.scene import Constraint, Scene

    return Scene(
        dim=1,
        mass=lambda q, p: jnp.eye(1),
        forces=lambda t, q, dq, p: -p["g"] + 0.0 * q,
        constraints=[Constraint("floor", lambda t, q, p: q[0], restitution=lambda p: p["e"])],
        bounds=((0.0, -5.0), (2.0, 5.0)),  # x = (q, dq)
        names=("h",),
    )


def ceiling_scene() -> Scene:
    r"""The ball thrown at a ceiling as a scene: q = (z,), unit mass, gravity -g, a ceiling
    H - z >= 0 with plastic impact. Its system equals `ceiling_ball`: the contact force -g < 0
    right after the impact lifts it off in a zero-length epoch."""
    from ._scenes.scene import Constraint, Scene

    return Scene(
        dim=1,
        mass=lambda q, p: jnp.eye(1),
        forces=lambda t, q, dq, p: -p["g"] + 0.0 * q,
        constraints=[Constraint("ceiling", lambda t, q, p: p["H"] - q[0])],
        bounds=((0.0, -5.0), (2.0, 5.0)),  # x = (q, dq)
        names=("z",),
    )


def polygon_particle(num_walls: int) -> Scene:
    r"""A planar point particle (unit mass, gravity -g) inside a regular polygon of `num_walls`
    walls at distance r from the centre, plastic impacts.

    Wall k has outward normal n_k = (sin(2 pi k / K), -cos(2 pi k / K)) (wall 0 is the floor) and
    gap a_k = r - n_k . q >= 0. K = 1 is a floor, K = 2 a floor and a ceiling. Of the 2^K contact
    sets only the free one, single walls and corners of adjacent walls can be reached.
    `args = {"g", "r"}`.
    """
    from ._scenes.scene import Constraint, Scene

    K = int(num_walls)
    if K < 1:
        raise ValueError(f"polygon_particle: num_walls must be >= 1, got {num_walls}.")

    def wall(k):
        s, c = math.sin(2 * math.pi * k / K), math.cos(2 * math.pi * k / K)
        return Constraint(f"w{k}", lambda t, q, p: p["r"] - (s * q[0] - c * q[1]))

    return Scene(
        dim=2,
        mass=lambda q, p: jnp.eye(2),
        forces=lambda t, q, dq, p: jnp.stack([0.0 * q[0], -p["g"] + 0.0 * q[1]]),
        constraints=[wall(k) for k in range(K)],
        bounds=((-1.2, -1.2, -3.0, -3.0), (1.2, 1.2, 3.0, 3.0)),  # x = (q, dq)
        names=("x", "z"),
    )


def rimless_wheel_scene(inertia: float = 0.1) -> tuple[Scene, Relabel]:
    r"""McGeer's rimless wheel on a slope as a scene, with the relabelling of its spokes.

    q = (x, z, phi): the hub in the slope's frame (x downhill, z normal to the slope) and the
    angle of spoke 0 from the slope's normal; hub mass m, moment of inertia `inertia` * m l^2
    about the hub (> 0: the mass matrix must be invertible; `rimless_wheel` is the limit 0). Spoke i (i = 0,
    1, 2 spokes apart by 2 alpha) ends at (x - l sin(phi - 2 alpha i), z - l cos(phi - 2 alpha i));
    its gap is that point's height and its tangent its x: a foot that touches sticks (plastic
    impact, unlimited friction). Gravity m g (sin gamma, -cos gamma, 0).
    `args = {"alpha", "gamma", "g", "l", "m"}`.

    The relabelling identifies the contact set {spoke1} with {spoke0}: phi -> phi - 2 alpha and
    the new foot moved to x = 0, so that the rolling gait is a periodic orbit. Returns
    `(scene, relabel)`; build with `contact_system(scene, ["spoke0"], args, relabels=[relabel])`.
    """
    from ._scenes.scene import Constraint, Relabel, Scene

    if not inertia > 0:
        raise ValueError(f"rimless_wheel_scene: `inertia` must be > 0, got {inertia}.")

    def tip(i):
        def point(q, p):
            th = q[2] - 2 * i * p["alpha"]
            return q[0] - p["l"] * jnp.sin(th), q[1] - p["l"] * jnp.cos(th)

        return point

    def spoke(i):
        return Constraint(
            f"spoke{i}", lambda t, q, p: tip(i)(q, p)[1], tangent=lambda t, q, p: tip(i)(q, p)[0]
        )

    def mass(q, p):
        ml2 = p["m"] * p["l"] ** 2
        return jnp.diag(jnp.stack([p["m"], p["m"], inertia * ml2 + 0.0 * q[2]]))

    def forces(t, q, dq, p):
        w = p["m"] * p["g"]
        return jnp.stack([w * jnp.sin(p["gamma"]), -w * jnp.cos(p["gamma"]), 0.0 * q[2]])

    def next_stance(t, q, p):
        x1 = tip(1)(q, p)[0]
        return jnp.stack([q[0] - x1, q[1], q[2] - 2 * p["alpha"]])

    scene = Scene(
        dim=3,
        mass=mass,
        forces=forces,
        constraints=[spoke(0), spoke(1)],
        bounds=((-0.5, 0.5, -0.5) + (-1.0,) * 3, (0.5, 1.0, 0.5) + (1.0,) * 3),  # x = (q, dq)
        names=("x", "z", "phi"),
    )
    return scene, Relabel(("spoke1",), ("spoke0",), q_map=next_stance)


def rimless_wheel_scene_closed_form(
    alpha: float, gamma: float, g: float, length: float, inertia: float
) -> dict:
    """The rolling gait of `rimless_wheel_scene`, by hand.

    Stance: (m l^2 + I) theta'' = m g l sin(theta + gamma), theta the stance spoke's angle
    from the slope's normal, from -alpha to alpha; energy gives omega_-^2 = omega_+^2 +
    4 kappa sin(alpha) sin(gamma), kappa = m g l / (m l^2 + I). The strike conserves angular
    momentum about the new foot: omega_+' = c omega_-, c = (m l^2 cos(2 alpha) + I) / (m l^2 + I).
    Fixed point omega*^2 = 4 c^2 kappa sin(alpha) sin(gamma) / (1 - c^2); return-map
    multiplier c^2. The state just after a strike: hub at (-l sin(alpha), l cos(alpha)), phi =
    -alpha, velocities of a rotation omega* about the foot at the origin.
    """
    kappa = g / (length * (1.0 + inertia))
    c = (math.cos(2 * alpha) + inertia) / (1.0 + inertia)
    w = math.sqrt(4 * c * c * kappa * math.sin(alpha) * math.sin(gamma) / (1 - c * c))
    th = -alpha
    q = np.array([length * math.sin(th), length * math.cos(th), th])
    dq = np.array([length * w * math.cos(th), -length * w * math.sin(th), w])
    return dict(state=np.concatenate([q, dq]), omega=w, multiplier=c * c)


def compass_gait_scene() -> tuple[Scene, Relabel]:
    r"""The compass-gait walker on a slope as a scene (Goswami, Thuilot and Espiau's model), with
    the relabelling of its legs.

    Three point masses in the slope's frame (x downhill, z normal to the slope): the hip
    (mass `m_H`) at q[0:2] and each leg's mass `m` at q[2:4] and q[4:6], a distance b from the
    hip along the leg; M is constant (diagonal), no velocity terms. Each leg is a rigid
    massless rod of length l = a + b (bilateral constraints `leg0`, `leg1`:
    $|p_i - h|^2 - b^2 = 0$) ending in a point foot $h + (l/b)(p_i - h)$. Foot i's gap is its
    height, its tangent its x: a foot that touches sticks (plastic impact, unlimited friction).
    Foot 1 is armed only where it is ahead of foot 0 by `args["ahead"]`, so the swing foot
    passing through the ground at mid-stance is not an impact (`Constraint.armed`). Gravity
    $g(\sin\gamma, -\cos\gamma)$ on every mass.
    `args = {"m", "m_H", "a", "b", "g", "gamma", "ahead"}`.

    The relabelling identifies {leg0, leg1, foot1} with {leg0, leg1, foot0}: the legs swapped
    and the new stance foot moved to x = 0, so the gait is a periodic orbit of the stance mode.
    Returns `(scene, relabel)`; build with
    `contact_system(scene, ["foot0"], args, relabels=[relabel])`.
    """
    from ._scenes.scene import Constraint, Relabel, Scene

    def hip(q):
        return q[0:2]

    def mass_of(i):
        return (lambda q: q[2:4]) if i == 0 else (lambda q: q[4:6])

    def foot(i):
        def point(q, p):
            h, m_i = hip(q), mass_of(i)(q)
            return h + (p["a"] + p["b"]) / p["b"] * (m_i - h)

        return point

    def leg(i):
        def length(t, q, p):
            d = mass_of(i)(q) - hip(q)
            return jnp.sum(d * d) - p["b"] ** 2

        return Constraint(f"leg{i}", length, kind="bilateral")

    def armed(t, q, p):
        return foot(1)(q, p)[0] - foot(0)(q, p)[0] - p["ahead"]

    def feet():
        f0 = Constraint("foot0", lambda t, q, p: foot(0)(q, p)[1], tangent=lambda t, q, p: foot(0)(q, p)[0])
        f1 = Constraint(
            "foot1", lambda t, q, p: foot(1)(q, p)[1], tangent=lambda t, q, p: foot(1)(q, p)[0], armed=armed
        )
        return [f0, f1]

    def mass(q, p):
        return jnp.diag(jnp.stack([p["m_H"], p["m_H"], p["m"], p["m"], p["m"], p["m"]]) + 0.0 * q)

    def forces(t, q, dq, p):
        w = jnp.stack([p["m_H"], p["m_H"], p["m"], p["m"], p["m"], p["m"]]) * p["g"]
        direction = jnp.stack([jnp.sin(p["gamma"]), -jnp.cos(p["gamma"])] * 3)
        return w * direction + 0.0 * q

    def swap(t, q, p):
        x1 = foot(1)(q, p)[0]
        shift = jnp.stack([x1, 0.0 * x1] * 3)
        return jnp.concatenate([q[0:2], q[4:6], q[2:4]]) - shift

    scene = Scene(
        dim=6,
        mass=mass,
        forces=forces,
        constraints=[leg(0), leg(1), *feet()],
        bounds=(
            (-0.5, 0.8, -0.6, 0.3, -0.6, 0.3) + (-2.0,) * 6,  # x = (q, dq)
            (0.5, 1.0, 0.6, 0.6, 0.6, 0.6) + (2.0,) * 6,
        ),
        names=("x_H", "z_H", "x_0", "z_0", "x_1", "z_1"),
    )
    return scene, Relabel(("leg0", "leg1", "foot1"), ("leg0", "leg1", "foot0"), q_map=swap)


# Goswami, Thuilot and Espiau's walker on a 3 degree slope; the swing foot armed 5 cm ahead.
COMPASS_GAIT_ARGS = {
    "m": 5.0, "m_H": 10.0, "a": 0.5, "b": 0.5, "g": 9.81, "gamma": 3 * math.pi / 180, "ahead": 0.05,
}


def rod_scene(friction: tuple[str, ...] = ()) -> Scene:
    r"""A rod of mass m and length L falling in a vertical plane onto a floor, frictionless
    except at the ends named in `friction` (`("left",)`, `("left", "right")`), which have
    Coulomb friction `args["mu"]`.

    q = (x, z, phi): the centre and the angle from horizontal; M = diag(m, m, m L^2 / 12);
    gravity -m g along z. Its ends are the contacts "left" (gap z - (L/2) sin phi) and "right"
    (gap z + (L/2) sin phi), plastic. Dropped tilted, it lands on its lower end, pivots and slides
    on it, then lands on the other: which end hits first, whether the first one is released and
    whether it comes to rest depend on the order of these events. `args = {"m", "g", "L"}`
    (and `"mu"`). With friction each end's tangent is its x coordinate, `x -/+ (L/2) cos phi`,
    and each end sticks or slips (modes such as `"left:stick+right:slip+"`).
    """
    from ._scenes.scene import Constraint, Scene

    def end(sign):
        return lambda t, q, p: q[1] + sign * 0.5 * p["L"] * jnp.sin(q[2])

    def end_x(sign):
        return lambda t, q, p: q[0] + sign * 0.5 * p["L"] * jnp.cos(q[2])

    def contact(name, sign):
        if name not in friction:
            return Constraint(name, end(sign))
        return Constraint(name, end(sign), tangent=end_x(sign), friction=lambda p: p["mu"])

    return Scene(
        dim=3,
        mass=lambda q, p: jnp.diag(jnp.stack([p["m"], p["m"], p["m"] * p["L"] ** 2 / 12 + 0.0 * q[2]])),
        forces=lambda t, q, dq, p: jnp.stack([0.0 * q[0], -p["m"] * p["g"] + 0.0 * q[1], 0.0 * q[2]]),
        constraints=[contact("left", -1.0), contact("right", 1.0)],
        bounds=((-0.5, 0.0, -1.0) + (-2.0,) * 3, (0.5, 1.0, 1.0) + (2.0,) * 3),  # x = (q, dq)
        names=("x", "z", "phi"),
    )
