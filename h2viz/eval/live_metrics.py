"""Ground-truth mesh metrics of the live map, cheap enough to refresh while a stream is mapped.

`mesh_metrics` samples both meshes and builds both KD-trees every time, after the chunks were welded into one
mesh: half a second at 400k faces. Here the ground truth's samples and their KD-tree are drawn once (the same
samples `mesh_metrics` draws with the same seed), the reconstruction is sampled straight from its chunks (no
welding; each chunk's face areas are kept while the chunk object is unchanged), and only the culling to the
allocated voxels and the reconstruction's tree are redone: tens of milliseconds.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from h2viz.eval.metrics import EvalError, distance_metrics, sample_surface, voxel_mask_fn
from h2viz.types import MeshChunk

ChunkKey = tuple[int, int, int]


def _face_areas(chunk: MeshChunk) -> np.ndarray:
    """Areas (M,) float64 of a chunk's faces."""
    return trimesh.triangles.area(chunk.vertices[chunk.faces].astype(np.float64))  # from (M,3,3)


class LiveMeshMetrics:
    """Acc / Comp / Comp ratio / F-score (as `mesh_metrics`) of chunked meshes against one ground truth.

    Not thread-safe: one caller at a time (the worker's meshing thread while mapping, then the mapping thread).
    """

    def __init__(self, gt: trimesh.Trimesh, n_points: int = 20_000, threshold_m: float = 0.05, seed: int = 0) -> None:
        if n_points < 1:
            raise EvalError(f"live metrics need at least one sample a mesh, got n_points={n_points}")
        self.n_points, self.threshold_m = int(n_points), float(threshold_m)
        self.seed = int(seed)
        self._gt_points = sample_surface(gt, self.n_points, seed + 1)  # (M,3) as mesh_metrics draws them
        self._gt_tree = cKDTree(self._gt_points)
        self._areas: dict[ChunkKey, tuple[MeshChunk, np.ndarray]] = {}  # per chunk: (the chunk, its face areas)

    def __call__(
        self, chunks: Mapping[ChunkKey, MeshChunk], voxel_coords: np.ndarray, voxel_size_m: float
    ) -> dict[str, float]:
        """Metrics of the surface of `chunks`, the ground truth culled to the allocated voxels (V,3) (its kept
        share is `gt_kept_pct`); EvalError when either side is empty."""
        rec = self.sample(chunks)  # (N,3)
        keep = voxel_mask_fn(voxel_coords, voxel_size_m)(self._gt_points)  # (M,)
        gt = self._gt_points[keep]
        if len(gt) == 0:
            raise EvalError("no ground truth lies in the allocated voxels yet")
        d_rec, nearest = self._gt_tree.query(rec)  # (N,) reconstruction -> every ground-truth sample ...
        culled = ~keep[nearest]  # ... of which only the kept ones count: match again those that found a culled one
        if culled.any():
            d_rec[culled], _ = cKDTree(gt).query(rec[culled])
        d_gt, _ = cKDTree(rec).query(gt)  # (M',) ground truth -> reconstruction
        out = distance_metrics(d_rec, d_gt, self.threshold_m)
        out["gt_kept_pct"] = 100.0 * float(keep.mean())
        return out

    def sample(self, chunks: Mapping[ChunkKey, MeshChunk]) -> np.ndarray:
        """`n_points` points (N,3) float64 drawn uniformly by area from the chunks' faces (the same points for
        the same chunks)."""
        rng = np.random.default_rng(self.seed)
        items = [c for c in chunks.values() if len(c.faces)]
        self._areas = {c.key: self._areas_of(c) for c in items}
        if not items:
            raise EvalError("the live mesh has no faces yet")
        areas = [self._areas[c.key][1] for c in items]
        cum = np.cumsum(np.concatenate(areas))  # (F,)
        if not cum[-1] > 0:
            raise EvalError("the live mesh has zero area")
        pick = np.searchsorted(cum, rng.random(self.n_points) * cum[-1], side="right")  # (N,) global faces
        pick = np.minimum(pick, len(cum) - 1)
        starts = np.cumsum([0] + [len(a) for a in areas[:-1]])  # (C,) first global face of each chunk
        owner = np.searchsorted(starts, pick, side="right") - 1  # (N,) chunk of each pick
        tri = np.empty((self.n_points, 3, 3), np.float64)
        for c in np.unique(owner):
            rows = np.flatnonzero(owner == c)
            chunk = items[c]
            tri[rows] = chunk.vertices[chunk.faces[pick[rows] - starts[c]]]
        u, v = rng.random((2, self.n_points))
        flip = u + v > 1.0  # fold the unit square onto the triangle
        u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
        return tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])

    def _areas_of(self, chunk: MeshChunk) -> tuple[MeshChunk, np.ndarray]:
        held = self._areas.get(chunk.key)
        return held if held is not None and held[0] is chunk else (chunk, _face_areas(chunk))
