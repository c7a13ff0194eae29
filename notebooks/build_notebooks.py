"""Build the notebooks from their cells and execute them, saving outputs (plots) in the files.

    python notebooks/build_notebooks.py          # rewrites notebooks/*.ipynb, executed
"""

import base64
import sys
import time
from pathlib import Path

import nbformat
from nbclient import NotebookClient

HERE = Path(__file__).parent
SETUP = """import jax, jax.numpy as jnp, numpy as np, diffrax
import matplotlib.pyplot as plt
import hybridjax as hj, hybridjax.plot as hjp
from hybridjax import examples
jax.config.update("jax_enable_x64", True)
%matplotlib inline"""

NOTEBOOKS = {
    "01_defining_and_simulating": [
        ("md", """# Defining and simulating hybrid systems

A hybrid dynamical system is a tuple $\\mathcal{H} = (\\mathcal{J}, \\Gamma, \\mathcal{D}, \\mathcal{F}, \\mathcal{G}, \\mathcal{R})$:
modes $\\mathcal{J}$, transitions $\\Gamma$, domains $D_I$, flows $\\dot x = F_I(t, x)$, guard sets
$G_{I,J} = \\{g_{I,J}(t, x) \\le 0\\}$ and resets $x^+ = R_{I,J}(t, x^-)$. In hybridjax a `Mode` holds a flow (and
optionally a domain), a `Transition` holds a guard and a reset, and a `HybridSystem` collects them."""),
        ("code", SETUP),
        ("md", """## The bouncing ball

One mode, `flight`, with $F(h, v) = (v, -g)$; one transition back to itself with guard $g(h, v) = h$ and reset
$(h, v) \\mapsto (h, -e v)$. Dropped from $h_0$ at rest, the impacts happen at
$t_k = \\sqrt{2 h_0 / g}\\,(1 + 2e + \\dots + 2e^{k-1})$."""),
        ("code", """flight = hj.Mode("flight", flow=lambda t, x, args: jnp.array([x[1], -args["g"]]), dim=2)
bounce = hj.Transition("flight", "flight", guard=lambda t, x, args: x[0],
                       reset=lambda t, x, args: jnp.array([x[0], -args["e"] * x[1]]), name="bounce")
ball = hj.HybridSystem(modes=[flight], transitions=[bounce])
ball"""),
        ("code", """args = {"g": 9.8, "e": 0.8}
sol = hj.simulate(ball, jnp.array([1.0, 0.0]), "flight", 0.0, 3.0, args,
                  stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10))
ref = examples.bouncing_ball_closed_form(1.0, 0.0, 9.8, 0.8, 3.0)
n = int(sol.num_events)
print("impact times    ", np.asarray(sol.event_times[:n]))
print("max error vs closed form", np.max(np.abs(np.asarray(sol.event_times[:n]) - ref["event_times"])))
sol"""),
        ("md", "The execution lives on a *hybrid time domain*: epochs $[t_i, t_{i+1}]$, each in one mode."),
        ("code", """fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 3.5))
hjp.trajectory(sol, 0, a1); hjp.phase(sol, 0, 1, a2); plt.show()"""),
        ("md", """## The thermostat (practice problem 2)

Modes off / heat / cool; $\\dot T = a (T_{amb} - T) + P_{mode}$. Heat turns on below $s - 4$ and off above $s - 2$;
cooling turns on above $s + 4$ and off below $s + 2$. Each mode's domain is the band it lives in, and the guards cover
the parts of the domains' boundaries the flow leaves through, so the system is nonblocking."""),
        ("code", """thermo = examples.thermostat()
p = dict(a=0.1, T_amb=5.0, P_heat=2.5, P_cool=2.0, s=20.0)
th = hj.simulate(thermo, jnp.array([19.0]), "off", 0.0, 30.0, p)
fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 3.5))
hjp.trajectory(th, 0, a1); hjp.hybrid_time_domain(th, a2); plt.show()
thermo"""),
        ("md", """## A reset into a guard: the ball thrown at a ceiling

Plastic impact zeroes the velocity at the ceiling, in the `contact` mode, where the lift-off guard already holds:
the contact epoch has zero length (the chapter's Figure 8, epoch $T_3$)."""),
        ("code", """ceiling = examples.ceiling_ball()
cs = hj.simulate(ceiling, jnp.array([0.0, 7.0]), "flight", 0.0, 1.0, {"g": 9.8, "H": 2.0})
print(cs.hybrid_time_domain())
fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 3.5))
hjp.hybrid_time_domain(cs, a1); hjp.transition_graph(ceiling, cs, a2); plt.show()"""),
        ("md", "## A thousand executions at once\n\n`jax.vmap` runs a batch; `jax.jit` compiles it once."),
        ("code", """run = jax.jit(jax.vmap(lambda h, v: hj.simulate(ball, jnp.stack([h, v]), "flight", 0.0, 2.5, args,
                                                  saveat=jnp.linspace(0, 2.5, 120), max_epochs=32)))
rng = np.random.default_rng(0)
batch = run(jnp.asarray(rng.uniform(0.5, 1.5, 1000)), jnp.asarray(rng.uniform(-1, 1, 1000)))
print(batch)
hjp.batch(batch, 0, alpha=0.05, max_lines=300); plt.show()"""),
    ],
    "02_gradients_and_saltation": [
        ("md", """# Gradients and saltation matrices

Every number `simulate` returns is differentiable. Event times follow the implicit function theorem,
$\\frac{dt^*}{d\\theta} = -\\frac{\\partial g/\\partial\\theta}{D_t g + D_x g\\,F(t^*, x^*)}$, and AD through the
epoch loop composes flows and resets into the *saltation matrix*
$\\Xi = D_xR + \\frac{(F_J - D_xR\\,F_I - D_tR)\\,D_xg}{D_tg + D_xg\\,F_I}$."""),
        ("code", SETUP),
        ("md", "## Event-time sensitivities of the bouncing ball\n\n$t_1 = \\sqrt{2h_0/g}$, so $dt_1/dh_0 = 1/\\sqrt{2 g h_0}$ and $dt_1/dg = -t_1 / (2g)$."),
        ("code", """ball = examples.bouncing_ball()
ctrl = diffrax.PIDController(rtol=1e-10, atol=1e-10)
def first_impact(h0, g):
    return hj.simulate(ball, jnp.stack([h0, 0.0]), "flight", 0.0, 2.0, {"g": g, "e": 0.8},
                       stepsize_controller=ctrl).event_times[0]
dh, dg = jax.grad(first_impact, argnums=(0, 1))(1.0, 9.8)
t1 = np.sqrt(2 / 9.8)
print(f"dt1/dh0 = {dh:.12f}   closed form {1 / np.sqrt(2 * 9.8):.12f}")
print(f"dt1/dg  = {dg:.12f}   closed form {-t1 / (2 * 9.8):.12f}")"""),
        ("md", "## The saltation matrix\n\nFor the ball, $\\Xi = \\begin{pmatrix} -e & 0 \\\\ -(1+e) g / v & -e \\end{pmatrix}$ at pre-impact velocity $v$."),
        ("code", """print(hj.saltation_matrix(ball, 0, 0.45, jnp.array([0.0, -4.0]), {"g": 9.8, "e": 0.8}))
print(np.array([[-0.8, 0], [-(1.8) * 9.8 / -4.0, -0.8]]))"""),
        ("md", """## AD against the variational equations

`variational_jacobian` integrates $\\dot\\Phi = D_xF\\,\\Phi$ in each epoch with diffrax and multiplies in the saltation
matrices: an independent check of `jax.jacfwd(simulate)`. Here on a nonlinear pendulum hitting a wall."""),
        ("code", """pend = examples.pendulum_wall(); pp = {"theta_w": 0.2, "e": 0.7}
x0 = jnp.array([-0.5, 0.8])
ps = hj.simulate(pend, x0, "swing", 0.0, 9.0, pp, stepsize_controller=ctrl)
J_ad = jax.jacfwd(lambda x: hj.simulate(pend, x, "swing", 0.0, 9.0, pp, stepsize_controller=ctrl,
                                        adjoint=diffrax.ForwardMode()).final_state)(x0)
J_var = hj.variational_jacobian(ps).final_state
print(int(ps.num_events), "impacts"); print(np.asarray(J_ad)); print(J_var)
print("max difference", np.max(np.abs(np.asarray(J_ad) - J_var)))
hjp.phase(ps, 0, 1); plt.show()"""),
        ("md", """## Zero-length epochs chain their sensitivities

At the ceiling the lift-off happens at the impact instant, so its time sensitivity is the impact's. With
$z_0 = 0, v_0 = 7, H = 2, g = 9.8, T = 1$: $\\partial v(T)/\\partial v_0 = 1 - \\sqrt 5$."""),
        ("code", """ceiling = examples.ceiling_ball(); pc = {"g": 9.8, "H": 2.0}
J = jax.jacrev(lambda x: hj.simulate(ceiling, x, "flight", 0.0, 1.0, pc, stepsize_controller=ctrl).final_state)(jnp.array([0.0, 7.0]))
print(J[1, 1], 1 - np.sqrt(5))"""),
        ("md", """## A periodic orbit: the rimless wheel

A fixed point of the return map through heel strike (optimistix Newton), and its Floquet multipliers by AD and by
saltation composition. Closed form: the nontrivial multiplier is $\\cos^2(2\\alpha)$."""),
        ("code", """alpha, gamma = 0.3, 0.08
ref = examples.rimless_wheel_closed_form(alpha, gamma)
orbit = hj.periodic_orbit(examples.rimless_wheel(), 0, ref["state"] * np.array([1.0, 1.2]),
                          {"alpha": alpha, "gamma": gamma})
print("fixed point", orbit.state, "closed form", ref["state"])
print("multipliers (AD)        ", orbit.multipliers_ad.real)
print("multipliers (saltation) ", orbit.multipliers_saltation.real)
print("cos^2(2 alpha)          ", ref["multiplier"])"""),
    ],
    "03_zeno_and_blocking": [
        ("md", """# Zeno, blocking and Monte Carlo

The chapter's ball ($h_0 = 1$, $g = 9.8$, $e = 1/\\sqrt 2$) bounces infinitely often before
$t_\\infty = \\sqrt{2h_0/g}\\,\\frac{1+e}{1-e} \\approx 2.633$ s (practice problem 3: $|T_{i+1}| = e\\,|T_i|$).
hybridjax detects the geometric accumulation, stops with `ZENO` and extrapolates the limit."""),
        ("code", SETUP),
        ("code", """ball = examples.bouncing_ball(); e = 1 / np.sqrt(2)
zs = hj.simulate(ball, jnp.array([1.0, 0.0]), "flight", 0.0, 5.0, {"g": 9.8, "e": e})
print(zs.status_name, "after", int(zs.num_events), "bounces; zeno_time", float(zs.zeno_time),
      "closed form", examples.zeno_time(1.0, 9.8, e), "limit state", np.asarray(zs.zeno_state))"""),
        ("md", "## Completion: the ball comes to rest\n\nA `ZenoCompletion` jumps to $(t_\\infty, x_\\infty)$ and continues in a `rest` mode."),
        ("code", """rest = hj.Mode("rest", lambda t, x, p: jnp.zeros_like(x), dim=1)
completed = hj.HybridSystem([ball.modes[0], rest], ball.transitions,
                            completions=[hj.ZenoCompletion("flight", "rest", reset=lambda t, x, p: x[:1])])
cs = hj.simulate(completed, jnp.array([1.0, 0.0]), "flight", 0.0, 4.0, {"g": 9.8, "e": e})
print(cs)
fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 3.5))
hjp.trajectory(cs, 0, a1); hjp.hybrid_time_domain(cs, a2); plt.show()"""),
        ("md", "## Truncation: stop rebounding below a speed\n\nThe chapter's second remedy changes the model: landing slower than $v_{min}$ settles the ball. Finitely many transitions."),
        ("code", """trunc = examples.truncated_ball(); pt = {"g": 9.8, "e": e, "v_min": 0.05}
ts_ = hj.simulate(trunc, jnp.array([1.0, 0.0]), "flight", 0.0, 4.0, pt, zeno=False)
ref = examples.truncated_ball_closed_form(1.0, 9.8, e, 0.05)
print(ts_, "settles at", float(ts_.event_times[int(ts_.num_events) - 1]), "closed form", ref["settle_time"])"""),
        ("md", "## Blocking\n\nLeaving a mode's domain $\\{a \\ge 0\\}$ where no guard fires ends the execution with `BLOCKED` (the system is not nonblocking there)."),
        ("code", """m = hj.Mode("m", lambda t, x, p: jnp.ones_like(x), dim=1, domain=lambda t, x, p: 1.0 - x[0])
bs = hj.simulate(hj.HybridSystem([m]), jnp.array([0.25]), "m", 0.0, 2.0)
print(bs.status_name, "at t =", float(bs.final_time), "x =", np.asarray(bs.final_state))"""),
        ("md", """## Monte Carlo: how often is the ball Zeno before $t_1 = 4$?

With $h_0 \\sim U(0.5, 1.5)$ and $e \\sim U(0.3, 0.9)$, an execution is Zeno before $t_1$ exactly when
$\\sqrt{2h_0/g}(1+e)/(1-e) \\le t_1$. `monte_carlo` runs chunks sharded across the devices and reports the fraction
with a 95% Wilson interval."""),
        ("code", """def sampler(key, m):
    k1, k2 = jax.random.split(key)
    e = jax.random.uniform(k1, (m,), minval=0.3, maxval=0.9)
    h = jax.random.uniform(k2, (m,), minval=0.5, maxval=1.5)
    return jnp.stack([h, 0 * h], 1), {"g": jnp.full((m,), 9.8), "e": e}
res = hj.monte_carlo(ball, sampler, 20_000, mode0="flight", t1=4.0, chunk_size=10_000, max_epochs=32, progress=False)
print(res.table())
x0, a = sampler(jax.random.fold_in(jax.random.PRNGKey(0), 0), 10_000)
x1, b = sampler(jax.random.fold_in(jax.random.PRNGKey(0), 1), 10_000)
h = np.r_[x0[:, 0], x1[:, 0]]; ee = np.r_[a["e"], b["e"]]
print("closed-form Zeno fraction of the same samples:", np.mean(np.sqrt(2 * h / 9.8) * (1 + ee) / (1 - ee) <= 4.0))
fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 3.5))
hjp.status_histogram(res, a1); hjp.zeno_histogram(res, a2); plt.show()"""),
    ],
    "04_speed_versus_accuracy": [
        ("md", """# Speed versus accuracy

Every knob trades time for error: the solver (its order $p$: the local error of a step $h$ is $O(h^{p+1})$),
the tolerances (`rtol`, `atol`: each step keeps $\\|\\text{err}_i / (\\text{atol} + \\text{rtol}\\,|y_i|)\\|_{\\text{RMS}} \\le 1$),
the event tolerance (event times are located to `event_tol` $\\times$ the step), and the dtype. This notebook shows
what each costs, measured by `benchmarks/work_precision.py` against closed forms (the file it wrote is read here),
and then checks a few points live."""),
        ("code", SETUP + """
import json, pathlib
res = json.loads(pathlib.Path("../benchmarks/results/work_precision.json").read_text())
m = res["machine"]
print(f"measured on {m['cpu']} ({m['cores']} cores, {m['device']}); jax {m['jax']}, diffrax {m['diffrax']}")"""),
        ("md", """## Work-precision diagrams

One point per (solver, tolerance): the largest final-state error over the batch against the wall time per
execution (the batch run under `jax.jit(jax.vmap(...))`). Down and to the left is better. Solid: float64;
dashed: float32, whose error floor is its resolution, about $10^{-7}$ relative."""),
        ("code", """colors = dict(Bosh3="C0", Tsit5="C1", Dopri5="C2", Dopri8="C3", Kvaerno3="C4", Kvaerno5="C5")
wp = res["work_precision"]
from matplotlib.ticker import NullFormatter
fig, axes = plt.subplots(2, 2, figsize=(10, 7.5))
axes = axes.ravel()
for ax, (name, block) in zip(axes, wp.items()):
    for solver in dict.fromkeys(r["solver"] for r in block["rows"]):
        for dtype, style in (("float64", "-o"), ("float32", "--s")):
            rs = [r for r in block["rows"] if r["solver"] == solver and r["dtype"] == dtype and r["error"] == r["error"]]
            if rs:
                ax.loglog([r["run_s"] / r["n"] * 1e6 for r in rs], [max(r["error"], 1e-16) for r in rs], style,
                          color=colors[solver], ms=3, label=f"{solver} {dtype[-2:]}")
    ax.set_title(name, fontsize=9); ax.set_xlabel("us per execution (batched)"); ax.grid(True, which="both", alpha=0.3)
    ax.xaxis.set_minor_formatter(NullFormatter()); ax.set_ylabel("max final-state error"); ax.legend(fontsize=7)
fig.tight_layout(); plt.show()"""),
        ("md", """Read off the diagrams:

- **A (bouncing ball)**: the flow is a polynomial that every Runge-Kutta method integrates exactly, so the
  error is round-off and the event location at every tolerance; the cheapest solver wins.
- **B (Van der Pol relay)** and **C (thermostat)**: the error falls as the tolerance does, until the event
  location on the dense output dominates. Dopri8 takes long steps and its events are located on its interpolant over
  them: at equal tolerance it is *less* accurate than Dopri5 or Tsit5 here, which is why the `precise` preset uses Dopri5.
- **D (stiff relay)**: only the implicit Kvaerno solvers get anywhere (Tsit5 needs about $10^6 \\times 20 / 3$ steps).
- Executions whose number of events is wrong appear at loose tolerances on C: an event missed or added changes
  the whole rest of the execution, so they are counted apart (see the documentation's Speed versus accuracy pages)."""),
        ("md", """## Against what you would write otherwise

Same problems, same tolerance ($10^{-9}$), same run. hybridjax is `jax.jit(hj.simulate_batch)` (the batched
engine), with the batch split over the machine's cores (`benchmarks/work_precision.py` asks JAX for one CPU device
per core; `one_device` is the same engine with `devices=1`); against it, each on one core as written: `scipy.integrate.solve_ivp` with terminal events in a Python loop over epochs, a plain diffrax
loop (a jitted `vmap` of a bounded while loop of `diffeqsolve` + `Event`, the loop reverse mode can pass through;
`diffrax_lockstep_lax` is the same with its epochs in a `lax.while_loop`, forward only), and hybridjax's own
per-execution engine under `jax.vmap`."""),
        ("code", """for name, b in res["baselines"].items():
    print(name)
    print(f"  hybridjax             {b['ours_exec_per_s']:10.0f} executions/s")
    for key in ("one_device", "scipy_RK45", "scipy_DOP853", "diffrax_lockstep", "diffrax_lockstep_lax", "engine_vmap",
                "bare_loop", "closed_form_jax"):
        if key not in b:
            continue
        x = b[key]
        print(f"  {key:<21} {x['exec_per_s']:10.0f} executions/s  error {x['error']:.0e}  -> hybridjax {x['ratio']:.2g}x")"""),
        ("md", """hybridjax is two to three orders of magnitude faster than the scipy loop, and 6-29x its own
per-execution engine under `vmap`. Against the plain diffrax loop (on one core) it is about 4x on the ball and 8x on
Van der Pol at 10,000 executions on two cores, 2-4x on one (`one_device`), and 2.6x on the thermostat (1.5x on one
core); with the plain loop split over both cores too, about 2x on the ball (`benchmarks/per_core.py`).
The plain loop runs as fast with its epochs in a `lax.while_loop` as in the bounded loop reverse mode needs.
The plain loop does less per step (no interior guard samples or minimum search, no third-order Lie derivatives
at epoch starts, no Zeno detection, no blocking checks), and it gets away with it here. Where it does not (short
epochs, grazing, resets into guards, Zeno), see notebook 03 and the documentation's Numerical limits page. `bare_loop` is the
ball alone on a bare hand-written loop (one Tsit5 step per execution per iteration, the guard and reset written in,
none of those checks and no event record): what an event-driven integrator in JAX reaches here with nothing general,
on one core. `closed_form_jax` is the ball's closed form jitted over the batch: the speed limit, ahead of all of
them. Timings on a shared 2-core machine move by +-20 % between runs: read the ratios, from one run."""),
        ("md", """## Throughput against batch size

Executions per second grow with the batch until the machine's vector units are busy."""),
        ("code", """tp = res["throughput"]["batch"]
fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 3.6))
a1.loglog([r["n"] for r in tp], [r["ours_exec_per_s"] for r in tp], "-o", label="hybridjax")
a1.loglog([r["n"] for r in tp], [r["lockstep_exec_per_s"] for r in tp], "-s", label="diffrax lock-step loop")
a1.set_xlabel("batch size"); a1.set_ylabel("executions / s"); a1.legend(); a1.grid(True, which="both", alpha=0.3)
md = res["throughput"]["modes"]
a2.semilogx([r["modes"] for r in md], [r["exec_per_s"] for r in md], "-o", base=2)
a2.set_xlabel("modes (= guards) in a ring"); a2.set_ylabel("executions / s"); a2.grid(True, which="both", alpha=0.3)
fig.tight_layout(); plt.show()"""),
        ("md", """Under `vmap` every mode's flow is evaluated for every execution at each step (then one is selected), so
the cost grows with the number of modes modelled: model only the modes a scene needs."""),
        ("md", """## Presets, checked live

`hj.accuracy_preset(name)` gives `solver`, `stepsize_controller` and `event_tol` for `simulate`. Here they run on
200 random balls with a restitution that makes the flight times irregular, against the closed form."""),
        ("code", """ball = examples.bouncing_ball()
rng = np.random.default_rng(0)
h0, v0 = rng.uniform(0.5, 1.5, 200), rng.uniform(-1, 1, 200)
x0 = jnp.asarray(np.stack([h0, v0], 1))
ref = np.stack([examples.bouncing_ball_closed_form(h, v, 9.8, 0.8, 2.5)["final_state"] for h, v in zip(h0, v0)])
import time
for name in hj.PRESET_NAMES:
    kw = hj.accuracy_preset(name)
    run = jax.jit(jax.vmap(lambda x: hj.simulate(ball, x, "flight", 0.0, 2.5, {"g": 9.8, "e": 0.8}, **kw)))
    jax.block_until_ready(run(x0))
    t = time.perf_counter(); sol = jax.block_until_ready(run(x0)); dt = time.perf_counter() - t
    err = np.max(np.abs(np.asarray(sol.final_state) - ref))
    print(f"{name:>9}: {type(kw['solver']).__name__:>6}, rtol {kw['stepsize_controller'].rtol:.0e}:"
          f" {200 / dt:8.0f} executions/s, max error {err:.1e}")"""),
        ("md", """## float32

float32 resolves about $10^{-7}$ relative: tolerances below $8\\varepsilon \\approx 10^{-6}$ cannot be honoured, and
`simulate` warns when asked (it still ends with a status, never hangs). Within that, float32 runs the same
events (the Zeno point of the ball is found to $3 \\times 10^{-6}$ relative) at lower memory per execution."""),
        ("code", """import warnings
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    s32 = hj.simulate(ball, jnp.array([1.0, 0.0], jnp.float32), "flight", 0.0, 5.0, {"g": 9.8, "e": 0.8},
                      stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-9))
print(caught[0].message if caught else "no warning")
print(s32.status_name, "Zeno time", float(s32.zeno_time), "closed form", examples.zeno_time(1.0, 9.8, 0.8))"""),
    ],
    "06_scenes": [
        ("md", """# Scenes: contact systems from constraints

A point of mass $m$ above a floor $a_G = z \\ge 0$ and a ramp $a_H = -x \\sin\\theta + z \\cos\\theta \\ge 0$ under
gravity (A. M. Johnson, "Hybrid Dynamical Systems", practice problem 1). `hj.contact_system` builds its hybrid system
from the constraints: modes are contact sets, and only the sets reached through achievable transitions are built."""),
        ("code", SETUP),
        ("code", """scene = examples.wedge_particle()
args = {"m": jnp.asarray(1.0), "g": jnp.asarray(9.81), "theta": jnp.asarray(np.pi / 4)}
system = hj.contact_system(scene, ["free"], args)
system"""),
        ("md", """For $\\theta < \\pi/2$ the corner G+H is never held: sliding into it along the floor, holding both would
need the floor to pull ($P_G = -v \\cot\\theta < 0$), so the floor is released and the point runs up the ramp. The
pruned transitions still lead to terminal `unbuilt: ...` modes, so an execution that reaches a set that was not
built stops there with `BLOCKED`."""),
        ("code", """rng = np.random.default_rng(0)
x0 = np.stack([rng.uniform(-0.9, -0.1, 16), rng.uniform(0.1, 0.8, 16),
               rng.uniform(0.0, 2.0, 16), rng.uniform(-1.0, 1.0, 16)], 1)
ts = jnp.linspace(0.0, 1.5, 151)
sols = hj.simulate_batch(system, x0, "free", 0.0, 1.5, args, saveat=ts, max_epochs=16)
print({hj.STATUS_NAMES[c]: int(n) for c, n in zip(*np.unique(np.asarray(sols.status), return_counts=True))})
forces = np.asarray(system.contact_forces(sols))   # (executions, saves, constraints)
print(system.force_names, forces.shape)"""),
        ("code", """fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 3.5))
for i in range(4):
    a1.plot(sols.ys[i, :, 0], sols.ys[i, :, 1])
a1.plot([-1, 0, 1], [0, 0, 1], "k", lw=2); a1.set_xlabel("x"); a1.set_ylabel("z"); a1.set_aspect("equal")
a2.plot(ts, forces[0, :, 0], label="$\\lambda_G$"); a2.plot(ts, forces[0, :, 1], label="$\\lambda_H$")
a2.axhline(9.81 * np.cos(np.pi / 4), color="gray", ls=":")
a2.set_xlabel("t"); a2.set_ylabel("contact force"); a2.legend(); plt.show()"""),
        ("md", """On the floor the force is $m g$; on the ramp it is $m g \\cos\\theta$ (the dotted line); in flight both are 0."""),
        ("md", """## Animating an execution

A rod dropped tilted onto a frictionless floor (`examples.rod_scene()`, $q = (x, z, \\phi)$): it lands on its lower
end, pivots and slides on it, lands on the other end and rests with $m g / 2$ on each. `hjp.SceneDrawing` says which
points to draw (here the ends, as functions of $q$, and the centre, coordinates 0 and 1), which segments join them and
where each contact is drawn; `hjp.animate_scene` marks the contacts whose gap is 0 and draws their forces as arrows."""),
        ("code", """rod_args = {"m": jnp.asarray(1.0), "g": jnp.asarray(9.81), "L": jnp.asarray(1.0)}
rod = hj.contact_system(examples.rod_scene(), ["free"], rod_args)
rod_sol = hj.simulate(rod, jnp.array([0.1, 0.5, 0.3, 0.0, 0.0, 0.0]), "free", 0.0, 0.45, rod_args,
                      saveat=jnp.linspace(0.0, 0.45, 46), max_epochs=8)

def end(sign):
    return lambda q, p: jnp.stack([q[0] + sign * 0.5 * p["L"] * jnp.cos(q[2]), q[1] + sign * 0.5 * p["L"] * jnp.sin(q[2])])

drawing = hjp.SceneDrawing(points={"left": end(-1.0), "right": end(1.0), "centre": (0, 1)},
                           segments=[("left", "right")], contacts={"left": "left", "right": "right"},
                           ground=[((-0.6, 0.0), (0.8, 0.0))])
fig, ax = plt.subplots(figsize=(6, 3), dpi=60)
anim = hjp.animate_scene(rod_sol, drawing, ax=ax)
plt.close(fig)
from IPython.display import HTML
HTML(anim.to_jshtml())"""),
        ("md", """`anim.save("rod.gif", writer="pillow", fps=20)` writes the same animation to a file."""),
    ],
    "07_estimation_and_sensitivity": [
        ("md", """# Estimation and global sensitivity

Two tools for executions with impacts: the **salted Kalman filter**, an extended Kalman filter whose covariance
crosses each transition with the saltation matrix (N. J. Kong, J. J. Payne, G. Council, A. M. Johnson, "The
Salted Kalman Filter", Automatica 131, 2021), and **global sensitivity** (Sobol' indices, Morris effects, DGSM)
of any output of an execution, discrete ones included."""),
        ("code", SETUP),
        ("md", """## Tracking a bouncing ball through impacts

100 balls dropped from $h_0 \\sim N(1, 0.01^2)$, $v_0 \\sim N(0, 0.01^2)$, their height measured every 0.04 s with
noise of standard deviation 0.01. A batch of filters is one `jax.vmap`; the two updates differ only at the
impacts: the saltation matrix $\\Xi$ against the reset's Jacobian $D_x R$."""),
        ("code", """ball = examples.bouncing_ball()
args = {"g": 9.81, "e": 0.8}
ts = 0.03 + 0.04 * np.arange(38)
rng = np.random.default_rng(0)
x0s = np.array([1.0, 0.0]) + 0.01 * rng.normal(size=(100, 2))
truth = jax.jit(jax.vmap(lambda x: hj.simulate(ball, x, 0, 0.0, ts[-1], args, saveat=jnp.asarray(ts)).ys))
xs = np.asarray(truth(jnp.asarray(x0s)))
ys = xs[:, :, :1] + 0.01 * rng.normal(size=(100, len(ts), 1))
P0, R = np.diag([0.01**2, 0.01**2]), np.array([[0.01**2]])

results = {}
for update in ("saltation", "reset"):
    kf = hj.SaltedKalmanFilter(ball, lambda t, x, args: x[:1], update=update)
    run = jax.jit(jax.vmap(lambda y: kf(np.array([1.0, 0.0]), P0, ts, y, jnp.zeros((2, 2)), R, t0=0.0, args=args)))
    results[update] = run(jnp.asarray(ys))
    err = xs - np.asarray(results[update].means)
    nees = np.einsum("nki,nkij,nkj->nk", err, np.linalg.inv(np.asarray(results[update].covariances)), err)
    print(f"{update:>9}: average NEES before the first impact {nees[:, ts < 0.45].mean():.2f}, "
          f"after it {nees[:, ts > 0.45].mean():.2f} (2 for a consistent filter)")"""),
        ("code", """fig, axes = plt.subplots(1, 2, figsize=(12, 3.5))
tt = np.linspace(0, ts[-1], 400)
dense = np.asarray(hj.simulate(ball, jnp.asarray(x0s[0]), 0, 0.0, ts[-1], args, saveat=jnp.asarray(tt)).ys)
axes[0].plot(tt, dense[:, 0], "k-", lw=1, label="truth")
axes[0].plot(ts, ys[0, :, 0], "x", color="0.5", label="measurements")
axes[0].plot(ts, results["saltation"].means[0, :, 0], ".", label="estimate (saltation)")
axes[0].set(xlabel="t", ylabel="h"); axes[0].legend()
for update, color in (("saltation", "C0"), ("reset", "C3")):
    e = xs[0, :, 1] - np.asarray(results[update].means[0, :, 1])
    s = np.sqrt(np.asarray(results[update].covariances[0, :, 1, 1]))
    axes[1].plot(ts, e, "o", ms=3, color=color, label=f"{update}: velocity error")
    axes[1].fill_between(ts, -2 * s, 2 * s, color=color, alpha=0.2, label=f"{update}: 2 sigma")
axes[1].set(xlabel="t", ylabel="v error, one trial"); axes[1].legend(fontsize=7); plt.show()"""),
        ("md", """## Sobol' indices of the first impact time and the bounce count

Parameters $h_0 \\sim U(0.5, 1.5)$, $g \\sim U(5, 15)$; outputs $t_1 = \\sqrt{2 h_0 / g}$ and the number of impacts
before $T = 1.5$, a discrete output. `hj.execution_model` turns the system into a batched model of the
parameters; `hj.sobol_indices` runs Saltelli's scheme, $n(d + 2)$ executions, with bootstrap intervals."""),
        ("code", """def inputs(theta):
    return jnp.stack([theta[0], 0.0 * theta[0]]), {"g": theta[1], "e": 0.8}

def outputs(sol):
    return jnp.stack([sol.event_times[:, 0], sol.num_events.astype(float)], axis=1)

model = hj.execution_model(ball, inputs, outputs, t1=1.5)
bounds = np.array([[0.5, 1.5], [5.0, 15.0]])
sobol = hj.sobol_indices(model, bounds, 2**12, names=("h0", "g"))
print(sobol.table(("t1", "bounces before T")))
morris = hj.morris_effects(model, bounds, 100, names=("h0", "g"))
print("Morris mu* (t1):", morris.mu_star[0], " (bounces):", morris.mu_star[1])"""),
        ("code", """fig, axes = plt.subplots(1, 2, figsize=(12, 3.2), sharey=True)
for j, (ax, title) in enumerate(zip(axes, ("t1", "bounces before T"))):
    x = np.arange(2)
    for k, (vals, ints, label) in enumerate(((sobol.first_order, sobol.first_order_interval, "first order"),
                                             (sobol.total, sobol.total_interval, "total"))):
        err = np.abs(ints[j].T - vals[j])
        ax.bar(x + 0.35 * k, vals[j], 0.35, yerr=err, capsize=3, label=label)
    ax.set_xticks(x + 0.175, sobol.names); ax.set_title(title); ax.legend()
plt.show()"""),
    ],
}

