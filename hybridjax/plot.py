"""Plots of hybrid executions (matplotlib; install the `plot` extra).

- `hybrid_time_domain(sol)`: the epochs [t_i, t_{i+1}] as bars on a time axis, stacked by mode,
  zero-length epochs as diamonds (the chapter's Figure 8).
- `trajectory(sol, component)`: one state component against time, coloured by mode, events
  marked, resets drawn as dashed jumps.
- `phase(sol, i, j)`: a phase plane coloured by mode, with the zero sets of the guards drawn
  where the modes are 2-D.
- `batch(sol, component)`: many executions at once (alpha-blended), from their saved states.
- `status_histogram(result)`, `zeno_histogram(result)`: Monte Carlo summaries.
- `transition_graph(system)`: modes and transitions; edges seen in an execution solid.

Every function takes an optional `ax` and returns it.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np

try:
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyArrowPatch
except ImportError as err:  # pragma: no cover - exercised only without matplotlib
    raise ImportError("hybridjax.plot needs matplotlib: pip install 'hybridjax[plot]'") from err

from ._status import STATUS_NAMES


def _ax(ax):
    return plt.subplots()[1] if ax is None else ax


def _colour(mode: int):
    return plt.get_cmap("tab10")(int(mode) % 10)


def hybrid_time_domain(sol, ax=None):
    """Epochs as horizontal bars at the height of their mode; zero-length epochs as diamonds."""
    ax = _ax(ax)
    epochs = sol.hybrid_time_domain()
    names = sol.system.mode_names
    for ep in epochs:
        if ep.length > 0:
            ax.barh(ep.mode, ep.length, left=ep.start, height=0.5, color=_colour(ep.mode),
                    edgecolor="k", linewidth=0.5, label="_epoch")
        else:
            ax.plot([ep.start], [ep.mode], marker="D", color=_colour(ep.mode), ms=7,
                    linestyle="none", label="_zero_length")
    for a, b in zip(epochs, epochs[1:], strict=False):
        ax.plot([b.start, b.start], [a.mode, b.mode], color="0.4", lw=0.8, ls="--", label="_jump")
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("t")
    ax.set_title(f"hybrid time domain ({len(epochs)} epochs)")
    return ax


def _epoch_grid(sol, points_per_epoch: int):
    """Times inside each positive-length epoch, and the (right-continuous) states there."""
    segments = []
    K = sol.system.num_transitions
    for ep in sol.hybrid_time_domain():
        zeno_tail = ep.index < int(sol.num_events) and int(sol.transitions[ep.index]) >= K
        if ep.length <= 0 or zeno_tail:
            continue
        ts = np.linspace(ep.start, ep.end, points_per_epoch)
        ts[-1] = ep.end - 1e-12 * max(1.0, abs(ep.end)) if ep.index < int(sol.num_events) else ep.end
        segments.append((ep, ts))
    if not segments:
        return []
    all_t = jnp.asarray(np.concatenate([ts for _, ts in segments]))
    xs, _ = jax.vmap(sol.evaluate)(all_t)
    xs = np.asarray(xs)
    out, k = [], 0
    for ep, ts in segments:
        out.append((ep, ts, xs[k : k + len(ts)]))
        k += len(ts)
    return out


def trajectory(sol, component: int = 0, ax=None, points_per_epoch: int = 60):
    """x[component] against t, one line per epoch coloured by mode; events and resets marked."""
    ax = _ax(ax)
    seen = set()
    for ep, ts, xs in _epoch_grid(sol, points_per_epoch):
        name = sol.system.mode_names[ep.mode]
        label = name if ep.mode not in seen else "_" + name
        seen.add(ep.mode)
        ax.plot(ts, xs[:, component], color=_colour(ep.mode), lw=1.5, label=label)
    n = int(sol.num_events)
    if n:
        t_ev = np.asarray(sol.event_times[:n])
        before = np.asarray(sol.states_before[:n, component])
        after = np.asarray(sol.states_after[:n, component])
        ax.plot(t_ev, before, "kx", ms=5, label="events")
        K = sol.system.num_transitions
        for i in range(1, n):
            if int(sol.transitions[i]) >= K:  # the Zeno tail: accumulating events, not drawn
                ax.plot([t_ev[i - 1], t_ev[i]], [after[i - 1], before[i]], color="0.5", lw=1.0,
                        ls="--", label="_zeno_tail")
        for t, b, a in zip(t_ev, before, after, strict=True):
            if np.isfinite(a) and a != b:
                ax.plot([t, t], [b, a], color="k", lw=0.8, ls=":", label="_reset")
    ax.set_xlabel("t")
    ax.set_ylabel(f"x[{component}]")
    ax.legend(loc="best", fontsize="small")
    return ax


def phase(sol, i: int = 0, j: int = 1, ax=None, points_per_epoch: int = 80, guards: bool = True,
          grid: int = 200):
    """x[j] against x[i], coloured by mode, with guard zero sets g(t_final, x) = 0 overlaid
    for transitions between 2-D modes (other components fixed at 0)."""
    ax = _ax(ax)
    segments = _epoch_grid(sol, points_per_epoch)
    for ep, _, xs in segments:
        ax.plot(xs[:, i], xs[:, j], color=_colour(ep.mode), lw=1.5)
    n = int(sol.num_events)
    if n:
        ax.plot(np.asarray(sol.states_before[:n, i]), np.asarray(sol.states_before[:n, j]), "kx", ms=5)
    if guards and segments:
        system = sol.system
        lo = np.min([xs[:, [i, j]].min(axis=0) for _, _, xs in segments], axis=0)
        hi = np.max([xs[:, [i, j]].max(axis=0) for _, _, xs in segments], axis=0)
        pad = 0.1 * np.maximum(hi - lo, 1e-9)
        gx, gy = np.meshgrid(np.linspace(lo[0] - pad[0], hi[0] + pad[0], grid),
                             np.linspace(lo[1] - pad[1], hi[1] + pad[1], grid))
        modes_seen = {ep.mode for ep, _, _ in segments}
        for k, tr in enumerate(system.transitions):
            src = system.modes[system.sources[k]]
            if system.sources[k] not in modes_seen or src.dim != 2 or {i, j} != {0, 1}:
                continue
            pts = np.zeros((gx.size, 2))
            pts[:, i], pts[:, j] = gx.ravel(), gy.ravel()
            guard = jax.vmap(lambda x, tr=tr: jnp.asarray(tr.guard(sol.final_time, x, sol.args)))
            g = guard(jnp.asarray(pts))
            ax.contour(gx, gy, np.asarray(g).reshape(gx.shape), levels=[0.0], colors="k",
                       linestyles="--", linewidths=0.8)
    ax.set_xlabel(f"x[{i}]")
    ax.set_ylabel(f"x[{j}]")
    return ax


def batch(sol, component: int = 0, ax=None, alpha: float = 0.15, max_lines: int = 500):
    """Saved states (`saveat`) of many executions, alpha-blended, coloured by mode."""
    ax = _ax(ax)
    ts, ys, ms = (np.asarray(a) for a in (sol.ts, sol.ys[..., component], sol.saved_modes))
    if ts.ndim != 2 or ts.shape[1] == 0:
        raise ValueError("plot.batch needs a batched solution with saved states (saveat).")
    for b in range(min(ts.shape[0], max_lines)):
        for m in np.unique(ms[b][ms[b] >= 0]):
            y = np.where(ms[b] == m, ys[b], np.nan)
            ax.plot(ts[b], y, color=_colour(m), alpha=alpha, lw=1.0)
    ax.set_xlabel("t")
    ax.set_ylabel(f"x[{component}]")
    return ax


def _status_codes(result) -> np.ndarray:
    if hasattr(result, "status_counts"):
        return np.asarray([result.status_counts[name] for name in STATUS_NAMES])
    return np.bincount(np.asarray(result.status_code).ravel(), minlength=len(STATUS_NAMES))


def status_histogram(result, ax=None):
    """Executions per status, from a `MonteCarloResult` or a batched `Solution`."""
    ax = _ax(ax)
    counts = _status_codes(result)
    keep = counts > 0
    names = [n for n, k in zip(STATUS_NAMES, keep, strict=True) if k]
    ax.bar(names, counts[keep], color=[_colour(i) for i in np.nonzero(keep)[0]])
    ax.set_ylabel("executions")
    ax.set_title("status")
    return ax


def zeno_histogram(result, ax=None, bins: int = 40):
    """Histogram of Zeno times (executions that stopped with ZENO)."""
    ax = _ax(ax)
    if hasattr(result, "per_execution"):
        if result.per_execution is None:
            raise ValueError("zeno_histogram needs per-execution results (keep='all').")
        status, zt = result.per_execution["status"], result.per_execution["zeno_time"]
    else:
        status, zt = np.asarray(result.status_code), np.asarray(result.zeno_time)
    zt = zt[status == STATUS_NAMES.index("ZENO")]
    ax.hist(zt, bins=bins, color="tab:purple")
    ax.set_xlabel("Zeno time")
    ax.set_ylabel("executions")
    return ax


def transition_graph(system, sol=None, ax=None):
    """Modes on a circle and the transitions between them. With `sol` (one execution or a
    batch), transitions taken are solid and the others dashed."""
    ax = _ax(ax)
    n = system.num_modes
    pos = {i: (math.cos(2 * math.pi * i / n + math.pi / 2), math.sin(2 * math.pi * i / n + math.pi / 2))
           for i in range(n)} if n > 1 else {0: (0.0, 0.0)}
    taken = None
    if sol is not None:
        tr = np.asarray(sol.transitions).ravel()
        taken = set(int(k) for k in tr[(tr >= 0) & (tr < system.num_transitions)])
    for i, m in enumerate(system.modes):
        x, y = pos[i]
        ax.add_patch(plt.Circle((x, y), 0.18, color=_colour(i), alpha=0.35))
        ax.text(x, y, m.name, ha="center", va="center", fontsize=9)
    for k, tr in enumerate(system.transitions):
        a, b = system.sources[k], system.targets[k]
        style = "-" if taken is None or k in taken else "--"
        (x0, y0), (x1, y1) = pos[a], pos[b]
        if a == b:
            arrow = FancyArrowPatch((x0 - 0.1, y0 + 0.16), (x0 + 0.1, y0 + 0.16),
                                    connectionstyle="arc3,rad=-1.8", arrowstyle="-|>", mutation_scale=12,
                                    linestyle=style, color="k", label=f"transition {k}")
            tx, ty = x0, y0 + 0.45
        else:
            arrow = FancyArrowPatch((x0, y0), (x1, y1), connectionstyle="arc3,rad=0.15", shrinkA=16,
                                    shrinkB=16, arrowstyle="-|>", mutation_scale=12, linestyle=style,
                                    color="k", label=f"transition {k}")
            tx, ty = (x0 + x1) / 2 + 0.1 * (y1 - y0), (y0 + y1) / 2 - 0.1 * (x1 - x0)
        ax.add_patch(arrow)
        ax.text(tx, ty, tr.label, fontsize=7, ha="center", va="center")
    ax.set_xlim(-1.5, 1.5)
    ax.set_ylim(-1.5, 1.5)
    ax.set_aspect("equal")
    ax.axis("off")
    return ax
