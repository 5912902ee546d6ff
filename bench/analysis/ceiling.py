"""The PSNR ceiling of the map's colour representation: how well it can fit a scene's colours at all.

`fit_colour_ceiling` trains the very colour field `h2viz map` trains (HybridField's colour hash grid and
decoder, built from the same MappingConfig) directly on ground-truth colours at ground-truth surface points:
one point per valid pixel of the views that are scored, lifted with the view's own depth (`surface_colours`).
It then scores the field at those points. Everything favours the field:

- geometry is exact (no SDF to learn, no volume rendering blending neighbouring samples);
- it is fitted to exactly the pixels it is scored on, with a squared loss (what PSNR measures), for as many
  steps as asked, where mapping gets a few iterations a frame of 4096 rays spread over many more views.

The PSNR it reaches is therefore, in practice, an upper bound for mapping runs with that colour representation on
those views. Views are handled as `h2viz map` scores them: at 1/downscale, ground-truth colour area-averaged.
Switches bring mapping's own conditions back one at a time: its L1 colour loss, its batch of rays, and
(`render="volume"`) each pixel volume-rendered from samples 1 cm apart with mapping's weights.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from h2viz.config import MappingConfig
from h2viz.eval.metrics import EvalError, psnr
from h2viz.eval.report import EvalView, scale_intrinsics, shrink_view
from h2viz.geometry import backproject
from h2viz.mapping.backend import resolve_backend
from h2viz.mapping.field.hybrid_field import HybridField
from h2viz.mapping.rendering.volume import composite, live_samples, render_weights
from h2viz.mapping.sampling.samples import Samples

LOSSES: tuple[str, ...] = ("l2", "l1")
RENDERS: tuple[str, ...] = ("surface", "volume")
"""surface: a sample's colour is the field's at its surface point; volume: its pixel is volume-rendered."""
EVAL_CHUNK = 1 << 17
"""Points per no-gradient colour evaluation (bounded memory)."""


@dataclass
class SurfaceColours:
    """Ground-truth colour samples on the true surface, one per valid pixel of the scored views."""

    points: np.ndarray  # (N,3) float32 world metres
    rgb: np.ndarray  # (N,3) float32 in [0,1]
    view: np.ndarray  # (N,) int64 index of the view each sample comes from
    origins: np.ndarray  # (V,3) float32 camera centre of each view


def surface_colours(views: Sequence[EvalView], downscale: int = 1) -> SurfaceColours:
    """Every pixel with valid depth of every view at 1/downscale (colour area-averaged, depth the block mean as
    `report.render_view` scores them), lifted along its pixel-centre ray to its depth in world coordinates."""
    points, rgb, view = [], [], []
    origins = np.array([T_world_camera[:3, 3] for _, T_world_camera, _, _ in views], np.float32).reshape(-1, 3)
    for i, (K, T_world_camera, image, depth_m) in enumerate(views):
        gt_rgb, gt_depth = shrink_view(np.asarray(image), np.asarray(depth_m), downscale)  # (h,w,3), (h,w)
        valid = gt_depth > 0
        points.append(backproject(gt_depth, scale_intrinsics(K, downscale), T_world_camera).astype(np.float32))
        rgb.append(gt_rgb[valid])  # backproject walks the valid pixels in the same row-major order
        view.append(np.full(int(valid.sum()), i, dtype=np.int64))
    if not points or sum(len(p) for p in points) == 0:
        raise EvalError("no pixel with valid depth in the views: nothing to fit the colour field to")
    return SurfaceColours(np.concatenate(points), np.concatenate(rgb).astype(np.float32), np.concatenate(view), origins)


@dataclass
class CeilingPoint:
    """The fitted field's PSNR after `steps` steps: pooled over every sample, and the mean of the views' own
    PSNRs (as metrics.json averages views)."""

    steps: int
    pooled_psnr_db: float
    mean_view_psnr_db: float


def colour_field(cfg: MappingConfig) -> HybridField:
    """The mapping's field for `cfg` on the CPU (with the kernels `cfg.kernels` picks); only its colour grid and
    decoder are used here."""
    torch.manual_seed(cfg.runtime.seed)
    return HybridField(cfg, resolve_backend(cfg.runtime.kernels, "cpu"))


@torch.no_grad()
def predict(field: HybridField, points: np.ndarray) -> np.ndarray:
    """Colour (N,3) float32 of the field at points (N,3)."""
    x = torch.from_numpy(points)
    return torch.cat([field.color(x[i : i + EVAL_CHUNK]) for i in range(0, len(x), EVAL_CHUNK)]).numpy()


def score(pred: np.ndarray, data: SurfaceColours) -> tuple[float, float]:
    """(pooled PSNR, mean per-view PSNR) in dB of predicted colours (N,3) against the samples, by `metrics.psnr`."""
    image, truth = pred[None], data.rgb[None]  # (1,N,3): the samples as one row of pixels
    per_view = [psnr(image, truth, (data.view == v)[None]) for v in np.unique(data.view)]
    return psnr(image, truth), float(np.mean(per_view))


def volume_colour(
    field: HybridField, cfg: MappingConfig, points: torch.Tensor, origins: torch.Tensor, rng: torch.Generator
) -> torch.Tensor:
    """Colour (B,3) of each surface point's (B,3) pixel seen from origins (B,3), volume-rendered as mapping renders
    it (h2viz.mapping.rendering.volume): samples cfg.step_m apart with one random offset a ray over the truncation band
    around the surface, weighted by the projective SDF along the ray, colour read where the weights matter."""
    dist = torch.linalg.norm(points - origins, dim=1, keepdim=True)  # (B,1)
    dirs = (points - origins) / dist  # (B,3)
    n = int(round(2 * cfg.representation.truncation_m / cfg.sampling.step_m)) + 1
    offset = torch.rand(len(points), 1, generator=rng) * cfg.sampling.step_m  # (B,1)
    tr, step = cfg.representation.truncation_m, cfg.sampling.step_m
    t = dist - tr + offset + step * torch.arange(n, dtype=torch.float32)  # (B,n)
    ray = torch.arange(len(points)).repeat_interleave(n)  # (B*n,)
    xyz = (origins[:, None] + t[..., None] * dirs[:, None]).reshape(-1, 3)  # (B*n,3)
    samples = Samples(xyz, t.reshape(-1), ray, torch.zeros_like(ray), len(points))
    sdf = ((dist - t) / cfg.representation.truncation_m).reshape(-1)  # (B*n,) truncation units
    weights = render_weights(samples, sdf, cfg.representation.truncation_m, cfg.rendering.render_temperature)
    live = live_samples(samples, weights)
    return composite(samples, weights, field.color(xyz[live]), live).rgb


def _check_fit(steps: int, batch: int, n_reports: int, loss: str, render: str) -> None:
    """Raise EvalError for fit settings that cannot work."""
    if steps < 1 or batch < 1 or n_reports < 1:
        raise EvalError(f"steps ({steps}), batch ({batch}) and n_reports ({n_reports}) must be >= 1")
    if loss not in LOSSES:
        raise EvalError(f"unknown colour loss {loss!r}; use one of {', '.join(LOSSES)}")
    if render not in RENDERS:
        raise EvalError(f"unknown render {render!r}; use one of {', '.join(RENDERS)}")


def fit_colour_ceiling(
    data: SurfaceColours,
    cfg: MappingConfig,
    steps: int,
    batch: int = 1 << 16,
    n_reports: int = 4,
    on_report: Callable[[CeilingPoint], None] | None = None,
    loss: str = "l2",
    render: str = "surface",
) -> list[CeilingPoint]:
    """Fit the colour field of `cfg` to the samples with Adam (the mapping's lr and betas) on random batches,
    minimising the squared error ("l2", what PSNR measures) or the absolute error ("l1", mapping's colour loss);
    each sample's colour is the field's at its point ("surface") or its pixel volume-rendered ("volume",
    `volume_colour`); score the field at the points `n_reports` times, evenly over the steps (the last after the
    final step)."""
    _check_fit(steps, batch, n_reports, loss, render)
    field = colour_field(cfg)
    params = [*field.color_grid.parameters(), *field.color_mlp.parameters()]
    optim = torch.optim.Adam(params, lr=cfg.optimization.lr, betas=(0.9, 0.99), eps=1e-15)
    points, rgb = torch.from_numpy(data.points), torch.from_numpy(data.rgb)
    origins = torch.from_numpy(data.origins)[torch.from_numpy(data.view)]  # (N,3)
    rng = torch.Generator().manual_seed(cfg.runtime.seed)
    report_at = {max(1, round(steps * (k + 1) / n_reports)) for k in range(n_reports)}
    curve: list[CeilingPoint] = []
    for step in range(1, steps + 1):
        pick = torch.randint(len(points), (min(batch, len(points)),), generator=rng)  # (B,)
        if render == "surface":
            colour = field.color(points[pick])  # (B,3)
        else:
            colour = volume_colour(field, cfg, points[pick], origins[pick], rng)
        error = colour - rgb[pick]  # (B,3)
        value = torch.mean(error**2) if loss == "l2" else torch.mean(error.abs())
        optim.zero_grad(set_to_none=True)
        value.backward()
        optim.step()
        if step in report_at:
            curve.append(CeilingPoint(step, *score(predict(field, data.points), data)))
            if on_report is not None:
                on_report(curve[-1])
    return curve
