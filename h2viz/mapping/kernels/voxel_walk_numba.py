"""Numba kernels of the ray walks through the allocated leaf voxels (the Python side is voxel_walk.py).

A walk is an exact 3-D DDA that jumps over empty space: the leaves sit in an open-addressing hash table (key =
the octree's packed cell key, value = voxel id), rays are clipped to the map's bounding box, and a grid of
chessboard distances to the nearest allocated voxel lets a walk skip the cells that cannot hold one. Every
helper that the kernels inline lives in this module: numba's on-disk cache only notices edits to the file a
cached function is defined in. Parallel kernels are entered under `jit.parallel_region()`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numba
import numpy as np

from h2viz.mapping.field.octree import OFFSET
from h2viz.mapping.kernels.jit import njit

if TYPE_CHECKING:
    from h2viz.mapping.kernels.voxel_walk import WalkTable

_HASH_MULT = -7046029254386353131  # 0x9E3779B97F4A7C15 as int64 (Fibonacci hashing)
PROBE, COARSE, TRUSTED = 1, 2, 4  # lattice flags
MODES = {"trust": 0, "distrust": 1, "prior": 2}


@njit
def _slot(key: int, mask: int) -> int:
    h = key * _HASH_MULT
    return (h ^ (h >> 29)) & mask


@njit
def build_table(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hash table (keys (cap,), ids (cap,)) with cap a power of two >= 2 * len(keys); -1 marks empty slots."""
    cap = 16
    while cap < 2 * keys.shape[0]:
        cap *= 2
    table_keys = np.full(cap, -1, np.int64)
    table_ids = np.full(cap, -1, np.int64)
    for i in range(keys.shape[0]):
        s = _slot(keys[i], cap - 1)
        while table_keys[s] != -1:
            s = (s + 1) & (cap - 1)
        table_keys[s] = keys[i]
        table_ids[s] = i
    return table_keys, table_ids


@njit(inline=True)
def lookup(table_keys: np.ndarray, table_ids: np.ndarray, cx: int, cy: int, cz: int) -> int:
    """Voxel id of cell (cx, cy, cz), -1 when not allocated."""
    key = ((cx + OFFSET) << 42) | ((cy + OFFSET) << 21) | (cz + OFFSET)
    mask = table_keys.shape[0] - 1
    s = _slot(key, mask)
    while table_keys[s] != -1:
        if table_keys[s] == key:
            return table_ids[s]
        s = (s + 1) & mask
    return -1


@njit(inline=True)
def clip(o: np.ndarray, d: np.ndarray, box: np.ndarray, t0: float, t1: float) -> tuple[float, float]:
    """[t0, t1] clipped to the box (2,3) [lo, hi] in metres (empty when t0 >= t1)."""
    for a in range(3):
        if d[a] != 0.0:
            ta, tb = (box[0, a] - o[a]) / d[a], (box[1, a] - o[a]) / d[a]
            t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
        elif o[a] < box[0, a] or o[a] > box[1, a]:
            return t0, t0
    return t0, t1


@njit(inline=True)
def _axis(o: float, d: float, t: float, vs: float) -> tuple[int, int, float, float]:
    """One axis of a walk at t: cell, step sign, t of the next cell boundary, t between boundaries."""
    c = np.floor((o + d * t) / vs)
    if d > 0.0:
        return np.int64(c), 1, ((c + 1.0) * vs - o) / d, vs / d
    if d < 0.0:
        return np.int64(c), -1, (c * vs - o) / d, -vs / d
    return np.int64(c), 0, np.inf, np.inf


@njit(inline=True)
def _free_cells(table: WalkTable, cx: int, cy: int, cz: int) -> int:
    """Chessboard distance, in skip cells, from the skip cell of voxel cell (cx, cy, cz) to an allocated voxel."""
    g, lo, sh = table.skip, table.skip_lo, table.skip_shift
    ix = min(max((cx >> sh) - lo[0], 0), g.shape[0] - 1)
    iy = min(max((cy >> sh) - lo[1], 0), g.shape[1] - 1)
    iz = min(max((cz >> sh) - lo[2], 0), g.shape[2] - 1)
    return g[ix, iy, iz]


@njit(inline=True)
def walk_begin(o: np.ndarray, d: np.ndarray, t: float, vs: float) -> Any:
    """Walk state at t: (t, cell x y z, step sign x y z, next boundary t x y z, t between boundaries x y z)."""
    cx, sx, nx, dx = _axis(o[0], d[0], t, vs)
    cy, sy, ny, dy = _axis(o[1], d[1], t, vs)
    cz, sz, nz, dz = _axis(o[2], d[2], t, vs)
    return t, cx, cy, cz, sx, sy, sz, nx, ny, nz, dx, dy, dz


