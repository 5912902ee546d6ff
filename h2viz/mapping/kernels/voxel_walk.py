"""Ray walks through the allocated leaf voxels on the CPU: the Python side of the numba kernels in voxel_walk_numba.py.

- `voxel_hits`: every allocated voxel a ray crosses between t_near and t_far, with its entry and exit t
  (what `h2viz.mapping.sampling.samples.traverse` returns; two passes, count then fill);
- `render_lattice`: the samples a render may need, at exactly the positions of `sample_hits` without jitter
  (every `step` from each voxel's entry, the last one clipped to its exit, in the same float32 arithmetic),
  with the trilinear corner prior at each. In "trust" mode the walk stops `after_m` beyond the first sample
  whose prior is negative in a voxel with trusted priors, and flags as probes what must be evaluated first:
  the two samples around that prior crossing, the closest approach of a trusted near miss (a local minimum
  of the prior below `probe_below`, or the last trusted sample before the priors stop), and every third
  sample (and the last) of each untrusted voxel. "distrust" walks to t_far and probes every third sample of
  every voxel; "prior" trusts every voxel and stops at the first prior crossing + after_m. Chunks of rays
  walk in one pass each, side by side on a small thread pool (the kernel releases the GIL).

Rays are z-normalised (see sampling/samples.py), so t is depth along the camera axis.
"""

from __future__ import annotations

import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch
from scipy import ndimage

from h2viz.mapping.field.octree import VoxelOctree, decode
from h2viz.mapping.kernels.jit import parallel_region
from h2viz.mapping.kernels.voxel_walk_numba import MODES, build_table, hits_kernel, lattice_chunk


class WalkTable(NamedTuple):
    """What a walk needs to know of the map (a NamedTuple so that numba kernels take it whole)."""

    keys: np.ndarray  # (cap,) hash table of leaf keys, -1 = empty slot
    ids: np.ndarray  # (cap,) voxel id of each slot
    box: np.ndarray  # (2,3) bounding box of the leaves in metres, padded a little
    skip: np.ndarray  # (X,Y,Z) uint8 chessboard distance in skip cells to the nearest allocated voxel
    skip_lo: np.ndarray  # (3,) int64 coordinates of skip[0, 0, 0] (in skip cells)
    skip_shift: int  # a skip cell is 2**skip_shift voxels a side
    voxel_size: float


SKIP_CELLS = 1 << 20
"""Most cells of the empty-space grid; larger maps use coarser skip cells."""
_TABLES: weakref.WeakKeyDictionary[Any, tuple[np.ndarray, WalkTable]] = weakref.WeakKeyDictionary()


_HASHES: weakref.WeakKeyDictionary[Any, tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]] = weakref.WeakKeyDictionary()


def voxel_hash(octree: VoxelOctree) -> tuple[np.ndarray, np.ndarray]:
    """The octree's voxel hash table (keys, ids) alone, rebuilt only after voxels were added: what point lookups
    need, without the walk table's skip grid (a distance transform of ~5 ms on every frame that adds voxels)."""
    keys = octree.voxels.keys
    table = _TABLES.get(octree.voxels)
    if table is not None and table[0] is keys:
        return table[1].keys, table[1].ids
    cached = _HASHES.get(octree.voxels)
    if cached is not None and cached[0] is keys:
        return cached[1]
    pair = build_table(np.ascontiguousarray(keys, dtype=np.int64))
    _HASHES[octree.voxels] = (keys, pair)
    return pair


def walk_table(octree: VoxelOctree) -> WalkTable:
    """The octree's walk table, rebuilt only after voxels were added."""
    keys = octree.voxels.keys
    cached = _TABLES.get(octree.voxels)
    if cached is not None and cached[0] is keys:
        return cached[1]
    vs = octree.voxel_size_m
    coords = decode(keys) if keys.size else np.zeros((1, 3), np.int64)
    pad = 1e-3 * vs
    box = np.stack([coords.min(0) * vs - pad, (coords.max(0) + 1) * vs + pad]).astype(np.float64)
    table_keys, table_ids = build_table(np.ascontiguousarray(keys, dtype=np.int64))
    shift = 0
    while np.prod((coords.max(0) >> shift) - (coords.min(0) >> shift) + 1) > SKIP_CELLS:
        shift += 1
    cells = coords >> shift
    lo = cells.min(0)
    free = np.ones(tuple(cells.max(0) - lo + 1), dtype=bool)
    free[tuple((cells - lo).T)] = False
    skip = np.minimum(ndimage.distance_transform_cdt(free, metric="chessboard"), 255).astype(np.uint8)
    table = WalkTable(table_keys, table_ids, box, skip, lo.astype(np.int64), shift, float(vs))
    _TABLES[octree.voxels] = (keys, table)
    return table


