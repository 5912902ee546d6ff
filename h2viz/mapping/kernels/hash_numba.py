"""Fused CPU kernels (numba) of the hash-grid encoding: features and the gradient w.r.t. the tables.

Same lattice, hash and corner order as `h2viz.mapping.field.encoding`, whose pure-torch path is the reference.
Each point's position is divided by the cell size in float64, its 8 corner rows are hashed in int64 and
masked to [0, T) (equal to the remainder for a power-of-two T, negatives included), and the corners are
blended with float64 trilinear weights. Nothing is materialised per corner: one pass reads the points and
writes the features, and the backward pass recomputes the corners and scatters into a zero-filled table.

Parallel layout: the forward pass splits the points into one block per thread and walks one level at a
time inside a block (one table at a time is kinder to caches and the TLB); while it blends a point it
prefetches the table rows of the point PREFETCH_AHEAD places further, so that cache misses overlap. The
backward pass gives every level to exactly one thread (no two threads add into the same row), coarse and
fine levels interleaved across threads; each level sums its points in order, so gradients are deterministic
and do not depend on the thread count. It prefetches rows the same way (49k samples: 11 -> 6 ms a grid).
F = 2 (the default) has its own blend, ~20 % faster than the loop.

Compiled code is cached next to this file (or in numba's user cache directory when that is read-only, or
in NUMBA_CACHE_DIR); without any writable cache the kernels compile in every process (a few seconds).
Importing this module raises ImportError when numba is not installed.
"""

from __future__ import annotations

import time
import weakref
from collections.abc import Sequence
from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from h2viz.errors import H2vizError
from h2viz.mapping.field.encoding import HASH_PRIMES
from h2viz.mapping.kernels.jit import njit, parallel_region, prefetch

P_Y, P_Z = HASH_PRIMES[1], HASH_PRIMES[2]  # the x multiplier is 1
PREFETCH_AHEAD = 8
"""Points between the one being blended (or scattered) and the one whose table rows are prefetched."""


@njit
def _corners(x0: float, x1: float, x2: float, cell: float, mask: int) -> tuple[Any, Any]:
    """Table rows (8 ints in [0, T)) and trilinear weights (8 floats) of a point's cell, corner 4dx+2dy+dz."""
    px, py, pz = x0 / cell, x1 / cell, x2 / cell
    fx, fy, fz = np.floor(px), np.floor(py), np.floor(pz)
    tx, ty, tz = px - fx, py - fy, pz - fz
    hx, hy, hz = np.int64(fx), np.int64(fy) * P_Y, np.int64(fz) * P_Z  # int64 wraps like torch's
    x_lo, x_hi = hx & mask, (hx + 1) & mask  # masking each term commutes with XOR
    y_lo, y_hi = hy & mask, (hy + P_Y) & mask
    z_lo, z_hi = hz & mask, (hz + P_Z) & mask
    a, b, c, d = x_lo ^ y_lo, x_lo ^ y_hi, x_hi ^ y_lo, x_hi ^ y_hi
    rows = (a ^ z_lo, a ^ z_hi, b ^ z_lo, b ^ z_hi, c ^ z_lo, c ^ z_hi, d ^ z_lo, d ^ z_hi)
    sx, sy, sz = 1.0 - tx, 1.0 - ty, 1.0 - tz
    w00, w01, w10, w11 = sx * sy, sx * ty, tx * sy, tx * ty
    weights = (w00 * sz, w00 * tz, w01 * sz, w01 * tz, w10 * sz, w10 * tz, w11 * sz, w11 * tz)
    return rows, weights


@njit
def _prefetch_corners(x: np.ndarray, p: int, table: np.ndarray, cell: float, mask: int) -> None:
    """Prefetch the 8 table rows (T,F) of point p's cell."""
    rows, _ = _corners(x[p, 0], x[p, 1], x[p, 2], cell, mask)
    for c in range(8):
        prefetch(table, rows[c])


@njit
def _blend_block(
    x: np.ndarray, table: np.ndarray, cell: float, start: int, stop: int, col: int, out: np.ndarray
) -> None:
    """out[start:stop, col:col+F] <- one level's features of points start..stop-1 from its table (T,F)."""
    mask = table.shape[0] - 1
    n_feat = table.shape[1]
    for p in range(start, stop):
        if p + PREFETCH_AHEAD < stop:
            _prefetch_corners(x, p + PREFETCH_AHEAD, table, cell, mask)
        r, w = _corners(x[p, 0], x[p, 1], x[p, 2], cell, mask)
        if n_feat == 2:
            a0, a1 = 0.0, 0.0
            for c in range(8):
                a0 += w[c] * table[r[c], 0]
                a1 += w[c] * table[r[c], 1]
            out[p, col], out[p, col + 1] = a0, a1
        else:
            for f in range(n_feat):
                a = 0.0
                for c in range(8):
                    a += w[c] * table[r[c], f]
                out[p, col + f] = a


