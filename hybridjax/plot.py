"""Plots of hybrid executions (matplotlib; install the `plot` extra).

- `hybrid_time_domain(sol)`: the epochs [t_i, t_{i+1}] as bars on a time axis, stacked by mode,
  zero-length epochs as diamonds (the chapter's Figure 8).
- `trajectory(sol, component)`: one state component, or a function `f(mode, x)` of the state,
  against time, coloured by mode, events marked, resets drawn as dashed jumps.
- `phase(sol, i, j)`: a phase plane coloured by mode, with the zero sets of the guards drawn
  where the modes are 2-D.
- `batch(sol, component)`: many executions at once (alpha-blended), from their saved states.
- `status_histogram(result)`, `zeno_histogram(result)`: Monte Carlo summaries.
- `transition_graph(system)`: modes and transitions; edges seen in an execution solid.
- `animate_scene(sol, drawing)`: an animation of a planar scene's execution (`SceneDrawing`:
  points, segments, contacts), contacts marked and their forces as arrows; `scene_frames` gives
  what it draws.

Every function takes an optional `ax` and returns it. Where colour encodes the mode, a legend
names the modes; axis labels use the modes' component names (`Mode(..., names=("h", "v"))`);
plots of one execution give its status in the title; where there is nothing to plot (no Zeno
execution, no positive-length epoch) the axis carries a note saying so.

The plotted quantity `component` is an index into the state, or a function `f(mode, x)` of the
mode's name and the state in that mode (its own `dim` components), returning a scalar: with
modes of different dimension it puts one quantity on one axis.

!!! Example

    ```python
    import hybridjax.plot as hjp

    def height(mode, x):  # the body's height in flight (h, v) and in stance (compression c,)
        return x[0] if mode == "flight" else -x[0]

    ax = hjp.trajectory(sol, height)
    ```
"""

import functools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

try:
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyArrowPatch
except ImportError as err:  # pragma: no cover - exercised only without matplotlib
    raise ImportError("hybridjax.plot needs matplotlib: pip install 'hybridjax[plot]'") from err

from matplotlib.lines import Line2D

from ._core.status import STATUS_NAMES


def _ax(ax):
    return plt.subplots()[1] if ax is None else ax


def _colour(mode: int):
    return plt.get_cmap("tab10")(int(mode) % 10)


def _note(ax, text: str) -> None:
    """An explicit note in the middle of an axis that has nothing to show."""
    ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", color="0.35",
            label="_note")


def _title(sol, what: str) -> str:
    n = int(sol.num_events)
    inside = sol.inside_guard_count()
    # Events fired from strictly inside a guard (`Solution.inside_guard`): often a modelling mistake.
    mark = f", {inside} fired inside a guard" if inside else ""
    return f"{what}: {sol.status_name}, {n} event{'' if n == 1 else 's'}{mark}"


def _mode_legend(ax, system, modes) -> None:
    """A legend naming the modes whose colours appear (alpha-free proxies, not drawn on the axis)."""
    handles = [Line2D([], [], color=_colour(m), lw=2, label=system.mode_names[m]) for m in sorted(modes)]
    if handles:
        ax.legend(handles=handles, loc="best", fontsize="small", title="mode")


def _values(system, component, mode: int, xs) -> np.ndarray | None:
    """The plotted quantity at the (zero-padded) states `xs` (rows) of mode `mode`: component
    `component` (None where the mode has no such component), or `component(name, x)` with x
    the mode's own `dim` components."""
    m = system.modes[mode]
    xs = np.asarray(xs)
    if not callable(component):
        return xs[:, component] if component < m.dim else None
    xs = xs[:, : m.dim]
    try:
        ys = jax.vmap(lambda x: jnp.asarray(component(m.name, x)))(jnp.asarray(xs))
    except Exception:  # a function that is not traceable (numpy, Python branches on values)
        ys = [component(m.name, x) for x in xs]
    ys = np.asarray(ys, dtype=float)
    if ys.shape != (xs.shape[0],):
        raise ValueError(
            f"The plotted function must return a scalar per state; in mode '{m.name}' it returned "
            f"shape {ys.shape[1:]}."
        )
    return ys


