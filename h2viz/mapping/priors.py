"""Octree SDF priors: corner SDF values initialised by projecting voxel corners into the depth image.

A voxel is initialised when all 8 corners project inside the image onto valid depth and
|D(u) - z| <= sqrt(6) * voxel size; each corner is written once; voxels that fail are retried later.
Values are stored in truncation units (sdf / tr) so that one learning rate suits priors and networks.
"""

from __future__ import annotations

import numpy as np

from h2viz.geometry import project
from h2viz.mapping.octree import CORNER_OFFSETS, VoxelOctree


class PriorInitializer:
    """Tracks which corners hold a prior and which voxels still wait for initialisation."""

    def __init__(self, truncation_m: float, enabled: bool = True) -> None:
        self.truncation_m = float(truncation_m)
        self.enabled = enabled
        self.written = np.zeros(0, dtype=bool)  # (C,) corner already holds a prior
        self.pending = np.zeros(0, dtype=np.int64)  # voxel ids still to initialise

    def grow(self, n_corners: int, new_voxels: np.ndarray) -> None:
        """Account for corners and voxels created by the last allocation."""
        self.written = np.concatenate([self.written, np.zeros(n_corners - self.written.size, dtype=bool)])
        if self.enabled and new_voxels.size:
            self.pending = np.concatenate([self.pending, new_voxels])

    def initialize(
        self, octree: VoxelOctree, depth_m: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Priors for pending voxels seen in this frame: (corner ids (n,), values in tr units (n,))."""
        if not self.enabled or self.pending.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.float32)
        vs = octree.voxel_size_m
        coords = octree.voxel_coords()[self.pending]  # (P,3)
        corners_w = ((coords[:, None, :] + CORNER_OFFSETS[None]) * vs).reshape(-1, 3)  # (P*8,3)
        uv, z = project(corners_w, K, T_world_camera)
        h, w = depth_m.shape
        u = np.round(np.nan_to_num(uv[:, 0], nan=-1.0)).astype(np.int64)
        v = np.round(np.nan_to_num(uv[:, 1], nan=-1.0)).astype(np.int64)
        inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        d = np.zeros_like(z)
        d[inside] = depth_m[v[inside], u[inside]]
        sdf = d - z  # (P*8,)
        ok_corner = inside & (d > 0) & (np.abs(sdf) <= np.sqrt(6.0) * vs)
        ok_voxel = ok_corner.reshape(-1, 8).all(axis=1)  # (P,)
        cids = octree.voxel_corners[self.pending[ok_voxel]].reshape(-1)
        vals = sdf.reshape(-1, 8)[ok_voxel].reshape(-1) / self.truncation_m
        cids, first = np.unique(cids, return_index=True)
        vals = vals[first]
        fresh = ~self.written[cids]
        self.written[cids] = True
        self.pending = self.pending[~ok_voxel]
        return cids[fresh], vals[fresh].astype(np.float32)

    def initialised(self, n_voxels: int) -> np.ndarray:
        """(V,) True for voxels whose corners all hold priors (every voxel when priors are disabled)."""
        mask = np.ones(n_voxels, dtype=bool)
        mask[self.pending] = False
        return mask

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"written": self.written, "pending": self.pending}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.written = np.asarray(state["written"], dtype=bool)
        self.pending = np.asarray(state["pending"], dtype=np.int64)
