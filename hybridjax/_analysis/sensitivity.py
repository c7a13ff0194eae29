r"""Global sensitivity of an execution's outputs to its parameters: Sobol' indices (Saltelli's
scheme, bootstrap intervals), Morris elementary effects and derivative-based measures (DGSM).

The parameters theta in R^d are independent and uniform on a box [low, high]. A *model* maps
a batch of parameter vectors (m, d) to outputs (m,) or (m, k): `execution_model` builds one
from a hybrid system (each row one execution, run by `simulate_batch`), with any output of the
`Solution`, discrete ones included (event count, final mode, status). Models are evaluated in
chunks of a fixed size (one compiled program; only the outputs are kept), so 10^6 executions
run in bounded memory.

References: A. Saltelli, P. Annoni, I. Azzini, F. Campolongo, M. Ratto, S. Tarantola,
"Variance based sensitivity analysis of model output. Design and estimator for the total
sensitivity index", Comput. Phys. Commun. 181, 2010 (first-order estimator (b), Jansen's total
estimator (f) of its Table 2); M. D. Morris, "Factorial sampling plans for preliminary
computational experiments", Technometrics 33, 1991, with F. Campolongo, J. Cariboni,
A. Saltelli, "An effective screening design for sensitivity analysis of large models",
Environ. Model. Softw. 22, 2007 (mu*); I. M. Sobol', S. Kucherenko, "Derivative based global
sensitivity measures and their link with global sensitivity indices", Math. Comput. Simul.
79, 2009.
"""

import math
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._core.checks import check_int
from .._core.names import one_of
from .._definition.system import HybridSystem
from .._solve.simulate_batch import simulate_batch

SAMPLERS = ("sobol", "lhs", "random")


def numpy_seed(owner: str, key: Any, seed: Any) -> int:
    """The seed of numpy's and scipy's samplers: drawn from `key` (a `jax.random` key, typed or
    a legacy uint32 pair) through `numpy.random.SeedSequence`, the same for the same key; an int
    given as `key`, or as the shorthand `seed`, is the seed itself; 0 where neither is given.
    Both at once is a `ValueError` naming them."""
    key = one_of(owner, key=key, seed=seed, default=None)
    if key is None:
        return 0
    if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
        check_int(owner, "seed" if seed is not None else "key", key, 0)
        return int(key)
    if isinstance(key, bool) or not hasattr(key, "dtype"):
        raise TypeError(f"{owner}: key must be a jax.random key (or an int seed), got {key!r}.")
    data = np.asarray(jax.random.key_data(key) if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key)
                      else key)
    return int(np.random.SeedSequence(data.astype(np.uint32).ravel().tolist()).generate_state(1)[0])


class SensitivityOptions(eqx.Module):
    """How samples are drawn and models evaluated, for `sobol_indices`, `morris_effects`, `dgsm`.

    - `sampler`: `"sobol"` (scrambled Sobol' sequence, `scipy.stats.qmc.Sobol`; the number of
      base samples is rounded up to a power of 2), `"lhs"` (Latin hypercube,
      `scipy.stats.qmc.LatinHypercube`) or `"random"` (independent uniforms).
    - `key`: a `jax.random` key for the sampler, the Morris trajectories and the bootstrap
      (numpy and scipy draw them, seeded by the `seed` field the key gives); default: seed 0.
    - `chunk_size`: rows per model call (one compiled program for all; the last chunk padded).
    - `n_bootstrap`, `confidence`: bootstrap resamples and the level of the percentile
      intervals of the Sobol' indices.

    **Keyword shorthand:** `seed=s` (an int >= 0, also accepted as `key`) sets the seed itself.

    ```python
    options = hj.SensitivityOptions(key=jax.random.key(1), chunk_size=50_000)
    ```
    """

    # Static: a name, and ints read by numpy/scipy (seed, array sizes).
    sampler: str = eqx.field(static=True)
    seed: int = eqx.field(static=True)  # the numpy/scipy seed `key` gives
    chunk_size: int = eqx.field(static=True)
    n_bootstrap: int = eqx.field(static=True)
    confidence: float

    def __init__(
        self,
        sampler: str = "sobol",
        key: PRNGKeyArray | int | None = None,
        chunk_size: int = 100_000,
        n_bootstrap: int = 200,
        confidence: float = 0.95,
        **shorthands,
    ):
        unknown = sorted(set(shorthands) - {"seed"})
        if unknown:
            raise TypeError(f"SensitivityOptions() got an unexpected keyword argument {unknown[0]!r}.")
        self.sampler = sampler
        self.seed = numpy_seed("SensitivityOptions", key, shorthands.get("seed"))
        self.chunk_size = chunk_size
        self.n_bootstrap = n_bootstrap
        self.confidence = confidence

    def __check_init__(self):
        if self.sampler not in SAMPLERS:
            raise ValueError(f"SensitivityOptions: sampler must be one of {SAMPLERS}, got {self.sampler!r}.")
        for name, low in (("chunk_size", 1), ("n_bootstrap", 0)):
            check_int("SensitivityOptions", name, getattr(self, name), low)
        if not 0 < self.confidence < 1:
            raise ValueError(f"SensitivityOptions: confidence must be in (0, 1), got {self.confidence!r}.")


