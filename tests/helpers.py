"""Shared helpers: compiled runners reused across tests (JAX compiles are slow on 2 cores)."""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import hybridjax as hj
from hybridjax import examples

TIGHT = diffrax.PIDController(rtol=1e-10, atol=1e-10)
BALL = examples.bouncing_ball()
BALL_ARGS = {"g": 9.8, "e": 0.8}
THERMO = examples.thermostat()
WALL = examples.wall_particle()
CEILING = examples.ceiling_ball()


def line_system(domain=None, guard=None):
    """x' = 1 in mode m (domain 1 - x >= 0 if given), optional guard 1 - x to mode 'done'."""
    m = hj.Mode("m", lambda t, x, p: jnp.ones_like(x), dim=1, domain=domain)
    done = hj.Mode("done", lambda t, x, p: jnp.zeros_like(x), dim=1)
    trs = [] if guard is None else [hj.Transition("m", "done", guard=guard)]
    return hj.HybridSystem([m, done], trs)


def with_trace_counter(system):
    """`system` with every mode's flow recording each call on traced values (not calls on
    concrete ones, which `variational_jacobian` makes at each event): (system, calls). A run
    that did not trace the problem again leaves `calls` as it was."""
    calls = []

    def counted(flow):
        def f(t, x, p):
            if isinstance(x, jax.core.Tracer):
                calls.append(1)
            return flow(t, x, p)
        return f

    modes = [eqx.tree_at(lambda m: m.flow, m, counted(m.flow)) for m in system.modes]
    return eqx.tree_at(lambda s: s.modes, system, tuple(modes)), calls


_COMPILES = [0]


def _count_compile(event: str, duration_secs: float, **kwargs) -> None:
    if event == "/jax/core/compile/backend_compile_duration":
        _COMPILES[0] += 1


jax.monitoring.register_event_duration_secs_listener(_count_compile)


def compile_count() -> int:
    """XLA compilations in this process so far (JAX's monitoring event of each backend compile,
    which a program found in a cache does not record)."""
    return _COMPILES[0]


def tree_allclose(a, b, rtol=1e-8, atol=1e-8) -> bool:
    leaves = jax.tree_util.tree_leaves(jax.tree_util.tree_map(
        lambda x, y: np.allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol), a, b))
    return all(leaves)


def central_difference(f, x, eps=None):
    """Jacobian of f at x by central differences, step sqrt(eps) * max(1, |x_i|)."""
    x = np.asarray(x, dtype=np.float64)
    base = np.sqrt(np.finfo(np.float64).eps) if eps is None else eps
    cols = []
    for i in range(x.size):
        h = base * max(1.0, abs(x[i]))
        e = np.zeros_like(x)
        e[i] = h
        cols.append((np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2 * h))
    return np.stack(cols, axis=-1)


@functools.cache
def ball_runner(t1: float, max_epochs: int = 64, adjoint: str = "checkpointed"):
    """jit(simulate) of the ball with x0 and args traced; cached per (t1, max_epochs)."""
    adj = diffrax.ForwardMode() if adjoint == "forward" else diffrax.RecursiveCheckpointAdjoint()

    def run(x0, args):
        return hj.simulate(BALL, x0, "flight", 0.0, t1, args, stepsize_controller=TIGHT,
                           max_epochs=max_epochs, adjoint=adj)

    return jax.jit(run)


def ball_reference(h0, v0, g, e, t1):
    return examples.bouncing_ball_closed_form(float(h0), float(v0), float(g), float(e), float(t1))


def as_f64(x):
    return jnp.asarray(x, dtype=jnp.float64)


