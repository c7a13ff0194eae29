"""Monte Carlo over many executions: chunked, sharded across devices, streamed to the host.

Each chunk of executions is one call of a jitted `simulate_batch` (on CPU the batched engine,
or `vmap(simulate)` where it does not apply; on GPUs `vmap(simulate)`), its batch axis sharded
over `jax.devices()` with `jax.sharding` (GPUs, or CPU devices asked for with
`jax.config.update("jax_num_cpu_devices", N)` right after `import jax`): on CPU devices each
runs the batched loop on its part (`simulate_batch(devices=...)`); on GPUs XLA partitions the
vmapped loop along the sharded batch axis. After each chunk only small
per-execution results (status, events, final time/mode/state, Zeno time) come back to the
host, and running summaries are updated, so memory stays bounded however many executions run;
`keep="summary"` keeps nothing per execution.

Several hosts: start every process with `jax.distributed.initialize(...)` before calling
`monte_carlo`; `jax.devices()` then lists every host's devices, each chunk is sharded over all
of them, and each process reads back the rows of its own devices (pass a different `key` per
run, the same on every process).
"""

import dataclasses
import math
import sys
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import PRNGKeyArray

from .._core.names import one_of
from .._core.status import STATUS_NAMES, Status
from .._definition.system import HybridSystem
from .._solve.engines import AutoEngine, BatchedEngine, as_engine
from .._solve.simulator import Simulator, simulator_of


