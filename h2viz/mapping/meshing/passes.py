"""What one mesher update works on: the voxels grouped by chunk, the work items (which points of which chunk
to evaluate) cut into passes, and the coloured surface of a chunk's lattice values."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import Enum
from types import ModuleType

import numpy as np

from h2viz.geometry import drop_unused_vertices
from h2viz.mapping.meshing.field_values import ColorFn, FaceValues, MeshingError, SdfFn, call_field
from h2viz.mapping.meshing.marching import ChunkLattice, surface_mesh
from h2viz.types import MeshChunk

ChunkKey = tuple[int, int, int]
KeepFn = Callable[[np.ndarray], np.ndarray]
"""Points (N,3) -> (N,) bool: faces whose centroid it rejects are left out of the mesh."""
POINTS_PER_PASS = 1 << 17  # lattice points evaluated together: the granularity of progress
REFRESH_POINTS_PER_PASS = 1 << 15  # the same for optional refresh work: the granularity of its time budget


class Eval(Enum):
    """Which lattice points of a chunk an item evaluates (the others come from the chunk's cache)."""

    NEW = "new"  # only points the cache does not know (cells of new voxels)
    DIRTY = "dirty"  # also the points of the chunk's dirty voxels
    WHOLE = "whole"  # every point


Item = tuple[ChunkKey, Eval]


def signature_head(resolution: int, filtered: bool) -> bytes:
    """The first bytes of a chunk signature: resolution (4 bytes, what a chunk's value cache depends on), then
    whether faces went through a keep_fn (1 byte)."""
    return resolution.to_bytes(4, "little") + (b"\x01" if filtered else b"\x00")


@dataclass(frozen=True)
class Meshed:
    """What a chunk was last meshed from."""

    signature: bytes  # resolution and sorted voxel coordinates
    field_version: int  # of the field all its lattice values were last evaluated from
    version: int  # update that last re-meshed it


NEVER = Meshed(b"", -1, -1)


@dataclass(frozen=True)
class Group:
    """The voxels of one chunk."""

    coords: np.ndarray  # (n,3) int64, sorted
    ids: np.ndarray  # (n,) int64 the caller's ids (handed to sdf_fn)
    flags: np.ndarray  # (n,) bool dirty voxels
    n_flagged: int  # flags.sum(), counted for all chunks at once


def group_voxels(coords: np.ndarray, ids: np.ndarray, flags: np.ndarray, chunk_voxels: int) -> dict[ChunkKey, Group]:
    """Unique voxels (V,3) with their ids (V,) and flags (V,) split by chunk key floor(coord / chunk_voxels),
    sorted within each chunk (so equal voxel sets give equal bytes)."""
    if len(coords) == 0:
        return {}
    keys = np.floor_divide(coords, chunk_voxels)
    order = np.lexsort((coords[:, 2], coords[:, 1], coords[:, 0], keys[:, 2], keys[:, 1], keys[:, 0]))
    coords, keys, ids, flags = coords[order], keys[order], ids[order], flags[order]
    fresh = np.ones(len(coords), dtype=bool)
    fresh[1:] = np.any(coords[1:] != coords[:-1], axis=1)  # drop repeated voxels
    coords, keys, ids, flags = coords[fresh], keys[fresh], ids[fresh], flags[fresh]
    starts = np.flatnonzero(np.r_[True, np.any(keys[1:] != keys[:-1], axis=1)])
    bounds = [*starts.tolist(), len(coords)]  # plain slices: np.split costs ~10 us a piece, 60 ms at 100k voxels
    counts = np.add.reduceat(flags.astype(np.int64), starts).tolist()
    return {
        (k[0], k[1], k[2]): Group(coords[a:b], ids[a:b], flags[a:b], n)
        for k, a, b, n in zip(keys[starts].tolist(), bounds[:-1], bounds[1:], counts, strict=True)
    }


class Update:
    """What one `ChunkedMesher.update` call works with."""

    def __init__(
        self,
        groups: dict[ChunkKey, Group],
        resolution: int,
        sdf_fn: SdfFn,
        color_fn: ColorFn,
        version: int,
        field_version: int,
        keep_fn: KeepFn | None = None,
    ) -> None:
        self.groups, self.resolution = groups, resolution
        self.sdf_fn, self.color_fn, self.keep_fn = sdf_fn, color_fn, keep_fn
        self.version, self.field_version = version, field_version
        coords = np.concatenate([g.coords for g in groups.values()]) if groups else np.zeros((1, 3), np.int64)
        self.faces = FaceValues(coords.min(axis=0) * resolution, (coords.max(axis=0) + 1) * resolution)

    def signature(self, key: ChunkKey) -> bytes:
        """Resolution, whether faces are filtered, and voxel set: a chunk meshed under others is re-meshed."""
        return signature_head(self.resolution, self.keep_fn is not None) + self.groups[key].coords.tobytes()

    def passes(self, items: list[Item], refresh: bool = False) -> Iterator[list[Item]]:
        """Items in passes of about POINTS_PER_PASS (REFRESH_POINTS_PER_PASS for `refresh` work) evaluated
        lattice points (a single pass when face values cannot be carried from one pass to the next)."""
        batch: list[Item] = []
        n_points = 0
        limit = (REFRESH_POINTS_PER_PASS if refresh else POINTS_PER_PASS) if self.faces.enabled else math.inf
        for key, mode in items:
            batch.append((key, mode))
            g = self.groups[key]
            voxels = {Eval.NEW: 1, Eval.DIRTY: 1 + g.n_flagged, Eval.WHOLE: len(g.coords)}[mode]
            n_points += voxels * self.resolution**3
            if n_points >= limit:
                yield batch
                batch, n_points = [], 0
        if batch:
            yield batch


def surface(
    lat: ChunkLattice, values: np.ndarray, spacing_m: float, fast: ModuleType | None = None
) -> tuple[ChunkKey, np.ndarray, np.ndarray] | None:
    """(key, welded world vertices (N,3), faces (M,3)) of one chunk's lattice values, or None when empty; `fast`
    as in `surface_mesh`."""
    vertices, faces = surface_mesh(lat, values, spacing_m, fast)
    return (lat.key, vertices, faces) if len(faces) else None


def kept_faces(
    surfaces: list[tuple[ChunkKey, np.ndarray, np.ndarray]], keep_fn: KeepFn
) -> list[tuple[ChunkKey, np.ndarray, np.ndarray]]:
    """The surfaces without the faces whose centroid `keep_fn` rejects (and without the vertices only they used),
    leaving out surfaces with no face left; one keep_fn call for all of them."""
    if not surfaces:
        return []
    offsets = np.cumsum([0] + [len(v) for _, v, _ in surfaces[:-1]])
    points = np.concatenate([v for _, v, _ in surfaces])  # (N,3) every surface's vertices
    corners = np.concatenate([f + o for (_, _, f), o in zip(surfaces, offsets, strict=True)])  # (M,3) into points
    centroids = (points[corners[:, 0]] + points[corners[:, 1]] + points[corners[:, 2]]) / np.float32(3.0)
    keep = np.asarray(keep_fn(centroids), dtype=bool)  # (M,)
    ends = np.cumsum([len(faces) for _, _, faces in surfaces])
    out = []
    for surface, kept in zip(surfaces, np.split(keep, ends[:-1]), strict=True):
        key, vertices, faces = surface
        if kept.all():
            out.append(surface)
        elif kept.any():
            used, faces = drop_unused_vertices(len(vertices), faces[kept])
            out.append((key, vertices[used], faces))
    return out


def coloured(
    surfaces: list[tuple[ChunkKey, np.ndarray, np.ndarray]],
    color_fn: ColorFn,
    version: int,
    previous: dict[ChunkKey, MeshChunk],
    fast: ModuleType | None = None,
) -> dict[ChunkKey, MeshChunk]:
    """MeshChunks of the surfaces, coloured by one color_fn call. A vertex at exactly the position it had in
    the chunk's `previous` mesh keeps its colour (pass only the chunks whose colours may be kept); `fast` as in
    `surface_mesh`."""
    if not surfaces:
        return {}
    kept = [_same_vertex(v, previous[key], fast) if key in previous else None for key, v, _ in surfaces]
    ask = [np.ones(len(v), bool) if k is None else k < 0 for (_, v, _), k in zip(surfaces, kept, strict=True)]
    points = np.concatenate([v[a] for (_, v, _), a in zip(surfaces, ask, strict=True)])
    colors = call_field(color_fn, "color_fn", 3, points) if len(points) else np.zeros((0, 3), np.uint8)
    if colors.dtype != np.uint8:
        raise MeshingError(f"meshing: color_fn must return uint8 colours (0..255), got {colors.dtype}")
    out, start = {}, 0
    for (key, vertices, faces), k, a in zip(surfaces, kept, ask, strict=True):
        rgb = np.empty((len(vertices), 3), dtype=np.uint8)
        if k is not None:
            rgb[~a] = previous[key].colors[k[~a]]
        rgb[a] = colors[start : start + int(a.sum())]
        start += int(a.sum())
        out[key] = MeshChunk(key, vertices, faces.astype(np.int32), rgb, int(version))
    return out


def _same_vertex(vertices: np.ndarray, before: MeshChunk, fast: ModuleType | None = None) -> np.ndarray:
    """Index (N,) of each vertex (N,3) float32 in `before.vertices` when bit-identical there, else -1."""
    if fast is not None:
        return fast.match_vertices(before.vertices, vertices)
    n_old = len(before.vertices)
    both = np.concatenate([before.vertices, vertices]).astype(np.float32) + np.float32(0.0)  # -0.0 -> +0.0
    _, first, inverse = np.unique(both.view(np.dtype((np.void, 12))).ravel(), return_index=True, return_inverse=True)
    match = first[inverse.reshape(-1)[n_old:]]
    return np.where(match < n_old, match, -1)
