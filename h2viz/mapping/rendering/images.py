"""Render the field at any camera: rgb, depth, normal or prior-only depth, in ray chunks without gradients.

`render_image` runs the networks only where rendering weight can be. Each ray walks the allocated voxels
(numba, kernels/voxel_walk.py) on the lattice of an exhaustive render (every 1 cm of every voxel, the same positions
bit for bit); voxels whose 8 corners hold measured priors point at the first surface through the trilinear
prior, other voxels are searched coarse then fine with the full SDF, and evaluation spreads from there only
while the SDF stays near zero (kernels/render_search.py). The kept samples get exactly the paper's weights
(`render_weights`); the skipped ones would weigh less than `NEGLIGIBLE_WEIGHT`, as long as the hash-grid
residual does not add surfaces where the measured priors see none. `render_image_reference` is the exhaustive
render, kept as the baseline the fast path is checked against, and what a backend without array kernels (numba
absent, or `mapping.runtime.kernels: torch`) runs. Depth is along the camera axis (z-normalised
rays); rays whose weights sum below HIT_WEIGHT render empty (0) in both.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from h2viz.config import MappingConfig
from h2viz.mapping.field.hybrid_field import HybridField, keep_prior_sign
from h2viz.mapping.field.octree import VoxelOctree
from h2viz.mapping.rendering.volume import (
    composite,
    first_hit,
    live_samples,
    render_weights,
    segment_sum,
    surface_crossings,
)
from h2viz.mapping.sampling.rays import pixel_rays
from h2viz.mapping.sampling.samples import Samples, sample_rays

if TYPE_CHECKING:
    from h2viz.mapping.backend import Backend

MODES = ("rgb", "depth", "normal", "prior")
NEGLIGIBLE_WEIGHT = 1e-3
"""Rendering weights (peak 0.25) below this are treated as zero when choosing what to evaluate."""
MLP_ROWS = 32768
"""Field evaluations that build autograd graphs (normals) run on this many points at a time, so that their
intermediate tensors stay in the CPU's cache."""
CHUNK_RAYS = 65536
HIT_WEIGHT = 1e-2
"""A ray shows a surface when its rendering weights sum above this (a crossing sums to ~0.25 or more); rays
that only pass near surfaces, with tiny weights and meaningless depths, render empty."""


@dataclass(frozen=True)
class SearchParams:
    """How the fast render walks and searches the lattice (kernels/render_search.py)."""

    step_m: float
    truncation_m: float
    temperature: float
    after_m: float  # the walk goes this far beyond the first prior crossing
    wave: int = 8  # probes per ray and round

    @property
    def theta(self) -> float:
        """|SDF| (truncation units) beyond which a sample's weight is negligible."""
        return self.temperature * math.log(1.0 / NEGLIGIBLE_WEIGHT)


@dataclass(frozen=True)
class RenderParams:
    t_far: float  # metres along the camera axis
    step_m: float
    truncation_m: float
    temperature: float
    band: float | None  # reference path: keep samples with |prior| < band (truncation units); None keeps all
    after_m: float = 0.1  # fast path: walk this far beyond the first prior crossing before trusting it
    surface: bool = False  # rgb/depth/normal at the first observed zero crossing instead of volume-rendered
    prior_band: float = 0.0  # surface renders: the prior's sign beyond this (truncation units), as meshing

    def search(self) -> SearchParams:
        return SearchParams(self.step_m, self.truncation_m, self.temperature, self.after_m)

    @staticmethod
    def from_config(cfg: MappingConfig, max_depth_m: float) -> RenderParams:
        """The mapper's render settings: rays reach 1.5x the deepest depth seen."""
        rep = cfg.representation
        return RenderParams(
            t_far=max(max_depth_m, 1.0) * 1.5 + rep.voxel_size_m,
            step_m=cfg.sampling.step_m,
            truncation_m=rep.truncation_m,
            temperature=cfg.rendering.render_temperature,
            band=4.0 * rep.voxel_size_m / rep.truncation_m if rep.priors else None,
            surface=cfg.rendering.render_surface,
            prior_band=cfg.meshing.mesh_prior_band if rep.priors else 0.0,
        )


def locate(octree: VoxelOctree, points: torch.Tensor) -> torch.Tensor:
    """Voxel ids (N,) of points (N,3), also accepting points on the outer face of an allocated voxel
    (up to rounding in either direction), -1 elsewhere."""
    return octree.locate_points(points)


NORMAL_STEP_M = 1e-3
"""Finite-difference step of the rendered normals (a tenth of the finest hash cell at the defaults)."""


def sdf_gradient(field: HybridField, points: torch.Tensor, voxel: torch.Tensor, rows: int = MLP_ROWS) -> torch.Tensor:
    """Unit normals (N,3) as the normalised SDF gradient (autograd through the field, `rows` points at a time)."""
    grads = []
    with torch.enable_grad():
        for i in range(0, points.shape[0], rows):
            p = points[i : i + rows].detach().requires_grad_(True)
            (grad,) = torch.autograd.grad(field.sdf(p, voxel[i : i + rows]).sum(), p)
            grads.append(grad)
    grad = torch.cat(grads) if grads else torch.zeros_like(points)
    return torch.nn.functional.normalize(grad, dim=1)


