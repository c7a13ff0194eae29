"""Zeno detection: event times accumulating geometrically, and the extrapolated limit.

For the bouncing ball the flights shrink as |T_{i+1}| = e |T_i| (A. M. Johnson, "Hybrid
Dynamical Systems", Sec. 3.6 and practice problem 3), so the accumulation time is
t_inf = t_n + |T_n| r / (1 - r) with r the ratio of successive epoch lengths. An execution
is declared Zeno when the last `window` ratios of consecutive
epoch lengths are all in (0, max_ratio] and agree with the latest to a relative `ratio_tol`,
and t_inf <= t1. The limit state is extrapolated per component from the last three
post-event states, x_inf = x_n + d_n rho / (1 - rho), rho = d_n / d_{n-1}, d_n = x_n - x_{n-1}
(Aitken's delta-squared), where that ratio is in [0, 1); otherwise x_n.
Reference: A. D. Ames, H. Zheng, R. D. Gregg, S. Sastry, "Is there life after Zeno?", ACC 2006.
"""

import equinox as eqx
import jax.numpy as jnp

from .._step.runge_kutta import fold

DEFAULT_WINDOW, DEFAULT_RATIO_TOL, DEFAULT_MAX_RATIO = 3, 0.05, 0.99


class ZenoOptions(eqx.Module):
    r"""The settings of Zeno detection, in one object (`simulate(..., zeno=hj.ZenoOptions(...))`).

    After each event, if the last `window` ratios $r = |T_{i+1}| / |T_i|$ of consecutive epoch
    lengths lie in $(0, \text{max\_ratio}]$ and agree with the latest to `ratio_tol` (relative),
    and the extrapolated accumulation time $t_\infty = t_n + |T_n| r / (1 - r)$ is $\le t_1$,
    the execution stops with `ZENO`, or jumps to the limit through the mode's `ZenoCompletion`.
    `zeno=True` is `ZenoOptions()`; `zeno=False` switches detection off. The keywords
    `zeno_window`, `zeno_ratio_tol`, `zeno_max_ratio` of `simulate` set the same fields.

    !!! Example

        ```python
        import hybridjax as hj, jax.numpy as jnp
        ball = hj.examples.bouncing_ball()
        sol = hj.simulate(ball, jnp.array([1.0, 0.0]), "flight", 0.0, 5.0, {"g": 9.8, "e": 0.7},
                          zeno=hj.ZenoOptions(window=4, ratio_tol=0.01))
        sol.status_name, sol.zeno_time  # 'ZENO', sqrt(2 h0 / g) (1 + e) / (1 - e)
        ```
    """

    window: int = eqx.field(static=True, default=DEFAULT_WINDOW)  # static: the event times kept (a shape)
    ratio_tol: float = DEFAULT_RATIO_TOL
    max_ratio: float = DEFAULT_MAX_RATIO

    def __check_init__(self):
        if isinstance(self.window, bool) or not isinstance(self.window, int) or self.window < 1:
            raise ValueError(f"ZenoOptions: window must be an int >= 1, got {self.window!r}.")
        if not 0 < self.max_ratio < 1:
            raise ValueError(f"ZenoOptions: max_ratio must be in (0, 1), got {self.max_ratio!r}.")
        if not self.ratio_tol >= 0:
            raise ValueError(f"ZenoOptions: ratio_tol must be >= 0, got {self.ratio_tol!r}.")


def zeno_options(zeno, window=DEFAULT_WINDOW, ratio_tol=DEFAULT_RATIO_TOL,
                 max_ratio=DEFAULT_MAX_RATIO) -> "ZenoOptions | None":
    """The Zeno settings of a call: `zeno` itself if a `ZenoOptions`, None for `zeno=False`,
    else the keywords' (`simulate`'s `zeno_window`, `zeno_ratio_tol`, `zeno_max_ratio`)."""
    if isinstance(zeno, ZenoOptions):
        if (window, ratio_tol, max_ratio) != (DEFAULT_WINDOW, DEFAULT_RATIO_TOL, DEFAULT_MAX_RATIO):
            raise ValueError("zeno=ZenoOptions(...) holds the Zeno settings: pass zeno_window, "
                             "zeno_ratio_tol and zeno_max_ratio there, not beside it.")
        return zeno
    return ZenoOptions(int(window), float(ratio_tol), float(max_ratio)) if zeno else None


def detect_zeno(recent_times, recent_states, t1, options: ZenoOptions):
    """(is_zeno, t_inf, x_inf) from the last `options.window + 2` event times and last 3
    post-event states, oldest first (inf where fewer events have happened).

    The window is the leading axis, of `recent_times` (R, ...) and `recent_states` (3, n, ...);
    any further axes are executions (lanes last, `t1` (...)), each tested on its own: the
    reductions over the window are written out (`fold`), elementwise, so a batch of lanes
    needs no `jax.vmap` and no transposition."""
    ratio_tol, max_ratio = options.ratio_tol, options.max_ratio
    T = recent_times
    L = T[1:] - T[:-1]
    ok = fold(jnp.logical_and, jnp.isfinite(T)) & fold(jnp.logical_and, L > 0)
    L_safe = jnp.where(ok[None], L, 1.0)  # [None]: the window axis, under any rank-promotion setting
    r = L_safe[1:] / L_safe[:-1]
    r_last = r[-1]
    ok = ok & fold(jnp.logical_and, (r > 0) & (r <= max_ratio) & (jnp.abs(r - r[-1:]) <= ratio_tol * r[-1:]))
    r_safe = jnp.where(ok, r_last, 0.5)
    t_inf = T[-1] + L_safe[-1] * r_safe / (1 - r_safe)
    X = jnp.where(ok[None, None], recent_states, 0.0)
    d1, d2 = X[1] - X[0], X[2] - X[1]
    d1_safe = jnp.where(d1 != 0, d1, 1.0)
    rho = d2 / d1_safe
    contracting = (d1 != 0) & (rho >= 0) & (rho < 1) & ok[None]
    rho_safe = jnp.where(contracting, rho, 0.0)
    x_inf = X[2] + jnp.where(contracting, d2 * rho_safe / (1 - rho_safe), 0.0)
    return ok & (t_inf <= t1), jnp.where(ok, t_inf, jnp.inf), x_inf
