"""SDF-based volume rendering over ragged samples.

w = sigmoid(s / tau) * sigmoid(-s / tau) with s the SDF in truncation units and tau = `temperature`
(the truncation distance's value, 0.05, as in the reference implementation, which divides the already
truncation-normalised SDF by tr once more: a bell a few millimetres wide around the surface). Weights beyond
the first sign change + tr are zeroed, then normalised per ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from h2viz.mapping.sampling.samples import Samples


@dataclass
class RayRender:
    depth: torch.Tensor  # (R,) weighted mean t, 0 where the ray has no weight
    rgb: torch.Tensor  # (R,3)
    weight_sum: torch.Tensor  # (R,) before normalisation
    hit: torch.Tensor  # (R,) bool: the ray has samples with weight


def segment_sum(values: torch.Tensor, ray: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Sum per ray of values (S,) or (S,C) -> (R,) or (R,C)."""
    out = values.new_zeros((n_rays, *values.shape[1:]))
    return out.index_add_(0, ray, values)


def first_crossing(t: torch.Tensor, sdf: torch.Tensor, ray: torch.Tensor, n_rays: int) -> torch.Tensor:
    """t of the first sample with negative SDF on each ray (R,), +inf when none."""
    t_neg = torch.where(sdf < 0, t, torch.full_like(t, float("inf")))
    out = torch.full((n_rays,), float("inf"), device=t.device, dtype=t.dtype)
    return out.scatter_reduce(0, ray, t_neg, reduce="amin")


def render_weights(samples: Samples, sdf: torch.Tensor, truncation_m: float, temperature: float) -> torch.Tensor:
    """Unnormalised weights (S,) with samples beyond the first surface + tr removed."""
    w = torch.sigmoid(sdf / temperature) * torch.sigmoid(-sdf / temperature)
    t_cross = first_crossing(samples.t.detach(), sdf.detach(), samples.ray, samples.n_rays)
    return w * (samples.t <= t_cross[samples.ray] + truncation_m).to(w.dtype)


def composite(
    samples: Samples, weights: torch.Tensor, rgb: torch.Tensor | None, rgb_index: torch.Tensor | None = None
) -> RayRender:
    """Normalised weighted sums of t and colour per ray. rgb is (S,3), or (S',3) for the samples rgb_index (S',)
    when colour was evaluated only where the weights are not negligible (then normalised over those)."""
    R = samples.n_rays
    wsum = segment_sum(weights, samples.ray, R)  # (R,)
    hit = wsum > 1e-8
    norm = torch.where(hit, wsum, torch.ones_like(wsum))
    depth = segment_sum(weights * samples.t, samples.ray, R) / norm
    if rgb is None:
        color = torch.zeros(R, 3, device=weights.device)
    elif rgb_index is None:
        color = segment_sum(weights[:, None] * rgb, samples.ray, R) / norm[:, None]
    else:
        w_live = weights[rgb_index]  # (S',)
        live_sum = segment_sum(w_live, samples.ray[rgb_index], R)
        live_norm = torch.where(live_sum > 1e-12, live_sum, torch.ones_like(live_sum))
        color = segment_sum(w_live[:, None] * rgb, samples.ray[rgb_index], R) / live_norm[:, None]
    return RayRender(depth=depth * hit, rgb=color, weight_sum=wsum, hit=hit)


LIVE_SHARE = 1e-2
"""Samples holding less than this share of their ray's weight are left out of its colour (on the synthetic
room they carry 0.5 % of the weight in all, and colour is averaged over the samples kept): the colour
network runs on ~2/3 of the samples it would otherwise need."""


def live_samples(samples: Samples, weights: torch.Tensor) -> torch.Tensor:
    """Indices (S',) of samples whose weight (S,) is at least LIVE_SHARE of their ray's total."""
    w = weights.detach()
    total = segment_sum(w, samples.ray, samples.n_rays)  # (R,)
    return torch.nonzero(w >= LIVE_SHARE * total[samples.ray])[:, 0]


@dataclass
class SurfaceHits:
    """Where rays cross the zero level set of the SDF, from outside (positive) to inside (negative)."""

    ray: torch.Tensor  # (C,) ray of each crossing, non-decreasing
    t: torch.Tensor  # (C,) depth of the crossing along the ray (linear interpolation between two samples)
    points: torch.Tensor  # (C,3) world position of the crossing


def surface_crossings(samples: Samples, sdf: torch.Tensor, max_gap_m: float) -> SurfaceHits:
    """Every sign change + -> - of the SDF (S,) between two consecutive samples of a ray at most `max_gap_m` apart
    in t, in ray-major, front-to-back order. Samples further apart (a gap in the allocated voxels, a sample the
    render search skipped) bound no crossing: nothing was evaluated between them."""
    s0, s1 = sdf[:-1], sdf[1:]
    pair = (samples.ray[:-1] == samples.ray[1:]) & (samples.t[1:] - samples.t[:-1] <= max_gap_m)
    j = torch.nonzero(pair & (s0 >= 0) & (s1 < 0))[:, 0]  # (C,) first sample of each crossing pair
    frac = (s0[j] / (s0[j] - s1[j])).clamp(0.0, 1.0)[:, None]  # (C,1)
    t = samples.t[j] + frac[:, 0] * (samples.t[j + 1] - samples.t[j])
    points = samples.points[j] + frac * (samples.points[j + 1] - samples.points[j])
    return SurfaceHits(samples.ray[j], t, points)


def first_hit(hits: SurfaceHits, keep: torch.Tensor, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The first crossing per ray among those with keep (C,) True: (index into hits (R,), hit (R,) bool)."""
    order = torch.arange(hits.t.numel(), device=hits.t.device)
    big = torch.full_like(order, hits.t.numel())
    first = torch.full((n_rays,), hits.t.numel(), dtype=order.dtype, device=order.device)
    first = first.scatter_reduce(0, hits.ray, torch.where(keep, order, big), reduce="amin")
    hit = first < hits.t.numel()
    return torch.where(hit, first, torch.zeros_like(first)), hit
