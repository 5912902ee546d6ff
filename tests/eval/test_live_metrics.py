"""LiveMeshMetrics: the live map's metrics from its chunks, matching mesh_metrics on the welded mesh."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from h2viz.eval.live_metrics import LiveMeshMetrics
from h2viz.eval.metrics import EvalError, mesh_metrics, voxel_mask_fn
from h2viz.types import MeshChunk
from tests.eval.scenes import grid_plane

VOXEL_M = 0.1


def _chunks(mesh: trimesh.Trimesh, splits: int = 4) -> dict[tuple[int, int, int], MeshChunk]:
    """The mesh cut into `splits` chunks by face order (each chunk keeps only the vertices its faces use)."""
    out = {}
    for i, faces in enumerate(np.array_split(np.asarray(mesh.faces), splits)):
        used, local = np.unique(faces, return_inverse=True)
        verts = np.asarray(mesh.vertices, np.float32)[used]
        colors = np.zeros((len(used), 3), np.uint8)
        out[(i, 0, 0)] = MeshChunk((i, 0, 0), verts, local.reshape(-1, 3).astype(np.int32), colors, 0)
    return out


def _voxels(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    """Voxel coordinates (V,3) covering [x0,x1) x [y0,y1) around z = 0 (two layers, so z = +-1 cm is inside)."""
    xs = np.arange(np.floor(x0 / VOXEL_M), np.ceil(x1 / VOXEL_M))
    ys = np.arange(np.floor(y0 / VOXEL_M), np.ceil(y1 / VOXEL_M))
    gx, gy, gz = np.meshgrid(xs, ys, [-1, 0], indexing="ij")
    return np.stack([gx.ravel(), gy.ravel(), gz.ravel()], 1).astype(np.int64)


def test_plane_shifted_1cm_gives_1cm_acc_and_comp() -> None:
    gt = grid_plane(0.0, 0.4, 0.0, 0.4, cells=20)  # 20k samples 3 mm apart: nearest ones lie almost straight below
    rec = gt.copy()
    rec.apply_translation([0.0, 0.0, 0.01])
    live = LiveMeshMetrics(gt, n_points=20_000, threshold_m=0.05)
    m = live(_chunks(rec), _voxels(-0.1, 0.5, -0.1, 0.5), VOXEL_M)
    assert m["acc_cm"] == pytest.approx(1.0, abs=0.05)
    assert m["comp_cm"] == pytest.approx(1.0, abs=0.05)
    assert m["comp_ratio"] == 100.0 and m["gt_kept_pct"] == 100.0


def test_matches_mesh_metrics_on_the_welded_mesh_with_culling() -> None:
    gt = grid_plane(0.0, 2.0, 0.0, 1.0, cells=40)
    rec = grid_plane(0.0, 1.0, 0.0, 1.0, cells=20)  # only the left half reconstructed ...
    rec.vertices[:, 2] += 0.004 * np.sin(7.0 * rec.vertices[:, 0])  # ... a little wavy
    voxels = _voxels(0.0, 1.2, 0.0, 1.0)  # allocated a little beyond it: part of the missing half counts
    live = LiveMeshMetrics(gt, n_points=30_000, threshold_m=0.05)
    got = live(_chunks(rec, splits=5), voxels, VOXEL_M)
    want = mesh_metrics(rec, gt, 30_000, 0.05, gt_mask_fn=voxel_mask_fn(voxels, VOXEL_M))
    assert got["gt_kept_pct"] == pytest.approx(want["gt_kept_pct"], abs=1e-9)  # the same ground-truth samples
    assert 50.0 < got["gt_kept_pct"] < 70.0
    for key in ("acc_cm", "comp_cm"):
        assert got[key] == pytest.approx(want[key], rel=0.05), key
    assert got["comp_ratio"] == pytest.approx(want["comp_ratio"], abs=1.5)
    assert got["comp_ratio"] < 95.0  # the culled-in strip beyond the reconstruction is missed


def test_same_chunks_give_the_same_numbers_and_a_changed_chunk_is_resampled() -> None:
    gt = grid_plane(0.0, 1.0, 0.0, 1.0, cells=20)
    chunks = _chunks(gt)
    live = LiveMeshMetrics(gt, n_points=5_000)
    voxels = _voxels(0.0, 1.0, 0.0, 1.0)
    assert live(chunks, voxels, VOXEL_M) == live(chunks, voxels, VOXEL_M)
    moved = chunks[(0, 0, 0)]
    chunks[(0, 0, 0)] = MeshChunk(moved.key, moved.vertices + np.float32([0, 0, 0.03]), moved.faces, moved.colors, 1)
    assert live(chunks, voxels, VOXEL_M)["acc_cm"] > 0.3  # a quarter of the surface 3 cm off


def test_empty_inputs_are_errors() -> None:
    gt = grid_plane(0.0, 1.0, 0.0, 1.0, cells=10)
    live = LiveMeshMetrics(gt, n_points=1_000)
    with pytest.raises(EvalError, match="no faces"):
        live({}, _voxels(0.0, 1.0, 0.0, 1.0), VOXEL_M)
    with pytest.raises(EvalError, match="ground truth"):
        live(_chunks(gt), _voxels(5.0, 6.0, 5.0, 6.0), VOXEL_M)
    with pytest.raises(EvalError):
        LiveMeshMetrics(gt, n_points=0)