def wilson_interval(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion k/n (95% by default)."""
    if n == 0:
        return (0.0, 1.0)
    p = k / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


class _Running:
    """Streaming count, mean, variance (Welford/Chan), min and max of a quantity."""

    def __init__(self):
        self.n, self.mean, self.m2 = 0, 0.0, 0.0
        self.min, self.max = math.inf, -math.inf

    def update(self, x: np.ndarray) -> None:
        x = np.asarray(x, dtype=np.float64)
        x = x[np.isfinite(x)]
        if x.size == 0:
            return
        n_b, mean_b = x.size, float(np.mean(x))
        m2_b = float(np.sum((x - mean_b) ** 2))
        n = self.n + n_b
        delta = mean_b - self.mean
        self.mean += delta * n_b / n
        self.m2 += m2_b + delta * delta * self.n * n_b / n
        self.n = n
        self.min, self.max = min(self.min, float(np.min(x))), max(self.max, float(np.max(x)))

    def result(self) -> dict:
        std = math.sqrt(self.m2 / (self.n - 1)) if self.n > 1 else 0.0
        return dict(n=self.n, mean=self.mean if self.n else math.nan, std=std, min=self.min, max=self.max)


class MonteCarloResult(NamedTuple):
    """What `monte_carlo` returns.

    - `n`: executions run.
    - `per_execution`: dict of numpy arrays (status, num_events, final_time, final_mode,
      final_state, zeno_time), or None with `keep="summary"`. `status` holds the integer codes
      of `hj.Status` (`per_execution["status"] == hj.Status.ZENO` selects the Zeno executions).
    - `status_fractions`: {name: (fraction, (low, high))} with 95% Wilson intervals.
    - `zeno_time`, `num_events`: running statistics (n, mean, std, min, max).
    - `event_histogram`: counts of executions by number of events (index = events).
    - `run_s`, `compile_s` (0 where an earlier call's compiled program was reused),
      `executions_per_s`, `devices`, `chunks`.
    """

    n: int
    per_execution: dict | None
    status_counts: dict
    status_fractions: dict
    zeno_time: dict
    num_events: dict
    event_histogram: np.ndarray
    run_s: float
    compile_s: float
    executions_per_s: float
    devices: int
    chunks: int

    def table(self) -> str:
        lines = [f"{self.n} executions on {self.devices} device(s) in {self.chunks} chunk(s): "
                 f"{self.run_s:.2f} s (+ {self.compile_s:.2f} s compile), "
                 f"{self.executions_per_s:,.0f} executions/s",
                 f"{'status':<12} {'count':>10} {'fraction':>10}  95% interval"]
        for name, count in self.status_counts.items():
            if count:
                frac, (lo, hi) = self.status_fractions[name]
                lines.append(f"{name:<12} {count:>10} {frac:>10.5f}  [{lo:.5f}, {hi:.5f}]")
        z, e = self.zeno_time, self.num_events
        if z["n"]:
            lines.append(f"Zeno time: mean {z['mean']:.6g}, std {z['std']:.3g}, "
                         f"range [{z['min']:.6g}, {z['max']:.6g}] over {z['n']} executions")
        lines.append(f"events per execution: mean {e['mean']:.3f}, std {e['std']:.3f}, max {e['max']:.0f}")
        return "\n".join(lines)


def _progress_line(done: int, total: int, run_s: float) -> str:
    """The progress bar after `done` of `total` executions, which took `run_s` seconds of run
    time (the compile excluded): the time left is the run time per execution so far times the
    executions still to run.

    ```python
    _progress_line(200, 1000, 0.8)  # '[######      ...]  20.0% 200/1000 0.8 s run, 3.2 s left'
    ```
    """
    frac = done / total
    left = run_s / done * (total - done) if done > 0 else math.nan
    return (f"[{'#' * int(30 * frac):<30}] {100 * frac:5.1f}% {done}/{total} "
            f"{run_s:6.1f} s run, {left:6.1f} s left")


class _Progress:
    """One text progress bar for the whole run (stderr by default); silent when disabled. The
    compile is reported once, apart, and the time left estimated from run time only."""

    def __init__(self, total: int, enabled: bool, stream=None, clock=time.perf_counter):
        self.total, self.enabled, self.clock = total, enabled, clock
        self.stream = sys.stderr if stream is None else stream
        self.run_start = clock()

    def _write(self, text: str) -> None:
        if self.enabled:
            self.stream.write(text)
            self.stream.flush()

    def compiling(self) -> None:
        self._write("compiling the chunk program...")

    def compiled(self, compile_s: float | None) -> None:
        """Report the compile (None: an earlier call's program reused) and start the run clock."""
        what = "reused a compiled program" if compile_s is None else f"compiled in {compile_s:.2f} s"
        self._write(f"\r{what:<40}\n")
        self.run_start = self.clock()

    def update(self, done: int) -> None:
        self._write("\r" + _progress_line(done, self.total, self.clock() - self.run_start))
        if done >= self.total:
            self._write("\n")


# Compiled chunk programs of recent calls, by configuration (`_program_key`): a notebook that
# runs `monte_carlo` again on the same problem (another n, sampler or key) does not compile again.
_COMPILED: "OrderedDict[Any, Any]" = OrderedDict()
_COMPILED_MAX = 8


def _program_key(config: tuple, inputs) -> Any:
    """A hashable key of everything the chunk program depends on: the configuration (system,
    mode, t0, t1, devices, `simulate_batch` options; functions by identity, numbers by value)
    and the chunk's input shapes, dtypes and shardings. None where some part is not hashable
    (arrays in the system or options): such calls compile as before."""
    leaves, treedef = jax.tree_util.tree_flatten(inputs)
    key = (config, treedef, tuple((leaf.shape, leaf.dtype, leaf.sharding) for leaf in leaves))
    try:
        hash(key)
    except TypeError:
        return None
    return key


def _remember(key, compiled) -> None:
    if key is None:
        return
    _COMPILED[key] = compiled
    while len(_COMPILED) > _COMPILED_MAX:
        _COMPILED.popitem(last=False)


def _run_settings(simulator: Simulator | None, shorthands: dict[str, Any]) -> tuple[Simulator, list]:
    """The run's `Simulator` (from `simulator` or the keyword shorthands) and the devices its
    chunks are sharded over: the `devices` shorthand, else those of the simulator's
    `BatchedEngine`, else every device; the simulator's batched engine set to those devices."""
    batch = {name: shorthands.pop(name) for name in ("block", "lanes", "devices") if name in shorthands}
    batch = {name: value for name, value in batch.items() if value is not None}  # None: not given
    if simulator is not None and batch:
        raise ValueError(f"monte_carlo: simulator and {' and '.join(batch)} are the same option (the "
                         "simulator's BatchedEngine holds them); pass one of them.")
    sim = simulator_of("monte_carlo", simulator, shorthands)
    engine = as_engine(sim.engine, **batch)
    batched = engine.batched if isinstance(engine, AutoEngine) else engine
    batched = batched if isinstance(batched, BatchedEngine) else None
    wanted = batch.get("devices", batched.devices if batched is not None else None)
    available = jax.devices()
    if wanted is None:
        devices = list(available)
    elif isinstance(wanted, (int, np.integer)) and not isinstance(wanted, bool):
        if not 1 <= wanted <= len(available):
            raise ValueError(f"monte_carlo: devices={wanted}: between 1 and the {len(available)} device(s) "
                             f"of the default backend.")
        devices = list(available[:wanted])
    else:
        devices = list(wanted)
    if batched is not None:
        batched = dataclasses.replace(batched, devices=devices)
        engine = AutoEngine(batched=batched) if isinstance(engine, AutoEngine) else batched
    return dataclasses.replace(sim, engine=engine), devices


def monte_carlo(
    system: HybridSystem,
    sampler: Callable[[PRNGKeyArray, int], tuple[Any, Any]] | None = None,
    num_samples: int | None = None,
    *,
    x0: Any = None,
    args: Any = None,
    mode0: str | int = 0,
    t0: float = 0.0,
    t1: float = 1.0,
    key: PRNGKeyArray | None = None,
    chunk_size: int = 10_000,
    keep: str = "all",
    progress: bool = True,
    simulator: Simulator | None = None,
    **shorthands,
) -> MonteCarloResult:
    r"""Run many executions of `system` in chunks, sharded across devices; summarise them.

    Give either `sampler(key, m) -> (x0 of shape (m, n), args pytree with leading axis m)`
    with `num_samples` executions (chunk c samples with `jax.random.fold_in(key, c)`; `key` a
    `jax.random` key, default `jax.random.PRNGKey(0)`), or arrays `x0` (N, n) and `args` (a
    pytree whose leaves have leading axis N). Every chunk has the same shape (the last one is
    padded), so one compilation serves the run.

    Each chunk is one `simulator.batch(...)` call (`hj.Simulator`: solver, tolerances,
    `max_epochs`, Zeno options, engine; default `hj.Simulator()`): on the batched engine where
    it applies (explicit RK solvers), else as `jax.vmap(simulate)`. The chunk's batch axis is
    sharded over the devices of the simulator's `BatchedEngine` (`devices`: None, the default,
    every device of the default backend; an int, the first that many; or a list).

    Returns a `MonteCarloResult`: per-execution results (unless `keep="summary"`), the
    fraction of executions per status with 95% Wilson intervals, Zeno-time and event-count
    statistics, timings.

    The compiled chunk program is kept (the last 8, by configuration: system and simulator by
    equality, their functions by identity, chunk shapes, dtypes and shardings), so running
    `monte_carlo` again on the same problem with another `num_samples`, `sampler` or `key` does
    not compile again (`compile_s` 0). Python numbers in `t0`, `t1` and the simulator are part of
    the program: a changed one compiles a new one.

    With `progress=True` a bar on stderr reports the compile once, on its own line ("compiled
    in 3.40 s", or that a compiled program was reused), then the executions done, the run time
    and the time left, estimated from the run time per execution so far (the compile excluded).

    **Keyword shorthands** (passing one with the name it stands for is a `ValueError`):

    - `n`: `num_samples` (also as the third positional argument).
    - `simulate_batch`'s keywords (`solver`, `stepsize_controller`, `saveat`, `adjoint`,
      `engine`, `options` and its shorthands `max_epochs`, `max_steps`, `zeno`, ...):
      `simulator=hj.Simulator(...)` with them.
    - `block`, `lanes`, `devices`: the simulator's `BatchedEngine` (`engine="auto"` or
      `"batched"`), as in `simulate_batch`.

    !!! Example

        ```python
        ball = hj.examples.bouncing_ball()

        def sampler(key, m):
            h = jax.random.uniform(key, (m,), minval=0.5, maxval=1.5)
            return jnp.stack([h, jnp.zeros(m)], 1), {"g": jnp.full(m, 9.8), "e": jnp.full(m, 0.8)}

        res = hj.monte_carlo(ball, sampler, num_samples=10_000, mode0="flight", t1=4.0,
                             simulator=hj.Simulator(max_epochs=32))
        res.status_fractions["ZENO"]  # (fraction, (low, high))
        ```
    """
    if keep not in ("all", "summary"):
        raise ValueError(f"keep must be 'all' or 'summary', got {keep!r}.")
    if (sampler is None) == (x0 is None):
        raise ValueError("Give either a sampler (with num_samples) or arrays x0 (and args).")
    num_samples = one_of("monte_carlo", num_samples=num_samples, n=shorthands.pop("n", None), default=None)
    sim, devices = _run_settings(simulator, shorthands)
    if sampler is not None:
        if num_samples is None or num_samples < 1:
            raise ValueError("With a sampler, give the number of executions num_samples >= 1.")
        key = jax.random.PRNGKey(0) if key is None else key
        total = int(num_samples)
    else:
        x0 = np.asarray(x0)
        total = x0.shape[0]
    n_dev = len(devices)
    chunk = int(math.ceil(min(chunk_size, total) / n_dev) * n_dev)
    mesh = Mesh(np.asarray(devices), ("batch",))
    batch_sharding = NamedSharding(mesh, PartitionSpec("batch"))
    mode_index = system.mode_index(mode0)

    def run_chunk(x, a):
        sol = sim.batch(system, x, mode_index, t0, t1, a, args_batched=a is not None)
        return dict(status=sol.status_code, num_events=sol.num_events, final_time=sol.final_time,
                    final_mode=sol.final_mode, final_state=sol.final_state, zeno_time=sol.zeno_time)

    run_chunk = jax.jit(run_chunk)

    def chunk_inputs(c: int, m: int):
        if sampler is not None:
            xs, a = sampler(jax.random.fold_in(key, c), chunk)
            return jnp.asarray(xs), a
        lo = c * chunk
        idx = np.minimum(np.arange(lo, lo + chunk), total - 1)  # pad by repeating the last row
        a = None if args is None else jax.tree_util.tree_map(lambda v: np.asarray(v)[idx], args)
        return jnp.asarray(x0[idx]), a

    counts = np.zeros(len(STATUS_NAMES), dtype=np.int64)
    zeno_stats, event_stats = _Running(), _Running()
    hist = np.zeros(1, dtype=np.int64)
    kept: dict[str, list] = {}
    n_chunks = int(math.ceil(total / chunk))
    bar = _Progress(total, progress)
    compiled, compile_s, t_start = None, 0.0, time.perf_counter()
    for c in range(n_chunks):
        m = min(chunk, total - c * chunk)
        xs, a = chunk_inputs(c, m)
        xs = jax.device_put(xs, batch_sharding)
        a = jax.device_put(a, batch_sharding) if a is not None else None
        if compiled is None:
            # Compile ahead of time, once (every chunk has the same shapes and shardings), or
            # take the program an earlier call with the same configuration compiled.
            tc = time.perf_counter()
            bar.compiling()
            cache_key = _program_key((system, mode_index, t0, t1, tuple(devices), sim), (xs, a))
            compiled = _COMPILED.get(cache_key) if cache_key is not None else None
            if compiled is None:
                compiled = run_chunk.lower(xs, a).compile()
                compile_s = time.perf_counter() - tc
                _remember(cache_key, compiled)
                bar.compiled(compile_s)
            else:
                bar.compiled(None)
            t_start = time.perf_counter()
        out = compiled(xs, a)
        host = {k: np.asarray(jax.device_get(v))[:m] for k, v in out.items()}
        counts += np.bincount(host["status"], minlength=len(STATUS_NAMES))
        zeno_stats.update(host["zeno_time"][host["status"] == Status.ZENO])
        event_stats.update(host["num_events"])
        h = np.bincount(host["num_events"])
        if h.size > hist.size:
            hist = np.pad(hist, (0, h.size - hist.size))
        hist[: h.size] += h
        if keep == "all":
            for k, v in host.items():
                kept.setdefault(k, []).append(v)
        bar.update(min((c + 1) * chunk, total))
    run_s = time.perf_counter() - t_start
    per = {k: np.concatenate(v) for k, v in kept.items()} if keep == "all" else None
    status_counts = {name: int(counts[i]) for i, name in enumerate(STATUS_NAMES)}
    fractions = {name: (cnt / total, wilson_interval(cnt, total)) for name, cnt in status_counts.items()}
    return MonteCarloResult(
        n=total, per_execution=per, status_counts=status_counts, status_fractions=fractions,
        zeno_time=zeno_stats.result(), num_events=event_stats.result(), event_histogram=hist,
        run_s=run_s, compile_s=compile_s, executions_per_s=total / max(run_s, 1e-12),
        devices=n_dev, chunks=n_chunks,
    )
