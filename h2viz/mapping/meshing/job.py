"""Mesh extraction that can run beside mapping: a frozen copy of the field and a job that meshes with it.

The mapping thread builds a MeshJob in a few milliseconds (it copies the hash tables, decoders and corner
priors, and takes the voxel lists); the job may then run on any thread while mapping goes on training the
live field. Each lattice point's voxel comes from the mesher, so no voxel lookup is needed.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from h2viz.mapping.field.copy_pool import CopyPool
from h2viz.mapping.field.hybrid_field import HybridField, keep_prior_sign
from h2viz.mapping.meshing.mesher import ChunkedMesher, ChunkKey
from h2viz.mapping.meshing.observed import ObservedSupport

if TYPE_CHECKING:
    from h2viz.mapping.backend import Backend
from h2viz.types import MeshChunk

FIELD_BATCH = 1 << 16  # points per network call (the activations stay in cache)


class FrozenField:
    """A copy of a HybridField's parameters at one moment; evaluating it never touches the live field.

    sdf = trilinear(corner priors) + MLP(hash(x)), as HybridField.sdf. With the backend's array kernels the prior
    and, for the default decoder (one hidden ReLU layer) on CPU features, the decoder run in compiled
    single-threaded loops over the points: the meshing thread leaves the cores to mapping and builds no large
    intermediate arrays. Without them (None, "torch"), and for features on the GPU, the field's torch code runs.
    """

    def __init__(
        self,
        field: HybridField,
        truncation_m: float,
        prior_band: float = 0.0,
        backend: Backend | None = None,
        pool: CopyPool | None = None,
    ) -> None:
        """`pool`: where the large copies (hash tables, fine lattices) take their memory from; their storage goes
        back to it when this field is collected (None: fresh memory for each)."""
        prior, fine, octree = field.color_prior, field.fine_prior, field.octree
        field.color_prior, field.fine_prior, field.octree = None, None, None  # not deep-copied (~18 kB a voxel)
        memo: dict[int, object] = {}
        if pool is not None:  # deepcopy takes the pooled copies of the large parameters from its memo
            for p in field.parameters():
                memo[id(p)] = nn.Parameter(pool.copy(p, self), requires_grad=False)
        try:
            with torch.no_grad():
                frozen = copy.deepcopy(field, memo)
                frozen.requires_grad_(False)
                frozen.priors = frozen.priors.detach()
        finally:
            field.color_prior, field.fine_prior, field.octree = prior, fine, octree
        frozen.color_prior = None if prior is None else prior.shared()
        frozen.fine_prior = None if fine is None else fine.frozen(pool, self)  # geometry frozen too (~6 kB a voxel)
        frozen.octree = octree  # its lookups beyond the frozen voxels are ignored by the colour prior
        self.field = frozen
        self.truncation_m = float(truncation_m)
        self.prior_band = float(prior_band)  # tr units; 0 = surfaces wherever the residual puts them
        self.device = frozen.priors.device
        self.kernels = None if backend is None else backend.array_kernels
        if self.kernels is not None:
            self._priors = frozen.priors.cpu().numpy().astype(np.float32)  # (C,)
            self._corner_ids = frozen.corner_ids.cpu().numpy()  # (V,8) int64
            self._origin = frozen.voxel_origin.cpu().numpy().astype(np.float32)  # (V,3) metres
        on_cpu = self.device.type == "cpu"
        decoder = self.kernels.decoder if self.kernels is not None and on_cpu else None
        supported = decoder is not None and decoder.is_supported(frozen.geo_mlp)
        self._decoder = decoder.decoder_weights(frozen.geo_mlp) if decoder is not None and supported else None

    def prior(self, points: np.ndarray, voxel_ids: np.ndarray) -> np.ndarray:
        """Prior SDF in truncation units (N,) float32 at points (N,3) in (or on the faces of) voxels (N,)."""
        return self._prior_parts(points, voxel_ids)[0]

    def _prior_parts(self, points: np.ndarray, voxel_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The prior (N,) and the residual's weight (N,) or None (1), as `HybridField.prior_parts`."""
        pts = np.ascontiguousarray(points, dtype=np.float32)
        vox = np.ascontiguousarray(voxel_ids, dtype=np.int64)
        if self.kernels is None:
            p, v = torch.from_numpy(pts).to(self.device), torch.from_numpy(vox).to(self.device)
            with torch.no_grad():
                prior, weight = self.field.prior_parts(p, v)
            return prior.cpu().numpy().astype(np.float32), None if weight is None else weight.cpu().numpy()
        out = np.empty(len(points), dtype=np.float32)
        inv_vs = 1.0 / self.field.voxel_size_m
        blend = self.kernels.prior.blend_range
        blend(pts, vox, self._origin, self._corner_ids, self._priors, inv_vs, 0, len(pts), out)
        if self.field.fine_prior is None:
            return out, None
        value, cover = self.field.fine_prior.blend_numpy(self._origin, pts, vox)
        rest = np.float32(1.0) - cover
        return value + rest * out, None if self.field.fine_residual else rest

    @torch.no_grad()
    def sdf_m(self, points: np.ndarray, voxel_ids: np.ndarray) -> np.ndarray:
        """SDF in metres (N,) float32 at points (N,3) lying in (or on the faces of) voxels `voxel_ids` (N,), with
        the prior's sign beyond `prior_band` (see `keep_prior_sign`)."""
        prior, weight = self._prior_parts(points, voxel_ids)
        out = prior.copy()
        if self.field.use_residual:
            for i in range(0, len(points), FIELD_BATCH):
                p = torch.from_numpy(np.ascontiguousarray(points[i : i + FIELD_BATCH], np.float32)).to(self.device)
                feats = self.field.geo_grid(p)  # (n, L*F)
                if self._decoder is None or self.kernels is None:
                    residual = self.field.geo_mlp(feats).cpu().numpy()
                else:  # single-threaded: the cores are mapping's; CPU features (a decoder only on the CPU)
                    residual = np.empty((feats.shape[0], 1), np.float32)
                    decode = self.kernels.decoder.decode_range
                    decode(feats.contiguous().numpy(), *self._decoder, 0, feats.shape[0], residual)
                r = self.field.bound(torch.from_numpy(residual))[:, 0].numpy()
                out[i : i + FIELD_BATCH] += r if weight is None else r * weight[i : i + FIELD_BATCH]
        if self.prior_band > 0:
            out = keep_prior_sign(out, prior, self.prior_band)
        return out * np.float32(self.truncation_m)

    @torch.no_grad()
    def color_u8(self, points: np.ndarray) -> np.ndarray:
        """Colour (N,3) uint8 of the field at points (N,3)."""
        out = np.empty((len(points), 3), dtype=np.uint8)
        for i in range(0, len(points), FIELD_BATCH):
            p = torch.from_numpy(np.ascontiguousarray(points[i : i + FIELD_BATCH], np.float32)).to(self.device)
            rgb = (self.field.color(p) * 255.0).round().clamp(0, 255).to(torch.uint8)
            out[i : i + FIELD_BATCH] = rgb.cpu().numpy()
        return out


