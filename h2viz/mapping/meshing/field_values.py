"""Field values at the marching-cubes lattice points of a set of chunks, each point evaluated once.

A lattice point on a chunk face belongs to several chunks. Within one mesher update it is evaluated once,
whichever pass meets it first, and every later chunk reuses that value: neighbouring chunks then see
bit-identical values on their shared faces, so their vertices weld by exact match.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from h2viz.errors import H2vizError
from h2viz.mapping.meshing.marching import ChunkLattice, on_chunk_face, pack_rows, unique_rows
from h2viz.mapping.meshing.value_cache import ChunkValues, as_stored

log = logging.getLogger(__name__)

SdfFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""points (N,3) float32 metres, ids (N,) int64 of a voxel containing each point -> SDF (N,) float32 metres."""
ColorFn = Callable[[np.ndarray], np.ndarray]
"""points (N,3) float32 metres -> colours (N,3) uint8."""
FIELD_BATCH = 1 << 20  # points per sdf_fn / color_fn call


class MeshingError(H2vizError):
    """A field callback returned the wrong shape or type, or a mesh cannot be written."""


def call_field(
    fn: Callable[..., np.ndarray], what: str, width: int, points: np.ndarray, *extra: np.ndarray
) -> np.ndarray:
    """Evaluate `fn(points, *extra)` (points (N,3)) in batches, checking each answer has shape (n,) or (n,width)."""
    parts = []
    for start in range(0, len(points), FIELD_BATCH):
        batch = points[start : start + FIELD_BATCH]
        want = (len(batch),) if width == 0 else (len(batch), width)
        out = np.asarray(fn(batch, *(e[start : start + FIELD_BATCH] for e in extra)))
        if out.shape != want:
            raise MeshingError(f"meshing: {what} returned shape {out.shape} for {len(batch)} points; expected {want}")
        parts.append(out)
    return np.concatenate(parts) if parts else np.zeros((0,) if width == 0 else (0, width))


class FaceValues:
    """Values of chunk-face lattice points already evaluated in this update, keyed by global lattice index.

    `lo` and `hi` (3,) bound every lattice index the update can meet; when that box is too large to pack
    into int64 keys the cache stays disabled (`enabled` is False) and the caller must use a single pass.
    """

    def __init__(self, lo: np.ndarray, hi: np.ndarray) -> None:
        self.lo, self.hi = np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)
        self.enabled = pack_rows(self.lo[None], self.lo, self.hi) is not None
        self._keys = np.zeros(0, dtype=np.int64)  # sorted
        self._values = np.zeros(0, dtype=np.float32)

    def keys(self, index: np.ndarray) -> np.ndarray:
        """Packed keys (N,) of global lattice indices (N,3)."""
        keys = pack_rows(index, self.lo, self.hi) if self.enabled else None
        return np.zeros(len(index), dtype=np.int64) if keys is None else keys

    def lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(found (N,) bool, values (N,) float32, meaningful where found)."""
        if not self.enabled or len(self._keys) == 0:
            return np.zeros(len(keys), dtype=bool), np.zeros(len(keys), dtype=np.float32)
        pos = np.clip(np.searchsorted(self._keys, keys), 0, len(self._keys) - 1)
        return self._keys[pos] == keys, self._values[pos]

    def add(self, keys: np.ndarray, values: np.ndarray) -> None:
        if not self.enabled or len(keys) == 0:
            return
        all_keys = np.concatenate([self._keys, keys])
        order = np.argsort(all_keys, kind="stable")
        self._keys, self._values = all_keys[order], np.concatenate([self._values, values])[order]


Neighbours = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""global lattice indices (U,3) on chunk faces -> (known (U,) bool, values (U,) float32) from the caches of
chunks outside the current pass."""


