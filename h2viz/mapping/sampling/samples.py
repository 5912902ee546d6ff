"""Ray samples inside allocated leaf voxels: voxel traversal (3-D DDA) plus fixed-step samples.

Rays use z-normalised directions (camera z of the direction = 1), so a sample's parameter t is its depth
along the camera axis and compares directly with depth images.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from h2viz.mapping.field.octree import VoxelOctree, decode, encode

if TYPE_CHECKING:
    from h2viz.mapping.backend import Backend


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
    octree: VoxelOctree,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    t_near: torch.Tensor,
    t_far: torch.Tensor,
    backend: Backend | None = None,
) -> Hits:
    """Allocated voxels crossed by each ray between t_near and t_far (R,): an exact voxel walk per ray, compiled
    and jumping over empty space with the backend's array kernels (h2viz.mapping.kernels.voxel_walk), else
    `voxel_hits_reference`."""
    kernels = None if backend is None else backend.array_kernels
    walk = voxel_hits_reference if kernels is None else kernels.walk.voxel_hits
    return Hits(*walk(octree, origins, dirs, t_near, t_far))


def voxel_hits_reference(
    octree: VoxelOctree, origins: torch.Tensor, dirs: torch.Tensor, t_near: torch.Tensor, t_far: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(ray, voxel, t_in, t_out) (H,) as voxel_walk.voxel_hits, in NumPy: the same 3-D DDA in float64 (cell to cell
    across the nearest boundary, the first axis on ties, inside the leaves' bounding box), stepped for all rays at
    once and without skipping empty space."""
    R, dev, vs = origins.shape[0], origins.device, octree.voxel_size_m
    if octree.n_voxels == 0 or R == 0:
        empty = torch.zeros(0, dtype=torch.long, device=dev)
        return empty, empty, empty.float(), empty.float()
    o, d = (a.detach().cpu().numpy().astype(np.float64) for a in (origins, dirs))  # (R,3)
    near, far = (a.detach().cpu().numpy().astype(np.float64) for a in (t_near, t_far))  # (R,)
    coords = decode(octree.voxels.keys)
    lo, hi = coords.min(0) * vs - 1e-3 * vs, (coords.max(0) + 1) * vs + 1e-3 * vs  # (3,) as the walk table's box
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d  # (R,3)
        t0 = np.maximum(near, np.where(d != 0, np.minimum(ta, tb), -np.inf).max(1))
        t1 = np.minimum(far, np.where(d != 0, np.maximum(ta, tb), np.inf).min(1))
    outside = ((d == 0) & ((o < lo) | (o > hi))).any(1)
    t1 = np.where(outside, t0, t1)
    cell = np.floor((o + d * t0[:, None]) / vs)  # (R,3)
    step = np.sign(d).astype(np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        nxt = np.where(d > 0, ((cell + 1) * vs - o) / d, np.where(d < 0, (cell * vs - o) / d, np.inf))
        delta = np.where(d != 0, vs / np.abs(d), np.inf)
    cell, t, live = cell.astype(np.int64), t0.copy(), np.flatnonzero(t0 < t1)
    out: list[tuple[np.ndarray, ...]] = []
    while live.size:
        vid = octree.voxels.lookup(encode(cell[live]))  # (A,)
        axis = np.argmin(nxt[live], axis=1)  # (A,) first axis on ties
        t_in, t_next = t[live], nxt[live, axis]
        t_out = np.minimum(t_next, t1[live])
        hit = (vid >= 0) & (t_out > t_in)
        out.append((live[hit], vid[hit], t_in[hit], t_out[hit]))
        cell[live, axis] += step[live, axis]
        nxt[live, axis] += delta[live, axis]
        t[live] = t_next
        live = live[t_next < t1[live]]
    ray, voxel, t_in, t_out = (np.concatenate(col) for col in zip(*out, strict=True))
    order = np.argsort(ray, kind="stable")  # ray-major; each ray's hits were found front to back
    as_t = lambda a, dtype: torch.from_numpy(np.ascontiguousarray(a[order]).astype(dtype)).to(dev)  # noqa: E731
    return as_t(ray, np.int64), as_t(voxel, np.int64), as_t(t_in, np.float32), as_t(t_out, np.float32)


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
    backend: Backend | None = None,
) -> Samples:
    """Traverse and sample R rays (origins, dirs (R,3), t_far (R,)) inside allocated voxels."""
    near = torch.zeros_like(t_far) if t_near is None else t_near
    hits = traverse(octree, origins, dirs, near, t_far, backend)
    samples = sample_hits(hits, origins, dirs, step_m, jitter)
    # A sample rounded onto a voxel face may fall in a neighbour; keep the voxel the traversal found.
    return samples


