"""Fine SDF priors: every frame's projective SDF, truncated and averaged on a lattice inside each leaf voxel.

H2-Mapping's corner priors hold one SDF value per 10 cm voxel corner, written once by the first frame that sees
the corner; the hash-grid residual has to carve every detail finer than that (thin structures, the folds of a
curtain, object outlines) and, with collisions at its fine levels, it does not hold them all. Here each voxel
also carries a (SUB+1)^3 lattice (1.25 cm apart at 10 cm voxels) updated by every frame, as TSDF fusion updates
its voxels: each lattice point in view projects into the depth image, and where it lies at most one truncation
distance behind the measured surface its SDF d - z, clamped to [-tr, tr], joins a running average (free space in
front of the surface counts as +tr, so a point a later view sees through is carved back to open space).

The prior at a point blends the 8 lattice points around it; lattice points no frame has reached yet (e.g. more
than tr behind every surface seen) take the corner prior's value instead, so the two priors join without a seam.
Values are in truncation units, like the corner priors; the residual learns what the average misses.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from h2viz.geometry import invert_se3
from h2viz.mapping.field.row_storage import RowStorage

if TYPE_CHECKING:
    from h2viz.mapping.backend import Backend
    from h2viz.mapping.field.copy_pool import CopyPool

SUB = 8
"""Lattice cells per voxel edge (SUB + 1 points per edge, 1.25 cm apart at 10 cm voxels)."""

_OFFSETS = torch.tensor([[dx, dy, dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)])  # (8,3)


class FinePrior:
    """Per-voxel lattices (V, (SUB+1)^3, 2) of summed truncated SDF (tr units) and weight (frames).
    A backend with kernels runs the numba ones (kernels.fine_prior_numba) on host lattices; the torch code is
    their reference (and runs without a backend)."""

    def __init__(self, voxel_size_m: float, truncation_m: float, backend: Backend | None = None) -> None:
        self.voxel_size_m = float(voxel_size_m)
        self.truncation_m = float(truncation_m)
        self.n = SUB + 1
        self.state = torch.zeros(0, self.n**3, 2)  # (V, P, 2), a view of the first V of _storage
        self._storage = RowStorage()  # the storage behind it, zeroed ahead of use
        self.backend = backend

    def _kernels(self) -> object | None:
        """The compiled module when the backend has one and the lattices live on the host, else None."""
        kernels = None if self.backend is None else self.backend.array_kernels
        return kernels.fine_prior if kernels is not None and self.state.device.type == "cpu" else None

    # ------------------------------------------------------------------------------------------- storage
    def grow(self, n_voxels: int) -> None:
        """Give voxels allocated since the last call empty lattices (see `row_storage`: no stall, no full copy)."""
        self.state = self._storage.grow(self.state, n_voxels)

    def to(self, device: torch.device) -> None:
        if self.state.device != device:
            self.state = self.state.to(device)
            self._storage.release()

    def frozen(self, pool: CopyPool | None = None, owner: object = None) -> FinePrior:
        """A copy of the lattices as they are now (for a frozen field: the live map keeps fusing into its own); with
        a `pool`, in memory from it that returns to it when `owner` is collected."""
        view = FinePrior(self.voxel_size_m, self.truncation_m, self.backend)
        view.state = self.state.clone() if pool is None else pool.copy(self.state, owner)
        return view

    def load(self, state: torch.Tensor) -> None:
        """Take saved lattices (V, (SUB+1)^3, 2) (a checkpoint's)."""
        if state.shape[1:] != (self.n**3, 2):
            raise ValueError(f"fine SDF prior lattices of shape {tuple(state.shape)}; expected (V, {self.n**3}, 2)")
        self.state = state.to(self.state.device, torch.float32)
        self._storage.release()

    @torch.no_grad()
    def share_faces(self, new_voxels: np.ndarray, neighbours: np.ndarray) -> None:
        """Start new voxels (n,) with their older face neighbours' (n,6) lattice values on the faces they share
        (-1 = no neighbour; neighbours as `VoxelOctree.face_neighbours` orders them).

        A face's lattice points exist once in each of the two voxels. A voxel allocated late has seen only the
        frames since, so where an older neighbour averages dozens of frames of free space, the newcomer can hold
        the one noisy frame that put a surface there: the field jumps across the face and renders show a sliver
        of surface in open space. Copying the older side's sums and weights once makes the two faces equal, and
        they stay equal: every later frame that reaches a face point fuses the same value into both voxels."""
        if len(new_voxels) == 0:
            return
        n = self.n
        lattice = self.state.view(-1, n, n, n, 2)  # (V, x, y, z, 2)
        is_new = np.zeros(self.state.shape[0], bool)
        is_new[new_voxels] = True
        for face in range(6):
            nb = neighbours[:, face]
            take = (nb >= 0) & ~is_new[np.maximum(nb, 0)]
            if not take.any():
                continue
            axis, positive = face // 2, face % 2 == 1
            dev = self.state.device
            mine = torch.from_numpy(new_voxels[take]).to(dev)
            theirs = torch.from_numpy(nb[take]).to(dev)
            own_side, their_side = (n - 1, 0) if positive else (0, n - 1)
            index: list[slice | int] = [slice(None)] * 3
            index[axis] = their_side
            shared = lattice[(theirs, *index)]  # (m, n, n, 2): the face alone, not the whole lattices
            index[axis] = own_side
            lattice[(mine, *index)] = shared

    # ------------------------------------------------------------------------------------------- fusion
    @torch.no_grad()
    def fuse(
        self,
        voxel_origin: torch.Tensor,
        depth_m: np.ndarray,
        K: np.ndarray,
        T_world_camera: np.ndarray,
        voxels: np.ndarray | None = None,
    ) -> None:
        """Average one frame's truncated projective SDF into every lattice point in view (voxels (V,3) origins);
        with `voxels` (M,) (distinct indices), into those voxels' lattices only."""
        n_voxels = min(voxel_origin.shape[0], self.state.shape[0])
        if voxels is not None:
            voxels = np.asarray(voxels, np.int64)
            voxels = voxels[voxels < n_voxels]
            if voxels.size == 0:
                return
        if n_voxels == 0:
            return
        T_camera_world = invert_se3(np.asarray(T_world_camera, np.float64))
        kernels = self._kernels()
        if kernels is None:
            self._fuse_reference(voxel_origin[:n_voxels], depth_m, K, T_camera_world, voxels)
            return
        kernels.fuse(  # type: ignore[attr-defined]
            np.ascontiguousarray(voxel_origin[:n_voxels].cpu().numpy(), np.float32),
            np.ascontiguousarray(depth_m, np.float32),
            np.ascontiguousarray(K, np.float64),
            np.ascontiguousarray(T_camera_world, np.float64),
            self.voxel_size_m,
            SUB,
            self.truncation_m,
            self.state.view(-1, 2).numpy(),
            voxels,
        )

    def _lattice_points(self, voxel_origin: torch.Tensor) -> torch.Tensor:
        """World positions (V, P, 3) of the voxels' lattice points, in flat lattice order (x-major)."""
        r = torch.arange(self.n, dtype=torch.float32, device=voxel_origin.device)
        grid = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), dim=-1).reshape(-1, 3)  # (P,3)
        return voxel_origin[:, None, :].float() + grid[None] * (self.voxel_size_m / SUB)

    def _fuse_reference(
        self,
        voxel_origin: torch.Tensor,
        depth_m: np.ndarray,
        K: np.ndarray,
        T_camera_world: np.ndarray,
        voxels: np.ndarray | None = None,
    ) -> None:
        """`fuse` in torch, every lattice point of every voxel (or of `voxels` (M,)) at once."""
        dev = self.state.device
        rows = torch.arange(voxel_origin.shape[0], device=dev) if voxels is None else torch.from_numpy(voxels).to(dev)
        pts = self._lattice_points(voxel_origin.to(dev)[rows]).reshape(-1, 3).double()  # (M*P,3)
        T = torch.from_numpy(np.asarray(T_camera_world, np.float64)).to(dev)
        cam = pts @ T[:3, :3].T + T[:3, 3]  # (V*P,3)
        z = cam[:, 2]
        front = z > 1e-6
        zs = torch.where(front, z, torch.ones_like(z))
        u = torch.round(K[0, 0] * cam[:, 0] / zs + K[0, 2])
        v = torch.round(K[1, 1] * cam[:, 1] / zs + K[1, 2])
        h, w = depth_m.shape
        inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        depth = torch.from_numpy(np.ascontiguousarray(depth_m, np.float32)).to(dev)
        d = torch.zeros_like(z)
        d[inside] = depth[v[inside].long(), u[inside].long()].double()
        sdf = d - z
        take = inside & (d > 0) & (sdf >= -self.truncation_m)
        val = (sdf.clamp(max=self.truncation_m) / self.truncation_m).float()
        P = self.n**3
        at = (rows[:, None] * P + torch.arange(P, device=dev)).reshape(-1)[take]  # flat rows (distinct) fused
        flat = self.state.view(-1, 2)  # written in place
        flat[at, 0] += val[take]
        flat[at, 1] += 1.0

    # ------------------------------------------------------------------------------------------- lookups
    def blend(
        self, voxel_origin: torch.Tensor, points: torch.Tensor, voxel: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """At points (N,3) in (or on the faces of) voxels (N,) with origins voxel_origin (V,3): the fused lattice
        points' part of the trilinear blend (N,) (tr units) and their share of the weights (N,) in [0, 1] (0 where
        no frame reached the lattice). Differentiable w.r.t. points that require gradients (autograd normals)."""
        wants_grad = torch.is_grad_enabled() and points.requires_grad
        if self._kernels() is None or points.device.type != "cpu" or wants_grad:
            return self.blend_reference(voxel_origin, points, voxel)
        value, cover = self.blend_numpy(voxel_origin.numpy(), points.detach().numpy(), voxel.numpy())
        return torch.from_numpy(value), torch.from_numpy(cover)

    def blend_numpy(
        self, voxel_origin: np.ndarray, points: np.ndarray, voxel: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """`blend` on CPU NumPy arrays (the meshing thread's), through the numba kernel when it imports."""
        kernels = self._kernels()
        if kernels is None:
            value_t, cover_t = self.blend_reference(
                torch.from_numpy(voxel_origin), torch.from_numpy(points), torch.from_numpy(voxel)
            )
            return value_t.numpy(), cover_t.numpy()
        p = np.ascontiguousarray(points, dtype=np.float32)
        value, cover = np.empty(p.shape[0], np.float32), np.empty(p.shape[0], np.float32)
        kernels.blend(  # type: ignore[attr-defined]
            p,
            np.ascontiguousarray(voxel, np.int64),
            np.ascontiguousarray(voxel_origin, np.float32),
            self.voxel_size_m,
            SUB,
            self.state.view(-1, 2).cpu().numpy(),
            value,
            cover,
        )
        return value, cover

    def blend_reference(
        self, voxel_origin: torch.Tensor, points: torch.Tensor, voxel: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """`blend` in torch."""
        dev = self.state.device
        value = torch.zeros(points.shape[0], device=dev, dtype=points.dtype)
        cover = torch.zeros(points.shape[0], device=dev, dtype=points.dtype)
        n_voxels = min(self.state.shape[0], voxel_origin.shape[0])  # a frozen copy may lag the live octree
        keep = ((voxel >= 0) & (voxel < n_voxels)).to(dev)
        if not bool(keep.any()):
            return value, cover
        p, vid = points.to(dev)[keep].float(), voxel.to(dev)[keep]
        local = ((p - voxel_origin.to(dev)[vid].float()) / self.voxel_size_m * SUB).clamp(0.0, float(SUB))  # (n,3)
        base = torch.floor(local).clamp(max=SUB - 1)
        frac = local - base
        offsets = _OFFSETS.to(dev)
        corner = base.long()[:, None, :] + offsets[None]  # (n,8,3)
        flat = vid[:, None] * self.n**3 + (corner[..., 0] * self.n + corner[..., 1]) * self.n + corner[..., 2]
        w = torch.where(offsets[None].bool(), frac[:, None, :], 1.0 - frac[:, None, :]).prod(dim=2)  # (n,8)
        sums = self.state.view(-1, 2)[flat]  # (n,8,2)
        seen = sums[..., 1] > 0
        mean = torch.where(seen, sums[..., 0] / sums[..., 1].clamp(min=1e-6), torch.zeros_like(w))
        value = value.index_put((keep,), (w * mean).sum(dim=1).to(value.dtype))
        cover = cover.index_put((keep,), (w * seen).sum(dim=1).to(cover.dtype))
        return value, cover
