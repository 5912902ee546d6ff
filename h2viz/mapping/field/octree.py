"""Sparse voxel octree of 10 cm leaves, unbounded: hashed leaf voxels, shared corners, coarser levels.

Leaves are stored as integer grid coordinates; voxel i covers [c_i * vs, (c_i + 1) * vs)^3. Lookup uses
sorted 64-bit keys (21 bits per axis, +-1M voxels = +-100 km at 10 cm), so memory grows with the surface
mapped and no scene bounds are ever set. Coarser octree levels are the leaf coordinates shifted right.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

OFFSET = 1 << 20
CORNER_OFFSETS = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=np.int64)  # (8,3)
FACE_DIRS = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.int64)
"""Leaf-coordinate steps to a voxel's six face neighbours: -x, +x, -y, +y, -z, +z."""


def encode(coords: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """Pack integer coords (...,3) into one int64 key per point (works for numpy and torch)."""
    c = coords + OFFSET
    return (c[..., 0] << 42) | (c[..., 1] << 21) | c[..., 2]


def decode(keys: np.ndarray) -> np.ndarray:
    """Inverse of `encode` for numpy keys (N,) -> (N,3) int64."""
    mask = (1 << 21) - 1
    return np.stack([(keys >> 42) & mask, (keys >> 21) & mask, keys & mask], axis=-1) - OFFSET


@dataclass
class OccupiedCells:
    """Distinct integer cells of a point set."""

    coords: np.ndarray  # (M,3) int64, distinct
    inverse: np.ndarray  # (N,) index into coords of each point
    counts: np.ndarray  # (M,) points per cell


def occupied_cells(coords: np.ndarray, max_bins: int = 1 << 22) -> OccupiedCells:
    """Distinct cells of integer coords (N,3) with per-point inverse and counts. Counts on a dense local grid
    (linear time) when the points' bounding box is small enough, else by sorting."""
    if coords.shape[0] == 0:
        return OccupiedCells(np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    x, y, z = np.ascontiguousarray(coords.T)  # (N,) each: reductions over (N,3) columns are slow
    lo = np.array([x.min(), y.min(), z.min()])
    dims = np.array([x.max(), y.max(), z.max()]) - lo + 1  # (3,)
    if int(np.prod(dims)) > max_bins:
        keys, inverse, counts = np.unique(encode(coords), return_inverse=True, return_counts=True)
        return OccupiedCells(decode(keys), inverse.reshape(-1), counts)
    linear = ((x - lo[0]) * dims[1] + (y - lo[1])) * dims[2] + (z - lo[2])  # (N,)
    bins = np.bincount(linear, minlength=int(np.prod(dims)))
    occupied = np.flatnonzero(bins)  # (M,) sorted linear cells
    rank = np.zeros(bins.size, np.int32)
    rank[occupied] = np.arange(occupied.size)
    cells = np.stack(np.unravel_index(occupied, tuple(int(d) for d in dims)), 1) + lo  # (M,3)
    return OccupiedCells(cells.astype(np.int64), rank[linear], bins[occupied])


class KeyIndex:
    """Growing set of int64 keys -> dense ids, with vectorised lookup in numpy and torch."""

    def __init__(self) -> None:
        self.keys = np.zeros(0, dtype=np.int64)  # (n,) in insertion order, id = position
        self._sorted = np.zeros(0, dtype=np.int64)
        self._order = np.zeros(0, dtype=np.int64)
        self._torch: dict[torch.device, tuple[torch.Tensor, torch.Tensor]] = {}

    @classmethod
    def from_keys(cls, keys: np.ndarray) -> KeyIndex:
        """Rebuild an index whose ids are the positions in `keys` (for checkpoints)."""
        index = cls()
        index.keys = np.asarray(keys, dtype=np.int64).copy()
        index._order = np.argsort(index.keys, kind="stable")
        index._sorted = index.keys[index._order]
        return index

    def __len__(self) -> int:
        return int(self.keys.size)

    def add(self, keys: np.ndarray) -> np.ndarray:
        """Insert keys not present yet; return the ids of all given keys (N,)."""
        keys = np.asarray(keys, dtype=np.int64)
        ids = self.lookup(keys)
        new = np.unique(keys[ids < 0])
        if new.size:
            start = self.keys.size
            self.keys = np.concatenate([self.keys, new])
            self._order = np.argsort(self.keys, kind="stable")
            self._sorted = self.keys[self._order]
            self._torch.clear()
            ids[ids < 0] = start + np.searchsorted(new, keys[ids < 0])
        return ids

    def lookup(self, keys: np.ndarray) -> np.ndarray:
        """Ids of keys (N,), -1 where absent."""
        if self._sorted.size == 0:
            return np.full(np.shape(keys), -1, dtype=np.int64)
        pos = np.clip(np.searchsorted(self._sorted, keys), 0, self._sorted.size - 1)
        return np.where(self._sorted[pos] == keys, self._order[pos], -1)

    def lookup_torch(self, keys: torch.Tensor) -> torch.Tensor:
        """Torch twin of `lookup` on the keys' device."""
        if self._sorted.size == 0:
            return torch.full_like(keys, -1)
        dev = keys.device
        if dev not in self._torch:
            self._torch[dev] = (torch.from_numpy(self._sorted).to(dev), torch.from_numpy(self._order).to(dev))
        sorted_keys, order = self._torch[dev]
        pos = torch.searchsorted(sorted_keys, keys).clamp_(max=sorted_keys.numel() - 1)
        return torch.where(sorted_keys[pos] == keys, order[pos], torch.full_like(keys, -1))


@dataclass
class Allocation:
    """Result of allocating one frame's points."""

    new_voxels: np.ndarray  # (n,) ids of voxels created by this frame
    observed: np.ndarray  # (m,) ids of allocated voxels containing this frame's points


class VoxelOctree:
    """Leaf voxels and their shared corners; corner i of voxel v is `voxel_corners[v, i]`."""

    def __init__(
        self, voxel_size_m: float, min_points: int = 10, expansion: bool = True, cell_stats: Any = None
    ) -> None:
        """`cell_stats`: the backend's compiled cell counter (kernels.octree_numba), or None for NumPy's."""
        self.voxel_size_m = float(voxel_size_m)
        self._cell_kernel = cell_stats
        self.min_points = int(min_points)
        self.expansion = bool(expansion)
        self.voxels = KeyIndex()
        self.corners = KeyIndex()
        self.voxel_corners = np.zeros((0, 8), dtype=np.int64)  # (V,8) corner ids
        self._coords: tuple[np.ndarray, np.ndarray] = (self.voxels.keys, np.zeros((0, 3), np.int64))

    @property
    def n_voxels(self) -> int:
        return len(self.voxels)

    @property
    def n_corners(self) -> int:
        return len(self.corners)

    def voxel_coords(self) -> np.ndarray:
        """(V,3) int64 leaf coordinates in id order (read-only). Voxels are only ever appended, so each call decodes
        the keys added since the last: the map's voxels are decoded once, not at every frame."""
        keys = self.voxels.keys
        decoded_keys, coords = self._coords
        if keys is decoded_keys:
            return coords
        n = len(coords)
        if n <= keys.size and np.array_equal(decoded_keys[:n], keys[:n]):  # appended to (else replaced: all anew)
            coords = np.concatenate([coords, decode(keys[n:])])
        else:
            coords = decode(keys)
        coords.flags.writeable = False  # shared by every caller
        self._coords = (keys, coords)
        return coords

    def corner_coords(self) -> np.ndarray:
        """(C,3) int64 corner lattice coordinates in id order."""
        return decode(self.corners.keys)

    def level_coords(self, level: int) -> np.ndarray:
        """(V',3) coordinates of occupied cells `level` octree levels above the leaves (cell = vs * 2**level)."""
        return np.unique(self.voxel_coords() >> level, axis=0) if self.n_voxels else np.zeros((0, 3), np.int64)

    def candidate_voxels(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Keys of voxels holding > min_points of the points (N,3) plus expanded neighbours, and the keys of
        every voxel holding any point."""
        stats = self._cell_stats(points_world)
        if stats is None:  # NumPy: the reference
            cells = occupied_cells(np.floor(points_world / self.voxel_size_m).astype(np.int64))  # (M,3)
            coords, counts = cells.coords, cells.counts
        else:
            coords, counts, means = stats
        keep = counts > self.min_points
        base = coords[keep]  # (n,3)
        chosen = [encode(base)]
        if self.expansion and keep.any():
            if stats is None:
                scaled = points_world / self.voxel_size_m  # (N,3) in voxels
                sums = np.stack(
                    [np.bincount(cells.inverse, scaled[:, a], minlength=counts.size) for a in range(3)], 1
                )
                local = sums[keep] / counts[keep, None] - base  # (n,3) mean point in [0,1)^3
            else:
                local = means[keep]
            for axis in range(3):
                for side, hit in ((-1, local[:, axis] < 0.1), (1, local[:, axis] > 0.9)):
                    nb = base[hit].copy()
                    nb[:, axis] += side
                    chosen.append(encode(nb))
        return np.unique(np.concatenate(chosen)), encode(coords)

    def _cell_stats(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The numba kernel's distinct cells, counts and mean points (kernels.octree_numba), or None where it
        does not apply (numba missing, no points, a box too large for a dense grid)."""
        if self._cell_kernel is None or len(points_world) == 0:
            return None
        points = np.ascontiguousarray(points_world, dtype=np.float32)
        coords, counts, means = self._cell_kernel(points, self.voxel_size_m, 1 << 22)
        return None if counts.size == 0 else (coords, counts, means)

    def allocate(self, points_world: np.ndarray) -> Allocation:
        """Allocate voxels for one frame's back-projected points (N,3); corners are created with them."""
        return self.allocate_candidates(*self.candidate_voxels(points_world))

    def allocate_candidates(self, keys: np.ndarray, hit_keys: np.ndarray) -> Allocation:
        """Allocate what `candidate_voxels` chose for a frame (which depends on the frame alone, so that any thread
        may compute it ahead): voxel `keys` (n,) and their corners; `hit_keys` (m,) are every voxel hit."""
        n_before = self.n_voxels
        self.voxels.add(keys)
        new_ids = np.arange(n_before, self.n_voxels, dtype=np.int64)
        if new_ids.size:
            coords = decode(self.voxels.keys[new_ids])  # (n,3)
            corner_keys = encode(coords[:, None, :] + CORNER_OFFSETS[None])  # (n,8)
            cids = self.corners.add(corner_keys.reshape(-1)).reshape(-1, 8)
            self.voxel_corners = np.concatenate([self.voxel_corners, cids])
        observed = self.voxels.lookup(hit_keys)
        return Allocation(new_voxels=new_ids, observed=observed[observed >= 0])

    def face_neighbours(self, voxels: np.ndarray) -> np.ndarray:
        """Ids (n,6) of the voxels across the -x, +x, -y, +y, -z, +z faces of voxels (n,), -1 where none."""
        coords = decode(self.voxels.keys[np.asarray(voxels, np.int64)])  # (n,3): only these voxels' keys decoded
        return self.voxels.lookup(encode(coords[:, None, :] + FACE_DIRS[None]))  # (n,6)

    def lookup_points(self, points: torch.Tensor) -> torch.Tensor:
        """Voxel ids (N,) of points (N,3) in metres, -1 outside allocated voxels."""
        coords = torch.floor(points / self.voxel_size_m).long()
        return self.voxels.lookup_torch(encode(coords))

    def locate_points(self, points: torch.Tensor) -> torch.Tensor:
        """Voxel ids (N,) of points (N,3), also accepting points on the outer face of an allocated voxel (up to
        rounding in either direction), -1 elsewhere."""
        ids = self.lookup_points(points)
        eps = 1e-4 * self.voxel_size_m
        for code in range(27):
            missing = ids < 0
            if not bool(missing.any()):
                break
            shift = (torch.tensor([code // 9, code // 3 % 3, code % 3], device=points.device) - 1) * eps
            ids[missing] = self.lookup_points(points[missing] + shift)
        return ids

    def state_dict(self) -> dict[str, np.ndarray]:
        return {
            "voxel_keys": self.voxels.keys,
            "corner_keys": self.corners.keys,
            "voxel_corners": self.voxel_corners,
        }

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.voxels = KeyIndex.from_keys(state["voxel_keys"])
        self.corners = KeyIndex.from_keys(state["corner_keys"])
        self.voxel_corners = np.asarray(state["voxel_corners"], dtype=np.int64)
