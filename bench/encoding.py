"""Hash-grid encoding speed on CPU: forward and forward+backward for one batch of 4096 rays x 40 samples.

Reproduce:  .venv/bin/python bench/encoding.py            (add --compile for the torch.compile row,
                                                           --alternatives for the design comparisons)

Points are 1 cm samples around the surface hit by 4096 camera rays in a room, so corners repeat the way
they do during mapping. Times are the best of --reps interleaved runs with torch.set_num_threads(2);
the 1-minute load average is printed because other jobs on the machine inflate every number.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from h2viz.mapping.encoding import (  # noqa: E402
    HashGrid,
    corners_and_weights,
    encode,
    encode_for_compile,
    hash_grid_reference,
    level_cell_sizes,
)

EncodeFn = Callable[[Tensor, Tensor, list[float]], Tensor]


def ray_samples(n_rays: int = 4096, n_samples: int = 40, seed: int = 0) -> Tensor:
    """Points (R*S,3): 1 cm samples centred on depths of 1-4 m along rays of a camera 1.3 m off-origin."""
    g = torch.Generator().manual_seed(seed)
    dirs = torch.randn(n_rays, 3, generator=g) * torch.tensor([0.4, 0.3, 0.0]) + torch.tensor([0.0, 0.0, 1.0])
    dirs = dirs / dirs.norm(dim=1, keepdim=True)  # (R,3)
    depth_m = 1.0 + 3.0 * torch.rand(n_rays, 1, generator=g)  # (R,1)
    t_m = depth_m + (torch.arange(n_samples) - n_samples / 2) * 0.01  # (R,S)
    origin = torch.tensor([1.3, -0.7, 0.4])
    return (origin + t_m[..., None] * dirs[:, None, :]).reshape(-1, 3)


def _blend(rows: Tensor, weights: Tensor, corner_feats: Tensor, n_features: int) -> Tensor:
    """Weighted sum over the 8 corners with bmm: (N,L,8) weights, (N*L*8,F) features -> (N, L*F)."""
    n, n_levels, _ = rows.shape
    blended = torch.bmm(weights.view(n * n_levels, 1, 8), corner_feats.view(n * n_levels, 8, n_features))
    return blended.view(n, n_levels * n_features)


def gather_variant(kind: str) -> EncodeFn:
    """The encoding with another way of reading the table rows (and hence another backward)."""

    def run(x: Tensor, tables: Tensor, cells: list[float]) -> Tensor:
        n_levels, table_size, n_features = tables.shape
        rows, weights = corners_and_weights(x, cells, table_size.bit_length() - 1, tables.dtype)
        flat, idx = tables.reshape(n_levels * table_size, n_features), rows.reshape(-1)
        if kind == "gather":
            feats = flat.gather(0, idx[:, None].expand(-1, n_features))
        elif kind == "embedding":
            feats = F.embedding(idx, flat)
        elif kind == "embedding_sparse":  # sparse grads cannot flow back through a reshape: own leaf
            feats = F.embedding(idx, flat.detach().requires_grad_(flat.requires_grad), sparse=True)
        elif kind == "indexing":
            feats = flat[idx]
        else:
            raise ValueError(kind)
        return _blend(rows, weights, feats, n_features)

    return run


def mul_sum_blend(x: Tensor, tables: Tensor, cells: list[float]) -> Tensor:
    """The encoding with an elementwise multiply + sum over corners instead of bmm."""
    n_levels, table_size, n_features = tables.shape
    rows, weights = corners_and_weights(x, cells, table_size.bit_length() - 1, tables.dtype)
    feats = tables.reshape(n_levels * table_size, n_features).index_select(0, rows.reshape(-1))
    blended = (feats.view(*rows.shape, n_features) * weights[..., None]).sum(dim=2)  # (N,L,F)
    return blended.reshape(x.shape[0], n_levels * n_features)


def per_level_loop(x: Tensor, tables: Tensor, cells: list[float]) -> Tensor:
    """The batched encoding called once per level (a Python loop over L)."""
    return torch.cat([encode(x, tables[lv : lv + 1], [cells[lv]]) for lv in range(tables.shape[0])], dim=1)


def per_corner_loop(x: Tensor, tables: Tensor, cells: list[float]) -> Tensor:
    """A Python loop over the 8 corners, each gathering (N*L,F) rows and accumulating."""
    n_levels, table_size, n_features = tables.shape
    rows, weights = corners_and_weights(x, cells, table_size.bit_length() - 1, tables.dtype)
    flat = tables.reshape(n_levels * table_size, n_features)
    out = torch.zeros(x.shape[0] * n_levels, n_features, dtype=tables.dtype)
    for c in range(8):
        feats = flat.index_select(0, rows[:, :, c].reshape(-1))  # (N*L,F)
        out = out + weights[:, :, c].reshape(-1, 1) * feats
    return out.view(x.shape[0], n_levels * n_features)


def reference(x: Tensor, tables: Tensor, cells: list[float]) -> Tensor:
    """The plain per-level, per-corner reference."""
    return hash_grid_reference(x, tables, cells[0], cells[0] / cells[1])


def time_pair(fn: EncodeFn, grid: HashGrid, x: Tensor, upstream: Tensor) -> tuple[float, float]:
    """One forward (no grad) and one forward+backward into the tables, in seconds."""
    t0 = time.perf_counter()
    with torch.no_grad():
        fn(x, grid.tables, grid.cell_sizes_m)
    t1 = time.perf_counter()
    grid.tables.grad = None
    (fn(x, grid.tables, grid.cell_sizes_m) * upstream).sum().backward()
    return t1 - t0, time.perf_counter() - t1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=5, help="timed runs per row (best is kept)")
    parser.add_argument("--compile", action="store_true", help="add torch.compile(encode) rows")
    parser.add_argument("--alternatives", action="store_true", help="add gather/blend/loop design rows")
    args = parser.parse_args()
    torch.set_num_threads(2)
    torch.manual_seed(0)
    grid = HashGrid()
    x = ray_samples()  # (N,3)
    upstream = torch.randn(x.shape[0], grid.output_dim)
    rows: dict[str, EncodeFn] = {"HashGrid (eager)": encode, "reference": reference}
    if args.compile:
        rows["HashGrid(compile=True)"] = torch.compile(encode_for_compile, dynamic=True)
    if args.alternatives:
        rows |= {
            f"gather: {k}": gather_variant(k) for k in ("gather", "embedding", "embedding_sparse", "indexing")
        }
        rows |= {"blend: mul+sum": mul_sum_blend, "blend: 8 multiply-adds": encode_for_compile}
        rows |= {"loop over levels": per_level_loop}
        rows |= {"loop over corners": per_corner_loop}
    warm: dict[str, float] = {}
    for name, fn in rows.items():  # first call: allocation warm-up, compilation for torch.compile
        t0 = time.perf_counter()
        time_pair(fn, grid, x, upstream)
        warm[name] = time.perf_counter() - t0
    best = {name: (float("inf"), float("inf")) for name in rows}
    for _ in range(args.reps):  # interleaved so that load changes hit every row alike
        for name, fn in rows.items():
            fwd, both = time_pair(fn, grid, x, upstream)
            best[name] = (min(best[name][0], fwd), min(best[name][1], both))
    cells = ", ".join(f"{c * 100:g}" for c in level_cell_sizes())
    print(f"N = {x.shape[0]} points (4096 rays x 40 samples), L=4 F=2 T=2^19, cells {cells} cm")
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, load average {os.getloadavg()[0]:.2f}"
    )
    print(f"{'variant':28s} {'forward ms':>11s} {'fwd+bwd ms':>11s} {'first call s':>13s}")
    for name, (fwd, both) in best.items():
        print(f"{name:28s} {fwd * 1e3:11.1f} {both * 1e3:11.1f} {warm[name]:13.2f}")


if __name__ == "__main__":
    main()