@njit(inline=True)
def walk_next(o: np.ndarray, d: np.ndarray, t1: float, table: WalkTable, state: Any) -> Any:
    """The next allocated voxel the ray crosses before t1, as (id, t_in, t_out, cx, cy, cz, state); id -1
    at the end. Steps cell to cell across the nearest boundary (first axis on ties) and jumps over empty
    space: from a skip cell whose nearest allocated voxel is k >= 2 skip cells away, every point within k - 1
    skip cells (L-inf) is free, so t advances by (k - 1) skip cells / max |d|."""
    vs = table.voxel_size
    t, cx, cy, cz, sx, sy, sz, nx, ny, nz, dx, dy, dz = state
    while t < t1:
        vid = lookup(table.keys, table.ids, cx, cy, cz)
        if vid < 0:
            k = _free_cells(table, cx, cy, cz)
            if k >= 2:
                jump = (k - 1) * vs * (1 << table.skip_shift) / max(abs(d[0]), abs(d[1]), abs(d[2]))
                t, cx, cy, cz, sx, sy, sz, nx, ny, nz, dx, dy, dz = walk_begin(o, d, t + jump, vs)
                continue
        t_in, px, py, pz = t, cx, cy, cz
        if nx <= ny and nx <= nz:
            t, cx, nx = nx, cx + sx, nx + dx
        elif ny <= nz:
            t, cy, ny = ny, cy + sy, ny + dy
        else:
            t, cz, nz = nz, cz + sz, nz + dz
        if vid >= 0 and min(t, t1) > t_in:
            return vid, t_in, min(t, t1), px, py, pz, (t, cx, cy, cz, sx, sy, sz, nx, ny, nz, dx, dy, dz)
    return -1, t1, t1, 0, 0, 0, (t, cx, cy, cz, sx, sy, sz, nx, ny, nz, dx, dy, dz)


@njit(inline=True)
def trilinear(corner: np.ndarray, fx: float, fy: float, fz: float) -> float:
    """Blend of 8 corner values (x,y,z bits 4,2,1) at local coordinates clamped to [0, 1]."""
    fx, fy, fz = min(max(fx, 0.0), 1.0), min(max(fy, 0.0), 1.0), min(max(fz, 0.0), 1.0)
    c00 = corner[0] * (1 - fx) + corner[4] * fx
    c01 = corner[1] * (1 - fx) + corner[5] * fx
    c10 = corner[2] * (1 - fx) + corner[6] * fx
    c11 = corner[3] * (1 - fx) + corner[7] * fx
    return (c00 * (1 - fy) + c10 * fy) * (1 - fz) + (c01 * (1 - fy) + c11 * fy) * fz


@njit(parallel=True)
def hits_kernel(o: np.ndarray, d: np.ndarray, t_near: np.ndarray, t_far: np.ndarray, table: WalkTable,
                 offsets: np.ndarray, write: bool, out_voxel: np.ndarray, out_t: np.ndarray,
                 n_blocks: int) -> np.ndarray:  # fmt: skip
    """Per-ray hit counts (R,); with `write`, the hits at `offsets`. Block b walks rays b, b + n_blocks, ..."""
    counts = np.zeros(o.shape[0], np.int64)
    for b in numba.prange(n_blocks):
        for r in range(b, o.shape[0], n_blocks):
            t0, t1 = clip(o[r], d[r], table.box, t_near[r], t_far[r])
            n, pos, state = 0, offsets[r], walk_begin(o[r], d[r], t0, table.voxel_size)
            while True:
                vid, t_in, t_out, _, _, _, state = walk_next(o[r], d[r], t1, table, state)
                if vid < 0:
                    break
                if write:
                    out_voxel[pos + n], out_t[pos + n, 0], out_t[pos + n, 1] = vid, t_in, t_out
                n += 1
            counts[r] = n
    return counts


@njit(inline=True)
def _near_miss(prev_trusted: bool, prev_prior: float, trusted: bool, prior: float, probe_below: float) -> bool:
    """Is the previous sample the closest approach of trusted priors to zero (without crossing it)?"""
    return prev_trusted and 0.0 <= prev_prior < probe_below and (not trusted or prior > prev_prior)


