"""SDF volume rendering: the weights' bell, the first-surface cut, and colour on live samples only."""

from __future__ import annotations

import torch

from h2viz.mapping.rendering.volume import composite, live_samples, render_weights
from h2viz.mapping.sampling.samples import Samples

TR = 0.05


def ray_through_plane(depths: list[float], step_m: float = 0.01) -> tuple[Samples, torch.Tensor]:
    """Samples every step along R rays hitting a plane at the given depths, and their exact SDF (tr units)."""
    ts, rays = [], []
    for r, d in enumerate(depths):
        t = torch.arange(0.3, d + 0.2, step_m)
        ts.append(t)
        rays.append(torch.full_like(t, r, dtype=torch.long))
    t = torch.cat(ts)
    ray = torch.cat(rays)
    depth = torch.tensor(depths)[ray]
    sdf = (depth - t) / TR
    points = torch.stack([torch.zeros_like(t), torch.zeros_like(t), t], 1)
    return Samples(points, t, ray, torch.zeros_like(ray), len(depths)), sdf


def test_rendered_depth_is_the_plane_depth() -> None:
    samples, sdf = ray_through_plane([1.0, 1.537, 2.2])
    out = composite(samples, render_weights(samples, sdf, TR, 0.05), None)
    torch.testing.assert_close(out.depth, torch.tensor([1.0, 1.537, 2.2]), atol=1e-3, rtol=0)
    assert bool(out.hit.all())


def test_a_second_surface_behind_the_first_is_cut() -> None:
    samples, sdf = ray_through_plane([1.0])
    behind = samples.t > 1.1
    sdf = torch.where(behind, (1.15 - samples.t).abs() / TR * torch.sign(1.15 - samples.t), sdf)
    out = composite(samples, render_weights(samples, sdf, TR, 0.05), None)
    assert abs(float(out.depth[0]) - 1.0) < 2e-3


def test_colour_on_live_samples_equals_colour_on_all() -> None:
    samples, sdf = ray_through_plane([1.0, 1.537, 2.2])
    weights = render_weights(samples, sdf, TR, 0.05)
    rgb = torch.rand(samples.t.shape[0], 3, generator=torch.Generator().manual_seed(0))
    live = live_samples(samples, weights)
    assert 0 < live.numel() < samples.t.numel() // 4  # most samples are skipped
    full = composite(samples, weights, rgb)
    part = composite(samples, weights, rgb[live], live)
    torch.testing.assert_close(part.rgb, full.rgb, atol=1e-2, rtol=0)  # the left-out samples weigh < 1 % each
    grey = composite(samples, weights, torch.full((live.numel(), 3), 0.3), live)
    torch.testing.assert_close(grey.rgb, torch.full_like(grey.rgb, 0.3))  # normalised over the live samples
    torch.testing.assert_close(part.depth, full.depth)
