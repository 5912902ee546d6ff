"""Compiled test of points against observed cells (numba); `ObservedSupport.contains` over `dilated_rows` is the
reference.

One loop over the points: the 27 voxels around a point's voxel are looked up once, in the voxel hash table of
`voxel_walk_numba.build_table` (the ray walks use it too), and remembered in a small direct-mapped cache (marching emits
faces cell by cell and chunk by chunk, so nearly every point hits it); then the 27 cells around the point are
tested bit by bit. A neighbour cell in another voxel counts only along the path the reference's separable
dilation takes (z, then y, then x through allocated voxels), so both give the same answer everywhere.
"""

from __future__ import annotations

import numpy as np

from h2viz.mapping.kernels.jit import njit
from h2viz.mapping.kernels.voxel_walk_numba import build_table, lookup
from h2viz.mapping.meshing.observed import SUB

__all__ = ["build_table", "contains_kernel", "mark_kernel"]  # build_table: the voxel hash table the kernels look up
_SLOTS = 1024  # voxels whose neighbours are remembered (a power of two; a chunk has 512)


@njit
def contains_kernel(
    cells: np.ndarray, table_keys: np.ndarray, table_ids: np.ndarray, words: np.ndarray, strict: np.ndarray
) -> np.ndarray:
    """(N,) bool: integer cells (N,3) within one cell of an observed cell (their own cell in `strict` voxels;
    strict (V,) bool or empty), with words (V,8) uint64 the cell bits of voxel ids and (table_keys, table_ids)
    the voxels' `build_table`."""
    n = cells.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    # direct-mapped cache of voxels' neighbour ids: slot -> voxel coords (3,) and 27 ids, (dx+1)*9+(dy+1)*3+(dz+1)
    slot_voxel = np.full((_SLOTS, 3), np.iinfo(np.int64).min, dtype=np.int64)
    slot_nb = np.empty((_SLOTS, 27), dtype=np.int64)
    for i in range(n):
        cx, cy, cz = cells[i, 0], cells[i, 1], cells[i, 2]
        ux, uy, uz = cx // SUB, cy // SUB, cz // SUB  # floor division, as in the reference
        s = ((ux * 73856093) ^ (uy * 19349663) ^ (uz * 83492791)) & (_SLOTS - 1)
        nb = slot_nb[s]
        if slot_voxel[s, 0] != ux or slot_voxel[s, 1] != uy or slot_voxel[s, 2] != uz:
            slot_voxel[s, 0], slot_voxel[s, 1], slot_voxel[s, 2] = ux, uy, uz
            for k in range(27):
                nb[k] = lookup(table_keys, table_ids, ux + k // 9 - 1, uy + (k // 3) % 3 - 1, uz + k % 3 - 1)
        own = nb[13]
        if own < 0:
            continue
        lx, ly, lz = cx % SUB, cy % SUB, cz % SUB
        if strict.shape[0] and strict[own]:
            out[i] = (words[own, lx] >> np.uint64(ly * SUB + lz)) & np.uint64(1) != 0
            continue
        hit = False
        for dx in range(-1, 2):
            ax = lx + dx
            ox = -1 if ax < 0 else (1 if ax >= SUB else 0)
            if nb[(ox + 1) * 9 + 4] < 0:  # the x step reads voxel (ox, 0, 0)
                continue
            for dy in range(-1, 2):
                ay = ly + dy
                oy = -1 if ay < 0 else (1 if ay >= SUB else 0)
                if nb[(ox + 1) * 9 + (oy + 1) * 3 + 1] < 0:  # the y step reads voxel (ox, oy, 0)
                    continue
                for dz in range(-1, 2):
                    az = lz + dz
                    oz = -1 if az < 0 else (1 if az >= SUB else 0)
                    v = nb[(ox + 1) * 9 + (oy + 1) * 3 + oz + 1]  # the z step reads voxel (ox, oy, oz)
                    if v < 0:
                        continue
                    bit = np.uint64((ay % SUB) * SUB + az % SUB)
                    if (words[v, ax % SUB] >> bit) & np.uint64(1) != 0:
                        hit = True
                        break
                if hit:
                    break
            if hit:
                break
        out[i] = hit
    return out


@njit
def mark_kernel(
    points: np.ndarray, cell_m: float, table_keys: np.ndarray, table_ids: np.ndarray, words: np.ndarray
) -> None:
    """words (V,8) uint64 |= the bits of the cells that points (N,3) fall in, where their voxel is in the table
    (`ObservedCells.add`'s NumPy code is the reference). Neighbouring points share a voxel: its lookup is reused."""
    last_x, last_y, last_z, last_v = np.iinfo(np.int64).min, 0, 0, -1
    for i in range(points.shape[0]):
        cx = int(np.floor(points[i, 0] / cell_m))
        cy = int(np.floor(points[i, 1] / cell_m))
        cz = int(np.floor(points[i, 2] / cell_m))
        ux, uy, uz = cx // SUB, cy // SUB, cz // SUB  # floor division, as the reference's shift
        if ux != last_x or uy != last_y or uz != last_z:
            last_x, last_y, last_z = ux, uy, uz
            last_v = lookup(table_keys, table_ids, ux, uy, uz)
        if last_v < 0 or last_v >= words.shape[0]:
            continue
        words[last_v, cx % SUB] |= np.uint64(1) << np.uint64((cy % SUB) * SUB + cz % SUB)
