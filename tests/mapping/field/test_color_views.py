"""View-dependent colour on analytic scenes: a textured plane seen by translated cameras comes back at its true
colour from a camera between them, an occluder hides a view, what no view sees keeps the field's colour, a render
coarser than the views samples their half-resolution copy, the budget retires the most redundant view, and
stored views survive a checkpoint record."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from h2viz.mapping.field.color_views import ColorViews, StoredView
from h2viz.types import RgbdFrame

W, H = 160, 120
K = np.array([[120.0, 0.0, W / 2], [0.0, 120.0, H / 2], [0.0, 0.0, 1.0]])
PLANE_Z = 2.0


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Colour (N,3) in [0,1] of the plane z = PLANE_Z at world x, y (N,): stripes 30 cm apart."""
    return np.stack([0.5 + 0.4 * np.sin(2 * np.pi * x / 0.3), 0.5 + 0.4 * np.cos(2 * np.pi * y / 0.3), 0.3 + 0 * x], 1)


def pose(x: float, y: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:2, 3] = (x, y)
    return T


def plane_frame(index: int, T: np.ndarray, tex: Callable[[np.ndarray, np.ndarray], np.ndarray] = texture) -> RgbdFrame:
    """What a camera at T (looking along +z) sees of the textured plane: colour and depth at pixel centres."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    depth = PLANE_Z - T[2, 3]
    x = (u - K[0, 2]) / K[0, 0] * depth + T[0, 3]
    y = (v - K[1, 2]) / K[1, 1] * depth + T[1, 3]
    rgb = tex(x.ravel(), y.ravel()).reshape(H, W, 3)
    rgb8 = np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)
    return RgbdFrame(index, 0.0, rgb8, np.full((H, W), depth, np.float32), K, T)


def plane_points(n: int = 400, half: float = 0.3, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-half, half, (n, 2)), np.full(n, PLANE_Z)]


def test_a_camera_between_two_views_gets_the_planes_true_colour() -> None:
    views = ColorViews(n_blend=2, budget_mb=0, field_weight=0.0)
    views.add(plane_frame(0, pose(-0.1)))
    views.add(plane_frame(1, pose(0.1)))
    pts = plane_points()
    field = np.zeros((len(pts), 3), np.float32)  # black: any of it left would show
    got = views.blend(pts, field, pose(0.0), K)
    truth = texture(pts[:, 0], pts[:, 1])
    assert np.abs(got - truth).max() < 0.02  # bilinear sampling of smooth stripes, 8-bit colour
    mixed = ColorViews(n_blend=2, budget_mb=0, field_weight=0.5)
    mixed.views = views.views
    assert np.allclose(mixed.blend(pts, field, pose(0.0), K), 0.5 * got, atol=1e-5)


def test_an_occluded_view_does_not_colour_the_point() -> None:
    views = ColorViews(n_blend=2, budget_mb=0, field_weight=0.0)
    blocked = plane_frame(0, pose(-0.1))
    depth, rgb = blocked.depth_m.copy(), blocked.rgb.copy()
    depth[:, : W // 2 + 20] = 1.0  # a red wall 1 m in front of this view covers the middle of the plane
    rgb[:, : W // 2 + 20] = (255, 0, 0)
    views.add(RgbdFrame(0, 0.0, rgb, depth, K, blocked.T_world_camera))
    views.add(plane_frame(1, pose(0.1)))
    pts = np.array([[-0.1, 0.0, PLANE_Z], [-0.05, 0.02, PLANE_Z]])
    got = views.blend(pts, np.zeros((2, 3), np.float32), pose(0.0), K)
    assert np.abs(got - texture(pts[:, 0], pts[:, 1])).max() < 0.02  # only the unblocked view's colour


def test_what_no_view_sees_keeps_the_fields_colour() -> None:
    views = ColorViews(n_blend=4, budget_mb=0, field_weight=0.0)
    views.add(plane_frame(0, pose(0.0)))
    pts = np.array([[5.0, 0.0, PLANE_Z], [0.0, 0.0, 1.5], [0.0, 0.0, PLANE_Z]])  # outside, in front, on the plane
    field = np.full((3, 3), 0.25, np.float32)
    got = views.blend(pts, field, pose(0.0), K)
    assert np.allclose(got[:2], 0.25) and not np.allclose(got[2], 0.25)
    assert ColorViews(n_blend=4, budget_mb=0, field_weight=0.0).blend(pts, field, pose(0.0), K) is field


def test_a_coarser_render_samples_the_half_resolution_copy() -> None:
    def stripes(x: np.ndarray, y: np.ndarray) -> np.ndarray:  # one-pixel stripes in the view: black, white, ...
        column = np.floor((x + 10.0) / (PLANE_Z / K[0, 0]) + 1e-6).astype(int)
        return np.repeat((column % 2).astype(float)[:, None], 3, axis=1)

    views = ColorViews(n_blend=1, budget_mb=0, field_weight=0.0)
    views.add(plane_frame(0, pose(0.0), stripes))
    pts = plane_points(200, 0.2)
    field = np.zeros((len(pts), 3), np.float32)
    coarse = views.blend(pts, field, pose(0.0), K / np.array([[2.0], [2.0], [1.0]]))  # half the render resolution
    assert np.abs(coarse - 0.5).max() < 0.03  # the 2x2 area mean, not whichever stripe a point falls on
    fine = views.blend(pts, field, pose(0.0), K)
    assert np.abs(fine - 0.5).mean() > 0.1  # at the view's own resolution the stripes stay


def test_the_budget_retires_the_most_redundant_view() -> None:
    frames = [plane_frame(i, pose(x)) for i, x in enumerate((0.0, 1.0, 1.05, 2.0))]
    size = StoredView.of(0, frames[0].T_world_camera, K, frames[0].rgb, frames[0].depth_m).nbytes
    views = ColorViews(n_blend=2, budget_mb=3.5 * size / 2**20, field_weight=0.0)
    for frame in frames:
        views.add(frame)
    assert [v.index for v in views.views] == [0, 2, 3]  # 1 and 2 were 5 cm apart: the older one went
    assert views.nbytes <= views.budget_bytes
    views.add(plane_frame(9, pose(2.002)))  # within MIN_SPACING of view 3: nothing to add
    assert [v.index for v in views.views] == [0, 2, 3]
    assert [v.index for v in views.nearest(pose(1.9))] == [3, 2]


def test_a_stored_view_survives_its_checkpoint_record() -> None:
    frame = plane_frame(7, pose(0.3, -0.2))
    view = StoredView.of(7, frame.T_world_camera, K, frame.rgb, frame.depth_m)
    back = StoredView.from_record(view.record())
    assert back.index == 7 and np.array_equal(back.T_world_camera, view.T_world_camera)
    assert np.abs(back.rgb.astype(int) - view.rgb).mean() < 1.5  # JPEG at quality 95
    assert np.allclose(back.depth_half, view.depth_half, atol=2e-3)
    with pytest.raises(ValueError, match="does not decode"):
        StoredView.from_record({**view.record(), "jpeg": np.zeros(10, np.uint8)})


def test_bad_settings_name_the_keys() -> None:
    with pytest.raises(ValueError, match="mapping.rendering.color_views_field"):
        ColorViews(n_blend=4, budget_mb=10, field_weight=2.0)
