"""Which render samples the geometry network evaluates: only those that can carry rendering weight.

A sample whose SDF s (truncation units) has |s| >= theta = temperature * ln(1 / images.NEGLIGIBLE_WEIGHT) gets a
rendering weight sigmoid(s/tau) * sigmoid(-s/tau) below NEGLIGIBLE_WEIGHT. Evaluation starts at the
lattice's probes (voxel_walk.py) and spreads, round by round, along each ray to the neighbours of evaluated
samples that may lie within theta of a surface: towards the camera while s < theta (in front of the surface,
or behind one further forward), away from it while |s| < theta, never beyond the ray's first negative sample
+ tr (the weights end there). Between two samples in voxels with trusted priors the residual s - prior
carries over, so a round proposes every sample predicted within theta + NEAR_SLACK at once; into voxels
without trusted priors a round proposes the samples up to the next coarse probe (every third sample), and a
coarse probe spreads while s < theta + the most the SDF can change in one step (LIPSCHITZ).

A ray takes its probes front to back, `wave` per round; it stops probing behind its first negative sample +
tr. A ray whose priors crossed zero but whose SDF shows no surface by the end of the walk (the residual moved
it further away) is walked again to t_far without trusting the priors. The bookkeeping runs in numba
(render_search_numba.py); only the networks run in torch.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from h2viz.mapping.field.hybrid_field import HybridField
from h2viz.mapping.field.octree import VoxelOctree
from h2viz.mapping.kernels import render_search_numba as ls
from h2viz.mapping.kernels.jit import parallel_region
from h2viz.mapping.kernels.voxel_walk import Lattice, MarchParams, rays64, render_lattice
from h2viz.mapping.rendering.images import SearchParams
from h2viz.mapping.sampling.samples import Samples

LIPSCHITZ = 1.5
"""Assumed bound on how fast the SDF changes per metre (1 for a true distance field), for coarse probes."""
NEAR_SLACK = 0.05
"""A walk over trusted priors proposes the samples predicted within theta + this of the surface."""
PRIOR_WEIGHT = 1e-6
"""Prior-only renders keep the samples above this weight (costless: no network runs on them)."""
NEAR_MISS = 0.5
"""Trusted priors that come within theta + this of zero without crossing it are probed there."""


def search_rules(params: SearchParams) -> ls.Rules:
    """The lattice search's rules for a render's search settings."""
    seeds = params.after_m + 1.5 * params.step_m
    return ls.Rules(params.truncation_m, params.theta, params.theta + NEAR_SLACK, params.wave, seeds)


def residual_sdf(field: HybridField, points: torch.Tensor) -> torch.Tensor:
    """The hash-grid part of `HybridField.sdf` (N,): sdf = trilinear prior + this."""
    if not field.use_residual:
        return torch.zeros(points.shape[0], device=points.device)
    return field.residual(field.geo_grid(points))[:, 0]


class LatticeSearch:
    """The field's SDF on a growing subset of a lattice's samples (NaN where not evaluated)."""

    def __init__(self, field: HybridField, lat: Lattice, o: np.ndarray, d: np.ndarray, params: SearchParams) -> None:
        self.field, self.lat, self.rules = field, lat, search_rules(params)
        self.o, self.d = o.astype(np.float32), d.astype(np.float32)  # (R,3) exactly the torch rays
        R, S = lat.start.shape[0], lat.t.shape[0]
        margin = LIPSCHITZ * params.step_m / params.truncation_m * np.linalg.norm(d, axis=1)
        self.state = ls.SearchState(
            np.full(S, np.nan, np.float32), np.full(R, np.inf), lat.start.copy(), np.zeros(R, np.int64), margin
        )
        self._marks = np.zeros(S, np.bool_)  # (S,) proposals of the current round
        self._active = np.flatnonzero(lat.count > 0)  # (A,) rays that may still propose samples
        self._frontier = np.zeros(0, np.int64)  # (F,) samples evaluated last round, ray-major
        self._f_lo = np.zeros(self._active.shape[0] + 1, np.int64)  # (A+1,) each active ray's frontier range

    @property
    def sdf(self) -> np.ndarray:
        return self.state.sdf

    def points(self, idx: np.ndarray) -> torch.Tensor:
        out = np.empty((idx.shape[0], 3), np.float32)
        with parallel_region():
            ls.points_kernel(idx, self.lat, self.o, self.d, out)
        return torch.from_numpy(out)

    def propose(self) -> np.ndarray:
        """Indices (N,) of the samples to evaluate next (ray-major). A ray that proposes nothing is done: only
        its own evaluations could give it something new."""
        A = self._active.shape[0]
        marked, lo, hi = np.empty(A, np.int64), np.empty(A, np.int64), np.empty(A, np.int64)
        with parallel_region():
            ls.propose_kernel(self.lat, self._active, self._frontier, self._f_lo, self.state, self.rules,
                              self._marks, marked, lo, hi)  # fmt: skip
            f_lo = np.zeros(A + 1, np.int64)
            np.cumsum(marked, out=f_lo[1:])
            idx = np.empty(int(f_lo[-1]), np.int64)
            ls.take_marked(marked, lo, hi, self._marks, f_lo[:-1], idx)
        busy = marked > 0
        self._active, self._frontier = self._active[busy], idx
        self._f_lo = np.concatenate([f_lo[:-1][busy], f_lo[-1:]])
        return idx

    def run(self, device: torch.device) -> LatticeSearch:
        """Propose and evaluate until nothing more may carry weight."""
        while (idx := self.propose()).size:
            points = self.points(idx).to(device)
            residual = residual_sdf(self.field, points).float().cpu().numpy()
            prior, weight = self._prior(points, idx)
            self.sdf[idx] = prior + (residual if weight is None else residual * weight)
        return self

    def _prior(self, points: torch.Tensor, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The prior SDF (n,) at lattice samples idx (n,) and the residual's weight (n,) or None (1): the walk's
        corner prior, or the field's own where it has fine priors that the walk does not see."""
        if self.field.fine_prior is None:
            return self.lat.prior[idx], None
        voxel = torch.from_numpy(self.lat.voxel[idx]).to(points.device)
        with torch.no_grad():
            prior, weight = self.field.prior_parts(points, voxel)
        return prior.float().cpu().numpy(), None if weight is None else weight.float().cpu().numpy()

    def samples(self, keep_ray: np.ndarray | None) -> tuple[np.ndarray, ...]:
        """The evaluated samples of the rays with keep_ray (R,) True (all when None), ray-major:
        t (N,), ray (N,), voxel (N,), sdf (N,), points (N,3)."""
        R = self.lat.start.shape[0]
        keep = np.ones(R, np.bool_) if keep_ray is None else keep_ray
        n = np.empty(R, np.int64)
        with parallel_region():
            ls.count_evaluated(self.lat, keep, self.sdf, n)
            N = int(n.sum())
            out = (np.empty(N, np.float32), np.empty(N, np.int64), np.empty(N, np.int64), np.empty(N, np.float32))
            out += (np.empty((N, 3), np.float32),)
            ls.take_evaluated(self.lat, keep, self.sdf, self.o, self.d, np.cumsum(n) - n, *out)
        return out


