"""Ground-truth images of a mesh by ray casting (embree through trimesh): the reference colour and
depth for cameras that have no captured frame, such as extrapolated views."""

from __future__ import annotations

import numpy as np
import trimesh

from h2viz.eval.metrics import EvalError
from h2viz.geometry import world_rays


class MeshRenderer:
    """A `Renderer` of a (vertex-coloured) mesh: render(K, T_world_camera, height, width, mode) with
    mode 'rgb' -> (H,W,3) float32 in [0,1] (barycentric vertex colours; grey without colours,
    black where nothing is hit) and 'depth' -> (H,W) float32 camera z in metres (0 = nothing hit)."""

    def __init__(self, mesh: trimesh.Trimesh) -> None:
        if len(mesh.faces) == 0:
            raise EvalError("cannot render a mesh without faces; check the ground-truth mesh file")
        self.mesh = mesh
        self.vertex_rgb = _vertex_rgb(mesh)  # (N,3) in [0,1]
        self._key: tuple[bytes, bytes, int, int] | None = None
        self._cached: tuple[np.ndarray, np.ndarray] | None = None

    def __call__(
        self, K: np.ndarray, T_world_camera: np.ndarray, height: int, width: int, mode: str
    ) -> np.ndarray:
        if mode not in ("rgb", "depth"):
            raise EvalError(f"mesh renderer: unknown mode '{mode}'; use 'rgb' or 'depth'")
        K, T = np.asarray(K, np.float64), np.asarray(T_world_camera, np.float64)
        rgb, depth = self._render(K, T, height, width)
        return rgb if mode == "rgb" else depth

    def _render(self, K: np.ndarray, T: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """Colour (H,W,3) and depth (H,W) of one camera; the last camera is cached so that asking for
        'rgb' then 'depth' casts the rays once."""
        key = (K.tobytes(), T.tobytes(), height, width)
        if key == self._key and self._cached is not None:
            return self._cached
        origins, dirs = world_rays(K, T, height, width)  # (H*W,3) each, dirs have camera z = 1
        locations, ray_idx, tri_idx = self.mesh.ray.intersects_location(origins, dirs, multiple_hits=False)
        depth = np.zeros(height * width, dtype=np.float32)
        rgb = np.zeros((height * width, 3), dtype=np.float32)
        if len(ray_idx):
            depth[ray_idx] = (locations - T[:3, 3]) @ T[:3, 2]  # camera z of each hit
            faces = self.mesh.faces[tri_idx]  # (M,3)
            bary = trimesh.triangles.points_to_barycentric(self.mesh.vertices[faces], locations)  # (M,3)
            rgb[ray_idx] = np.einsum("mk,mkc->mc", np.clip(bary, 0.0, 1.0), self.vertex_rgb[faces])
        self._key = key
        self._cached = (np.clip(rgb, 0.0, 1.0).reshape(height, width, 3), depth.reshape(height, width))
        return self._cached


def _vertex_rgb(mesh: trimesh.Trimesh) -> np.ndarray:
    """Vertex colours (N,3) in [0,1] from vertex, face or texture colours; mid-grey without any."""
    visual = mesh.visual.to_color() if mesh.visual.kind == "texture" else mesh.visual
    colors = visual.vertex_colors if visual.kind in ("vertex", "face") else None
    if colors is None or len(colors) != len(mesh.vertices):
        return np.full((len(mesh.vertices), 3), 0.5, dtype=np.float64)
    return np.asarray(colors, dtype=np.float64)[:, :3] / 255.0
