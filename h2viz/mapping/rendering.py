"""SDF-based volume rendering over ragged samples.

w = sigmoid(s / tau) * sigmoid(-s / tau) with s the SDF in truncation units and tau = `temperature`
(the truncation distance's value, 0.05, as in the reference implementation, which divides the already
truncation-normalised SDF by tr once more: a bell a few millimetres wide around the surface). Weights beyond
the first sign change + tr are zeroed, then normalised per ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from h2viz.mapping.sampling import Samples


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
