"""The package installs: a wheel built from this tree, installed into a fresh virtual environment (its
dependencies taken from this environment, nothing downloaded), maps a Replica-layout folder from another working
directory with the per-format configuration that ships inside the wheel."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest
import yaml

from tests.sources.fixtures import write_replica

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _copy_tree(dest: Path) -> Path:
    """The files git would commit (tracked and untracked-but-not-ignored), symlinks kept, copied to `dest`: the
    build then writes its build/ and egg-info there, not into the checkout."""
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, capture_output=True,
                            check=True).stdout.decode().split("\0")  # fmt: skip
    for rel in filter(None, listed):
        src, dst = ROOT / rel, dest / rel
        if not src.exists() and not src.is_symlink():
            continue  # deleted in the work tree
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.is_symlink():
            os.symlink(os.readlink(src), dst)
        else:
            shutil.copy2(src, dst)
    return dest


def _run(cmd: list[str], cwd: Path, env: dict[str, str] | None = None) -> str:
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, f"{' '.join(cmd)} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
    return proc.stdout


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """bin/ of a fresh venv holding only the h2viz wheel; this environment's packages serve its dependencies."""
    tmp = tmp_path_factory.mktemp("packaging")
    src = _copy_tree(tmp / "src")
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w",
          str(tmp / "dist"), str(src)], cwd=tmp)  # fmt: skip
    (wheel,) = (tmp / "dist").glob("h2viz-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    shipped = {"h2viz/configs/default.yaml", "h2viz/configs/replica.yaml", "h2viz/assets/synthetic_room.yaml"}
    assert shipped <= set(names)
    _run([sys.executable, "-m", "venv", str(tmp / "venv")], cwd=tmp)
    bin_dir = tmp / "venv" / "bin"
    purelib = _run([str(bin_dir / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                   cwd=tmp).strip()  # fmt: skip
    # the dependencies from this environment, after the venv's own site-packages (its h2viz wins)
    Path(purelib, "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run([str(bin_dir / "python"), "-m", "pip", "install", "--no-deps", "--no-index", str(wheel)], cwd=tmp)
    return bin_dir


def test_the_installed_wheel_maps_a_replica_folder_with_the_replica_config(installed: Path, tmp_path: Path) -> None:
    data = write_replica(tmp_path / "room0", n=6, broken=False).root
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    where = _run([str(installed / "python"), "-c", "import h2viz, sys; print(h2viz.__file__)"], elsewhere, env)
    assert str(installed.parent) in where and str(ROOT) not in where  # the wheel's copy, not this checkout
    tiny = ["--set", "mapping.runtime.kernels=torch", "--set", "mapping.runtime.device=cpu", "--set",
            "mapping.representation.hash_log2_size=12",
            "--set", "mapping.representation.min_points_per_voxel=1", "--set", "mapping.sampling.rays_per_iter=256",
            "--set", "mapping.optimization.max_iters=2", "--set", "eval.n_interpolate=0",
            "--set", "eval.n_extrapolate=0"]  # fmt: skip
    _run([str(installed / "h2viz"), "map", "--data", str(data), "--out", "run", "-q", *tiny], elsewhere, env)
    cfg = yaml.safe_load((elsewhere / "run" / "config.yaml").read_text())
    replica = yaml.safe_load((ROOT / "configs" / "replica.yaml").read_text())["source"]
    assert cfg["source"]["format"] == "replica"
    assert cfg["source"]["intrinsics"] == replica["intrinsics"] and cfg["source"]["depth_max_m"] == 12.0
    assert (elsewhere / "run" / "mesh.ply").is_file() and (elsewhere / "run" / "checkpoint.pt").is_file()
    backend = _run([str(installed / "python"), "-c",
                    "from h2viz.mapping.backend import resolve_backend; print(resolve_backend('auto', 'cpu').name)"],
                   elsewhere, env)  # fmt: skip
    assert backend.strip() == "numba"  # the compiled kernels ship too