@dataclass(frozen=True)
class BandLayout:
    """Where a training ray's candidate samples lie, relative to its measured depth d: `n_free` strata from
    the camera to d - band_m; strata of `front_step_m` (rounded to tile the span) from d - band_m to d - tr,
    where only the free-space loss acts; every `step_m` from d - tr to d + `behind_m`, where the SDF loss and the
    render weights live."""

    band_m: float
    truncation_m: float
    step_m: float
    front_step_m: float
    n_free: int
    behind_m: float | None = None  # None = tr

    @property
    def behind(self) -> float:
        return self.truncation_m if self.behind_m is None else self.behind_m

    @property
    def n_front(self) -> int:
        return max(0, int(round((self.band_m - self.truncation_m) / self.front_step_m)))

    @property
    def n_truncation(self) -> int:
        return max(1, int(round((self.truncation_m + self.behind) / self.step_m)))

    @property
    def n_candidates(self) -> int:
        return self.n_free + self.n_front + self.n_truncation

    @property
    def front_stride_m(self) -> float:
        """The front strata's width: front_step_m rounded so that n_front strata tile band_m - tr exactly."""
        return (self.band_m - self.truncation_m) / max(self.n_front, 1)


def band_samples(
    octree: VoxelOctree,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    depth: torch.Tensor,
    layout: BandLayout,
    generator: torch.Generator | None = None,
    backend: Backend | None = None,
) -> Samples:
    """Training samples where the losses act, without traversing the whole ray (see BandLayout); only
    candidates inside allocated voxels are kept. depth (R,) > 0. A backend with tensor kernels runs the numba one
    (kernels.band_numba) for CPU rays; the torch code below is its reference (and runs without a backend)."""
    R, dev = depth.shape[0], depth.device
    n_free, n_front, n_trunc = layout.n_free, layout.n_front, layout.n_truncation
    jitter = torch.rand(R, layout.n_candidates, generator=generator)  # (R,F+N+B) reproducible on any device
    kernels = None if backend is None else backend.cpu_kernels(depth)
    if kernels is not None:
        points, t, ray, voxel = kernels.band.band_candidates(octree, origins, dirs, depth, jitter, layout)
        return Samples(points, t, ray, voxel, R)
    jitter = jitter.to(dev)
    f32 = lambda v: torch.tensor(v, dtype=torch.float32).to(depth.dtype)  # noqa: E731  (the kernel's float32)
    band, front, tr, step = f32(layout.band_m), f32(layout.front_stride_m), f32(layout.truncation_m), f32(layout.step_m)
    k = torch.arange(n_front, device=dev, dtype=depth.dtype)
    t_front = (depth - band)[:, None] + (k + jitter[:, n_free : n_free + n_front]) * front  # (R,N)
    k = torch.arange(n_trunc, device=dev, dtype=depth.dtype)
    t_trunc = (depth - tr)[:, None] + (k + jitter[:, n_free + n_front :]) * step  # (R,B)
    free_end = (depth - band).clamp(min=0.0)
    j = torch.arange(n_free, device=dev, dtype=depth.dtype)
    t_free = (j + jitter[:, :n_free]) / max(n_free, 1) * free_end[:, None]  # (R,F)
    t = torch.cat([t_free, t_front, t_trunc], dim=1)  # (R,F+N+B) increasing along each row
    points = origins[:, None, :] + dirs[:, None, :] * t[..., None]  # (R,F+N+B,3)
    voxel = octree.lookup_points(points.reshape(-1, 3))  # (R*(F+N+B),)
    keep = (voxel >= 0) & (t.reshape(-1) > 0)
    ray = torch.arange(R, device=dev).repeat_interleave(t.shape[1])
    return Samples(points.reshape(-1, 3)[keep], t.reshape(-1)[keep], ray[keep], voxel[keep], R)
