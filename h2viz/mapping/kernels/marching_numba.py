"""Compiled marching cubes over one chunk's lattice (numba), `marching.march` + `world_vertices` + `weld` the
reference (scikit-image's Lewiner marching cubes).

One pass over the masked cells emits triangles from `case_table`; each vertex is created once, keyed by its
lattice edge (or by the lattice point a crossing snaps to), so the mesh comes out welded. Vertex positions use
the reference's arithmetic on global lattice indices: a crossing on a face shared by two chunks gets the same
bits in both, whichever path meshed them.
"""

from __future__ import annotations

import numpy as np

from h2viz.mapping.kernels.jit import njit
from h2viz.mapping.meshing.case_table import case_table


@njit(inline=True)
def _vertex(
    x: int,
    y: int,
    z: int,
    axis: int,
    volume: np.ndarray,
    origin: np.ndarray,
    spacing: float,
    snap: float,
    edge_vertex: np.ndarray,
    point_vertex: np.ndarray,
    vertices: np.ndarray,
    n: int,
) -> tuple[int, int]:
    """(vertex id, vertex count) of the crossing on the lattice edge from point (x,y,z) along `axis`."""
    known = edge_vertex[x, y, z, axis]
    if known >= 0:
        return known, n
    ox, oy, oz = x, y, z
    if axis == 0:
        ox += 1
    elif axis == 1:
        oy += 1
    else:
        oz += 1
    v0 = np.float64(volume[x, y, z])
    v1 = np.float64(volume[ox, oy, oz])
    t = v0 / (v0 - v1) if v0 != v1 else 0.5
    if t < snap or t > 1.0 - snap:  # on a lattice point: shared with every edge that snaps there
        sx, sy, sz = (ox, oy, oz) if t > 1.0 - snap else (x, y, z)
        vid = point_vertex[sx, sy, sz]
        if vid < 0:
            vid = n
            point_vertex[sx, sy, sz] = vid
            px, py, pz = np.float64(origin[0] + sx), np.float64(origin[1] + sy), np.float64(origin[2] + sz)
            vertices[n, 0], vertices[n, 1], vertices[n, 2] = px * spacing, py * spacing, pz * spacing
            n += 1
    else:
        px, py, pz = np.float64(origin[0] + x), np.float64(origin[1] + y), np.float64(origin[2] + z)
        if axis == 0:
            px += t
        elif axis == 1:
            py += t
        else:
            pz += t
        vid = n
        vertices[n, 0], vertices[n, 1], vertices[n, 2] = px * spacing, py * spacing, pz * spacing
        n += 1
    edge_vertex[x, y, z, axis] = vid
    return vid, n


