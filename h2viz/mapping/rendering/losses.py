"""The four H2-Mapping losses on a batch of rays: colour (L1, or L2 by choice), depth L1, free-space and SDF
(truncation band)."""

from __future__ import annotations

import torch

from h2viz.config import MappingConfig
from h2viz.errors import ConfigError
from h2viz.mapping.rendering.volume import RayRender, segment_sum
from h2viz.mapping.sampling.samples import Samples

RGB_LOSSES: tuple[str, ...] = ("l1", "l2")
"""mapping.losses.rgb_loss choices: absolute or squared colour error."""


COLOR_SUPERVISION: tuple[str, ...] = ("none", "surface", "volume")
"""mapping.losses.color_supervision choices: no colour training (the colour priors alone), colour at each ray's measured
surface point, or volume-rendered colour."""


def check_color_settings(rgb_loss: str, supervision: str = "volume", color_prior: bool = False) -> None:
    """Raise ConfigError for an unknown mapping.losses.rgb_loss or mapping.losses.color_supervision, or for a map with
    neither colour priors nor colour training."""
    if rgb_loss not in RGB_LOSSES:
        raise ConfigError(f"mapping.losses.rgb_loss: unknown {rgb_loss!r}; use one of {RGB_LOSSES}")
    if supervision not in COLOR_SUPERVISION:
        raise ConfigError(f"mapping.losses.color_supervision: unknown {supervision!r}; use one of {COLOR_SUPERVISION}")
    if supervision == "none" and not color_prior:
        raise ConfigError(
            "mapping.losses.color_supervision: none leaves colour to the colour priors, but mapping.color.color_prior "
            "is false; turn the priors on or pick surface / volume"
        )


def color_error(pred: torch.Tensor, target: torch.Tensor, squared: bool) -> torch.Tensor:
    """Mean colour error over rays and channels: pred, target (R,3) in [0,1] -> () (zero for no rays)."""
    if pred.shape[0] == 0:
        return pred.sum() * 0.0
    error = pred - target
    return (error**2 if squared else error.abs()).mean()


def per_ray_mean(values: torch.Tensor, mask: torch.Tensor, samples: Samples) -> torch.Tensor:
    """Mean over rays that have masked samples of the per-ray mean of `values` (S,) under `mask` (S,)."""
    m = mask.to(values.dtype)
    num = segment_sum(values * m, samples.ray, samples.n_rays)
    cnt = segment_sum(m, samples.ray, samples.n_rays)
    has = cnt > 0
    if not bool(has.any()):
        return values.sum() * 0.0
    return (num[has] / cnt[has]).mean()


def mapping_losses(
    samples: Samples,
    sdf: torch.Tensor,
    render: RayRender,
    rgb_gt: torch.Tensor,
    depth_gt: torch.Tensor,
    cfg: MappingConfig,
) -> dict[str, torch.Tensor]:
    """Weighted loss terms and their sum: sdf (S,) in tr units, rgb_gt (R,3) in [0,1], depth_gt (R,) metres."""
    tr = cfg.representation.truncation_m
    d = depth_gt[samples.ray]  # (S,)
    valid = d > 0
    front = valid & (samples.t < d - tr)
    band = valid & ~front & (samples.t <= d + tr)
    fs = per_ray_mean((sdf - 1.0) ** 2, front, samples)
    sdf_term = per_ray_mean((samples.t + sdf * tr - d) ** 2, band, samples)
    ok = render.hit & (depth_gt > 0)
    zero = sdf.sum() * 0.0
    depth = (render.depth - depth_gt).abs()[ok].mean() if bool(ok.any()) else zero
    rgb = color_error(render.rgb[render.hit], rgb_gt[render.hit], cfg.losses.rgb_loss == "l2")
    terms = {
        "rgb": cfg.losses.w_rgb * rgb,
        "depth": cfg.losses.w_depth * depth,
        "fs": cfg.losses.w_fs * fs,
        "sdf": cfg.losses.w_sdf * sdf_term,
    }
    terms["total"] = terms["rgb"] + terms["depth"] + terms["fs"] + terms["sdf"]
    return terms