def _num_samples(owner: str, num_samples: Any, shorthands: dict[str, Any], shorthand: str,
                 allowed: tuple[str, ...] = ()) -> int:
    """`num_samples` or its `shorthand` (`n`, `num`) from `shorthands`; a `TypeError` for an
    unknown keyword or neither given, a `ValueError` for both or fewer than 1."""
    unknown = sorted(set(shorthands) - {shorthand, *allowed})
    if unknown:
        raise TypeError(f"{owner}() got an unexpected keyword argument {unknown[0]!r}.")
    value = one_of(owner, num_samples=num_samples, **{shorthand: shorthands.get(shorthand)}, default=None)
    if value is None:
        raise TypeError(f"{owner}() missing the number of samples num_samples.")
    check_int(owner, "num_samples", value, 1)
    return int(value)


def _bounds(bounds) -> np.ndarray:
    b = np.asarray(bounds, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] != 2 or b.shape[0] < 1:
        raise ValueError(f"bounds must be (d, 2) rows [low, high], got shape {b.shape}.")
    if not np.all(b[:, 1] > b[:, 0]):
        raise ValueError(f"bounds: every row needs high > low, got {b.tolist()}.")
    return b


def sample(
    bounds: Float[ArrayLike, "d 2"],
    num_samples: int | None = None,
    sampler: str = "sobol",
    key: PRNGKeyArray | int | None = None,
    **shorthands,
) -> Float[np.ndarray, "num_samples d"]:
    """`num_samples` points uniform on the box `bounds` (rows [low, high]), drawn by `sampler`
    (`"sobol"`, scrambled, `num_samples` rounded up to a power of 2; `"lhs"`; `"random"`),
    seeded by `key` (a `jax.random` key; the same key, the same points; an int is numpy's seed
    itself; default seed 0).

    **Keyword shorthands:** `n`: `num_samples`; `seed`: an int `key`.

    ```python
    theta = hj.sample([[0.5, 1.5], [5.0, 15.0]], num_samples=1024, key=jax.random.key(0))
    ```
    """
    n = _num_samples("sample", num_samples, shorthands, "n", allowed=("seed",))
    seed = numpy_seed("sample", key, shorthands.get("seed"))
    b = _bounds(bounds)
    d = b.shape[0]
    # scipy.stats takes about a second to import: imported here, `import hybridjax` does not pay it.
    from scipy.stats import qmc

    if sampler == "sobol":
        u = qmc.Sobol(d, scramble=True, seed=seed).random_base2(max(0, math.ceil(math.log2(n))))
    elif sampler == "lhs":
        u = qmc.LatinHypercube(d, seed=seed).random(n)
    elif sampler == "random":
        u = np.random.default_rng(seed).random((n, d))
    else:
        raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}.")
    return b[:, 0] + u * (b[:, 1] - b[:, 0])


