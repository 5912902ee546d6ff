"""Explicit colour priors: the measured colours of every frame, averaged on a fine lattice inside each leaf voxel.

H2-Mapping's geometry is an explicit prior (corner SDFs projected from depth) plus a hash-grid residual. Colour
gets the same split here: every valid pixel's colour is splatted, with trilinear weights, onto the 8 nearest
points of a (sub+1)^3 lattice inside the voxel its measured surface point falls in (sub =
mapping.color.color_prior_cells: 0.83 cm apart at 12 and 10 cm voxels), and the lattice holds the weighted sums. The
prior at a point is the trilinear blend of the sums over the weights (lattice points nothing was splatted on do
not pull it to black); the colour field adds its residual to the prior's logit, so the network learns only what
an average of observations misses (texture finer than the lattice, shading it blurs) instead of every colour from
scratch. A frame costs one pass over its pixels, with no optimisation: every pixel of every frame contributes,
not only the few thousand rays a step samples.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from h2viz.mapping.field.octree import VoxelOctree
from h2viz.mapping.field.row_storage import RowStorage

if TYPE_CHECKING:
    from h2viz.mapping.backend import Backend

SUB = 12
"""Default lattice cells per voxel edge (SUB + 1 lattice points per edge, 0.83 cm apart at 10 cm voxels)."""
EMPTY = 0.5
"""Colour of the prior where nothing was observed (logit 0: the residual alone decides)."""
LOGIT_EPS = 1e-3
"""Prior colours are clamped to [eps, 1 - eps] before taking their logit."""

_OFFSETS = torch.tensor([[dx, dy, dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)])  # (8,3)


class ColorPrior:
    """Weighted colour sums (V, (sub+1)^3, 4) on each leaf voxel's lattice: r, g, b times weight, and the weight.
    A backend with tensor kernels runs the numba ones (kernels.color_prior_numba) on the CPU; the torch code is
    their reference (and runs without a backend)."""

    def __init__(
        self,
        voxel_size_m: float,
        device: torch.device | str = "cpu",
        backend: Backend | None = None,
        sub: int = SUB,
    ) -> None:
        self.voxel_size_m = float(voxel_size_m)
        self.sub = int(sub)
        self.n = self.sub + 1
        self.sums = torch.zeros(0, self.n**3, 4, device=device)  # (V, P, 4), a view of the first V of _storage
        self._storage = RowStorage()  # the storage behind it, zeroed ahead of use
        self.backend = backend

    def _kernels(self, points: torch.Tensor, octree: VoxelOctree) -> tuple[object, tuple] | None:
        """The numba module and the octree's hash table when the fast path applies, else None."""
        k = None if self.backend is None else self.backend.cpu_kernels(points, self.sums)
        if k is None or self.backend is None or self.backend.array_kernels is None:
            return None
        return k.color_prior, self.backend.array_kernels.walk.voxel_hash(octree)  # the octree's cached hash table

    def add(self, octree: VoxelOctree, voxel_origin: torch.Tensor, points: torch.Tensor, rgb: torch.Tensor) -> None:
        """Splat colours rgb (N,3) in [0,1] measured at world points (N,3); points outside the map are skipped."""
        fast = self._kernels(points, octree)
        if fast is None:
            self.splat(points, octree.lookup_points(points), voxel_origin, rgb)
            return
        kernels, table = fast
        p = np.ascontiguousarray(points.numpy(), dtype=np.float32)
        c = np.ascontiguousarray(rgb.numpy(), dtype=np.float32)
        origin = np.ascontiguousarray(voxel_origin.numpy(), dtype=np.float32)
        kernels.splat(p, c, *table, origin, self.voxel_size_m, self.sub, self.sums.view(-1, 4).numpy())  # type: ignore[attr-defined]

    def colors(
        self, octree: VoxelOctree, voxel_origin: torch.Tensor, points: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Prior colour (N,3) and weight (N,) at world points (N,3) (EMPTY and 0 outside the map)."""
        fast = self._kernels(points, octree)
        if fast is None:
            return self.query_reference(octree, voxel_origin, points)
        kernels, table = fast
        p = np.ascontiguousarray(points.detach().numpy(), dtype=np.float32)
        rgb, weight = np.empty((p.shape[0], 3), np.float32), np.empty(p.shape[0], np.float32)
        origin = np.ascontiguousarray(voxel_origin.numpy(), dtype=np.float32)
        sums = self.sums.view(-1, 4).numpy()
        kernels.blend(p, *table, origin, self.voxel_size_m, self.sub, sums, EMPTY, rgb, weight)  # type: ignore[attr-defined]
        return torch.from_numpy(rgb), torch.from_numpy(weight)

    def shared(self) -> ColorPrior:
        """A prior reading these lattices as they are now, without copying them (for a frozen field: the live map
        keeps splatting into them, which only makes its colours newer; lattices added later are not seen)."""
        view = ColorPrior(self.voxel_size_m, self.sums.device, self.backend, self.sub)
        view.sums = self.sums
        return view

    def load(self, sums: torch.Tensor | dict[str, torch.Tensor]) -> None:
        """Take saved lattices: (V, (sub+1)^3, 4), or `compact_sums`' form of them (a checkpoint's)."""
        if isinstance(sums, dict):
            sums = expand_sums(sums)
        if sums.shape[1:] != (self.n**3, 4):
            saved = round(float(sums.shape[1]) ** (1.0 / 3.0)) - 1 if sums.ndim == 3 and sums.shape[2] == 4 else None
            hint = f"; set mapping.color.color_prior_cells={saved} to load it" if saved is not None else ""
            raise ValueError(
                f"the checkpoint's colour prior lattices have shape {tuple(sums.shape)}, this configuration's "
                f"(V, {self.n**3}, 4) ({self.sub} cells a voxel edge){hint}"
            )
        self.sums = sums.to(self.sums.device, torch.float32)
        self._storage.release()

    def to(self, device: torch.device) -> None:
        """Keep the lattices on `device` (the field's)."""
        if self.sums.device != device:
            self.sums = self.sums.to(device)
            self._storage.release()

    def grow(self, n_voxels: int) -> None:
        """Give voxels allocated since the last call empty lattices (see `row_storage`: no stall, no full copy)."""
        self.sums = self._storage.grow(self.sums, n_voxels)

    def _lattice(
        self, points: torch.Tensor, voxel: torch.Tensor, voxel_origin: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Flat indices into sums.view(-1, 4) (N,8) of the 8 lattice points around points (N,3) in voxels (N,),
        and their trilinear weights (N,8)."""
        local = ((points - voxel_origin[voxel]) / self.voxel_size_m * self.sub).clamp(0.0, float(self.sub))  # (N,3)
        base = torch.floor(local).clamp(max=self.sub - 1)  # (N,3) lower lattice point
        frac = local - base  # (N,3) in [0,1]
        offsets = _OFFSETS.to(points.device)
        corner = base.long()[:, None, :] + offsets[None]  # (N,8,3)
        flat = (corner[..., 0] * self.n + corner[..., 1]) * self.n + corner[..., 2]  # (N,8)
        w = torch.where(offsets[None].bool(), frac[:, None, :], 1.0 - frac[:, None, :]).prod(dim=2)  # (N,8)
        return voxel[:, None] * self.n**3 + flat, w

    @torch.no_grad()
    def splat(self, points: torch.Tensor, voxel: torch.Tensor, voxel_origin: torch.Tensor, rgb: torch.Tensor) -> None:
        """Splat colours rgb (N,3) in [0,1] measured at points (N,3) lying in voxels (N,) (-1 = none: skipped)."""
        keep = voxel >= 0
        points, voxel, rgb = points[keep], voxel[keep], rgb[keep]
        if points.shape[0] == 0:
            return
        idx, w = self._lattice(points, voxel, voxel_origin)  # (N,8)
        values = torch.cat([rgb[:, None, :] * w[..., None], w[..., None]], dim=2)  # (N,8,4)
        self.sums.view(-1, 4).index_add_(0, idx.reshape(-1), values.reshape(-1, 4))

    def query_reference(
        self, octree: VoxelOctree, voxel_origin: torch.Tensor, points: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """`colors` in torch: the point's own voxel and, within one lattice cell of a face, the neighbours across
        it (each blending its lattice at the point moved onto its box), their weighted sums added."""
        vs = self.voxel_size_m
        cell = vs / self.sub
        own = torch.floor(points / vs)  # (N,3) the point's own voxel cell
        inside = points - own * vs  # (N,3) metres within it
        acc = torch.zeros(points.shape[0], 4, device=points.device)
        for code in range(27):
            off = torch.tensor([code // 9 - 1, code // 3 % 3 - 1, code % 3 - 1], device=points.device)
            near = torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
            for a in range(3):
                if off[a] == -1:
                    near &= inside[:, a] < cell
                elif off[a] == 1:
                    near &= inside[:, a] > vs - cell
            voxel = torch.full((points.shape[0],), -1, dtype=torch.long, device=points.device)
            if bool(near.any()):
                voxel[near] = octree.lookup_points((own[near] + off + 0.5) * vs)
            keep = (voxel >= 0) & (voxel < min(voxel_origin.shape[0], self.sums.shape[0]))  # a frozen copy may lag
            if bool(keep.any()):
                idx, w = self._lattice(points[keep], voxel[keep], voxel_origin)  # (N',8)
                acc[keep] += (self.sums.view(-1, 4)[idx] * w[..., None]).sum(dim=1)
        seen = acc[:, 3] > 1e-6
        rgb = torch.where(seen[:, None], acc[:, :3] / acc[:, 3:].clamp(min=1e-6), EMPTY)
        return rgb, acc[:, 3]

    def logit(self, octree: VoxelOctree, voxel_origin: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """logit of the prior colour (N,3) at world points (N,3): the colour field's output before its residual."""
        rgb, _ = self.colors(octree, voxel_origin, points)
        return torch.logit(rgb.clamp(LOGIT_EPS, 1.0 - LOGIT_EPS))


def compact_sums(sums: torch.Tensor) -> dict[str, torch.Tensor]:
    """The lattices (V, P, 4) as a checkpoint keeps them: the lattice points something was splatted on (a surface
    crosses a voxel's lattice in a thin sheet: about 1 in 8 at the defaults), as their flat indices (M,) into
    (V*P) (int32 while they fit) and sums (M,4), with (V, P). Lossless: a point's colour sums are weight * colour,
    zero where its weight is."""
    flat = sums.detach().cpu().reshape(-1, 4)  # (V*P,4)
    rows = torch.nonzero(flat[:, 3] != 0)[:, 0]  # (M,)
    if flat.shape[0] < 2**31:
        rows = rows.to(torch.int32)
    shape = torch.tensor([int(sums.shape[0]), int(sums.shape[1])])
    return {"shape": shape, "rows": rows, "sums": flat[rows]}


def expand_sums(saved: dict[str, torch.Tensor]) -> torch.Tensor:
    """`compact_sums`' inverse: the lattices (V, P, 4)."""
    n_voxels, points_per_voxel = (int(x) for x in saved["shape"])
    rows, values = saved["rows"].long(), saved["sums"].float()
    if values.shape != (rows.numel(), 4) or (rows.numel() and int(rows.max()) >= n_voxels * points_per_voxel):
        raise ValueError(
            f"the checkpoint's colour prior is inconsistent: {values.shape[0]} sums for {rows.numel()} lattice "
            f"points, of {n_voxels} voxels x {points_per_voxel}"
        )
    flat = torch.zeros(n_voxels * points_per_voxel, 4)
    flat[rows] = values
    return flat.view(n_voxels, points_per_voxel, 4)