def _values_per_row(system, component, modes, xs) -> np.ndarray:
    """`_values` for rows in different modes (mode -1: no state); NaN where undefined."""
    modes, xs = np.asarray(modes).ravel(), np.asarray(xs).reshape(-1, np.shape(xs)[-1])
    out = np.full(modes.shape, np.nan)
    for m in np.unique(modes[modes >= 0]):
        sel = modes == m
        v = _values(system, component, int(m), xs[sel])
        if v is not None:
            out[sel] = v
    return out


def _component_label(system, component, mode: int) -> str | None:
    m = system.modes[mode]
    return m.component_names[component] if component < m.dim else None


def _quantity_name(system, component, modes) -> str:
    """Axis label: the function's name, or the component's names in the modes drawn."""
    if callable(component):
        name = getattr(component, "__name__", "")
        return "f(mode, x)" if name in ("", "<lambda>") else name
    names = []
    for m in sorted(modes):
        c = _component_label(system, component, m)
        if c is not None and c not in names:
            names.append(c)
    return " / ".join(names) if names else f"x[{component}]"


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
    ax.set_title(f"hybrid time domain ({len(epochs)} epochs), {sol.status_name}")
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
    xs, _ = sol.evaluate(all_t)  # one pass over the epochs
    xs = np.asarray(xs)
    out, k = [], 0
    for ep, ts in segments:
        out.append((ep, ts, xs[k : k + len(ts)]))
        k += len(ts)
    return out


def trajectory(sol, component=0, ax=None, points_per_epoch: int = 60):
    """One quantity of one execution against t: one line per epoch, coloured by mode (with a
    legend); events marked, resets drawn as dotted jumps; the status in the title.

    `component` is a state index, or a function `f(mode, x) -> scalar` of the mode's name and
    the state in that mode (its own `dim` components). An index is drawn only in the modes
    that have it, labelled with their component names (`Mode(..., names=...)`); where those
    names differ between modes the legend gives each mode's.

    !!! Example

        ```python
        ax = hjp.trajectory(sol, 0)  # the height of the bouncing ball
        ax = hjp.trajectory(sol, lambda mode, x: 0.5 * x[1] ** 2 + 9.8 * x[0])  # its energy
        ```
    """
    ax = _ax(ax)
    system = sol.system
    segments = [(ep, ts, _values(system, component, ep.mode, xs))
                for ep, ts, xs in _epoch_grid(sol, points_per_epoch)]
    segments = [(ep, ts, ys) for ep, ts, ys in segments if ys is not None]
    drawn = {ep.mode for ep, _, _ in segments}
    differ = not callable(component) and len({_component_label(system, component, m) for m in drawn}) > 1
    seen = set()
    for ep, ts, ys in segments:
        name = system.mode_names[ep.mode]
        if differ:
            name = f"{name}: {_component_label(system, component, ep.mode)}"
        label = name if ep.mode not in seen else "_" + name
        seen.add(ep.mode)
        ax.plot(ts, ys, color=_colour(ep.mode), lw=1.5, label=label)
    n = int(sol.num_events)
    if n:
        t_ev = np.asarray(sol.event_times[:n])
        modes = np.asarray(sol.epoch_modes[: n + 1])
        before = _values_per_row(system, component, modes[:n], np.asarray(sol.states_before[:n]))
        after = _values_per_row(system, component, modes[1:], np.asarray(sol.states_after[:n]))
        ax.plot(t_ev, before, "kx", ms=5, label="events")
        K = system.num_transitions
        for i in range(1, n):
            if int(sol.transitions[i]) >= K:  # the Zeno tail: accumulating events, not drawn
                ax.plot([t_ev[i - 1], t_ev[i]], [after[i - 1], before[i]], color="0.5", lw=1.0,
                        ls="--", label="_zeno_tail")
        for t, b, a in zip(t_ev, before, after, strict=True):
            if np.isfinite(a) and np.isfinite(b) and a != b:
                ax.plot([t, t], [b, a], color="k", lw=0.8, ls=":", label="_reset")
    if not segments:
        _note(ax, "no positive-length epoch with this quantity to draw")
    ax.set_xlabel("t")
    ax.set_ylabel(_quantity_name(system, component, drawn or set(range(system.num_modes))))
    ax.set_title(_title(sol, "trajectory"))
    if segments or n:
        ax.legend(loc="best", fontsize="small")
    return ax


