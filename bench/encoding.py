"""Hash-grid encoding speed on CPU: forward and forward+backward of one grid (L=4 F=2 T=2^19) per batch size.

Reproduce:  .venv/bin/python bench/encoding.py            (--compile adds the torch.compile row,
                                                           --alternatives the reference and design comparisons)
Rows: "numba fused" is what HashGrid runs on the CPU with the numba backend; "numba kernels only" times the same
forward and table-gradient kernels without autograd and with a reused gradient buffer (the difference is
allocating and page-faulting the dense (L,T,F) gradient, plus autograd); "torch eager" is the torch backend
(and the path for CUDA and for gradients w.r.t. points); HashGrid(compile=True) uses the compiled row's
forward for gradient-free calls that the fused kernels do not serve.

Points are 1 cm samples (40 per ray, sorted along each ray) around the surface hit by camera rays in a
room, so corners repeat the way they do during mapping; --points sets the batch sizes. Wall times are the
median and the best of --reps interleaved runs with torch.set_num_threads(2) (--threads); the CPU column is
the median process CPU time. The 1-minute load average is printed because other jobs on the machine
inflate wall times (with --threads 1 the CPU column is the load-independent figure). "1st s" is the first
call: compilation, or loading compiled code from numba's cache.
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

from h2viz.mapping.backend import resolve_backend  # noqa: E402
from h2viz.mapping.field.encoding import (  # noqa: E402
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


def time_kernels_only(grid: HashGrid, x: Tensor, upstream: Tensor, grad_buffer: Tensor) -> Timing:
    """The fused forward and table-gradient kernels alone: no autograd, the gradient buffer is reused."""
    kernels = resolve_backend("auto", "cpu").tensor_kernels
    assert kernels is not None
    fused = kernels.hash
    x64 = x.double()
    w0, c0 = time.perf_counter(), time.process_time()
    fused.forward_features(x64, grid.tables, grid.cell_sizes_m)
    w1, c1 = time.perf_counter(), time.process_time()
    fused.forward_features(x64, grid.tables, grid.cell_sizes_m)
    fused.table_gradient(x64, upstream, grid.cell_sizes_m, grid.tables.shape, out=grad_buffer)
    w2, c2 = time.perf_counter(), time.process_time()
    return w1 - w0, w2 - w1, c1 - c0, c2 - c1


def variants(compiled: bool, alternatives: bool) -> dict[str, EncodeFn]:
    """The rows of the table: the fused kernels, the torch module path, optionally compile and alternatives."""
    rows: dict[str, EncodeFn] = {}
    kernels = resolve_backend("auto", "cpu").tensor_kernels
    if kernels is not None:
        rows["numba fused"] = kernels.hash.fused_encode
        rows["numba kernels only"] = kernels.hash.fused_encode  # timed by time_kernels_only
    rows["torch eager"] = encode
    if compiled:
        rows["compiled encode_for_compile"] = torch.compile(encode_for_compile, dynamic=True)
    if alternatives:
        rows["reference"] = reference
        for kind in ("index_select", "gather", "embedding", "embedding_sparse", "indexing"):
            rows[f"autograd {kind}"] = gather_variant(kind)
        rows |= {"8 multiply-adds (eager)": encode_for_compile, "points-first + bmm": corner_last_bmm}
        rows |= {"all levels batched": all_levels_batched, "loop over corners": per_corner_loop}
    return rows


def measure(rows: dict[str, EncodeFn], x: Tensor, reps: int) -> tuple[dict[str, list[Timing]], dict[str, float]]:
    """Per row: `reps` timings (interleaved, so load changes hit every row alike) and the first call in s."""
    torch.manual_seed(0)
    grid = HashGrid()
    upstream = torch.randn(x.shape[0], grid.output_dim)
    expected = encode(x, grid.tables, grid.cell_sizes_m).detach()
    grad_buffer = torch.empty_like(grid.tables)  # (L,T,F)

    def timed(name: str) -> Timing:
        if name == "numba kernels only":
            return time_kernels_only(grid, x, upstream, grad_buffer)
        return time_pair(rows[name], grid, x, upstream)

    first: dict[str, float] = {}
    for name, fn in rows.items():  # allocation warm-up; compilation (numba, torch.compile)
        t0 = time.perf_counter()
        timed(name)
        first[name] = time.perf_counter() - t0
        got = fn(x, grid.tables, grid.cell_sizes_m)
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-7, msg=f"{name} differs")
    runs: dict[str, list[Timing]] = {name: [] for name in rows}
    for _ in range(reps):
        for name in rows:
            runs[name].append(timed(name))
    return runs, first


def print_table(runs: dict[str, list[Timing]], first: dict[str, float], n_points: int) -> None:
    """One line per row: median and best wall ms of forward and fwd+bwd, median CPU ms, first call s."""
    for name, timings in runs.items():
        by_column = [sorted(column) for column in zip(*timings, strict=True)]
        fwd, both, _, both_cpu = (column[len(column) // 2] * 1e3 for column in by_column)
        best_fwd, best_both = by_column[0][0] * 1e3, by_column[1][0] * 1e3
        ms = f"{fwd:8.1f} {best_fwd:8.1f} {both:10.1f} {best_both:10.1f} {both_cpu:10.1f}"
        print(f"{n_points:7d} {name:28s} {ms} {first[name]:6.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=9, help="timed runs per row and size")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads (numba follows)")
    parser.add_argument("--points", default="20480,65536,163840", help="batch sizes, comma separated")
    parser.add_argument("--compile", action="store_true", help="add the torch.compile row")
    parser.add_argument("--alternatives", action="store_true", help="add the reference and design rows")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = variants(args.compile, args.alternatives)
    cells = ", ".join(f"{c * 100:g}" for c in level_cell_sizes())
    print(f"points: 40 per ray, 1 cm apart; L=4 F=2 T=2^19, cells {cells} cm")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    heads = f"{'fwd ms':>8s} {'best':>8s} {'fwd+bwd ms':>10s} {'best':>10s} {'f+b CPU ms':>10s} {'1st s':>6s}"
    print(f"{'N':>7s} {'variant':28s} {heads}")
    for n_points in (int(n) for n in args.points.split(",")):
        x = ray_samples(n_rays=max(1, n_points // 40))  # (N,3)
        runs, first = measure(rows, x, args.reps)
        print_table(runs, first, x.shape[0])
    print(f"load average {os.getloadavg()[0]:.2f}; median and best of {args.reps} runs per row")
    print(f"command: .venv/bin/python bench/encoding.py {' '.join(sys.argv[1:])}".rstrip())


if __name__ == "__main__":
    main()
