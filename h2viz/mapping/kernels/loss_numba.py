"""Fused CPU kernels (numba) of SDF-based volume rendering and the four mapping losses, with a hand-written
backward; `rendering.render_weights`, `rendering.live_samples`, `rendering.composite` and
`losses.mapping_losses` are the torch reference, whose values and gradients these reproduce.

Through torch, rendering and the losses are some forty small passes over the (S,) samples and their backward
twins, about 10 ms an iteration on the CPU; here samples are visited ray by ray (they are sorted by ray, then
by t) in three parallel passes: weights and the live set, the rendered depth and colour with the loss terms,
and the gradients w.r.t. the SDF (S,) and the live samples' colour (S',3).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from h2viz.config import MappingConfig
from h2viz.mapping.kernels.jit import njit, parallel_region
from h2viz.mapping.rendering.volume import LIVE_SHARE
from h2viz.mapping.sampling.samples import Samples

TERMS = ("rgb", "depth", "fs", "sdf")
"""Loss terms in the order the kernels hold them."""


@njit(inline=True)
def _sigmoid(a: float) -> float:
    return 1.0 / (1.0 + math.exp(-a))


@njit(parallel=True)
def _weights_kernel(
    t: np.ndarray, sdf: np.ndarray, offsets: np.ndarray, tr: float, tau: float, share: float,
    w: np.ndarray, wsum: np.ndarray, live: np.ndarray,
) -> None:  # fmt: skip
    """Render weights w (S,) (zero beyond the first sign change + tr), their sum per ray (R,) and the live mask
    (S,): samples holding at least `share` of their ray's weight."""
    for r in numba.prange(offsets.shape[0] - 1):
        lo, hi = offsets[r], offsets[r + 1]
        t_cross = np.inf
        for j in range(lo, hi):
            if sdf[j] < 0:
                t_cross = t[j]
                break
        total = np.float32(0.0)
        for j in range(lo, hi):
            if t[j] <= t_cross + tr:
                a = sdf[j] / tau
                w[j] = _sigmoid(a) * _sigmoid(-a)
            else:
                w[j] = 0.0
            total += w[j]
        wsum[r] = total
        for j in range(lo, hi):
            live[j] = w[j] >= share * total


@njit(parallel=True)
def _render_kernel(
    t: np.ndarray, sdf: np.ndarray, offsets: np.ndarray, w: np.ndarray, wsum: np.ndarray,
    live_offsets: np.ndarray, rgb: np.ndarray, live_ids: np.ndarray, rgb_gt: np.ndarray, depth_gt: np.ndarray,
    tr: float, squared: bool, depth: np.ndarray, color: np.ndarray, live_sum: np.ndarray, per_ray: np.ndarray,
) -> None:  # fmt: skip
    """Per ray: rendered depth (R,) and colour (R,3) over live samples (live ids (S',) into the samples, their
    colours rgb (S',3), live_offsets (R+1,)), live weight sum (R,), and per_ray (R,8) partial loss sums: rgb
    error sum (absolute, or squared when `squared`), depth L1, free-space mean, SDF mean, and the counts of hit
    rays, depth rays, fs rays, SDF rays."""
    for r in numba.prange(offsets.shape[0] - 1):
        lo, hi = offsets[r], offsets[r + 1]
        d = depth_gt[r]
        total = wsum[r]
        hit = total > 1e-8
        acc_t = 0.0
        fs, n_fs, band, n_band = 0.0, 0, 0.0, 0
        for j in range(lo, hi):
            acc_t += w[j] * t[j]
            if d > 0:
                if t[j] < d - tr:
                    fs += (sdf[j] - 1.0) ** 2
                    n_fs += 1
                elif t[j] <= d + tr:
                    band += (t[j] + sdf[j] * tr - d) ** 2
                    n_band += 1
        depth[r] = acc_t / total if hit else 0.0
        lsum = 0.0
        c0, c1, c2 = 0.0, 0.0, 0.0
        for k in range(live_offsets[r], live_offsets[r + 1]):
            wk = w[live_ids[k]]
            lsum += wk
            c0 += wk * rgb[k, 0]
            c1 += wk * rgb[k, 1]
            c2 += wk * rgb[k, 2]
        norm = lsum if lsum > 1e-12 else 1.0
        live_sum[r] = lsum
        color[r, 0], color[r, 1], color[r, 2] = c0 / norm, c1 / norm, c2 / norm
        for c in range(8):
            per_ray[r, c] = 0.0
        if hit:
            for c in range(3):
                e = color[r, c] - rgb_gt[r, c]
                per_ray[r, 0] += e * e if squared else abs(e)
            per_ray[r, 4] = 1.0
            if d > 0:
                per_ray[r, 1] = abs(depth[r] - d)
                per_ray[r, 5] = 1.0
        if n_fs:
            per_ray[r, 2] = fs / n_fs
            per_ray[r, 6] = 1.0
        if n_band:
            per_ray[r, 3] = band / n_band
            per_ray[r, 7] = 1.0


