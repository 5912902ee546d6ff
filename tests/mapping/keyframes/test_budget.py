"""The keyframe memory budget: removal keeps the set consistent, redundant keyframes go first, thinning halves rays,
and a mapper under a small budget stays within it while every voxel a keyframe saw is still seen by one."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from h2viz.mapping.keyframes.budget import KeyframeBudget, keyframe_bytes
from h2viz.mapping.keyframes.keyframe_set import KeyframeSet
from h2viz.mapping.mapper import Mapper
from h2viz.mapping.sampling.rays import FrameRays
from h2viz.types import KeyframeState, RgbdFrame
from tests.mapping.analytic import Scene, orbit
from tests.mapping.backends import REFERENCE
from tests.mapping.test_mapper import small_cfg

torch.set_num_threads(2)
BUDGET_MB = 0.9
SETS = [np.arange(0, 30), np.arange(10, 40), np.arange(20, 50), np.arange(35, 60)]


def build(sets: list[np.ndarray], k: int = 2) -> KeyframeSet:
    ks = KeyframeSet(k=k)
    for i, ids in enumerate(sets):
        ks.insert(10 * i, ids)
    return ks


def flat_frame(index: int, height: int = 40, width: int = 50) -> RgbdFrame:
    depth = np.full((height, width), 1.5, np.float32)
    rgb = np.full((height, width, 3), 100, np.uint8)
    K = np.array([[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]])
    return RgbdFrame(index, 0.0, rgb, depth, K, np.eye(4))


def test_unique_counts_and_redundancy_on_overlapping_ranges() -> None:
    unique, redundancy = build(SETS).unique_counts()
    # 0-9 only in the first; 30-34 in the second and third; 50-59 only in the fourth
    np.testing.assert_array_equal(unique, [10, 0, 0, 10])
    # second: 10-19 in 1 other, 20-29 in 2 others, 30-34 in 1, 35-39 in 2 -> (10 + 20 + 5 + 10) / 30
    assert redundancy[1] == pytest.approx(45 / 30)


def test_removal_renumbers_positions_and_keeps_covered_voxels_and_selection() -> None:
    ks = build(SETS)
    picks = ks.select(np.arange(0, 5))
    assert picks == [0, 3]  # the largest gains: 30 new voxels, then 25
    ks.remove([1])
    assert ks.frame_indices == [0, 20, 30] and ks.selected == [0, 2]
    np.testing.assert_array_equal(ks.voxel_ids(1), np.arange(20, 50))
    assert ks.states() == [KeyframeState.SELECTED, KeyframeState.UNCOVERED, KeyframeState.SELECTED]
    assert ks.coverage_fraction == pytest.approx(55 / 60)  # 0-29 and 35-59 of 0-59
    assert ks.select(np.arange(0, 5)) == [1, 0]  # 30-34 completes the round, then a new one starts
    np.testing.assert_array_equal(ks.covered_voxels(), np.arange(60))


def test_budget_retires_the_redundant_keyframe_then_thins_the_largest() -> None:
    ks, rays, thumbs = KeyframeSet(k=2), [], []
    for i, ids in enumerate(SETS[:3]):
        ks.insert(i, ids)
        rays.append(FrameRays(flat_frame(i), REFERENCE))
        thumbs.append(np.zeros((4, 5, 3), np.uint8))
    one = rays[0].nbytes  # 2000 pixels x 11 bytes
    assert one == 2000 * 11
    total = keyframe_bytes(ks, rays, thumbs)
    budget = KeyframeBudget((total - one // 2) / 1e6)  # one keyframe too many, less than a whole one
    assert budget.fit(ks, rays, thumbs) == [1]  # the middle one: its voxels lie in the others
    assert budget.report.retired == 1 and len(rays) == 2 and ks.frame_indices == [0, 2]
    np.testing.assert_array_equal(ks.covered_voxels(), np.arange(50))  # coverage kept
    tight = KeyframeBudget(keyframe_bytes(ks, rays, thumbs) / 1e6 - 1e-3)
    tight.thinning = [0, 0]
    assert tight.fit(ks, rays, thumbs) == []  # both keyframes alone see voxels: thinned, not retired
    assert tight.report.thinned == 1 and len(rays[0]) == 1000 and len(rays[1]) == 2000
    np.testing.assert_array_equal(rays[0].valid.numpy(), np.arange(0, 2000, 2))  # every other pixel of the image
    assert keyframe_bytes(ks, rays, thumbs) <= tight.budget_bytes


def test_budget_without_room_to_thin_retires_the_least_unique_and_counts_it() -> None:
    ks, rays, thumbs = build(SETS), [FrameRays(flat_frame(i), REFERENCE) for i in range(4)], []
    thumbs = [np.zeros((1, 1, 3), np.uint8)] * 4
    ks.remove([1])  # no redundant keyframe left: 0-29, 20-49, 35-59 each alone see some
    del rays[1], thumbs[1]
    budget = KeyframeBudget(1e-6)
    budget.thinning = [3, 3, 3]  # thinned as far as allowed
    budget.fit(ks, rays, thumbs)
    assert len(rays) == 1 and ks.frame_indices == [30]  # the newest stays
    assert budget.report.coverage_lost == 2


def test_a_mapper_under_a_small_budget_stays_within_it_and_keeps_every_voxel_covered() -> None:
    scene = Scene("room", center=np.array([0.0, 0.0, 1.0]))
    poses = orbit(scene, 10, 0.3, 1.0, np.array([0.0, 0.0, 0.9])) * 2  # the room twice: the second lap revisits
    free = Mapper(small_cfg(max_iters=1, keyframe_iou=0.95, keyframe_budget_mb=0))
    bounded = Mapper(small_cfg(max_iters=1, keyframe_iou=0.95, keyframe_budget_mb=BUDGET_MB))
    peak = 0.0
    for i, T in enumerate(poses):
        frame = scene.frame(i, T)
        free.integrate(frame)
        peak = max(peak, bounded.integrate(frame).keyframe_mb)
    assert free.keyframe_mb > 1.5 * BUDGET_MB and peak <= BUDGET_MB  # 96x72 frames: ~76 kB of rays a keyframe
    assert len(bounded.keyframes) < len(free.keyframes)
    report = bounded.keyframe_budget.report
    assert report.retired > 0 and report.coverage_lost == 0  # the second lap's keyframes overlap the first's
    np.testing.assert_array_equal(bounded.keyframes.covered_voxels(), free.keyframes.covered_voxels())
    assert len(bounded.thumbnails) == len(bounded.keyframe_rays) == len(bounded.keyframes)


def test_a_lone_keyframe_over_the_budget_is_thinned_but_kept() -> None:
    ks, rays, thumbs = build(SETS[:1]), [FrameRays(flat_frame(0), REFERENCE)], [np.zeros((1, 1, 3), np.uint8)]
    budget = KeyframeBudget(1e-6)
    assert budget.fit(ks, rays, thumbs) == [] and len(rays) == 1
    assert budget.report.thinned == 3 and len(rays[0]) == 2000 // 8  # down to 1/8 of its pixels, then left alone