@njit(inline=True)
def _ray_lattice(o: np.ndarray, d: np.ndarray, t1: float, table: WalkTable, priors: np.ndarray,
                 corner_ids: np.ndarray, trusted: np.ndarray, step: float, mode: int, probe_below: float,
                 after_m: float, pos: int, out_t: np.ndarray, out_voxel: np.ndarray, out_prior: np.ndarray,
                 out_flags: np.ndarray, corner: np.ndarray) -> tuple[int, float]:  # fmt: skip
    """Lattice samples of one ray written from `pos` (see voxel_walk.py); returns the count and the first prior
    crossing + after_m (inf when none), up to which the list holds every sample. corner (8,) is scratch."""
    t0, t1 = clip(o, d, table.box, 0.0, t1)
    vs, inv_vs, step32 = table.voxel_size, 1.0 / table.voxel_size, np.float32(step)
    n, t_stop, prev_trusted, prev_prior = 0, np.inf, False, np.inf
    state = walk_begin(o, d, t0, vs)
    while True:
        vid, t_in, t_out, cx, cy, cz, state = walk_next(o, d, t1, table, state)
        if vid < 0:
            break
        trust = mode == 2 or (mode == 0 and trusted[vid])
        for c in range(8):
            corner[c] = priors[corner_ids[vid, c]]
        t_in32, t_out32 = np.float32(t_in), np.float32(t_out)  # float32 like sample_hits: the same positions
        k_max = max(1, int(np.ceil((t_out32 - t_in32) / step32)))
        for k in range(k_max):
            t = min(t_in32 + (np.float32(k) + np.float32(0.5)) * step32, t_out32)
            if t > t_stop:
                return n, t_stop
            fx = (o[0] + d[0] * t) * inv_vs - cx
            fy = (o[1] + d[1] * t) * inv_vs - cy
            prior = trilinear(corner, fx, fy, (o[2] + d[2] * t) * inv_vs - cz)
            flag = 0
            if trust:
                flag = TRUSTED
                if t_stop == np.inf and prior < 0.0:  # the first prior crossing: probe both sides
                    t_stop, flag = t + after_m, flag | PROBE
                    if n > 0:
                        out_flags[pos + n - 1] |= PROBE
            elif k % 3 == 0 or k == k_max - 1:
                flag = PROBE | COARSE
            if t_stop == np.inf and _near_miss(prev_trusted, prev_prior, trust, prior, probe_below):
                out_flags[pos + n - 1] |= PROBE  # the previous sample is the closest approach of a near miss
            prev_trusted, prev_prior = trust, prior
            out_t[pos + n], out_voxel[pos + n], out_prior[pos + n], out_flags[pos + n] = t, vid, prior, flag
            n += 1
    if t_stop == np.inf and _near_miss(prev_trusted, prev_prior, False, 0.0, probe_below):
        out_flags[pos + n - 1] |= PROBE  # the walk ends while the prior still approaches zero
    return n, t_stop


@njit(inline=True)
def _most_samples(o: np.ndarray, d: np.ndarray, t1: float, table: WalkTable, step: float) -> int:
    """An upper bound of one ray's lattice samples: one per step plus one per cell crossed."""
    t0, t1 = clip(o, d, table.box, 0.0, t1)
    length = max(t1 - t0, 0.0)
    return int(length / step + length * (abs(d[0]) + abs(d[1]) + abs(d[2])) / table.voxel_size) + 4


@njit
def lattice_chunk(o: np.ndarray, d: np.ndarray, t_far: np.ndarray, r0: int, r1: int, table: WalkTable,
                  priors: np.ndarray, corner_ids: np.ndarray, trusted: np.ndarray, step: float, mode: int,
                  probe_below: float, after_m: float) -> Any:  # fmt: skip
    """Lattice of rays r0..r1-1 in one pass into arrays that grow as needed: (t, voxel, prior, flags) of the
    samples, and per ray the count and the crossing end. Runs without the GIL (one chunk per thread)."""
    cap = 32 * (r1 - r0) + 64
    t, voxel, prior, flags = (
        np.empty(cap, np.float32),
        np.empty(cap, np.int64),
        np.empty(cap, np.float32),
        np.empty(cap, np.uint8),
    )
    counts, crossing_end, corner, pos = np.empty(r1 - r0, np.int64), np.empty(r1 - r0), np.empty(8), 0
    for q in range(r1 - r0):
        need = pos + _most_samples(o[r0 + q], d[r0 + q], t_far[r0 + q], table, step)
        if need > cap:
            cap = max(2 * cap, need)
            t, voxel, prior, flags = _grown(t, cap), _grown(voxel, cap), _grown(prior, cap), _grown(flags, cap)
        counts[q], crossing_end[q] = _ray_lattice(
            o[r0 + q], d[r0 + q], t_far[r0 + q], table, priors, corner_ids, trusted, step, mode, probe_below,
            after_m, pos, t, voxel, prior, flags, corner,
        )  # fmt: skip
        pos += counts[q]
    return t[:pos], voxel[:pos], prior[:pos], flags[:pos], counts, crossing_end


@njit(inline=True)
def _grown(a: np.ndarray, cap: int) -> np.ndarray:
    out = np.empty(cap, a.dtype)
    out[: a.shape[0]] = a
    return out
