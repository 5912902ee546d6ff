"""The `h2viz eval` back-end: image metrics over camera sets, mesh metrics from files, a text table
and metrics.json."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import trimesh

from h2viz.config import EvalConfig
from h2viz.eval.metrics import EvalError, MaskFn, depth_l1_cm, mesh_metrics, psnr, ssim
from h2viz.eval.views import extrapolate_views, interpolate_views
from h2viz.geometry import backproject
from h2viz.types import RgbdFrame

Renderer = Callable[[np.ndarray, np.ndarray, int, int, str], np.ndarray]
"""render(K, T_world_camera, height, width, mode): mode 'rgb' -> (H,W,3) float32 in [0,1],
'depth' -> (H,W) float32 metres (0 = nothing rendered)."""

EvalView = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""(K (3,3), T_world_camera (4,4), rgb (H,W,3) uint8 or float in [0,1], depth_m (H,W), 0 = invalid)."""

_UNITS = {"comp_ratio": "%", "precision": "%", "recall": "%", "fscore": "%", "ssim": "", "gt_kept_pct": "%"}
_SUFFIX_UNITS = {"_cm": "cm", "_m": "m", "_db": "dB", "_pct": "%", "_s": "s"}


# ---------------------------------------------------------------------------------- image metrics


def scale_intrinsics(K: np.ndarray, downscale: int) -> np.ndarray:
    """Intrinsics (3,3) of an image shrunk by an integer factor (pixel centres stay consistent)."""
    Ks = np.asarray(K, dtype=np.float64).copy()
    Ks[0, 0] /= downscale
    Ks[1, 1] /= downscale
    Ks[0, 2] = (Ks[0, 2] + 0.5) / downscale - 0.5
    Ks[1, 2] = (Ks[1, 2] + 0.5) / downscale - 0.5
    return Ks


