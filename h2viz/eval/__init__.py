"""Evaluation against ground truth: mesh metrics (Acc / Comp / Comp ratio), image metrics (PSNR /
SSIM / depth L1) on interpolated and extrapolated cameras, and the report written by `h2viz eval`."""

from h2viz.eval.mesh_render import MeshRenderer
from h2viz.eval.metrics import (
    PSNR_MAX_DB,
    EvalError,
    MaskFn,
    depth_l1_cm,
    mesh_metrics,
    observed_mask_fn,
    point_metrics,
    psnr,
    sample_surface,
    ssim,
    voxel_mask_fn,
)
from h2viz.eval.report import (
    EvalView,
    Renderer,
    evaluate_images,
    evaluate_mesh_files,
    format_table,
    image_metrics,
    load_mesh,
    scale_intrinsics,
    view_metrics,
    write_metrics,
)
from h2viz.eval.views import estimate_up, extrapolate_views, interpolate_views

__all__ = [
    "PSNR_MAX_DB",
    "EvalError",
    "EvalView",
    "MaskFn",
    "MeshRenderer",
    "Renderer",
    "depth_l1_cm",
    "estimate_up",
    "evaluate_images",
    "evaluate_mesh_files",
    "extrapolate_views",
    "format_table",
    "image_metrics",
    "interpolate_views",
    "load_mesh",
    "mesh_metrics",
    "observed_mask_fn",
    "point_metrics",
    "psnr",
    "sample_surface",
    "scale_intrinsics",
    "ssim",
    "view_metrics",
    "voxel_mask_fn",
    "write_metrics",
]