def execution_model(
    system: HybridSystem,
    inputs: Callable[[Array], tuple[Any, Any]],
    output: Callable[[Any], Array],
    *,
    mode0: str | int = 0,
    t0: float = 0.0,
    t1: float = 1.0,
    **simulate_kwargs,
) -> Callable[[Array], Array]:
    """A model `thetas (m, d) -> outputs (m,) or (m, k)` from executions of `system`.

    `inputs(theta) -> (x0, args)` for one parameter vector (mapped over the rows);
    `output(sol)` reads the batched `Solution` of `simulate_batch` (leading axis m), e.g.
    `lambda sol: sol.num_events` or `lambda sol: sol.event_times[:, 0]`; integer outputs are
    converted to floats. `simulate_kwargs` go to `simulate_batch`.

    ```python
    model = hj.execution_model(ball, lambda th: (jnp.stack([th[0], 0.0]), {"g": th[1], "e": 0.8}),
                               lambda sol: sol.num_events, t1=1.5)
    ```
    """

    def model(thetas):
        x0, args = jax.vmap(inputs)(thetas)
        sol = simulate_batch(system, x0, mode0, t0, t1, args, args_batched=True, **simulate_kwargs)
        out = jnp.asarray(output(sol))
        return out.astype(thetas.dtype)

    return model


# Compiled chunk programs of recent calls, by (model, chunk rows, d, dtype): the same model
# evaluated again (another design, another estimator) does not compile again.
_COMPILED: dict = {}


def evaluate(
    model: Callable[[Array], Array], thetas: np.ndarray, chunk_size: int
) -> tuple[np.ndarray, float, float]:
    """`model` on the rows of `thetas` in chunks of `chunk_size` (one compiled program, the
    last chunk padded by repeating its last row); (outputs (N, k), run seconds, compile
    seconds: 0 where the program of an earlier call was reused). Only the outputs come back
    to the host."""
    thetas = np.asarray(thetas)
    total = thetas.shape[0]
    chunk = min(chunk_size, total)
    dtype = jnp.result_type(float)
    key = (model, chunk, thetas.shape[1], jnp.dtype(dtype))
    compiled = _COMPILED.pop(key, None)
    compile_s = time.perf_counter()
    if compiled is None:
        compiled = jax.jit(model).lower(jax.ShapeDtypeStruct((chunk, thetas.shape[1]), dtype)).compile()
    compile_s = time.perf_counter() - compile_s
    _COMPILED[key] = compiled
    while len(_COMPILED) > 8:
        _COMPILED.pop(next(iter(_COMPILED)))
    outs = []
    start = time.perf_counter()
    for lo in range(0, total, chunk):
        idx = np.minimum(np.arange(lo, lo + chunk), total - 1)
        out = np.asarray(compiled(jnp.asarray(thetas[idx], dtype)))
        outs.append(out.reshape(chunk, -1)[: min(chunk, total - lo)])
    return np.concatenate(outs), time.perf_counter() - start, compile_s


class SobolResult(NamedTuple):
    """First-order and total Sobol' indices, per output (rows) and parameter (columns).

    - `first_order`, `total`: (k, d); `first_order_interval`, `total_interval`: (k, d, 2)
      bootstrap percentile intervals at `confidence`.
    - `variance`: (k,) the output's variance; `n`: base samples; `evaluations`: n (d + 2).
    - `run_s`, `executions_per_s`: the model's run time (compile excluded); `compile_s`.
    """

    names: tuple[str, ...]
    first_order: np.ndarray
    total: np.ndarray
    first_order_interval: np.ndarray
    total_interval: np.ndarray
    variance: np.ndarray
    confidence: float
    n: int
    evaluations: int
    run_s: float
    executions_per_s: float
    compile_s: float

    def table(self, outputs: tuple[str, ...] | None = None) -> str:
        """A Markdown table: output, parameter, S_i and S_Ti with their intervals."""
        outputs = outputs or tuple(f"y[{j}]" for j in range(self.first_order.shape[0]))
        pct = f"{100 * self.confidence:g}%"
        lines = [f"| output | parameter | first order | {pct} interval | total | {pct} interval |",
                 "| --- | --- | --- | --- | --- | --- |"]
        for j, out in enumerate(outputs):
            for i, name in enumerate(self.names):
                lo, hi = self.first_order_interval[j, i]
                tlo, thi = self.total_interval[j, i]
                lines.append(f"| {out} | {name} | {self.first_order[j, i]:.4f} | [{lo:.4f}, {hi:.4f}] | "
                             f"{self.total[j, i]:.4f} | [{tlo:.4f}, {thi:.4f}] |")
        return "\n".join(lines)


def _names(names, d: int) -> tuple[str, ...]:
    if names is None:
        return tuple(f"theta[{i}]" for i in range(d))
    names = tuple(names)
    if len(names) != d:
        raise ValueError(f"names has {len(names)} entries for {d} parameters.")
    return names


