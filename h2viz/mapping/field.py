"""The hierarchical hybrid field: sdf(x) = trilinear(corner priors) + MLP_s(hash_s(x)); colour = MLP_c(hash_c(x)).

SDF values are in truncation units (metres / tr). Corner priors live in a plain tensor that grows with the
octree; the two hash grids and decoders are ordinary modules.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from h2viz.config import MappingConfig
from h2viz.mapping.encoding import HashGrid, corners_and_weights
from h2viz.mapping.octree import VoxelOctree


def mlp(d_in: int, hidden: int, layers: int, d_out: int) -> nn.Sequential:
    """ReLU MLP with `layers` hidden layers of width `hidden`."""
    mods: list[nn.Module] = []
    d = d_in
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    mods.append(nn.Linear(d, d_out))
    return nn.Sequential(*mods)


class HybridField(nn.Module):
    """Octree SDF priors plus residual geometry and colour hash-grid fields."""

    def __init__(self, cfg: MappingConfig) -> None:
        super().__init__()
        base = cfg.hash_base_resolution_m or cfg.voxel_size_m
        grid = dict(n_levels=cfg.hash_levels, n_features=cfg.hash_features, log2_size=cfg.hash_log2_size)
        self.geo_grid = HashGrid(**grid, base_cell_m=base, scale=cfg.hash_scale)
        self.color_grid = HashGrid(**grid, base_cell_m=base, scale=cfg.hash_scale)
        self.geo_mlp = mlp(self.geo_grid.output_dim, cfg.geo_hidden, cfg.geo_layers, 1)
        self.color_mlp = mlp(self.color_grid.output_dim, cfg.color_hidden, cfg.color_layers, 3)
        with torch.no_grad():  # the residual starts near zero so the priors rule at first
            last = self.geo_mlp[-1]
            assert isinstance(last, nn.Linear)
            last.weight.mul_(0.01)
            last.bias.zero_()
        self.voxel_size_m = cfg.voxel_size_m
        self.use_residual = True
        # Corners without a prior start as free space at the truncation distance: a zero would put a
        # surface on every corner whose projection failed.
        self.unset_prior = 1.0 if cfg.priors else 0.0
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
            self.voxel_origin = torch.from_numpy(octree.voxel_coords()).to(dev, torch.float32) * self.voxel_size_m

    def prior_sdf(self, points: torch.Tensor, voxel: torch.Tensor) -> torch.Tensor:
        """Trilinear interpolation of the 8 corner priors of each point's voxel: (N,3), (N,) -> (N,)."""
        return self._trilinear(points, voxel, self.priors[self.corner_ids[voxel]])

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
        s = self.prior_sdf(points, voxel)
        if self.use_residual:
            s = s + self.geo_mlp(self.geo_grid(points))[:, 0]
        return s

    def color(self, points: torch.Tensor) -> torch.Tensor:
        """RGB in [0,1] (N,3)."""
        return torch.sigmoid(self.color_mlp(self.color_grid(points)))

    def forward(self, points: torch.Tensor, voxel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.sdf(points, voxel), self.color(points)

    def train_forward(
        self, points: torch.Tensor, voxel: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, list[Leaf]]:
        """sdf (N,), colour (N,3) and the gathered rows of priors and hash tables as gradient leaves:
        the backward pass then only touches the entries these points use."""
        leaves: list[Leaf] = []
        if self.priors.requires_grad:
            leaf, inverse = gather_leaf("priors", self.priors[:, None], self.corner_ids[voxel])
            leaves.append(leaf)
            s = self._trilinear(points, voxel, leaf.values[:, 0][inverse])
        else:
            s = self.prior_sdf(points, voxel)
        geo, leaf = sparse_encode("geo_tables", self.geo_grid, points)
        leaves.append(leaf)
        if self.use_residual:
            s = s + self.geo_mlp(geo)[:, 0]
        color, leaf = sparse_encode("color_tables", self.color_grid, points)
        leaves.append(leaf)
        return s, torch.sigmoid(self.color_mlp(color)), leaves


@dataclass
class Leaf:
    """Rows of a large tensor gathered as a gradient leaf for one training step."""

    name: str  # optimiser slot of the tensor
    rows: torch.Tensor  # (U,) row indices
    values: torch.Tensor  # (U,width) leaf with requires_grad


def gather_leaf(name: str, table: torch.Tensor, rows: torch.Tensor) -> tuple[Leaf, torch.Tensor]:
    """Leaf of the unique rows of table (T,width) used by `rows` (any shape), and the inverse index."""
    unique, inverse = torch.unique(rows, return_inverse=True)
    values = table.detach()[unique].requires_grad_(True)  # (U,width)
    return Leaf(name, unique, values), inverse


def sparse_encode(name: str, grid: HashGrid, x: torch.Tensor) -> tuple[torch.Tensor, Leaf]:
    """HashGrid features (N, L*F) computed from a gathered leaf of its table rows (equal to grid(x))."""
    rows, weights = corners_and_weights(x, grid.cell_sizes_m, grid.log2_size, grid.tables.dtype)  # (8,L,N) x2
    flat = grid.tables.view(-1, grid.n_features)  # (L*T,F)
    leaf, inverse = gather_leaf(name, flat, rows.long())
    feats = leaf.values[inverse.reshape(-1)].view(8, -1, grid.n_features)  # (8,L*N,F)
    out = (weights.reshape(8, -1, 1) * feats).sum(0)  # (L*N,F)
    return out.view(grid.n_levels, x.shape[0], grid.n_features).permute(1, 0, 2).reshape(x.shape[0], -1), leaf
