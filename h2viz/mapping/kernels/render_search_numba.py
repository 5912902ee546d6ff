"""Numba kernels of the render search (render_search.py): which lattice samples to evaluate next, and the gathering
of the evaluated ones.

Per ray, a round proposes the unevaluated neighbours of the samples evaluated in the previous round that may
lie within theta of a surface, and the next `wave` probes. Rays own disjoint index ranges of the lattice, so
the kernels run one ray per iteration in parallel.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from h2viz.mapping.kernels.jit import njit
from h2viz.mapping.kernels.voxel_walk import Lattice
from h2viz.mapping.kernels.voxel_walk_numba import COARSE, PROBE, TRUSTED


class SearchState(NamedTuple):
    """Per-ray state of a search (R rays) and the SDF of the lattice's samples (S)."""

    sdf: np.ndarray  # (S,) float32, NaN where not evaluated
    t_neg: np.ndarray  # (R,) t of the first negative evaluated sample (inf: none yet)
    cursor: np.ndarray  # (R,) where the next probe wave starts looking
    waves: np.ndarray  # (R,) probe waves taken so far
    margin: np.ndarray  # (R,) most the SDF can change in one step (truncation units)


class Rules(NamedTuple):
    tr: float  # truncation distance (m): the weights end at the first negative sample + tr
    theta: float  # |SDF| beyond which a weight is negligible
    near: float  # walks over trusted priors propose samples predicted below this |SDF|
    wave: int  # probes per ray and round (doubling up to 16x on the rounds that follow)
    seeds: float  # the samples around a prior crossing lie beyond the walk's end (crossing_end) - this


@njit(inline=True)
def _walk(i: int, step: int, end: int, s_i: float, lat: Lattice, sdf: np.ndarray, t_limit: float, near: float,
          right: bool, out: np.ndarray) -> tuple[int, int]:  # fmt: skip
    """Mark unevaluated neighbours of evaluated sample i (SDF s_i) on one side (step -1 or +1, stopping
    before `end`). Across trusted priors the residual s_i - prior[i] carries over and the walk marks the
    samples predicted below `near` (in |SDF| on the right); into trusted priors from an untrusted sample it
    marks one; through untrusted ones it runs to the next coarse probe. Returns (newly marked, last index)."""
    i_trusted = (lat.flags[i] & TRUSTED) > 0
    j, n = i + step, 0
    while j != end and np.isnan(sdf[j]) and lat.t[j] <= t_limit:
        if lat.flags[j] & TRUSTED and i_trusted:
            p = lat.prior[j] + s_i - lat.prior[i]
            if (abs(p) if right else p) >= near:
                break
        n += not out[j]
        out[j] = True
        if (lat.flags[j] & TRUSTED and not i_trusted) or lat.flags[j] & COARSE:
            return n, j
        j += step
    return n, j - step


@njit(inline=True)
def _mark(j: int, out: np.ndarray, n: int, lo: int, hi: int) -> tuple[int, int, int]:
    """Mark sample j; returns the updated (newly marked, lowest, highest index)."""
    n += not out[j]
    out[j] = True
    return n, min(lo, j), max(hi, j)


@njit  # not inlined: numba drops writes to a NamedTuple's arrays made directly in a parallel loop's body
def _propose_ray(r: int, lat: Lattice, frontier: np.ndarray, f0: int, f1: int, st: SearchState, rules: Rules,
                 out: np.ndarray) -> tuple[int, int, int]:  # fmt: skip
    """Mark in `out` what ray r evaluates next, given the samples it evaluated last round (frontier[f0:f1]).
    Returns (newly marked, lowest, highest index marked)."""
    a, b, sdf, t = lat.start[r], lat.start[r] + lat.count[r], st.sdf, lat.t
    for q in range(f0, f1):
        if sdf[frontier[q]] < 0:
            st.t_neg[r] = min(st.t_neg[r], t[frontier[q]])
    t_limit = st.t_neg[r] + rules.tr
    n, lo, hi = 0, b, a - 1
    for q in range(f0, f1):
        i = frontier[q]
        if t[i] > t_limit:
            continue
        limit = rules.theta + st.margin[r] if lat.flags[i] & COARSE else rules.theta
        if sdf[i] < limit:
            k, j = _walk(i, -1, a - 1, sdf[i], lat, sdf, np.inf, rules.near, False, out)
            n, lo, hi = n + k, min(lo, j), max(hi, i - 1)
        if abs(sdf[i]) < limit:
            k, j = _walk(i, 1, b, sdf[i], lat, sdf, t_limit, rules.near, True, out)
            n, lo, hi = n + k, min(lo, i + 1), max(hi, j)
    last = frontier[f1 - 1] if f1 > f0 else a
    if n == 0 and st.t_neg[r] == np.inf and sdf[last] > 0 and t[last] >= lat.crossing_end[r] - rules.seeds:
        for j in range(last + 1, min(last + 5, b)):  # beyond the prior crossing with no surface yet: the
            if np.isnan(sdf[j]):  # residual moved it back; look four samples further
                n, lo, hi = _mark(j, out, n, lo, hi)
    k, taken, wave = st.cursor[r], 0, rules.wave << min(st.waves[r], 4)  # waves double: long runs end soon
    st.waves[r] += 1
    while k < b and taken < wave and t[k] <= t_limit:
        if lat.flags[k] & PROBE and np.isnan(sdf[k]):
            n, lo, hi = _mark(k, out, n, lo, hi)
            taken += 1
        k += 1
    st.cursor[r] = k
    return n, lo, hi


