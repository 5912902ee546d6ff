"""The fused rendering + loss kernels against the torch reference (render_weights, live_samples, composite,
mapping_losses): every term and the gradients w.r.t. the SDF and the colours, on ragged rays with holes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from h2viz.config import MappingConfig
from h2viz.errors import ConfigError
from h2viz.mapping.mapper import Mapper
from h2viz.mapping.rendering import losses
from h2viz.mapping.rendering.volume import composite, live_samples, render_weights
from h2viz.mapping.sampling.samples import Samples
from tests.mapping.analytic import Scene, orbit

fused = pytest.importorskip("h2viz.mapping.kernels.loss_numba")


def _batch(seed: int) -> tuple[Samples, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays with 0-40 samples around a surface at their measured depth (some without depth or samples)."""
    rng = np.random.default_rng(seed)
    R = 300
    depth = rng.uniform(0.5, 3.0, R).astype(np.float32)
    depth[rng.random(R) < 0.1] = 0.0  # no measured depth
    counts = rng.integers(0, 41, R)
    counts[:3] = 0
    ray = np.repeat(np.arange(R), counts)
    surface = np.where(depth > 0, depth + rng.normal(0, 0.01, R), 2.0).astype(np.float32)  # (R,)
    t = np.concatenate(
        [np.sort(rng.uniform(max(0.05, surface[r] - 0.3), surface[r] + 0.1, counts[r])) for r in range(R)]
    )
    t = t.astype(np.float32)  # (S,) sorted within each ray
    sdf = ((surface[ray] - t) / 0.05 + rng.normal(0, 0.05, t.size)).astype(np.float32)
    sdf[rng.random(t.size) < 0.02] *= -1  # spurious sign changes
    points = torch.zeros(t.size, 3)
    points[:, 0] = torch.arange(t.size, dtype=torch.float32)  # a sample's point names its row of `colours`
    samples = Samples(points, torch.from_numpy(t), torch.from_numpy(ray), torch.zeros(t.size, dtype=torch.long), R)
    rgb_gt = torch.from_numpy(rng.random((R, 3)).astype(np.float32))
    colours = torch.from_numpy(rng.random((t.size, 3)).astype(np.float32))  # per sample, indexed by position
    return samples, torch.from_numpy(sdf), colours, rgb_gt, torch.from_numpy(depth)


@pytest.mark.parametrize(("seed", "rgb_loss"), [(0, "l1"), (1, "l1"), (2, "l1"), (0, "l2"), (1, "l2")])
def test_fused_render_losses_match_the_torch_reference(seed: int, rgb_loss: str) -> None:
    cfg = MappingConfig().updated(rgb_loss=rgb_loss)
    samples, sdf0, colours, rgb_gt, depth_gt = _batch(seed)
    sdf_ref = sdf0.clone().requires_grad_()
    col_ref = colours.clone().requires_grad_()
    w = render_weights(samples, sdf_ref, cfg.representation.truncation_m, cfg.rendering.render_temperature)
    live = live_samples(samples, w)
    render = composite(samples, w, col_ref[live], live)
    ref = losses.mapping_losses(samples, sdf_ref, render, rgb_gt, depth_gt, cfg)
    ref["total"].backward()

    sdf_fast = sdf0.clone().requires_grad_()
    col_fast = colours.clone().requires_grad_()
    got = fused.mapping_losses(samples, sdf_fast, lambda p: col_fast[p[:, 0].long()], rgb_gt, depth_gt, cfg)
    got["total"].backward()

    for key in ("rgb", "depth", "fs", "sdf", "total"):
        torch.testing.assert_close(got[key], ref[key], rtol=2e-4, atol=1e-6, msg=key)
    assert all(float(ref[k].detach()) > 0 for k in ("rgb", "depth", "fs", "sdf"))
    scale = sdf_ref.grad.abs().max()
    torch.testing.assert_close(sdf_fast.grad / scale, sdf_ref.grad / scale, rtol=1e-3, atol=2e-5)
    torch.testing.assert_close(col_fast.grad, col_ref.grad, rtol=1e-3, atol=1e-7)


def test_a_batch_without_samples_gives_zero_terms() -> None:
    cfg = MappingConfig()
    none = torch.zeros(0, dtype=torch.long)
    empty = Samples(torch.zeros(0, 3), torch.zeros(0), none, none, 4)
    sdf = torch.zeros(0, requires_grad=True)
    got = fused.mapping_losses(empty, sdf, lambda p: torch.zeros(p.shape[0], 3), torch.rand(4, 3), torch.ones(4), cfg)
    assert all(float(v.detach()) == 0.0 for v in got.values())
    got["total"].backward()
    assert sdf.grad.shape == (0,)


@pytest.mark.parametrize(("rgb_loss", "error"), [("l1", 0.1), ("l2", 0.01)])
def test_colour_term_is_the_mean_absolute_or_squared_error(rgb_loss: str, error: float) -> None:
    cfg = MappingConfig().updated(rgb_loss=rgb_loss)
    R = 4  # one sample a ray, on the surface: each ray renders its sample's colour, 0.1 off in every channel
    samples = Samples(torch.zeros(R, 3), torch.ones(R), torch.arange(R), torch.zeros(R, dtype=torch.long), R)
    colours = torch.full((R, 3), 0.5)
    rgb_gt = colours + torch.tensor([0.1, -0.1, 0.1])
    sdf = torch.zeros(R)
    got = fused.mapping_losses(samples, sdf, lambda p: colours[: len(p)], rgb_gt, torch.ones(R), cfg)
    w = render_weights(samples, sdf, cfg.representation.truncation_m, cfg.rendering.render_temperature)
    ref = losses.mapping_losses(samples, sdf, composite(samples, w, colours), rgb_gt, torch.ones(R), cfg)
    assert float(got["rgb"]) == pytest.approx(cfg.losses.w_rgb * error, rel=1e-5)
    assert float(ref["rgb"]) == pytest.approx(cfg.losses.w_rgb * error, rel=1e-5)


def test_an_unknown_colour_loss_is_refused_by_name() -> None:
    with pytest.raises(ConfigError, match="mapping.losses.rgb_loss: unknown 'huber'"):
        losses.check_color_settings("huber")


def test_colour_supervision_is_checked_by_name_and_needs_a_colour_source() -> None:
    with pytest.raises(ConfigError, match="mapping.losses.color_supervision: unknown 'pixels'"):
        losses.check_color_settings("l2", "pixels")
    with pytest.raises(ConfigError, match="color_prior is false"):
        losses.check_color_settings("l2", "none", color_prior=False)
    for supervision in ("none", "surface", "volume"):
        losses.check_color_settings("l2", supervision, color_prior=True)


@pytest.mark.parametrize("supervision", ["none", "surface", "volume"])
def test_each_colour_supervision_trains_the_colour_branch_only_when_asked(supervision: str) -> None:
    scene = Scene("plane")
    cfg = MappingConfig().updated(device="cpu", min_points_per_voxel=3, rays_per_iter=512, hash_log2_size=12,
    max_iters=2,
                        color_rays_per_iter=512, color_supervision=supervision)  # fmt: skip
    mapper = Mapper(cfg)
    before = mapper.field.color_grid.tables.detach().clone()
    for i, T in enumerate(orbit(scene, 2, 0.5, 1.0, np.zeros(3))):
        stats = mapper.integrate(scene.frame(i, T))
    moved = not torch.equal(before, mapper.field.color_grid.tables.detach())
    assert moved == (supervision != "none")
    assert (stats.losses["rgb"] > 0) == (supervision != "none")
