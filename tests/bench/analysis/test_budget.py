"""Quality budget: region masks, pooled region errors, half-pixel sensitivity and the Acc floor on analytic cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from bench.analysis.budget import REGIONS, RegionErrors, acc_budget, closest_on_mesh, half_pixel_psnr, region_masks
from h2viz.eval.metrics import EvalError, mesh_metrics


def _scene() -> tuple[np.ndarray, np.ndarray]:
    """A 60x80 view: a wall at 1 m on the left, 2 m on the right (depth jump at column 40), uniform grey with a
    dark vertical stripe (columns 15-19) painted on the left wall."""
    depth = np.ones((60, 80), np.float32)
    depth[:, 40:] = 2.0
    rgb = np.full((60, 80, 3), 0.6, np.float32)
    rgb[:, 15:20] = 0.1
    return rgb, depth


def test_regions_are_disjoint_and_find_depth_jumps_and_texture_edges() -> None:
    rgb, depth = _scene()
    masks = region_masks(rgb, depth)
    assert list(masks) == list(REGIONS)
    stacked = np.stack(list(masks.values()))  # (3,H,W)
    assert np.all(stacked.sum(axis=0) == 1)  # every pixel in exactly one region
    geometry, texture, flat = masks["geometry edges"], masks["texture edges"], masks["flat"]
    assert np.all(geometry[:, 38:42]) and not geometry[:, :36].any() and not geometry[:, 44:].any()
    assert np.all(texture[:, 14]) and np.all(texture[:, 20]) and not texture[:, 25:36].any()
    assert np.all(flat[:, 25:36]) and np.all(flat[:, 50:])


def test_region_errors_pool_each_region_and_what_a_perfect_region_would_give() -> None:
    rgb, depth = _scene()
    texture = region_masks(rgb, depth)["texture edges"]
    pred = rgb.copy()
    pred[texture] += 0.1  # error 0.01 (MSE) on texture edges only
    errors = RegionErrors.empty()
    valid = np.ones(depth.shape, bool)
    errors.add(pred, rgb, depth, valid)
    errors.add(rgb, rgb, depth, valid)  # a perfect second view halves the pooled error
    rows = {r.region: r for r in errors.table()}
    assert rows["texture edges"].error_pct == pytest.approx(100.0)
    assert rows["texture edges"].psnr_db == pytest.approx(-10.0 * np.log10(0.01 / 2.0), abs=1e-4)  # 23.01 dB
    assert rows["texture edges"].psnr_without_db == math.inf and rows["flat"].psnr_db == math.inf
    share = texture.mean()  # of the pixels of each view
    assert rows["texture edges"].pixels_pct == pytest.approx(100.0 * share)
    assert rows["all"].psnr_db == pytest.approx(-10.0 * np.log10(0.01 * share / 2.0), abs=1e-4)
    with pytest.raises(EvalError, match="do not match"):
        errors.add(pred[:10], rgb, depth, valid)


def test_half_pixel_psnr_of_a_ramp_and_a_flat_image() -> None:
    ramp = np.broadcast_to((np.arange(64, dtype=np.float32) * 0.01)[None, :, None], (32, 64, 3)).copy()
    inside = np.zeros((32, 64), bool)
    inside[:, 1:-1] = True  # the outer columns meet the border
    assert half_pixel_psnr(ramp, inside) == pytest.approx(-10.0 * np.log10(0.005**2), abs=0.01)  # 0.5 px x 0.01
    assert half_pixel_psnr(np.full((8, 8, 3), 0.3, np.float32)) == math.inf


def _plane(offset_m: float = 0.0) -> trimesh.Trimesh:
    """A 1 m x 1 m square in z = offset, split into many triangles."""
    grid = trimesh.creation.box(extents=(1.0, 1.0, 1e-6))
    grid = grid.subdivide().subdivide().subdivide()
    top = grid.vertices[:, 2] > 0
    faces = grid.faces[np.all(top[grid.faces], axis=1)]
    mesh = trimesh.Trimesh(grid.vertices, faces, process=True)
    mesh.vertices[:, 2] = offset_m
    return mesh


def test_closest_points_on_a_plane_drop_straight_down() -> None:
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-0.4, 0.4, (500, 2)), rng.uniform(-0.1, 0.1, 500)])
    closest = closest_on_mesh(_plane(), points, 50_000)
    np.testing.assert_allclose(closest[:, 2], 0.0, atol=1e-9)  # always on the surface
    off = np.linalg.norm(closest[:, :2] - points[:, :2], axis=1)  # (N,) distance from the true foot point
    assert np.mean(off < 1e-9) > 0.99 and off.max() < 5e-4  # exact but next to a few triangle edges


def test_acc_of_a_perfect_mesh_is_its_floor_and_an_offset_adds_to_the_first_bin() -> None:
    gt = _plane()
    same = acc_budget(gt.copy(), gt, n_points=20_000, dense_factor=10)
    assert same.mean_error_cm < 1e-3 and same.floor_cm == pytest.approx(same.acc_cm, abs=1e-3)
    reference = mesh_metrics(gt.copy(), gt, 20_000)["acc_cm"]  # the same samples as mesh_metrics draws
    assert same.acc_cm == pytest.approx(reference, abs=1e-9)

    moved = acc_budget(_plane(0.004), gt, n_points=20_000, dense_factor=10)
    assert moved.mean_error_cm == pytest.approx(0.4, abs=1e-3)  # every sample 4 mm above the plane
    assert moved.floor_cm == pytest.approx(same.floor_cm, rel=0.02)  # samples at the same (x, y)
    bins = moved.bins
    assert bins[0].points_pct == pytest.approx(100.0) and sum(b.points_pct for b in bins) == pytest.approx(100.0)
    excess = sum(b.excess_cm for b in bins)
    assert excess == pytest.approx(moved.acc_cm - moved.floor_cm, abs=1e-9) and excess > 0.0
