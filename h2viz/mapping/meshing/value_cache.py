"""Cached field values of each chunk's marching-cubes lattice, so that an update evaluates only the points it
must (new cells, voxels marked dirty) and re-marches the rest from memory.

Values are kept as float16 (about 1 KB per meshed voxel at the default resolution; 0.05 mm steps near the
surface) and every value the mesher uses goes through that rounding first, so a value taken from the cache
and the same value just evaluated are bit-identical.
"""

from __future__ import annotations

import numpy as np


def as_stored(values: np.ndarray) -> np.ndarray:
    """Field values (N,) rounded as the cache stores them, as float32."""
    return np.asarray(values, dtype=np.float32).astype(np.float16).astype(np.float32)


class ChunkValues:
    """Values over a box of global lattice indices [origin, origin + shape) with a known-mask."""

    def __init__(self, resolution: int, origin: np.ndarray, shape: tuple[int, ...]) -> None:
        self.resolution = int(resolution)
        self.origin = np.asarray(origin, dtype=np.int64)
        self.values = np.zeros(shape, dtype=np.float16)  # (X,Y,Z)
        self.known = np.zeros(shape, dtype=bool)  # (X,Y,Z)

    @property
    def nbytes(self) -> int:
        return self.values.nbytes + self.known.nbytes

    def covering(self, resolution: int, lo: np.ndarray, hi: np.ndarray) -> ChunkValues:
        """This cache if it already covers global indices [lo, hi] at `resolution`, else a grown copy (a fresh
        one for another resolution)."""
        lo, hi = np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)
        end = self.origin + self.values.shape
        if resolution == self.resolution and (lo >= self.origin).all() and (hi < end).all():
            return self
        if resolution != self.resolution or not self.known.any():
            return ChunkValues(resolution, lo, tuple(hi - lo + 1))
        new_lo, new_hi = np.minimum(lo, self.origin), np.maximum(hi, end - 1)
        grown = ChunkValues(resolution, new_lo, tuple(new_hi - new_lo + 1))
        at = tuple(slice(a, a + n) for a, n in zip(self.origin - new_lo, self.values.shape, strict=True))
        grown.values[at], grown.known[at] = self.values, self.known
        return grown

    def get(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(known (N,) bool, values (N,) float32) at global lattice indices (N,3) inside the box."""
        at = tuple((index - self.origin).T)
        return self.known[at], self.values[at].astype(np.float32)

    def lookup(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Like `get` for any global lattice indices (N,3): points outside the box are unknown."""
        local = index - self.origin
        inside = np.all((local >= 0) & (local < self.values.shape), axis=1)
        known, values = np.zeros(len(index), dtype=bool), np.zeros(len(index), dtype=np.float32)
        known[inside], values[inside] = self.get(index[inside])
        return known, values

    def set(self, index: np.ndarray, values: np.ndarray) -> None:
        """Store values (N,) at global lattice indices (N,3) inside the box."""
        at = tuple((index - self.origin).T)
        self.values[at] = values
        self.known[at] = True
