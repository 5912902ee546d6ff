"""The Open3D TSDF baseline of the benchmarks reconstructs an analytic coloured room (a box seen from
inside) from exact depth (skipped when open3d is not installed)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from bench.tsdf_baseline import TsdfConfig, TsdfFusion
from h2viz.eval.mesh_render import MeshRenderer
from h2viz.eval.metrics import observed_mask_fn, sample_surface
from h2viz.geometry import look_at
from h2viz.types import RgbdFrame

pytestmark = pytest.mark.skipif(importlib.util.find_spec("open3d") is None, reason="open3d is not installed")

HALF_EXTENTS_M = np.array([1.0, 1.2, 0.8])  # the room spans [-1, 1] x [-1.2, 1.2] x [-0.8, 0.8]
ROOM_RGB = np.array([200, 80, 30], dtype=np.uint8)


def _room() -> trimesh.Trimesh:
    """Walls, floor and ceiling of the room, in one colour, normals facing inwards."""
    room = trimesh.creation.box(extents=2.0 * HALF_EXTENTS_M)
    room.invert()
    room.visual.vertex_colors = np.tile(np.append(ROOM_RGB, 255), (len(room.vertices), 1))
    return room


def _distance_to_room(points: np.ndarray) -> np.ndarray:
    """Exact distance (N,) of points (N,3) near the room's surface to it (inside or just outside)."""
    return np.abs((HALF_EXTENTS_M - np.abs(points)).min(axis=1))


def _frames(room: trimesh.Trimesh, n: int = 12, height: int = 180, width: int = 240) -> list[RgbdFrame]:
    """Exact colour and depth of the room from cameras near its centre turning around, looking
    alternately 25 deg down and up."""
    render = MeshRenderer(room)
    f = 0.9 * width
    K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    frames = []
    for i, angle in enumerate(np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)):
        eye = np.array([0.1 * np.cos(3 * angle), 0.1 * np.sin(2 * angle), 0.05 * (-1) ** i])
        pitch = np.deg2rad(25.0) * (-1) ** i
        target = eye + np.array([np.cos(angle) * np.cos(pitch), np.sin(angle) * np.cos(pitch), np.sin(pitch)])
        T_world_camera = look_at(eye, target)
        rgb = np.round(render(K, T_world_camera, height, width, "rgb") * 255.0).astype(np.uint8)
        depth = render(K, T_world_camera, height, width, "depth")
        frames.append(RgbdFrame(i, i / 30.0, rgb, depth, K, T_world_camera))
    return frames


def test_tsdf_reconstructs_room_within_a_centimetre() -> None:
    room = _room()
    frames = _frames(room)
    fusion = TsdfFusion(TsdfConfig(voxel_size_m=0.01, trunc_voxels=5.0))
    for frame in frames:
        assert fusion.integrate(frame) > 0.0
    mesh = fusion.mesh()
    assert len(mesh.faces) > 100_000

    err = _distance_to_room(mesh.vertices)  # (N,) accuracy of every vertex
    assert err.mean() < 0.003 and err.max() < 0.01
    gt = sample_surface(room, 100_000)  # (M,3)
    gt = gt[observed_mask_fn([(f.K, f.T_world_camera, f.depth_m) for f in frames])(gt)]  # what was seen
    assert len(gt) > 50_000
    gap, _ = cKDTree(mesh.vertices).query(gt)  # (M,) completeness, floored by the ~1 cm vertex spacing
    assert np.mean(gap < 0.01) > 0.99

    colors = np.asarray(mesh.visual.vertex_colors)[:, :3].astype(np.float64)  # (N,3)
    assert np.median(np.abs(colors - ROOM_RGB), axis=0).max() <= 1.0


def test_empty_fusion_gives_empty_mesh() -> None:
    assert len(TsdfFusion().mesh().faces) == 0