def phase(sol, i: int = 0, j: int = 1, ax=None, points_per_epoch: int = 80, guards: bool = True,
          grid: int = 200):
    """x[j] against x[i] in the modes that have both components, coloured by mode (with a
    legend), with guard zero sets g(t_final, x) = 0 overlaid for transitions between 2-D modes
    (other components fixed at 0); axes labelled with the component names, status in the title.

    !!! Example

        ```python
        ax = hjp.phase(sol, 0, 1)  # (h, v) of the bouncing ball, the guard h = 0 dashed
        ```
    """
    ax = _ax(ax)
    system = sol.system
    segments = [(ep, ts, xs) for ep, ts, xs in _epoch_grid(sol, points_per_epoch)
                if max(i, j) < system.modes[ep.mode].dim]
    seen = set()
    for ep, _, xs in segments:
        name = system.mode_names[ep.mode]
        ax.plot(xs[:, i], xs[:, j], color=_colour(ep.mode), lw=1.5,
                label=name if ep.mode not in seen else "_" + name)
        seen.add(ep.mode)
    n = int(sol.num_events)
    if n:
        has = np.asarray([max(i, j) < system.modes[m].dim for m in np.asarray(sol.epoch_modes[:n])])
        if has.any():
            ax.plot(np.asarray(sol.states_before[:n, i])[has], np.asarray(sol.states_before[:n, j])[has],
                    "kx", ms=5, label="events")
    if guards and segments:
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
    if not segments:
        _note(ax, f"no positive-length epoch in a mode with components {i} and {j}")
    else:
        ax.legend(loc="best", fontsize="small")
    ax.set_xlabel(_quantity_name(system, i, seen or set(range(system.num_modes))))
    ax.set_ylabel(_quantity_name(system, j, seen or set(range(system.num_modes))))
    ax.set_title(_title(sol, "phase plane"))
    return ax


def batch(sol, component=0, ax=None, alpha: float = 0.15, max_lines: int = 500):
    """Saved states (`saveat`) of many executions, alpha-blended, coloured by mode (with a
    legend). `component` is a state index or a function `f(mode, x) -> scalar`, as in
    `trajectory`.

    !!! Example

        ```python
        sols = jax.vmap(lambda h: hj.simulate(ball, jnp.stack([h, 0.0 * h]), "flight", 0.0, 3.0,
                                              args, saveat=jnp.linspace(0, 3, 100)))(heights)
        ax = hjp.batch(sols, 0)
        ```
    """
    ax = _ax(ax)
    system = sol.system
    ts, ys, ms = (np.asarray(a) for a in (sol.ts, sol.ys, sol.saved_modes))
    if ts.ndim != 2 or ts.shape[1] == 0:
        raise ValueError("plot.batch needs a batched solution with saved states (saveat).")
    ts, ys, ms = ts[:max_lines], ys[:max_lines], ms[:max_lines]
    vals = _values_per_row(system, component, ms, ys).reshape(ms.shape)
    drawn = set()
    for b in range(ts.shape[0]):
        for m in np.unique(ms[b][ms[b] >= 0]):
            y = np.where(ms[b] == m, vals[b], np.nan)
            if np.isnan(y).all():
                continue  # this mode has no such component
            ax.plot(ts[b], y, color=_colour(m), alpha=alpha, lw=1.0)
            drawn.add(int(m))
    if drawn:
        _mode_legend(ax, system, drawn)
    else:
        _note(ax, f"nothing to draw among {ts.shape[0]} executions")
    # Executions with an event fired from strictly inside a guard (`Solution.inside_guard`).
    inside = sol.inside_guard_count()
    if inside:
        total = int(np.size(sol.num_events))
        ax.set_title(f"{inside} of {total} executions fired a transition from inside a guard")
    ax.set_xlabel("t")
    ax.set_ylabel(_quantity_name(system, component, drawn or set(range(system.num_modes))))
    return ax


