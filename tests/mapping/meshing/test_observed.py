"""Observed cells: the bit dilation against a brute-force neighbourhood search, and meshing that keeps only the
faces near measured depth."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from h2viz.mapping.field.octree import VoxelOctree
from h2viz.mapping.meshing.mesher import ChunkedMesher, merge_chunks
from h2viz.mapping.meshing.observed import SUB, ObservedCells
from tests.mapping.backends import FAST, needs_numba

VS = 0.1
CELL = VS / SUB


def _octree(rng: np.random.Generator) -> tuple[VoxelOctree, np.ndarray]:
    """Clustered voxels around the origin, negative coordinates included, with gaps between them; and the
    points (N,3) that allocated them."""
    octree = VoxelOctree(VS, min_points=0, expansion=False)
    centres = rng.uniform(-0.35, 0.35, size=(40, 3))
    points = centres.repeat(3, axis=0) + rng.normal(0, 0.06, size=(120, 3))
    octree.allocate(points)
    return octree, points


def test_dilated_cells_match_a_brute_force_search_across_voxel_borders() -> None:
    rng = np.random.default_rng(4)
    octree, points = _octree(rng)
    observed = ObservedCells(VS)
    marked = points.repeat(25, axis=0) + rng.normal(0.0, 0.03, size=(3000, 3))  # some outside any voxel
    observed.add(octree, marked)
    allocated = {tuple(c) for c in octree.voxel_coords()}
    cells = {tuple(c) for c in np.floor(marked / CELL).astype(np.int64) if tuple(c // SUB) in allocated}
    offsets = list(itertools.product((-1, 0, 1), repeat=3))
    near = marked.repeat(4, axis=0) + rng.normal(0.0, 0.015, size=(12000, 3))  # 1-2 cells off a marked point
    queries = np.concatenate([near, rng.uniform(-0.45, 0.45, size=(10000, 3))])
    support = observed.snapshot(octree)
    got = support.contains(queries)
    want = np.array(
        [
            tuple(c // SUB) in allocated and any((c[0] + a, c[1] + b, c[2] + d) in cells for a, b, d in offsets)
            for c in np.floor(queries / CELL).astype(np.int64)
        ]
    )
    assert want.sum() > 1000 and (~want).sum() > 1000  # both answers well represented
    assert not (got & ~want).any()  # never a cell without an observed cell around it
    # bits travel along z, then y, then x through allocated voxels: exact wherever the block's voxels all exist
    whole_block = np.array(
        [
            all(tuple((c + np.array(o)) // SUB) in allocated for o in offsets)
            for c in np.floor(queries / CELL).astype(np.int64)
        ]
    )
    assert whole_block.sum() > 3000
    np.testing.assert_array_equal(got[whole_block], want[whole_block])
    assert (got == want).mean() > 0.995  # elsewhere too, but for cells diagonally across a missing voxel


def test_points_outside_allocated_voxels_are_ignored_and_snapshots_are_frozen() -> None:
    octree = VoxelOctree(VS, min_points=0, expansion=False)
    octree.allocate(np.array([[0.05, 0.05, 0.05]]))
    observed = ObservedCells(VS)
    observed.add(octree, np.array([[0.31, 0.05, 0.05], [0.01, 0.01, 0.01]]))  # the first is in no voxel
    support = observed.snapshot(octree)
    assert support.contains(np.array([[0.02, 0.02, 0.02], [0.024, 0.001, 0.001], [0.034, 0.01, 0.01]])).tolist() == [
        True,
        True,
        False,
    ]
    observed.add(octree, np.array([[0.09, 0.09, 0.09]]))
    assert not support.contains(np.array([[0.08, 0.08, 0.08]]))[0]  # marked after the snapshot
    assert observed.snapshot(octree).contains(np.array([[0.08, 0.08, 0.08]]))[0]


def test_strict_voxels_need_their_own_cell_observed() -> None:
    octree = VoxelOctree(VS, min_points=0, expansion=False)
    octree.allocate(np.array([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05]]))
    observed = ObservedCells(VS)
    observed.add(octree, np.array([[0.051, 0.051, 0.051], [0.151, 0.051, 0.051]]))
    own = np.array([[0.052, 0.052, 0.052], [0.152, 0.052, 0.052]])  # in the observed cells
    next_door = own + [0.0, CELL, 0.0]  # one cell over
    queries = np.concatenate([own, next_door])
    assert observed.snapshot(octree).contains(queries).tolist() == [True, True, True, True]
    second = observed.snapshot(octree, strict=np.array([False, True]))  # only the second voxel is strict
    assert second.contains(queries).tolist() == [True, True, True, False]


def test_meshing_keeps_only_the_surface_near_observed_depth() -> None:
    """Two parallel planes in one voxel slab; depth was measured on the first only: the second, 5 cm away, goes."""
    voxels = np.array([(i, j, k) for i in range(-3, 3) for j in range(-3, 3) for k in (0,)], dtype=np.int64)
    octree = VoxelOctree(VS, min_points=0, expansion=False)
    octree.allocate((voxels + 0.5) * VS)

    def two_planes(p: np.ndarray, voxel: np.ndarray | None = None) -> np.ndarray:  # zero at z = 2.2 and 7.2 cm
        return (np.abs(p[:, 2] - 0.047) - 0.025).astype(np.float32)

    def colour(p: np.ndarray) -> np.ndarray:
        return np.full((len(p), 3), 128, np.uint8)

    observed = ObservedCells(VS)
    grid = np.stack(np.meshgrid(np.linspace(-0.3, 0.3, 120), np.linspace(-0.3, 0.3, 120)), -1).reshape(-1, 2)
    observed.add(octree, np.c_[grid, np.full(len(grid), 0.022)])
    ids = octree.voxels.lookup(octree.voxels.keys)
    both = merge_chunks(ChunkedMesher(VS, 8, 4).update(octree.voxel_coords(), None, two_planes, colour, 1))
    keep = observed.snapshot(octree).contains
    near = merge_chunks(
        ChunkedMesher(VS, 8, 4).update(octree.voxel_coords(), None, two_planes, colour, 1, voxel_ids=ids, keep_fn=keep)
    )
    z_both, z_near = np.asarray(both.vertices)[:, 2], np.asarray(near.vertices)[:, 2]
    assert (np.abs(z_both - 0.072) < 1e-3).sum() > 100  # the unobserved plane is there without the filter
    np.testing.assert_allclose(z_near, 0.022, atol=1e-3)  # only the observed plane is left
    assert abs(near.area - both.area / 2) < 0.01 * both.area
    assert len(np.unique(near.faces)) == len(near.vertices)  # no vertex left without a face


def test_dilating_only_the_asked_voxels_gives_the_whole_map_dilation() -> None:
    rng = np.random.default_rng(9)
    octree, points = _octree(rng)
    observed = ObservedCells(VS)
    observed.add(octree, points.repeat(20, axis=0) + rng.normal(0.0, 0.03, size=(2400, 3)))
    ids = rng.integers(0, octree.n_voxels, size=300)  # with repeats, in any order
    whole = observed.snapshot(octree).dilated()
    assert whole.any() and (whole != observed.words).any()
    np.testing.assert_array_equal(observed.snapshot(octree).dilated_rows(ids), whole[ids])
    assert observed.snapshot(octree).dilated_rows(np.zeros(0, np.int64)).shape == (0, 8)


def test_cells_far_from_the_origin_are_marked_as_near_it() -> None:
    """20 km out (UTM-like poses): cell coordinates pass 2^20, where a packed key of them would wrap."""
    rng = np.random.default_rng(7)
    for origin in (np.zeros(3), np.array([20_000.0, -15_000.0, 3.0])):
        octree = VoxelOctree(VS, min_points=0, expansion=False)
        points = origin + rng.uniform(0.0, 0.3, size=(500, 3))
        octree.allocate(points)
        observed = ObservedCells(VS)
        observed.add(octree, points)
        support = observed.snapshot(octree)
        assert support.contains(points).all()
        assert not support.contains(points + np.array([0.0, 0.0, 0.35])).any()  # above every allocated voxel


@pytest.mark.parametrize("with_strict", [False, True])
@needs_numba
def test_compiled_test_matches_the_dilation_reference(with_strict: bool) -> None:
    """The compiled point test (27-cell search with a voxel-neighbour cache) against `dilated_rows`, points in any
    order, inside and outside allocated voxels, with gaps where bits may only travel the reference's path."""
    rng = np.random.default_rng(11 + with_strict)
    for origin in (np.zeros(3), np.array([-20_000.0, 15_000.0, -3.0])):
        octree, points = _octree(rng)
        points = points + origin
        octree = VoxelOctree(VS, min_points=0, expansion=False)
        octree.allocate(points)
        observed = ObservedCells(VS, FAST)
        observed.add(octree, points.repeat(25, axis=0) + rng.normal(0.0, 0.03, size=(3000, 3)))
        strict = rng.random(octree.n_voxels) < 0.3 if with_strict else None
        support = observed.snapshot(octree, strict)
        near = points.repeat(40, axis=0) + rng.normal(0.0, 0.02, size=(4800, 3))
        queries = np.concatenate([near, origin + rng.uniform(-0.5, 0.5, size=(20000, 3))])
        got = support.contains(queries)
        want = support.contains_reference(np.floor(queries / CELL).astype(np.int64))
        assert 0.05 < want.mean() < 0.5  # both answers well represented
        np.testing.assert_array_equal(got, want)
    assert support.contains(np.zeros((0, 3))).shape == (0,)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@needs_numba
def test_compiled_marking_sets_the_same_bits_as_numpy(dtype: type) -> None:
    """The compiled `add` (one loop, voxels from the hash table) against NumPy's: points in and out of allocated
    voxels, on both sides of the origin and 20 km out, float32 (a frame's points) and float64."""
    rng = np.random.default_rng(5)
    for origin in (np.zeros(3), np.array([20_000.0, -15_000.0, 3.0])):
        octree, points = _octree(rng)
        octree = VoxelOctree(VS, min_points=0, expansion=False)
        octree.allocate(points + origin)
        marks = (origin + np.concatenate([points.repeat(50, axis=0), rng.uniform(-0.6, 0.6, (4000, 3))])).astype(dtype)
        fast, numpy = ObservedCells(VS, FAST), ObservedCells(VS)
        fast.add(octree, marks)
        numpy.add(octree, marks)
        assert fast.words.any() and np.count_nonzero(fast.words) > 100
        np.testing.assert_array_equal(fast.words, numpy.words)