def weighted_samples(
    field: HybridField,
    octree: VoxelOctree,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    t_far: float,
    trusted: torch.Tensor | None,
    params: SearchParams,
) -> tuple[Samples, torch.Tensor]:
    """Samples (S',) of R rays (origins, dirs (R,3)) that may carry rendering weight, with their SDF (S',),
    at an exhaustive walk's sample positions. trusted (V,) bool marks voxels whose corner priors locate the
    surface (None: no priors; every voxel is searched coarse then fine with the full SDF)."""
    o, d = rays64(origins, dirs)
    far = np.full(o.shape[0], t_far)
    args = (octree, field.priors, field.corner_ids, trusted)
    mode = "distrust" if trusted is None else "trust"
    lat = render_lattice(*args, o, d, far, MarchParams(params.step_m, mode, params.theta + NEAR_MISS, params.after_m))
    first = LatticeSearch(field, lat, o, d, params).run(origins.device)
    again = first.state.t_neg + params.truncation_m > lat.crossing_end  # (R,) the SDF's surface is further
    parts = [(first, ~again, np.arange(o.shape[0]))]
    if again.any():
        rays = np.flatnonzero(again)
        redo = MarchParams(params.step_m, "distrust", 0.0, params.after_m)
        lat2 = render_lattice(*args, o[rays], d[rays], far[rays], redo)
        parts.append((LatticeSearch(field, lat2, o[rays], d[rays], params).run(origins.device), None, rays))
    return _gather(parts, o.shape[0], origins.device)


def _gather(parts: list, n_rays: int, device: torch.device) -> tuple[Samples, torch.Tensor]:
    """Samples and SDF of each (search, keep_ray or None, ray ids) part, concatenated."""
    pieces = []
    for search, keep_ray, rays in parts:
        t, ray, voxel, sdf, points = search.samples(keep_ray)
        pieces.append((t, rays[ray], voxel, sdf, points))
    cat = [torch.from_numpy(np.concatenate([p[k] for p in pieces])).to(device) for k in range(5)]
    return Samples(cat[4], cat[0], cat[1], cat[2], n_rays), cat[3]


def prior_samples(
    octree: VoxelOctree,
    field: HybridField,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    t_far: float,
    params: SearchParams,
) -> tuple[Samples, torch.Tensor]:
    """The lattice samples up to the first prior crossing + tr whose weight is above PRIOR_WEIGHT (and every
    negative one, for the crossing), with the prior as SDF (no networks)."""
    o, d = rays64(origins, dirs)
    after = params.truncation_m + params.step_m
    fine = field.fine_prior is not None  # the walk knows only the corner priors: walk to t_far, blend the field's
    march = MarchParams(params.step_m, "distrust" if fine else "prior", 0.0, after)
    lat = render_lattice(octree, field.priors, field.corner_ids, None, o, d, np.full(o.shape[0], t_far), march)
    search = LatticeSearch(field, lat, o, d, params)
    prior = lat.prior
    if fine:
        idx = np.arange(lat.t.shape[0])
        points, voxel = search.points(idx).to(origins.device), torch.from_numpy(lat.voxel).to(origins.device)
        with torch.no_grad():
            prior = field.prior_sdf(points, voxel).float().cpu().numpy()
        first = np.full(lat.n_rays, np.inf, np.float32)  # (R,) each ray's first negative prior sample
        neg = prior < 0
        np.minimum.at(first, lat.ray[neg], lat.t[neg])
        prior = np.where(lat.t <= first[lat.ray] + after, prior, np.inf)  # the walk in "prior" mode stops there
    keep = prior < params.temperature * math.log(1.0 / PRIOR_WEIGHT)  # the prior is the SDF
    search.sdf[:] = np.where(keep, prior, np.nan)
    return _gather([(search, None, np.arange(o.shape[0]))], o.shape[0], origins.device)