def _status_codes(result) -> np.ndarray:
    if hasattr(result, "status_counts"):
        return np.asarray([result.status_counts[name] for name in STATUS_NAMES])
    return np.bincount(np.asarray(result.status_code).ravel(), minlength=len(STATUS_NAMES))


def status_histogram(result, ax=None):
    """Executions per status, from a `MonteCarloResult` or a batched `Solution`."""
    ax = _ax(ax)
    counts = _status_codes(result)
    if counts.sum() == 0:
        _note(ax, "no executions")
    keep = counts > 0
    names = [n for n, k in zip(STATUS_NAMES, keep, strict=True) if k]
    ax.bar(names, counts[keep], color=[_colour(i) for i in np.nonzero(keep)[0]])
    ax.set_ylabel("executions")
    ax.set_title("status")
    return ax


def zeno_histogram(result, ax=None, bins: int = 40):
    """Histogram of Zeno times (executions that stopped with ZENO), from a `MonteCarloResult`
    (`keep="all"`) or a batched `Solution`; a note on the axis where no execution was Zeno.

    !!! Example

        ```python
        ax = hjp.zeno_histogram(hj.monte_carlo(ball, sampler, 10_000, t1=4.0, progress=False))
        ```
    """
    ax = _ax(ax)
    if hasattr(result, "per_execution"):
        if result.per_execution is None:
            raise ValueError("zeno_histogram needs per-execution results (keep='all').")
        status, zt = result.per_execution["status"], result.per_execution["zeno_time"]
    else:
        status, zt = np.asarray(result.status_code), np.asarray(result.zeno_time)
    total = np.size(status)
    zt = zt[status == STATUS_NAMES.index("ZENO")]
    if zt.size:
        ax.hist(zt, bins=bins, color="tab:purple")
    else:
        _note(ax, f"no Zeno execution among {total}")
    ax.set_title(f"Zeno times: {zt.size} of {total} executions")
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


# ----------------------------------------------------------------------------- scene animation


def _frozen(value):
    """Lists, tuples and arrays, nested, as tuples (hashable); the rest as given."""
    if isinstance(value, (list, tuple)):
        return tuple(_frozen(v) for v in value)
    if isinstance(value, np.ndarray):
        return _frozen(value.tolist())
    return value


def _items(value):
    """A mapping as a tuple of (key, value) pairs (hashable, ordered); other sequences as tuples."""
    if isinstance(value, dict):
        return tuple((k, _frozen(v)) for k, v in value.items())
    return _frozen(tuple(value))


def _is_index(i) -> bool:
    return isinstance(i, (int, np.integer)) and not isinstance(i, bool) and i >= 0


