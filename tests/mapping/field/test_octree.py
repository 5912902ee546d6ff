"""Octree allocation: the > N points rule, expansion across faces, shared corners, lookup, coarse levels."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from h2viz.mapping.field.octree import CORNER_OFFSETS, KeyIndex, VoxelOctree, decode, encode, occupied_cells
from tests.mapping.backends import needs_numba


def cloud_in_voxel(
    coord: tuple[int, int, int], n: int, lo: float = 0.3, hi: float = 0.7, vs: float = 0.1
) -> np.ndarray:
    rng = np.random.default_rng(0)
    return (np.array(coord) + rng.uniform(lo, hi, size=(n, 3))) * vs


def test_encode_decode_round_trip_negative_and_large() -> None:
    c = np.array([[0, 0, 0], [-5, 7, -1_000_000], [999_999, -999_999, 3]])
    assert np.array_equal(decode(encode(c)), c)
    assert np.array_equal(encode(torch.from_numpy(c)).numpy(), encode(c))


def test_key_index_ids_are_stable_and_lookup_misses() -> None:
    idx = KeyIndex()
    a = idx.add(np.array([30, 10, 20]))
    b = idx.add(np.array([20, 40, 10]))
    assert sorted(a.tolist()) == [0, 1, 2]
    assert b[0] == a[2] and b[2] == a[1] and b[1] == 3
    assert idx.lookup(np.array([40, 99])).tolist() == [3, -1]
    assert idx.lookup_torch(torch.tensor([10, 5])).tolist() == [a[1], -1]
    again = KeyIndex.from_keys(idx.keys)
    assert np.array_equal(again.lookup(idx.keys), np.arange(4))


def test_more_than_min_points_rule() -> None:
    tree = VoxelOctree(0.1, min_points=10, expansion=False)
    pts = np.concatenate([cloud_in_voxel((0, 0, 0), 10), cloud_in_voxel((2, 0, 0), 11)])
    alloc = tree.allocate(pts)
    assert tree.n_voxels == 1
    assert decode(tree.voxels.keys).tolist() == [[2, 0, 0]]
    assert alloc.new_voxels.tolist() == [0]


def test_expansion_allocates_the_neighbour_across_the_hugged_face() -> None:
    tree = VoxelOctree(0.1, min_points=10, expansion=True)
    pts = cloud_in_voxel((0, 0, 0), 50, lo=0.3, hi=0.7)
    pts[:, 2] = 0.095  # all points hug the +z face (mean at 95 % of the voxel)
    tree.allocate(pts)
    assert sorted(map(tuple, tree.voxel_coords().tolist())) == [(0, 0, 0), (0, 0, 1)]
    pts[:, 2] = 0.005
    tree2 = VoxelOctree(0.1, expansion=True)
    tree2.allocate(pts)
    assert sorted(map(tuple, tree2.voxel_coords().tolist())) == [(0, 0, -1), (0, 0, 0)]
    tree3 = VoxelOctree(0.1, expansion=False)
    tree3.allocate(pts)
    assert tree3.n_voxels == 1


def test_corners_are_shared_between_neighbours() -> None:
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    tree.allocate(np.concatenate([cloud_in_voxel((0, 0, 0), 5), cloud_in_voxel((1, 0, 0), 5)]))
    assert tree.n_voxels == 2 and tree.n_corners == 12
    coords = tree.voxel_coords()
    cc = tree.corner_coords()
    for v in range(2):
        assert np.array_equal(cc[tree.voxel_corners[v]], coords[v] + CORNER_OFFSETS)


def test_allocation_is_incremental_and_observed_lists_seen_voxels() -> None:
    tree = VoxelOctree(0.1, min_points=10, expansion=False)
    tree.allocate(cloud_in_voxel((0, 0, 0), 20))
    alloc = tree.allocate(np.concatenate([cloud_in_voxel((0, 0, 0), 20), cloud_in_voxel((-3, 1, 0), 20)]))
    assert tree.n_voxels == 2
    assert alloc.new_voxels.tolist() == [1]
    assert sorted(alloc.observed.tolist()) == [0, 1]


def test_voxel_coords_follow_appended_and_replaced_voxels() -> None:
    """Coordinates are decoded once per voxel (the ones appended since the last call) and stay those of the keys:
    after growth, after nothing changed (the same array), and after the voxels were replaced (a loaded map)."""
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    tree.allocate(cloud_in_voxel((0, 0, 0), 3))
    first = tree.voxel_coords()
    assert first.tolist() == [[0, 0, 0]] and tree.voxel_coords() is first and not first.flags.writeable
    tree.allocate(np.concatenate([cloud_in_voxel(c, 3) for c in [(2, -1, 0), (0, 0, 0), (-4, 3, 7)]]))
    assert np.array_equal(tree.voxel_coords(), decode(tree.voxels.keys)) and len(tree.voxel_coords()) == 3
    other = VoxelOctree(0.1, min_points=0, expansion=False)
    other.allocate(np.concatenate([cloud_in_voxel(c, 3) for c in [(9, 9, 9), (8, 0, 0), (1, 1, 1), (5, 5, 5)]]))
    tree.load_state_dict(other.state_dict())
    assert tree.voxel_coords().tolist() == other.voxel_coords().tolist()


def test_lookup_points_and_levels() -> None:
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    tree.allocate(np.concatenate([cloud_in_voxel(c, 3) for c in [(0, 0, 0), (1, 1, 1), (-1, 0, 0), (5, 0, 0)]]))
    ids = tree.lookup_points(torch.tensor([[0.05, 0.05, 0.05], [-0.05, 0.05, 0.05], [0.25, 0.0, 0.0]]))
    coords = tree.voxel_coords()
    assert coords[ids[0]].tolist() == [0, 0, 0] and coords[ids[1]].tolist() == [-1, 0, 0] and ids[2] == -1
    lvl1 = {tuple(c) for c in tree.level_coords(1).tolist()}
    assert lvl1 == {(0, 0, 0), (-1, 0, 0), (2, 0, 0)}
    assert {tuple(c) for c in tree.level_coords(3).tolist()} == {(0, 0, 0), (-1, 0, 0)}


@pytest.mark.parametrize("far_point", [False, True])  # dense local grid / sorting fallback for a huge box
def test_occupied_cells_match_numpy_unique(far_point: bool) -> None:
    rng = np.random.default_rng(3)
    coords = (rng.normal(size=(5000, 3)) * 6).astype(np.int64) - 40
    if far_point:
        coords = np.concatenate([coords, [[-(1 << 19), 7, 1 << 19]]])
    cells = occupied_cells(coords)
    keys, inverse, counts = np.unique(encode(coords), return_inverse=True, return_counts=True)
    np.testing.assert_array_equal(encode(cells.coords), keys)
    np.testing.assert_array_equal(cells.inverse, inverse)
    np.testing.assert_array_equal(cells.counts, counts)
    np.testing.assert_array_equal(cells.coords[cells.inverse], coords)


def test_occupied_cells_of_nothing() -> None:
    cells = occupied_cells(np.zeros((0, 3), np.int64))
    assert cells.coords.shape == (0, 3) and cells.inverse.size == 0 and cells.counts.size == 0


@needs_numba
def test_the_allocation_kernel_matches_the_numpy_reference() -> None:
    from h2viz.mapping.kernels import octree_numba

    rng = np.random.default_rng(3)
    points = rng.uniform(-1.0, 2.0, (20000, 3)).astype(np.float32)
    points[:5000, 0] = np.round(points[:5000, 0], 1)  # on voxel faces, where rounding picks the side
    tree = VoxelOctree(0.1, min_points=3, cell_stats=octree_numba.cell_stats)
    fused_keys, fused_hit = tree.candidate_voxels(points)
    numpy_keys, numpy_hit = VoxelOctree(0.1, min_points=3).candidate_voxels(points)
    np.testing.assert_array_equal(fused_keys, numpy_keys)
    np.testing.assert_array_equal(np.sort(fused_hit), np.sort(numpy_hit))
    coords, counts, means = octree_numba.cell_stats(points, 0.1, 1 << 22)
    cells = occupied_cells(np.floor(points / np.float32(0.1)).astype(np.int64))
    np.testing.assert_array_equal(coords, cells.coords)
    np.testing.assert_array_equal(counts, cells.counts)
    scaled = points / np.float32(0.1)
    sums = np.stack([np.bincount(cells.inverse, scaled[:, a]) for a in range(3)], 1)
    np.testing.assert_allclose(means, sums / cells.counts[:, None] - cells.coords, atol=1e-9)
    assert (means >= -1e-6).all() and (means <= 1 + 1e-6).all()
    empty = octree_numba.cell_stats(np.array([[0, 0, 0], [1e5, 1e5, 1e5]], np.float32), 0.1, 1 << 22)
    assert empty[1].size == 0  # a box too large for the dense grid: the caller sorts instead
    assert fused_keys.size and fused_hit.size == len(cells.coords)


def test_face_neighbours_in_the_order_of_face_steps() -> None:
    octree = VoxelOctree(0.1, min_points=0, expansion=False)
    cells = np.array([[0, 0, 0], [1, 0, 0], [0, -1, 0], [0, 0, 1], [1, 1, 1]])  # (5,3); the last touches no face
    points = (cells + 0.5) * 0.1  # one point at each voxel's centre
    octree.allocate(np.repeat(points, 2, axis=0))
    ids = octree.voxels.lookup(encode(cells))
    got = octree.face_neighbours(ids[:1])  # the voxel at the origin
    assert got.tolist() == [[-1, ids[1], ids[2], -1, -1, ids[3]]]
    assert (octree.face_neighbours(ids[4:]) == -1).all()
