"""Numba kernels of the colour prior (`h2viz.mapping.field.color_prior.ColorPrior`'s torch code is their reference):
splatting a frame's colours onto the voxels' lattices, and blending them at query points, each voxel found in
the octree's hash table."""

from __future__ import annotations

import numba
import numpy as np

from h2viz.mapping.kernels.jit import njit, parallel_region, prefetch
from h2viz.mapping.kernels.voxel_walk_numba import lookup


@njit(inline=True)
def _lattice(
    p: np.ndarray, v: int, origin: np.ndarray, inv_cell: float, sub: int, idx: np.ndarray, w: np.ndarray
) -> None:
    """idx (8,) flat indices into the (V*(sub+1)^3, 4) sums and w (8,) trilinear weights of point p in voxel v."""
    n = sub + 1
    base = np.empty(3, np.int64)
    frac = np.empty(3, np.float32)
    for a in range(3):
        x = min(max((p[a] - origin[v, a]) * inv_cell, 0.0), float(sub))
        b = min(int(np.floor(x)), sub - 1)
        base[a], frac[a] = b, x - b
    k = 0
    for dx in range(2):
        for dy in range(2):
            for dz in range(2):
                wx = frac[0] if dx else 1.0 - frac[0]
                wy = frac[1] if dy else 1.0 - frac[1]
                wz = frac[2] if dz else 1.0 - frac[2]
                idx[k] = v * n * n * n + ((base[0] + dx) * n + base[1] + dy) * n + base[2] + dz
                w[k] = wx * wy * wz
                k += 1