class SceneDrawing(eqx.Module):
    r"""How to draw a planar scene (`hj.Scene`): named points of the plane as functions of its
    coordinates $q$, the segments between them, and the point where each contact is drawn.

    **Arguments:**

    - `points`: `{name: spec}`, each spec a pair `(i, j)` of coordinate indices (the point
      $(q_i, q_j)$) or a function `p(q, args) -> (x, y)`.
    - `segments`: pairs `(name, name)` of points joined by a line (a rod, a leg).
    - `contacts`: `{constraint name: point name}`: the point marked while the constraint's gap is
      0 (to `contact_tol`) and where its force is drawn.
    - `ground`: fixed segments `((x0, y0), (x1, y1))` drawn in grey (a floor, a wall).
    - `force_scale`: the length of the arrow of a unit force; `None` draws the largest force of
      the animation at a fifth of the view's width.
    - `contact_tol`: the gap below which a contact is marked.

    A contact's arrow is the planar force $F$ at its point $p(q)$ that does the work of its
    generalised force, $J_p^\top F = J_a^\top \lambda_a + J_b^\top \lambda_t$ (normal and, with
    friction, tangential force from `contact_forces`; $J_p = \partial p / \partial q$), solved by
    least squares: the contact's force itself when its gap depends on $q$ through $p$ alone.

    Errors at construction name the field at fault; `animate_scene` checks the names and
    indices against the scene.

    !!! Example

        ```python
        drawing = hjp.SceneDrawing(
            points={"ball": (0, 1)},                      # (q[0], q[1])
            contacts={"floor": "ball"},
            ground=[((-1.0, 0.0), (3.0, 0.0))],
        )
        ```
    """

    points: tuple = eqx.field(static=True, converter=_items)
    segments: tuple = eqx.field(static=True, default=(), converter=_items)
    contacts: tuple = eqx.field(static=True, default=(), converter=_items)
    ground: tuple = eqx.field(static=True, default=(), converter=_items)
    force_scale: float | None = None
    contact_tol: float = 1e-6

    def __check_init__(self):
        if not self.points:
            raise ValueError("SceneDrawing: `points` must name at least one point.")
        names = set()
        for entry in self.points:
            if not (isinstance(entry, tuple) and len(entry) == 2 and isinstance(entry[0], str)):
                raise TypeError(f"SceneDrawing: `points` must map names to specs, got {entry!r}.")
            name, spec = entry
            pair = isinstance(spec, (tuple, list)) and len(spec) == 2 and all(_is_index(i) for i in spec)
            if not (callable(spec) or pair):
                raise TypeError(
                    f"SceneDrawing: `points['{name}']` must be a pair of coordinate indices or a "
                    f"function p(q, args) -> (x, y), got {spec!r}."
                )
            names.add(name)
        for k, seg in enumerate(self.segments):
            if not (isinstance(seg, tuple) and len(seg) == 2):
                raise TypeError(f"SceneDrawing: `segments[{k}]` must be a pair of point names, got {seg!r}.")
            for end in seg:
                if end not in names:
                    raise ValueError(f"SceneDrawing: `segments[{k}]` names unknown point {end!r}.")
        for entry in self.contacts:
            if not (isinstance(entry, tuple) and len(entry) == 2 and isinstance(entry[0], str)):
                raise TypeError(f"SceneDrawing: `contacts` must map constraints to points, got {entry!r}.")
            if entry[1] not in names:
                raise ValueError(f"SceneDrawing: `contacts['{entry[0]}']` names unknown point {entry[1]!r}.")
        for k, seg in enumerate(self.ground):
            if np.shape(seg) != (2, 2):
                raise ValueError(f"SceneDrawing: `ground[{k}]` must be ((x0, y0), (x1, y1)), got {seg!r}.")
        if self.force_scale is not None and not (np.isfinite(self.force_scale) and self.force_scale > 0):
            raise ValueError(f"SceneDrawing: `force_scale` must be > 0 or None, got {self.force_scale!r}.")
        if not (np.isfinite(self.contact_tol) and self.contact_tol >= 0):
            raise ValueError(f"SceneDrawing: `contact_tol` must be >= 0, got {self.contact_tol!r}.")

    def point_function(self, name: str):
        """`p(q, args) -> (2,)` of the point `name`."""
        spec = dict(self.points)[name]
        if callable(spec):
            return lambda q, args: jnp.reshape(jnp.asarray(spec(q, args), q.dtype), (2,))
        i, j = spec
        return lambda q, args: jnp.stack([q[i], q[j]])


class SceneFrames(NamedTuple):
    """What `animate_scene` draws, frame by frame (F frames, P points, C contacts of the drawing)."""

    times: np.ndarray  # (F,)
    modes: np.ndarray  # (F,) mode index
    points: np.ndarray  # (F, P, 2), in the order of `SceneDrawing.points`
    touching: np.ndarray  # (F, C) bool: the contact's gap is 0 (to `contact_tol`)
    forces: np.ndarray  # (F, C, 2) the contacts' planar forces (0 where not held)


