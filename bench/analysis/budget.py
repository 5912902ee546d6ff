"""Where the quality metrics lose: PSNR split by image region and Acc split into the protocol's sampling floor
and the reconstruction's own error.

PSNR: every ground-truth pixel falls in one region (`region_masks`): geometry edges (depth jumps), texture
edges (strong colour gradients away from depth jumps) or flat (the rest). The squared error is pooled per
region over all views, giving each region's share of the error, its own PSNR and the PSNR the views would
score if that region were rendered perfectly. `half_pixel_psnr` tells how demanding the images are: the score
of the ground truth itself misregistered by half a pixel.

Acc: the paper's protocol samples points on both meshes, so even a perfect mesh scores the mean distance
between two random point sets (the floor). `acc_budget` moves each reconstructed sample onto the ground-truth
surface (its closest point on the ground-truth triangles, `closest_on_mesh`) and measures Acc again: that is the
floor for this reconstruction's sample layout; the rest is split by how far the samples really are from the
surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import trimesh
from scipy.spatial import cKDTree

from h2viz.eval.metrics import EvalError, MaskFn, sample_pair

REGIONS: tuple[str, ...] = ("geometry edges", "texture edges", "flat")
DEPTH_JUMP = 0.03
"""A pixel is on a geometry edge when the depth within 2 pixels of it spans more than this share of its depth."""
TEXTURE_GRADIENT = 0.15
"""A pixel is on a texture edge when the Sobel gradient of grey ([0,1]) within 1 pixel of it exceeds this."""
ERROR_BINS_M: tuple[float, ...] = (0.0, 0.005, 0.01, 0.02, 0.05, np.inf)
"""Bins of a reconstructed point's distance to the ground-truth surface for the Acc split."""


def region_masks(rgb: np.ndarray, depth_m: np.ndarray) -> dict[str, np.ndarray]:
    """Disjoint boolean masks (H,W) of REGIONS for a ground-truth image rgb (H,W,3) in [0,1] and its depth (H,W)
    (0 = invalid); together they cover every pixel."""
    if rgb.shape[:2] != depth_m.shape or rgb.ndim != 3:
        raise EvalError(f"rgb {rgb.shape} and depth {depth_m.shape} must be (H,W,3) and (H,W)")
    d = depth_m.astype(np.float32)
    kernel = np.ones((5, 5), np.uint8)
    high = cv2.dilate(d, kernel)
    low = cv2.erode(np.where(d > 0, d, np.float32(np.inf)), kernel)
    geometry = (high - np.where(np.isfinite(low), low, 0.0)) > DEPTH_JUMP * np.maximum(d, 1e-3)
    grey = cv2.cvtColor(rgb.astype(np.float32), cv2.COLOR_RGB2GRAY)
    gradient = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
    texture = (cv2.dilate(gradient, np.ones((3, 3), np.uint8)) > TEXTURE_GRADIENT) & ~geometry
    return {"geometry edges": geometry, "texture edges": texture, "flat": ~geometry & ~texture}


@dataclass
class RegionRow:
    """One region's share of the pixels and of the squared error (%), its PSNR and the PSNR of all pixels were it
    rendered perfectly (dB; None for the "all" row)."""

    region: str
    pixels_pct: float
    error_pct: float
    psnr_db: float
    psnr_without_db: float | None = None


@dataclass
class RegionErrors:
    """Squared colour error pooled per region over views: sums and pixel counts."""

    sq_error: dict[str, float]
    pixels: dict[str, int]

    @staticmethod
    def empty() -> RegionErrors:
        return RegionErrors({r: 0.0 for r in REGIONS}, {r: 0 for r in REGIONS})

    def add(self, pred: np.ndarray, gt: np.ndarray, depth_m: np.ndarray, valid: np.ndarray) -> None:
        """Add one view: pred and gt (H,W,3) in [0,1], gt depth (H,W), valid (H,W) pixels to count."""
        if pred.shape != gt.shape or valid.shape != gt.shape[:2]:
            raise EvalError(f"rendered {pred.shape}, ground truth {gt.shape} and mask {valid.shape} do not match")
        se = ((pred.astype(np.float64) - gt) ** 2).mean(axis=-1)  # (H,W) per-pixel MSE over channels
        for name, mask in region_masks(gt, depth_m).items():
            m = mask & valid
            self.sq_error[name] += float(se[m].sum())
            self.pixels[name] += int(m.sum())

    def table(self) -> list[RegionRow]:
        """A row per region, then the "all" row."""
        total_se, total_n = sum(self.sq_error.values()), sum(self.pixels.values())
        if total_n == 0:
            raise EvalError("no valid pixels were compared")
        rows = []
        for name in REGIONS:
            se, n = self.sq_error[name], self.pixels[name]
            share = 100.0 * se / total_se if total_se > 0 else 0.0
            rows.append(RegionRow(name, 100.0 * n / total_n, share, _psnr(se, n), _psnr(total_se - se, total_n)))
        return [*rows, RegionRow("all", 100.0, 100.0, _psnr(total_se, total_n))]


