"""Hash-grid encoding speed on CPU: forward and forward+backward for one batch of 4096 rays x 40 samples.

Reproduce:  .venv/bin/python bench/encoding.py            (add --compile for the torch.compile row,
                                                           --alternatives for the design comparisons)
HashGrid(compile=True) uses the compiled row's forward for gradient-free calls and the eager row otherwise.

Points are 1 cm samples around the surface hit by 4096 camera rays in a room, so corners repeat the way
they do during mapping. Times are the best of --reps interleaved runs with torch.set_num_threads(2)
(--threads), as wall time and as process CPU time; the 1-minute load average is printed because other
jobs on the machine inflate wall times (with --threads 1 the CPU column is the load-independent figure).
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
    HASH_PRIMES,
    HashGrid,
    corners_and_weights,
    encode,
    encode_for_compile,
    gather_blend,
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


def gather_variant(kind: str) -> EncodeFn:
    """Plain-autograd encoding: read (R,F) table rows one way, blend with multiply + sum over corners."""

    def run(x: Tensor, tables: Tensor, cells: list[float]) -> Tensor:
        n_levels, table_size, n_features = tables.shape
        rows, weights = corners_and_weights(x, cells, table_size.bit_length() - 1, tables.dtype)
        flat, idx = tables.reshape(n_levels * table_size, n_features), rows.reshape(-1).long()
        if kind == "index_select":
            feats = flat.index_select(0, idx)
        elif kind == "gather":
            feats = flat.gather(0, idx[:, None].expand(-1, n_features))
        elif kind == "embedding":
            feats = F.embedding(idx, flat)
        elif kind == "embedding_sparse":  # sparse grads cannot flow back through a reshape: own leaf
            feats = F.embedding(idx, flat.detach().requires_grad_(flat.requires_grad), sparse=True)
        elif kind == "indexing":
            feats = flat[idx]
        else:
            raise ValueError(kind)
        blended = (feats.view(*rows.shape, n_features) * weights[..., None]).sum(dim=0)  # (L,N,F)
        return blended.permute(1, 0, 2).reshape(x.shape[0], n_levels * n_features)

    return run


def corner_last_bmm(x: Tensor, tables: Tensor, cells: list[float]) -> Tensor:
    """Points-first layout: int64 (N,L,3,2) hash terms, (N,L,8) rows and weights, bmm blend."""
    n, (n_levels, table_size, n_features) = x.shape[0], tables.shape
    cell = torch.tensor(cells, dtype=torch.float64)[:, None]  # (L,1)
    pos = x.double()[:, None, :] / cell  # (N,L,3)
    lower = torch.floor(pos)
    frac = (pos - lower).to(tables.dtype)
    step, primes = torch.tensor([0, 1]), torch.tensor(HASH_PRIMES)[:, None]
    terms = ((lower.long()[..., None] + step) * primes) & (table_size - 1)  # (N,L,3,2)
    tx = terms[:, :, 0] | (torch.arange(n_levels) * table_size)[:, None]
    rows = (tx[..., :, None] ^ terms[:, :, 1, None, :]).reshape(n, n_levels, 4)
    rows = (rows[..., :, None] ^ terms[:, :, 2, None, :]).reshape(-1)
    ramps = torch.stack([1.0 - frac, frac], dim=-1)  # (N,L,3,2)
    w = (ramps[:, :, 0, :, None] * ramps[:, :, 1, None, :]).reshape(n, n_levels, 4)
    w = (w[..., :, None] * ramps[:, :, 2, None, :]).reshape(n * n_levels, 1, 8)
    feats = tables.reshape(-1, n_features).index_select(0, rows).view(n * n_levels, 8, n_features)
    return torch.bmm(w, feats).view(n, n_levels * n_features)


def all_levels_batched(x: Tensor, tables: Tensor, cells: list[float]) -> Tensor:
    """The module's gather/blend applied to all levels at once ((8,L,N) arrays, one flat table)."""
    n_levels, table_size, n_features = tables.shape
    rows, weights = corners_and_weights(x, cells, table_size.bit_length() - 1, tables.dtype)
    flat = tables.reshape(n_levels * table_size, n_features)
    blended = gather_blend(flat, rows.view(8, -1), weights.view(8, -1))  # (F, L*N)
    return blended.view(n_features, n_levels, -1).permute(2, 1, 0).reshape(x.shape[0], -1)


