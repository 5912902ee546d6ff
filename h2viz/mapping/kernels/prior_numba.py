"""Fused CPU kernel (numba) of the trilinear corner prior, `HybridField.prior_sdf`'s torch code the reference.

The torch version gathers an (N,8) block of corner values and blends it through a dozen (N,2,2,2)
temporaries that autograd keeps; here one pass reads each point's 8 corners and blends them, and the
backward pass adds each point's upstream gradient, times its 8 weights, into the corner gradient (one thread:
corners are shared between points, and the pass is a small part of a step).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from h2viz.mapping.kernels.jit import njit, parallel_region


@njit(inline=True)
def _weights(points: np.ndarray, p: int, origin: np.ndarray, v: int, inv_vs: np.float32) -> tuple[Any, Any, Any]:
    """In-voxel coordinates of point p in voxel v, clamped to [0, 1]."""
    x = min(max((points[p, 0] - origin[v, 0]) * inv_vs, np.float32(0.0)), np.float32(1.0))
    y = min(max((points[p, 1] - origin[v, 1]) * inv_vs, np.float32(0.0)), np.float32(1.0))
    z = min(max((points[p, 2] - origin[v, 2]) * inv_vs, np.float32(0.0)), np.float32(1.0))
    return x, y, z


@njit
def blend_range(
    points: np.ndarray,
    voxel: np.ndarray,
    origin: np.ndarray,
    corners: np.ndarray,
    priors: np.ndarray,
    inv_vs: float,
    start: int,
    stop: int,
    out: np.ndarray,
) -> None:
    """out[start:stop] <- trilinear blend of the corner priors (C,) (corner order 4x+2y+z) at points (N,3) in
    voxels (N,); one thread (the meshing thread calls it for whole batches)."""
    s = np.float32(inv_vs)
    one = np.float32(1.0)
    for p in range(start, stop):
        v = voxel[p]
        x, y, z = _weights(points, p, origin, v, s)
        c = corners[v]
        v00 = priors[c[0]] * (one - z) + priors[c[1]] * z
        v01 = priors[c[2]] * (one - z) + priors[c[3]] * z
        v10 = priors[c[4]] * (one - z) + priors[c[5]] * z
        v11 = priors[c[6]] * (one - z) + priors[c[7]] * z
        out[p] = (v00 * (one - y) + v01 * y) * (one - x) + (v10 * (one - y) + v11 * y) * x


@njit(parallel=True)
def _forward_kernel(
    points: np.ndarray,
    voxel: np.ndarray,
    origin: np.ndarray,
    corners: np.ndarray,
    priors: np.ndarray,
    inv_vs: float,
    n_blocks: int,
    out: np.ndarray,
) -> None:
    """out (N,) <- `blend_range` over blocks of points in parallel."""
    n = points.shape[0]
    for block in numba.prange(n_blocks):
        blend_range(
            points, voxel, origin, corners, priors, inv_vs, block * n // n_blocks, (block + 1) * n // n_blocks, out
        )


@njit
def _backward_kernel(
    points: np.ndarray,
    voxel: np.ndarray,
    origin: np.ndarray,
    corners: np.ndarray,
    grad_out: np.ndarray,
    inv_vs: float,
    grad: np.ndarray,
) -> None:
    """grad (C,) <- zeros, then every point's upstream gradient spread onto its voxel's 8 corners."""
    grad[:] = 0.0
    s = np.float32(inv_vs)
    for p in range(points.shape[0]):
        v = voxel[p]
        x, y, z = _weights(points, p, origin, v, s)
        g = grad_out[p]
        c = corners[v]
        one = np.float32(1.0)
        for k in range(8):
            wx = x if k & 4 else one - x
            wy = y if k & 2 else one - y
            wz = z if k & 1 else one - z
            grad[c[k]] += g * wx * wy * wz


class _FusedPrior(torch.autograd.Function):
    """Trilinear corner prior, differentiable w.r.t. the priors only."""

    @staticmethod
    def forward(
        ctx: Any, priors: Tensor, points: Tensor, voxel: Tensor, origin: Tensor, corners: Tensor, voxel_size_m: float
    ) -> Tensor:
        """priors (C,), points (N,3), voxel (N,), origin (V,3), corners (V,8) -> (N,)."""
        args = (
            points.detach().contiguous().numpy(),
            voxel.contiguous().numpy(),
            origin.contiguous().numpy(),
            corners.contiguous().numpy(),
        )
        out = torch.empty(points.shape[0], dtype=torch.float32)
        with parallel_region() as n_blocks:
            _forward_kernel(*args, priors.detach().contiguous().numpy(), 1.0 / voxel_size_m, n_blocks, out.numpy())
        ctx.args, ctx.inv_vs, ctx.n_priors = args, 1.0 / voxel_size_m, priors.shape[0]
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, ...]:
        grad = torch.empty(ctx.n_priors, dtype=torch.float32)
        _backward_kernel(*ctx.args, grad_out.float().contiguous().numpy(), ctx.inv_vs, grad.numpy())
        return grad, None, None, None, None, None


def fused_prior(
    priors: Tensor, points: Tensor, voxel: Tensor, origin: Tensor, corners: Tensor, voxel_size_m: float
) -> Tensor:
    """Trilinear prior (N,) at CPU float32 points (N,3) in voxels (N,); gradients reach `priors` (C,)."""
    return _FusedPrior.apply(priors, points, voxel, origin, corners, voxel_size_m)
