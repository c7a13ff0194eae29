r"""The salted Kalman filter: an extended Kalman filter whose prediction runs `simulate`.

Reference: N. J. Kong, J. J. Payne, G. Council, A. M. Johnson, "The Salted Kalman Filter:
Kalman filtering on hybrid dynamical systems", Automatica 131, 2021.

Between measurements the mean follows the hybrid flow (one `simulate` call, so transitions
are found by the engine) and the covariance follows its linearisation,

    P^- = J P J^T + Q,   J = Phi_m M_{m-1} Phi_{m-1} ... M_1 Phi_1,

with Phi_i the state-transition matrix of epoch i (dPhi/dt = D_x F_I Phi, integrated beside
the state) and M_i at each transition either the saltation matrix
Xi = D_x R + (F_J - D_x R F_I - D_t R) D_x g / (D_t g + D_x g F_I) (`update="saltation"`)
or the reset's Jacobian D_x R alone (`update="reset"`, the update the paper compares
against). A transition fired at the start of an epoch (at once after a measurement or after
another transition at the same instant) has no timing term: its time does not depend on
the state (N. J. Kong, J. J. Payne, J. Zhu, A. M. Johnson, "Saltation matrices: the essential
tool for linearizing hybrid dynamical systems", Proc. IEEE, 2024).
The measurement update is the EKF's with the measurement function of the predicted mode.
"""

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Float, Int

from .._core.names import one_of
from .._definition.kernels import dispatch
from .._definition.system import AbstractHybridSystem, HybridSystem, Mode, Transition, as_mode_index
from .._solve.simulate import simulate


def _pad_vector(v, n: int):
    return v if v.shape[0] == n else jnp.concatenate([v, jnp.zeros((n - v.shape[0],), v.dtype)])


def _pad_rows(a, n: int):
    return a if a.shape[0] == n else jnp.concatenate([a, jnp.zeros((n - a.shape[0],) + a.shape[1:], a.dtype)])


def _variational_mode(mode: Mode, n: int) -> Mode:
    """Mode I with state (x, Phi, s): x in R^{n_I}, Phi (n_I x n) the Jacobian of x with respect
    to the state at the start of the prediction, s the start time of the current epoch."""
    ni = mode.dim

    def flow(t, z, args):
        x, phi = z[:ni], z[ni : ni + ni * n].reshape(ni, n)
        f, A = mode.flow(t, x, args), jax.jacfwd(lambda xx: mode.flow(t, xx, args))(x)
        return jnp.concatenate([jnp.asarray(f), (A @ phi).reshape(-1), jnp.zeros((1,), z.dtype)])

    domain = None if mode.domain is None else (lambda t, z, args: mode.domain(t, z[:ni], args))
    return Mode(mode.name, flow, ni + ni * n + 1, domain)


def _variational_transition(system: HybridSystem, k: int, n: int, salted: bool) -> Transition:
    tr = system.transitions[k]
    mode_i, mode_j = system.modes[system.sources[k]], system.modes[system.targets[k]]
    ni = mode_i.dim

    def guard(t, z, args):
        return tr.guard(t, z[:ni], args)

    def reset(t, z, args):
        x, phi, s = z[:ni], z[ni : ni + ni * n].reshape(ni, n), z[-1]
        t = jnp.asarray(t, z.dtype)
        x_plus = jnp.asarray(tr.reset(t, x, args))
        M = jax.jacfwd(lambda xx: jnp.asarray(tr.reset(t, xx, args)))(x)  # D_x R
        if salted:
            DtR = jax.jacfwd(lambda tt: jnp.asarray(tr.reset(tt, x, args)))(t)
            Dtg, Dxg = jax.grad(lambda tt, xx: jnp.asarray(tr.guard(tt, xx, args)), argnums=(0, 1))(t, x)
            F_i = jnp.asarray(mode_i.flow(t, x, args))
            F_j = jnp.asarray(mode_j.flow(t, x_plus, args))
            # Timed only after an epoch of positive length; the untaken branch divides by 1,
            # so that no NaN reaches a gradient.
            timed = t > s
            gdot = jnp.where(timed, Dtg + Dxg @ F_i, 1.0)
            M = M + jnp.where(timed, jnp.outer(F_j - M @ F_i - DtR, Dxg) / gdot, 0.0)
        return jnp.concatenate([x_plus, (M @ phi).reshape(-1), jnp.reshape(t, (1,))])

    return Transition(tr.source, tr.target, guard, reset, name=tr.label)