@dataclass(frozen=True)
class MeshJob:
    """One mesher update, frozen on the mapping thread and runnable on any thread (one job at a time)."""

    mesher: ChunkedMesher
    voxel_coords: np.ndarray  # (V,3) int64 voxels to mesh
    voxel_ids: np.ndarray  # (V,) int64 their ids in the octree (and the field's tables)
    dirty_voxels: np.ndarray  # (V,) bool allocated or observed since the last job: their points are re-evaluated
    field: FrozenField
    version: int  # stamped on the chunks it meshes
    field_version: int  # frames integrated into the frozen field
    refresh_s: float  # then refresh dirty voxels and the stalest chunks for up to this long
    whole: bool = False  # re-evaluate every chunk from this field (one consistent mesh, e.g. for export)
    support: ObservedSupport | None = None  # faces away from observed depth are left out (None: all kept)

    def run(
        self,
        stop: Callable[[], bool] | None = None,
        on_pass: Callable[[list[ChunkKey], bool], None] | None = None,
        hurry: Callable[[], bool] | None = None,
    ) -> dict[ChunkKey, MeshChunk]:
        """Mesh new voxels, then (within the budget, until `stop()` and while `hurry()` is not true) dirty voxels
        and stale chunks; see ChunkedMesher.update. Returns every chunk."""
        return self.mesher.update(
            self.voxel_coords,
            None if self.whole else (),
            self.field.sdf_m,
            self.field.color_u8,
            self.version,
            voxel_ids=self.voxel_ids,
            dirty_voxels=self.dirty_voxels,
            field_version=self.field_version,
            refresh_s=self.refresh_s,
            stop=stop,
            on_pass=on_pass,
            keep_fn=None if self.support is None else self.support.contains,
            hurry=hurry,
        )

    def after(self, older: MeshJob) -> MeshJob:
        """This job, also covering the dirty voxels of an `older` job it replaces before that one ran."""
        dirty = self.dirty_voxels | np.isin(self.voxel_ids, older.voxel_ids[older.dirty_voxels])
        refresh_s, whole = max(self.refresh_s, older.refresh_s), self.whole or older.whole
        return replace(self, dirty_voxels=dirty, refresh_s=refresh_s, whole=whole)