NOTEBOOKS["03_zeno_and_blocking"] += [
    ("md", """## Checking a system before running it

`hj.check_properties` looks for counterexamples to the properties of the chapter's section 3 (achievable
transitions, disjoint guards, guards covering the boundary where the flow leaves a domain, resets into the target
domain, resets into guards and zero-time cycles) by sampling each mode in the `bounds` given and refining the best
samples by local least squares. Every finding comes with a witness state; a property reported as holding had no
counterexample among the samples, which is not a proof. Here, the thermostat with its heater's switch-off
threshold in `args`: at $s - 2$ it is `examples.thermostat()`."""),
    ("code", """base = examples.thermostat()
trs = list(base.transitions)
trs[1] = hj.Transition("heat", "off", guard=lambda t, x, p: p["off_at"] - x[0], name="heat off")
thermo = hj.HybridSystem(base.modes, trs)
pth = {"a": 0.5, "T_amb": 10.0, "P_heat": 15.0, "P_cool": 10.0, "s": 20.0, "off_at": 18.0}
bounds = {"off": (5.0, 35.0), "heat": (5.0, 35.0), "cool": (5.0, 35.0)}
hj.check_properties(thermo, pth, bounds=bounds)"""),
    ("md", """With the switch-off threshold at $s - 1 = 19$, above the heat domain $T \\le s - 2$, the boundary $T = 18$,
where heating leaves the domain, is in no guard: the check reports the gap with its witness (the compiled searches
are reused for the new `args`), and a simulation that heats from 17 °C ends `BLOCKED` there."""),
    ("code", """gap = hj.check_properties(thermo, {**pth, "off_at": 19.0}, bounds=bounds)
print(gap.nonblocking, gap.gaps)
run = hj.simulate(thermo, jnp.array([17.0]), "heat", 0.0, 5.0, {**pth, "off_at": 19.0})
print(run.status_name, "at T =", np.asarray(run.final_state))"""),
    ("md", """Resets into guards are allowed (section 3.7) and reported as chains: the ball thrown at the ceiling
lands, by its plastic impact, inside the lift-off guard; the chain has length two and there is no cycle."""),
    ("code", """ceiling_report = hj.check_properties(examples.ceiling_ball(), {"g": 9.8, "H": 2.0},
                                     bounds={"flight": (-5.0, 5.0), "contact": (-5.0, 5.0)})
print(ceiling_report)"""),
]