class KalmanResult(NamedTuple):
    """What `SaltedKalmanFilter` returns, one row per measurement (K measurements, padded
    state of length n = `system.max_dim`, m measured components).

    - `means`, `covariances`: the filtered estimate x_k^+ (K, n) and P_k^+ (K, n, n).
    - `modes`: the estimate's mode at each measurement (K,).
    - `predicted_means`, `predicted_covariances`: x_k^- and P_k^- before each update.
    - `innovations`: y_k - h(x_k^-) (K, m); `innovation_covariances`: S_k = H P^- H^T + R.
    - `log_likelihood`: sum_k log N(innovation_k; 0, S_k), a scalar (maximise it to tune
      noise or model parameters by gradient).
    - `num_events`: transitions found in each prediction (K,).
    - `status`: the `hj.Status` code of each prediction's execution (K,); `T1_REACHED` when
      it reached the measurement time.
    """

    means: Float[Array, "K n"]
    covariances: Float[Array, "K n n"]
    modes: Int[Array, " K"]
    predicted_means: Float[Array, "K n"]
    predicted_covariances: Float[Array, "K n n"]
    innovations: Float[Array, "K m"]
    innovation_covariances: Float[Array, "K m m"]
    log_likelihood: Float[Array, ""]
    num_events: Int[Array, " K"]
    status: Int[Array, " K"]


