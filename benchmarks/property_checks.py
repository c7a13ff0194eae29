"""Time of `hj.check_properties`: the first call (tracing and compiling its batched searches) and
later calls (new `args`, the compiled searches reused), on the examples and on rings of modes.

A ring of M modes: mode i has x' = 1 on the domain x <= 1 and one transition to mode i + 1
(mod M) with guard 1 - x and reset x -> 0: M achievable transitions, no gap, no overlap, no
reset into a guard. Each check is verified against that expectation (and the thermostat and the
ceiling against theirs) before it is timed.

    python benchmarks/property_checks.py      # prints a table, writes results/property_checks.json
"""

import time

import jax
import jax.numpy as jnp
from _common import machine_info, write_json

import hybridjax as hj

jax.config.update("jax_enable_x64", True)


def ring(m: int) -> hj.HybridSystem:
    modes = [
        hj.Mode(
            f"m{i}", lambda t, x, p: jnp.ones_like(x) * p["speed"], dim=1, domain=lambda t, x, p: 1.0 - x[0]
        )
        for i in range(m)
    ]
    trs = [
        hj.Transition(
            f"m{i}", f"m{(i + 1) % m}", guard=lambda t, x, p: 1.0 - x[0], reset=lambda t, x, p: 0.0 * x
        )
        for i in range(m)
    ]
    return hj.HybridSystem(modes, trs)


def cases():
    thermo_args = {"a": 0.5, "T_amb": 10.0, "P_heat": 15.0, "P_cool": 10.0, "s": 20.0}
    yield (
        "thermostat",
        hj.examples.thermostat(),
        thermo_args,
        {"s": 21.0},
        {m: (5.0, 35.0) for m in ("off", "heat", "cool")},
        lambda r: r.nonblocking and r.disjoint_guards and len(r.achievable_transitions) == 4,
    )
    yield (
        "ceiling_ball",
        hj.examples.ceiling_ball(),
        {"g": 9.8, "H": 2.0},
        {"H": 2.5},
        {"flight": (-5.0, 5.0), "contact": (-5.0, 5.0)},
        lambda r: r.max_chain_length == 2 and not r.cycles,
    )
    for m in (10, 20, 40):
        yield (
            f"ring of {m}",
            ring(m),
            {"speed": 1.0},
            {"speed": 2.0},
            {f"m{i}": (-1.0, 2.0) for i in range(m)},
            lambda r, m=m: len(r.achievable_transitions) == m and r.nonblocking and not r.chains,
        )


def main():
    rows = []
    for name, system, args, change, bounds, expected in cases():
        t = time.perf_counter()
        report = hj.check_properties(system, args, bounds=bounds)
        first = time.perf_counter() - t
        assert expected(report), (name, report)
        later = []
        for _ in range(3):
            t = time.perf_counter()
            again = hj.check_properties(system, {**args, **change}, bounds=bounds)
            later.append(time.perf_counter() - t)
        assert expected(again), (name, again)
        rows.append(
            dict(
                system=name,
                modes=system.num_modes,
                transitions=system.num_transitions,
                samples_per_mode=report.num_samples,
                first_call_s=first,
                later_call_s=min(later),
            )
        )
        print(
            f"{name:>14}: {system.num_modes:3d} modes, first call {first:6.2f} s, later calls {min(later):6.3f} s"
        )
    path = write_json("property_checks", dict(machine=machine_info(), rows=rows))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
