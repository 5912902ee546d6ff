"""Chunked, welded meshing of the sparse voxel map: re-meshes only chosen chunks, merges and exports.

The map is cut into chunks of chunk_voxels^3 leaf voxels, keyed by floor(voxel / chunk_voxels). Each chunk
keeps its own MeshChunk and a cache of its lattice values. `update` re-meshes first the chunks whose voxel
set changed (evaluating only their new lattice points), then, within a time budget, the chunks holding dirty
voxels (evaluating those voxels' points) and the chunks evaluated longest ago (all their points); it hands
back the same objects for the others, so a viewer can diff by identity.

One update runs at a time (on any thread). After each pass the mesher swaps in new `chunks` and bookkeeping
dicts whole, so other threads may read `chunks` and call `stale` while an update runs.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from h2viz.errors import ConfigError
from h2viz.mapping.meshing.field_values import ColorFn, MeshingError, SdfFn, sample_lattices
from h2viz.mapping.meshing.marching import ChunkLattice, chunk_lattice, unique_rows, weld
from h2viz.mapping.meshing.passes import (
    NEVER,
    ChunkKey,
    Eval,
    Item,
    KeepFn,
    Meshed,
    Update,
    coloured,
    group_voxels,
    kept_faces,
    signature_head,
    surface,
)
from h2viz.mapping.meshing.value_cache import ChunkValues
from h2viz.types import MeshChunk

if TYPE_CHECKING:
    from h2viz.mapping.backend import Backend

__all__ = ["ChunkKey", "ChunkedMesher", "ColorFn", "MeshingError", "SdfFn", "export_mesh", "merge_chunks"]

EXPORT_SUFFIXES = (".ply", ".glb", ".obj")
MAX_LATTICE_CELLS = 1024  # lattice cells along a chunk edge (chunk_voxels * resolution)


def _as_voxels(voxel_coords: np.ndarray) -> np.ndarray:
    """Voxel coordinates as an int64 (V,3) array, or MeshingError."""
    coords = np.asarray(voxel_coords)
    if coords.ndim != 2 or coords.shape[1] != 3 or not np.issubdtype(coords.dtype, np.integer):
        raise MeshingError(
            f"meshing: voxel coordinates must be an integer (V,3) array, got {coords.shape} {coords.dtype}"
        )
    return coords.astype(np.int64, copy=False)


class ChunkedMesher:
    """Per-chunk marching-cubes meshes of the allocated leaf voxels, re-meshing only what it is asked to."""

    def __init__(
        self, voxel_size_m: float, resolution: int = 8, chunk_voxels: int = 8, backend: Backend | None = None
    ) -> None:
        if not (np.isfinite(voxel_size_m) and voxel_size_m > 0):
            raise ConfigError(f"meshing: voxel_size_m must be a positive number of metres, got {voxel_size_m}")
        if int(chunk_voxels) < 1:
            raise ConfigError(f"meshing: chunk_voxels must be >= 1, got {chunk_voxels}")
        self._voxel_size_m = float(voxel_size_m)
        self._chunk_voxels = int(chunk_voxels)
        arrays = None if backend is None else backend.array_kernels
        self._fast = None if arrays is None else arrays.marching  # compiled marching (None: the NumPy code)
        self._chunks: dict[ChunkKey, MeshChunk] = {}  # replaced whole, never changed in place
        self._meshed: dict[ChunkKey, Meshed] = {}  # every chunk with voxels, surface or not; same rule
        self._values: dict[ChunkKey, ChunkValues] = {}  # lattice values per chunk (used by `update` only)
        self._resolution = 0
        self.resolution = resolution
        self.remeshed: list[ChunkKey] = []  # chunks the last update re-meshed, in order

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
                f"meshing: resolution {value} is out of range; use 1 .. {top} with chunk_voxels = {self._chunk_voxels}"
            )
        self._resolution = value

    @property
    def chunks(self) -> dict[ChunkKey, MeshChunk]:
        """The current non-empty chunks (a new dict holding the cached MeshChunk objects)."""
        return dict(self._chunks)

    @property
    def cache_bytes(self) -> int:
        """Memory held by the lattice value caches."""
        return sum(v.nbytes for v in list(self._values.values()))

    def stale(self, field_version: int, filtered: bool | None = None) -> int:
        """How many chunks were evaluated whole from a field older than `field_version`, or meshed at another
        resolution or (unless `filtered` is None) with faces filtered otherwise than `filtered` says."""
        head = signature_head(self._resolution, bool(filtered))[: 4 if filtered is None else None]
        return sum(m.field_version < field_version or m.signature[: len(head)] != head for m in self._meshed.values())

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
        dirty: Iterable[Sequence[int]] | None,
        sdf_fn: SdfFn,
        color_fn: ColorFn,
        version: int,
        *,
        voxel_ids: np.ndarray | None = None,
        dirty_voxels: np.ndarray | None = None,
        field_version: int = 0,
        refresh_s: float = 0.0,
        stop: Callable[[], bool] | None = None,
        on_pass: Callable[[list[ChunkKey], bool], None] | None = None,
        keep_fn: KeepFn | None = None,
        hurry: Callable[[], bool] | None = None,
    ) -> dict[ChunkKey, MeshChunk]:
        """Mesh the voxels (V,3); returns every non-empty chunk (those not re-meshed are the same objects).

        Required, in this order: chunks whose voxel set or resolution changed (only their new lattice points
        are evaluated) and the `dirty` chunks (None = all; every point). Then, for up to `refresh_s` seconds:
        chunks with `dirty_voxels` (V,) bool, most first (those voxels' points), and chunks evaluated whole
        longest ago from a field older than `field_version` (every point). Work stops between passes when
        `stop()` is true (a newer update is waiting; chunks left out stay as they are and count as changed or
        stale next time), and the optional refresh also while `hurry()` is true (another thread needs the cores).

        `voxel_ids` (V,) are what sdf_fn receives with the points (default: row numbers); `on_pass(keys,
        required)` runs after each pass of chunks has been swapped in; `keep_fn` (face centroids (M,3) -> (M,)
        bool) leaves the faces it rejects out of the re-meshed chunks.
        """
        coords = _as_voxels(voxel_coords)
        ids = np.arange(len(coords), dtype=np.int64) if voxel_ids is None else np.asarray(voxel_ids, np.int64)
        flags = np.zeros(len(coords), bool) if dirty_voxels is None else np.asarray(dirty_voxels, dtype=bool)
        if ids.shape != (len(coords),) or flags.shape != (len(coords),):
            raise MeshingError(f"meshing: voxel_ids and dirty_voxels must have shape ({len(coords)},)")
        groups = group_voxels(coords, ids, flags, self._chunk_voxels)
        job = Update(groups, self._resolution, sdf_fn, color_fn, version, field_version, keep_fn)
        self._forget(set(groups))
        required = self._required(job, dirty)
        self.remeshed = []
        stopped = lambda: stop is not None and stop()  # noqa: E731
        for n, items in enumerate(job.passes(required)):
            if n and stopped():
                return dict(self._chunks)
            self._remesh(items, job, on_pass, True)
        deadline = time.perf_counter() + refresh_s
        whole = {k for k, mode in required if mode is Eval.WHOLE}
        for items in job.passes(self._optional(job, whole), refresh=True) if job.faces.enabled else ():
            if time.perf_counter() >= deadline or stopped() or (hurry is not None and hurry()):
                break
            self._remesh(items, job, on_pass, False)
        return dict(self._chunks)

    def _forget(self, present: set[ChunkKey]) -> None:
        """Drop the chunks that have no voxels any more."""
        if set(self._meshed) - present or set(self._chunks) - present:
            self._chunks = {k: c for k, c in self._chunks.items() if k in present}
            self._meshed = {k: m for k, m in self._meshed.items() if k in present}
        for key in set(self._values) - present:
            del self._values[key]

    def _required(self, job: Update, dirty: Iterable[Sequence[int]] | None) -> list[Item]:
        """The chunks whose voxel set or resolution changed, then the dirty ones (whole)."""
        if dirty is None:
            asked = sorted(job.groups)
        else:
            asked = [k for k in dict.fromkeys(tuple(int(i) for i in k) for k in dirty) if k in job.groups]
        changed = [k for k in job.groups if self._meshed.get(k, NEVER).signature != job.signature(k)]
        changed.sort(key=lambda k: (job.groups[k].n_flagged == 0, k))  # the latest frames' chunks first
        whole = set(asked)
        new = [(k, Eval.WHOLE if k in whole else Eval.NEW) for k in changed]
        return new + [(k, Eval.WHOLE) for k in asked if k not in set(changed)]  # type: ignore[misc]

    def _optional(self, job: Update, exclude: set[ChunkKey]) -> list[Item]:
        """Chunks with dirty voxels (most first), then those evaluated whole longest ago from an older field
        (a chunk that only had its new points evaluated counts as such), leaving out `exclude`."""
        groups = job.groups
        flagged = sorted((-g.n_flagged, k) for k, g in groups.items() if g.n_flagged and k not in exclude)
        old = sorted(
            (m.field_version, m.version, k)
            for k, m in self._meshed.items()
            if k in groups and k not in exclude and m.field_version < job.field_version
        )
        partial = {k for _, k in flagged}
        return [(k, Eval.DIRTY) for _, k in flagged] + [(k, Eval.WHOLE) for _, _, k in old if k not in partial]

    def _remesh(self, items: list[Item], job: Update, on_pass: Callable | None, required: bool) -> None:
        """Sample, march, weld and colour a pass of chunks, then swap in the new chunk and bookkeeping dicts."""
        res, keys = job.resolution, [k for k, _ in items]
        lattices = [chunk_lattice(k, job.groups[k].coords, res, job.groups[k].flags, self._fast) for k in keys]
        need = [_need(lat, mode) for lat, (_, mode) in zip(lattices, items, strict=True)]
        caches = [self._cache(lat, res) for lat in lattices]
        ids = [job.groups[k].ids for k in keys]
        spacing_m, chunk_cells = self._voxel_size_m / res, self._chunk_voxels * res
        outside = lambda points: self._held_by_others(points, set(keys), chunk_cells)  # noqa: E731
        values = sample_lattices(lattices, ids, need, caches, spacing_m, job.sdf_fn, chunk_cells, job.faces, outside)
        surfaces = [s for lat, v in zip(lattices, values, strict=True) if (s := surface(lat, v, spacing_m, self._fast))]
        if job.keep_fn is not None:
            surfaces = kept_faces(surfaces, job.keep_fn)
        replaced = set(keys)
        chunks = {k: c for k, c in self._chunks.items() if k not in replaced}
        keep = {k: self._chunks[k] for k, mode in items if mode is not Eval.WHOLE and k in self._chunks}
        # unmoved vertices keep their colour
        chunks.update(coloured(surfaces, job.color_fn, job.version, keep, self._fast))
        meshed = dict(self._meshed)
        for key, mode in items:
            before = self._meshed.get(key, NEVER)
            whole = mode is Eval.WHOLE or before.signature[:4] != job.signature(key)[:4]
            meshed[key] = Meshed(job.signature(key), job.field_version if whole else before.field_version, job.version)
        self._chunks, self._meshed = chunks, meshed
        self.remeshed += keys
        if on_pass is not None:
            on_pass(keys, required)

    def _held_by_others(
        self, points: np.ndarray, exclude: set[ChunkKey], chunk_cells: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """(known (U,), values (U,)) of chunk-face lattice points (U,3) in the caches of the chunks sharing them,
        other than `exclude` (a chunk's cache holds the resolution it was last meshed at)."""
        known, values = np.zeros(len(points), dtype=bool), np.zeros(len(points), dtype=np.float32)
        base, on_face = np.floor_divide(points, chunk_cells), points % chunk_cells == 0
        for offset in itertools.product((0, -1), repeat=3):
            rows = np.flatnonzero(np.all(on_face | (np.array(offset) == 0), axis=1) & ~known)
            if len(rows) == 0:
                continue
            keys, _, inverse = unique_rows(base[rows] + offset)
            order = np.argsort(inverse, kind="stable")  # rows grouped by chunk
            groups = np.split(rows[order], np.cumsum(np.bincount(inverse, minlength=len(keys)))[:-1])
            for key, sel in zip((tuple(int(i) for i in k) for k in keys), groups, strict=True):
                cache = None if key in exclude else self._values.get(key)
                if cache is not None and cache.resolution == chunk_cells // self._chunk_voxels:
                    found, held = cache.lookup(points[sel])
                    known[sel[found]], values[sel[found]] = True, held[found]
        return known, values

    def _cache(self, lat: ChunkLattice, resolution: int) -> ChunkValues:
        """The value cache of a lattice's chunk, covering its lattice box."""
        hi = lat.origin + lat.cells.shape
        cache = self._values.get(lat.key) or ChunkValues(resolution, lat.origin, tuple(hi - lat.origin + 1))
        self._values[lat.key] = cache = cache.covering(resolution, lat.origin, hi)
        return cache


def _need(lat: ChunkLattice, mode: Eval) -> np.ndarray:
    """(N,) bool lattice points an item evaluates even when cached."""
    if mode is Eval.WHOLE:
        return np.ones(len(lat.points), dtype=bool)
    return lat.point_flagged if mode is Eval.DIRTY else np.zeros(len(lat.points), dtype=bool)


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
