"""Where depth was observed: one bit per cell of an 8x8x8 grid inside every leaf voxel (1.25 cm cells at 10 cm
voxels), set by the cells that back-projected depth points fall in. Meshing keeps a face only when an observed
cell lies in the 3x3x3 block of cells around it, i.e. when depth was measured within 1-4 cm of it.

Why: the field is only constrained near measured depth. Behind observed surfaces, the corner priors say
"inside" and in unobserved gaps (between a sofa and the wall, under a table) the residual is free, so their sum
can cross zero and close such gaps with surfaces nobody saw, 3-7 cm in front of the true ones.

A voxel's 512 bits are 8 uint64 words, word x holding bit 8*y + z of local cell (x, y, z); dilating by one cell
is then a few shifts and ORs over all voxels at once, along z, then y, then x, with the six face neighbours
supplying the border cells. Bits travel through allocated voxels only: a cell whose only observed neighbour lies
diagonally across a voxel that does not exist stays unsupported (a corner of the allocated region). With a
backend's array kernels, `contains` tests the points in one compiled loop (`kernels.observed_numba`) that gives the same
answers.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from h2viz.mapping.field.octree import FACE_DIRS, KeyIndex, VoxelOctree, decode, encode
from h2viz.mapping.meshing.marching import pack_rows, unique_rows, unpack_rows

if TYPE_CHECKING:
    from h2viz.mapping.backend import Backend

SUB = 8  # cells per voxel edge
_ONE = np.uint64(1)
_Z0 = np.uint64(sum(1 << (8 * y) for y in range(8)))  # bits of the cells with z = 0
_Z7 = _Z0 << np.uint64(7)  # ... with z = 7
_Y0 = np.uint64(0xFF)  # ... with y = 0
_Y7 = _Y0 << np.uint64(56)  # ... with y = 7


def _cell_bits(local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(word index x (N,), bit mask (N,) uint64) of local cells (N,3) in [0, 8)."""
    return local[:, 0], np.left_shift(_ONE, (local[:, 1] * 8 + local[:, 2]).astype(np.uint64))


def _distinct(cells: np.ndarray) -> np.ndarray:
    """The distinct rows of integer cells (N,3): one sort of their packed index in the cells' bounding box
    (`unique_rows` also returns first and inverse indices, which take 2-3x longer here)."""
    cols = np.ascontiguousarray(cells.T)  # (3,N): reductions over the columns of (N,3) are slow
    lo, hi = cols.min(axis=1), cols.max(axis=1)
    keys = pack_rows(cells, lo, hi)
    if keys is None:  # a box too large to pack
        return unique_rows(cells)[0]
    keys.sort()
    return unpack_rows(keys[np.r_[True, keys[1:] != keys[:-1]]], lo, hi)