def _row_terms(fA: np.ndarray, fB: np.ndarray, fAB: np.ndarray) -> np.ndarray:
    """Per row (n, k (4 + 3 d)): f(A), f(B), their squares, f(B) D_i, D_i and D_i^2, with
    D_i = f(A_B^i) - f(A); the outputs shifted by their overall mean first (the indices do not
    change; the variance is then a difference of small numbers). The estimators are functions
    of these terms' means, so a bootstrap resample costs one gather and one sum."""
    shift = np.concatenate([fA, fB]).mean(axis=0)
    fA, fB, fAB = fA - shift, fB - shift, fAB - shift
    n = fA.shape[0]
    D = fAB - fA[None]  # (d, n, k)
    per_i = [np.moveaxis(x, 0, 1).reshape(n, -1) for x in (fB[None] * D, D, D**2)]
    return np.concatenate([fA, fB, fA**2, fB**2, *per_i], axis=1)


def _indices_from_means(means: np.ndarray, d: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    mA, mB, mA2, mB2 = (means[..., j * k : (j + 1) * k] for j in range(4))
    rest = means[..., 4 * k :].reshape(means.shape[:-1] + (3, d, k))
    mBD, mD, mD2 = rest[..., 0, :, :], rest[..., 1, :, :], rest[..., 2, :, :]
    f0 = (mA + mB) / 2
    V = (mA2 + mB2) / 2 - f0**2
    Vs = np.where(V > 0, V, np.nan)[..., None, :]
    S = (mBD - f0[..., None, :] * mD) / Vs
    ST = 0.5 * mD2 / Vs
    return np.swapaxes(S, -1, -2), np.swapaxes(ST, -1, -2)


def saltelli_estimates(fA: np.ndarray, fB: np.ndarray, fAB: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(S, S_T), each (k, d), from f(A), f(B) (n, k) and f(A_B^i) (d, n, k), A_B^i being A with
    column i from B: V = Var[f(A), f(B)], S_i = mean((f(B) - f0) (f(A_B^i) - f(A))) / V and
    S_Ti = mean((f(A) - f(A_B^i))^2) / (2 V) (Saltelli et al. 2010; Jansen). f(B) is centred
    on f0 = mean[f(A), f(B)], which leaves the estimator's expectation unchanged
    (E[f(A_B^i) - f(A)] = 0) and lowers its variance where the output's mean is large."""
    d, _, k = fAB.shape
    return _indices_from_means(_row_terms(fA, fB, fAB).mean(axis=0), d, k)


def sobol_indices(
    model: Callable[[Array], Array],
    bounds: Float[ArrayLike, "d 2"],
    num_samples: int | None = None,
    *,
    names: tuple[str, ...] | None = None,
    options: SensitivityOptions = SensitivityOptions(),
    **shorthands,
) -> SobolResult:
    r"""First-order and total Sobol' indices of `model`'s outputs, Saltelli's scheme.

    S_i = Var(E[Y | theta_i]) / Var(Y), S_Ti = E[Var(Y | theta_{~i})] / Var(Y). Two independent
    samples A, B of n = `num_samples` rows (rounded up to a power of 2 with the Sobol' sampler; one
    2d-dimensional design split in two) and the d matrices
    A_B^i (A with column i from B): n (d + 2) evaluations, in chunks. Estimators: S_i =
    mean((f(B) - f0) (f(A_B^i) - f(A))) / V, S_Ti = mean((f(A) - f(A_B^i))^2) / (2 V) (Saltelli et
    al. 2010). Intervals: percentiles of the estimates over `n_bootstrap` resamples of the n
    rows. Valid for discontinuous and discrete outputs (event counts, final modes).

    **Keyword shorthand:** `n`: `num_samples` (also as the third positional argument).
    """
    if not isinstance(options, SensitivityOptions):
        raise TypeError(f"options must be a SensitivityOptions, got {type(options).__name__}.")
    n = _num_samples("sobol_indices", num_samples, shorthands, "n")
    b = _bounds(bounds)
    d = b.shape[0]
    both = sample(np.concatenate([b, b]), n, options.sampler, options.seed)
    if options.sampler == "lhs":  # two independent Latin hypercubes
        both = np.concatenate([both[:, :d], sample(b, n, "lhs", options.seed + 1)], axis=1)
    A, B = both[:, :d], both[:, d:]
    m = A.shape[0]
    AB = np.repeat(A[None], d, axis=0)
    AB[np.arange(d), :, np.arange(d)] = B.T
    out, run_s, compile_s = evaluate(model, np.concatenate([A, B, AB.reshape(d * m, d)]), options.chunk_size)
    fA, fB, fAB = out[:m], out[m : 2 * m], out[2 * m :].reshape(d, m, -1)
    k = fA.shape[1]
    terms = _row_terms(fA, fB, fAB)
    S, ST = _indices_from_means(terms.mean(axis=0), d, k)
    rng = np.random.default_rng(options.seed)
    boot = np.array([terms[rng.integers(0, m, m)].mean(axis=0) for _ in range(options.n_bootstrap)])
    boot_S, boot_T = _indices_from_means(boot, d, k) if options.n_bootstrap else ([], [])
    alpha = 100 * (1 - options.confidence) / 2
    if options.n_bootstrap:
        S_int = np.moveaxis(np.nanpercentile(np.array(boot_S), [alpha, 100 - alpha], axis=0), 0, -1)
        T_int = np.moveaxis(np.nanpercentile(np.array(boot_T), [alpha, 100 - alpha], axis=0), 0, -1)
    else:
        S_int = T_int = np.full(S.shape + (2,), np.nan)
    evals = out.shape[0]
    V = np.var(np.concatenate([fA, fB]), axis=0)
    return SobolResult(_names(names, d), S, ST, S_int, T_int, V, options.confidence, m, evals, run_s,
                       evals / max(run_s, 1e-12), compile_s)


class MorrisResult(NamedTuple):
    """Morris screening: elementary effects in the unit hypercube, per output and parameter.

    - `mu`, `mu_star`, `sigma`: (k, d) mean, mean of absolute values and standard deviation
      (ddof 1) of the elementary effects.
    - `elementary_effects`: (r, k, d); `points`: (r, d + 1, d) each trajectory's parameter
      vectors; `delta`: the step in the unit hypercube.
    """

    names: tuple[str, ...]
    mu: np.ndarray
    mu_star: np.ndarray
    sigma: np.ndarray
    elementary_effects: np.ndarray
    points: np.ndarray
    delta: float
    run_s: float


def morris_trajectories(d: int, r: int, levels: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`r` one-at-a-time trajectories on the `levels`-level grid of [0, 1]^d: (points (r, d+1,
    d), the coordinate changed at each step (r, d), its sign (r, d)). Each starts at a random
    grid point and moves each coordinate once, in random order, by +-delta,
    delta = levels / (2 (levels - 1))."""
    rng = np.random.default_rng(seed)
    delta = levels / (2 * (levels - 1))
    base = rng.integers(0, levels // 2, (r, d)) / (levels - 1)
    sign = rng.choice([-1.0, 1.0], (r, d))
    start = np.where(sign > 0, base, base + delta)
    order = np.argsort(rng.random((r, d)), axis=1)
    pts = np.empty((r, d + 1, d))
    pts[:, 0] = start
    for s in range(d):
        pts[:, s + 1] = pts[:, s]
        j = order[:, s]
        pts[np.arange(r), s + 1, j] += sign[np.arange(r), j] * delta
    return pts, order, sign


def morris_effects(
    model: Callable[[Array], Array],
    bounds: Float[ArrayLike, "d 2"],
    r: int,
    *,
    levels: int = 4,
    names: tuple[str, ...] | None = None,
    options: SensitivityOptions = SensitivityOptions(),
) -> MorrisResult:
    r"""Morris elementary effects of `model`'s outputs: r (d + 1) evaluations.

    With theta = low + u (high - low), u on a `levels`-level grid, each trajectory changes
    one coordinate at a time by +-delta (delta = levels / (2 (levels - 1))); the elementary
    effect of parameter i is EE_i = [f(u + delta e_i) - f(u)] / delta, in output units per
    unit of the parameter's range. mu* = mean |EE_i| ranks the parameters (Campolongo et
    al. 2007); sigma shows interactions or non-linearity.
    """
    if isinstance(levels, bool) or not isinstance(levels, int) or levels < 2 or levels % 2:
        raise ValueError(f"levels must be an even int >= 2, got {levels!r}.")
    if isinstance(r, bool) or not isinstance(r, int) or r < 2:
        raise ValueError(f"r must be an int >= 2, got {r!r}.")
    b = _bounds(bounds)
    d = b.shape[0]
    u, order, sign = morris_trajectories(d, r, levels, options.seed)
    theta = b[:, 0] + u * (b[:, 1] - b[:, 0])
    out, run_s, _ = evaluate(model, theta.reshape(r * (d + 1), d), options.chunk_size)
    f = out.reshape(r, d + 1, -1)
    delta = levels / (2 * (levels - 1))
    ee = np.empty((r, f.shape[2], d))
    for s in range(d):
        j = order[:, s]
        ee[np.arange(r), :, j] = (f[:, s + 1] - f[:, s]) / (sign[np.arange(r), j] * delta)[:, None]
    return MorrisResult(_names(names, d), ee.mean(0), np.abs(ee).mean(0), ee.std(0, ddof=1), ee,
                        theta, delta, run_s)


class DGSMResult(NamedTuple):
    """Derivative-based global sensitivity measures, per output (rows) and parameter.

    - `nu`: (k, d) E[(df/dtheta_i)^2]; `nu_stderr`: its Monte Carlo standard error.
    - `total_bound`: (k, d) nu_i (high_i - low_i)^2 / (pi^2 V), an upper bound on the total
      Sobol' index of a uniform parameter (Sobol' and Kucherenko 2009).
    - `variance`: (k,) the output's variance over the same sample; `gradients`: (n, k, d).
    """

    names: tuple[str, ...]
    nu: np.ndarray
    nu_stderr: np.ndarray
    total_bound: np.ndarray
    variance: np.ndarray
    gradients: np.ndarray
    run_s: float


_GRADIENT_MODELS: dict = {}


def _with_gradients(model):
    """thetas (m, d) -> [outputs (m, k), gradients (m, k d)]: one reverse pass per output of
    the chunk's summed outputs (each row's output depends on that row alone). Kept per model,
    so that its compiled program is reused."""
    if model in _GRADIENT_MODELS:
        return _GRADIENT_MODELS[model]

    def both(thetas):
        out, vjp = jax.vjp(model, thetas)
        out2 = out.reshape(out.shape[0], -1)
        grads = []
        for j in range(out2.shape[1]):
            ct = jnp.zeros_like(out2).at[:, j].set(1.0).reshape(out.shape)
            grads.append(vjp(ct)[0])
        return jnp.concatenate([out2, jnp.stack(grads, axis=1).reshape(out.shape[0], -1)], axis=1)

    _GRADIENT_MODELS[model] = both
    while len(_GRADIENT_MODELS) > 8:
        _GRADIENT_MODELS.pop(next(iter(_GRADIENT_MODELS)))
    return both


def dgsm(
    model: Callable[[Array], Array],
    bounds: Float[ArrayLike, "d 2"],
    num_samples: int | None = None,
    *,
    names: tuple[str, ...] | None = None,
    options: SensitivityOptions = SensitivityOptions(),
    **shorthands,
) -> DGSMResult:
    r"""Derivative-based global sensitivity measures nu_i = E[(df/dtheta_i)^2], from the exact
    derivatives of `model` (reverse mode through the executions: event times are
    differentiated by the implicit function theorem), at `num_samples` points drawn by
    `options` (shorthand: `n`, also as the third positional argument).

    Each row's output depends on its own parameters only, so one gradient of the sum of a
    chunk's outputs gives every row's gradient. A discrete output (an event count) has zero
    derivative almost everywhere: its nu is 0 whatever its Sobol' indices; use
    `sobol_indices` for it.
    """
    n = _num_samples("dgsm", num_samples, shorthands, "n")
    b = _bounds(bounds)
    d = b.shape[0]
    theta = sample(b, n, options.sampler, options.seed)

    res, run_s, _ = evaluate(_with_gradients(model), theta, options.chunk_size)
    m = res.shape[0]
    k = res.shape[1] // (d + 1)
    f, grads = res[:, :k], res[:, k:].reshape(m, k, d)
    sq = grads**2
    nu, se = sq.mean(0), sq.std(0, ddof=1) / math.sqrt(m)
    V = np.var(f, axis=0)
    bound = nu * (b[:, 1] - b[:, 0]) ** 2 / (np.pi**2 * np.where(V > 0, V, np.nan)[:, None])
    return DGSMResult(_names(names, d), nu, se, bound, V, grads, run_s)
