"""Snapshot diffing: which mesh chunks and which octree blocks changed since they were drawn."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from h2viz.types import MeshChunk

Key = tuple[int, int, int]


@dataclass(frozen=True)
class ChunkDiff:
    changed: list[Key]  # new or re-meshed since drawn (send these)
    removed: list[Key]  # drawn but gone from the map (remove these)


def diff_chunks(drawn: Mapping[Key, MeshChunk], current: Mapping[Key, MeshChunk]) -> ChunkDiff:
    """Compare by object identity: the mapper hands out the same MeshChunk object for a chunk that
    was not re-meshed, so anything else (new key, new object) must be sent again."""
    changed = sorted(k for k, c in current.items() if drawn.get(k) is not c)
    removed = sorted(k for k in drawn if k not in current)
    return ChunkDiff(changed, removed)


def group_cells(cells: np.ndarray, block: int) -> dict[Key, np.ndarray]:
    """Split integer cells (N,3) into blocks of `block`^3 cells: block key -> its cells (n,3),
    each block's cells in lexicographic order (so equal sets give equal bytes)."""
    cells = np.unique(np.asarray(cells, dtype=np.int32).reshape(-1, 3), axis=0)  # sorted rows
    if len(cells) == 0:
        return {}
    keys = np.floor_divide(cells, block)  # (N,3)
    order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))  # stable: cells stay sorted
    keys, cells = keys[order], cells[order]
    starts = np.flatnonzero(np.any(np.diff(keys, axis=0) != 0, axis=1)) + 1
    bounds = np.concatenate([[0], starts, [len(cells)]])
    return {
        (int(keys[a, 0]), int(keys[a, 1]), int(keys[a, 2])): cells[a:b]
        for a, b in zip(bounds[:-1], bounds[1:], strict=True)
    }


def block_signatures(groups: Mapping[Key, np.ndarray]) -> dict[Key, int]:
    """A content hash per block (equal cell sets give equal values)."""
    return {k: hash(v.tobytes()) for k, v in groups.items()}


def diff_signatures(drawn: Mapping[Key, int], current: Mapping[Key, int]) -> ChunkDiff:
    changed = sorted(k for k, s in current.items() if drawn.get(k) != s)
    removed = sorted(k for k in drawn if k not in current)
    return ChunkDiff(changed, removed)