class SaltedKalmanFilter(eqx.Module):
    r"""An extended Kalman filter for a hybrid system, with the saltation update at transitions.

    Call it with the prior, the measurements and the noise covariances:
    `kf(x0, P0, ts, ys, Q, R, mode0=..., t0=..., args=...) -> KalmanResult`.
    Before measurement k (time `ts[k]`) the estimate is predicted from the previous time by
    `simulate` (x^- = the execution's final state, its mode the estimate's mode) and
    P^- = J P J^T + Q, with J the Jacobian of the execution's final state with respect to its
    initial state, composed of the flows' state-transition matrices and, at each transition,
    the saltation matrix Xi (`update="saltation"`) or the reset's Jacobian D_x R
    (`update="reset"`). The update is the EKF's, in Joseph form:
    S = H P^- H^T + R, K = P^- H^T S^{-1}, x^+ = x^- + K (y - h(x^-)),
    P^+ = (I - K H) P^- (I - K H)^T + K R K^T, with h the measurement function of the mode
    and H its Jacobian. Q is the process-noise covariance added per prediction (n x n; a
    mode of smaller dimension uses its leading block).

    Pure in its array arguments: `jax.jit`, `jax.vmap` (a batch of filters: many trials, or
    many parameter values), `jax.grad` with respect to `x0`, `P0`, `ys`, `Q`, `R` and `args`
    (the `log_likelihood` is the usual objective).

    **Arguments:**

    - `system`: the `HybridSystem` (without `ZenoCompletion`s).
    - `measurement`: `h(t, x, args) -> y` of shape (m,), one callable for every mode or a
      sequence of one per mode (each sees its own mode's state).
    - `update`: `"saltation"` (default) or `"reset"`.
    - `max_epochs`: the most transitions in one prediction (`simulate`'s `max_epochs`; default
      16; `max_events` is the same keyword under another name).
    - `solver`, `stepsize_controller`, `max_steps`: passed to `simulate` (the default
      controller is `simulate`'s).

    !!! Example

        ```python
        ball = hj.examples.bouncing_ball()
        args = {"g": 9.81, "e": 0.8}
        ts = 0.03 + 0.04 * jnp.arange(38)
        ys = hj.simulate(ball, jnp.array([1.0, 0.0]), "flight", 0.0, ts[-1], args, saveat=ts).ys[:, :1]
        kf = hj.SaltedKalmanFilter(ball, lambda t, x, args: x[:1])   # the height is measured
        res = kf(jnp.array([1.0, 0.0]), 1e-4 * jnp.eye(2), ts, ys + 0.01, jnp.zeros((2, 2)),
                 1e-4 * jnp.eye(1), t0=0.0, args=args)
        res.means[:, 0], res.covariances[:, 0, 0], res.num_events   # through two impacts
        ```
    """

    system: HybridSystem
    measurement: tuple[Callable, ...]
    update: str = eqx.field(static=True)
    max_epochs: int = eqx.field(static=True)
    solver: diffrax.AbstractSolver
    stepsize_controller: diffrax.AbstractStepSizeController | None
    max_steps: int = eqx.field(static=True)
    variational: HybridSystem

    def __init__(
        self,
        system: HybridSystem,
        measurement: Callable | Sequence[Callable],
        *,
        update: str = "saltation",
        max_epochs: int | None = None,
        solver: diffrax.AbstractSolver = diffrax.Tsit5(),
        stepsize_controller: diffrax.AbstractStepSizeController | None = None,
        max_steps: int = 4096,
        max_events: int | None = None,
    ):
        if not isinstance(system, AbstractHybridSystem):
            raise TypeError(f"SaltedKalmanFilter: system must be a hybridjax.HybridSystem, "
                            f"got {type(system).__name__}.")
        if system.completions:
            raise ValueError("SaltedKalmanFilter: system has ZenoCompletions, whose limit point has "
                             "no saltation matrix; give the system without them.")
        hs = (measurement,) * system.num_modes if callable(measurement) else tuple(measurement)
        if len(hs) != system.num_modes or not all(callable(h) for h in hs):
            raise ValueError(f"SaltedKalmanFilter: measurement must be one callable or one per mode "
                             f"({system.num_modes}), got {measurement!r}.")
        if update not in ("saltation", "reset"):
            raise ValueError(f"SaltedKalmanFilter: update must be 'saltation' or 'reset', got {update!r}.")
        max_epochs = one_of("SaltedKalmanFilter", max_epochs=max_epochs, max_events=max_events, default=16)
        for name, value in (("max_epochs", max_epochs), ("max_steps", max_steps)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"SaltedKalmanFilter: {name} must be an int >= 1, got {value!r}.")
        if not isinstance(solver, diffrax.AbstractSolver):
            raise TypeError(f"SaltedKalmanFilter: solver must be a diffrax solver, got {solver!r}.")
        self.system = system
        self.measurement = hs
        self.update = update
        self.max_epochs = int(max_epochs)
        self.solver = solver
        self.stepsize_controller = stepsize_controller
        self.max_steps = int(max_steps)
        n = system.max_dim
        self.variational = HybridSystem(
            [_variational_mode(m, n) for m in system.modes],
            [_variational_transition(system, k, n, update == "saltation")
             for k in range(system.num_transitions)],
        )

    # ------------------------------------------------------------------ pieces
    @property
    def max_events(self) -> int:
        """`max_epochs` under its other name."""
        return self.max_epochs

    def _start(self, mode, t, x):
        """The variational state (x, [I 0], t) of `mode`, padded."""
        n, size = self.system.max_dim, self.variational.max_dim

        def branch(i):
            ni = self.system.modes[i].dim

            def f(x):
                phi = jnp.eye(n, dtype=x.dtype)[:ni].reshape(-1)
                z = jnp.concatenate([x[:ni], phi, jnp.reshape(t, (1,))])
                return _pad_vector(z, size)

            return f

        return dispatch(mode, [branch(i) for i in range(self.system.num_modes)], x)

    def _split(self, mode, z):
        """(x padded to n, J padded to n x n) from the variational state of `mode`."""
        n = self.system.max_dim

        def branch(i):
            ni = self.system.modes[i].dim
            return lambda z: (_pad_vector(z[:ni], n), _pad_rows(z[ni : ni + ni * n].reshape(ni, n), n))

        return dispatch(mode, [branch(i) for i in range(self.system.num_modes)], z)

    def _measure(self, mode, t, x, args):
        """(h(x), H padded to m x n) of the measurement function of `mode`."""
        n = self.system.max_dim

        def branch(i):
            ni, h = self.system.modes[i].dim, self.measurement[i]

            def f(x):
                y = jnp.asarray(h(t, x[:ni], args))
                H = jax.jacfwd(lambda xx: jnp.asarray(h(t, xx, args)))(x[:ni])
                return y, jnp.concatenate([H, jnp.zeros((H.shape[0], n - ni), H.dtype)], axis=1)

            return f

        return dispatch(mode, [branch(i) for i in range(self.system.num_modes)], x)

    def _mask(self, mode, dtype):
        dims = jnp.asarray([m.dim for m in self.system.modes])
        return (jnp.arange(self.system.max_dim) < dims[mode]).astype(dtype)

    def __call__(
        self,
        x0: Float[ArrayLike, " n"],
        P0: Float[ArrayLike, "n n"],
        ts: Float[ArrayLike, " K"],
        ys: Float[ArrayLike, "K m"],
        Q: Float[ArrayLike, "n n"],
        R: Float[ArrayLike, "m m"],
        *,
        mode0: str | int | Int[ArrayLike, ""] = 0,
        t0: Float[ArrayLike, ""] | None = None,
        args: Any = None,
    ) -> KalmanResult:
        """Filter the measurements `ys` taken at times `ts` (non-decreasing, >= t0: a prediction
        to a time before the previous one has the status `T1_BEFORE_T0`) from the prior
        N(x0, P0) in `mode0` at `t0` (default `ts[0]`: the first measurement is not predicted)."""
        system, n = self.system, self.system.max_dim
        x0 = jnp.asarray(x0)
        dtype = jnp.result_type(x0.dtype, jnp.float32)
        ts, ys = jnp.asarray(ts, dtype), jnp.asarray(ys, dtype)
        if ts.ndim != 1 or ys.ndim != 2 or ys.shape[0] != ts.shape[0]:
            raise ValueError(f"SaltedKalmanFilter: ts must be (K,) and ys (K, m); got {ts.shape} "
                             f"and {ys.shape}.")
        m = ys.shape[1]
        mode = as_mode_index(system, mode0)
        static_mode = isinstance(mode0, (str, int, np.integer))
        if static_mode and x0.shape == (system.modes[system.mode_index(mode0)].dim,):
            x0 = _pad_vector(x0, n)
        x0 = x0.astype(dtype)
        P0, Q, R = (jnp.asarray(a, dtype) for a in (P0, Q, R))
        for name, a, k in (("x0", x0, (n,)), ("P0", P0, (n, n)), ("Q", Q, (n, n)), ("R", R, (m, m))):
            if a.shape != k:
                raise ValueError(f"SaltedKalmanFilter: {name} has shape {a.shape}, expected {k} "
                                 f"(state padded to {n}, {m} measured components).")
        t0 = ts[0] if t0 is None else jnp.asarray(t0, dtype)
        return _run(self, x0, P0, ts, ys, Q, R, mode, t0, args)


