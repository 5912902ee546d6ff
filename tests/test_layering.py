"""The dashboard's side never loads torch: importing h2viz.viewer and h2viz.worker (every module of both) leaves
torch, and numba, out of the process; only the mapper, made by whoever starts the worker, brings them."""

from __future__ import annotations

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
