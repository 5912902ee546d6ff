"""Colour ceiling: surface samples land where their pixels see, scores are exact, and the fitted colour field
reproduces what its grid can hold (a smooth ramp) but not what it cannot (texture finer than its finest cell)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from bench.analysis.ceiling import (
    SurfaceColours,
    colour_field,
    fit_colour_ceiling,
    score,
    surface_colours,
    volume_colour,
)
from h2viz.config import MappingConfig
from h2viz.eval.metrics import EvalError

F, W, H, Z = 500.0, 64, 48, 1.0
"""A camera at the origin looking down +z at the plane z = 1 m: one pixel covers 2 mm of it."""
K = np.array([[F, 0.0, (W - 1) / 2], [0.0, F, (H - 1) / 2], [0.0, 0.0, 1.0]])


def _plane_view(colour: np.ndarray, depth: float = Z) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return K, np.eye(4), colour.astype(np.float32), np.full((H, W), depth, np.float32)


def _plane_xy() -> tuple[np.ndarray, np.ndarray]:
    """World x, y (H,W) of every pixel's point on the plane."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return (u - K[0, 2]) / F * Z, (v - K[1, 2]) / F * Z


def _small(**kw: object) -> MappingConfig:
    return MappingConfig().updated(hash_log2_size=14, **kw)  # type: ignore[arg-type]


def test_surface_samples_lie_on_the_plane_under_their_pixels() -> None:
    x, y = _plane_xy()
    rgb = np.stack([np.clip(x * 5 + 0.5, 0, 1), np.clip(y * 5 + 0.5, 0, 1), np.full_like(x, 0.3)], axis=-1)
    view = _plane_view(rgb)
    depth = view[3].copy()
    depth[0, 0] = 0.0  # a hole: its 2x2 block is left out at half resolution
    data = surface_colours([view, (K, view[1], view[2], depth)], downscale=2)
    assert len(data.points) == 2 * (H // 2) * (W // 2) - 1
    assert np.bincount(data.view).tolist() == [(H // 2) * (W // 2), (H // 2) * (W // 2) - 1]
    np.testing.assert_allclose(data.points[:, 2], Z, atol=1e-6)
    # the half-resolution pixel centre sees the middle of its 2x2 block, whose colour is the block's mean
    assert data.points[0, :2] == pytest.approx([(x[0, 0] + x[0, 1]) / 2, (y[0, 0] + y[1, 0]) / 2], abs=1e-6)
    assert data.rgb[0] == pytest.approx(rgb[:2, :2].reshape(-1, 3).mean(axis=0), abs=1e-6)


def test_surface_samples_need_valid_depth() -> None:
    with pytest.raises(EvalError, match="no pixel with valid depth"):
        surface_colours([_plane_view(np.zeros((H, W, 3)), depth=0.0)])


def test_score_pools_samples_and_averages_views() -> None:
    rgb = np.full((4, 3), 0.5, np.float32)
    data = SurfaceColours(np.zeros((4, 3), np.float32), rgb, np.array([0, 0, 0, 1]), np.zeros((2, 3), np.float32))
    pred = rgb.copy()
    pred[3] += 0.1  # view 1 off by 0.1 in every channel, view 0 perfect
    pooled, mean_view = score(pred, data)
    assert pooled == pytest.approx(-10 * math.log10(0.01 / 4), abs=1e-4)  # 26.02 dB
    assert mean_view == pytest.approx((100.0 + 20.0) / 2, abs=1e-3)  # perfect view capped at 100 dB


def test_fit_reproduces_a_smooth_ramp_but_not_texture_finer_than_the_grid() -> None:
    x, y = _plane_xy()
    ramp = np.stack([0.2 + 4 * (x + 0.07), 0.3 + 4 * (y + 0.05), 0.5 - 2 * (x + 0.07)], axis=-1)  # in [0.2, 0.9]
    noise = np.random.default_rng(0).uniform(0, 1, (H, W, 3))  # every 2 mm pixel its own colour
    # the paper's colour grid: finest cell 12.5 mm, six pixels wide here; float32 products, since bfloat16's
    # rounding (where the CPU has it) puts a noise floor near 50 dB under the fit being judged
    cfg = _small(color_precision="float32")
    smooth = fit_colour_ceiling(surface_colours([_plane_view(ramp)]), cfg, steps=300, batch=1024, n_reports=2)
    rough = fit_colour_ceiling(surface_colours([_plane_view(noise)]), cfg, steps=300, batch=1024, n_reports=2)
    assert [p.steps for p in smooth] == [150, 300]
    assert smooth[-1].pooled_psnr_db > 45.0
    assert smooth[-1].pooled_psnr_db >= smooth[0].pooled_psnr_db - 0.5  # no divergence
    # uniform noise has variance 1/12 (10.8 dB around its mean): a 12.5 mm grid can hardly do better
    assert rough[-1].pooled_psnr_db < 13.0
    # a grid whose finest cell (1.6 mm) is finer than a pixel fits much of the same noise
    fine = _small(hash_levels=4, hash_base_resolution_m=0.0125)
    finer = fit_colour_ceiling(surface_colours([_plane_view(noise)]), fine, steps=300, batch=1024, n_reports=1)
    assert finer[-1].pooled_psnr_db > rough[-1].pooled_psnr_db + 5.0


def test_fit_rejects_nonsense_settings() -> None:
    zeros = np.zeros((2, 3), np.float32)
    data = SurfaceColours(zeros, zeros, np.zeros(2, np.int64), zeros[:1])
    with pytest.raises(EvalError, match="must be >= 1"):
        fit_colour_ceiling(data, _small(), steps=0)
    with pytest.raises(EvalError, match="unknown colour loss 'huber'"):
        fit_colour_ceiling(data, _small(), steps=1, loss="huber")
    with pytest.raises(EvalError, match="unknown render 'mesh'"):
        fit_colour_ceiling(data, _small(), steps=1, render="mesh")


def test_mapping_colour_loss_and_volume_rendering_fit_too() -> None:
    x, _ = _plane_xy()
    ramp = np.stack([0.2 + 4 * (x + 0.07)] * 3, axis=-1)
    data = surface_colours([_plane_view(ramp)])
    curve = fit_colour_ceiling(data, _small(), steps=300, batch=1024, loss="l1")
    assert len(curve) == 4 and curve[-1].pooled_psnr_db > 40.0
    rendered = fit_colour_ceiling(data, _small(), steps=300, batch=1024, loss="l1", render="volume")
    assert rendered[-1].pooled_psnr_db > 35.0


def test_volume_colour_of_a_constant_field_is_that_colour_and_reads_around_the_surface() -> None:
    cfg = _small()
    field = colour_field(cfg)
    seen: list[torch.Tensor] = []
    field.color = lambda x: (seen.append(x), torch.full((len(x), 3), 0.25))[1]  # type: ignore[method-assign]
    points = torch.tensor([[0.0, 0.0, 2.0], [1.0, 0.0, 1.0]])
    origins = torch.zeros(2, 3)
    rgb = volume_colour(field, cfg, points, origins, torch.Generator().manual_seed(0))
    assert torch.allclose(rgb, torch.full((2, 3), 0.25))
    dist = torch.linalg.norm(seen[0], dim=1)  # where colour was read: within two sample steps of either surface
    near = torch.minimum((dist - 2.0).abs(), (dist - math.sqrt(2.0)).abs())
    assert len(seen[0]) >= 2 and float(near.max()) < 2 * cfg.sampling.step_m  # the 5 cm band holds 11 samples a ray
