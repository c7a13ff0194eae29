"""The package's layers: each module imports only from its own layer and the layers before it.

The layers, upstream first (docs: Architecture), are the private subpackages of `hybridjax`.
Data flows definition -> validation -> solve -> solution -> analysis; the `Solution` type sits
before the entry points that build it (as diffrax's `_solution.py` before `_integrate.py`).
The public modules (`examples`, `plot`) and the package root come last: they may import
anything, and nothing in a subpackage may import them.
"""

import ast
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "hybridjax"

LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("foundation", ("_core",)),
    ("definition and validation", ("_definition",)),
    ("step", ("_step",)),
    ("rules", ("_rules",)),
    ("engines", ("_engines",)),
    ("solution", ("_solution",)),
    ("solve", ("_solve",)),
    ("analysis", ("_analysis",)),
    ("estimation", ("_estimation",)),
    ("trajectory optimisation", ("_optimise",)),
    ("scenes", ("_scenes",)),
    ("public modules", ("examples", "plot", "_demo")),
    ("package", ("__init__", "__main__")),
]
LAYER_OF = {m: i for i, (_, mods) in enumerate(LAYERS) for m in mods}


def _modules() -> list[str]:
    """Every module of the package, dotted from `hybridjax` (`_rules.start`, `examples`)."""
    out = []
    for p in sorted(PACKAGE.rglob("*.py")):
        parts = p.relative_to(PACKAGE).with_suffix("").parts
        out.append(".".join(parts))
    return out


def _top(module: str) -> str:
    """The layer's key of a module: its subpackage, or the module at the top."""
    return module.split(".")[0]


def _imports(module: str, source: str | None = None) -> set[str]:
    """The package modules (or subpackages) `module` imports, anywhere in it (functions included),
    dotted from `hybridjax`; `source` in place of the module's file where given."""
    path = PACKAGE / (module.replace(".", "/") + ".py")
    tree = ast.parse(path.read_text() if source is None else source)
    package = module.split(".")[:-1]  # the package holding `module`
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level == 0:
                if node.module == "hybridjax":
                    out.update(a.name for a in node.names)
                elif node.module and node.module.startswith("hybridjax."):
                    out.add(node.module[len("hybridjax.") :])
                continue
            base = package[: len(package) - (node.level - 1)]
            if node.module is None:  # from . import x, from .. import x
                out.update(".".join([*base, a.name]) for a in node.names)
            else:
                out.add(".".join([*base, node.module]))
        elif isinstance(node, ast.Import):
            out.update(a.name[len("hybridjax.") :] for a in node.names if a.name.startswith("hybridjax."))
    return out


def _layer(module: str) -> int:
    return LAYER_OF[_top(module)]


@pytest.mark.parametrize("module", _modules())
def test_no_module_imports_from_a_later_layer(module):
    bad = sorted(m for m in _imports(module) if _layer(m) > _layer(module))
    assert not bad, (
        f"hybridjax.{module} ({LAYERS[_layer(module)][0]}) imports {bad}, of a later layer "
        f"({[LAYERS[_layer(m)][0] for m in bad]}): move the shared piece upstream"
    )


def test_every_module_is_in_a_layer():
    assert {_top(m) for m in _modules()} <= set(LAYER_OF)


def test_the_import_parser_sees_every_form():
    # The check above is only as good as `_imports`: `from ..x.y import z` (the engines import
    # the rules), `from .y import z` (within a subpackage) and `from . import x` (the package
    # root imports `examples`) are all seen.
    assert {"_rules.start", "_step.runge_kutta", "_definition.kernels"} <= _imports("_engines.batched")
    assert "_engines.lanes" in _imports("_engines.batched")
    assert "examples" in _imports("__init__")
    assert "_solution.dense" in _imports("_solution.solution")