NOTEBOOKS["05_trajectory_optimisation"] = [
    ("md", """# Trajectory optimisation through impacts

Shooting with optax (`hj.Shooting`, `hj.shoot`) and hybrid iLQR (`hj.hybrid_ilqr`): the cost against the
iteration, the optimised executions, and the event sequence of each iterate. See the
[Trajectory optimisation](../trajectory_optimisation.md) guide."""),
    ("code", SETUP + "\nimport math, optax"),
    ("md", """## Shooting: the k-th impact at a target

A ball launched from the floor at angle $\\varphi$ with speed $v$ makes its $k$-th impact at
$x_k = v^2 \\sin 2\\varphi\\,(1 - e^k) / (g (1 - e))$; the speed that puts it at $x^*$ is known in closed form.
Three initial guesses, solved together."""),
    ("code", """G, E, PHI, K, X_STAR = 9.8, 0.6, 0.9, 3, 4.0
flight = hj.Mode("flight", lambda t, s, a: jnp.stack([s[2], s[3], 0.0 * s[2], -a["g"] + 0.0 * s[3]]), dim=4)
bounce = hj.Transition("flight", "flight", guard=lambda t, s, a: s[1],
                       reset=lambda t, s, a: s.at[3].multiply(-a["e"]), name="bounce")
ball = hj.HybridSystem([flight], [bounce])
args = {"g": jnp.asarray(G), "e": jnp.asarray(E)}
launch = lambda v: jnp.stack([0.0 * v, 0.0 * v, v * math.cos(PHI), v * math.sin(PHI)])
tight = diffrax.PIDController(rtol=1e-10, atol=1e-10)
problem = hj.Shooting(ball, lambda v, sol: (sol.states_before[K - 1, 0] / X_STAR - 1) ** 2, x0=launch,
                      mode0="flight", t1=20.0, args=args, max_epochs=K, stepsize_controller=tight)
result = hj.shoot(problem, jnp.array([3.0, 4.0, 6.0]), optax.sgd(1.5), steps=30, batched=True)
v_star = math.sqrt(X_STAR * G * (1 - E) / (math.sin(2 * PHI) * (1 - E ** K)))
print("closed form", v_star, " found", np.asarray(result.params))

fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 3.5))
for i in range(3):
    a1.semilogy(np.asarray(result.costs[i]) + 1e-32, label=f"guess {float(result.params_history[i, 0]):.0f}")
a1.set(xlabel="iteration", ylabel="cost"); a1.legend()
ts = jnp.linspace(0, 2.0, 400)
for v in (3.0, float(result.params[0])):
    s = hj.simulate(ball, launch(jnp.asarray(v)), "flight", 0.0, 2.0, args, saveat=ts, stepsize_controller=tight)
    a2.plot(s.ys[:, 0], s.ys[:, 1], label=f"v = {v:.3f}")
a2.axvline(X_STAR, color="gray", ls=":"); a2.set(xlabel="x", ylabel="h", xlim=(0, 5)); a2.legend(); plt.show()"""),
    ("md", """## The event sequence of each iterate

The ball's position at $t_1 = 2$ is fixed, whatever its bounces; its speed decides how many bounces happen
before $t_1$. Unconstrained, the iterates go from two bounces to one (`sequence_changed`); with exactly two
required (`transitions=(0, 0)`), steps are halved to stay there and the iterates stop on the boundary."""),
    ("code", """X_T1 = 9.0 * math.cos(PHI) * 2.0
def reach(transitions=None):
    return hj.Shooting(ball, lambda v, sol: (sol.final_state[0] / X_T1 - 1) ** 2, x0=launch, mode0="flight",
                       t1=2.0, args=args, max_epochs=4, transitions=transitions, max_backtracks=40,
                       stepsize_controller=tight)
sgd = optax.sgd(0.45 * 81)
free = hj.shoot(reach(), jnp.asarray(7.0), sgd, steps=12)
two = hj.shoot(reach((0, 0)), jnp.asarray(7.0), sgd, steps=12)
print("sequence changed at iterates", free.changes)
fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 3.5))
a1.plot(np.asarray(free.params_history), "o-", label="free"); a1.plot(np.asarray(two.params_history), "s-", label="exactly 2 bounces")
a1.set(xlabel="iteration", ylabel="speed v"); a1.legend()
a2.step(range(13), np.asarray(free.num_events), where="mid", label="free"); a2.step(range(13), np.asarray(two.num_events), where="mid", label="exactly 2 bounces")
a2.set(xlabel="iteration", ylabel="bounces before t1"); a2.legend(); plt.show()"""),
    ("md", """## Hybrid iLQR: tracking a bouncing reference

The ball with a vertical thrust $u$ on 20 intervals over $[0, 1]$ tracks the passive ball (impact at
0.4518) from $u = 2.5$ (impact at 0.5234, one interval later). The backward pass crosses the impact with its
saltation matrix; the reference extension compares states of the same epoch while the impact moves back."""),
    ("code", """thrust_ball = hj.HybridSystem(
    [hj.Mode("flight", lambda t, x, a: jnp.stack([x[1], -a["g"] + a["u"][0]]), dim=2)],
    [hj.Transition("flight", "flight", guard=lambda t, x, a: x[0],
                   reset=lambda t, x, a: x.at[1].multiply(-a["e"]), name="bounce")])
grid = jnp.linspace(0, 1, 21)
cargs = lambda u: {"g": 9.8, "e": 0.8, "u": u}
Q = jnp.diag(jnp.array([10.0, 1.0]))
x0 = jnp.array([1.0, 0.0])
passive = lambda u: hj.simulate(thrust_ball, x0, "flight", 0.0, 1.0, cargs(jnp.full(1, u)), saveat=grid).ys
reference = passive(0.0)
lqr = hj.HybridLQRProblem(thrust_ball, cargs, x0, "flight", grid, reference, Q, 1e-3, 10 * Q)
u0 = jnp.full((20, 1), 2.5)
res = hj.hybrid_ilqr(lqr, u0, iterations=8)
first = passive(2.5)  # the initial guess: u = 2.5 on every interval
print("costs", np.asarray(res.costs))
print("impact interval per iterate", [int(np.flatnonzero(np.isfinite(np.asarray(t[:, 0])))[0]) for t in res.event_times])
fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 3.5))
a1.semilogy(np.asarray(res.costs) + 1e-32, "o-"); a1.set(xlabel="iteration", ylabel="cost")
a2.plot(grid, reference[:, 0], "k-", label="reference"); a2.plot(grid, first[:, 0], "--", label="initial u = 2.5")
a2.plot(grid, res.states[:, 0], ".", label="iLQR"); a2.set(xlabel="t", ylabel="h"); a2.legend(); plt.show()"""),
]


def build(name: str, cells, execute: bool = True) -> float:
    nb = nbformat.v4.new_notebook()
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nb.cells = [nbformat.v4.new_markdown_cell(src) if kind == "md" else nbformat.v4.new_code_cell(src)
                for kind, src in cells]
    t = time.perf_counter()
    if execute:
        NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(HERE)}}).execute()
    nbformat.write(nb, HERE / f"{name}.ipynb")
    elapsed = time.perf_counter() - t
    for cell in nb.cells:  # the first figure becomes the notebook's thumbnail
        for out in cell.get("outputs", []):
            if "image/png" in out.get("data", {}):
                (HERE / "thumbnails").mkdir(exist_ok=True)
                (HERE / "thumbnails" / f"{name}.png").write_bytes(base64.b64decode(out["data"]["image/png"]))
                return elapsed
    return elapsed


if __name__ == "__main__":
    names = sys.argv[1:] or list(NOTEBOOKS)
    for name in names:
        print(f"{name}: executed in {build(name, NOTEBOOKS[name]):.1f} s")
