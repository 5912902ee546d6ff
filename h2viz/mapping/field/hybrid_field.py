"""The hierarchical hybrid field: sdf(x) = trilinear(corner priors) + MLP_s(hash_s(x)); colour = MLP_c(hash_c(x)).

SDF values are in truncation units (metres / tr). Corner priors live in a plain tensor that grows with the
octree; the two hash grids and decoders are ordinary modules.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, TypeVar

import numpy as np
import torch
from torch import nn

from h2viz.config import MappingConfig
from h2viz.mapping.field.bf16 import decode_bf16, use_bf16
from h2viz.mapping.field.color_prior import ColorPrior
from h2viz.mapping.field.encoding import HashGrid
from h2viz.mapping.field.fine_prior import FinePrior
from h2viz.mapping.field.octree import VoxelOctree
from h2viz.mapping.field.tiled import tiled

if TYPE_CHECKING:
    from h2viz.mapping.backend import Backend, TensorKernels


def mlp(d_in: int, hidden: int, layers: int, d_out: int) -> nn.Sequential:
    """ReLU MLP with `layers` hidden layers of width `hidden`."""
    mods: list[nn.Module] = []
    d = d_in
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    mods.append(nn.Linear(d, d_out))
    return nn.Sequential(*mods)


Values = TypeVar("Values", np.ndarray, torch.Tensor)


def keep_prior_sign(sdf: Values, prior: Values, band: float) -> Values:
    """SDF (N,) where every point the prior (N,) puts more than `band` from its surface (all in truncation units)
    has the prior's sign: the surface can be moved by the residual only within the band around the surface the
    depth measured. Keeps meshing and surface renders from drawing the residual's unconstrained zero crossings.
    NumPy arrays (meshing) or tensors (rendering), float32 either way."""
    xp = torch if isinstance(sdf, torch.Tensor) else np
    flip = (abs(prior) > band) & (xp.sign(sdf) != xp.sign(prior))
    return xp.where(flip, prior, sdf)


class HybridField(nn.Module):
    """Octree SDF priors plus residual geometry and colour hash-grid fields; `backend` (None: the torch reference)
    picks the kernels of the encoders, the prior, the decoders and the colour prior."""

    def __init__(self, cfg: MappingConfig, backend: Backend | None = None) -> None:
        super().__init__()
        rep, col = cfg.representation, cfg.color
        base = rep.hash_base_resolution_m or rep.voxel_size_m
        grid = dict(n_levels=rep.hash_levels, n_features=rep.hash_features, log2_size=rep.hash_log2_size)
        self.geo_grid = HashGrid(**grid, base_cell_m=base, scale=rep.hash_scale, backend=backend)
        color = dict(
            n_levels=col.color_hash_levels or rep.hash_levels,
            n_features=rep.hash_features,
            log2_size=col.color_hash_log2_size or rep.hash_log2_size,
        )
        self.color_grid = HashGrid(**color, base_cell_m=base, scale=rep.hash_scale, backend=backend)
        self.geo_mlp = mlp(self.geo_grid.output_dim, rep.geo_hidden, rep.geo_layers, 1)
        self.color_mlp = mlp(self.color_grid.output_dim, col.color_hidden, col.color_layers, 3)
        with torch.no_grad():  # the residual starts near zero so the priors rule at first
            for net in (self.geo_mlp, self.color_mlp) if col.color_prior else (self.geo_mlp,):
                last = net[-1]
                assert isinstance(last, nn.Linear)
                last.weight.mul_(0.01)
                last.bias.zero_()
        self.voxel_size_m = rep.voxel_size_m
        self.backend = backend
        self.color_bf16 = use_bf16(col.color_precision)  # applies on the CPU only
        self.use_residual = True
        self.residual_bound = float(rep.residual_bound) if rep.priors else 0.0  # tr units, 0 = unbounded
        # Corners without a prior start as free space at the truncation distance: a zero would put a
        # surface on every corner whose projection failed.
        self.unset_prior = 1.0 if rep.priors else 0.0
        self.color_prior = (
            ColorPrior(rep.voxel_size_m, backend=backend, sub=col.color_prior_cells) if col.color_prior else None
        )
        fine = rep.fine_priors and rep.priors
        self.fine_prior = FinePrior(rep.voxel_size_m, rep.truncation_m, backend=backend) if fine else None
        self.fine_residual = cfg.experimental.fine_prior_residual  # the residual also corrects the fine prior
        self.octree: VoxelOctree | None = None  # where the colour prior looks points up (set by sync)
        self.priors = torch.zeros(0)  # (C,) corner SDF in tr units, grows with the octree
        self.corner_ids = torch.zeros(0, 8, dtype=torch.long)  # (V,8)
        self.voxel_origin = torch.zeros(0, 3)  # (V,3) metres, min corner of each voxel

    def sync(self, octree: VoxelOctree) -> None:
        """Grow priors and voxel tables to match the octree (new corners start at `unset_prior`)."""
        dev = self.priors.device
        n_new = octree.n_corners - self.priors.numel()
        if n_new > 0:
            grown = torch.cat([self.priors.detach(), torch.full((n_new,), self.unset_prior, device=dev)])
            self.priors = grown.requires_grad_(self.priors.requires_grad)
        if octree.n_voxels != self.corner_ids.shape[0]:
            self.corner_ids = torch.from_numpy(octree.voxel_corners).to(dev)
            coords = octree.voxel_coords().astype(np.float32)  # (V,3) a writable copy
            self.voxel_origin = torch.from_numpy(coords).to(dev) * self.voxel_size_m
        if self.color_prior is not None:
            self.color_prior.to(dev)
            self.color_prior.grow(octree.n_voxels)
        if self.fine_prior is not None:
            self.fine_prior.to(dev)
            self.fine_prior.grow(octree.n_voxels)
        self.octree = octree

    def add_colors(self, points: torch.Tensor, rgb: torch.Tensor) -> None:
        """Splat measured colours rgb (N,3) in [0,1] at surface points (N,3) into the colour prior (if any)."""
        if self.color_prior is not None and self.octree is not None:
            self.color_prior.add(self.octree, self.voxel_origin, points, rgb)

    def prior_sdf(self, points: torch.Tensor, voxel: torch.Tensor) -> torch.Tensor:
        """Prior SDF (N,) at points (N,3) in voxels (N,): the fine lattice's blend where frames reached it, the
        corner priors' trilinear interpolation elsewhere (gradients reach the corner priors by their share)."""
        return self.prior_parts(points, voxel)[0]

    def prior_parts(self, points: torch.Tensor, voxel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The prior SDF (N,) and the residual's weight (N,) at points (N,3) in voxels (N,): the share of the
        prior the corner priors make up when the residual corrects only those (experimental.fine_prior_residual off),
        else None (weight 1 everywhere)."""
        coarse = self.corner_prior(points, voxel)
        if self.fine_prior is None:
            return coarse, None
        value, cover = self.fine_prior.blend(self.voxel_origin, points, voxel)  # (N,), (N,)
        rest = 1.0 - cover.to(coarse.device)
        return value.to(coarse.device) + rest * coarse, None if self.fine_residual else rest

    def corner_prior(self, points: torch.Tensor, voxel: torch.Tensor) -> torch.Tensor:
        """Trilinear interpolation of the 8 corner priors of each point's voxel: (N,3), (N,) -> (N,)."""
        k = self._kernels(points)
        if k is not None and not (torch.is_grad_enabled() and points.requires_grad):
            prior = k.prior.fused_prior
            return prior(self.priors, points, voxel, self.voxel_origin, self.corner_ids, self.voxel_size_m)
        return self._trilinear(points, voxel, self.priors[self.corner_ids[voxel]])

    def _kernels(self, *tensors: torch.Tensor) -> TensorKernels | None:
        """The backend's tensor kernels when they can read these tensors, else None (the torch code runs)."""
        return None if self.backend is None else self.backend.cpu_kernels(*tensors)

    def _trilinear(self, points: torch.Tensor, voxel: torch.Tensor, vals: torch.Tensor) -> torch.Tensor:
        """Blend corner values vals (N,8) (corner order x,y,z bits 4,2,1) at points (N,3) in voxels (N,)."""
        local = ((points - self.voxel_origin[voxel]) / self.voxel_size_m).clamp(0.0, 1.0)  # (N,3)
        x, y, z = local[:, 0:1], local[:, 1:2], local[:, 2:3]
        v = vals.view(-1, 2, 2, 2)  # [x][y][z]
        vx = v[:, 0] * (1 - x[:, :, None]) + v[:, 1] * x[:, :, None]  # (N,2,2) over (y,z)
        vy = vx[:, 0] * (1 - y) + vx[:, 1] * y  # (N,2) over z
        return vy[:, 0] * (1 - z[:, 0]) + vy[:, 1] * z[:, 0]

    def sdf(self, points: torch.Tensor, voxel: torch.Tensor) -> torch.Tensor:
        """Signed distance in truncation units (N,) at points (N,3) lying in voxels (N,)."""
        s, weight = self.prior_parts(points, voxel)
        if self.use_residual:
            residual = self.residual(self.geo_grid(points))[:, 0]
            s = s + (residual if weight is None else residual * weight)
        return s

    def residual(self, features: torch.Tensor) -> torch.Tensor:
        """Bounded residual SDF (N,1) from hash features (N, L*F)."""
        return self.bound(self._decode(self.geo_mlp, features))

    def _decode(self, net: nn.Sequential, features: torch.Tensor) -> torch.Tensor:
        """net(features): the fused CPU kernels for one-hidden-layer decoders (h2viz.mapping.kernels.decoder_numba; the
        two-layer colour decoder is faster as torch's matrix products), else torch tile by tile."""
        k = self._kernels(features)
        if k is not None and k.decoder.is_supported(net) and features.dtype == torch.float32:
            return k.decoder.fused_decoder(net, features)
        return tiled(net, features)

    def bound(self, raw: torch.Tensor) -> torch.Tensor:
        """The decoder's raw output squashed to at most `residual_bound` either way: b * tanh(raw / b)."""
        b = self.residual_bound
        return b * torch.tanh(raw / b) if b > 0 else raw

    def color(self, points: torch.Tensor) -> torch.Tensor:
        """RGB in [0,1] (N,3): sigmoid(logit(colour prior) + MLP_c(hash_c(x))), without a prior sigmoid(MLP_c(...))."""
        features = self.color_grid(points)  # (N, L*F)
        if self.color_bf16 and features.device.type == "cpu":
            raw = decode_bf16(self.color_mlp, features)
        else:
            raw = self._decode(self.color_mlp, features)
        if self.color_prior is not None and self.octree is not None:
            raw = raw + self.color_prior.logit(self.octree, self.voxel_origin, points).to(raw.device)
        return torch.sigmoid(raw)

    def forward(self, points: torch.Tensor, voxel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.sdf(points, voxel), self.color(points)