def first_order_jets(kern, mode, t, x, args, rtol, atol, tol_t) -> tuple:
    """`Kernels.guard_jets`'s first-order fields (L0, L1, band, scale1) of `mode`'s watched
    functions, from one jvp of `kern.guards` along `kern.flow` and its Jacobian: the start
    test's first-order inputs without the nested jvps of L2 and L3."""
    g = lambda t_, y_: kern.guards(mode, t_, y_, args)  # noqa: E731
    F = kern.flow(mode, t, x, args)
    L0, L1 = jax.jvp(g, (t, x), (jnp.ones_like(t), F))
    gt, gx = jax.jacfwd(g, argnums=(0, 1))(t, x)
    scale1 = jnp.abs(gt) + jnp.sum(jnp.abs(gx * F[None, :]), axis=-1)
    band = jnp.sum(jnp.abs(gx) * (atol + rtol * jnp.abs(x))[None, :], axis=-1) + scale1 * tol_t
    return L0, L1, band, scale1


def evaluations_agree(system, args, xs, rtol=1e-9, jet_order: int = 3) -> int:
    """Check a mode-indexed system's one evaluation per call (`system.mode_indexed()`) against
    its modes' and transitions' own functions, as the engines see them (`Kernels` with and
    without it), at the states `xs` (num, n) in every mode: flows, every watched value, every
    reset and the start test's Lie derivatives of the mode's own watched functions, up to
    `jet_order` (3: L0..L3 and the band; 1: L0, L1 and the band, for systems whose own
    functions' third-order jets take minutes to compile). Returns the number of finite values
    compared."""
    from hybridjax._definition.kernels import Kernels

    if jet_order not in (1, 3):
        raise ValueError(f"evaluations_agree: jet_order is 1 or 3, got {jet_order}")
    mask = Kernels(system, args)
    own = Kernels(system, args)
    own.indexed = None
    assert mask.indexed is not None
    # The engines' view: guards that share a function located on it, the transition chosen at
    # the event (`ModeIndexed.locate_watch`, `select`).
    located = Kernels(system, args, located=True)

    @jax.jit
    def both(mode, x):
        t = jnp.asarray(0.0)
        out = []
        for kern in (mask, own):
            # Jets are defined for the mode's own watched functions (the others are masked).
            mine = kern.outgoing_mask(mode)
            tols = (1e-8, 1e-8, 1e-10)
            if jet_order == 3:
                jets = kern.guard_jets(mode, t, x, args, *tols)
            elif kern is mask:  # the engine's jets of the one evaluation, first-order fields
                j = kern.guard_jets(mode, t, x, args, *tols)
                jets = (j.L0, j.L1, j.band, j.scale1)
            else:
                jets = first_order_jets(kern, mode, t, x, args, *tols)
            jets = [jnp.where(mine, j, 0.0) for j in jets]
            resets = jnp.stack([kern.reset(k, t, x, args) for k in range(system.num_transitions)])
            out.append((kern.flow(mode, t, x, args), kern.guards(mode, t, x, args), resets, *jets))
        chosen = jnp.stack([located.select(mode, jnp.asarray(k), t, x, args) for k in range(located.num_watch)])
        return out, (located.guards(mode, t, x, args), chosen)

    compared = 0
    for m in range(system.num_modes):
        (a, b), (g_located, chosen) = jax.vmap(lambda x, m=m: both(jnp.asarray(m), x))(xs)
        for u, v in zip(a, b, strict=True):
            u, v = np.asarray(u), np.asarray(v)
            ok = np.isfinite(v)
            np.testing.assert_array_equal(np.isfinite(u), ok)
            scale = 1 + np.max(np.abs(v[ok]), initial=0)
            np.testing.assert_allclose(u[ok], v[ok], rtol=rtol, atol=rtol * scale)
            compared += int(ok.sum())
        # Each located value (but the constant 1 of a guard located through another) is the own
        # guard of the transition chosen there: an impact located on its gap takes the release
        # candidate whose own selection guard reads that gap.
        g_own, g_located, chosen = np.asarray(b[1]), np.asarray(g_located), np.asarray(chosen)
        read = np.take_along_axis(g_own, chosen, axis=1)
        ok = np.isfinite(g_located) & (g_located != 1.0)
        np.testing.assert_allclose(read[ok], g_located[ok], rtol=rtol,
                                   atol=rtol * (1 + np.max(np.abs(g_located[ok]), initial=0)))
        compared += int(ok.sum())
    return compared
