"""Numba kernel of voxel allocation (`VoxelOctree.candidate_voxels`' NumPy code is its reference): the distinct
voxel cells of a frame's points, how many points each holds and their mean position, in three passes over the
points instead of NumPy's dozen."""

from __future__ import annotations

import numpy as np

from h2viz.mapping.kernels.jit import njit


@njit
def cell_stats(points: np.ndarray, voxel_size_m: float, max_bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distinct cells (M,3) int64 (sorted like NumPy's dense-grid path) of points (N,3), their point counts (M,)
    and the mean point (M,3) in voxel units relative to each cell's corner; empty outputs when the points' box holds
    more than `max_bins` cells (the caller sorts instead)."""
    n = points.shape[0]
    vs = np.float32(voxel_size_m)  # float32 division, as NumPy divides the float32 points: same cells on faces
    lo = np.full(3, np.iinfo(np.int64).max, np.int64)
    hi = np.full(3, np.iinfo(np.int64).min, np.int64)
    for i in range(n):  # the box (cells are recomputed below rather than stored: 24 bytes a point less to write)
        for a in range(3):
            c = int(np.floor(points[i, a] / vs))
            lo[a] = min(lo[a], c)
            hi[a] = max(hi[a], c)
    if n == 0:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros((0, 3), np.float64)
    d1, d2 = hi[1] - lo[1] + 1, hi[2] - lo[2] + 1
    n_bins = (hi[0] - lo[0] + 1) * d1 * d2
    if n_bins > max_bins:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros((0, 3), np.float64)
    rank = np.zeros(n_bins, np.int64)  # counts first, then rank + 1 of each occupied bin
    linear = np.empty(n, np.int64)
    for i in range(n):
        cx = int(np.floor(points[i, 0] / vs))
        cy = int(np.floor(points[i, 1] / vs))
        cz = int(np.floor(points[i, 2] / vs))
        b = ((cx - lo[0]) * d1 + cy - lo[1]) * d2 + cz - lo[2]
        linear[i] = b
        rank[b] += 1
    m = 0
    for b in range(n_bins):
        if rank[b] > 0:
            m += 1
    coords = np.empty((m, 3), np.int64)
    counts = np.empty(m, np.int64)
    j = 0
    for b in range(n_bins):
        if rank[b] > 0:
            counts[j] = rank[b]
            coords[j, 0] = b // (d1 * d2) + lo[0]
            coords[j, 1] = b // d2 % d1 + lo[1]
            coords[j, 2] = b % d2 + lo[2]
            rank[b] = j
            j += 1
    means = np.zeros((m, 3), np.float64)
    for i in range(n):
        j = rank[linear[i]]
        for a in range(3):
            means[j, a] += points[i, a] / vs
    for j in range(m):
        for a in range(3):
            means[j, a] = means[j, a] / counts[j] - coords[j, a]
    return coords, counts, means