def sdf_gradient_fd(
    field: HybridField, octree: VoxelOctree, points: torch.Tensor, voxel: torch.Tensor, step_m: float = NORMAL_STEP_M
) -> torch.Tensor:
    """Unit normals (N,3) by tetrahedral differences of the SDF: grad ~ sum_k e_k sdf(x + step e_k) over the four
    corners e_k of a tetrahedron, second-order accurate as central differences with 4 gradient-free evaluations
    a point instead of 6 (they run the fused CPU kernels: ~10x faster than autograd through the field). An
    offset point outside the map keeps its point's voxel."""
    corners = torch.tensor([[1.0, -1.0, -1.0], [-1.0, -1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, 1.0, 1.0]]).to(points)
    probe = (points[None] + corners[:, None] * step_m).reshape(-1, 3)  # (4N,3)
    vid = voxel.repeat(4)  # (4N,) most probes stay in their point's voxel
    local = (probe - field.voxel_origin[vid]) / octree.voxel_size_m
    out = ((local < 0) | (local >= 1)).any(dim=1)
    moved = octree.lookup_points(probe[out])
    vid[out] = torch.where(moved >= 0, moved, vid[out])
    sdf = torch.cat(
        [field.sdf(probe[i : i + MLP_ROWS], vid[i : i + MLP_ROWS]) for i in range(0, probe.shape[0], MLP_ROWS)]
    )
    grad = sdf.view(4, -1).T @ corners  # (N,3), the 1/(4 step) factor drops out in the normalisation
    return torch.nn.functional.normalize(grad, dim=1)


Support = Callable[[np.ndarray], np.ndarray]
"""Which world points (N,3) lie where depth was observed, (N,) bool: a surface render draws only those."""
SurfaceColor = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""Colour (N,3) of surface hit points (N,3) given the colour field's there (N,3)."""


