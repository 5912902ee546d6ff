"""Reusable memory for the copies a frozen field takes of the live one.

A mesh job meshes a frozen copy of the field (hash tables, fine SDF lattices: ~100 MB at 10k voxels), taken on the
mapping thread a few times a second while a stream plays. A fresh copy writes memory the OS has not committed yet,
and the page faults make it ~7x slower than copying into memory already in use (82 MB: 46 ms vs 6 ms on a 2-core
laptop CPU), time taken from integrating frames. `CopyPool` hands out destinations from the storages of copies no
longer alive (their owner, the frozen field, is gone), so that in steady state a copy faults no page.
"""

from __future__ import annotations

import threading
import weakref

import torch

MIN_BYTES = 1 << 20  # smaller tensors are cloned: their pages are few and the allocator reuses them anyway
HEADROOM = 1.5  # a new storage is this much larger than its first copy, so that the growing lattices fit it again
MAX_FREE = 3  # storages kept for reuse (one frozen field's: two hash tables, the fine lattices); the smallest beyond go


class CopyPool:
    """`copy(src, owner)` returns a copy of `src` whose storage goes back to the pool when `owner` is collected."""

    def __init__(self) -> None:
        self._free: list[torch.Tensor] = []  # flat storages (n,) not in use
        self._lock = threading.Lock()  # owners die on whichever thread dropped them last (the meshing thread)
        self.reused = 0  # copies made into a storage from the pool
        self.allocated = 0  # copies that needed a new storage

    def copy(self, src: torch.Tensor, owner: object) -> torch.Tensor:
        """A contiguous copy of `src`, valid while `owner` lives (nothing else may keep it beyond that)."""
        if src.numel() * src.element_size() < MIN_BYTES:
            return src.detach().clone()
        flat = self._take(src)
        if flat is None:
            flat = torch.empty(int(src.numel() * HEADROOM), dtype=src.dtype, device=src.device)
            self.allocated += 1
        else:
            self.reused += 1
        dst = flat[: src.numel()].view(src.shape)
        dst.copy_(src.detach())
        weakref.finalize(owner, self._give_back, flat)
        return dst

    @property
    def free_bytes(self) -> int:
        with self._lock:
            return sum(t.numel() * t.element_size() for t in self._free)

    def _take(self, src: torch.Tensor) -> torch.Tensor | None:
        """The smallest free storage that holds `src` (same dtype and device), removed from the pool."""
        with self._lock:
            fits = [
                i
                for i, t in enumerate(self._free)
                if t.dtype == src.dtype and t.device == src.device and t.numel() >= src.numel()
            ]
            if not fits:
                return None
            best = min(fits, key=lambda i: self._free[i].numel())
            return self._free.pop(best)

    def _give_back(self, flat: torch.Tensor) -> None:
        with self._lock:
            self._free.append(flat)
            if len(self._free) > MAX_FREE:
                self._free.pop(min(range(len(self._free)), key=lambda i: self._free[i].numel()))
