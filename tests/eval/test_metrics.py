"""Mesh metrics on analytic shapes, ground-truth culling, and image metrics on known images."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import trimesh

from h2viz.eval.metrics import (
    PSNR_MAX_DB,
    EvalError,
    depth_l1_cm,
    mesh_metrics,
    observed_mask_fn,
    point_metrics,
    psnr,
    sample_surface,
    ssim,
    voxel_mask_fn,
)
from h2viz.geometry import look_at
from tests.eval.scenes import grid_plane, load_7scenes

PLANE = grid_plane(-0.5, 0.5, -0.5, 0.5, 0.0)  # 1 x 1 m, 1 cm cells
# Point-to-point distances overestimate a 1 cm gap by about 1 / (2 pi density 1 cm): sample densely
# (>= 300k points / m^2 -> < 0.01 cm) on small shapes, which also keeps the neighbour searches cheap.
SMALL_PLANE = grid_plane(-0.15, 0.15, -0.15, 0.15, 0.0, cells=30)  # 30 x 30 cm, 1 cm cells


# ----------------------------------------------------------------------------------- sampling


def test_sample_surface_exact_count_on_surface_and_uniform_by_area() -> None:
    # two separated triangles with areas 1 and 3: a uniform-by-area sampler puts 25 % on the first
    small = [[0, 0, 0], [2, 0, 0], [0, 1, 0]]
    big = [[0, 0, 1], [3, 0, 1], [0, 2, 1]]
    mesh = trimesh.Trimesh(np.array(small + big, dtype=float), [[0, 1, 2], [3, 4, 5]], process=False)
    pts = sample_surface(mesh, 40_000, seed=3)
    assert pts.shape == (40_000, 3)
    assert np.all(np.isclose(pts[:, 2], 0.0) | np.isclose(pts[:, 2], 1.0))
    assert np.mean(pts[:, 2] < 0.5) == pytest.approx(0.25, abs=0.01)
    np.testing.assert_array_equal(pts, sample_surface(mesh, 40_000, seed=3))
    assert not np.array_equal(pts, sample_surface(mesh, 40_000, seed=4))


def test_sample_surface_rejects_empty_mesh() -> None:
    with pytest.raises(EvalError, match="without faces"):
        sample_surface(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int)), 10)


# ------------------------------------------------------------------------------- mesh metrics


def test_plane_shifted_1cm_gives_1cm_acc_and_comp() -> None:
    shifted = SMALL_PLANE.copy()
    shifted.apply_translation([0.0, 0.0, 0.01])
    m = mesh_metrics(shifted, SMALL_PLANE, n_points=40_000)
    assert m["acc_cm"] == pytest.approx(1.0, abs=0.05)
    assert m["comp_cm"] == pytest.approx(1.0, abs=0.05)
    assert m["comp_ratio"] == 100.0 and m["precision"] == 100.0 and m["fscore"] == 100.0
    assert m["gt_kept_pct"] == 100.0 and m["n_gt_points"] == 40_000


def test_sphere_grown_1cm_gives_1cm_acc_and_comp() -> None:
    gt = trimesh.creation.icosphere(subdivisions=5, radius=0.1)  # ~3 mm edges
    rec = gt.copy()
    rec.apply_scale(0.11 / 0.1)  # every point moves 1 cm along its normal
    m = mesh_metrics(rec, gt, n_points=40_000, seed=5)
    assert m["acc_cm"] == pytest.approx(1.0, abs=0.05)
    assert m["comp_cm"] == pytest.approx(1.0, abs=0.05)
    assert m["comp_ratio"] == 100.0


def test_plane_shifted_10cm_completes_nothing_at_5cm() -> None:
    shifted = PLANE.copy()
    shifted.apply_translation([0.0, 0.0, 0.10])
    m = mesh_metrics(shifted, PLANE, n_points=20_000, threshold_m=0.05)
    assert m["comp_ratio"] == 0.0 and m["precision"] == 0.0 and m["fscore"] == 0.0
    assert m["acc_cm"] == pytest.approx(10.0, abs=0.1)
    assert m["comp_cm"] == pytest.approx(10.0, abs=0.1)
    # at a 15 cm threshold the same pair is complete
    assert mesh_metrics(shifted, PLANE, n_points=20_000, threshold_m=0.15)["comp_ratio"] == 100.0


def test_missing_half_gives_large_comp_and_half_ratio() -> None:
    half = grid_plane(-0.5, 0.0, -0.5, 0.5, 0.0, cells=50)
    m = mesh_metrics(half, PLANE, n_points=50_000)
    # gt points on the missing half x in (0, 0.5] are x away from the reconstruction: mean 25 cm,
    # so Comp = 12.5 cm over the whole plane; within 5 cm: the kept half plus x <= 5 cm -> 55 %
    assert m["comp_cm"] == pytest.approx(12.5, abs=0.3)
    assert m["acc_cm"] < 0.5  # in-plane sample spacing only
    assert m["comp_ratio"] == pytest.approx(55.0, abs=1.0)
    assert m["precision"] == 100.0
    assert m["fscore"] == pytest.approx(2 * 100 * m["recall"] / (100 + m["recall"]))


def test_culling_to_the_reconstructed_half_restores_completion() -> None:
    half = grid_plane(-0.5, 0.0, -0.5, 0.5, 0.0, cells=50)
    m = mesh_metrics(half, PLANE, n_points=50_000, gt_mask_fn=lambda p: p[:, 0] < 0.0)
    assert m["gt_kept_pct"] == pytest.approx(50.0, abs=1.0)
    assert m["n_gt_points"] == pytest.approx(25_000, rel=0.02)
    assert m["comp_cm"] < 0.5
    assert m["comp_ratio"] == 100.0


def test_culling_everything_is_an_error() -> None:
    with pytest.raises(EvalError, match="culling removed all ground truth"):
        mesh_metrics(PLANE, PLANE, n_points=1000, gt_mask_fn=lambda p: np.zeros(len(p), dtype=bool))


def test_point_metrics_counts_threshold_strictly() -> None:
    gt = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    rec = np.array([[0.0, 0.0, 0.04], [1.0, 0.0, 0.06]])
    m = point_metrics(rec, gt, threshold_m=0.05)
    assert m["acc_cm"] == pytest.approx(5.0) and m["comp_cm"] == pytest.approx(5.0)
    assert m["comp_ratio"] == 50.0 and m["precision"] == 50.0 and m["fscore"] == pytest.approx(50.0)


# -------------------------------------------------------------------------------------- culling


def test_voxel_mask_keeps_points_in_allocated_voxels_including_negative_cells() -> None:
    mask = voxel_mask_fn(np.array([[0, 0, 0], [-1, 0, 0], [5, -3, 2]], dtype=np.int32), 0.1)
    pts = np.array(
        [
            [0.05, 0.05, 0.05],  # cell (0,0,0)
            [-0.05, 0.05, 0.05],  # cell (-1,0,0): floor, not truncation towards zero
            [-0.15, 0.05, 0.05],  # cell (-2,0,0): not allocated
            [0.55, -0.25, 0.21],  # cell (5,-3,2)
            [0.55, 0.25, 0.21],  # cell (5,2,2): not allocated
            [1e9, 0.0, 0.0],  # far outside the key range
        ]
    )
    np.testing.assert_array_equal(mask(pts), [True, True, False, True, False, False])
    assert not voxel_mask_fn(np.zeros((0, 3), dtype=np.int32), 0.1)(pts).any()


K_CULL = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])  # 64 x 48 image


def _plane_depth_with_occluder() -> np.ndarray:
    """Camera at the origin looking +z at the plane z = 2; a square at z = 1 covers pixels 10..19."""
    depth = np.full((48, 64), 2.0, dtype=np.float32)
    depth[10:20, 10:20] = 1.0  # occluder in front
    depth[30:40, 40:50] = 0.0  # no measurement
    return depth


def _pixel_point(u: float, v: float, z: float) -> np.ndarray:
    return np.array([(u - 31.5) / 50.0 * z, (v - 23.5) / 50.0 * z, z])


def test_observed_mask_keeps_frustum_drops_outside_occluded_and_unmeasured() -> None:
    mask = observed_mask_fn([(K_CULL, np.eye(4), _plane_depth_with_occluder())], margin_m=0.05)
    pts = np.stack(
        [
            _pixel_point(30, 30, 2.0),  # on the plane in view -> kept
            _pixel_point(30, 30, 2.04),  # within the margin behind the surface -> kept
            _pixel_point(30, 30, 1.5),  # in front of the measured surface -> kept
            _pixel_point(30, 30, 2.2),  # 20 cm behind the surface -> occluded
            _pixel_point(15, 15, 2.0),  # plane behind the occluding square -> dropped
            _pixel_point(15, 15, 1.0),  # the occluder itself -> kept
            _pixel_point(45, 35, 2.0),  # pixel without depth -> dropped
            _pixel_point(80, 30, 2.0),  # right of the image -> dropped
            _pixel_point(30, -5, 2.0),  # above the image -> dropped
            np.array([0.0, 0.0, -2.0]),  # behind the camera -> dropped
        ]
    )
    np.testing.assert_array_equal(mask(pts), [1, 1, 1, 0, 0, 1, 0, 0, 0, 0])


def test_observed_mask_is_the_union_over_frames() -> None:
    depth = _plane_depth_with_occluder()
    hidden = _pixel_point(15, 15, 2.0)[None]
    assert not observed_mask_fn([(K_CULL, np.eye(4), depth)])(hidden)[0]
    # a second camera 1 m to the right, looking at the hidden point over the occluder's side
    T2 = look_at(np.array([1.0, 0.0, 0.0]), hidden[0], up=np.array([0.0, -1.0, 0.0]))
    plane = np.full((48, 64), 0.0, dtype=np.float32)
    z2 = (hidden[0] - T2[:3, 3]) @ T2[:3, 2]
    plane[:] = z2  # only its depth at the hidden point's pixel matters
    both = observed_mask_fn([(K_CULL, np.eye(4), depth), (K_CULL, T2, plane)])
    assert both(hidden)[0]


def test_observed_mask_on_real_fountain_keeps_the_scanned_reference(
    shared_dataset: Callable[[str], Path],
) -> None:
    root = shared_dataset("fountain_33")
    K, poses, depths = load_7scenes(root, stride=2)
    mesh = trimesh.load(root / "reference_mesh.ply", process=False)
    pts = sample_surface(mesh, 50_000)
    kept = observed_mask_fn(list(zip([K] * len(poses), poses, depths, strict=True)))(pts)
    assert kept.mean() > 0.95  # the reference was reconstructed from these very frames
    # moved 1 m behind the wall the cameras face, the surface is hidden from every frame
    behind = pts + 1.0 * np.mean(poses[:, :3, 2], axis=0)
    assert observed_mask_fn(list(zip([K] * len(poses), poses, depths, strict=True)))(behind).mean() < 0.05


# -------------------------------------------------------------------------------- image metrics


def _noisy(rng: np.random.Generator, shape: tuple[int, ...], sigma: float) -> tuple[np.ndarray, np.ndarray]:
    gt = rng.uniform(0.3, 0.7, size=shape)  # far from 0 and 1: noise is never clipped
    return np.clip(gt + rng.normal(0.0, sigma, size=shape), 0.0, 1.0), gt


def test_psnr_of_known_gaussian_noise() -> None:
    pred, gt = _noisy(np.random.default_rng(0), (256, 256, 3), 0.01)
    assert psnr(pred, gt) == pytest.approx(20 * math.log10(1 / 0.01), abs=0.2)
    pred, gt = _noisy(np.random.default_rng(1), (256, 256, 3), 0.1)
    assert psnr(pred, gt) == pytest.approx(20.0, abs=0.2)


def test_psnr_of_identical_images_is_capped() -> None:
    img = np.random.default_rng(0).uniform(size=(32, 32, 3))
    assert psnr(img, img) == PSNR_MAX_DB == 100.0


def test_psnr_and_ssim_honour_the_mask() -> None:
    rng = np.random.default_rng(2)
    gt = rng.uniform(0.3, 0.7, size=(64, 64, 3))
    pred = gt.copy()
    pred[:, 32:] = 1.0 - pred[:, 32:]  # ruin the right half
    mask = np.zeros((64, 64), dtype=bool)
    mask[:, :16] = True  # left quarter: 7x7 SSIM windows there never reach the ruined half
    assert psnr(pred, gt, mask) == PSNR_MAX_DB
    assert ssim(pred, gt, mask) == pytest.approx(1.0, abs=1e-9)
    assert psnr(pred, gt) < 20.0 and ssim(pred, gt) < 0.7
    assert math.isnan(psnr(pred, gt, np.zeros((64, 64), dtype=bool)))
    with pytest.raises(EvalError, match="mask"):
        psnr(pred, gt, np.ones((10, 10), dtype=bool))


def test_ssim_identical_is_one_and_drops_with_noise() -> None:
    noisy, gt = _noisy(np.random.default_rng(3), (64, 80, 3), 0.05)
    assert ssim(gt, gt) == pytest.approx(1.0, abs=1e-9)
    assert ssim(gt[..., 0], gt[..., 0]) == pytest.approx(1.0, abs=1e-9)  # single channel
    light = ssim(_noisy(np.random.default_rng(3), (64, 80, 3), 0.01)[0], gt)
    heavy = ssim(noisy, gt)
    assert heavy < light < 0.999


def test_depth_l1_of_a_known_offset_over_valid_pixels_only() -> None:
    gt = np.full((20, 30), 2.0, dtype=np.float32)
    pred = gt + 0.03
    gt[0, :] = 0.0  # invalid ground truth
    pred[1, :] = 0.0  # nothing rendered
    pred[0, :] = 9.0  # would count if invalid gt were used
    gt[2, :] = 7.0  # would count if nothing-rendered pixels were used
    pred[2, :] = 0.0
    assert depth_l1_cm(pred, gt) == pytest.approx(3.0, abs=1e-4)
    mask = np.zeros(gt.shape, dtype=bool)
    mask[5:, :] = True
    pred[3:5] = 5.0  # outside the mask
    assert depth_l1_cm(pred, gt, mask) == pytest.approx(3.0, abs=1e-4)
    assert math.isnan(depth_l1_cm(np.zeros_like(gt), gt))