def _scalar(fn):
    """A constraint's function `fn(t, q, args)` as a scalar of q's dtype."""
    return lambda t, q, args: jnp.reshape(jnp.asarray(fn(t, q, args), q.dtype), ())


def _gradients(fn, ts, q, args):
    """The gradients in q of a constraint's function at the frames' (t, q): (F, n)."""
    return jax.vmap(jax.grad(_scalar(fn), argnums=1), in_axes=(0, 0, None))(jnp.asarray(ts), q, args)


def _check_drawing(drawing: SceneDrawing, scene) -> None:
    for name, spec in drawing.points:
        if not callable(spec) and max(spec) >= scene.dim:
            raise ValueError(
                f"SceneDrawing: `points['{name}']` = {spec} indexes past the scene's {scene.dim} coordinates."
            )
    for constraint, _ in drawing.contacts:
        if constraint not in scene.constraint_names:
            raise ValueError(
                f"SceneDrawing: `contacts` names unknown constraint '{constraint}'; the scene's "
                f"constraints: {list(scene.constraint_names)}."
            )


def scene_frames(sol, drawing: SceneDrawing, times=None) -> SceneFrames:
    """The drawn positions, marked contacts and force arrows of one execution of a contact
    system (`hj.contact_system`) at the saved states (`saveat`), or at `times` (the dense output,
    `Solution.evaluate`); times the execution did not reach are left out."""
    system = sol.system
    scene = getattr(system, "scene", None)
    if scene is None or not hasattr(system, "contact_forces"):
        raise TypeError("scene_frames needs a solution of a contact system (hj.contact_system).")
    _check_drawing(drawing, scene)
    if times is not None:
        ts = jnp.asarray(times, sol.final_time.dtype)
        ys, modes = sol.evaluate(ts)
        sol = eqx.tree_at(lambda s: (s.ts, s.ys, s.saved_modes), sol, (ts, ys, modes))
    if np.ndim(sol.ts) != 1:
        raise ValueError("scene_frames draws one execution, not a batch.")
    keep = (np.asarray(sol.saved_modes) >= 0) & np.isfinite(np.asarray(sol.ts))
    if not keep.any():
        raise ValueError("scene_frames: no state to draw (give `saveat` to simulate, or `times`).")
    lam = np.asarray(system.contact_forces(sol))[keep]
    ts, ys, modes = (np.asarray(a)[keep] for a in (sol.ts, sol.ys, sol.saved_modes))
    n, args = scene.dim, sol.args
    q = jnp.asarray(ys[:, :n])
    names = [name for name, _ in drawing.points]
    pts = np.stack([np.asarray(jax.vmap(functools.partial(drawing.point_function(p), args=args))(q))
                    for p in names], axis=1)
    columns = list(system.force_names)
    touching, forces = [], []
    for constraint, point in drawing.contacts:
        c = scene.constraints[scene.index(constraint)]
        p_fn = drawing.point_function(point)
        gap = jax.vmap(lambda t, q_, c=c: _scalar(c.fn)(t, q_, args))(jnp.asarray(ts), q)
        touching.append(np.abs(np.asarray(gap)) <= drawing.contact_tol)
        # The generalised force J_a^T lambda_n (+ J_b^T lambda_t), then F from J_p^T F = it.
        lam_n = jnp.asarray(lam[:, columns.index(constraint)])
        gen = _gradients(c.fn, ts, q, args) * lam_n[:, None]
        if c.tangent is not None:
            lam_t = jnp.asarray(lam[:, columns.index(constraint + ".t")])
            gen = gen + _gradients(c.tangent, ts, q, args) * lam_t[:, None]
        J_p = np.asarray(jax.vmap(jax.jacfwd(p_fn), in_axes=(0, None))(q, args))  # (F, 2, n)
        rows = zip(J_p, np.asarray(gen), strict=True)
        forces.append(np.stack([np.linalg.lstsq(J.T, g, rcond=None)[0] for J, g in rows]))
    C = len(drawing.contacts)
    return SceneFrames(
        times=ts,
        modes=modes,
        points=pts,
        touching=np.stack(touching, axis=1) if C else np.zeros((len(ts), 0), bool),
        forces=np.stack(forces, axis=1) if C else np.zeros((len(ts), 0, 2)),
    )


