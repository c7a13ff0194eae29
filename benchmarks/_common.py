"""Shared benchmark helpers: machine/version record, warm-up-then-time, JSON output."""

import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import jax


def machine_info() -> dict:
    import diffrax
    import equinox
    import numpy

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return dict(
        cpu=cpu, cores=os.cpu_count(), platform=platform.platform(),
        device=str(jax.devices()[0]), device_kind=jax.devices()[0].device_kind, num_devices=len(jax.devices()), python=platform.python_version(),
        jax=jax.__version__, diffrax=diffrax.__version__, equinox=equinox.__version__,
        numpy=numpy.__version__, x64=bool(jax.config.jax_enable_x64),
        xla_flags=os.environ.get("XLA_FLAGS", ""),
    )


def timed(fn, *args, repeat: int = 3):
    """(compile_s, run_s, out): first call minus best later call; best of `repeat` runs."""
    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t)
    return max(first - best, 0.0), best, out


def compiled_and_alternated(fns: dict, x, rounds: int) -> tuple[dict, dict]:
    """Each jitted `fns[label]` compiled for `x` (trace + lower + XLA compile) and run once, then
    all run in turn for `rounds` rounds, the order reversed every other round so that the
    machine's drift touches each alike: ({label: (output, compile_s)}, {label: best run_s})."""
    compiled, outs = {}, {}
    for label, fn in fns.items():
        t = time.perf_counter()
        compiled[label] = fn.trace(x).lower().compile()
        compile_s = time.perf_counter() - t
        outs[label] = (jax.block_until_ready(compiled[label](x)), compile_s)
    best = dict.fromkeys(compiled, float("inf"))
    for r in range(rounds):
        for label in (list(compiled) if r % 2 == 0 else list(compiled)[::-1]):
            t = time.perf_counter()
            jax.block_until_ready(compiled[label](x))
            best[label] = min(best[label], time.perf_counter() - t)
    return outs, best


def write_json(name: str, payload: dict) -> Path:
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    path = out / f"{name}.json"
    path.write_text(json.dumps(payload, indent=2, default=float))
    return path


def run_per_setting(script: str, settings: dict[str, str], env: dict[str, str] | None = None) -> dict:
    """`python script --one` once per XLA setting ({name: XLA_FLAGS to add}), each in a fresh
    process (JAX reads XLA_FLAGS once, when it creates its CPU backend), with the environment
    variables `env` added: {name: the JSON that the run printed on its last line}."""
    out = {}
    for name, flags in settings.items():
        proc_env = dict(os.environ, **(env or {}),
                        XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " " + flags).strip())
        res = subprocess.run([sys.executable, script, "--one"], env=proc_env, capture_output=True, text=True,
                             check=True, cwd=os.path.dirname(os.path.abspath(script)))
        out[name] = json.loads(res.stdout.splitlines()[-1])
    return out
