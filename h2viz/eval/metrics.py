"""Reconstruction and image metrics: Acc / Comp / Comp ratio / F-score between meshes, ground-truth
culling (to what the input frames observed, or to allocated voxels), depth L1, PSNR and SSIM.

Mesh distances follow the H2-Mapping protocol: points are sampled uniformly by area from both meshes
and matched by nearest neighbour in each direction (no torch, NumPy / SciPy / trimesh only).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from skimage.metrics import structural_similarity

from h2viz.errors import H2vizError
from h2viz.geometry import project

MaskFn = Callable[[np.ndarray], np.ndarray]
"""Maps world points (N,3) to a boolean keep-mask (N,)."""

PSNR_MAX_DB = 100.0
"""PSNR reported for (near-)identical images: the MSE is floored at 1e-10 so means stay finite."""

_MSE_FLOOR = 10.0 ** (-PSNR_MAX_DB / 10.0)
_KEY_OFFSET = 1 << 20  # voxel coordinates are packed as 3 x 21 bits into one int64 key


class EvalError(H2vizError):
    """Evaluation inputs cannot be used (missing or empty mesh, nothing left after culling...)."""


# ------------------------------------------------------------------------------------ mesh metrics


def sample_surface(mesh: trimesh.Trimesh, n: int, seed: int = 0) -> np.ndarray:
    """Exactly `n` points (N,3) drawn uniformly by area from the mesh surface, reproducible from `seed`."""
    if len(mesh.faces) == 0 or not mesh.area > 0:
        raise EvalError("cannot sample a mesh without faces or with zero area; check the mesh file")
    points, _ = trimesh.sample.sample_surface(mesh, int(n), seed=np.random.default_rng(seed))
    return np.asarray(points, dtype=np.float64)


def point_metrics(rec_pts: np.ndarray, gt_pts: np.ndarray, threshold_m: float = 0.05) -> dict[str, float]:
    """Acc / Comp (cm), Comp ratio, precision, recall and F-score (%) between point sets (N,3), (M,3)."""
    if len(rec_pts) == 0 or len(gt_pts) == 0:
        raise EvalError(
            f"no points to compare ({len(rec_pts)} reconstructed, {len(gt_pts)} ground truth); "
            "the reconstruction is empty or culling removed all ground truth"
        )
    d_rec, _ = cKDTree(gt_pts).query(rec_pts, workers=-1)  # (N,) reconstruction -> ground truth
    d_gt, _ = cKDTree(rec_pts).query(gt_pts, workers=-1)  # (M,) ground truth -> reconstruction
    return distance_metrics(d_rec, d_gt, threshold_m)


def distance_metrics(d_rec: np.ndarray, d_gt: np.ndarray, threshold_m: float = 0.05) -> dict[str, float]:
    """`point_metrics` from the nearest distances reconstruction -> ground truth (N,) and back (M,), metres."""
    precision = 100.0 * float(np.mean(d_rec < threshold_m))
    recall = 100.0 * float(np.mean(d_gt < threshold_m))
    fscore = 2.0 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {
        "acc_cm": 100.0 * float(np.mean(d_rec)),
        "comp_cm": 100.0 * float(np.mean(d_gt)),
        "comp_ratio": recall,
        "precision": precision,
        "recall": recall,
        "fscore": fscore,
        "n_rec_points": float(len(d_rec)),
        "n_gt_points": float(len(d_gt)),
    }


def sample_pair(
    rec: trimesh.Trimesh, gt: trimesh.Trimesh, n_points: int, gt_mask_fn: MaskFn | None = None, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, float]:
    """The points Acc and Comp compare: `n_points` samples of the reconstruction (N,3) and of the ground truth
    culled by `gt_mask_fn` (M,3), and the share of ground truth kept (%)."""
    rec_pts = sample_surface(rec, n_points, seed)  # (N,3)
    gt_pts = sample_surface(gt, n_points, seed + 1)  # (M,3)
    if gt_mask_fn is None:
        return rec_pts, gt_pts, 100.0
    keep = np.asarray(gt_mask_fn(gt_pts), dtype=bool)  # (M,)
    return rec_pts, gt_pts[keep], 100.0 * float(keep.mean())


def mesh_metrics(
    rec: trimesh.Trimesh,
    gt: trimesh.Trimesh,
    n_points: int = 200_000,
    threshold_m: float = 0.05,
    gt_mask_fn: MaskFn | None = None,
    seed: int = 0,
) -> dict[str, float]:
    """Acc, Comp (cm: mean nearest distance rec->gt, gt->rec), Comp ratio / precision / recall /
    F-score (% of points closer than `threshold_m`) on `n_points` samples of each mesh.

    `gt_mask_fn` culls the ground-truth samples to what was observed before matching; the share of
    ground truth it kept is reported as `gt_kept_pct`.
    """
    rec_pts, gt_pts, kept = sample_pair(rec, gt, n_points, gt_mask_fn, seed)
    out = point_metrics(rec_pts, gt_pts, threshold_m)
    out["gt_kept_pct"] = kept
    return out


# ----------------------------------------------------------------------------------------- culling


def observed_mask_fn(frames: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], margin_m: float = 0.05) -> MaskFn:
    """Culling to what `frames` = [(K, T_world_camera, depth_m), ...] observed.

    A point counts as observed when, in at least one frame, it lies in front of the camera, projects
    to a pixel (nearest pixel centre) inside the image whose depth is valid (> 0), and its camera
    depth is at most that depth + `margin_m` (points further behind the measured surface are occluded).
    """
    frames = [(np.asarray(K, np.float64), np.asarray(T, np.float64), np.asarray(d)) for K, T, d in frames]

    def mask(points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64)
        seen = np.zeros(len(points), dtype=bool)  # (N,)
        for K, T_world_camera, depth_m in frames:
            seen |= _seen_by(points, K, T_world_camera, depth_m, margin_m)
        return seen

    return mask


def _seen_by(
    points: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, depth_m: np.ndarray, margin_m: float
) -> np.ndarray:
    """Which points (N,3) one depth frame observed (see `observed_mask_fn`)."""
    height, width = depth_m.shape
    uv, z = project(points, K, T_world_camera)  # (N,2), (N,)
    with np.errstate(invalid="ignore"):
        u = np.floor(uv[:, 0] + 0.5)
        v = np.floor(uv[:, 1] + 0.5)
        inside = (z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    ui = np.where(inside, u, 0).astype(np.int64)
    vi = np.where(inside, v, 0).astype(np.int64)
    d = depth_m[vi, ui].astype(np.float64)  # (N,)
    return inside & (d > 0) & (z <= d + margin_m)


def _voxel_keys(coords: np.ndarray) -> np.ndarray:
    """Pack integer voxel coordinates (V,3) into int64 keys (V,)."""
    c = np.clip(coords.astype(np.int64) + _KEY_OFFSET, 0, 2 * _KEY_OFFSET - 1)
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


def voxel_mask_fn(voxel_coords: np.ndarray, voxel_size_m: float) -> MaskFn:
    """Culling to allocated voxels: keep points whose grid cell floor(p / voxel_size_m) is in
    `voxel_coords` (V,3) int (the map's leaf voxels, grid anchored at the world origin)."""
    coords = np.asarray(voxel_coords).reshape(-1, 3)
    keys = np.unique(_voxel_keys(coords))  # (V,) sorted

    def mask(points: np.ndarray) -> np.ndarray:
        cells = np.floor(np.asarray(points, dtype=np.float64) / voxel_size_m)  # (N,3)
        outside = np.any(np.abs(cells) >= _KEY_OFFSET, axis=1)
        q = _voxel_keys(np.where(outside[:, None], 0, cells).astype(np.int64))  # (N,)
        if len(keys) == 0:
            return np.zeros(len(q), dtype=bool)
        pos = np.clip(np.searchsorted(keys, q), 0, len(keys) - 1)
        return (keys[pos] == q) & ~outside

    return mask


# ---------------------------------------------------------------------------------- image metrics


def _valid_mask(shape: tuple[int, ...], mask: np.ndarray | None) -> np.ndarray:
    if mask is None:
        return np.ones(shape[:2], dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != shape[:2]:
        raise EvalError(f"mask is {mask.shape} but the images are {shape[:2]}; pass an (H,W) mask")
    return mask


def _check_same_shape(pred: np.ndarray, gt: np.ndarray, what: str) -> None:
    if pred.shape != gt.shape:
        raise EvalError(f"{what}: rendered image is {pred.shape} but ground truth is {gt.shape}")


def depth_l1_cm(pred_depth: np.ndarray, gt_depth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean |pred - gt| in cm over pixels (H,W) where both depths are valid (> 0, finite) and `mask`
    holds; NaN when no pixel qualifies."""
    _check_same_shape(pred_depth, gt_depth, "depth L1")
    pred = np.asarray(pred_depth, dtype=np.float64)
    gt = np.asarray(gt_depth, dtype=np.float64)
    valid = _valid_mask(gt.shape, mask) & np.isfinite(pred) & np.isfinite(gt) & (pred > 0) & (gt > 0)
    if not valid.any():
        return math.nan
    return 100.0 * float(np.mean(np.abs(pred[valid] - gt[valid])))


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB of float images in [0,1] ((H,W) or (H,W,C)) over masked pixels; identical images
    give PSNR_MAX_DB (100 dB), an empty mask gives NaN."""
    _check_same_shape(pred, gt, "PSNR")
    valid = _valid_mask(gt.shape, mask)
    if not valid.any():
        return math.nan
    diff = np.asarray(pred, dtype=np.float64)[valid] - np.asarray(gt, dtype=np.float64)[valid]
    mse = max(float(np.mean(diff**2)), _MSE_FLOOR)
    return -10.0 * math.log10(mse)


def ssim(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """SSIM of float images in [0,1] ((H,W) or (H,W,C), at least 7x7): the full SSIM map (7x7
    windows, data_range 1) averaged over masked pixels and channels; NaN for an empty mask.
    Outside the mask `pred` is replaced by `gt` first, so that unmeasured pixels do not lower the
    score of the windows around them."""
    _check_same_shape(pred, gt, "SSIM")
    valid = _valid_mask(gt.shape, mask)
    if not valid.any():
        return math.nan
    if min(gt.shape[:2]) < 7:
        raise EvalError(f"SSIM needs images of at least 7x7 pixels, got {gt.shape[:2]}; render larger")
    channel_axis = -1 if gt.ndim == 3 else None
    gt = np.asarray(gt, dtype=np.float64)
    pred = np.where(valid if gt.ndim == 2 else valid[..., None], np.asarray(pred, dtype=np.float64), gt)
    _, smap = structural_similarity(
        pred,
        gt,
        channel_axis=channel_axis,
        data_range=1.0,
        full=True,
    )
    if smap.ndim == 3:
        smap = smap.mean(axis=2)  # (H,W)
    return float(smap[valid].mean())
