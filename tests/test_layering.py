"""The dashboard's side never loads torch: importing h2viz.viewer and h2viz.worker (every module of both) leaves
torch, and numba, out of the process; only the mapper, made by whoever starts the worker, brings them."""

from __future__ import annotations

import ast
import json
import os
import pkgutil
import subprocess
import sys
from pathlib import Path

import h2viz.viewer
import h2viz.worker

ROOT = Path(__file__).resolve().parents[1]
PROBE = """
import importlib, json, sys
for name in sys.argv[1:]:
    importlib.import_module(name)
print(json.dumps(sorted(m for m in ("torch", "numba") if m in sys.modules)))
"""


def _modules(package: object) -> list[str]:
    return [m.name for m in pkgutil.iter_modules(package.__path__, package.__name__ + ".")]  # type: ignore[attr-defined]


def _loaded_after_importing(names: list[str]) -> list[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", PROBE, *names], capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_importing_the_viewer_and_the_worker_never_imports_torch() -> None:
    names = ["h2viz.viewer", "h2viz.worker", *_modules(h2viz.viewer), *_modules(h2viz.worker)]
    assert len(names) > 10
    assert _loaded_after_importing(names) == []


def test_the_probe_sees_torch_when_the_mapper_is_imported() -> None:
    """The check above can fail: importing the mapper does load torch."""
    assert "torch" in _loaded_after_importing(["h2viz.mapping.mapper"])


def _imports(module: str, path: Path, known: set[str]) -> set[str]:
    """h2viz modules that `module` imports at run time, anywhere in it (not under `if TYPE_CHECKING:`)."""
    tree = ast.parse(path.read_text())
    typing_only = {
        id(n)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
        for n in ast.walk(node)
    }
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("h2viz"):
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"  # `from h2viz.mapping import band` imports a module
                found.add(sub if sub in known else node.module)
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("h2viz")}
    return {m for m in found if m in known and m != module}


def test_the_import_graph_has_no_cycles_even_through_imports_inside_functions() -> None:
    paths = {}
    for path in (ROOT / "h2viz").rglob("*.py"):
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        paths[name] = path
    graph = {m: _imports(m, p, set(paths)) for m, p in paths.items()}
    state: dict[str, int] = {}  # 1 = on the current path, 2 = done

    def visit(m: str, trail: list[str]) -> None:
        state[m], path = 1, [*trail, m]
        for dep in sorted(graph[m]):
            assert state.get(dep) != 1, "import cycle: " + " -> ".join([*path[path.index(dep) :], dep])
            if dep not in state:
                visit(dep, path)
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])
    mapping = (ROOT / "h2viz" / "mapping").rglob("*.py")
    assert not [p.name for p in mapping if "import_module" in p.read_text()]  # no imports hidden in strings
