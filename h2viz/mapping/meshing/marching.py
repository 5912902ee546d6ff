"""Masked marching cubes on one chunk's part of the global SDF lattice, with chunk-independent vertices.

A chunk samples the lattice (spacing voxel_size_m / resolution) only at corners of cells inside its
allocated voxels, and only those cells produce triangles. Edge crossings are recomputed from the two
lattice values of their edge in global lattice indices, so a crossing on a face shared by two chunks gets
bit-identical coordinates in both and `weld` merges them by exact match.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Iterator
from dataclasses import dataclass
from types import ModuleType

import numpy as np
from skimage.measure import marching_cubes

from h2viz.geometry import drop_unused_vertices

SNAP = 1e-4  # crossings closer than this (in edge lengths) to a lattice point are placed on it


@dataclass(frozen=True)
class ChunkLattice:
    """The part of the global lattice that one chunk samples."""

    key: tuple[int, int, int]
    origin: np.ndarray  # (3,) int64 global lattice index of local index (0,0,0)
    cells: np.ndarray  # (X,Y,Z) bool, cells (by lower corner) inside allocated voxels
    points: np.ndarray  # (N,3) int64 local lattice indices of every corner of those cells
    point_voxel: np.ndarray  # (N,) int64 row (into the chunk's voxels) of a voxel containing each point
    point_flagged: np.ndarray  # (N,) bool, the point is a corner of a cell of a flagged voxel


def corner_slices(shape: tuple[int, ...]) -> Iterator[tuple[slice, ...]]:
    """Slices of a (X+1,Y+1,Z+1) corner array that line each of the 8 cell corners up with (X,Y,Z) cells."""
    for offset in itertools.product((0, 1), repeat=3):
        yield tuple(slice(o, o + n) for o, n in zip(offset, shape, strict=True))


def chunk_lattice(
    key: tuple[int, int, int],
    voxels: np.ndarray,
    resolution: int,
    flags: np.ndarray | None = None,
    fast: ModuleType | None = None,
) -> ChunkLattice:
    """Cells and needed lattice points of one chunk's allocated voxels (V,3) (global voxel coords); `flags`
    (V,) marks voxels whose points are reported in `point_flagged`. `fast`: the compiled kernels
    (h2viz.mapping.kernels.marching_numba, a backend's `array_kernels.marching`), None for this NumPy code."""
    lo = voxels.min(axis=0)
    if fast is not None:
        marks = np.zeros(len(voxels), dtype=bool) if flags is None else flags
        cells, points, voxel, flagged = fast.lattice_arrays(voxels - lo, voxels.max(axis=0) - lo + 1, resolution, marks)
        return ChunkLattice(key, lo * resolution, cells, points, voxel, flagged)
    rows = np.full(voxels.max(axis=0) - lo + 1, -1, dtype=np.int32)  # voxel row per occupied voxel cell
    rows[tuple((voxels - lo).T)] = np.arange(len(voxels), dtype=np.int32)
    cell_rows = rows.repeat(resolution, 0).repeat(resolution, 1).repeat(resolution, 2)  # (X,Y,Z)
    cells = cell_rows >= 0
    flagged_cells = cells & np.append(np.zeros(len(voxels), bool) if flags is None else flags, False)[cell_rows]
    point_rows = np.full(np.add(cells.shape, 1), -1, dtype=np.int32)  # (X+1,Y+1,Z+1)
    flagged = np.zeros(point_rows.shape, dtype=bool)
    for sl in corner_slices(cells.shape):  # a point takes the voxel of any cell it is a corner of
        np.copyto(point_rows[sl], cell_rows, where=cells)
        flagged[sl] |= flagged_cells
    points = np.argwhere(point_rows >= 0)
    at = tuple(points.T)
    return ChunkLattice(key, lo * resolution, cells, points, point_rows[at].astype(np.int64), flagged[at])


def unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique int64 rows (U,3) of (N,3), the index (U,) of each one's first occurrence and the inverse
    index (N,) (packed keys when the span allows)."""
    if len(rows) == 0:
        return rows, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    keys = pack_rows(rows, rows.min(axis=0), rows.max(axis=0))
    if keys is None:
        _, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    else:
        _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    return rows[first], first, inverse.reshape(-1)


def pack_rows(rows: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray | None:
    """One int64 key (N,) per integer row (N,3) inside the box [lo, hi], or None when the box is too large."""
    span = np.asarray(hi, dtype=np.int64) - lo + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0**62:
        return None
    d = rows - lo
    return (d[:, 0] * span[1] + d[:, 1]) * span[2] + d[:, 2]


def unpack_rows(keys: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The integer rows (N,3) int64 of keys (N,) made by `pack_rows` with the same box."""
    lo = np.asarray(lo, dtype=np.int64)
    span = np.asarray(hi, dtype=np.int64) - lo + 1
    out = np.empty((len(keys), 3), np.int64)
    out[:, 0], out[:, 1], out[:, 2] = keys // (span[1] * span[2]), keys // span[2] % span[1], keys % span[2]
    return out + lo


def on_chunk_face(lat: ChunkLattice, chunk_cells: int) -> np.ndarray:
    """(N,) bool: which of the lattice's points lie on a chunk face (global index % chunk_cells == 0)."""
    on_face = [(o + np.arange(n + 1)) % chunk_cells == 0 for o, n in zip(lat.origin, lat.cells.shape, strict=True)]
    p = lat.points
    return on_face[0][p[:, 0]] | on_face[1][p[:, 1]] | on_face[2][p[:, 2]]


@functools.cache
def mask_offset() -> int:
    """Index shift (0 or 1) between a cell's lower corner and the mask entry skimage reads for that cell."""
    volume = np.broadcast_to(np.array([-1, 1, 1], np.float32)[:, None, None], (3, 3, 3)).copy()
    mask = np.zeros((3, 3, 3), dtype=bool)
    mask[1, 1, 1] = True  # the crossing is only in cells with lower corner x = 0
    try:
        marching_cubes(volume, 0.0, mask=mask)
    except RuntimeError:
        return 0
    return 1


def lattice_volume(lat: ChunkLattice, values: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The dense volume (X+1,Y+1,Z+1) float32 of a lattice's values (N,) and its cells (X,Y,Z) bool without those
    with a non-finite corner; None when no cell can hold a level-0 crossing."""
    finite = np.isfinite(values)
    sampled = values if finite.all() else values[finite]
    if len(sampled) == 0 or sampled.min() > 0 or sampled.max() <= 0:
        return None
    volume = np.zeros(np.add(lat.cells.shape, 1), dtype=np.float32)  # unsampled points: never read
    volume[tuple(lat.points.T)] = np.where(finite, values, np.float32(0.0))
    cells = lat.cells
    if not finite.all():  # drop cells with a non-finite corner
        bad = np.zeros(volume.shape, dtype=bool)
        bad[tuple(lat.points[~finite].T)] = True
        cells = cells.copy()
        for sl in corner_slices(cells.shape):
            cells &= ~bad[sl]
    return volume, cells


def march(lat: ChunkLattice, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Marching cubes (level 0, scikit-image) over a lattice's cells given values (N,) at its points.

    Returns local vertices (N,3), faces (M,3) and the dense volume (X+1,Y+1,Z+1), or None when empty.
    """
    prepared = lattice_volume(lat, values)
    if prepared is None:
        return None
    volume, cells = prepared
    off = mask_offset()
    mask = np.zeros(volume.shape, dtype=bool)
    mask[off : off + cells.shape[0], off : off + cells.shape[1], off : off + cells.shape[2]] = cells
    try:  # "descent" with (x,y,z) axes orients faces towards positive SDF (free space)
        verts, faces, _, _ = marching_cubes(volume, 0.0, mask=mask, gradient_direction="descent")
    except RuntimeError:  # no crossing inside the masked cells
        return None
    return verts, faces.astype(np.int64), volume


def surface_mesh(
    lat: ChunkLattice, values: np.ndarray, spacing_m: float, fast: ModuleType | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Welded world vertices (N,3) float32 and faces (M,3) int64 of the level-0 surface of a lattice's values
    (N,): compiled with `fast` (h2viz.mapping.kernels.marching_numba), else scikit-image's marching cubes welded by
    position. Both place every crossing at the same bits."""
    if fast is None:
        marched = march(lat, values)
        if marched is None:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64)
        verts, faces, volume = marched
        vertices, faces, _ = weld(world_vertices(verts, volume, lat.origin, spacing_m), faces)
        return vertices, faces
    prepared = lattice_volume(lat, values)
    if prepared is None:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64)
    vertices, faces, collapsed = fast.march_welded(*prepared, lat.origin, spacing_m, SNAP)
    if not collapsed:
        return vertices, faces
    used, faces = drop_unused_vertices(len(vertices), faces)
    return vertices[used], faces


def world_vertices(verts: np.ndarray, volume: np.ndarray, origin: np.ndarray, spacing_m: float) -> np.ndarray:
    """World positions (N,3) float32 of marching-cubes vertices (N,3) given in local lattice units.

    A crossing on lattice edge (g, g+e) is placed at (g + t e) * spacing with t from the two lattice values,
    computed in global indices: the result does not depend on which chunk produced it.
    """
    c = verts.astype(np.float64)
    integral = c == np.round(c)  # skimage writes the two fixed coordinates of an edge vertex exactly
    on_edge = integral.sum(axis=1) == 2
    out = origin + c  # interior (cell-centre) vertices keep their position
    at_point = integral.all(axis=1)
    out[at_point] = origin + np.round(c[at_point])
    step = np.eye(3, dtype=np.int64)[np.argmin(integral[on_edge], axis=1)]  # (E,3) edge direction
    lo = np.floor(c[on_edge]).astype(np.int64)
    v0 = volume[tuple(lo.T)].astype(np.float64)
    v1 = volume[tuple((lo + step).T)].astype(np.float64)
    t = np.divide(v0, v0 - v1, out=np.full_like(v0, 0.5), where=v0 != v1)
    t = np.where(t < SNAP, 0.0, np.where(t > 1.0 - SNAP, 1.0, t))
    out[on_edge] = (origin + lo) + step * t[:, None]
    return (out * spacing_m).astype(np.float32)


def weld(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge bit-identical vertices, drop faces that collapse and vertices left unused.

    Returns vertices (U,3) float32, faces (M,3) int64 and, per kept vertex, its index in the input.
    """
    v = np.ascontiguousarray(vertices, dtype=np.float32) + np.float32(0.0)  # -0.0 -> +0.0
    _, first, inverse = np.unique(v.view(np.dtype((np.void, 12))).ravel(), return_index=True, return_inverse=True)
    f = inverse.reshape(-1)[faces]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    used, f = drop_unused_vertices(len(first), f)
    source = first[used]
    return v[source], f, source