@njit(parallel=True)
def propose_kernel(lat: Lattice, active: np.ndarray, frontier: np.ndarray, f_lo: np.ndarray, st: SearchState,
                   rules: Rules, out: np.ndarray, marked: np.ndarray, lo: np.ndarray,
                   hi: np.ndarray) -> None:  # fmt: skip
    """Proposals of the active rays (A,); ray active[q] evaluated frontier[f_lo[q]:f_lo[q + 1]] last round."""
    for q in numba.prange(active.shape[0]):
        marked[q], lo[q], hi[q] = _propose_ray(active[q], lat, frontier, f_lo[q], f_lo[q + 1], st, rules, out)


@njit(parallel=True)
def take_marked(marked: np.ndarray, lo: np.ndarray, hi: np.ndarray, out: np.ndarray, offsets: np.ndarray,
                idx: np.ndarray) -> None:  # fmt: skip
    """idx <- the marked samples, ray-major (active ray q from offsets[q], within [lo[q], hi[q]]); clears the
    marks."""
    for q in numba.prange(marked.shape[0]):
        if marked[q]:
            k = offsets[q]
            for i in range(lo[q], hi[q] + 1):
                if out[i]:
                    idx[k], k, out[i] = i, k + 1, False


@njit(parallel=True)
def points_kernel(idx: np.ndarray, lat: Lattice, o: np.ndarray, d: np.ndarray, out: np.ndarray) -> None:
    """out (N,3) <- positions of the lattice samples idx (N,), in float32 arithmetic like torch's."""
    for k in numba.prange(idx.shape[0]):
        r, tk = lat.ray[idx[k]], lat.t[idx[k]]
        for a in range(3):
            out[k, a] = o[r, a] + d[r, a] * tk


@njit(parallel=True)
def count_evaluated(lat: Lattice, keep: np.ndarray, sdf: np.ndarray, n: np.ndarray) -> None:
    """n (R,) <- evaluated samples of each kept ray."""
    for r in numba.prange(lat.start.shape[0]):
        n[r] = 0
        if keep[r]:
            for i in range(lat.start[r], lat.start[r] + lat.count[r]):
                n[r] += not np.isnan(sdf[i])


@njit(parallel=True)
def take_evaluated(lat: Lattice, keep: np.ndarray, sdf: np.ndarray, o: np.ndarray, d: np.ndarray,
                   offsets: np.ndarray, out_t: np.ndarray, out_ray: np.ndarray, out_voxel: np.ndarray,
                   out_sdf: np.ndarray, out_points: np.ndarray) -> None:  # fmt: skip
    """The evaluated samples of the kept rays, ray r from offsets[r]; points in float32 like torch's."""
    for r in numba.prange(lat.start.shape[0]):
        if keep[r]:
            k = offsets[r]
            for i in range(lat.start[r], lat.start[r] + lat.count[r]):
                if not np.isnan(sdf[i]):
                    out_t[k], out_ray[k], out_voxel[k], out_sdf[k] = lat.t[i], r, lat.voxel[i], sdf[i]
                    for a in range(3):
                        out_points[k, a] = o[r, a] + d[r, a] * lat.t[i]
                    k += 1