def _cycle(graph: dict[str, set[str]]) -> list[str]:
    """An import cycle of `graph` (module -> the modules it imports), as the modules along it with
    the first repeated at the end; [] if there is none (depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(m):
        state[m] = 1
        path.append(m)
        for n in sorted(graph.get(m, ())):
            if state.get(n) == 1:
                return path[path.index(n) :] + [n]
            if n not in state and (found := visit(n)):
                return found
        state[m] = 2
        path.pop()
        return []

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return []


def test_the_cycle_search_finds_a_cycle_and_only_a_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) == []
    assert _cycle({"a": {"a"}}) == ["a", "a"]


def test_a_function_level_import_is_seen():
    source = "def f():\n    from .friction import friction_system\n    return friction_system\n"
    assert _imports("_scenes.scene", source) == {"_scenes.friction"}


def test_scenes_modules_have_no_import_cycle():
    # Module-level and function-level imports alike: a lazy import inside a function is a cycle too.
    scenes = [m for m in _modules() if _top(m) == "_scenes"]
    graph = {m: {i for i in _imports(m) if i in scenes} for m in scenes}
    assert len(scenes) >= 5 and graph["_scenes.friction"]
    cycle = _cycle(graph)
    assert not cycle, f"import cycle in hybridjax._scenes: {' -> '.join(cycle)}"


def _names_used(module: str) -> set[str]:
    tree = ast.parse((PACKAGE / (module.replace(".", "/") + ".py")).read_text())
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} | {
        n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)
    }


def _source(subpackage: str) -> str:
    return "\n".join(p.read_text() for p in sorted((PACKAGE / subpackage).glob("*.py")))


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
    "within_step",
    "stop_first",
    "detect_zeno",
    "zeno_completion",
)
# The step and the step-size rule (`_step.runge_kutta`): the per-execution engine calls them
# through `UnrolledERK` and `FastIController`.
SHARED_STEP = ("explicit_rk_step", "rk_error_estimate", "scaled_error", "pid_controller")


def test_both_engines_call_the_same_rule_functions():
    loop, batched = _names_used("_engines.loop"), _names_used("_engines.batched")
    step = _names_used("_step.runge_kutta")
    for name in SHARED_RULES:
        assert name in loop and name in batched, name
    for name in SHARED_STEP:
        assert name in batched and name in step, name
    assert "UnrolledERK" in loop or "UnrolledERK" in _names_used("_solve.simulate")
    # and no engine module keeps a copy of a rule's body under another name
    rules_src = _source("_rules")
    engines = {p.stem: p.read_text() for p in (PACKAGE / "_engines").glob("*.py")}
    for engine, src in engines.items():
        for line in ("tk <= t_min + tol", "jnp.nextafter(sg(t), jnp.inf)", "(D0 < 0) & (D1 > 0)"):
            assert line in rules_src and line not in src, (engine, line)


def test_import_leaves_the_optional_heavy_modules_to_the_functions_that_use_them():
    # scipy.stats (the samplers of `hj.sample`, about a second to import) and matplotlib
    # (`hybridjax.plot`) are imported by what uses them, and analysis, estimation, optimisation
    # (with optax) and scenes by the first use of one of their names: `import hybridjax` loads
    # none of them, and then `hj.Scene` loads the scenes.
    import subprocess
    import sys

    lazy = ("hybridjax._analysis", "hybridjax._estimation", "hybridjax._optimise", "hybridjax._scenes")
    code = ("import sys, hybridjax as hj\n"
            "def loaded(): return sorted(m for m in sys.modules if m.split('.')[0] in ('scipy', 'matplotlib', "
            f"'optax') or m.startswith({lazy!r}))\n"
            "print(loaded()); hj.Scene; print('hybridjax._scenes.scene' in loaded())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         timeout=120)
    assert out.stdout.split() == ["[]", "True"], out.stdout


def test_every_lazily_imported_name_is_its_modules_object_and_named_for_static_analysis():
    # `hybridjax.__getattr__` imports a name of `_LAZY` on first use; the `TYPE_CHECKING` block
    # names the same objects for type checkers and the docs (mkdocstrings reads the source).
    import ast
    import importlib

    import hybridjax as hj

    tree = ast.parse(pathlib.Path(hj.__file__).read_text())
    static = {(node.module, a.name) for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
              and any(isinstance(p, ast.If) and node in ast.walk(p) for p in tree.body) for a in node.names}
    lazy = {(module[1:], name) for module, names in hj._LAZY.items() for name in names}
    assert static == lazy
    for module, name in lazy:
        assert getattr(hj, name) is getattr(importlib.import_module(f"hybridjax.{module}"), name)
        assert name in dir(hj) and name in hj.__all__
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        hj.no_such_name  # noqa: B018
