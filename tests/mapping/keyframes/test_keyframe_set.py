"""Keyframe insertion (IoU / gap rule) and selection (coverage, random, overlap) on hand-built voxel sets."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from h2viz.errors import CheckpointError, ConfigError, FrameError
from h2viz.mapping.keyframes.keyframe_set import KeyframeSet, voxel_iou
from h2viz.types import KeyframeState

SEL, COV, UNC = KeyframeState.SELECTED, KeyframeState.COVERED, KeyframeState.UNCOVERED


def span(*ranges: tuple[int, int]) -> np.ndarray:
    """Voxel ids of the half-open ranges [a, b)."""
    return np.concatenate([np.arange(a, b, dtype=np.int64) for a, b in ranges])


def build(sets: list[np.ndarray], k: int, **kwargs: object) -> KeyframeSet:
    ks = KeyframeSet(k=k, **kwargs)  # type: ignore[arg-type]
    for i, ids in enumerate(sets):
        assert ks.insert(10 * i, ids) == i
    return ks


class GreedyReference:
    """Plain-set greedy coverage with the same round rule, written for clarity, not speed."""

    def __init__(self, k: int) -> None:
        self.k, self.sets, self.covered, self.rounds = k, [], set(), 0

    def select(self, skip: int | None = None) -> list[int]:
        universe = set().union(*self.sets)
        picks: list[int] = []
        while len(picks) < self.k:
            gains = [
                -1 if (i in picks or i == skip) else len(s - self.covered) for i, s in enumerate(self.sets)
            ]
            j = int(np.argmax(gains))
            if gains[j] <= 0:
                break
            picks.append(j)
            self.covered |= self.sets[j]
            if self.covered >= universe:
                self.rounds, self.covered = self.rounds + 1, set()
        return picks


# -- insertion ---------------------------------------------------------------------------------------
def test_voxel_iou_hand_computed() -> None:
    assert voxel_iou(span((1, 5)), span((3, 6))) == pytest.approx(2 / 5)
    assert voxel_iou(span((0, 10)), span((10, 20))) == 0.0
    assert voxel_iou(span((0, 10)), span((0, 10))) == 1.0
    assert voxel_iou(span((0, 0)), span((0, 3))) == 0.0
    assert voxel_iou(span((0, 0)), span((0, 0))) == 1.0


def test_first_frame_is_a_keyframe_unless_it_sees_nothing() -> None:
    ks = KeyframeSet()
    assert not ks.should_insert(0, np.zeros(0, np.int64))
    assert ks.should_insert(3, [7, 7, 9])
    assert ks.insert(3, [9, 7, 7]) == 0
    assert ks.frame_indices == [3] and len(ks) == 1
    np.testing.assert_array_equal(ks.voxel_ids(0), [7, 9])


@pytest.mark.parametrize(
    ("ids", "expected_iou"),
    [(span((0, 90)), 0.90), (span((0, 85)), 0.85), (span((0, 84)), 0.84), (span((10, 110)), 90 / 110)],
)
def test_iou_threshold_crossing(ids: np.ndarray, expected_iou: float) -> None:
    ks = KeyframeSet(iou_threshold=0.85)
    ks.insert(0, span((0, 100)))
    assert voxel_iou(np.unique(ids), ks.voxel_ids(0)) == pytest.approx(expected_iou)
    assert ks.should_insert(5, ids) == (expected_iou < 0.85)
    assert KeyframeSet(iou_threshold=0.55).should_insert(0, ids)  # empty set: first frame
    low = KeyframeSet(iou_threshold=0.55)
    low.insert(0, span((0, 100)))
    assert not low.should_insert(5, ids)


def test_reference_is_the_last_inserted_keyframe() -> None:
    ks = KeyframeSet(iou_threshold=0.85)
    ks.insert(0, span((0, 100)))
    drift = [span((s, s + 100)) for s in range(0, 40, 5)]
    decisions = [ks.should_insert(i, ids) for i, ids in enumerate(drift)]
    # IoU with 0..99 falls below 0.85 once the shift exceeds 100 * 0.15 / 1.85 = 8.1 voxels
    assert decisions == [False, False, True, True, True, True, True, True]
    ks.insert(2, drift[2])
    assert not ks.should_insert(3, drift[3])  # 15..114 vs 10..109: IoU 95/105


def test_max_gap_forces_a_keyframe() -> None:
    ks = KeyframeSet(max_gap=100)
    ks.insert(7, span((0, 50)))
    assert not ks.should_insert(106, span((0, 50)))
    assert ks.should_insert(107, span((0, 50)))
    assert KeyframeSet(max_gap=3).should_insert(0, [1])


def test_invalid_input_raises_typed_errors() -> None:
    with pytest.raises(ConfigError, match="coverage.*random.*overlap"):
        KeyframeSet(strategy="loss")
    with pytest.raises(ConfigError):
        KeyframeSet(k=0)
    with pytest.raises(ConfigError):
        KeyframeSet(iou_threshold=1.5)
    ks = KeyframeSet()
    with pytest.raises(FrameError, match="frame 4"):
        ks.insert(4, np.zeros((3, 2), np.int64))
    with pytest.raises(FrameError, match="integer"):
        ks.should_insert(4, np.array([1.5, 2.0]))


# -- coverage selection ------------------------------------------------------------------------------
OPTIMAL_TWO = [
    span((10, 45)),  # 0: decoy, 35
    span((55, 95)),  # 1: decoy, 40
    span((30, 70)),  # 2: decoy, 40
    span((0, 50)),  # 3: optimal half, 50
    span((0, 20), (80, 100)),  # 4: decoy, 40
    span((50, 100)),  # 5: optimal half, 50
]


def test_greedy_finds_the_two_keyframes_that_cover_everything() -> None:
    ks = build(OPTIMAL_TWO, k=2)
    assert ks.select([]) == [3, 5]
    assert ks.rounds_completed == 1  # one step: the fewest possible
    assert ks.states() == [UNC, UNC, UNC, SEL, UNC, SEL]
    one = build(OPTIMAL_TWO, k=1)
    assert one.select([]) == [3] and one.rounds_completed == 0
    assert one.coverage_fraction == pytest.approx(0.5)
    assert one.select([]) == [5] and one.rounds_completed == 1
    assert one.coverage_fraction == 0.0


def test_completed_round_continues_into_the_next_within_one_call() -> None:
    ks = build(OPTIMAL_TWO, k=4)
    # round 1: 3, 5 (ties: the earliest first). Round 2, all uncovered again, 3 and 5 excluded:
    # 1 (40, earliest of three 40s), then 0 (35 new) beats 2 and 4 (25 new each).
    assert ks.select([]) == [3, 5, 1, 0]
    assert ks.rounds_completed == 1
    assert ks.states() == [SEL, SEL, UNC, SEL, UNC, SEL]
    assert ks.coverage_fraction == pytest.approx(75 / 100)  # 10..44 and 55..94


CHAIN = [span((0, 30)), span((20, 60)), span((50, 90)), span((25, 36)), span((85, 100))]
# greedy order: 1 (40), 2 (30 new), 0 (20 new), 4 (10 new); 3 lies inside 1 and never adds anything


def test_k1_visits_every_contributing_keyframe_then_resets() -> None:
    ks = build(CHAIN, k=1)
    expected_states = [
        [UNC, SEL, UNC, UNC, UNC],
        [UNC, COV, SEL, UNC, UNC],
        [SEL, COV, COV, UNC, UNC],
        [UNC, UNC, UNC, UNC, SEL],  # round complete: everything is uncovered again
    ]
    for step, (pick, states) in enumerate(zip([1, 2, 0, 4], expected_states, strict=True)):
        assert ks.select([]) == [pick]
        assert ks.states() == states
        assert ks.rounds_completed == (1 if step == 3 else 0)
    assert ks.select([]) == [1]  # second round starts like the first
    assert ks.states() == [UNC, SEL, UNC, UNC, UNC]


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_round_completes_within_ceil_needed_over_k_steps(k: int) -> None:
    ks = build(CHAIN, k=k)
    steps = 0
    while ks.rounds_completed == 0:
        ks.select([])
        steps += 1
    assert steps == math.ceil(4 / k)


def test_round_spill_over_states() -> None:
    ks = build(CHAIN, k=3)
    assert ks.select([]) == [1, 2, 0]
    assert ks.select([]) == [4, 1, 2]  # 4 completes the round, 1 and 2 open the next
    assert ks.rounds_completed == 1
    assert ks.states() == [UNC, SEL, SEL, UNC, SEL]
    assert ks.select([]) == [0, 4, 1]  # 3 adds nothing; 4 completes round 2, 1 opens round 3
    assert ks.rounds_completed == 2
    assert ks.states() == [SEL, SEL, UNC, UNC, SEL]


def test_new_voxels_mid_round_are_uncovered() -> None:
    ks = build([span((0, 50)), span((50, 100))], k=1)
    assert ks.select([]) == [0]
    assert ks.insert(99, span((40, 60), (100, 120))) == 2  # 20 voxels never seen before
    assert ks.states() == [SEL, UNC, UNC]
    assert ks.select([]) == [1]
    assert ks.rounds_completed == 0 and ks.coverage_fraction == pytest.approx(100 / 120)
    assert ks.states() == [COV, SEL, UNC]
    assert ks.select([]) == [2]
    assert ks.rounds_completed == 1


def test_current_frame_keyframe_is_not_selected() -> None:
    ks = build(OPTIMAL_TWO, k=2)  # frame indices 0, 10, ..., 50
    assert ks.select([], current_frame_index=30) == [5, 0]  # position 3 is the current frame
    assert ks.select([], current_frame_index=30) == [4, 2]
    assert ks.rounds_completed == 1


@pytest.mark.parametrize("k", [1, 3, 10])
def test_lazy_greedy_matches_plain_greedy(k: int) -> None:
    rng = np.random.default_rng(k)
    ks, ref = KeyframeSet(k=k), GreedyReference(k)
    for step in range(80):
        if step % 3 == 0:  # windows over a growing map, large sparse ids, many ties
            lo = int(rng.integers(0, 4 * step + 10))
            ids = rng.choice(np.arange(lo, lo + 60), size=int(rng.integers(1, 40)), replace=False)
            ids = ids.astype(np.int64) * 1_000_003 - 2**40
            ks.insert(step, ids)
            ref.sets.append(set(ids.tolist()))
        skip = len(ref.sets) - 1 if step % 5 == 0 else None
        current = None if skip is None else ks.frame_indices[skip]
        assert ks.select([], current_frame_index=current) == ref.select(skip), f"step {step}"
        assert ks.rounds_completed == ref.rounds


@pytest.mark.parametrize("layout", ["windows", "scattered"])
def test_large_instance_matches_dense_greedy(layout: str) -> None:
    rng = np.random.default_rng(0)
    if layout == "windows":  # spatially coherent views
        starts, sizes = rng.integers(0, 18_500, size=300), rng.integers(200, 1500, size=300)
        sets = [np.arange(s, s + n) for s, n in zip(starts, sizes, strict=True)]
    else:  # every keyframe sees a random 5 % of the map: many near-equal gains
        sets = [rng.choice(20_000, size=1000, replace=False) for _ in range(300)]
    ks = build(sets, k=10)
    member = np.zeros((300, 20_000), bool)  # keyframe x voxel
    for i, ids in enumerate(sets):
        member[i, ids] = True
    universe, uncovered, rounds = member.any(axis=0), member.any(axis=0), 0
    for step in range(12):
        picks, allowed = [], np.ones(300, bool)
        while len(picks) < 10:
            gains = np.where(allowed, (member & uncovered).sum(axis=1), 0)
            j = int(np.argmax(gains))
            if gains[j] == 0:
                break
            picks.append(j)
            allowed[j], uncovered = False, uncovered & ~member[j]
            if not uncovered.any():
                rounds, uncovered = rounds + 1, universe.copy()
        assert ks.select([]) == picks, f"step {step}"
        assert ks.rounds_completed == rounds
    assert rounds >= 1  # the comparison spans a round reset


# -- other strategies --------------------------------------------------------------------------------
def test_random_strategy_is_seeded_and_distinct() -> None:
    sets = [span((i, i + 5)) for i in range(0, 200, 10)]
    a, b, c = (build(sets, k=5, strategy="random", seed=s) for s in (3, 3, 4))
    runs_a = [a.select([]) for _ in range(6)]
    assert runs_a == [b.select([]) for _ in range(6)]
    assert runs_a != [c.select([]) for _ in range(6)]
    for picks in runs_a:
        assert len(picks) == 5 and len(set(picks)) == 5 and all(0 <= j < 20 for j in picks)
    assert len(build(sets[:3], k=5, strategy="random").select([])) == 3


def test_overlap_strategy_returns_highest_iou() -> None:
    sets = [span((50, 150)), span((200, 300)), span((0, 50)), span((0, 100)), span((90, 110))]
    # IoU with 0..99: 50/150, 0, 50/100, 1, 10/110
    ks = build(sets, k=3, strategy="overlap")
    assert ks.select(span((0, 100))) == [3, 2, 0]
    assert ks.states() == [SEL, UNC, SEL, SEL, UNC]
    wide = build(sets, k=10, strategy="overlap")
    assert wide.select(span((0, 100))) == [3, 2, 0, 4]  # no overlap, not selected
    assert wide.select(span((0, 100)), current_frame_index=30) == [2, 0, 4]
    assert wide.select(span((1000, 1010))) == []


# -- checkpoints -------------------------------------------------------------------------------------
@pytest.mark.parametrize("strategy", ["coverage", "random", "overlap"])
def test_state_dict_round_trip_reproduces_the_next_selection(strategy: str) -> None:
    rng = np.random.default_rng(1)
    starts, sizes = rng.integers(0, 900, 25), rng.integers(5, 120, 25)
    sets = [np.arange(s, s + n) for s, n in zip(starts, sizes, strict=True)]
    ks = build(sets, k=4, strategy=strategy, seed=9)
    for _ in range(3):
        ks.select(sets[-1])
    state = copy.deepcopy(ks.state_dict())
    for value in state.values():
        assert isinstance(value, np.ndarray | int | dict)
    other = KeyframeSet(k=4, strategy=strategy, seed=123)
    other.load_state_dict(state)
    assert other.states() == ks.states() and other.frame_indices == ks.frame_indices
    assert other.coverage_fraction == ks.coverage_fraction
    for step in range(8):
        assert other.select(sets[step]) == ks.select(sets[step])
        assert other.rounds_completed == ks.rounds_completed
        assert other.states() == ks.states()


def test_load_state_dict_rejects_incomplete_state() -> None:
    state = build(OPTIMAL_TWO, k=2).state_dict()
    del state["covered_ids"]
    with pytest.raises(CheckpointError, match="covered_ids"):
        KeyframeSet().load_state_dict(state)
    state = build(OPTIMAL_TWO, k=2).state_dict()
    state["offsets"] = state["offsets"][:-1]
    with pytest.raises(CheckpointError, match="length"):
        KeyframeSet().load_state_dict(state)
    state = build(OPTIMAL_TWO, k=2).state_dict()
    state["covered_ids"] = np.array([5000])
    target = KeyframeSet()
    with pytest.raises(CheckpointError, match="covered"):
        target.load_state_dict(state)
    assert len(target) == 0
