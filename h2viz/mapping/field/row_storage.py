"""Per-voxel arrays that grow with the octree without stalling the frame that grows them.

The colour and fine SDF priors keep one lattice per voxel (35 KB and 6 KB at the defaults), so a map of 10k voxels
holds half a gigabyte of them. Growing them the plain way (allocate zeroed storage, copy the old rows in) makes the
frame that crosses a size step write the whole new block, and the OS commits its pages on that first write: on a
2-core laptop CPU that stalls integration for a few hundred milliseconds, and where page faults are costly (VMs,
sandboxes), for seconds, longer than a live stream's backlog.

`RowStorage` reserves storage uninitialised (the OS commits nothing until it is written), doubles it when it runs
out (each row is copied about once), and zeroes only the rows it hands out: a frame pays for the memory its own
new voxels take, and a size step for one copy of the rows in use. On the host the first reservation is large
(`RESERVE_BYTES` of address space, of which only the rows in use are ever committed), so that a map of up to ~30k
voxels never copies its colour lattices: each doubling copy of a live map's lattices (hundreds of MB into memory
that page-faults as it is written) held integration for 0.2-0.5 s, 15 % of a live stream's mapping time on 2 cores.

A background thread that zeroed rows ahead of use was measured and not kept: on 2 cores the page faults it takes
slow the mapping thread more than the stalls it removes (median integration 30 -> 85 ms on the synthetic room).
"""

from __future__ import annotations

import torch

MIN_ROWS = 256  # the first reservation, rows (at least)
RESERVE_BYTES = 1 << 30  # the first reservation on the host, bytes of address space (committed only as used)


class RowStorage:
    """The storage behind one growing (V, ...) array: `grow(rows, n)` returns `rows` grown to n rows, the new ones
    zero, as a view of the first n rows of a larger storage. `rows` may be any tensor (a loaded checkpoint's, one
    moved to another device): one that is not this storage's view is copied into fresh storage."""

    def __init__(self) -> None:
        self._storage: torch.Tensor | None = None  # (C, ...); rows past those handed out are uninitialised
        self._used = 0  # rows handed out

    @property
    def capacity(self) -> int:
        return 0 if self._storage is None else int(self._storage.shape[0])

    def grow(self, rows: torch.Tensor, n: int) -> torch.Tensor:
        """`rows` (V, ...) grown to max(V, n) rows, the new ones zero."""
        v = int(rows.shape[0])
        if n <= v:
            return rows
        if not self._backs(rows) or n > self.capacity:
            grown = self._reserve(rows, max(n, 2 * v, MIN_ROWS))
            grown[:v] = rows
            self._storage = grown
        assert self._storage is not None
        self._storage[v:n].zero_()
        self._used = n
        return self._storage[:n]

    def _reserve(self, rows: torch.Tensor, n: int) -> torch.Tensor:
        """Uninitialised storage for at least n rows like `rows`'; on the host, the first holds `RESERVE_BYTES`."""
        shape, dtype, device = rows.shape[1:], rows.dtype, rows.device
        if self._storage is None and device.type == "cpu":
            row_bytes = max(1, shape.numel() * rows.element_size())
            large = max(n, RESERVE_BYTES // row_bytes)
            try:
                return torch.empty((large, *shape), dtype=dtype, device=device)
            except RuntimeError:  # address space refused (strict overcommit, a ulimit): grow by doubling
                pass
        return torch.empty((n, *shape), dtype=dtype, device=device)

    def release(self) -> None:
        """Drop the storage (the array was replaced: a checkpoint loaded, moved to another device)."""
        self._storage, self._used = None, 0

    def _backs(self, rows: torch.Tensor) -> bool:
        """`rows` is the view this storage handed out last."""
        s = self._storage
        return (
            s is not None
            and rows.device == s.device
            and rows.dtype == s.dtype
            and rows.shape[1:] == s.shape[1:]
            and rows.data_ptr() == s.data_ptr()
            and rows.shape[0] == self._used
        )
