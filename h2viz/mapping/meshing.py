"""Chunked, welded meshing of the sparse voxel map: re-meshes only changed chunks, merges and exports.

The map is cut into chunks of chunk_voxels^3 leaf voxels, keyed by floor(voxel / chunk_voxels). Each chunk
keeps its own MeshChunk; `update` re-meshes the chunks it is told changed (and those whose voxel set
changed) and hands back the same objects for the others, so a viewer can diff by identity or `.version`.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path

import numpy as np
import trimesh

from h2viz.errors import ConfigError, H2vizError
from h2viz.mapping.marching import (
    ChunkLattice,
    chunk_lattice,
    march,
    on_chunk_face,
    unique_rows,
    weld,
    world_vertices,
)
from h2viz.types import MeshChunk

log = logging.getLogger(__name__)

ChunkKey = tuple[int, int, int]
SdfFn = Callable[[np.ndarray], np.ndarray]  # points (N,3) float32 -> SDF (N,) float32 metres
ColorFn = Callable[[np.ndarray], np.ndarray]  # points (N,3) float32 -> colours (N,3) uint8
EXPORT_SUFFIXES = (".ply", ".glb", ".obj")
MAX_LATTICE_CELLS = 1024  # lattice cells along a chunk edge (chunk_voxels * resolution)
_FIELD_BATCH = 1 << 20  # points per sdf_fn / color_fn call
_POINTS_PER_PASS = 1 << 22  # lattice points sampled together (bounds memory on full re-meshes)


class MeshingError(H2vizError):
    """A field callback returned the wrong shape or type, or a mesh cannot be written."""


def _call_field(
    fn: Callable[[np.ndarray], np.ndarray], points: np.ndarray, what: str, width: int
) -> np.ndarray:
    """Evaluate `fn` on points (N,3) float32 in batches, checking each answer has shape (n,) or (n,width)."""
    parts = []
    for start in range(0, len(points), _FIELD_BATCH):
        batch = points[start : start + _FIELD_BATCH]
        want = (len(batch),) if width == 0 else (len(batch), width)
        out = np.asarray(fn(batch))
        if out.shape != want:
            raise MeshingError(
                f"meshing: {what} returned shape {out.shape} for {len(batch)} points; expected {want}"
            )
        parts.append(out)
    return np.concatenate(parts) if parts else np.zeros((0,) if width == 0 else (0, width))


def _sample(
    lattices: list[ChunkLattice], spacing_m: float, sdf_fn: SdfFn, chunk_cells: int
) -> list[np.ndarray]:
    """SDF values (N,) float32 at each lattice's points.

    Points on a chunk face (global index a multiple of `chunk_cells`) can belong to several chunks: they are
    evaluated once for all of them, so neighbouring chunks see identical values there.
    """
    index = [lat.origin + lat.points for lat in lattices]  # (N,3) global lattice indices per chunk
    shared = [on_chunk_face(lat, chunk_cells) for lat in lattices]
    uniq, inverse = unique_rows(np.concatenate([idx[s] for idx, s in zip(index, shared, strict=True)]))
    own = [idx[~s] for idx, s in zip(index, shared, strict=True)]
    points = (np.concatenate([*own, uniq]) * spacing_m).astype(np.float32)  # (N,3) world metres
    values = _call_field(sdf_fn, points, "sdf_fn", 0).astype(np.float32)
    if not np.isfinite(values).all():
        log.warning(
            "sdf_fn gave %d non-finite values; cells touching them stay unmeshed",
            (~np.isfinite(values)).sum(),
        )
    n_own = len(points) - len(uniq)
    own_values, shared_values = values[:n_own], values[n_own:][inverse]
    out, a, b = [], 0, 0
    for s in shared:
        n_shared = int(s.sum())
        v = np.empty(len(s), dtype=np.float32)
        v[~s], v[s] = own_values[a : a + len(s) - n_shared], shared_values[b : b + n_shared]
        a, b = a + len(s) - n_shared, b + n_shared
        out.append(v)
    return out


def _as_voxels(voxel_coords: np.ndarray) -> np.ndarray:
    """Voxel coordinates as an int64 (V,3) array, or MeshingError."""
    coords = np.asarray(voxel_coords)
    if coords.ndim != 2 or coords.shape[1] != 3 or not np.issubdtype(coords.dtype, np.integer):
        raise MeshingError(
            f"meshing: voxel coordinates must be an integer (V,3) array, got {coords.shape} {coords.dtype}"
        )
    return coords.astype(np.int64, copy=False)


class ChunkedMesher:
    """Per-chunk marching-cubes meshes of the allocated leaf voxels, re-meshing only what changed."""

    def __init__(self, voxel_size_m: float, resolution: int = 8, chunk_voxels: int = 8) -> None:
        if not (np.isfinite(voxel_size_m) and voxel_size_m > 0):
            raise ConfigError(
                f"meshing: voxel_size_m must be a positive number of metres, got {voxel_size_m}"
            )
        if int(chunk_voxels) < 1:
            raise ConfigError(f"meshing: chunk_voxels must be >= 1, got {chunk_voxels}")
        self._voxel_size_m = float(voxel_size_m)
        self._chunk_voxels = int(chunk_voxels)
        self._chunks: dict[ChunkKey, MeshChunk] = {}
        self._meshed_voxels: dict[ChunkKey, bytes] = {}  # voxel set each chunk was last meshed with
        self._resolution = 0
        self.resolution = resolution

    @property
    def voxel_size_m(self) -> float:
        return self._voxel_size_m

    @property
    def chunk_voxels(self) -> int:
        return self._chunk_voxels

    @property
    def resolution(self) -> int:
        """Marching-cubes cells per voxel edge; a new value re-meshes every chunk on the next update."""
        return self._resolution

    @resolution.setter
    def resolution(self, value: int) -> None:
        value = int(value)
        if value < 1 or value * self._chunk_voxels > MAX_LATTICE_CELLS:
            top = MAX_LATTICE_CELLS // self._chunk_voxels
            raise ConfigError(
                f"meshing: resolution {value} is out of range; use 1 .. {top} "
                f"with chunk_voxels = {self._chunk_voxels}"
            )
        if value != self._resolution:
            self._resolution = value
            self._meshed_voxels.clear()  # every chunk counts as changed

    @property
    def chunks(self) -> dict[ChunkKey, MeshChunk]:
        """The current non-empty chunks (a new dict holding the cached MeshChunk objects)."""
        return dict(self._chunks)

    def chunks_of(self, voxel_coords: np.ndarray, halo: bool = False) -> set[ChunkKey]:
        """Chunk keys floor(coord / chunk_voxels) of voxels (V,3).

        With `halo`, also the chunks of their 26 neighbour voxels, whose cells share lattice points with them.
        """
        coords = _as_voxels(voxel_coords)
        if halo:
            offsets = np.array(list(itertools.product((-1, 0, 1), repeat=3)), dtype=np.int64)  # (27,3)
            coords = (coords[:, None, :] + offsets[None]).reshape(-1, 3)
        keys = np.unique(np.floor_divide(coords, self._chunk_voxels), axis=0)
        return {(int(k[0]), int(k[1]), int(k[2])) for k in keys}

    def update(
        self,
        voxel_coords: np.ndarray,
        dirty_chunks: Iterable[tuple[int, int, int]] | None,
        sdf_fn: SdfFn,
        color_fn: ColorFn,
        version: int,
    ) -> dict[ChunkKey, MeshChunk]:
        """Re-mesh the dirty chunks (None = all) plus chunks whose voxel set changed; return every chunk.

        Unchanged chunks are the same MeshChunk objects as before; chunks with no surface are left out.
        """
        groups = self._group(_as_voxels(voxel_coords))
        for key in set(self._chunks) - set(groups):
            del self._chunks[key]
        for key in set(self._meshed_voxels) - set(groups):
            del self._meshed_voxels[key]
        wanted = (
            set(groups) if dirty_chunks is None else {tuple(map(int, k)) for k in dirty_chunks} & set(groups)
        )
        wanted |= {k for k, v in groups.items() if self._meshed_voxels.get(k) != v.tobytes()}
        for batch in self._passes(sorted(wanted), groups):
            self._remesh(batch, sdf_fn, color_fn, version)
        self._meshed_voxels.update((k, groups[k].tobytes()) for k in wanted)
        return dict(self._chunks)

    def _group(self, coords: np.ndarray) -> dict[ChunkKey, np.ndarray]:
        """Unique voxels (V,3) split by chunk key, sorted within each chunk (so bytes identify the set)."""
        if len(coords) == 0:
            return {}
        keys = np.floor_divide(coords, self._chunk_voxels)
        order = np.lexsort((coords[:, 2], coords[:, 1], coords[:, 0], keys[:, 2], keys[:, 1], keys[:, 0]))
        coords, keys = coords[order], keys[order]
        fresh = np.ones(len(coords), dtype=bool)
        fresh[1:] = np.any(coords[1:] != coords[:-1], axis=1)  # drop repeated voxels
        coords, keys = coords[fresh], keys[fresh]
        starts = np.flatnonzero(np.r_[True, np.any(keys[1:] != keys[:-1], axis=1)])
        return {
            (int(keys[s, 0]), int(keys[s, 1]), int(keys[s, 2])): part
            for s, part in zip(starts, np.split(coords, starts[1:]), strict=True)
        }

    def _passes(
        self, keys: list[ChunkKey], groups: dict[ChunkKey, np.ndarray]
    ) -> Iterator[list[ChunkLattice]]:
        """Lattices of the chunks to re-mesh, in passes of at most ~_POINTS_PER_PASS lattice points."""
        batch: list[ChunkLattice] = []
        n_points = 0
        for key in keys:
            batch.append(chunk_lattice(key, groups[key], self._resolution))
            n_points += len(batch[-1].points)
            if n_points >= _POINTS_PER_PASS:
                yield batch
                batch, n_points = [], 0
        if batch:
            yield batch

    def _remesh(self, lattices: list[ChunkLattice], sdf_fn: SdfFn, color_fn: ColorFn, version: int) -> None:
        """Sample, march, weld and colour a pass of chunks, replacing their cache entries."""
        spacing_m = self._voxel_size_m / self._resolution
        meshes: list[tuple[ChunkKey, np.ndarray, np.ndarray]] = []
        chunk_cells = self._chunk_voxels * self._resolution
        for lat, values in zip(lattices, _sample(lattices, spacing_m, sdf_fn, chunk_cells), strict=True):
            self._chunks.pop(lat.key, None)
            marched = march(lat, values)
            if marched is None:
                continue
            verts, faces, volume = marched
            vertices, faces, _ = weld(world_vertices(verts, volume, lat.origin, spacing_m), faces)
            if len(faces):
                meshes.append((lat.key, vertices, faces))
        if not meshes:
            return
        colors = _call_field(color_fn, np.concatenate([m[1] for m in meshes]), "color_fn", 3)
        if colors.dtype != np.uint8:
            raise MeshingError(f"meshing: color_fn must return uint8 colours (0..255), got {colors.dtype}")
        ends = np.cumsum([len(m[1]) for m in meshes])
        for (key, vertices, faces), rgb in zip(meshes, np.split(colors, ends[:-1]), strict=True):
            self._chunks[key] = MeshChunk(key, vertices, faces.astype(np.int32), rgb, int(version))


def merge_chunks(chunks: Mapping[ChunkKey, MeshChunk] | Iterable[MeshChunk]) -> trimesh.Trimesh:
    """One coloured mesh of all chunks, with the vertices shared by neighbouring chunks welded."""
    items = sorted(chunks.values() if isinstance(chunks, Mapping) else chunks, key=lambda c: c.key)
    if not items:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), process=False)
    offsets = np.cumsum([0] + [len(c.vertices) for c in items[:-1]])
    faces = np.concatenate([c.faces.astype(np.int64) + o for c, o in zip(items, offsets, strict=True)])
    vertices, faces, source = weld(np.concatenate([c.vertices for c in items]), faces)
    colors = np.concatenate([c.colors for c in items])[source]
    return trimesh.Trimesh(vertices, faces, vertex_colors=colors, process=False)


def export_mesh(mesh: trimesh.Trimesh, path: Path) -> None:
    """Write `mesh` as binary PLY, GLB or OBJ (chosen by the suffix), with vertex colours."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in EXPORT_SUFFIXES:
        raise MeshingError(f"{path}: unknown mesh format '{suffix}'; use one of {', '.join(EXPORT_SUFFIXES)}")
    if len(mesh.faces) == 0:
        raise MeshingError(f"{path}: the mesh is empty; map some frames before exporting it")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if suffix == ".ply":
            mesh.export(path, file_type="ply", encoding="binary")
        else:
            mesh.export(path, file_type=suffix[1:])
    except OSError as e:
        raise MeshingError(f"{path}: cannot write the mesh ({e}); check the folder is writable") from e
