"""Where depth was observed: one bit per cell of an 8x8x8 grid inside every leaf voxel (1.25 cm cells at 10 cm
voxels), set by the cells that back-projected depth points fall in. Meshing keeps a face only when an observed
cell lies in the 3x3x3 block of cells around it, i.e. when depth was measured within 1-4 cm of it.

Why: the field is only constrained near measured depth. Behind observed surfaces, the corner priors say
"inside" and in unobserved gaps (between a sofa and the wall, under a table) the residual is free, so their sum
can cross zero and close such gaps with surfaces nobody saw, 3-7 cm in front of the true ones.

A voxel's 512 bits are 8 uint64 words, word x holding bit 8*y + z of local cell (x, y, z); dilating by one cell
is then a few shifts and ORs over all voxels at once, along z, then y, then x, with the six face neighbours
supplying the border cells. Bits travel through allocated voxels only: a cell whose only observed neighbour lies
diagonally across a voxel that does not exist stays unsupported (a corner of the allocated region).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from h2viz.mapping.marching import pack_rows, unique_rows, unpack_rows
from h2viz.mapping.octree import FACE_DIRS, KeyIndex, VoxelOctree, decode, encode

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

    def __init__(self, voxel_size_m: float) -> None:
        self.cell_m = float(voxel_size_m) / SUB
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
        _, vid, word, bit = _in_voxels(octree.voxels, _distinct(np.floor(points / self.cell_m).astype(np.int64)))
        np.bitwise_or.at(self.words, (vid, word), bit)

    def snapshot(self, octree: VoxelOctree, strict: np.ndarray | None = None) -> ObservedSupport:
        """What meshing needs to test faces, frozen now: the voxel keys and the cell bits (the lookup index and
        the dilation are built on the thread that first tests a face); `strict` (V,) bool marks voxels whose faces
        need depth measured in their own cell (see ObservedSupport)."""
        self.grow(octree.n_voxels)
        return ObservedSupport(self.cell_m, octree.voxels.keys[: octree.n_voxels], self.words.copy(), strict)

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
    _index: KeyIndex | None = None
    _dilated: np.ndarray | None = None

    @property
    def index(self) -> KeyIndex:
        if self._index is None:
            self._index = KeyIndex.from_keys(self.keys)
        return self._index

    def dilated(self) -> np.ndarray:
        """(V,8) words with every cell that has an observed cell among its 26 neighbours (or itself) set."""
        if self._dilated is None:
            self._dilated = dilate(self.words, neighbours(self.index))
        return self._dilated

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: points (N,3) whose cell is within one cell of an observed cell (in `strict` voxels: whose
        cell is observed)."""
        ok, vid, word, bit = _in_voxels(self.index, np.floor(np.asarray(points) / self.cell_m).astype(np.int64))
        held = self.dilated()[vid, word]  # (N',) uint64
        if self.strict is not None:
            held = np.where(self.strict[vid], self.words[vid, word], held)
        out = np.zeros(len(ok), dtype=bool)
        out[ok] = (held & bit) != 0
        return out


def neighbours(index: KeyIndex) -> np.ndarray:
    """(V,6) ids of each voxel's face neighbours in FACE_DIRS order (-x, +x, -y, +y, -z, +z), -1 where none."""
    coords = decode(index.keys)  # (V,3)
    return np.stack([index.lookup(encode(coords + d)) for d in FACE_DIRS], axis=1)


def _gather(words: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """words[ids] with zeros where ids is -1: (V,8)."""
    got = words[np.maximum(ids, 0)]
    got[ids < 0] = 0
    return got


def dilate(words: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """One-cell dilation (3x3x3 block) of the cell bits (V,8) uint64 across voxels, nb (V,6) face neighbours."""
    if len(words) == 0:
        return words.copy()
    one, seven, eight, fifty_six = (np.uint64(k) for k in (1, 7, 8, 56))
    # along z (bits 8y+z of each word)
    lo, hi = _gather(words, nb[:, 4]), _gather(words, nb[:, 5])
    w = words | ((words << one) & ~_Z0) | ((words >> one) & ~_Z7) | ((lo & _Z7) >> seven) | ((hi & _Z0) << seven)
    # along y (rows of 8 bits), from the z-dilated words of the y neighbours
    lo, hi = _gather(w, nb[:, 2]), _gather(w, nb[:, 3])
    w = w | (w << eight) | (w >> eight) | ((lo & _Y7) >> fifty_six) | ((hi & _Y0) << fifty_six)
    # along x (words), from the yz-dilated words of the x neighbours
    lo, hi = _gather(w, nb[:, 0]), _gather(w, nb[:, 1])
    out = w.copy()
    out[:, 1:] |= w[:, :-1]
    out[:, :-1] |= w[:, 1:]
    out[:, 0] |= lo[:, SUB - 1]
    out[:, SUB - 1] |= hi[:, 0]
    return out