def rays64(origins: torch.Tensor, dirs: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Rays (R,3) as contiguous float64 CPU arrays (the same values as the float32 tensors)."""
    o = np.ascontiguousarray(origins.detach().cpu().numpy(), dtype=np.float64)
    return o, np.ascontiguousarray(dirs.detach().cpu().numpy(), dtype=np.float64)


def _offsets(counts: np.ndarray) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)


def voxel_hits(
    octree: VoxelOctree, origins: torch.Tensor, dirs: torch.Tensor, t_near: torch.Tensor, t_far: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(ray, voxel, t_in, t_out) (H,) of every allocated voxel crossed by R rays, ray-major, front to back."""
    R, dev = origins.shape[0], origins.device
    if octree.n_voxels == 0 or R == 0:
        empty = torch.zeros(0, dtype=torch.long, device=dev)
        return empty, empty, empty.float(), empty.float()
    o, d = rays64(origins, dirs)
    near = np.ascontiguousarray(t_near.detach().cpu().numpy(), dtype=np.float64)
    far = np.ascontiguousarray(t_far.detach().cpu().numpy(), dtype=np.float64)
    args = (o, d, near, far, walk_table(octree))
    with parallel_region() as n_blocks:
        counts = hits_kernel(*args, np.zeros(R, np.int64), False, np.zeros(0, np.int64), np.zeros((0, 2)), n_blocks)
        voxel, t = np.empty(int(counts.sum()), np.int64), np.empty((int(counts.sum()), 2))
        hits_kernel(*args, _offsets(counts), True, voxel, t, n_blocks)
    ray = torch.from_numpy(np.repeat(np.arange(R, dtype=np.int64), counts))
    t32 = torch.from_numpy(t.astype(np.float32))
    return ray.to(dev), torch.from_numpy(voxel).to(dev), t32[:, 0].to(dev), t32[:, 1].to(dev)


class Lattice(NamedTuple):
    """Render samples of R rays, ray-major and front to back (S samples), in NumPy; see `render_lattice`.
    (A NamedTuple, so that numba kernels take it whole.)"""

    t: np.ndarray  # (S,) float32 depth along the camera axis
    voxel: np.ndarray  # (S,) int64 leaf voxel id
    prior: np.ndarray  # (S,) float32 trilinear corner prior, truncation units
    flags: np.ndarray  # (S,) uint8 PROBE | COARSE | TRUSTED
    ray: np.ndarray  # (S,) int64 ray index, non-decreasing
    start: np.ndarray  # (R,) int64 index of each ray's first sample
    count: np.ndarray  # (R,) int64 samples per ray
    crossing_end: np.ndarray  # (R,) the first prior crossing + after_m, where the walk stops (inf: none)

    @property
    def n_rays(self) -> int:
        return int(self.start.shape[0])


@dataclass(frozen=True)
class MarchParams:
    step_m: float
    mode: str  # trust | distrust | prior (see the module docstring)
    probe_below: float  # trusted near misses whose prior gets below this (truncation units) are probed
    after_m: float  # walk this far beyond the first prior crossing


def render_lattice(
    octree: VoxelOctree,
    priors: torch.Tensor,
    corner_ids: torch.Tensor,
    trusted: torch.Tensor | None,
    origins: np.ndarray,
    dirs: np.ndarray,
    t_far: np.ndarray,
    params: MarchParams,
) -> Lattice:
    """Walk R rays (origins, dirs (R,3) float64, t_far (R,) float64) through the leaves; priors (C,),
    corner_ids (V,8) and trusted (V,) bool (None: no voxel trusted) come from the field. Chunks of rays run
    on torch's number of threads, in one pass each."""
    R = origins.shape[0]
    trust = np.zeros(octree.n_voxels, np.bool_) if trusted is None else trusted.cpu().numpy().astype(np.bool_)
    args = (
        walk_table(octree),
        np.ascontiguousarray(priors.detach().cpu().numpy(), dtype=np.float32),
        np.ascontiguousarray(corner_ids.cpu().numpy(), dtype=np.int64),
        trust, params.step_m, MODES[params.mode], params.probe_below, params.after_m,
    )  # fmt: skip
    n = max(1, torch.get_num_threads())
    bounds = np.linspace(0, R, min(4 * n, max(R // 256, 1)) + 1).astype(np.int64)
    run = lambda b: lattice_chunk(origins, dirs, t_far, bounds[b], bounds[b + 1], *args)  # noqa: E731
    parts = list(_pool(n).map(run, range(len(bounds) - 1))) if n > 1 else [run(b) for b in range(len(bounds) - 1)]
    t, voxel, prior, flags, counts, crossing_end = (np.concatenate([p[k] for p in parts]) for k in range(6))
    ray = np.repeat(np.arange(R, dtype=np.int64), counts)
    return Lattice(t, voxel, prior, flags, ray, _offsets(counts), counts, crossing_end)


_POOLS: dict[int, ThreadPoolExecutor] = {}


def _pool(n: int) -> ThreadPoolExecutor:
    """A pool of n threads for the GIL-free walk kernels, made once per size."""
    if n not in _POOLS:
        _POOLS[n] = ThreadPoolExecutor(max_workers=n, thread_name_prefix="h2viz-walk")
    return _POOLS[n]
