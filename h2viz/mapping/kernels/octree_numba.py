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
    more than `max_bins` cells (the caller sorts instead).

    The box comes from the points' extremes (floor(x / vs) never decreases with x, so the extreme cells are those
    of the extreme points), and each point's quotient x / vs is computed once, in float32 as NumPy divides the
    float32 points: the same cells on voxel faces."""
    n = points.shape[0]
    if n == 0:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros((0, 3), np.float64)
    vs = np.float32(voxel_size_m)
    lo_p = np.empty(3, np.float32)
    hi_p = np.empty(3, np.float32)
    for a in range(3):
        lo_p[a], hi_p[a] = points[0, a], points[0, a]
    for i in range(1, n):
        for a in range(3):
            x = points[i, a]
            if x < lo_p[a]:
                lo_p[a] = x
            elif x > hi_p[a]:
                hi_p[a] = x
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for a in range(3):
        lo[a] = int(np.floor(lo_p[a] / vs))
        hi[a] = int(np.floor(hi_p[a] / vs))
    d1, d2 = hi[1] - lo[1] + 1, hi[2] - lo[2] + 1
    n_bins = (hi[0] - lo[0] + 1) * d1 * d2
    if n_bins > max_bins:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros((0, 3), np.float64)
    rank = np.zeros(n_bins, np.int64)  # counts first, then the rank of each occupied bin
    linear = np.empty(n, np.int64)
    scaled = np.empty((n, 3), np.float32)  # (N,3) x / vs
    for i in range(n):
        qx, qy, qz = points[i, 0] / vs, points[i, 1] / vs, points[i, 2] / vs
        scaled[i, 0], scaled[i, 1], scaled[i, 2] = qx, qy, qz
        b = ((int(np.floor(qx)) - lo[0]) * d1 + int(np.floor(qy)) - lo[1]) * d2 + int(np.floor(qz)) - lo[2]
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
            means[j, a] += scaled[i, a]
    for j in range(m):
        for a in range(3):
            means[j, a] = means[j, a] / counts[j] - coords[j, a]
    return coords, counts, means