def shrink_view(rgb: np.ndarray, depth_m: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth at 1/k resolution: colour float (h,w,3) by area averaging; depth (h,w) as the
    block mean where the whole k x k block is valid, else 0."""
    img = rgb.astype(np.float32) / 255.0 if rgb.dtype == np.uint8 else rgb.astype(np.float32)
    if k == 1:
        return img, depth_m.astype(np.float32)
    h, w = depth_m.shape[0] // k, depth_m.shape[1] // k
    img = cv2.resize(img[: h * k, : w * k], (w, h), interpolation=cv2.INTER_AREA)
    blocks = depth_m[: h * k, : w * k].reshape(h, k, w, k).astype(np.float32)  # (h,k,w,k)
    valid = np.all(blocks > 0, axis=(1, 3))
    return img, np.where(valid, blocks.mean(axis=(1, 3)), 0.0).astype(np.float32)


RenderedView = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""(pred rgb (h,w,3) float32, pred depth (h,w), gt rgb (h,w,3) float32 in [0,1], gt depth (h,w), mask (h,w))."""


def render_view(render: Renderer, view: EvalView, downscale: int = 1) -> RenderedView:
    """One view rendered at 1/downscale with its ground truth shrunk to match, and the pixels to compare: where
    GT and rendered depth are valid."""
    K, T_world_camera, rgb, depth_m = view
    gt_rgb, gt_depth = shrink_view(np.asarray(rgb), np.asarray(depth_m), downscale)  # (h,w,3), (h,w)
    h, w = gt_depth.shape
    Ks = scale_intrinsics(K, downscale)
    pred_rgb = np.asarray(render(Ks, T_world_camera, h, w, "rgb"), dtype=np.float32)
    pred_depth = np.asarray(render(Ks, T_world_camera, h, w, "depth"), dtype=np.float32)
    if pred_rgb.shape != (h, w, 3) or pred_depth.shape != (h, w):
        raise EvalError(
            f"renderer returned rgb {pred_rgb.shape} and depth {pred_depth.shape} for a {w}x{h} request; "
            "it must return (H,W,3) and (H,W)"
        )
    mask = (gt_depth > 0) & (pred_depth > 0) & np.isfinite(pred_depth)  # (h,w)
    return pred_rgb, pred_depth, gt_rgb, gt_depth, mask


def view_metrics(render: Renderer, view: EvalView, downscale: int = 1) -> dict[str, float]:
    """PSNR / SSIM / depth L1 of one rendered view, over pixels where GT and rendered depth are valid."""
    pred_rgb, pred_depth, gt_rgb, gt_depth, mask = render_view(render, view, downscale)
    return {
        "psnr_db": psnr(np.clip(pred_rgb, 0.0, 1.0), gt_rgb, mask),
        "ssim": ssim(np.clip(pred_rgb, 0.0, 1.0), gt_rgb, mask),
        "depth_l1_cm": depth_l1_cm(pred_depth, gt_depth, mask),
        "valid_pct": 100.0 * float(mask.mean()),
    }


def image_metrics(render: Renderer, views: Sequence[EvalView], downscale: int = 1) -> dict[str, float]:
    """Mean PSNR (dB), SSIM and depth L1 (cm) over views [(K, T_world_camera, rgb, depth_m), ...],
    each masked to pixels where GT and rendered depth are valid; views with no such pixel are left out
    of the means (NaN when none is left)."""
    if downscale < 1:
        raise EvalError(f"eval.render_downscale must be >= 1, got {downscale}")
    per_view = [view_metrics(render, v, downscale) for v in views]
    out: dict[str, float] = {"n_views": float(len(per_view))}
    for key in ("psnr_db", "ssim", "depth_l1_cm", "valid_pct"):
        values = np.array([m[key] for m in per_view], dtype=np.float64)
        values = values[np.isfinite(values)]
        out[key] = float(values.mean()) if len(values) else math.nan
    return out


def training_views(frames: Sequence[RgbdFrame], n: int) -> list[EvalView]:
    """The "interpolate" views: `n` of the frames spread evenly over the trajectory, as evaluation picks them."""
    poses = np.stack([f.T_world_camera for f in frames])  # (N,4,4)
    return [(f.K, f.T_world_camera, f.rgb, f.depth_m) for f in (frames[i] for i in interpolate_views(poses, n))]


def evaluate_images(
    render: Renderer, frames: Sequence[RgbdFrame], cfg: EvalConfig, gt_render: Renderer | None = None
) -> dict[str, dict[str, float]]:
    """ "interpolate" metrics on `cfg.n_interpolate` training frames and, when a ground-truth renderer
    (e.g. `MeshRenderer(gt_mesh)`) is given, "extrapolate" metrics on `cfg.n_extrapolate` novel views
    whose reference images come from it."""
    if len(frames) == 0:
        raise EvalError("no frames to evaluate images on; check the source path and stride")
    views = training_views(frames, cfg.n_interpolate)
    out = {"interpolate": image_metrics(render, views, cfg.render_downscale)}
    if gt_render is None or cfg.n_extrapolate <= 0:
        return out
    scene = np.concatenate(
        [backproject(depth_m[::8, ::8], _stride_K(K, 8), T_world_camera) for K, T_world_camera, _, depth_m in views]
    )  # (P,3) observed surface
    if len(scene) < 2:
        raise EvalError("the evaluated frames have no valid depth; extrapolated views need observed surface")
    offsets = (cfg.extrapolate_min_offset_m, cfg.extrapolate_max_offset_m)
    min_gap = cfg.extrapolate_min_distance_m
    poses = np.stack([f.T_world_camera for f in frames])  # (N,4,4)
    cams = extrapolate_views(poses, cfg.n_extrapolate, scene, cfg.seed, offsets, min_gap)  # (n,4,4)
    ds = cfg.render_downscale
    K, h, w = scale_intrinsics(frames[0].K, ds), frames[0].height // ds, frames[0].width // ds
    novel = [(K, T, gt_render(K, T, h, w, "rgb"), gt_render(K, T, h, w, "depth")) for T in cams]
    out["extrapolate"] = image_metrics(render, novel, 1)
    return out


def _stride_K(K: np.ndarray, step: int) -> np.ndarray:
    """Intrinsics of an image subsampled as image[::step, ::step]."""
    Ks = np.asarray(K, dtype=np.float64).copy()
    Ks[:2] /= step
    return Ks


# ----------------------------------------------------------------------------------- mesh metrics


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """A triangle mesh from a file trimesh reads (.ply, .obj, .stl, .glb...), scenes concatenated."""
    path = Path(path)
    if not path.is_file():
        raise EvalError(f"mesh file {path} does not exist; pass the path of a .ply/.obj mesh")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for unreadable files
        raise EvalError(f"mesh file {path} cannot be read ({type(e).__name__}: {e}); re-export it") from e
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise EvalError(f"mesh file {path} holds no triangles (empty or a point cloud); pass a mesh")
    if not mesh.area > 0:
        raise EvalError(f"mesh file {path} has zero surface area; pass a non-degenerate mesh")
    return mesh


def evaluate_mesh_files(
    rec_path: str | Path, gt_path: str | Path, cfg: EvalConfig, gt_mask_fn: MaskFn | None = None
) -> dict[str, float]:
    """Acc / Comp / Comp ratio / F-score of the mesh at `rec_path` against `gt_path` (see
    `mesh_metrics`); `gt_mask_fn` culls the ground truth (`observed_mask_fn` or `voxel_mask_fn`)."""
    rec, gt = load_mesh(rec_path), load_mesh(gt_path)
    return mesh_metrics(rec, gt, cfg.n_points, cfg.threshold_m, gt_mask_fn, cfg.seed)


# ------------------------------------------------------------------------------------ presentation


def _unit(name: str) -> str:
    if name in _UNITS:
        return _UNITS[name]
    return next((unit for suffix, unit in _SUFFIX_UNITS.items() if name.endswith(suffix)), "")


def _format_value(name: str, value: Any) -> str:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return str(value)
    if not math.isfinite(value):
        return "n/a" if math.isnan(value) else str(value)
    if name.startswith("n_") and float(value).is_integer():
        return str(int(value))
    return f"{value:.4f}" if abs(value) < 1000 else f"{value:.1f}"


def _flatten(metrics: Mapping[str, Any], prefix: str = "") -> list[tuple[str, str, Any]]:
    """(dotted name, leaf name, value) rows of possibly nested metrics."""
    rows: list[tuple[str, str, Any]] = []
    for key, value in metrics.items():
        if isinstance(value, Mapping):
            rows += _flatten(value, f"{prefix}{key}.")
        else:
            rows.append((f"{prefix}{key}", str(key), value))
    return rows


def format_table(metrics: Mapping[str, Any]) -> str:
    """Aligned text table with rows (metric, value, unit); nested sections become dotted names."""
    rows = [("metric", "value", "unit")]
    rows += [(name, _format_value(leaf, v), _unit(leaf)) for name, leaf, v in _flatten(metrics)]
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    lines = [f"{a:<{w0}}  {b:>{w1}}  {c}".rstrip() for a, b, c in rows]
    lines.insert(1, "-" * max(len(line) for line in lines))
    return "\n".join(lines)


def _jsonable(value: Any) -> Any:
    """Nested metrics with floats rounded to 6 significant digits and NaN / inf as None."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, bool | int | str) or value is None:
        return value
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        x = float(value)
        return float(f"{x:.6g}") if math.isfinite(x) else None
    raise EvalError(f"metrics.json: cannot write a value of type {type(value).__name__}; use numbers")


def write_metrics(metrics: Mapping[str, Any], path: str | Path) -> Path:
    """Write metrics as JSON (to `path`, or to `path`/metrics.json when it is a folder); return the file."""
    path = Path(path)
    if path.is_dir():
        path = path / "metrics.json"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(_jsonable(metrics), indent=2, allow_nan=False) + "\n")
    except OSError as e:
        raise EvalError(f"cannot write {path} ({e}); choose a writable output folder") from e
    return path
