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

import jax.numpy as jnp


def detect_zeno(recent_times, recent_states, t1, *, window: int, ratio_tol: float, max_ratio: float):
    """(is_zeno, t_inf, x_inf) from the last `window + 2` event times and last 3 post-event
    states, oldest first (inf where fewer events have happened)."""
    T = recent_times
    L = jnp.diff(T)
    ok = jnp.all(jnp.isfinite(T)) & jnp.all(L > 0)
    L_safe = jnp.where(ok, L, 1.0)
    r = L_safe[1:] / L_safe[:-1]
    r_last = r[-1]
    ok = ok & jnp.all(r > 0) & jnp.all(r <= max_ratio) & jnp.all(jnp.abs(r - r_last) <= ratio_tol * r_last)
    r_safe = jnp.where(ok, r_last, 0.5)
    t_inf = T[-1] + L_safe[-1] * r_safe / (1 - r_safe)
    X = jnp.where(ok, recent_states, 0.0)
    d1, d2 = X[1] - X[0], X[2] - X[1]
    d1_safe = jnp.where(d1 != 0, d1, 1.0)
    rho = d2 / d1_safe
    contracting = (d1 != 0) & (rho >= 0) & (rho < 1) & ok
    rho_safe = jnp.where(contracting, rho, 0.0)
    x_inf = X[2] + jnp.where(contracting, d2 * rho_safe / (1 - rho_safe), 0.0)
    return ok & (t_inf <= t1), jnp.where(ok, t_inf, jnp.inf), x_inf