def _psnr(sq_error: float, n: int) -> float:
    """PSNR (dB) of a pooled squared error over n pixels, colours in [0,1] (inf without error, NaN without pixels)."""
    if n == 0:
        return float("nan")
    return float("inf") if sq_error <= 0 else float(-10.0 * np.log10(sq_error / n))


def half_pixel_psnr(rgb: np.ndarray, valid: np.ndarray | None = None) -> float:
    """PSNR (dB) of an image (H,W,3) in [0,1] against itself moved half a pixel right (bilinear): how much a
    render misregistered by half a pixel would lose on this image."""
    h, w = rgb.shape[:2]
    shift = np.float32([[1.0, 0.0, 0.5], [0.0, 1.0, 0.0]])
    moved = cv2.warpAffine(rgb.astype(np.float32), shift, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    se = ((moved.astype(np.float64) - rgb) ** 2).mean(axis=-1)
    m = np.ones((h, w), bool) if valid is None else valid
    return _psnr(float(se[m].sum()), int(m.sum()))


def closest_on_mesh(mesh: trimesh.Trimesh, points: np.ndarray, n_dense: int, seed: int = 0, k: int = 8) -> np.ndarray:
    """Closest points (N,3) on `mesh` to points (N,3): the closest among the triangles of the `k` nearest of
    `n_dense` points sampled on the surface (exact whenever one of them holds the true closest point, which
    dense sampling makes the rule). trimesh.proximity.closest_point is exact but needs rtree and loops over
    candidate faces in Python, far slower on 200k points."""
    dense, faces = trimesh.sample.sample_surface(mesh, int(n_dense), seed=np.random.default_rng(seed))
    _, nearest = cKDTree(dense).query(points, k=k, workers=-1)  # (N,k)
    triangles = np.asarray(mesh.triangles)[faces[nearest.reshape(-1)]]  # (N*k,3,3)
    candidates = trimesh.triangles.closest_point(triangles, np.repeat(points, k, axis=0)).reshape(-1, k, 3)
    best = np.argmin(np.linalg.norm(candidates - points[:, None], axis=2), axis=1)  # (N,)
    return candidates[np.arange(len(points)), best]


@dataclass
class ErrorBin:
    """Reconstructed samples whose distance to the true surface lies in [from_cm, to_cm): their share (%) and
    what they add to Acc above the floor (cm, over all samples)."""

    from_cm: float
    to_cm: float
    points_pct: float
    excess_cm: float


@dataclass
class AccBudget:
    """Acc (cm), its floor for the same samples moved onto the true surface, the samples' mean true distance and
    the excess over the floor per distance bin."""

    acc_cm: float
    floor_cm: float
    mean_error_cm: float
    bins: list[ErrorBin]


def acc_budget(
    rec: trimesh.Trimesh,
    gt: trimesh.Trimesh,
    n_points: int = 200_000,
    gt_mask_fn: MaskFn | None = None,
    seed: int = 0,
    dense_factor: int = 20,
) -> AccBudget:
    """Acc (cm) as `mesh_metrics` computes it (same samples and culling), its floor (the reconstructed samples
    moved onto the ground-truth surface) and the excess over the floor per bin of true distance ERROR_BINS_M."""
    rec_pts, gt_pts, _ = sample_pair(rec, gt, n_points, gt_mask_fn, seed)  # (N,3), (M,3) as mesh_metrics has them
    if len(gt_pts) == 0:
        raise EvalError("culling removed every ground-truth point; nothing to measure Acc against")
    tree = cKDTree(gt_pts)
    acc, _ = tree.query(rec_pts, workers=-1)  # (N,)
    on_surface = closest_on_mesh(gt, rec_pts, dense_factor * n_points, seed + 2)  # (N,3)
    floor, _ = tree.query(on_surface, workers=-1)  # (N,)
    true_error = np.linalg.norm(rec_pts - on_surface, axis=1)  # (N,)
    bins = []
    for lo, hi in zip(ERROR_BINS_M[:-1], ERROR_BINS_M[1:], strict=True):
        m = (true_error >= lo) & (true_error < hi)
        excess = 100.0 * float((acc[m] - floor[m]).sum()) / len(acc)
        bins.append(ErrorBin(100.0 * lo, 100.0 * hi, 100.0 * float(m.mean()), excess))
    cm = lambda d: 100.0 * float(d.mean())  # noqa: E731
    return AccBudget(cm(acc), cm(floor), cm(true_error), bins)