@njit(inline=True)
def _error_slope(e: float, squared: bool) -> float:
    """d/de of the colour error: |e| -> sign(e), e^2 -> 2e."""
    return 2.0 * e if squared else np.sign(e)


@njit(parallel=True)
def _backward_kernel(
    t: np.ndarray, sdf: np.ndarray, offsets: np.ndarray, w: np.ndarray, wsum: np.ndarray,
    live_offsets: np.ndarray, rgb: np.ndarray, live_ids: np.ndarray, rgb_gt: np.ndarray, depth_gt: np.ndarray,
    tr: float, tau: float, squared: bool, depth: np.ndarray, color: np.ndarray, live_sum: np.ndarray,
    coef: np.ndarray, g_sdf: np.ndarray, g_rgb: np.ndarray, g_w: np.ndarray,
) -> None:  # fmt: skip
    """Gradients w.r.t. sdf (S,) and the live colours (S',3) of sum_k coef[k] * term_k, where coef holds each
    term's upstream gradient times its weight, already divided by its normalising count; g_w (S,) is scratch."""
    c_rgb, c_depth, c_fs, c_sdf = coef[0], coef[1], coef[2], coef[3]
    for r in numba.prange(offsets.shape[0] - 1):
        lo, hi = offsets[r], offsets[r + 1]
        d = depth_gt[r]
        total = wsum[r]
        hit = total > 1e-8
        n_fs, n_band = 0, 0
        for j in range(lo, hi):
            g_w[j] = 0.0
            g_sdf[j] = 0.0
            if d > 0:
                if t[j] < d - tr:
                    n_fs += 1
                elif t[j] <= d + tr:
                    n_band += 1
        if hit and d > 0:  # depth L1 through the normalised weighted mean of t
            e = c_depth * np.sign(depth[r] - d) / total
            for j in range(lo, hi):
                g_w[j] += e * (t[j] - depth[r])
        if hit:  # colour error through the live samples' normalised weighted mean
            lsum = live_sum[r]
            norm = lsum if lsum > 1e-12 else 1.0
            e0 = c_rgb * _error_slope(color[r, 0] - rgb_gt[r, 0], squared) / norm
            e1 = c_rgb * _error_slope(color[r, 1] - rgb_gt[r, 1], squared) / norm
            e2 = c_rgb * _error_slope(color[r, 2] - rgb_gt[r, 2], squared) / norm
            for k in range(live_offsets[r], live_offsets[r + 1]):
                j = live_ids[k]
                g_rgb[k, 0], g_rgb[k, 1], g_rgb[k, 2] = e0 * w[j], e1 * w[j], e2 * w[j]
                g_w[j] += (
                    e0 * (rgb[k, 0] - color[r, 0]) + e1 * (rgb[k, 1] - color[r, 1]) + e2 * (rgb[k, 2] - color[r, 2])
                )
        else:
            for k in range(live_offsets[r], live_offsets[r + 1]):
                g_rgb[k, 0], g_rgb[k, 1], g_rgb[k, 2] = 0.0, 0.0, 0.0
        for j in range(lo, hi):
            s = sdf[j]
            if w[j] > 0:  # w = sig(a) sig(-a), a = s / tau: dw/ds = w (sig(-a) - sig(a)) / tau
                a = s / tau
                g_sdf[j] += g_w[j] * w[j] * (_sigmoid(-a) - _sigmoid(a)) / tau
            if d > 0:
                if t[j] < d - tr:
                    g_sdf[j] += c_fs * 2.0 * (s - 1.0) / n_fs
                elif t[j] <= d + tr:
                    g_sdf[j] += c_sdf * 2.0 * (t[j] + s * tr - d) * tr / n_band


@dataclass
class Rendered:
    """What the forward pass keeps for the backward pass (NumPy views of CPU tensors)."""

    t: np.ndarray  # (S,)
    sdf: np.ndarray  # (S,) truncation units
    offsets: np.ndarray  # (R+1,) first sample of each ray
    w: np.ndarray  # (S,) render weights
    wsum: np.ndarray  # (R,)
    live_ids: np.ndarray  # (S',) samples that colour is evaluated at
    live_offsets: np.ndarray  # (R+1,)


