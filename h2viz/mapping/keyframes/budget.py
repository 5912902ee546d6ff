"""Keeping the keyframes within a memory budget (mapping.keyframes.keyframe_budget_mb), still covering the map.

While the keyframes' rays, voxel lists and thumbnails take more than the budget:
1. retire the most redundant keyframe whose voxels all lie in other keyframes (H3-Mapping's pruning: the map stays
   covered, so no voxel loses its supervision);
2. else thin the keyframe with the most rays (every other valid pixel; a keyframe is thinned at most
   MAX_THINNING times, to 1/2^MAX_THINNING of its pixels), which keeps the voxels it sees;
3. else (every keyframe thinned as far as allowed) retire the keyframe that alone sees the fewest voxels, counted in
   `BudgetReport.coverage_lost`.
The newest keyframe is never retired (it is what the current frame is optimised against next), only thinned; a
budget smaller than one keyframe thinned as far as allowed is exceeded by that keyframe alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from h2viz.mapping.keyframes.keyframe_set import KeyframeSet
from h2viz.mapping.sampling.rays import FrameRays

MAX_THINNING = 3  # a keyframe keeps at least 1/8 of its valid pixels


@dataclass
class BudgetReport:
    """What enforcing the budget did, cumulated over a run."""

    retired: int = 0  # keyframes dropped whose voxels other keyframes still saw
    thinned: int = 0  # halvings of a keyframe's rays
    coverage_lost: int = 0  # keyframes dropped although they alone saw some voxels


def keyframe_bytes(keyframes: KeyframeSet, rays: list[FrameRays], thumbnails: list[np.ndarray]) -> int:
    """Memory of the keyframes: rays, voxel lists and coverage bitmaps, thumbnails (bytes)."""
    return sum(r.nbytes for r in rays) + keyframes.nbytes() + sum(t.nbytes for t in thumbnails)


class KeyframeBudget:
    """Enforces a keyframe memory budget on a mapper's keyframe lists (kept aligned by position)."""

    def __init__(self, budget_mb: float) -> None:
        self.budget_bytes = int(budget_mb * 1e6) if budget_mb > 0 else 0  # 0: unbounded
        self.report = BudgetReport()
        self.thinning: list[int] = []  # per keyframe: times its rays were halved

    def fit(self, keyframes: KeyframeSet, rays: list[FrameRays], thumbnails: list[np.ndarray]) -> list[int]:
        """Retire or thin keyframes until they fit the budget; the frame indices of the retired ones."""
        self.thinning += [0] * (len(rays) - len(self.thinning))
        retired: list[int] = []
        if not self.budget_bytes:
            return retired
        while rays and keyframe_bytes(keyframes, rays, thumbnails) > self.budget_bytes:
            unique, redundancy = keyframes.unique_counts()
            unique[-1] = np.iinfo(np.int64).max  # the newest keyframe stays
            free = np.flatnonzero(unique == 0)
            if free.size:
                j = int(free[np.argmax(redundancy[free])])
                self.report.retired += 1
            else:
                sizes = np.array([len(r) if t < MAX_THINNING else -1 for r, t in zip(rays, self.thinning, strict=True)])
                if sizes.max() > 0:
                    k = int(np.argmax(sizes))
                    rays[k].thin(2)
                    self.thinning[k] += 1
                    self.report.thinned += 1
                    continue
                if len(rays) == 1:  # the newest alone, thinned as far as allowed: over a budget this small
                    break
                j = int(np.argmin(unique))
                self.report.coverage_lost += 1
            retired.append(keyframes.frame_indices[j])
            keyframes.remove([j])
            del rays[j], thumbnails[j], self.thinning[j]
        return retired
