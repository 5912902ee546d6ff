"""Multiresolution spatial-hash feature grid over unbounded world coordinates (pure torch, CPU and CUDA).

Level l has cubic cells of edge `base_cell_m / scale**l` anchored at the world origin. A point reads the
F features stored at the 8 corners of its cell and blends them trilinearly; the levels are concatenated
coarse to fine. A corner with integer lattice coordinates (i, j, k) lives at entry
`(i * 1 ^ j * 2654435761 ^ k * 805459861) mod T` of its level's table (int64 arithmetic, correct for
negative coordinates), so no scene bounds are needed. Corners are ordered `4 * dx + 2 * dy + dz`.
Valid inputs: finite metres with |x| / finest cell < 2**31 (about 27 000 km at the default sizes).

With the "numba" backend, HashGrid runs the fused kernels of `kernels.hash_numba` on CPU tensors; the torch
functions here are the reference, serve CUDA and the gradient w.r.t. points.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from h2viz.errors import ConfigError, H2vizError

if TYPE_CHECKING:
    from h2viz.mapping.backend import Backend

HASH_PRIMES: tuple[int, int, int] = (1, 2654435761, 805459861)
"""Per-axis multipliers of the spatial hash (x, y, z)."""


def level_cell_sizes(n_levels: int = 4, base_cell_m: float = 0.1, scale: float = 2.0) -> list[float]:
    """Cell edge in metres of each level, coarse to fine: base_cell_m / scale**l."""
    return [base_cell_m / scale**level for level in range(n_levels)]


def spatial_hash(corners: Tensor, table_size: int) -> Tensor:
    """Table index in [0, table_size) of integer lattice corners (..., 3) int64 -> (...) int64."""
    h = corners[..., 0] * HASH_PRIMES[0]
    h = h ^ (corners[..., 1] * HASH_PRIMES[1])
    h = h ^ (corners[..., 2] * HASH_PRIMES[2])
    return torch.remainder(h, table_size)


def corners_and_weights(
    x: Tensor, cell_sizes_m: list[float], log2_size: int, weight_dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """Flat table row (level * T + hash) (8,L,N) int32 and trilinear weight (8,L,N) of every cell corner.

    Positions are divided by the cell size in float64 so that the in-cell fraction stays accurate far
    from the origin; the weights are differentiable w.r.t. x. Corners and levels lead so that every
    elementwise step runs over long contiguous runs of points.
    """
    n, n_levels, mask = x.shape[0], len(cell_sizes_m), (1 << log2_size) - 1
    cells = torch.tensor(cell_sizes_m, dtype=torch.float64, device=x.device)  # (L,)
    primes = torch.tensor(HASH_PRIMES, device=x.device)[:, None, None]  # (3,1,1)
    level_row = (torch.arange(n_levels, device=x.device, dtype=torch.int32) << log2_size)[:, None]  # (L,1)
    pos = x.to(torch.float64).T[:, None, :] / cells[:, None]  # (3,L,N) in cells
    lower = torch.floor(pos)
    frac = (pos - lower).to(weight_dtype)  # (3,L,N) in [0,1)
    # Hash terms of the lower and upper corner per axis, multiplied in int64 and masked to T. XOR
    # commutes with the mask, so XOR-ing the masked terms gives (i*p0 ^ j*p1 ^ k*p2) mod T; the level
    # offset (a multiple of T) is an OR. Masked values fit int32, which XORs far faster than int64.
    low = lower.long() * primes  # (3,L,N)
    terms = (torch.stack([low, low + primes]) & mask).int()  # (2,3,L,N) lower / upper corner
    tx = terms[:, 0] | level_row  # (2,L,N)
    rows = (tx[:, None] ^ terms[None, :, 1]).view(4, n_levels, n)
    rows = (rows[:, None] ^ terms[None, :, 2]).view(8, n_levels, n)  # corner 4*dx + 2*dy + dz
    ramps = torch.stack([1.0 - frac, frac])  # (2,3,L,N) weight of the lower / upper corner per axis
    weights = (ramps[:, None, 0] * ramps[None, :, 1]).view(4, n_levels, n)
    weights = (weights[:, None] * ramps[None, :, 2]).view(8, n_levels, n)
    return rows, weights


class _GatherBlend(torch.autograd.Function):
    """sum_c weights[c] * table[rows[c]], one feature column at a time, with a hand-written backward.

    Column-wise 1-D index_select / index_add_ run about twice as fast on CPU as their (R,F) row
    versions, which autograd's index_select backward would use (see bench/encoding.py).
    """

    @staticmethod
    def forward(ctx: Any, table: Tensor, rows: Tensor, weights: Tensor) -> Tensor:
        """table (R,F), rows (8,M) int32, weights (8,M) -> blended features (F,M)."""
        columns = table.T.contiguous()  # (F,R)
        idx = rows.reshape(-1)
        out = torch.stack([(weights * col.index_select(0, idx).view_as(weights)).sum(0) for col in columns])
        ctx.save_for_backward(columns if ctx.needs_input_grad[2] else None, rows, weights)
        ctx.n_rows = table.shape[0]
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, None, Tensor | None]:
        """Table gradient by column-wise index_add_; weight gradient only when x needs one."""
        columns, rows, weights = ctx.saved_tensors
        idx = rows.reshape(-1)
        grad_table = grad_weights = None
        if ctx.needs_input_grad[0]:
            grad_columns = grad_out.new_zeros(grad_out.shape[0], ctx.n_rows)  # (F,R)
            for f in range(grad_out.shape[0]):
                grad_columns[f].index_add_(0, idx, (weights * grad_out[f]).reshape(-1))
            grad_table = grad_columns.T
        if ctx.needs_input_grad[2]:
            grad_weights = torch.zeros_like(weights)
            for f, col in enumerate(columns):
                grad_weights += col.index_select(0, idx).view_as(weights) * grad_out[f]
        return grad_table, None, grad_weights


def gather_blend(table: Tensor, rows: Tensor, weights: Tensor) -> Tensor:
    """Blended features (F,M) = sum_c weights[c] * table[rows[c]] for table (R,F), rows/weights (8,M)."""
    return _GatherBlend.apply(table, rows, weights)


def encode(x: Tensor, tables: Tensor, cell_sizes_m: list[float]) -> Tensor:
    """Hash-grid features (N, L*F) of points x (N,3) from tables (L,T,F), T a power of two.

    One level at a time: a level's table and (8,N) corner arrays are kinder to caches and the TLB than
    all levels at once; measured ~20 % faster forward and no slower backward (see bench/encoding.py).
    """
    n_levels, table_size, n_features = tables.shape
    per_level = []
    for level, cell_m in enumerate(cell_sizes_m):
        rows, weights = corners_and_weights(x, [cell_m], table_size.bit_length() - 1, tables.dtype)
        per_level.append(gather_blend(tables[level], rows.view(8, -1), weights.view(8, -1)))  # (F,N)
    return torch.stack(per_level).permute(2, 0, 1).reshape(x.shape[0], n_levels * n_features)


def encode_for_compile(x: Tensor, tables: Tensor, cell_sizes_m: list[float]) -> Tensor:
    """Same as `encode` in plain autograd ops, meant for torch.compile (fused into one loop over points).

    The blend is written as 8 elementwise multiply-adds: a compiled sum over the 8-long corner axis
    parallelises that tiny reduction badly on CPU.
    """
    n_levels, table_size, n_features = tables.shape
    rows, weights = corners_and_weights(x, cell_sizes_m, table_size.bit_length() - 1, tables.dtype)
    flat = tables.reshape(n_levels * table_size, n_features)
    corner_feats = flat.index_select(0, rows.reshape(-1)).view(8, n_levels, -1, n_features)  # (8,L,N,F)
    blended = weights[0, :, :, None] * corner_feats[0]  # (L,N,F)
    for corner in range(1, 8):
        blended = blended + weights[corner, :, :, None] * corner_feats[corner]
    return blended.permute(1, 0, 2).reshape(x.shape[0], n_levels * n_features)


class HashGrid(nn.Module):
    """Trainable multiresolution hash encoding: points (N,3) in metres -> features (N, L*F).

    A backend with tensor kernels (h2viz.mapping.backend, "numba") runs CPU calls through the fused numba kernels
    (forward, and the table gradient) unless x needs a gradient (normals), which the torch path provides; without
    one (None, "torch", "cuda") the torch code runs. compile=True runs gradient-free calls that the fused kernels
    do not serve
    through torch.compile (needs a C++ compiler; compiles for several seconds on the first call).
    """

    def __init__(
        self,
        n_levels: int = 4,
        n_features: int = 2,
        log2_size: int = 19,
        base_cell_m: float = 0.1,
        scale: float = 2.0,
        init_std: float = 1e-4,
        compile: bool = False,
        backend: Backend | None = None,
    ) -> None:
        super().__init__()
        _check_args(n_levels, n_features, log2_size, base_cell_m, scale)
        self.backend = backend
        self.n_levels = n_levels
        self.n_features = n_features
        self.log2_size = log2_size
        self.cell_sizes_m = level_cell_sizes(n_levels, base_cell_m, scale)
        self.tables = nn.Parameter(torch.empty(n_levels, 1 << log2_size, n_features))  # (L,T,F)
        nn.init.uniform_(self.tables, -init_std, init_std)
        self._encode_no_grad: Callable[[Tensor, Tensor, list[float]], Tensor] = (
            torch.compile(encode_for_compile, dynamic=True) if compile else encode
        )

    @property
    def output_dim(self) -> int:
        """L * F, the width of the encoding."""
        return self.n_levels * self.n_features

    @property
    def table_size(self) -> int:
        """T, entries per level."""
        return 1 << self.log2_size

    def forward(self, x: Tensor) -> Tensor:
        """Features (N, L*F) of world points x (N,3) in metres, levels coarse to fine."""
        if x.ndim != 2 or x.shape[1] != 3:
            raise H2vizError(f"HashGrid expects points shaped (N,3), got {tuple(x.shape)}; reshape to (-1, 3).")
        x_needs_grad = torch.is_grad_enabled() and x.requires_grad
        kernels = None if self.backend is None or x_needs_grad else self.backend.cpu_kernels(x, self.tables)
        if kernels is not None:
            return kernels.hash.fused_encode(x, self.tables, self.cell_sizes_m)
        if torch.is_grad_enabled() and (self.tables.requires_grad or x.requires_grad):
            return encode(x, self.tables, self.cell_sizes_m)  # hand-written backward beats compiled
        return self._encode_no_grad(x, self.tables, self.cell_sizes_m)

    def corner_indices(self, x: Tensor) -> Tensor:
        """Per-level table index in [0, T) (N,L,8) of the 8 cell corners around each point x (N,3)."""
        rows, _ = corners_and_weights(x.detach(), self.cell_sizes_m, self.log2_size, self.tables.dtype)
        return (rows & (self.table_size - 1)).permute(2, 1, 0).long()


def _check_args(n_levels: int, n_features: int, log2_size: int, base_cell_m: float, scale: float) -> None:
    """Raise ConfigError for hash-grid settings that cannot work."""
    if n_levels < 1 or n_features < 1:
        raise ConfigError(f"hash grid: hash_levels ({n_levels}) and hash_features ({n_features}) must be >= 1.")
    if log2_size < 1 or n_levels << log2_size >= 1 << 31:
        raise ConfigError(
            f"hash grid: need hash_log2_size >= 1 and hash_levels * 2**hash_log2_size < 2**31, "
            f"got {log2_size} and {n_levels}."
        )
    if not base_cell_m > 0 or not scale >= 1:
        raise ConfigError(f"hash grid: the base cell size ({base_cell_m} m) must be > 0 and hash_scale ({scale}) >= 1.")


def hash_grid_reference(x: Tensor, tables: Tensor, base_cell_m: float, scale: float) -> Tensor:
    """Plain per-level, per-corner implementation of the same encoding (N, L*F); for parity checks only."""
    n_levels, table_size, _ = tables.shape
    per_level = []
    for level, cell_m in enumerate(level_cell_sizes(n_levels, base_cell_m, scale)):
        pos = x.to(torch.float64) / cell_m  # (N,3)
        lower = torch.floor(pos)
        frac = (pos - lower).to(tables.dtype)  # (N,3)
        acc = torch.zeros(x.shape[0], tables.shape[2], dtype=tables.dtype, device=x.device)  # (N,F)
        for dx, dy, dz in itertools.product((0, 1), repeat=3):
            offset = torch.tensor([dx, dy, dz], device=x.device)
            corner = lower.long() + offset  # (N,3)
            weight = torch.ones(x.shape[0], dtype=tables.dtype, device=x.device)
            for axis, d in enumerate((dx, dy, dz)):
                weight = weight * (frac[:, axis] if d == 1 else 1.0 - frac[:, axis])
            acc = acc + weight[:, None] * tables[level][spatial_hash(corner, table_size)]
        per_level.append(acc)
    return torch.cat(per_level, dim=1)