@njit
def _march_kernel(
    volume: np.ndarray,
    cells: np.ndarray,
    origin: np.ndarray,
    spacing: float,
    snap: float,
    counts: np.ndarray,
    table: np.ndarray,
    edge_corner: np.ndarray,
    edge_axis: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Vertices (N,3) float32 (world metres) and faces (M,3) int64 of the level-0 surface in the `cells`
    (X,Y,Z) bool of `volume` (X+1,Y+1,Z+1) float32, lattice index `origin` (3,) at volume[0,0,0], and whether
    snapping collapsed any triangle (then some vertices may be unused)."""
    nx, ny, nz = cells.shape
    pattern = np.zeros(cells.shape, dtype=np.uint8)
    n_faces = 0
    for x in range(nx):
        for y in range(ny):
            for z in range(nz):
                if not cells[x, y, z]:
                    continue
                p = 0
                for i in range(8):
                    if volume[x + ((i >> 2) & 1), y + ((i >> 1) & 1), z + (i & 1)] < 0:
                        p |= 1 << i
                pattern[x, y, z] = p
                n_faces += counts[p]
    faces = np.empty((n_faces, 3), dtype=np.int64)
    vertices = np.empty((3 * n_faces, 3), dtype=np.float32)
    edge_vertex = np.full((nx + 1, ny + 1, nz + 1, 3), -1, dtype=np.int32)
    point_vertex = np.full((nx + 1, ny + 1, nz + 1), -1, dtype=np.int32)
    n_vertices = 0
    m = 0
    ids = np.empty(3, dtype=np.int64)
    for x in range(nx):
        for y in range(ny):
            for z in range(nz):
                p = pattern[x, y, z]
                for t in range(counts[p]):
                    for k in range(3):
                        e = table[p, 3 * t + k]
                        c = edge_corner[e]
                        ids[k], n_vertices = _vertex(
                            x + ((c >> 2) & 1), y + ((c >> 1) & 1), z + (c & 1), edge_axis[e], volume, origin,
                            spacing, snap, edge_vertex, point_vertex, vertices, n_vertices,
                        )  # fmt: skip
                    if ids[0] != ids[1] and ids[1] != ids[2] and ids[0] != ids[2]:  # not collapsed by snapping
                        faces[m, 0], faces[m, 1], faces[m, 2] = ids[0], ids[1], ids[2]
                        m += 1
    return vertices[:n_vertices], faces[:m], m < n_faces


def march_welded(
    volume: np.ndarray, cells: np.ndarray, origin: np.ndarray, spacing_m: float, snap: float
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Welded world vertices (N,3) float32, faces (M,3) int64 and whether some vertices may be unused (snapping
    collapsed all their faces); see `_march_kernel`."""
    table = case_table()
    return _march_kernel(
        np.ascontiguousarray(volume, dtype=np.float32), np.ascontiguousarray(cells, dtype=np.bool_),
        np.asarray(origin, dtype=np.int64), float(spacing_m), float(snap), table.counts, table.edges,
        table.edge_corner, table.edge_axis,
    )  # fmt: skip


@njit
def _match_kernel(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Index (M,) of each row of new (M,3) uint32 in old (N,3) uint32, -1 when absent (open addressing)."""
    size = 1
    while size < 2 * len(old):
        size *= 2
    slots = np.full(size, -1, dtype=np.int64)
    for i in range(len(old)):
        s = _find_slot(slots, old, old, i)
        if slots[s] < 0:  # a repeated row keeps its first index
            slots[s] = i
    out = np.full(len(new), -1, dtype=np.int64)
    for i in range(len(new)):
        out[i] = slots[_find_slot(slots, old, new, i)]
    return out


@njit(inline=True)
def _find_slot(slots: np.ndarray, old: np.ndarray, rows: np.ndarray, i: int) -> int:
    """The slot holding the old row equal to rows[i], else the empty slot where the probe for it ends."""
    mask = len(slots) - 1
    h = (np.uint64(rows[i, 0]) * np.uint64(0x9E3779B1) ^ np.uint64(rows[i, 1]) * np.uint64(0x85EBCA77)
         ^ np.uint64(rows[i, 2]) * np.uint64(0xC2B2AE3D))  # fmt: skip
    s = np.int64(h ^ (h >> np.uint64(17))) & mask
    while slots[s] >= 0:
        j = slots[s]
        if old[j, 0] == rows[i, 0] and old[j, 1] == rows[i, 1] and old[j, 2] == rows[i, 2]:
            return s
        s = (s + 1) & mask
    return s


def match_vertices(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Index (M,) of each vertex of new (M,3) float32 in old (N,3) float32 when bit-identical there (-0.0 and
    0.0 count as equal), else -1."""
    bits = lambda v: (np.ascontiguousarray(v, dtype=np.float32) + np.float32(0.0)).view(np.uint32)  # noqa: E731
    return _match_kernel(bits(old), bits(new))


@njit
def _lattice_kernel(
    local: np.ndarray, dims: np.ndarray, resolution: int, flags: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`marching.chunk_lattice` for voxels at local coords (V,3) in a box of `dims` (3,) voxels: cells (X,Y,Z)
    bool, points (N,3) int64 in C order, each point's voxel row (N,) (that of its cell at the largest corner
    offset, as the reference's last write) and whether a cell of a flagged voxel has it as a corner (N,)."""
    r = resolution
    nx, ny, nz = dims[0] * r, dims[1] * r, dims[2] * r
    # each cell's voxel row (-1: none), cell (x, y, z) at [x + 1, y + 1, z + 1]: a border of -1 around the box
    # spares the corner loop below its bounds checks
    row_of = np.full((nx + 2, ny + 2, nz + 2), -1, dtype=np.int32)
    used = np.zeros((nx + 1, ny + 1, nz + 1), dtype=np.bool_)
    for i in range(len(local)):
        x0, y0, z0 = local[i, 0] * r, local[i, 1] * r, local[i, 2] * r
        row_of[x0 + 1 : x0 + r + 1, y0 + 1 : y0 + r + 1, z0 + 1 : z0 + r + 1] = i
        used[x0 : x0 + r + 1, y0 : y0 + r + 1, z0 : z0 + r + 1] = True
    n = int(used.sum())
    points = np.empty((n, 3), dtype=np.int64)
    point_voxel = np.empty(n, dtype=np.int64)
    point_flagged = np.zeros(n, dtype=np.bool_)
    k = 0
    for x in range(nx + 1):
        for y in range(ny + 1):
            for z in range(nz + 1):
                if not used[x, y, z]:
                    continue
                points[k, 0], points[k, 1], points[k, 2] = x, y, z
                first, flagged = -1, False
                for o in range(7, -1, -1):  # the cells this point is a corner of, largest offset first
                    row = row_of[x + 1 - ((o >> 2) & 1), y + 1 - ((o >> 1) & 1), z + 1 - (o & 1)]
                    if row < 0:
                        continue
                    if first < 0:
                        first = row
                    flagged |= flags[row]
                point_voxel[k], point_flagged[k] = first, flagged
                k += 1
    cells = row_of[1 : nx + 1, 1 : ny + 1, 1 : nz + 1] >= 0
    return cells, points, point_voxel, point_flagged


def lattice_arrays(
    local: np.ndarray, dims: np.ndarray, resolution: int, flags: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """See `_lattice_kernel`."""
    return _lattice_kernel(
        np.ascontiguousarray(local, dtype=np.int64), np.asarray(dims, dtype=np.int64), int(resolution),
        np.ascontiguousarray(flags, dtype=np.bool_),
    )  # fmt: skip