def animate_scene(sol, drawing: SceneDrawing, times=None, ax=None, interval: float = 40.0):
    """A matplotlib animation of one execution of a planar contact system: the drawing's points
    and segments, its contacts marked (red) where their gaps are 0, their forces as arrows; the
    time and mode in the title. Frames at the saved states, or at `times` (`scene_frames`).

    Returns a `matplotlib.animation.FuncAnimation` (`interval` milliseconds between frames):
    `anim.to_jshtml()` shows it in a notebook (`IPython.display.HTML`; close the figure,
    `plt.close(ax.figure)`, so that it is not shown as well), `anim.save("run.gif",
    writer="pillow")` writes a file.

    !!! Example

        ```python
        sol = hj.simulate(system, x0, "free", 0.0, 2.0, args, saveat=jnp.linspace(0.0, 2.0, 50))
        anim = hjp.animate_scene(sol, drawing)
        anim.save("ball.gif", writer="pillow", fps=25)
        ```
    """
    from matplotlib.animation import FuncAnimation

    frames = scene_frames(sol, drawing, times)
    ax = _ax(ax)
    names = [name for name, _ in drawing.points]
    index = {name: k for k, name in enumerate(names)}
    for (x0, y0), (x1, y1) in drawing.ground:
        ax.plot([x0, x1], [y0, y1], color="0.5", lw=2.0, label="_ground")
    # The view: every point of every frame and the ground, padded.
    xy = frames.points.reshape(-1, 2)
    if drawing.ground:
        xy = np.concatenate([xy, np.asarray(drawing.ground, float).reshape(-1, 2)])
    lo, hi = np.nanmin(xy, axis=0), np.nanmax(xy, axis=0)
    pad = 0.1 * max(float(np.max(hi - lo)), 1e-3)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    width = hi[0] - lo[0] + 2 * pad
    largest = float(np.max(np.linalg.norm(frames.forces, axis=-1), initial=0.0))
    scale = drawing.force_scale or (0.2 * width / largest if largest > 0 else 1.0)

    segments = [ax.plot([], [], color="k", lw=2.5, solid_capstyle="round", label="_segment")[0]
                for _ in drawing.segments]
    (dots,) = ax.plot([], [], "o", color="tab:blue", ms=7, label="_points")
    (marks,) = ax.plot([], [], "s", mfc="none", mec="tab:red", ms=12, mew=1.5, label="_contacts")
    C = len(drawing.contacts)
    at = [index[p] for _, p in drawing.contacts]
    arrows = None
    if C:
        zero = np.zeros(C)
        arrows = ax.quiver(zero, zero, zero, zero, angles="xy", scale_units="xy", scale=1.0, color="tab:red",
                           width=0.006, label="_forces")
    mode_names = sol.system.mode_names

    def draw(f):
        pts = frames.points[f]
        for line, (a, b) in zip(segments, drawing.segments, strict=True):
            line.set_data([pts[index[a], 0], pts[index[b], 0]], [pts[index[a], 1], pts[index[b], 1]])
        dots.set_data(pts[:, 0], pts[:, 1])
        touch = [k for k in range(C) if frames.touching[f, k]]
        marks.set_data(pts[[at[k] for k in touch], 0], pts[[at[k] for k in touch], 1])
        if arrows is not None:
            arrows.set_offsets(pts[at])
            arrows.set_UVC(scale * frames.forces[f, :, 0], scale * frames.forces[f, :, 1])
        ax.set_title(f"t = {frames.times[f]:.3f}, {mode_names[int(frames.modes[f])]}")
        return [*segments, dots, marks] + ([arrows] if arrows is not None else [])

    anim = FuncAnimation(ax.figure, draw, frames=len(frames.times), interval=interval, blit=False)
    draw(0)
    return anim
