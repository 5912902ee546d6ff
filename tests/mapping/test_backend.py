"""The backend is chosen once from mapping.runtime.kernels and the device; with kernels: torch the whole pipeline (map,
mesh, render, export, checkpoint, resume) runs with numba import-blocked; on CUDA (skipped without one) likewise."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from h2viz.config import MappingConfig, SourceConfig, SyntheticConfig
from h2viz.errors import ConfigError
from h2viz.mapping.backend import resolve_backend
from h2viz.mapping.mapper import Mapper
from h2viz.sources.base import make_source
from tests.mapping.backends import FAST, needs_numba

ROOT = Path(__file__).resolve().parents[2]
TINY = [
    "--set", "source.synthetic.width=96", "--set", "source.synthetic.height=72",
    "--set", "source.synthetic.n_frames=80", "--set", "mapping.representation.min_points_per_voxel=1",
    "--set", "mapping.representation.hash_log2_size=15", "--set", "mapping.sampling.rays_per_iter=1024", "--set",
    "mapping.optimization.max_iters=5",
    "--set", "eval.n_points=20000", "--set", "eval.n_interpolate=3",
    "--set", "eval.n_extrapolate=2", "--set", "eval.render_downscale=1",
]  # fmt: skip


@needs_numba
def test_auto_on_the_cpu_resolves_to_the_numba_kernels_and_torch_to_none() -> None:
    assert FAST.name == "numba" and FAST.tensor_kernels is not None and FAST.array_kernels is not None
    reference = resolve_backend("torch", "cpu")
    assert reference.name == "torch" and reference.tensor_kernels is None and reference.array_kernels is None
    gpu = resolve_backend("auto", torch.device("cuda"))  # resolving does not touch the device
    assert gpu.name == "cuda" and gpu.tensor_kernels is None and gpu.array_kernels is FAST.array_kernels
    assert resolve_backend("torch", torch.device("cuda")).array_kernels is None
    assert FAST.cpu_kernels(torch.zeros(2)) is FAST.tensor_kernels
    assert FAST.cpu_kernels(torch.zeros(2), torch.zeros(2, device="meta")) is None  # a tensor off the CPU


def test_an_unknown_kernel_choice_names_the_setting_and_the_choices() -> None:
    with pytest.raises(ConfigError, match=r"mapping.runtime.kernels: unknown 'numba'.*'auto', 'torch'"):
        resolve_backend("numba", "cpu")


BLOCKED_RUN = """
import json, sys

class BlockNumba:
    def find_spec(self, name, path=None, target=None):
        if name == "numba" or name.startswith("numba."):
            raise ImportError("numba is blocked in this test")
        return None

sys.meta_path.insert(0, BlockNumba())
import numpy as np
from h2viz.cli import main
from h2viz.mapping.backend import resolve_backend
from h2viz.mapping.checkpoint import load_checkpoint
from h2viz.mapping.mapper import Mapper
from h2viz.worker.requests import export_mesh_bytes

out, tiny = sys.argv[1], sys.argv[2:]
args = ["map", "--frames", "6", "--stride", "10", "-q", *tiny, "--set", "mapping.runtime.kernels=torch"]
assert main([*args, "--out", out]) == 0
assert main([*args, "--frames", "8", "--out", out + "-resumed", "--resume", out + "/checkpoint.pt"]) == 0
mapper, _ = load_checkpoint(out + "/checkpoint.pt")
K = np.array([[60.0, 0, 48], [0, 60.0, 36], [0, 0, 1]])
T = mapper.trajectory[-1]
depth = mapper.render(K, T, 72, 96, "depth")
rgb = mapper.render(K, T, 72, 96, "rgb")
glb = export_mesh_bytes(mapper, "glb")
print(json.dumps({
    "numba_imported": "numba" in sys.modules,
    "auto_backend": resolve_backend("auto", "cpu").name,
    "backend": mapper.backend.name,
    "depth_valid": float((depth > 0).mean()),
    "depth_median": float(np.median(depth[depth > 0])),
    "rgb_mean": float(rgb.mean()),
    "glb_bytes": len(glb),
}))
"""


FAST_MESH = ["--set", "mapping.meshing.mesh_resolution=4"]  # torch meshing at 8: half of the test (100 -> 53 s)


def test_the_whole_pipeline_runs_with_numba_import_blocked(tmp_path: Path) -> None:
    """`h2viz map` (mesh, checkpoint, evaluation renders), a resumed run, a checkpoint loaded into a new mapper,
    renders and a GLB export, all with numba unimportable: it is never imported, and the outputs are sound."""
    out = tmp_path / "run"
    script = tmp_path / "blocked.py"
    script.write_text(textwrap.dedent(BLOCKED_RUN))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, str(script), str(out), *TINY, "--set", "mapping.runtime.device=cpu", *FAST_MESH],
        capture_output=True, text=True, cwd=tmp_path, env=env, timeout=900,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["numba_imported"] is False
    assert report["auto_backend"] == "torch" and report["backend"] == "torch"  # auto falls back without numba
    assert report["depth_valid"] > 0.5 and 0.5 < report["depth_median"] < 6.0  # the room is 1-5 m away
    assert 0.05 < report["rgb_mean"] < 0.95 and report["glb_bytes"] > 10_000
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["mesh"]["fscore"] > 60.0 and metrics["interpolate"]["psnr_db"] > 18.0
    assert (out / "mesh.ply").stat().st_size > 10_000
    resumed = json.loads((tmp_path / "run-resumed" / "stats.json").read_text())
    assert [f["index"] for f in resumed["frames"]] == [0, 10, 20, 30, 40, 50, 60, 70]  # the first run's, continued
    assert (tmp_path / "run-resumed" / "mesh.ply").stat().st_size > 10_000


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_the_pipeline_runs_on_cuda(tmp_path: Path) -> None:
    """Map, mesh, render, checkpoint and reload on the GPU: every tensor the stages make stays on it."""
    from h2viz.mapping.checkpoint import load_checkpoint, save_checkpoint

    cfg = MappingConfig().updated(
        device="cuda", hash_log2_size=15, min_points_per_voxel=1, rays_per_iter=1024, max_iters=5
    )
    mapper = Mapper(cfg)
    assert mapper.backend.name == "cuda" and mapper.field.priors.device.type == "cuda"
    source = SourceConfig(format="synthetic", stride=4, synthetic=SyntheticConfig(width=96, height=72, n_frames=40))
    frames = list(make_source(source))
    for frame in frames:
        mapper.integrate(frame)
    assert mapper.field.geo_grid.tables.device.type == "cuda"
    mesh = mapper.mesh()
    assert len(mesh.faces) > 1000
    depth = mapper.render(frames[-1].K, frames[-1].T_world_camera, 72, 96, "depth")
    valid = depth > 0
    assert valid.mean() > 0.5
    np.testing.assert_allclose(np.median(depth[valid]), np.median(frames[-1].depth_m[valid]), rtol=0.1)
    save_checkpoint(mapper, tmp_path / "checkpoint.pt")
    again, _ = load_checkpoint(tmp_path / "checkpoint.pt")
    np.testing.assert_allclose(again.render(frames[-1].K, frames[-1].T_world_camera, 72, 96, "depth"), depth, atol=1e-4)
