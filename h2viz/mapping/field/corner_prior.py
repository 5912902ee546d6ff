"""Octree SDF priors: corner SDF values initialised by projecting voxel corners into the depth image.

A corner is written, once, by the first frame in which it projects inside the image onto valid depth with
|D(u) - z| <= sqrt(6) * voxel size; a voxel is initialised when all 8 of its corners are written, by one frame
or several (a voxel at the edge of one view is completed by the next), and waits until then. A corner seen
more than that limit in front of the measured surface (through a silhouette, onto the background) is in
observed free space: it keeps the free-space value until a later view writes it, and counts as known, so that
its voxel is meshed. Values are stored in truncation units (sdf / tr) so that one learning rate suits priors
and networks.
"""

from __future__ import annotations

import numpy as np

from h2viz.geometry import project
from h2viz.mapping.field.octree import CORNER_OFFSETS, VoxelOctree


class PriorInitializer:
    """Tracks which corners hold a prior and which voxels still wait for initialisation."""

    def __init__(self, truncation_m: float, enabled: bool = True) -> None:
        self.truncation_m = float(truncation_m)
        self.enabled = enabled
        self.written = np.zeros(0, dtype=bool)  # (C,) corner already holds a prior
        self.free = np.zeros(0, dtype=bool)  # (C,) corner seen in free space beyond the sqrt(6) limit
        self.pending = np.zeros(0, dtype=np.int64)  # (P,) voxel ids with corners still to write
        self.ready = np.zeros(0, dtype=bool)  # (P,) pending voxel whose corners are all written or free

    def grow(self, n_corners: int, new_voxels: np.ndarray) -> None:
        """Account for corners and voxels created by the last allocation."""
        grown = np.zeros(n_corners - self.written.size, dtype=bool)
        self.written = np.concatenate([self.written, grown])
        self.free = np.concatenate([self.free, grown])
        if self.enabled and new_voxels.size:
            self.pending = np.concatenate([self.pending, new_voxels])
            self.ready = np.concatenate([self.ready, np.zeros(new_voxels.size, dtype=bool)])

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
        corner_ids = octree.voxel_corners[self.pending].reshape(-1)  # (P*8,)
        limit = np.sqrt(6.0) * vs
        take = inside & (d > 0) & (np.abs(sdf) <= limit) & ~self.written[corner_ids]
        cids, first = np.unique(corner_ids[take], return_index=True)  # a shared corner once
        vals = sdf[take][first] / self.truncation_m
        self.written[cids] = True
        self.free[corner_ids[inside & (d > 0) & (sdf > limit)]] = True
        corners = octree.voxel_corners[self.pending]  # (P,8)
        done = self.written[corners].all(axis=1)  # (P,)
        self.ready = (self.written | self.free)[corners[~done]].all(axis=1)
        self.pending = self.pending[~done]
        return cids, vals.astype(np.float32)

    def initialised(self, n_voxels: int) -> np.ndarray:
        """(V,) True for voxels whose corners all hold priors or lie in observed free space (every voxel when
        priors are disabled)."""
        mask = np.ones(n_voxels, dtype=bool)
        mask[self.pending[~self.ready]] = False
        return mask

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"written": self.written, "free": self.free, "pending": self.pending, "ready": self.ready}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.written = np.asarray(state["written"], dtype=bool)
        self.pending = np.asarray(state["pending"], dtype=np.int64)
        self.free = np.asarray(state.get("free", np.zeros_like(self.written)), dtype=bool)
        self.ready = np.asarray(state.get("ready", np.zeros(self.pending.size, bool)), dtype=bool)
