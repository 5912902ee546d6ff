"""Render the field at any camera: rgb, depth, normal or prior-only depth, in ray chunks without gradients.

With priors enabled, samples whose prior lies further than `band` truncation units from the surface are
dropped before the networks run: their rendering weight sigmoid(s)*sigmoid(-s) is negligible.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from h2viz.mapping.field import HybridField
from h2viz.mapping.octree import VoxelOctree
from h2viz.mapping.rays import pixel_rays
from h2viz.mapping.rendering import composite, render_weights
from h2viz.mapping.sampling import sample_rays

MODES = ("rgb", "depth", "normal", "prior")


@dataclass(frozen=True)
class RenderParams:
    t_far: float  # metres along the camera axis
    step_m: float
    truncation_m: float
    temperature: float
    band: float | None  # keep samples with |prior| < band (truncation units); None keeps all


def locate(octree: VoxelOctree, points: torch.Tensor) -> torch.Tensor:
    """Voxel ids (N,) of points (N,3), also accepting points on the outer face of an allocated voxel
    (up to rounding in either direction), -1 elsewhere."""
    ids = octree.lookup_points(points)
    eps = 1e-4 * octree.voxel_size_m
    for code in range(27):
        missing = ids < 0
        if not bool(missing.any()):
            break
        shift = (torch.tensor([code // 9, code // 3 % 3, code % 3], device=points.device) - 1) * eps
        ids[missing] = octree.lookup_points(points[missing] + shift)
    return ids


def sdf_gradient(field: HybridField, points: torch.Tensor, voxel: torch.Tensor) -> torch.Tensor:
    """Unit normals (N,3) as the normalised SDF gradient."""
    with torch.enable_grad():
        p = points.detach().requires_grad_(True)
        (grad,) = torch.autograd.grad(field.sdf(p, voxel).sum(), p)
    return torch.nn.functional.normalize(grad, dim=1)


@torch.no_grad()
def render_rays(
    field: HybridField,
    octree: VoxelOctree,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    mode: str,
    params: RenderParams,
) -> torch.Tensor:
    """Render R rays: (R,3) for rgb/normal, (R,) for depth/prior."""
    R = origins.shape[0]
    t_far = torch.full((R,), params.t_far, device=origins.device)
    samples = sample_rays(octree, origins, dirs, t_far, params.step_m, False)
    prior = field.prior_sdf(samples.points, samples.voxel)
    if params.band is not None:
        keep = prior.abs() < params.band
        samples, prior = samples.select(keep), prior[keep]
    sdf = prior if mode == "prior" else field.sdf(samples.points, samples.voxel)
    weights = render_weights(samples, sdf, params.truncation_m, params.temperature)
    rgb = field.color(samples.points[weights > 0]) if mode == "rgb" else None
    if rgb is not None:
        samples, weights = samples.select(weights > 0), weights[weights > 0]
    out = composite(samples, weights, rgb)
    if mode == "rgb":
        return out.rgb
    if mode != "normal":
        return out.depth
    normals = torch.zeros(R, 3, device=origins.device)
    if bool(out.hit.any()):
        pts = origins[out.hit] + dirs[out.hit] * out.depth[out.hit, None]
        vid = locate(octree, pts)
        ok = vid >= 0
        n = torch.zeros_like(pts)
        n[ok] = sdf_gradient(field, pts[ok], vid[ok])
        normals[out.hit] = n
    return normals


def render_image(
    field: HybridField,
    octree: VoxelOctree,
    K: np.ndarray,
    T_world_camera: np.ndarray,
    height: int,
    width: int,
    mode: str,
    params: RenderParams,
    chunk: int = 16384,
) -> np.ndarray:
    """(H,W,3) float32 rgb in [0,1] / normals in [-1,1], or (H,W) float32 depth in metres (0 = nothing)."""
    if mode not in MODES:
        raise ValueError(f"render mode '{mode}' is not one of {', '.join(MODES)}")
    dev = field.priors.device
    origins, dirs = pixel_rays(K, T_world_camera, height, width, dev)
    if octree.n_voxels == 0:
        parts = [
            torch.zeros(origins.shape[0], 3) if mode in ("rgb", "normal") else torch.zeros(origins.shape[0])
        ]
    else:
        parts = [
            render_rays(field, octree, origins[i : i + chunk], dirs[i : i + chunk], mode, params)
            for i in range(0, origins.shape[0], chunk)
        ]
    img = torch.cat(parts).float().cpu().numpy()
    return img.reshape(height, width, -1) if img.ndim == 2 else img.reshape(height, width)
