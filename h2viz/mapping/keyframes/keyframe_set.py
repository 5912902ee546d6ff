"""Keyframe insertion (voxel IoU / frame gap) and per-step keyframe selection (H2-Mapping coverage).

A keyframe is stored as the sorted unique int64 ids of the voxels it observed. Internally every id is
remapped to a dense index (in order of first appearance) and each keyframe becomes a compressed bitmap:
its non-empty 64-bit words over the dense index. Greedy coverage is evaluated lazily: after a pick,
every keyframe keeps its previous gain (uncovered voxels) as an upper bound, and only keyframes whose
bound could still beat the best exact gain are recounted, by popcount over their bitmap words.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from h2viz.errors import CheckpointError, ConfigError, FrameError
from h2viz.types import KeyframeState

STRATEGIES = ("coverage", "random", "overlap")
_STATE_KEYS = "frame_indices voxel_ids offsets covered_ids round_member selected rounds_completed rng_state"


def as_voxel_ids(voxel_ids: Any, what: str) -> np.ndarray:
    """Return `voxel_ids` as a sorted unique 1-D int64 array or raise FrameError naming `what`."""
    ids = np.asarray(voxel_ids)
    if ids.ndim != 1 or (ids.size > 0 and not np.issubdtype(ids.dtype, np.integer)):
        raise FrameError(f"{what}: voxel ids must be a 1-D integer array, got {ids.shape} {ids.dtype}")
    return np.unique(ids.astype(np.int64, copy=False))


def voxel_iou(a: np.ndarray, b: np.ndarray) -> float:
    """|a ∩ b| / |a ∪ b| of two sorted unique id arrays (1.0 when both are empty)."""
    if a.size == 0 and b.size == 0:
        return 1.0
    if a.size == 0 or b.size == 0:
        return 0.0
    pos = np.minimum(np.searchsorted(b, a), b.size - 1)
    inter = int(np.count_nonzero(b[pos] == a))
    return inter / (a.size + b.size - inter)


def _to_words(dense: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dense indices (N,) -> sorted unique word indices (W,) and their uint64 bit words (W,)."""
    d = np.sort(dense)
    word = d >> 6
    if d.size == 0:
        return word, np.zeros(0, np.uint64)
    starts = np.flatnonzero(np.r_[True, word[1:] != word[:-1]])
    bits = np.left_shift(np.uint64(1), (d & 63).astype(np.uint64))
    return word[starts], np.bitwise_or.reduceat(bits, starts)


def _ranges(starts: np.ndarray, lens: np.ndarray) -> np.ndarray:
    """Concatenation of arange(s, s + n) for every (s, n), vectorised."""
    ends = np.cumsum(lens)
    return np.repeat(starts - (ends - lens), lens) + np.arange(ends[-1] if ends.size else 0)