def _in_voxels(index: KeyIndex, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For integer cells (N,3): which lie in an indexed voxel (N,) bool, and for those their voxel ids, words and
    bit masks."""
    vid = index.lookup(encode(cells >> 3))  # arithmetic shift: floor division by SUB
    ok = vid >= 0
    word, bit = _cell_bits(cells[ok] & (SUB - 1))
    return ok, vid[ok], word, bit


class ObservedCells:
    """The observed-cell bits of every leaf voxel (8 uint64 words each), growing with the octree."""

    def __init__(self, voxel_size_m: float, backend: Backend | None = None) -> None:
        self.cell_m = float(voxel_size_m) / SUB
        arrays = None if backend is None else backend.array_kernels
        self.fast = None if arrays is None else arrays.support  # the snapshots' compiled test (None: NumPy)
        self._hash = None if arrays is None else arrays.walk.voxel_hash  # the octree's cached voxel hash table
        self.words = np.zeros((0, SUB), dtype=np.uint64)  # (V,8)

    def grow(self, n_voxels: int) -> None:
        """Give voxels created since the last call empty cells."""
        if n_voxels > len(self.words):
            self.words = np.concatenate([self.words, np.zeros((n_voxels - len(self.words), SUB), np.uint64)])

    def add(self, octree: VoxelOctree, points: np.ndarray) -> None:
        """Mark the cells of world points (N,3) that lie in allocated voxels."""
        if len(points) == 0:
            return
        self.grow(octree.n_voxels)
        if self.fast is not None and self._hash is not None:
            table = self._hash(octree)
            pts = np.ascontiguousarray(points)
            cell = pts.dtype.type(self.cell_m) if pts.dtype == np.float32 else self.cell_m  # NumPy's division
            self.fast.mark_kernel(pts, cell, *table, self.words)
            return
        _, vid, word, bit = _in_voxels(octree.voxels, _distinct(np.floor(points / self.cell_m).astype(np.int64)))
        np.bitwise_or.at(self.words, (vid, word), bit)

    def snapshot(self, octree: VoxelOctree, strict: np.ndarray | None = None) -> ObservedSupport:
        """What meshing needs to test faces, frozen now: the voxel keys and the cell bits (the lookup index and
        the dilation are built on the thread that first tests a face); `strict` (V,) bool marks voxels whose faces
        need depth measured in their own cell (see ObservedSupport)."""
        self.grow(octree.n_voxels)
        keys = octree.voxels.keys[: octree.n_voxels]
        return ObservedSupport(self.cell_m, keys, self.words.copy(), strict, fast=self.fast)

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"words": self.words}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.words = np.asarray(state["words"], dtype=np.uint64)


@dataclass
class ObservedSupport:
    """Observed cells frozen for one mesh job: voxel keys in id order (the octree replaces its key array when it
    grows, never changes it in place) and their cell bits."""

    cell_m: float
    keys: np.ndarray  # (V,) int64
    words: np.ndarray  # (V,8) uint64
    strict: np.ndarray | None = None  # (V,) bool: a face there needs its own cell observed, not only a neighbour
    fast: ModuleType | None = None  # the compiled test (kernels.observed_numba), None: `contains_reference`
    _index: KeyIndex | None = None
    _table: tuple[np.ndarray, np.ndarray] | None = None  # voxel hash table of the compiled test (built on first use)

    @property
    def index(self) -> KeyIndex:
        if self._index is None:
            self._index = KeyIndex.from_keys(self.keys)
        return self._index

    def dilated(self) -> np.ndarray:
        """(V,8) words with every cell that has an observed cell among its 26 neighbours (or itself) set, over
        the whole map at once (the reference for `dilated_rows`)."""
        return dilate(self.words, neighbours(self.index, self.keys))

    def dilated_rows(self, ids: np.ndarray) -> np.ndarray:
        """dilated()[ids] (N,8) for voxel ids (N,), computed over the asked voxels' neighbourhoods only: a mesh
        job's cost then grows with the chunks it meshes, not with the whole map."""
        want = np.unique(ids)  # the x step's rows
        nb_x = neighbours(self.index, self.keys[want])
        mid = _with_neighbours(want, nb_x[:, 0:2])  # the y step's rows: those and their x neighbours
        nb_y = neighbours(self.index, self.keys[mid])
        base = _with_neighbours(mid, nb_y[:, 2:4])  # the z step's rows: and their y neighbours
        nb_z = neighbours(self.index, self.keys[base])
        w = _z_step(self.words[base], _gather(self.words, nb_z[:, 4]), _gather(self.words, nb_z[:, 5]))
        w = _y_step(
            w[np.searchsorted(base, mid)], _gather(w, _rows(base, nb_y[:, 2])), _gather(w, _rows(base, nb_y[:, 3]))
        )
        w = _x_step(
            w[np.searchsorted(mid, want)], _gather(w, _rows(mid, nb_x[:, 0])), _gather(w, _rows(mid, nb_x[:, 1]))
        )
        return w[np.searchsorted(want, ids)]

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: points (N,3) whose cell is within one cell of an observed cell (in `strict` voxels: whose
        cell is observed)."""
        cells = np.floor(np.asarray(points) / self.cell_m).astype(np.int64)
        fast = self.fast
        if fast is not None:
            if self._table is None:
                self._table = fast.build_table(np.ascontiguousarray(self.keys, dtype=np.int64))
            strict = np.zeros(0, bool) if self.strict is None else np.asarray(self.strict, bool)
            return fast.contains_kernel(cells.reshape(-1, 3), *self._table, self.words, strict)
        return self.contains_reference(cells)

    def contains_reference(self, cells: np.ndarray) -> np.ndarray:
        """`contains` of integer cells (N,3), through `dilated_rows` (the reference for the compiled test)."""
        ok, vid, word, bit = _in_voxels(self.index, cells)
        held = self.dilated_rows(vid)[np.arange(len(vid)), word]  # (N',) uint64
        if self.strict is not None:
            held = np.where(self.strict[vid], self.words[vid, word], held)
        out = np.zeros(len(ok), dtype=bool)
        out[ok] = (held & bit) != 0
        return out


def neighbours(index: KeyIndex, keys: np.ndarray) -> np.ndarray:
    """(N,6) ids of the face neighbours of the voxels keys (N,) in FACE_DIRS order (-x, +x, -y, +y, -z, +z), -1
    where none."""
    coords = decode(keys)  # (N,3)
    return np.stack([index.lookup(encode(coords + d)) for d in FACE_DIRS], axis=1).reshape(-1, 6)


def _with_neighbours(ids: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """Sorted distinct voxel ids: ids (N,) and the existing ones of nb (N,k)."""
    return np.unique(np.concatenate([ids, nb[nb >= 0]]))


def _rows(ids: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Rows (N,) in the sorted voxel ids (M,) of the voxels wanted (N,), all among them or -1 (kept as -1)."""
    return np.where(wanted >= 0, np.searchsorted(ids, wanted), -1)


def _gather(words: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """words[ids] with zeros where ids is -1: (N,8)."""
    got = words[np.maximum(ids, 0)]
    got[ids < 0] = 0
    return got


def dilate(words: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """One-cell dilation (3x3x3 block) of the cell bits (V,8) uint64 across voxels, nb (V,6) face neighbours."""
    if len(words) == 0:
        return words.copy()
    w = _z_step(words, _gather(words, nb[:, 4]), _gather(words, nb[:, 5]))
    w = _y_step(w, _gather(w, nb[:, 2]), _gather(w, nb[:, 3]))  # from the z-dilated words of the y neighbours
    return _x_step(w, _gather(w, nb[:, 0]), _gather(w, nb[:, 1]))  # from the yz-dilated words of the x neighbours


def _z_step(w: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Dilation along z (bits 8y+z of each word) of words (N,8), given those of the -z and +z neighbours."""
    one, seven = np.uint64(1), np.uint64(7)
    return w | ((w << one) & ~_Z0) | ((w >> one) & ~_Z7) | ((lo & _Z7) >> seven) | ((hi & _Z0) << seven)


def _y_step(w: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Dilation along y (rows of 8 bits) of words (N,8), given those of the -y and +y neighbours."""
    eight, fifty_six = np.uint64(8), np.uint64(56)
    return w | (w << eight) | (w >> eight) | ((lo & _Y7) >> fifty_six) | ((hi & _Y0) << fifty_six)


def _x_step(w: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Dilation along x (the 8 words) of words (N,8), given those of the -x and +x neighbours."""
    out = w.copy()
    out[:, 1:] |= w[:, :-1]
    out[:, :-1] |= w[:, 1:]
    out[:, 0] |= lo[:, SUB - 1]
    out[:, SUB - 1] |= hi[:, 0]
    return out