def sample_lattices(
    lattices: list[ChunkLattice],
    voxel_ids: list[np.ndarray],
    need: list[np.ndarray],
    caches: list[ChunkValues],
    spacing_m: float,
    sdf_fn: SdfFn,
    chunk_cells: int,
    faces: FaceValues,
    neighbours: Neighbours | None = None,
) -> list[np.ndarray]:
    """SDF values (N,) float32 at each lattice's points, as stored. Lattice i's points flagged in need[i] (N,),
    or unknown to caches[i], are evaluated (voxel_ids[i] (n,) are the ids of its voxels); the others come from
    caches[i], which receives every new value.

    A point on a chunk face (global index a multiple of `chunk_cells`) gets one value for all lattices of the
    update: the one an earlier pass used (`faces`); else, unless a lattice needs it afresh, the cached one when
    the lattices here that know it agree, or the one a neighbouring chunk outside the pass holds
    (`neighbours`); else a fresh evaluation. Chunks meshed in one update therefore weld exactly along their
    shared faces, and new cells next to a chunk left as it is take that chunk's values on their common face.
    """
    index = [lat.origin + lat.points for lat in lattices]  # (N,3) global lattice indices per chunk
    ids = [vid[lat.point_voxel] for lat, vid in zip(lattices, voxel_ids, strict=True)]  # (N,) per chunk
    shared = [on_chunk_face(lat, chunk_cells) for lat in lattices]
    cached = [cache.get(idx) for cache, idx in zip(caches, index, strict=True)]  # (known, values) per chunk
    face = _FacePoints(index, ids, shared, need, cached, faces, neighbours)
    own_need = [(n | ~known) & ~s for n, (known, _), s in zip(need, cached, shared, strict=True)]
    points = np.concatenate([*(idx[n] for idx, n in zip(index, own_need, strict=True)), face.points[face.fresh]])
    point_ids = np.concatenate([*(i[n] for i, n in zip(ids, own_need, strict=True)), face.ids[face.fresh]])
    values = as_stored(call_field(sdf_fn, "sdf_fn", 0, (points * spacing_m).astype(np.float32), point_ids))
    if not np.isfinite(values).all():
        log.warning("sdf_fn gave %d non-finite values; cells touching them stay unmeshed", (~np.isfinite(values)).sum())
    n_own = len(values) - int(face.fresh.sum())
    face.settle(values[n_own:], faces)
    out, a, b = [], 0, 0
    for idx, s, n, (_, v), cache in zip(index, shared, own_need, cached, caches, strict=True):
        v = v.copy()
        v[n] = values[a : a + int(n.sum())]
        v[s] = face.values[face.inverse[b : b + int(s.sum())]]
        cache.set(idx[n | s], v[n | s])
        a, b = a + int(n.sum()), b + int(s.sum())
        out.append(v)
    return out


class _FacePoints:
    """The distinct chunk-face points of one pass and the value each will take."""

    def __init__(
        self,
        index: list[np.ndarray],
        ids: list[np.ndarray],
        shared: list[np.ndarray],
        need: list[np.ndarray],
        cached: list[tuple[np.ndarray, np.ndarray]],
        faces: FaceValues,
        neighbours: Neighbours | None,
    ) -> None:
        pick = lambda arrays: np.concatenate([a[s] for a, s in zip(arrays, shared, strict=True)])  # noqa: E731
        self.points, first, self.inverse = unique_rows(pick(index))  # (U,3), (U,), (S,)
        self.ids = pick(ids)[first]
        u, inv = len(self.points), self.inverse
        asked = np.bincount(inv, pick(need), u) > 0  # some lattice re-evaluates it
        known, values = pick([k for k, _ in cached]), pick([v for _, v in cached])
        known_here = np.bincount(inv, known, u) > 0
        low, high = np.full(u, np.inf, np.float32), np.full(u, -np.inf, np.float32)
        np.minimum.at(low, inv[known], values[known])
        np.maximum.at(high, inv[known], values[known])
        self.keys = faces.keys(self.points)
        self.known, face_values = faces.lookup(self.keys)  # used by an earlier pass of this update
        self.values = np.where(self.known, face_values, high)
        outside = ~known_here & ~asked & ~self.known
        if neighbours is not None and outside.any():
            found, held = neighbours(self.points[outside])
            self.values[np.flatnonzero(outside)[found]] = held[found]
            outside[np.flatnonzero(outside)[found]] = False
        self.fresh = (asked | outside | (known_here & ~(low == high))) & ~self.known

    def settle(self, fresh_values: np.ndarray, faces: FaceValues) -> None:
        """Take the values evaluated for the fresh points and record every value this pass decided."""
        self.values[self.fresh] = fresh_values
        faces.add(self.keys[~self.known], self.values[~self.known])