@njit(inline=True)
def _voxel(p: np.ndarray, vs: float, keys: np.ndarray, ids: np.ndarray, tolerant: bool) -> int:
    """Voxel id of point p (-1 outside the map); `tolerant` also accepts points on an allocated voxel's outer face."""
    v = lookup(keys, ids, int(np.floor(p[0] / vs)), int(np.floor(p[1] / vs)), int(np.floor(p[2] / vs)))
    if v >= 0 or not tolerant:
        return v
    eps = 1e-4 * vs
    for code in range(27):
        sx, sy, sz = (code // 9 - 1) * eps, (code // 3 % 3 - 1) * eps, (code % 3 - 1) * eps
        v = lookup(keys, ids, int(np.floor((p[0] + sx) / vs)), int(np.floor((p[1] + sy) / vs)),
                   int(np.floor((p[2] + sz) / vs)))  # fmt: skip
        if v >= 0:
            return v
    return -1


SPLAT_AHEAD = 8
"""Points between the one being splatted and the one whose lattice lines are prefetched: a frame's points land
on ~110k distinct lattice cells of a few hundred MB of lattices, each cell a cache miss (two threads: 40k points
6.5 -> 4 ms, 160k 17 -> 13 ms)."""


@njit(inline=True)
def _cell(
    p: np.ndarray, i: int, v: int, origin: np.ndarray, inv_cell: float, sub: int
) -> tuple[int, int, int, float, float, float]:
    """The lower lattice point (bx, by, bz) of the cell point i lies in within voxel v, and its position in that
    cell (fx, fy, fz) in [0, 1]."""
    x = min(max((p[i, 0] - origin[v, 0]) * inv_cell, 0.0), float(sub))
    y = min(max((p[i, 1] - origin[v, 1]) * inv_cell, 0.0), float(sub))
    z = min(max((p[i, 2] - origin[v, 2]) * inv_cell, 0.0), float(sub))
    bx, by, bz = min(int(np.floor(x)), sub - 1), min(int(np.floor(y)), sub - 1), min(int(np.floor(z)), sub - 1)
    return bx, by, bz, x - bx, y - by, z - bz


@njit(parallel=True)
def _splat_kernel(
    points: np.ndarray, rgb: np.ndarray, keys: np.ndarray, ids: np.ndarray, origin: np.ndarray, vs: float, sub: int,
    sums: np.ndarray, n_parts: int,
) -> None:  # fmt: skip
    """sums (V*(sub+1)^3, 4) += colours rgb (N,3) in [0,1] at points (N,3), trilinear weights; points outside the
    map are skipped. A point writes only its own voxel's lattice (a face's points exist once in each voxel), so
    `n_parts` threads share the voxels (voxel v to thread v mod n_parts) and each voxel's lattice takes its points in
    their order: the sums are those of a serial splat. Each thread prefetches the lattice lines of its point
    SPLAT_AHEAD places further. Scalar code with no array made per point (small arrays cost ~5x the splat itself
    at 160k points a frame)."""
    inv_cell = sub / vs
    n = sub + 1
    n_points = points.shape[0]
    n_voxels = min(origin.shape[0], sums.shape[0] // (n * n * n))
    corner = np.empty(n_points, np.int64)  # (N,) each point's lower lattice point in sums, -1 outside the map
    for i in numba.prange(n_points):
        v = lookup(keys, ids, int(np.floor(points[i, 0] / vs)), int(np.floor(points[i, 1] / vs)),
                   int(np.floor(points[i, 2] / vs)))  # fmt: skip
        corner[i] = -1
        if 0 <= v < n_voxels:
            bx, by, bz, _, _, _ = _cell(points, i, v, origin, inv_cell, sub)
            corner[i] = v * n * n * n + (bx * n + by) * n + bz
    for part in numba.prange(n_parts):
        mine = np.empty(n_points, np.int64)  # this thread's points, in order
        count = 0
        for i in range(n_points):
            if corner[i] >= 0 and (corner[i] // (n * n * n)) % n_parts == part:
                mine[count] = i
                count += 1
        for m in range(count):
            if m + SPLAT_AHEAD < count:
                ahead = corner[mine[m + SPLAT_AHEAD]]
                for line in (ahead, ahead + n, ahead + n * n, ahead + n * n + n):  # the 2x2 rows of z pairs
                    prefetch(sums, line)
            i = mine[m]
            v = corner[i] // (n * n * n)
            bx, by, bz, fx, fy, fz = _cell(points, i, v, origin, inv_cell, sub)
            r, g, b = rgb[i, 0], rgb[i, 1], rgb[i, 2]
            base = corner[i]
            for dx in range(2):
                wx = fx if dx else 1.0 - fx
                for dy in range(2):
                    wy = fy if dy else 1.0 - fy
                    for dz in range(2):
                        w = wx * wy * (fz if dz else 1.0 - fz)
                        k = base + (dx * n + dy) * n + dz
                        sums[k, 0] += w * r
                        sums[k, 1] += w * g
                        sums[k, 2] += w * b
                        sums[k, 3] += w


def splat(
    points: np.ndarray, rgb: np.ndarray, keys: np.ndarray, ids: np.ndarray, origin: np.ndarray, vs: float, sub: int,
    sums: np.ndarray,
) -> None:  # fmt: skip
    """`_splat_kernel` under the package's parallel-kernel lock."""
    with parallel_region() as threads:
        _splat_kernel(points, rgb, keys, ids, origin, vs, sub, sums, threads)


BLEND_CHUNK = 256
"""Points per parallel task of `blend` (its scratch arrays are allocated once a task, not once a point)."""


@njit(parallel=True)
def blend(
    points: np.ndarray, keys: np.ndarray, ids: np.ndarray, origin: np.ndarray, vs: float, sub: int,
    sums: np.ndarray, empty: float, out_rgb: np.ndarray, out_w: np.ndarray,
) -> None:  # fmt: skip
    """out_rgb (N,3) <- the prior colour at points (N,3) (`empty` where nothing was observed), out_w (N,) <- its
    blended weight. Within one lattice cell of a voxel face, the neighbour across it adds its own lattice's blend
    at the point moved onto the face: the splats of a surface on a face land on one side only."""
    inv_cell = sub / vs
    cell = vs / sub
    n_voxels = min(origin.shape[0], sums.shape[0] // ((sub + 1) ** 3))  # a frozen copy may lag the live octree
    n = points.shape[0]
    for task in numba.prange((n + BLEND_CHUNK - 1) // BLEND_CHUNK):
        idx, w = np.empty(8, np.int64), np.empty(8, np.float32)
        acc = np.empty(4, np.float32)
        q = np.empty(3, np.float32)
        for i in range(task * BLEND_CHUNK, min(n, (task + 1) * BLEND_CHUNK)):
            acc[:] = 0.0
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            c0x, c0y, c0z = int(np.floor(px / vs)), int(np.floor(py / vs)), int(np.floor(pz / vs))
            lox, loy, loz = px - c0x * vs, py - c0y * vs, pz - c0z * vs  # inside the point's own voxel, metres
            for ox in range(-1, 2):  # the point's voxel, and a neighbour only within one cell of their face
                if (ox == -1 and lox >= cell) or (ox == 1 and lox <= vs - cell):
                    continue
                for oy in range(-1, 2):
                    if (oy == -1 and loy >= cell) or (oy == 1 and loy <= vs - cell):
                        continue
                    for oz in range(-1, 2):
                        if (oz == -1 and loz >= cell) or (oz == 1 and loz <= vs - cell):
                            continue
                        v = lookup(keys, ids, c0x + ox, c0y + oy, c0z + oz)
                        if v < 0 or v >= n_voxels:
                            continue
                        q[0], q[1], q[2] = px, py, pz
                        _lattice(q, v, origin, inv_cell, sub, idx, w)  # clamps the point onto the voxel's box
                        for k in range(8):
                            for c in range(4):
                                acc[c] += w[k] * sums[idx[k], c]
            for c in range(3):
                out_rgb[i, c] = acc[c] / acc[3] if acc[3] > 1e-6 else empty
            out_w[i] = acc[3]