def per_corner_loop(x: Tensor, tables: Tensor, cells: list[float]) -> Tensor:
    """A Python loop over the 8 corners, each gathering (L*N,F) rows with autograd and accumulating."""
    n_levels, table_size, n_features = tables.shape
    rows, weights = corners_and_weights(x, cells, table_size.bit_length() - 1, tables.dtype)
    flat = tables.reshape(n_levels * table_size, n_features)
    out = torch.zeros(n_levels * x.shape[0], n_features, dtype=tables.dtype)
    for c in range(8):
        out = out + weights[c].reshape(-1, 1) * flat.index_select(0, rows[c].reshape(-1))
    return out.view(n_levels, x.shape[0], n_features).permute(1, 0, 2).reshape(x.shape[0], -1)


def reference(x: Tensor, tables: Tensor, cells: list[float]) -> Tensor:
    """The plain per-level, per-corner reference."""
    return hash_grid_reference(x, tables, cells[0], cells[0] / cells[1])


Timing = tuple[float, float, float, float]  # forward wall, fwd+bwd wall, forward CPU, fwd+bwd CPU (s)


def time_pair(fn: EncodeFn, grid: HashGrid, x: Tensor, upstream: Tensor) -> Timing:
    """One forward (no grad) and one forward+backward into the tables: wall and process CPU seconds."""
    w0, c0 = time.perf_counter(), time.process_time()
    with torch.no_grad():
        fn(x, grid.tables, grid.cell_sizes_m)
    w1, c1 = time.perf_counter(), time.process_time()
    grid.tables.grad = None
    (fn(x, grid.tables, grid.cell_sizes_m) * upstream).sum().backward()
    w2, c2 = time.perf_counter(), time.process_time()
    return w1 - w0, w2 - w1, c1 - c0, c2 - c1


def variants(compiled: bool, alternatives: bool) -> dict[str, EncodeFn]:
    """The rows of the table: the module, the reference and optionally compile and design alternatives."""
    rows: dict[str, EncodeFn] = {"HashGrid (eager)": encode, "reference": reference}
    if compiled:
        rows["compiled encode_for_compile"] = torch.compile(encode_for_compile, dynamic=True)
    if alternatives:
        for kind in ("index_select", "gather", "embedding", "embedding_sparse", "indexing"):
            rows[f"autograd {kind}"] = gather_variant(kind)
        rows |= {"8 multiply-adds (eager)": encode_for_compile, "points-first + bmm": corner_last_bmm}
        rows |= {"all levels batched": all_levels_batched, "loop over corners": per_corner_loop}
    return rows


def measure(rows: dict[str, EncodeFn], reps: int) -> tuple[dict[str, Timing], dict[str, float]]:
    """Best-of-`reps` timings per row (interleaved, so load changes hit every row alike) and first-call s."""
    torch.manual_seed(0)
    grid = HashGrid()
    x = ray_samples()  # (N,3)
    upstream = torch.randn(x.shape[0], grid.output_dim)
    expected = encode(x, grid.tables, grid.cell_sizes_m).detach()
    first: dict[str, float] = {}
    for name, fn in rows.items():  # allocation warm-up; compilation for torch.compile
        t0 = time.perf_counter()
        time_pair(fn, grid, x, upstream)
        first[name] = time.perf_counter() - t0
        torch.testing.assert_close(fn(x, grid.tables, grid.cell_sizes_m), expected, msg=f"{name} differs")
    best: dict[str, Timing] = {name: (float("inf"),) * 4 for name in rows}
    for _ in range(reps):
        for name, fn in rows.items():
            now = time_pair(fn, grid, x, upstream)
            best[name] = tuple(min(a, b) for a, b in zip(best[name], now, strict=True))  # type: ignore[assignment]
    return best, first


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=5, help="timed runs per row (best is kept)")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--compile", action="store_true", help="add the torch.compile row")
    parser.add_argument("--alternatives", action="store_true", help="add gather/blend/loop design rows")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    best, first = measure(variants(args.compile, args.alternatives), args.reps)
    cells = ", ".join(f"{c * 100:g}" for c in level_cell_sizes())
    print(f"N = {4096 * 40} points (4096 rays x 40 samples), L=4 F=2 T=2^19, cells {cells} cm")
    load = os.getloadavg()[0]
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, load average {load:.2f}")
    heads = ("fwd ms", "fwd+bwd ms", "fwd CPU ms", "f+b CPU ms")
    print(f"{'variant':26s} {heads[0]:>8s} {' '.join(f'{h:>11s}' for h in heads[1:])} {'1st s':>6s}")
    for name, (fwd, both, fwd_cpu, both_cpu) in best.items():
        ms = f"{fwd * 1e3:8.1f} {both * 1e3:11.1f} {fwd_cpu * 1e3:11.1f} {both_cpu * 1e3:11.1f}"
        print(f"{name:26s} {ms} {first[name]:6.1f}")


if __name__ == "__main__":
    main()