@njit
def _scatter_level(x: np.ndarray, grad_out: np.ndarray, cell: float, col: int, grad: np.ndarray) -> None:
    """grad (T,F) <- zeros, then every point's upstream gradient spread onto its 8 corner rows."""
    flat = grad.reshape(-1)
    for i in range(flat.shape[0]):
        flat[i] = 0
    mask = grad.shape[0] - 1
    n_feat = grad.shape[1]
    n = x.shape[0]
    for p in range(n):
        if p + PREFETCH_AHEAD < n:
            _prefetch_corners(x, p + PREFETCH_AHEAD, grad, cell, mask)
        r, w = _corners(x[p, 0], x[p, 1], x[p, 2], cell, mask)
        if n_feat == 2:
            u0, u1 = grad_out[p, col], grad_out[p, col + 1]
            for c in range(8):
                grad[r[c], 0] += w[c] * u0
                grad[r[c], 1] += w[c] * u1
        else:
            for f in range(n_feat):
                up = grad_out[p, col + f]
                for c in range(8):
                    grad[r[c], f] += w[c] * up


@njit(parallel=True)
def _forward_kernel(x: np.ndarray, tables: np.ndarray, cells: np.ndarray, n_blocks: int, out: np.ndarray) -> None:
    """out (N, L*F) <- features of x (N,3) float64 from tables (L,T,F); blocks of points x levels in parallel."""
    n, n_levels, n_feat = x.shape[0], tables.shape[0], tables.shape[2]
    for task in numba.prange(n_levels * n_blocks):
        block, level = task // n_levels, task % n_levels
        start, stop = block * n // n_blocks, (block + 1) * n // n_blocks
        _blend_block(x, tables[level], cells[level], start, stop, level * n_feat, out)


@njit(parallel=True)
def _table_grad_kernel(
    x: np.ndarray, grad_out: np.ndarray, cells: np.ndarray, level_order: np.ndarray, grad: np.ndarray
) -> None:
    """grad (L,T,F) <- d(sum grad_out * features)/d tables for x (N,3) float64; one thread per level."""
    n_feat = grad.shape[2]
    for task in numba.prange(level_order.shape[0]):
        level = level_order[task]
        _scatter_level(x, grad_out, cells[level], level * n_feat, grad[level])


