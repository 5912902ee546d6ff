"""Numba kernel of the training samples (`h2viz.mapping.sampling.samples.band_samples` is its torch reference).

Per ray: `n_free` stratified free-space candidates between the camera and the band, `n_front` strata of the
band's free-space part (from `band` to tr in front of the measured depth), then every `step` from tr in front
of it to tr behind it (each candidate jittered within its stratum), in float32 as the
reference computes them; each candidate is looked up in the octree's leaf hash table and kept when it falls in
an allocated voxel. Two parallel passes over blocks of rays: count (and remember each candidate's voxel), then
write the kept samples at each ray's offset, ray-major and in increasing t.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from h2viz.errors import H2vizError
from h2viz.mapping.field.octree import VoxelOctree
from h2viz.mapping.kernels.jit import njit, parallel_region
from h2viz.mapping.kernels.voxel_walk import walk_table
from h2viz.mapping.kernels.voxel_walk_numba import lookup
from h2viz.mapping.sampling.samples import BandLayout


@njit(inline=True)
def _candidate_t(
    depth: np.float32, jitter: np.ndarray, r: int, k: int, n_free: int, n_front: int, lay: np.ndarray
) -> np.float32:
    """t of candidate k of ray r: free-space strata, the band's front strata, then the truncation band.
    lay = (band, front stride, tr, step) in float32."""
    if k < n_free:
        free_end = max(depth - lay[0], np.float32(0.0))
        return (np.float32(k) + jitter[r, k]) / np.float32(n_free) * free_end
    k -= n_free
    if k < n_front:
        return (depth - lay[0]) + (np.float32(k) + jitter[r, k + n_free]) * lay[1]
    return (depth - lay[2]) + (np.float32(k - n_front) + jitter[r, k + n_free]) * lay[3]


@njit(parallel=True)
def _band_kernel(
    origins: np.ndarray,
    dirs: np.ndarray,
    depth: np.ndarray,
    jitter: np.ndarray,
    n_free: int,
    n_front: int,
    lay: np.ndarray,
    vs: float,
    table_keys: np.ndarray,
    table_ids: np.ndarray,
    n_blocks: int,
    counts: np.ndarray,
    voxel_of: np.ndarray,
) -> None:
    """voxel_of (R,K) <- voxel id of every candidate (-1 outside the map or behind the camera); counts (R,)."""
    n_rays, n_cand = jitter.shape
    vs32 = np.float32(vs)
    for block in numba.prange(n_blocks):
        for r in range(block * n_rays // n_blocks, (block + 1) * n_rays // n_blocks):
            kept = 0
            px, py, pz, pv = np.int64(0), np.int64(0), np.int64(0), np.int64(-2)  # last cell looked up
            for k in range(n_cand):
                t = _candidate_t(depth[r], jitter, r, k, n_free, n_front, lay)
                v = -1
                if t > 0.0:
                    cx = np.int64(np.floor((origins[r, 0] + dirs[r, 0] * t) / vs32))
                    cy = np.int64(np.floor((origins[r, 1] + dirs[r, 1] * t) / vs32))
                    cz = np.int64(np.floor((origins[r, 2] + dirs[r, 2] * t) / vs32))
                    if pv == -2 or cx != px or cy != py or cz != pz:  # 1 cm steps mostly stay in a 10 cm voxel
                        px, py, pz, pv = cx, cy, cz, lookup(table_keys, table_ids, cx, cy, cz)
                    v = pv
                voxel_of[r, k] = v
                kept += v >= 0
            counts[r] = kept


@njit(parallel=True)
def _band_fill(
    origins: np.ndarray,
    dirs: np.ndarray,
    depth: np.ndarray,
    jitter: np.ndarray,
    n_free: int,
    n_front: int,
    lay: np.ndarray,
    voxel_of: np.ndarray,
    offsets: np.ndarray,
    n_blocks: int,
    points: np.ndarray,
    t_out: np.ndarray,
    ray: np.ndarray,
    voxel: np.ndarray,
) -> None:
    """Write the kept candidates of every ray at offsets (R,) into points (S,3), t, ray, voxel (S,)."""
    n_rays, n_cand = jitter.shape
    for block in numba.prange(n_blocks):
        for r in range(block * n_rays // n_blocks, (block + 1) * n_rays // n_blocks):
            s = offsets[r]
            for k in range(n_cand):
                if voxel_of[r, k] < 0:
                    continue
                t = _candidate_t(depth[r], jitter, r, k, n_free, n_front, lay)
                for a in range(3):
                    points[s, a] = origins[r, a] + dirs[r, a] * t
                t_out[s], ray[s], voxel[s] = t, r, voxel_of[r, k]
                s += 1


def band_candidates(
    octree: VoxelOctree,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    depth: torch.Tensor,
    jitter: torch.Tensor,
    layout: BandLayout,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(points (S,3), t (S,), ray (S,), voxel (S,)) of the candidates inside allocated voxels, for CPU rays
    origins/dirs (R,3), depth (R,) and jitter (R, layout.n_candidates) in [0, 1)."""
    R = depth.shape[0]
    if origins.shape != (R, 3) or dirs.shape != (R, 3) or jitter.shape != (R, layout.n_candidates):
        raise H2vizError(  # the kernels do not check bounds
            f"band samples need origins and dirs (R,3), jitter (R, {layout.n_candidates}) for R = {R} rays, got "
            f"{tuple(origins.shape)}, {tuple(dirs.shape)}, {tuple(jitter.shape)}"
        )
    n_free, n_front = layout.n_free, layout.n_front
    lay = np.array([layout.band_m, layout.front_stride_m, layout.truncation_m, layout.step_m], np.float32)
    o = np.ascontiguousarray(origins.detach().numpy(), dtype=np.float32)
    d = np.ascontiguousarray(dirs.detach().numpy(), dtype=np.float32)
    z = np.ascontiguousarray(depth.detach().numpy(), dtype=np.float32)
    jit = np.ascontiguousarray(jitter.numpy(), dtype=np.float32)
    table = walk_table(octree)
    counts = np.zeros(z.shape[0], np.int64)
    voxel_of = np.empty(jit.shape, np.int64)
    with parallel_region() as n_blocks:
        _band_kernel(
            o, d, z, jit, n_free, n_front, lay, octree.voxel_size_m, table.keys, table.ids, n_blocks, counts, voxel_of
        )
        n = int(counts.sum())
        points, t = np.empty((n, 3), np.float32), np.empty(n, np.float32)
        ray, voxel = np.empty(n, np.int64), np.empty(n, np.int64)
        offsets = np.cumsum(counts) - counts
        _band_fill(o, d, z, jit, n_free, n_front, lay, voxel_of, offsets, n_blocks, points, t, ray, voxel)
    return tuple(torch.from_numpy(a) for a in (points, t, ray, voxel))  # type: ignore[return-value]