@eqx.filter_jit
def _run(kf: SaltedKalmanFilter, x0, P0, ts, ys, Q, R, mode, t0, args) -> KalmanResult:
    """The filter's scan over the measurements, compiled once per filter and shapes (the
    user's functions by identity; Python numbers in `args` are constants of the program), so
    that calls outside `jax.jit` do not trace and compile again."""
    n, m, dtype = kf.system.max_dim, ys.shape[1], ys.dtype
    eye = jnp.eye(n, dtype=dtype)

    def step(carry, inputs):
        t, x, P, mode = carry
        tk, yk = inputs
        sol = simulate(kf.variational, kf._start(mode, t, x), mode, t, tk, args,
                       solver=kf.solver, stepsize_controller=kf.stepsize_controller,
                       max_epochs=kf.max_epochs, max_steps=kf.max_steps, zeno=False)
        mode = sol.final_mode
        x_pred, J = kf._split(mode, sol.final_state)
        mask = kf._mask(mode, dtype)
        P_pred = J @ P @ J.T + Q * mask[:, None] * mask[None, :]
        h, H = kf._measure(mode, tk, x_pred, args)
        S = H @ P_pred @ H.T + R
        K = jnp.linalg.solve(S, H @ P_pred).T  # P H^T S^-1, S and P symmetric
        nu = yk - h
        x_new = x_pred + K @ nu
        A = eye - K @ H
        P_new = A @ P_pred @ A.T + K @ R @ K.T
        P_new = 0.5 * (P_new + P_new.T)
        _, logdet = jnp.linalg.slogdet(S)
        ll = -0.5 * (nu @ jnp.linalg.solve(S, nu) + logdet + m * jnp.log(2 * jnp.pi))
        out = (x_new, P_new, mode, x_pred, P_pred, nu, S, ll, sol.num_events, sol.status_code)
        return (tk, x_new, P_new, mode), out

    _, out = lax.scan(step, (t0, x0, P0, mode), (ts, ys))
    xs, Ps, modes, xp, Pp, nus, Ss, lls, nev, status = out
    return KalmanResult(xs, Ps, modes, xp, Pp, nus, Ss, jnp.sum(lls), nev, status)