def level_order(n_levels: int) -> np.ndarray:
    """Levels alternately from both ends (0, L-1, 1, L-2, ...), so that the contiguous share of levels each
    thread receives mixes coarse (few distinct cells) and fine (many cache misses) levels."""
    ends = [(i, n_levels - 1 - i) for i in range((n_levels + 1) // 2)]
    order = [level for pair in ends for level in dict.fromkeys(pair)]
    return np.asarray(order, dtype=np.int64)


def _points64(x: Tensor) -> Tensor:
    """x (N,3) as a contiguous float64 CPU tensor (positions are scaled in float64, as in the torch path)."""
    return x.detach().to(torch.float64).contiguous()


def _check_shapes(x: Tensor, table_shape: Sequence[int], n_cells: int) -> None:
    """The kernels do not check bounds: raise H2vizError for inputs they cannot index safely."""
    if x.ndim != 2 or x.shape[1] != 3:
        raise H2vizError(f"hash-grid points must be shaped (N,3), got {tuple(x.shape)}; reshape to (-1, 3)")
    if len(table_shape) != 3 or table_shape[1] & (table_shape[1] - 1) or n_cells != table_shape[0]:
        raise H2vizError(f"hash tables {tuple(table_shape)} need shape (L,T,F), T a power of two, L cell sizes")


def forward_features(x64: Tensor, tables: Tensor, cell_sizes_m: Sequence[float]) -> Tensor:
    """Features (N, L*F) in the tables' dtype of points x64 (N,3) float64 from tables (L,T,F); no autograd."""
    _check_shapes(x64, tables.shape, len(cell_sizes_m))
    n_levels, _, n_feat = tables.shape
    out = torch.empty(x64.shape[0], n_levels * n_feat, dtype=tables.dtype)  # (N, L*F)
    if x64.shape[0] == 0:
        return out
    cells = np.asarray(cell_sizes_m, dtype=np.float64)
    tab = tables.detach().contiguous().numpy()
    with parallel_region() as n_blocks:
        _forward_kernel(x64.numpy(), tab, cells, n_blocks, out.numpy())
    return out


def table_gradient(
    x64: Tensor, grad_out: Tensor, cell_sizes_m: Sequence[float], table_shape: torch.Size, out: Tensor | None = None
) -> Tensor:
    """Dense gradient (L,T,F) of sum(grad_out * features) w.r.t. the tables, for points x64 (N,3) float64.

    `out`, a contiguous CPU tensor of that shape and grad_out's dtype, is overwritten instead of allocating.
    """
    _check_shapes(x64, table_shape, len(cell_sizes_m))
    if grad_out.shape != (x64.shape[0], table_shape[0] * table_shape[2]):
        raise H2vizError(f"upstream gradient {tuple(grad_out.shape)} does not match points {tuple(x64.shape)}")
    if out is not None and (out.shape != table_shape or out.dtype != grad_out.dtype or not out.is_contiguous()):
        raise H2vizError(f"gradient buffer must be a contiguous {grad_out.dtype} tensor shaped {tuple(table_shape)}")
    grad = torch.empty(table_shape, dtype=grad_out.dtype) if out is None else out  # zero-filled by the kernel
    cells = np.asarray(cell_sizes_m, dtype=np.float64)
    with parallel_region():
        _table_grad_kernel(x64.numpy(), grad_out.contiguous().numpy(), cells, level_order(len(cells)), grad.numpy())
    return grad


_GRAD_BUFFERS: dict[int, tuple[weakref.ref[Tensor], Tensor, int]] = {}
"""Per table: a gradient buffer and its storage's use count when nothing but the buffer holds it. A fresh 16 MB
gradient per backward pass costs ~1.5 ms in page faults alone; the buffer is reused once no gradient handed
out over it is alive any more (the optimiser's zero_grad dropped it), and never while one is."""


def _storage_uses(t: Tensor) -> int:
    """References to t's storage (torch-internal counter; -1 where this torch does not expose it)."""
    counter = getattr(torch._C, "_storage_Use_Count", None)
    return int(counter(t.untyped_storage()._cdata)) if counter is not None else -1


def _gradient_buffer(tables: Tensor, dtype: torch.dtype) -> Tensor:
    """A contiguous (L,T,F) tensor to write the next table gradient into, over a reused buffer when free."""
    entry = _GRAD_BUFFERS.get(id(tables))
    if entry is not None and entry[0]() is tables and entry[2] >= 0 and _storage_uses(entry[1]) == entry[2]:
        buffer = entry[1]
        if buffer.shape == tables.shape and buffer.dtype == dtype:
            return buffer.view(tables.shape)  # a new tensor over the buffer: autograd adopts it without a copy
    for key in [k for k, (ref, _, _) in _GRAD_BUFFERS.items() if ref() is None]:
        del _GRAD_BUFFERS[key]  # tables that no longer exist
    buffer = torch.empty(tables.shape, dtype=dtype)
    _GRAD_BUFFERS[id(tables)] = (weakref.ref(tables), buffer, _storage_uses(buffer))
    return buffer.view(tables.shape)


class _FusedEncode(torch.autograd.Function):
    """Hash-grid features with the fused kernels; differentiable w.r.t. the tables only."""

    @staticmethod
    def forward(ctx: Any, tables: Tensor, x64: Tensor, cell_sizes_m: tuple[float, ...]) -> Tensor:
        """tables (L,T,F), points x64 (N,3) float64 -> features (N, L*F)."""
        ctx.save_for_backward(x64)
        ctx.cell_sizes_m, ctx.tables = cell_sizes_m, tables
        return forward_features(x64, tables, cell_sizes_m)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, None, None]:
        """grad_out (N, L*F) -> dense table gradient (L,T,F)."""
        (x64,) = ctx.saved_tensors
        if not ctx.needs_input_grad[0]:
            return None, None, None
        out = _gradient_buffer(ctx.tables, grad_out.dtype)
        return table_gradient(x64, grad_out, ctx.cell_sizes_m, ctx.tables.shape, out=out), None, None


def fused_encode(x: Tensor, tables: Tensor, cell_sizes_m: Sequence[float]) -> Tensor:
    """Features (N, L*F) of CPU points x (N,3) from CPU tables (L,T,F); gradients reach the tables, not x."""
    if x.device.type != "cpu" or tables.device.type != "cpu":
        raise H2vizError("the fused hash-grid kernels run on the CPU; use encoding.encode for other devices")
    if torch.is_grad_enabled() and x.requires_grad:
        raise H2vizError("the fused hash-grid kernels give no gradient w.r.t. points; use encoding.encode")
    x64 = _points64(x)
    if torch.is_grad_enabled() and tables.requires_grad:
        return _FusedEncode.apply(tables, x64, tuple(cell_sizes_m))
    return forward_features(x64, tables, cell_sizes_m)


def warmup(dtype: torch.dtype = torch.float32) -> float:
    """Compile (or load from the cache) both kernels for `dtype` tables on tiny inputs; returns seconds."""
    start = time.perf_counter()
    tables = torch.zeros(2, 16, 2, dtype=dtype, requires_grad=True)
    x = torch.rand(5, 3, dtype=torch.float64)
    fused_encode(x, tables, (0.1, 0.05)).sum().backward()
    return time.perf_counter() - start
