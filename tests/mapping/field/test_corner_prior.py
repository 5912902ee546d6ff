"""SDF priors by projection: exact on a plane, the sqrt(6) voxel rule, write-once corners and retries."""

from __future__ import annotations

import numpy as np

from h2viz.geometry import backproject, look_at
from h2viz.mapping.field.corner_prior import PriorInitializer
from h2viz.mapping.field.octree import VoxelOctree

K = np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]])


def plane_depth(T_world_camera: np.ndarray, z_plane: float = 0.0, h: int = 120, w: int = 160) -> np.ndarray:
    """Depth image of the horizontal plane z = z_plane."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d_w = d_cam @ T_world_camera[:3, :3].T
    t = (z_plane - T_world_camera[2, 3]) / d_w[..., 2]
    return np.where(t > 0, t, 0).astype(np.float32)


def test_priors_of_a_fronto_parallel_plane_are_exact() -> None:
    T = look_at(np.array([0.03, 0.02, 1.0]), np.array([0.03, 0.02, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    depth = plane_depth(T)
    tree = VoxelOctree(0.1, min_points=10, expansion=True)
    alloc = tree.allocate(backproject(depth, K, T))
    init = PriorInitializer(0.05)
    init.grow(tree.n_corners, alloc.new_voxels)
    cids, vals = init.initialize(tree, depth, K, T)
    assert cids.size > 50
    corners = tree.corner_coords()[cids] * 0.1
    # camera looks straight down: D(u) - z = height of the corner above the plane
    np.testing.assert_allclose(vals * 0.05, corners[:, 2], atol=1e-4)
    # write once: the same frame again writes nothing
    again, _ = init.initialize(tree, depth, K, T)
    assert again.size == 0


def test_voxels_outside_the_view_wait_and_are_retried() -> None:
    T = look_at(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    depth = plane_depth(T)
    tree = VoxelOctree(0.1, min_points=10, expansion=False)
    alloc = tree.allocate(backproject(depth, K, T))
    init = PriorInitializer(0.05)
    init.grow(tree.n_corners, alloc.new_voxels)
    T_away = look_at(np.array([5.0, 0.0, 1.0]), np.array([5.0, 0.0, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    cids, _ = init.initialize(tree, plane_depth(T_away), K, T_away)
    assert cids.size == 0 and init.pending.size == tree.n_voxels
    cids, _ = init.initialize(tree, depth, K, T)
    assert cids.size > 0 and init.pending.size < tree.n_voxels


def test_sqrt6_rule_rejects_occluded_corners() -> None:
    T = look_at(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    deep = np.array([[0.02, 0.02, -0.45], [0.03, 0.03, -0.42]])  # voxel 0.4-0.5 m below the plane
    alloc = tree.allocate(deep)
    init = PriorInitializer(0.05)
    init.grow(tree.n_corners, alloc.new_voxels)
    cids, _ = init.initialize(tree, plane_depth(T), K, T)
    assert cids.size == 0  # |D - z| = 0.4 m > sqrt(6) * 0.1 m


def test_disabled_priors_write_nothing() -> None:
    T = look_at(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    depth = plane_depth(T)
    tree = VoxelOctree(0.1)
    alloc = tree.allocate(backproject(depth, K, T))
    init = PriorInitializer(0.05, enabled=False)
    init.grow(tree.n_corners, alloc.new_voxels)
    assert init.initialize(tree, depth, K, T)[0].size == 0


def test_a_voxel_at_the_edge_of_one_view_is_completed_by_the_next() -> None:
    T_left = look_at(np.array([-0.4, 0.0, 1.0]), np.array([-0.4, 0.0, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    T_right = look_at(np.array([0.4, 0.0, 1.0]), np.array([0.4, 0.0, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    alloc = tree.allocate(np.array([[0.25, 0.05, 0.02]]))  # voxel x in [0.2, 0.3]: the left view sees x < 0.4
    init = PriorInitializer(0.05)
    init.grow(tree.n_corners, alloc.new_voxels)
    depth_left = plane_depth(T_left)
    depth_left[:, 150:] = 0.0  # the left view's depth ends at x ~ 0.25: only the voxel's x = 0.2 corners
    cids, vals = init.initialize(tree, depth_left, K, T_left)
    assert cids.size == 4 and init.pending.size == 1  # four corners written, the voxel still waits
    np.testing.assert_allclose(vals * 0.05, tree.corner_coords()[cids][:, 2] * 0.1, atol=1e-4)
    cids2, _ = init.initialize(tree, plane_depth(T_right), K, T_right)
    assert cids2.size == 4 and not set(cids2) & set(cids)  # the other four, never rewritten
    assert init.pending.size == 0 and init.initialised(1).all()


def test_corners_seen_through_a_silhouette_count_as_free_space() -> None:
    T = look_at(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    alloc = tree.allocate(np.array([[0.05, 0.05, 0.55]]))  # a voxel 0.5-0.6 m above the floor
    init = PriorInitializer(0.05)
    init.grow(tree.n_corners, alloc.new_voxels)
    depth = plane_depth(T)  # the camera sees the floor through the voxel: every corner is >= 0.4 m in front
    cids, _ = init.initialize(tree, depth, K, T)
    assert cids.size == 0 and init.pending.size == 1  # nothing written, the voxel still waits for values
    assert init.free[tree.voxel_corners[0]].all() and init.initialised(1).all()  # but it counts as known
    depth_near = plane_depth(T, z_plane=0.5)  # a later view sees a surface right below the voxel
    cids, vals = init.initialize(tree, depth_near, K, T)
    assert cids.size == 8 and init.pending.size == 0
    np.testing.assert_allclose(vals * 0.05, tree.corner_coords()[cids][:, 2] * 0.1 - 0.5, atol=1e-4)
