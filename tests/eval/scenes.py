"""Analytic scenes for the evaluation tests: grid planes, a textured plane renderer with exact images
at any camera, and real-sequence loading (7-Scenes layout) without going through the sources."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import trimesh

from h2viz.geometry import world_rays


def grid_plane(
    x0: float, x1: float, y0: float, y1: float, z: float = 0.0, cells: int = 100
) -> trimesh.Trimesh:
    """Rectangle [x0,x1] x [y0,y1] at height z, split into cells x cells squares (2 triangles each)."""
    xs, ys = np.linspace(x0, x1, cells + 1), np.linspace(y0, y1, cells + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    vertices = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1)
    idx = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return trimesh.Trimesh(vertices, faces, process=False)


def plane_texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smooth colour (..., 3) in [0.1, 0.9] of the world point (x, y) on the textured plane."""
    return np.stack(
        [0.5 + 0.4 * np.sin(9.0 * x), 0.5 + 0.4 * np.cos(7.0 * y), 0.5 + 0.4 * np.sin(5.0 * (x + y))], axis=-1
    )


def render_textured_plane(
    K: np.ndarray, T_world_camera: np.ndarray, height: int, width: int, mode: str, plane_z: float = 2.0
) -> np.ndarray:
    """Exact image of the plane z = plane_z (world) coloured by `plane_texture`; depth 0 off the plane."""
    origins, dirs = world_rays(K, T_world_camera, height, width)  # (H*W,3) each
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (plane_z - origins[:, 2]) / dirs[:, 2]  # (H*W,) camera z of the hit, since dirs have z_cam = 1
    hit = np.isfinite(t) & (t > 0)
    if mode == "depth":
        return np.where(hit, t, 0.0).reshape(height, width).astype(np.float32)
    p = origins + np.where(hit, t, 0.0)[:, None] * dirs
    rgb = np.where(hit[:, None], plane_texture(p[:, 0], p[:, 1]), 0.0)
    return rgb.reshape(height, width, 3).astype(np.float32)


def load_7scenes(root: Path, stride: int = 1) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """K (3,3), poses (N,4,4) and depths [(H,W) float32 metres] of a 7-Scenes-layout folder."""
    K = np.loadtxt(root / "camera-intrinsics.txt")
    pose_files = sorted(root.glob("frame-*.pose.txt"))[::stride]
    poses = np.stack([np.loadtxt(p) for p in pose_files])
    depths = []
    for p in pose_files:
        raw = cv2.imread(str(p).replace(".pose.txt", ".depth.png"), cv2.IMREAD_UNCHANGED)
        depths.append(np.where(raw == 65535, 0, raw).astype(np.float32) / 1000.0)
    return K, poses, depths
