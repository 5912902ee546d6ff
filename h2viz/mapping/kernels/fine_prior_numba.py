"""Numba kernels of the fine SDF prior (`h2viz.mapping.field.fine_prior.FinePrior`'s torch code is their reference):
fusing a frame's depth into the voxels' lattices, and blending them at query points."""

from __future__ import annotations

import numba
import numpy as np

from h2viz.mapping.kernels.jit import njit, parallel_region


@njit(parallel=True)
def _fuse_kernel(
    origin: np.ndarray, depth: np.ndarray, K: np.ndarray, T_camera_world: np.ndarray, vs: float, sub: int,
    tr: float, state: np.ndarray, voxels: np.ndarray,
) -> None:  # fmt: skip
    """state (V*(sub+1)^3, 2) += (truncated SDF in tr units, 1) at every lattice point of voxels with origins
    (V,3) that projects onto valid depth and lies at most tr behind it, in the voxels listed in `voxels` (M,)
    (distinct indices).

    Voxels whose bounding sphere projects wholly off the image are skipped (the bound holds off the optical axis
    too, where a sphere's image is stretched), and the threads then share the voxels in view (allocated together,
    they would otherwise fall to one thread); each voxel's lattice is written by one thread. A lattice point's
    camera coordinates are its row's start plus k steps along the lattice's z axis (no matrix product per point),
    and one division per point projects it."""
    n = sub + 1
    h, w = depth.shape
    cell = vs / sub
    radius = 0.5 * np.sqrt(3.0) * vs
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    R, t = T_camera_world[:3, :3], T_camera_world[:3, 3]
    in_view = np.zeros(voxels.shape[0], np.bool_)
    for c in numba.prange(voxels.shape[0]):
        v = voxels[c]
        hx, hy, hz = origin[v, 0] + 0.5 * vs, origin[v, 1] + 0.5 * vs, origin[v, 2] + 0.5 * vs
        zc = R[2, 0] * hx + R[2, 1] * hy + R[2, 2] * hz + t[2]
        if zc < -radius:
            continue
        if zc > radius:  # the whole voxel is in front of the camera: cull by its projected sphere
            xc = R[0, 0] * hx + R[0, 1] * hy + R[0, 2] * hz + t[0]
            yc = R[1, 0] * hx + R[1, 1] * hy + R[1, 2] * hz + t[1]
            uc, vc = fx * xc / zc + cx, fy * yc / zc + cy
            # |u - uc| <= fx r sqrt(zc^2 + xc^2) / ((zc - r) zc) within r of the centre, +1 px for rounding
            ru = fx * radius * np.sqrt(zc * zc + xc * xc) / ((zc - radius) * zc) + 1.0
            rv = fy * radius * np.sqrt(zc * zc + yc * yc) / ((zc - radius) * zc) + 1.0
            if uc < -ru or uc > w + ru or vc < -rv or vc > h + rv:
                continue
        in_view[c] = True
    visible = np.nonzero(in_view)[0]
    for q in numba.prange(visible.shape[0]):
        v = voxels[visible[q]]
        base = v * n * n * n
        ox, oy, oz = float(origin[v, 0]), float(origin[v, 1]), float(origin[v, 2])
        for i in range(n):
            px = ox + i * cell
            for j in range(n):
                py = oy + j * cell
                # camera coordinates of lattice point (i, j, 0) and the step to (i, j, k + 1)
                x0 = R[0, 0] * px + R[0, 1] * py + R[0, 2] * oz + t[0]
                y0 = R[1, 0] * px + R[1, 1] * py + R[1, 2] * oz + t[1]
                z0 = R[2, 0] * px + R[2, 1] * py + R[2, 2] * oz + t[2]
                row = base + (i * n + j) * n
                for k in range(n):
                    z = z0 + k * (R[2, 2] * cell)
                    if z <= 1e-6:
                        continue
                    inv_z = 1.0 / z
                    u = int(np.rint(fx * (x0 + k * (R[0, 2] * cell)) * inv_z + cx))  # rint: round half to even
                    vv = int(np.rint(fy * (y0 + k * (R[1, 2] * cell)) * inv_z + cy))
                    if u < 0 or u >= w or vv < 0 or vv >= h:
                        continue
                    d = depth[vv, u]
                    if d <= 0.0:
                        continue
                    sdf = d - z
                    if sdf < -tr:
                        continue
                    state[row + k, 0] += min(sdf, tr) / tr
                    state[row + k, 1] += 1.0


def fuse(
    origin: np.ndarray, depth: np.ndarray, K: np.ndarray, T_camera_world: np.ndarray, vs: float, sub: int,
    tr: float, state: np.ndarray, voxels: np.ndarray | None = None,
) -> None:  # fmt: skip
    """`_fuse_kernel` under the package's parallel-kernel lock (voxels (M,): fuse only those; None: all)."""
    listed = np.arange(origin.shape[0]) if voxels is None else np.ascontiguousarray(voxels, np.int64)
    if listed.size == 0:
        return
    with parallel_region():
        _fuse_kernel(origin, depth, K, T_camera_world, vs, sub, tr, state, listed)


@njit(parallel=True)
def blend(
    points: np.ndarray, voxel: np.ndarray, origin: np.ndarray, vs: float, sub: int, state: np.ndarray,
    out_value: np.ndarray, out_cover: np.ndarray,
) -> None:  # fmt: skip
    """out_value (N,) <- sum over the 8 lattice points around each point (N,3) in voxels (N,) that hold fused
    values of trilinear weight * mean SDF; out_cover (N,) <- the sum of their weights (0 where none)."""
    n = sub + 1
    inv_cell = sub / vs
    n_voxels = min(origin.shape[0], state.shape[0] // (n * n * n))  # a frozen copy may lag the live octree
    for p in numba.prange(points.shape[0]):
        v = voxel[p]
        out_value[p] = 0.0
        out_cover[p] = 0.0
        if v < 0 or v >= n_voxels:
            continue
        b0, b1, b2 = 0, 0, 0
        f0, f1, f2 = 0.0, 0.0, 0.0
        for a in range(3):
            x = min(max((points[p, a] - origin[v, a]) * inv_cell, 0.0), float(sub))
            b = min(int(np.floor(x)), sub - 1)
            if a == 0:
                b0, f0 = b, x - b
            elif a == 1:
                b1, f1 = b, x - b
            else:
                b2, f2 = b, x - b
        value, cover = 0.0, 0.0
        for dx in range(2):
            wx = f0 if dx else 1.0 - f0
            for dy in range(2):
                wy = f1 if dy else 1.0 - f1
                for dz in range(2):
                    idx = v * n * n * n + ((b0 + dx) * n + b1 + dy) * n + b2 + dz
                    weight = state[idx, 1]
                    if weight > 0.0:
                        wt = wx * wy * (f2 if dz else 1.0 - f2)
                        value += wt * state[idx, 0] / weight
                        cover += wt
        out_value[p] = value
        out_cover[p] = cover
