"""The package's layers: each module imports only from its own layer and the layers before it.

The layers, upstream first (docs: Architecture). Data flows definition -> validation -> solve
-> solution -> analysis; the `Solution` type sits before the entry points that build it (as
diffrax's `_solution.py` before `_integrate.py`). A module not listed counts as analysis: it may
import anything, and nothing listed before analysis may import it.
"""

import ast
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "hybridjax"

LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("foundation", ("_status", "_transforms")),
    ("definition and validation", ("_validation", "_system")),
    ("kernels", ("_kernels",)),
    ("step", ("_fast_rk",)),
    ("rules", ("_rules", "_zeno")),
    ("engines", ("_loop", "_batched")),
    ("solution", ("_solution", "_dense")),
    ("solve", ("_eager", "_simulate", "_simulate_batch")),
    ("analysis", ("_saltation", "_periodic", "_montecarlo", "_presets", "examples", "plot", "_demo")),
    ("package", ("__init__", "__main__")),
]
ANALYSIS = next(i for i, (name, _) in enumerate(LAYERS) if name == "analysis")
LAYER_OF = {m: i for i, (_, mods) in enumerate(LAYERS) for m in mods}


def _modules() -> list[str]:
    return sorted(p.stem for p in PACKAGE.glob("*.py"))


def _imports(module: str) -> set[str]:
    """The package modules `module` imports, anywhere in it (functions included)."""
    tree = ast.parse((PACKAGE / f"{module}.py").read_text())
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level == 1 and node.module is None:  # from . import x
                out.update(a.name for a in node.names)
            elif node.level == 1:  # from ._x import y
                out.add(node.module.split(".")[0])
            elif node.level == 0 and node.module and node.module.startswith("hybridjax."):
                out.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            out.update(a.name.split(".")[1] for a in node.names if a.name.startswith("hybridjax."))
    return out & set(_modules())


def _layer(module: str) -> int:
    return LAYER_OF.get(module, ANALYSIS)


@pytest.mark.parametrize("module", _modules())
def test_no_module_imports_from_a_later_layer(module):
    bad = sorted(m for m in _imports(module) if _layer(m) > _layer(module))
    assert not bad, (
        f"hybridjax/{module}.py ({LAYERS[_layer(module)][0]}) imports {bad}, of a later layer "
        f"({[LAYERS[_layer(m)][0] for m in bad]}): move the shared piece upstream"
    )


def test_the_import_parser_sees_every_form():
    # The check above is only as good as `_imports`: `from ._x import y` (the engines import
    # the rules) and `from . import x` (the package root imports `examples`, the solution
    # `_dense`) are both seen.
    assert {"_rules", "_fast_rk", "_kernels"} <= _imports("_batched")
    assert "examples" in _imports("__init__")
    assert "_dense" in _imports("_solution")


def _names_used(module: str) -> set[str]:
    tree = ast.parse((PACKAGE / f"{module}.py").read_text())
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} | {
        n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)
    }


# The rules both engines call (`_rules`); the per-execution engine calls the detection rules
# through `first_crossings` / `dip_candidates`, the batched one through `dip_interval` on its
# unrolled sample axis.
SHARED_RULES = (
    "event_time_tol",
    "step_end",
    "epoch_start",
    "nonfinite_step",
    "step_stops",
    "dip_filter",
    "event_brackets",
    "first_event",
    "event_point",
    "blocks",
    "jump_outcome",
    "push_recent",
    "saved_in_step",
    "stop_first",
    "detect_zeno",
    "zeno_completion",
)
# The step and the step-size rule (`_fast_rk`): the per-execution engine calls them through
# `UnrolledERK` and `FastIController`.
SHARED_STEP = ("explicit_rk_step", "rk_error_estimate", "scaled_error", "pid_controller")


def test_both_engines_call_the_same_rule_functions():
    loop, batched, step = _names_used("_loop"), _names_used("_batched"), _names_used("_fast_rk")
    for name in SHARED_RULES:
        assert name in loop and name in batched, name
    for name in SHARED_STEP:
        assert name in batched and name in step, name
    assert "UnrolledERK" in loop or "UnrolledERK" in _names_used("_simulate")
    # and neither engine keeps a copy of a rule's body under another name
    rules_src = (PACKAGE / "_rules.py").read_text()
    for engine in ("_loop", "_batched"):
        src = (PACKAGE / f"{engine}.py").read_text()
        for line in ("tk <= t_min + tol", "jnp.nextafter(sg(t), jnp.inf)", "(D0 < 0) & (D1 > 0)"):
            assert line in rules_src and line not in src, (engine, line)
