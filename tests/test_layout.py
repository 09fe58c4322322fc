"""The project's shape: one direction of dependency, no import circles, small modules.

CLI -> experiments/benchmarks -> {mitsuba_wai, restoration} -> wai_core. Imports are read from
the source (every ``import`` statement, inside functions too), so a lazy import counts; those
under ``if TYPE_CHECKING:`` are for annotations only, never run, and do not.
"""

from __future__ import annotations

import ast
import subprocess
import sys

import pytest

from tests.conftest import ROOT

PACKAGES = ("wai_core", "mitsuba_wai", "restoration", "wai")
CLI_MODULES = {"wai.cli", "wai.render_cli", "wai.restore_cli", "wai.demo"}
MAX_LINES = 600


def _module_name(path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _modules() -> dict[str, object]:
    return {
        _module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))
    }


MODULES = _modules()


def _imports(name: str) -> set[str]:
    """Project modules that module ``name`` imports (resolved to modules, not names)."""
    tree = ast.parse(MODULES[name].read_text())
    for node in ast.walk(tree):  # annotations' imports are never run: not a dependency
        if (isinstance(node, ast.If) and isinstance(node.test, ast.Name)
                and node.test.id == "TYPE_CHECKING"):
            node.body = []
    found = set()
    package = name if MODULES[name].name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1]
                                + ([base] if base else []))
            targets = [f"{base}.{a.name}" for a in node.names] + [base]
        for t in targets:
            while t and t not in MODULES:
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


GRAPH = {name: _imports(name) for name in MODULES}


def _layer(name: str) -> str:
    return name.split(".")[0]


@pytest.mark.parametrize(
    "lower, upper",
    [("wai_core", ("mitsuba_wai", "restoration", "wai")), ("mitsuba_wai", ("restoration", "wai")),
     ("restoration", ("mitsuba_wai", "wai"))],
)
def test_dependencies_point_one_way(lower, upper):
    wrong = {
        (m, d) for m, deps in GRAPH.items() if _layer(m) == lower for d in deps
        if _layer(d) in upper
    }
    assert not wrong


def test_no_import_circles():
    # Depth-first search for a back edge; an import of a package's own __init__ from inside
    # the package is the package importing itself, not a circle.
    state: dict[str, int] = {}
    cycle: list[str] = []

    def visit(node: str, path: list[str]) -> bool:
        state[node] = 1
        for dep in GRAPH[node]:
            if node.startswith(dep + "."):
                continue
            if state.get(dep) == 1:
                cycle.extend(path[path.index(dep):] + [dep])
                return True
            if state.get(dep) is None and visit(dep, path + [dep]):
                return True
        state[node] = 2
        return False

    for name in GRAPH:
        if state.get(name) is None and visit(name, [name]):
            break
    assert not cycle, " -> ".join(cycle)


def test_experiments_and_benchmarks_import_no_cli_module():
    users = [m for m in GRAPH if m.startswith(("wai.experiments", "wai.bench"))]
    assert users
    assert not {(m, d) for m in users for d in GRAPH[m] if d in CLI_MODULES}


def test_no_module_is_over_600_lines():
    long = {n: len(p.read_text().splitlines()) for n, p in MODULES.items()}
    assert not {n: k for n, k in long.items() if k > MAX_LINES}


def test_restoration_imports_without_the_renderer():
    code = (
        "import sys, restoration, wai_core; "
        "bad = [m for m in sys.modules if m.split('.')[0] in ('mitsuba', 'drjit', 'mitsuba_wai')];"
        "print(bad); sys.exit(1 if bad else 0)"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert run.returncode == 0, run.stdout + run.stderr


@pytest.mark.parametrize("package", PACKAGES[:3])
def test_every_public_name_is_importable_and_documented(package):
    mod = __import__(package)
    assert mod.__all__, f"{package} exports nothing"
    for name in mod.__all__:
        obj = getattr(mod, name)
        if callable(obj):
            assert obj.__doc__, f"{package}.{name} has no docstring"
