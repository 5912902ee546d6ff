"""Camera sets: evenly spread training views, and novel views away from the trajectory that look at
mapped, unoccluded content."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import trimesh

from h2viz.eval.metrics import EvalError, sample_surface
from h2viz.eval.views import estimate_up, extrapolate_views, interpolate_views
from h2viz.geometry import backproject, look_at
from h2viz.types import check_pose
from tests.eval.scenes import load_7scenes

Z_UP = np.array([0.0, 0.0, 1.0])


def _ring(n: int, radius: float, height: float, centre: np.ndarray) -> np.ndarray:
    """Poses (n,4,4) on a horizontal circle, all looking at `centre`."""
    angles = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    eyes = np.stack([radius * np.cos(angles), radius * np.sin(angles), np.full(n, height)], axis=1)
    return np.stack([look_at(e, centre, Z_UP) for e in eyes])


def _gaps(views: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Distance (n,) of every view to its nearest trajectory camera."""
    return np.linalg.norm(views[:, None, :3, 3] - poses[None, :, :3, 3], axis=2).min(axis=1)


def _first_hits(mesh: trimesh.Trimesh, views: np.ndarray) -> np.ndarray:
    """Distance (n,) along each view's optical axis to the first surface (inf when it sees nothing)."""
    locations, rays, _ = mesh.ray.intersects_location(views[:, :3, 3], views[:, :3, 2], multiple_hits=False)
    out = np.full(len(views), np.inf)
    out[rays] = np.linalg.norm(locations - views[rays, :3, 3], axis=1)
    return out


def test_interpolate_views_are_evenly_spread() -> None:
    poses = np.repeat(np.eye(4)[None], 100, axis=0)
    idx = interpolate_views(poses, 10)
    assert len(idx) == 10 and idx[0] == 0 and idx[-1] == 99
    assert set(np.diff(idx)) <= {11, 12}
    assert interpolate_views(poses[:5], 10) == [0, 1, 2, 3, 4]
    assert interpolate_views(poses, 0) == [] and interpolate_views(poses[:0], 3) == []
    assert interpolate_views(poses, 1) == [0]


def test_estimate_up_follows_the_cameras() -> None:
    np.testing.assert_allclose(estimate_up(_ring(12, 2.0, 1.0, np.array([0.0, 0.0, 1.0]))), Z_UP, atol=1e-9)
    y_down = np.array([0.0, -1.0, 0.0])  # 7-Scenes-like worlds have -y up
    ring = np.stack([look_at(np.array([np.cos(a), 0.0, np.sin(a)]), np.zeros(3), y_down) for a in range(8)])
    np.testing.assert_allclose(estimate_up(ring), y_down, atol=1e-9)


def test_extrapolated_views_of_an_object_are_far_from_the_trajectory_and_see_it() -> None:
    obj = trimesh.creation.box(extents=(1.0, 1.0, 0.5))
    obj.apply_translation([0.0, 0.0, 0.25])
    poses = _ring(24, 2.0, 0.8, np.array([0.0, 0.0, 0.25]))
    views = extrapolate_views(poses, 12, sample_surface(obj, 20_000), seed=0)
    assert views.shape == (12, 4, 4)
    for T in views:
        check_pose(T, "extrapolated view")
        assert abs(T[:3, 0] @ Z_UP) < 1e-9 and T[:3, 1] @ Z_UP < 0  # upright: x level, image-down is down
    assert np.all(_gaps(views, poses) >= 0.4)
    hits = _first_hits(obj, views)
    assert np.all(np.isfinite(hits)) and np.all(hits >= 0.3)  # the optical axis meets the object
    np.testing.assert_array_equal(views, extrapolate_views(poses, 12, sample_surface(obj, 20_000), seed=0))
    assert not np.allclose(views, extrapolate_views(poses, 12, sample_surface(obj, 20_000), seed=1))


def test_extrapolated_views_in_a_room_stay_inside_and_are_not_occluded() -> None:
    room = trimesh.creation.box(extents=(6.0, 5.0, 3.0))
    room.apply_translation([3.0, 2.5, 1.5])
    pillar = trimesh.creation.cylinder(radius=0.4, height=3.0)
    pillar.apply_translation([3.0, 2.6, 1.5])
    scene = trimesh.util.concatenate([room, pillar])
    # cameras walk along y = 1 looking across the pillar at the far wall
    xs = np.linspace(1.0, 5.0, 20)
    poses = np.stack([look_at(np.array([x, 1.0, 1.5]), np.array([x, 5.0, 1.4]), Z_UP) for x in xs])
    points = sample_surface(scene, 60_000)
    views = extrapolate_views(poses, 10, points, seed=2, margin_m=0.2)
    assert np.all(_gaps(views, poses) >= 0.4)
    eyes = views[:, :3, 3]
    assert np.all(eyes >= [0.2, 0.2, 0.2]) and np.all(eyes <= [5.8, 4.8, 2.8])
    hits = _first_hits(scene, views)
    for T, hit in zip(views, hits, strict=True):
        # the target is the scene point exactly on the optical axis; nothing may block the way to it
        rel = points - T[:3, 3]
        along = rel @ T[:3, 2]
        on_axis = (np.linalg.norm(rel - along[:, None] * T[:3, 2], axis=1) < 1e-6) & (along > 0)
        assert on_axis.any()
        assert hit >= along[on_axis].min() - 0.2


def test_extrapolated_views_from_bounds_only() -> None:
    poses = _ring(16, 1.5, 1.2, np.array([0.0, 0.0, 1.0]))
    bounds = np.array([[-3.0, -3.0, 0.0], [3.0, 3.0, 3.0]])
    views = extrapolate_views(poses, 6, bounds, seed=0, margin_m=0.3)
    assert views.shape == (6, 4, 4) and np.all(_gaps(views, poses) >= 0.4)
    assert np.all(np.abs(views[:, :2, 3]) <= 2.7) and np.all(
        (views[:, 2, 3] >= 0.3) & (views[:, 2, 3] <= 2.7)
    )


def test_impossible_distance_falls_back_with_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    poses = _ring(8, 1.0, 1.0, np.zeros(3))
    with caplog.at_level(logging.WARNING, logger="h2viz.eval"):
        views = extrapolate_views(
            poses, 2, np.array([[-2.0, -2.0, -1.0], [2.0, 2.0, 2.0]]), min_distance_m=5.0
        )
    assert views.shape == (2, 4, 4) and np.all(np.isfinite(views))
    assert "furthest" in caplog.text


def test_extrapolate_rejects_a_bad_scene() -> None:
    with pytest.raises(EvalError, match="scene points"):
        extrapolate_views(_ring(4, 1.0, 1.0, np.zeros(3)), 2, np.zeros((5, 2)))


def test_extrapolated_views_on_real_fountain(shared_dataset: Callable[[str], Path]) -> None:
    root = shared_dataset("fountain_33")
    K, poses, depths = load_7scenes(root)
    Ks = K.copy()
    Ks[:2] /= 8  # intrinsics of depth[::8, ::8]
    observed = np.concatenate([backproject(d[::8, ::8], Ks, T) for T, d in zip(poses, depths, strict=True)])
    views = extrapolate_views(poses, 10, observed, seed=0)
    assert np.all(_gaps(views, poses) >= 0.4)
    reference = trimesh.load(root / "reference_mesh.ply", process=False)
    assert np.all(np.isfinite(_first_hits(reference, views)))  # every view looks at the fountain