def render_weights(samples: Samples, sdf: Tensor, cfg: MappingConfig) -> Rendered:
    """Weights and live samples of a batch (no gradient); `sdf` (S,) detached, in truncation units."""
    t = samples.t.detach().contiguous().numpy()
    s = sdf.detach().contiguous().numpy()
    ray = samples.ray.numpy()
    offsets = np.zeros(samples.n_rays + 1, np.int64)
    np.cumsum(np.bincount(ray, minlength=samples.n_rays), out=offsets[1:])
    w = np.empty_like(s)
    wsum = np.empty(samples.n_rays, np.float32)
    live = np.empty(s.shape[0], np.bool_)
    with parallel_region():
        _weights_kernel(
            t, s, offsets, cfg.representation.truncation_m, cfg.rendering.render_temperature, LIVE_SHARE, w, wsum, live
        )
    live_ids = np.flatnonzero(live)
    live_offsets = np.zeros_like(offsets)
    np.cumsum(np.bincount(ray[live_ids], minlength=samples.n_rays), out=live_offsets[1:])
    return Rendered(t, s, offsets, w, wsum, live_ids, live_offsets)


class _RenderLosses(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx: Any, sdf: Tensor, rgb: Tensor, rendered: Rendered, rgb_gt: Tensor, depth_gt: Tensor, cfg: MappingConfig
    ) -> Tensor:
        """sdf (S,), live colours rgb (S',3) -> weighted terms (4,) in TERMS order."""
        R = rendered.wsum.shape[0]
        rgb_np = rgb.detach().contiguous().numpy()
        gt = rgb_gt.detach().contiguous().numpy()
        dgt = depth_gt.detach().contiguous().numpy()
        depth, color = np.empty(R, np.float32), np.empty((R, 3), np.float32)
        live_sum, per_ray = np.empty(R, np.float32), np.empty((R, 8), np.float32)
        with parallel_region():
            _render_kernel(
                rendered.t, rendered.sdf, rendered.offsets, rendered.w, rendered.wsum, rendered.live_offsets,
                rgb_np, rendered.live_ids, gt, dgt, cfg.representation.truncation_m, cfg.losses.rgb_loss == "l2",
                depth, color, live_sum,
                per_ray,
            )  # fmt: skip
        sums = per_ray.sum(0, dtype=np.float64)
        counts = np.maximum(sums[4:], 1.0) * np.array([3.0, 1.0, 1.0, 1.0])  # colour averages 3 channels
        weights = np.array([cfg.losses.w_rgb, cfg.losses.w_depth, cfg.losses.w_fs, cfg.losses.w_sdf])
        ctx.rendered, ctx.cfg, ctx.arrays = rendered, cfg, (rgb_np, gt, dgt, depth, color, live_sum)
        ctx.scale = weights / counts  # d(term_k)/d(per-ray sum_k)
        return torch.from_numpy((sums[:4] * ctx.scale).astype(np.float32))

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad_terms: Tensor) -> tuple[Tensor | None, ...]:
        """grad_terms (4,) -> gradients w.r.t. sdf (S,) and rgb (S',3)."""
        rendered, cfg = ctx.rendered, ctx.cfg
        rgb_np, gt, dgt, depth, color, live_sum = ctx.arrays
        coef = (grad_terms.double().numpy() * ctx.scale).astype(np.float32)
        g_sdf = np.empty_like(rendered.sdf)
        g_rgb = np.empty_like(rgb_np)
        g_w = np.empty_like(rendered.sdf)
        with parallel_region():
            _backward_kernel(
                rendered.t, rendered.sdf, rendered.offsets, rendered.w, rendered.wsum, rendered.live_offsets,
                rgb_np, rendered.live_ids, gt, dgt, cfg.representation.truncation_m, cfg.rendering.render_temperature,
                cfg.losses.rgb_loss == "l2",
                depth, color, live_sum, coef, g_sdf, g_rgb, g_w,
            )  # fmt: skip
        return torch.from_numpy(g_sdf), torch.from_numpy(g_rgb), None, None, None, None


def mapping_losses(
    samples: Samples,
    sdf: Tensor,
    color: Callable[[Tensor], Tensor],
    rgb_gt: Tensor,
    depth_gt: Tensor,
    cfg: MappingConfig,
) -> dict[str, Tensor]:
    """The weighted loss terms and their sum, as `losses.mapping_losses` after rendering with the torch functions:
    sdf (S,) in tr units (differentiable), `color` maps points (S',3) to RGB (S',3) and runs on the live samples
    only, rgb_gt (R,3) in [0,1], depth_gt (R,) metres. CPU float32 tensors."""
    rendered = render_weights(samples, sdf, cfg)
    rgb = color(samples.points[torch.from_numpy(rendered.live_ids)])  # (S',3)
    terms = _RenderLosses.apply(sdf, rgb, rendered, rgb_gt, depth_gt, cfg)
    out = dict(zip(TERMS, terms.unbind(0), strict=True))
    out["total"] = terms.sum()
    return out
