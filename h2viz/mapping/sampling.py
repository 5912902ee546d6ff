"""Ray samples inside allocated leaf voxels: voxel traversal (3-D DDA) plus fixed-step samples.

Rays use z-normalised directions (camera z of the direction = 1), so a sample's parameter t is its depth
along the camera axis and compares directly with depth images.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from h2viz.mapping.kernels import kernel_module
from h2viz.mapping.octree import VoxelOctree
from h2viz.mapping.raymarch import voxel_hits


@dataclass
class Samples:
    """Ragged samples of R rays, sorted by ray then by t."""

    points: torch.Tensor  # (S,3) world metres
    t: torch.Tensor  # (S,) depth along the ray (camera z)
    ray: torch.Tensor  # (S,) ray index, non-decreasing
    voxel: torch.Tensor  # (S,) leaf voxel id
    n_rays: int

    def select(self, keep: torch.Tensor) -> Samples:
        return Samples(self.points[keep], self.t[keep], self.ray[keep], self.voxel[keep], self.n_rays)


@dataclass
class Hits:
    """Ray/voxel intersections (H hits), in ray-major, front-to-back order."""

    ray: torch.Tensor  # (H,)
    voxel: torch.Tensor  # (H,)
    t_in: torch.Tensor  # (H,)
    t_out: torch.Tensor  # (H,)


def traverse(
    octree: VoxelOctree, origins: torch.Tensor, dirs: torch.Tensor, t_near: torch.Tensor, t_far: torch.Tensor
) -> Hits:
    """Allocated voxels crossed by each ray between t_near and t_far (R,): an exact voxel walk per ray that
    jumps over empty space (numba, see h2viz.mapping.raymarch)."""
    return Hits(*voxel_hits(octree, origins, dirs, t_near, t_far))


def sample_hits(hits: Hits, origins: torch.Tensor, dirs: torch.Tensor, step_m: float, jitter: bool) -> Samples:
    """Samples every `step_m` (in t) inside each hit segment; stratified jitter when training."""
    length = hits.t_out - hits.t_in  # (H,)
    counts = torch.ceil(length / step_m).long().clamp(min=1)  # (H,)
    hit_of = torch.repeat_interleave(torch.arange(counts.numel(), device=counts.device), counts)  # (S,)
    first = torch.cumsum(counts, 0) - counts
    k = torch.arange(hit_of.numel(), device=counts.device) - first[hit_of]  # (S,) index within the hit
    offset = torch.rand(k.shape, device=k.device) if jitter else torch.full(k.shape, 0.5, device=k.device)
    t = torch.minimum(hits.t_in[hit_of] + (k + offset) * step_m, hits.t_out[hit_of])
    ray = hits.ray[hit_of]
    points = origins[ray] + dirs[ray] * t[:, None]
    return Samples(points, t, ray, hits.voxel[hit_of], origins.shape[0])


def sample_rays(
    octree: VoxelOctree,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    t_far: torch.Tensor,
    step_m: float,
    jitter: bool,
    t_near: torch.Tensor | None = None,
) -> Samples:
    """Traverse and sample R rays (origins, dirs (R,3), t_far (R,)) inside allocated voxels."""
    near = torch.zeros_like(t_far) if t_near is None else t_near
    hits = traverse(octree, origins, dirs, near, t_far)
    samples = sample_hits(hits, origins, dirs, step_m, jitter)
    # A sample rounded onto a voxel face may fall in a neighbour; keep the voxel the traversal found.
    return samples


def band_samples(
    octree: VoxelOctree,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    depth: torch.Tensor,
    band_m: float,
    truncation_m: float,
    step_m: float,
    n_free: int,
    generator: torch.Generator | None = None,
    fused: bool = True,
) -> Samples:
    """Training samples where the losses act, without traversing the whole ray: every `step_m` from
    `band_m` in front of the measured depth to tr behind it, plus `n_free` stratified free-space candidates
    between the camera and the band; only candidates inside allocated voxels are kept. depth (R,) > 0.
    `fused` runs the numba kernel (h2viz.mapping.band) for CPU rays; the torch code below is its reference."""
    R, dev = depth.shape[0], depth.device
    n_band = int(round((band_m + truncation_m) / step_m))
    jitter = torch.rand(R, n_band + n_free, generator=generator)  # (R,F+B) reproducible on any device
    kernels = kernel_module("band") if fused and dev.type == "cpu" else None
    if kernels is not None:
        points, t, ray, voxel = kernels.band_candidates(octree, origins, dirs, depth, jitter, n_free, band_m, step_m)
        return Samples(points, t, ray, voxel, R)
    jitter = jitter.to(dev)
    k = torch.arange(n_band, device=dev, dtype=depth.dtype)
    t_band = (depth - band_m)[:, None] + (k + jitter[:, n_free:]) * step_m  # (R,B)
    free_end = (depth - band_m).clamp(min=0.0)
    j = torch.arange(n_free, device=dev, dtype=depth.dtype)
    t_free = (j + jitter[:, :n_free]) / max(n_free, 1) * free_end[:, None]  # (R,F)
    t = torch.cat([t_free, t_band], dim=1)  # (R,F+B) increasing along each row
    points = origins[:, None, :] + dirs[:, None, :] * t[..., None]  # (R,F+B,3)
    voxel = octree.lookup_points(points.reshape(-1, 3))  # (R*(F+B),)
    keep = (voxel >= 0) & (t.reshape(-1) > 0)
    ray = torch.arange(R, device=dev).repeat_interleave(t.shape[1])
    return Samples(points.reshape(-1, 3)[keep], t.reshape(-1)[keep], ray[keep], voxel[keep], R)