class _CoverageBits:
    """Keyframe x voxel incidence as compressed bitmaps, the covered voxels, and per keyframe an upper
    bound of its gain (uncovered voxels) that is exact where `exact` says so (lazy greedy)."""

    def __init__(self) -> None:
        self.word_idx = np.zeros(0, np.int64)  # (E,) word index of every bitmap entry, row by row
        self.words = np.zeros(0, np.uint64)  # (E,) bits of every entry
        self.row_start = np.zeros(1, np.int64)  # (n+1,) first entry of each keyframe
        self.covered = np.zeros(0, np.uint64)  # (ceil(U/64),) bits of covered voxels
        self.n_covered = 0
        self.sizes = np.zeros(0, np.int64)  # (n,) voxels per keyframe
        self.bound = np.zeros(0, np.int64)  # (n,) >= still-uncovered voxels per keyframe
        self.exact = np.zeros(0, bool)  # (n,) bound equals the gain

    def add_row(self, dense: np.ndarray, n_dense: int) -> None:
        """Append a keyframe given its dense voxel indices; the universe now has `n_dense` voxels."""
        idx, bits = _to_words(dense)
        n_words = (n_dense + 63) // 64
        self.covered = np.concatenate([self.covered, np.zeros(n_words - self.covered.size, np.uint64)])
        self.word_idx = np.concatenate([self.word_idx, idx])
        self.words = np.concatenate([self.words, bits])
        self.row_start = np.append(self.row_start, self.words.size)
        self.sizes = np.append(self.sizes, dense.size)
        self.bound = np.append(self.bound, int(np.bitwise_count(bits & ~self.covered[idx]).sum()))
        self.exact = np.append(self.exact, True)

    def counts(self, mask: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Per keyframe in `rows` (default: all), how many of its voxels are set in the word mask."""
        if rows is None:
            per_entry = np.bitwise_count(self.words & mask[self.word_idx])  # (E,)
            ends = self.row_start
        else:
            lens = self.row_start[rows + 1] - self.row_start[rows]
            ent = _ranges(self.row_start[rows], lens)  # (E',) entries of those rows
            per_entry = np.bitwise_count(self.words[ent] & mask[self.word_idx[ent]])
            ends = np.concatenate([[0], np.cumsum(lens)])
        cum = np.concatenate([[0], np.cumsum(per_entry, dtype=np.int64)])
        return cum[ends[1:]] - cum[ends[:-1]]

    def best(self, allowed: np.ndarray) -> int | None:
        """The allowed keyframe with the largest gain (the earliest among ties), None if all gains are 0.
        Stale bounds are refreshed only for keyframes that could still beat the best exact one."""
        batch, pos = 64, np.arange(allowed.size)
        while True:
            ub = np.where(allowed, self.bound, 0)  # (n,)
            ex = allowed & self.exact
            g = int(ub[ex].max()) if ex.any() else 0
            j = int(np.flatnonzero(ex & (ub == g))[0]) if g > 0 else allowed.size
            threat = allowed & ~self.exact & ((ub > g) | ((ub == g) & (pos < j)))
            if not threat.any():
                return j if g > 0 else None
            rows = np.flatnonzero(threat)
            if batch > 64 and rows.size * 4 > allowed.size:  # many contenders: refresh every bound
                self.refresh()
                continue
            rows = rows[np.lexsort((rows, -ub[rows]))[:batch]]  # the highest bounds first
            self.bound[rows] = self.sizes[rows] - self.counts(self.covered, rows)
            self.exact[rows] = True
            batch *= 4

    def cover(self, j: int) -> None:
        """Mark every voxel of keyframe `j` covered; other bounds become stale (gains only fall)."""
        s, e = self.row_start[j], self.row_start[j + 1]
        idx = self.word_idx[s:e]
        new = self.words[s:e] & ~self.covered[idx]  # newly covered bits per word
        self.covered[idx] |= new
        self.n_covered += int(np.bitwise_count(new).sum())
        self.bound[j] = 0
        self.exact = self.bound == 0

    def set_covered(self, mask: np.ndarray | None = None) -> None:
        """Replace the covered bits by `mask` (default: none covered) and make every bound exact."""
        self.covered = np.zeros_like(self.covered) if mask is None else mask.astype(np.uint64, copy=True)
        self.n_covered = int(np.bitwise_count(self.covered).sum())
        self.refresh()

    def refresh(self) -> None:
        """Make every gain bound exact."""
        self.bound = self.sizes - self.counts(self.covered) if self.n_covered else self.sizes.copy()
        self.exact = np.ones(self.sizes.size, bool)


class KeyframeSet:
    """The keyframes of a map: when to insert one, and which K to optimise with each new frame.

    Strategies: "coverage" (greedy coverage of not-yet-covered voxels, H2-Mapping), "random" (K
    uniformly random keyframes) and "overlap" (the K keyframes with the highest voxel IoU with the
    current frame). Every strategy marks the voxels of what it selects as covered, so rounds and
    keyframe states mean the same thing for all three.
    """

    def __init__(
        self,
        k: int = 10,
        iou_threshold: float = 0.85,
        max_gap: int = 100,
        strategy: str = "coverage",
        seed: int = 0,
    ) -> None:
        if strategy not in STRATEGIES:
            raise ConfigError(f"mapping.keyframes.keyframe_strategy: unknown {strategy!r}; use one of {STRATEGIES}")
        if k < 1 or max_gap < 1:
            raise ConfigError(f"mapping.keyframes.n_keyframes ({k}) and keyframe_max_gap ({max_gap}) must be >= 1")
        if not 0.0 <= iou_threshold <= 1.0:
            raise ConfigError(f"mapping.keyframes.keyframe_iou must lie in [0, 1], got {iou_threshold}")
        self.k, self.iou_threshold, self.max_gap = k, iou_threshold, max_gap
        self.strategy, self.seed = strategy, seed
        self._clear()

    def _clear(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        self._frames: list[int] = []
        self._ids: list[np.ndarray] = []  # per keyframe: sorted unique voxel ids (read-only)
        self._known = np.zeros(0, np.int64)  # sorted voxel ids seen in any keyframe
        self._known_dense = np.zeros(0, np.int64)  # dense index of each
        self._bits = _CoverageBits()
        self._round_member = np.zeros(0, bool)  # (n,) selected earlier in the current round
        self._selected: list[int] = []
        self.rounds_completed = 0

    # -- insertion ---------------------------------------------------------------------------------
    def should_insert(self, frame_index: int, voxel_ids: Any) -> bool:
        """True for the first frame, after `max_gap` frames, or when the voxel IoU with the last
        keyframe falls below the threshold. A frame that observes no voxel is never a keyframe."""
        ids = as_voxel_ids(voxel_ids, f"frame {frame_index}")
        if ids.size == 0:
            return False
        if not self._frames or frame_index - self._frames[-1] >= self.max_gap:
            return True
        return voxel_iou(ids, self._ids[-1]) < self.iou_threshold

    def insert(self, frame_index: int, voxel_ids: Any) -> int:
        """Add a keyframe (its voxels start uncovered unless already covered) and return its position."""
        ids = as_voxel_ids(voxel_ids, f"frame {frame_index}")
        ids.flags.writeable = False
        known, dense_known = self._lookup(ids)
        fresh = ids[~known]
        n_dense = self._known.size + fresh.size
        dense = np.empty(ids.size, np.int64)
        dense[known] = dense_known
        dense[~known] = np.arange(self._known.size, n_dense)
        at = np.searchsorted(self._known, fresh)
        self._known = np.insert(self._known, at, fresh)
        self._known_dense = np.insert(self._known_dense, at, dense[~known])
        self._bits.add_row(dense, n_dense)
        self._frames.append(int(frame_index))
        self._ids.append(ids)
        self._round_member = np.append(self._round_member, False)
        return len(self._frames) - 1

    def _lookup(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For sorted ids (N,): which are in a keyframe (N,) bool, and the dense index of those."""
        if self._known.size == 0:
            return np.zeros(ids.size, bool), np.zeros(0, np.int64)
        pos = np.minimum(np.searchsorted(self._known, ids), self._known.size - 1)
        known = self._known[pos] == ids
        return known, self._known_dense[pos[known]]

    def _word_mask(self, dense: np.ndarray) -> np.ndarray:
        """Bit-word mask (ceil(U/64),) with the given dense voxel indices set."""
        idx, bits = _to_words(dense)
        mask = np.zeros_like(self._bits.covered)
        mask[idx] = bits
        return mask

    # -- selection ---------------------------------------------------------------------------------
    def select(self, current_voxel_ids: Any, current_frame_index: int | None = None) -> list[int]:
        """Positions of the keyframes to optimise with the current frame, in pick order (at most K).

        Keyframes of `current_frame_index` are skipped: the current frame is optimised anyway.
        Coverage picks, greedily, the keyframe with the most uncovered voxels (ties: the earliest)
        while that gain is > 0. When every voxel is covered the round completes, all voxels are
        reset to uncovered and picking goes on in the new round (never repeating a keyframe within
        one call) until K are chosen or no remaining keyframe adds an uncovered voxel.
        """
        n = len(self._frames)
        allowed = np.ones(n, bool)
        if current_frame_index is not None:
            allowed &= np.asarray(self._frames, np.int64) != current_frame_index
        if self.strategy == "coverage":
            picks = self._select_coverage(allowed)
        elif self.strategy == "random":
            cand = np.flatnonzero(allowed)
            picks = [int(j) for j in self._rng.choice(cand, min(self.k, cand.size), replace=False)]
            for j in picks:
                self._mark(j)
        else:
            picks = self._select_overlap(current_voxel_ids, allowed)
        self._selected = picks
        return list(picks)

    def _select_coverage(self, allowed: np.ndarray) -> list[int]:
        picks: list[int] = []
        while len(picks) < self.k:
            j = self._bits.best(allowed)
            if j is None:
                break
            self._mark(j)
            allowed[j] = False
            picks.append(j)
        return picks

    def _select_overlap(self, current_voxel_ids: Any, allowed: np.ndarray) -> list[int]:
        cur = as_voxel_ids(current_voxel_ids, "current frame")
        inter = self._bits.counts(self._word_mask(self._lookup(cur)[1]))  # (n,)
        union = np.maximum(self._bits.sizes + cur.size - inter, 1)
        iou = np.where(allowed, inter / union, -1.0)
        order = np.lexsort((np.arange(iou.size), -iou))[: self.k]
        picks = [int(j) for j in order if iou[j] > 0]
        for j in picks:
            self._mark(j)
        return picks

    def _mark(self, j: int) -> None:
        """Cover keyframe j's voxels in the current round; complete the round when nothing is left."""
        self._bits.cover(j)
        self._round_member[j] = True
        if self._known.size and self._bits.n_covered == self._known.size:
            self.rounds_completed += 1
            self._bits.set_covered(None)
            self._round_member[:] = False

    # -- retirement ----------------------------------------------------------------------------------
    def remove(self, positions: list[int]) -> None:
        """Drop the keyframes at `positions`; the others keep their order, round membership, covered voxels (those
        still in a keyframe) and latest selection (renumbered)."""
        drop = np.zeros(len(self._frames), bool)
        drop[np.asarray(positions, np.int64)] = True
        if not drop.any():
            return
        state = self.state_dict()
        keep = np.flatnonzero(~drop)
        offsets = state["offsets"]
        new_pos = np.cumsum(~drop) - 1  # (n,) position after the removal, for the kept keyframes
        ids = [state["voxel_ids"][offsets[j] : offsets[j + 1]] for j in keep]
        remaining = np.unique(np.concatenate(ids)) if ids else np.zeros(0, np.int64)
        covered = state["covered_ids"]
        state.update(
            frame_indices=state["frame_indices"][keep],
            voxel_ids=np.concatenate(ids) if ids else np.zeros(0, np.int64),
            offsets=np.r_[0, np.cumsum([a.size for a in ids], dtype=np.int64)],
            covered_ids=covered[np.isin(covered, remaining)],
            round_member=state["round_member"][keep],
            selected=np.asarray([new_pos[j] for j in state["selected"] if not drop[j]], np.int64),
        )
        self.load_state_dict(state)

    def unique_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """Per keyframe: how many of its voxels no other keyframe saw (n,), and the mean number of other keyframes
        that saw each of its voxels (n,) (how redundant it is)."""
        if not self._ids:
            return np.zeros(0, np.int64), np.zeros(0)
        sizes = np.array([a.size for a in self._ids])
        _, inverse, counts = np.unique(np.concatenate(self._ids), return_inverse=True, return_counts=True)
        per_voxel = counts[inverse]  # (E,) keyframes seeing the voxel of each (keyframe, voxel) entry
        row = np.repeat(np.arange(sizes.size), sizes)  # (E,) keyframe of each entry
        unique = np.bincount(row, weights=per_voxel == 1, minlength=sizes.size).astype(np.int64)
        others = np.bincount(row, weights=per_voxel - 1, minlength=sizes.size) / np.maximum(sizes, 1)
        return unique, others

    def covered_voxels(self) -> np.ndarray:
        """Sorted ids of every voxel some keyframe saw."""
        return self._known.copy()

    def nbytes(self) -> int:
        """Memory held by the voxel lists and coverage bitmaps, bytes."""
        b = self._bits
        return int(sum(a.nbytes for a in self._ids) + self._known.nbytes * 2 + b.words.nbytes + b.word_idx.nbytes)

    # -- inspection --------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._frames)

    @property
    def frame_indices(self) -> list[int]:
        """Frame index of every keyframe, by position."""
        return list(self._frames)

    @property
    def selected(self) -> list[int]:
        """Positions chosen by the latest `select`."""
        return list(self._selected)

    @property
    def coverage_fraction(self) -> float:
        """Share of the keyframes' voxels covered in the current round."""
        total = self._known.size
        return self._bits.n_covered / total if total else 0.0

    def voxel_ids(self, position: int) -> np.ndarray:
        """Sorted unique (read-only) voxel ids observed by the keyframe at `position`."""
        return self._ids[position]

    def states(self) -> list[KeyframeState]:
        """Per keyframe: SELECTED in the latest selection, COVERED earlier in this round, else UNCOVERED."""
        out = [KeyframeState.COVERED if m else KeyframeState.UNCOVERED for m in self._round_member]
        for j in self._selected:
            out[j] = KeyframeState.SELECTED
        return out

    # -- checkpoints -------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly: NumPy arrays, ints and the RNG state."""
        ids = self._ids or [np.zeros(0, np.int64)]
        d = self._known_dense  # (U,) in id order
        covered = (self._bits.covered[d >> 6] >> (d & 63).astype(np.uint64)) & np.uint64(1) != 0
        return {
            "frame_indices": np.asarray(self._frames, np.int64),
            "voxel_ids": np.concatenate(ids),
            "offsets": np.r_[0, np.cumsum([a.size for a in self._ids], dtype=np.int64)],
            "covered_ids": self._known[covered],
            "round_member": self._round_member.copy(),
            "selected": np.asarray(self._selected, np.int64),
            "rounds_completed": self.rounds_completed,
            "rng_state": self._rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what `state_dict` returned (the constructor's settings are kept; on a
        CheckpointError the set is left empty or unchanged)."""
        missing = [key for key in _STATE_KEYS.split() if key not in state]
        if missing:
            raise CheckpointError(f"keyframe state lacks {missing}; the checkpoint is incomplete or too old")
        frames, offsets = np.asarray(state["frame_indices"]), np.asarray(state["offsets"])
        selected = np.asarray(state["selected"], np.int64)
        if offsets.size != frames.size + 1 or np.asarray(state["round_member"]).size != frames.size:
            raise CheckpointError("keyframe state: frame, offset and round arrays disagree in length")
        if np.any((selected < 0) | (selected >= frames.size)):
            raise CheckpointError("keyframe state: a selected position lies outside the keyframe set")
        self._clear()
        voxel_ids = np.asarray(state["voxel_ids"], np.int64)
        for i, frame in enumerate(frames):
            self.insert(int(frame), voxel_ids[offsets[i] : offsets[i + 1]])
        known, dense = self._lookup(as_voxel_ids(state["covered_ids"], "keyframe state"))
        if not np.all(known):
            self._clear()
            raise CheckpointError("keyframe state: covered voxels are not in any keyframe")
        self._bits.set_covered(self._word_mask(dense))
        self._round_member = np.asarray(state["round_member"], bool).copy()
        self._selected = [int(j) for j in selected]
        self.rounds_completed = int(state["rounds_completed"])
        self._rng.bit_generator.state = state["rng_state"]
