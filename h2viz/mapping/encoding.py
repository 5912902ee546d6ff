"""Multiresolution spatial-hash feature grid over unbounded world coordinates (pure torch, CPU and CUDA).

Level l has cubic cells of edge `base_cell_m / scale**l` anchored at the world origin. A point reads the
F features stored at the 8 corners of its cell and blends them trilinearly; the levels are concatenated
coarse to fine. A corner with integer lattice coordinates (i, j, k) lives at entry
`(i * 1 ^ j * 2654435761 ^ k * 805459861) mod T` of its level's table (int64 arithmetic, correct for
negative coordinates), so no scene bounds are needed. Corners are ordered `4 * dx + 2 * dy + dz`.
Valid inputs: finite metres with |x| / finest cell < 2**31 (about 27 000 km at the default sizes).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import torch
from torch import Tensor, nn

from h2viz.errors import ConfigError, H2vizError

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
    """Flat row (level * T + hash) (N,L,8) int64 and trilinear weight (N,L,8) of every cell corner.

    Positions are divided by the cell size in float64 so that the in-cell fraction stays accurate far
    from the origin; the weights are differentiable w.r.t. x.
    """
    n, n_levels, mask = x.shape[0], len(cell_sizes_m), (1 << log2_size) - 1
    cells = torch.tensor(cell_sizes_m, dtype=torch.float64, device=x.device)  # (L,)
    primes = torch.tensor(HASH_PRIMES, device=x.device)[:, None]  # (3,1)
    step = torch.tensor([0, 1], device=x.device)  # (2,) lower / upper corner along an axis
    level_row = (torch.arange(n_levels, device=x.device) << log2_size)[:, None]  # (L,1)
    pos = x.to(torch.float64)[:, None, :] / cells[:, None]  # (N,L,3) in cells
    lower = torch.floor(pos)
    frac = (pos - lower).to(weight_dtype)  # (N,L,3) in [0,1)
    # Per axis, hashed lower/upper terms masked to T; XOR commutes with the mask, so combining the
    # masked terms gives (i*p0 ^ j*p1 ^ k*p2) mod T, and the level offset (a multiple of T) is an OR.
    terms = ((lower.long()[..., None] + step) * primes) & mask  # (N,L,3,2)
    tx = terms[:, :, 0] | level_row  # (N,L,2)
    txy = (tx[:, :, :, None] ^ terms[:, :, 1, None, :]).reshape(n, n_levels, 4)
    rows = (txy[:, :, :, None] ^ terms[:, :, 2, None, :]).reshape(n, n_levels, 8)
    ramps = torch.stack([1.0 - frac, frac], dim=-1)  # (N,L,3,2) weight of lower / upper corner
    wxy = (ramps[:, :, 0, :, None] * ramps[:, :, 1, None, :]).reshape(n, n_levels, 4)
    weights = (wxy[:, :, :, None] * ramps[:, :, 2, None, :]).reshape(n, n_levels, 8)
    return rows, weights


def encode(x: Tensor, tables: Tensor, cell_sizes_m: list[float]) -> Tensor:
    """Hash-grid features (N, L*F) of points x (N,3) from tables (L,T,F), T a power of two."""
    n_levels, table_size, n_features = tables.shape
    log2_size = table_size.bit_length() - 1
    rows, weights = corners_and_weights(x, cell_sizes_m, log2_size, tables.dtype)  # (N,L,8) x2
    n = x.shape[0]
    # index_select backward is a dense index_add_, the fastest table gradient on CPU (see bench/).
    corner_feats = tables.reshape(n_levels * table_size, n_features).index_select(0, rows.reshape(-1))
    corner_feats = corner_feats.view(n * n_levels, 8, n_features)  # (N*L,8,F)
    blended = torch.bmm(weights.view(n * n_levels, 1, 8), corner_feats)  # (N*L,1,F)
    return blended.view(n, n_levels * n_features)


def encode_for_compile(x: Tensor, tables: Tensor, cell_sizes_m: list[float]) -> Tensor:
    """Same as `encode`, with the corner blend written as 8 elementwise multiply-adds.

    Meant for torch.compile, which fuses it into one loop over points; `encode`'s bmm is faster eagerly,
    and a compiled bmm over 8 corners parallelises the tiny reduction badly on CPU.
    """
    n_levels, table_size, n_features = tables.shape
    rows, weights = corners_and_weights(x, cell_sizes_m, table_size.bit_length() - 1, tables.dtype)
    flat = tables.reshape(n_levels * table_size, n_features)
    corner_feats = flat.index_select(0, rows.reshape(-1)).view(*rows.shape, n_features)  # (N,L,8,F)
    blended = weights[:, :, 0, None] * corner_feats[:, :, 0]  # (N,L,F)
    for corner in range(1, 8):
        blended = blended + weights[:, :, corner, None] * corner_feats[:, :, corner]
    return blended.reshape(x.shape[0], n_levels * n_features)


class HashGrid(nn.Module):
    """Trainable multiresolution hash encoding: points (N,3) in metres -> features (N, L*F)."""

    def __init__(
        self,
        n_levels: int = 4,
        n_features: int = 2,
        log2_size: int = 19,
        base_cell_m: float = 0.1,
        scale: float = 2.0,
        init_std: float = 1e-4,
        compile: bool = False,
    ) -> None:
        super().__init__()
        _check_args(n_levels, n_features, log2_size, base_cell_m, scale)
        self.n_levels = n_levels
        self.n_features = n_features
        self.log2_size = log2_size
        self.cell_sizes_m = level_cell_sizes(n_levels, base_cell_m, scale)
        self.tables = nn.Parameter(torch.empty(n_levels, 1 << log2_size, n_features))  # (L,T,F)
        nn.init.uniform_(self.tables, -init_std, init_std)
        self._encode: Callable[[Tensor, Tensor, list[float]], Tensor] = (
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
            raise H2vizError(
                f"HashGrid expects points shaped (N,3), got {tuple(x.shape)}; reshape to (-1, 3)."
            )
        return self._encode(x, self.tables, self.cell_sizes_m)

    def corner_indices(self, x: Tensor) -> Tensor:
        """Per-level table index in [0, T) (N,L,8) of the 8 cell corners around each point x (N,3)."""
        rows, _ = corners_and_weights(x.detach(), self.cell_sizes_m, self.log2_size, self.tables.dtype)
        return rows & (self.table_size - 1)


def _check_args(n_levels: int, n_features: int, log2_size: int, base_cell_m: float, scale: float) -> None:
    """Raise ConfigError for hash-grid sizes that cannot work."""
    if n_levels < 1 or n_features < 1:
        raise ConfigError(
            f"hash grid: hash_levels ({n_levels}) and hash_features ({n_features}) must be >= 1."
        )
    if not 1 <= log2_size <= 30:
        raise ConfigError(f"hash grid: hash_log2_size must be in [1, 30], got {log2_size}.")
    if not base_cell_m > 0 or not scale >= 1:
        raise ConfigError(
            f"hash grid: the base cell size ({base_cell_m} m) must be > 0 and hash_scale ({scale}) >= 1."
        )


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
