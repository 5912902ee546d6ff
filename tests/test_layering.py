"""The dashboard's side never loads torch: importing h2viz.viewer and h2viz.worker (every module of both) leaves
torch, and numba, out of the process; only the mapper, made by whoever starts the worker, brings them. The import
graph has no cycles, counting imports inside functions and the package `__init__` that every import runs, and the
mapping stages' packages depend on each other in one direction."""

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


def test_importing_h2viz_and_its_packages_loads_no_torch_until_a_public_name_is_used() -> None:
    assert _loaded_after_importing(["h2viz", "h2viz.mapping", "h2viz.sources", "h2viz.mapping.kernels"]) == []


def test_the_public_names_resolve() -> None:
    import h2viz
    import h2viz.mapping

    for package in (h2viz, h2viz.mapping):
        assert package.__all__ and all(getattr(package, name) is not None for name in package.__all__)
    assert h2viz.Mapper is h2viz.mapping.Mapper


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


def _packages_run_by(module: str, imported: str) -> set[str]:
    """The packages whose `__init__` importing `imported` runs first, leaving out `module`'s own packages (already
    being imported when `module` runs)."""
    parts = imported.split(".")
    return {".".join(parts[:i]) for i in range(1, len(parts))} - {module} - _ancestors(module)


def _ancestors(module: str) -> set[str]:
    parts = module.split(".")
    return {".".join(parts[:i]) for i in range(1, len(parts))}


def _graph() -> dict[str, set[str]]:
    paths = {}
    for path in (ROOT / "h2viz").rglob("*.py"):
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        paths[name] = path
    graph = {}
    for m, p in paths.items():
        deps = _imports(m, p, set(paths))
        graph[m] = deps | {pkg for d in deps for pkg in _packages_run_by(m, d) if pkg in paths}
    return graph


def test_the_import_graph_has_no_cycles_even_through_imports_inside_functions() -> None:
    graph = _graph()
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


def test_the_mapping_stages_depend_on_each_other_in_one_direction() -> None:
    """field <- sampling <- rendering, keyframes <- sampling, meshing <- field; kernels may use any stage's data
    types; no stage imports the mapper, the backend's kernels or another stage that imports it."""
    stage = {m: ".".join(m.split(".")[:3]) for m in _graph() if m.startswith("h2viz.mapping.")}
    graph: dict[str, set[str]] = {}
    for m, deps in _graph().items():
        if m in stage:
            graph.setdefault(stage[m], set()).update(stage[d] for d in deps if d in stage and stage[d] != stage[m])
    assert graph["h2viz.mapping.field"] == set()
    assert graph["h2viz.mapping.sampling"] == {"h2viz.mapping.field"}
    assert graph["h2viz.mapping.rendering"] == {"h2viz.mapping.field", "h2viz.mapping.sampling"}
    assert graph["h2viz.mapping.keyframes"] == {"h2viz.mapping.sampling"}
    assert graph["h2viz.mapping.meshing"] == {"h2viz.mapping.field"}
    stages = {"field", "sampling", "rendering", "keyframes", "meshing"}
    assert graph["h2viz.mapping.kernels"] <= {f"h2viz.mapping.{s}" for s in stages}