def surface_depth(
    field: HybridField,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    samples: Samples,
    sdf: torch.Tensor,
    params: RenderParams,
    support: Support | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Depth (R,) at each ray's first zero crossing of the SDF that the mesher would also draw (the prior's sign
    beyond `params.prior_band`, the crossing in observed space), 0 where there is none; hit (R,) bool and the
    hit rays' surface points (R',3). A ray with no crossing whose weights still show a surface (one that ends on
    the outer face of the allocated voxels, with no voxel behind it to cross into) takes the volume-rendered depth
    there, under the same observed-space test."""
    if params.prior_band > 0:
        sdf = keep_prior_sign(sdf, field.prior_sdf(samples.points, samples.voxel), params.prior_band)
    hits = surface_crossings(samples, sdf, 1.5 * params.step_m)
    R, dev = origins.shape[0], sdf.device
    first, crossed = first_hit(hits, _drawable(hits.points, support), R)
    depth = torch.zeros(R, device=dev)
    points = torch.zeros(R, 3, device=dev)
    depth[crossed] = hits.t[first[crossed]]
    points[crossed] = hits.points[first[crossed]]
    uncrossed = torch.ones(R, dtype=torch.bool, device=dev)
    uncrossed[hits.ray] = False
    rest = uncrossed[samples.ray]  # (S,) the samples of rays without a crossing: only those need weights
    samples, sdf = samples.select(rest), sdf[rest]
    weights = render_weights(samples, sdf, params.truncation_m, params.temperature)  # (S',)
    edge = uncrossed & (segment_sum(weights, samples.ray, R) > HIT_WEIGHT)  # (R,) a surface on the map's edge
    if bool(edge.any()):
        t_edge = composite(samples, weights, None).depth  # (R,)
        ray_of = torch.nonzero(edge)[:, 0]
        p = origins[ray_of] + dirs[ray_of] * t_edge[ray_of, None]  # (E,3)
        ok = _drawable(p, support)
        depth[ray_of[ok]], points[ray_of[ok]] = t_edge[ray_of[ok]], p[ok]
        crossed[ray_of[ok]] = True
    return depth, crossed, points[crossed]


def _drawable(points: torch.Tensor, support: Support | None) -> torch.Tensor:
    """(N,) bool: points (N,3) where a surface may be drawn (all when support is None)."""
    if support is None or points.shape[0] == 0:
        return torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
    return torch.from_numpy(support(points.cpu().numpy())).to(points.device)


def shade(
    field: HybridField,
    octree: VoxelOctree,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    samples: Samples,
    sdf: torch.Tensor,
    mode: str,
    params: RenderParams,
    support: Support | None = None,
    surface_color: SurfaceColor | None = None,
) -> torch.Tensor:
    """Shade R rays from their samples and SDF (S,): (R,3) for rgb/normal, (R,) for depth/prior. Surface renders
    take each ray's first observed zero crossing (and its colour there: the colour field's, passed through
    `surface_color` when given), others composite the rendering weights."""
    if params.surface and mode != "prior":
        depth, hit, points = surface_depth(field, origins, dirs, samples, sdf, params, support)
        if mode == "rgb":
            rgb = torch.zeros(origins.shape[0], 3, device=origins.device)
            if points.shape[0]:
                color = field.color(points)  # (H,3)
                rgb[hit] = color if surface_color is None else surface_color(points, color)
            return rgb
    else:
        weights = render_weights(samples, sdf, params.truncation_m, params.temperature)  # (S,)
        hit = segment_sum(weights, samples.ray, samples.n_rays) > HIT_WEIGHT  # (R,)
        if mode == "rgb":
            live = live_samples(samples, weights)  # (S',)
            return composite(samples, weights, field.color(samples.points[live]), live).rgb * hit[:, None]
        depth = composite(samples, weights, None).depth * hit  # (R,)
    if mode != "normal":
        return depth
    normals = torch.zeros(origins.shape[0], 3, device=origins.device)
    if bool(hit.any()):
        pts = origins[hit] + dirs[hit] * depth[hit, None]
        vid = locate(octree, pts)
        ok = vid >= 0
        n = torch.zeros_like(pts)
        n[ok] = sdf_gradient_fd(field, octree, pts[ok], vid[ok])
        normals[hit] = n
    return normals


@torch.no_grad()
def render_rays(
    field: HybridField,
    octree: VoxelOctree,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    mode: str,
    params: RenderParams,
    trusted: torch.Tensor | None,
    support: Support | None = None,
    backend: Backend | None = None,
    surface_color: SurfaceColor | None = None,
) -> torch.Tensor:
    """Render R rays (origins, dirs (R,3)), evaluating the networks only where weight can be (the backend's
    array kernels run the search; without them, `render_rays_reference`)."""
    kernels = None if backend is None else backend.array_kernels
    if kernels is None:
        args = (field, octree, origins, dirs, mode, params, trusted, support, backend, surface_color)
        return render_rays_reference(*args)
    if mode == "prior":
        samples, sdf = kernels.search.prior_samples(octree, field, origins, dirs, params.t_far, params.search())
    else:
        search = kernels.search.weighted_samples
        samples, sdf = search(field, octree, origins, dirs, params.t_far, trusted, params.search())
    return shade(field, octree, origins, dirs, samples, sdf, mode, params, support, surface_color)


@torch.no_grad()
def render_rays_reference(
    field: HybridField,
    octree: VoxelOctree,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    mode: str,
    params: RenderParams,
    trusted: torch.Tensor | None = None,
    support: Support | None = None,
    backend: Backend | None = None,
    surface_color: SurfaceColor | None = None,
) -> torch.Tensor:
    """Render R rays from every sample of every allocated voxel up to t_far (band-filtered by the prior)."""
    t_far = torch.full((origins.shape[0],), params.t_far, device=origins.device)
    samples = sample_rays(octree, origins, dirs, t_far, params.step_m, False, backend=backend)
    prior = field.prior_sdf(samples.points, samples.voxel)
    if params.band is not None:
        keep = prior.abs() < params.band
        samples, prior = samples.select(keep), prior[keep]
    sdf = prior if mode == "prior" else field.sdf(samples.points, samples.voxel)
    return shade(field, octree, origins, dirs, samples, sdf, mode, params, support, surface_color)


def render_image(
    field: HybridField,
    octree: VoxelOctree,
    K: np.ndarray,
    T_world_camera: np.ndarray,
    height: int,
    width: int,
    mode: str,
    params: RenderParams,
    trusted: torch.Tensor | None = None,
    chunk: int = CHUNK_RAYS,
    reference: bool = False,
    support: Support | None = None,
    backend: Backend | None = None,
    surface_color: SurfaceColor | None = None,
) -> np.ndarray:
    """(H,W,3) float32 rgb in [0,1] / normals in [-1,1], or (H,W) float32 depth in metres (0 = nothing).
    trusted (V,) bool: voxels whose 8 corner priors are all set (None: priors disabled, search the SDF);
    support: where surface renders may draw (None: everywhere); backend: its kernels walk the voxels and search
    the lattice (None: the reference render); surface_color: the colour of surface renders' hit points from the
    colour field's (None: the colour field's, h2viz.mapping.field.color_views)."""
    if mode not in MODES:
        raise ValueError(f"render mode '{mode}' is not one of {', '.join(MODES)}")
    dev = field.priors.device
    origins, dirs = pixel_rays(K, T_world_camera, height, width, dev)
    channels = (3,) if mode in ("rgb", "normal") else ()
    if octree.n_voxels == 0:
        return np.zeros((height, width, *channels), dtype=np.float32)
    fn = render_rays_reference if reference else render_rays
    args = (mode, params, trusted, support, backend, surface_color)
    parts = [
        fn(field, octree, origins[i : i + chunk], dirs[i : i + chunk], *args) for i in range(0, origins.shape[0], chunk)
    ]
    return torch.cat(parts).float().cpu().numpy().reshape(height, width, *channels)


def render_image_reference(*args: object, **kwargs: object) -> np.ndarray:
    """`render_image` over every sample of an exhaustive walk (slow; the baseline of the fast path)."""
    return render_image(*args, reference=True, **kwargs)  # type: ignore[arg-type]
