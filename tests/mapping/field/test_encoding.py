"""Hash-grid encoding: parity with the plain reference, lattice exactness, continuity, trilinearity, hashing
range and spread, fitting a smooth field, CUDA. Tests that take `kernels` run on the torch path and on the
fused numba kernels (the backend of kernels="auto" on the CPU; see test_hash_numba.py for the kernels themselves)."""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest
import torch
from torch import Tensor, nn

from h2viz.errors import ConfigError, H2vizError
from h2viz.mapping.backend import resolve_backend
from h2viz.mapping.field import encoding
from h2viz.mapping.field.encoding import (
    HashGrid,
    encode_for_compile,
    hash_grid_reference,
    level_cell_sizes,
    spatial_hash,
)

BASE_CELL_M = 0.1
SCALE = 2.0
FINEST_CELL_M = BASE_CELL_M / SCALE**3
NO_NUMBA = resolve_backend("auto", "cpu").tensor_kernels is None
KERNELS = ["torch", pytest.param("auto", marks=pytest.mark.skipif(NO_NUMBA, reason="no numba"))]


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    """These problems are small; one thread keeps them quick when other jobs share the cores."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _grid(log2_size: int = 19, spread: float = 1.0, seed: int = 0, kernels: str = "torch") -> HashGrid:
    """A float64 grid whose table entries are O(spread), so a wrong blend shows as an O(1) error."""
    torch.manual_seed(seed)
    grid = HashGrid(log2_size=log2_size, base_cell_m=BASE_CELL_M, scale=SCALE, init_std=spread,
                    backend=resolve_backend(kernels))
    return grid.double()


def _python_hash(i: int, j: int, k: int, table_size: int) -> int:
    """The spatial hash in exact Python integers (two's-complement XOR, floor modulo)."""
    return (i ^ (j * 2654435761) ^ (k * 805459861)) % table_size


def _test_points(n: int, seed: int) -> Tensor:
    """Points (N,3) float64: a room around the origin, far away (~1 km, negative too) and on cell faces."""
    g = torch.Generator().manual_seed(seed)
    room = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 8.0
    far = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 2000.0
    on_faces = room.clone()
    on_faces[:, 0] = torch.round(on_faces[:, 0] / FINEST_CELL_M) * FINEST_CELL_M  # x on a finest-level face
    half = on_faces[: n // 2]
    half[:, 1] = torch.round(half[:, 1] / BASE_CELL_M) * BASE_CELL_M  # y on a face of every level
    return torch.cat([room, far, on_faces])


def test_level_cell_sizes() -> None:
    assert level_cell_sizes(4, 0.1, 2.0) == pytest.approx([0.1, 0.05, 0.025, 0.0125], abs=1e-15)
    assert HashGrid(log2_size=4, base_cell_m=0.08, scale=1.5).cell_sizes_m == pytest.approx(
        [0.08, 0.08 / 1.5, 0.08 / 2.25, 0.08 / 3.375]
    )


@pytest.mark.parametrize("kernels", KERNELS)
def test_forward_matches_reference(kernels: str) -> None:
    grid = _grid(kernels=kernels)
    x = _test_points(2000, seed=1)
    out = grid(x)
    assert out.shape == (x.shape[0], grid.output_dim) and out.dtype == torch.float64
    ref = hash_grid_reference(x, grid.tables, BASE_CELL_M, SCALE)
    torch.testing.assert_close(out, ref, rtol=0.0, atol=1e-12)
    assert ref.abs().max() > 0.5  # the comparison is between O(1) values


def test_compile_friendly_form_matches_reference() -> None:
    grid = _grid(seed=15)
    x = _test_points(500, seed=16)
    upstream = torch.randn(x.shape[0], 8, dtype=torch.float64)
    out = encode_for_compile(x, grid.tables, grid.cell_sizes_m)
    ref = hash_grid_reference(x, grid.tables, BASE_CELL_M, SCALE)
    torch.testing.assert_close(out, ref, rtol=0.0, atol=1e-12)
    (got,) = torch.autograd.grad((out * upstream).sum(), grid.tables)
    (expected,) = torch.autograd.grad((ref * upstream).sum(), grid.tables)
    torch.testing.assert_close(got, expected, rtol=0.0, atol=1e-10)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_compiled_grid_matches_eager() -> None:
    """torch.compile (needs a C++ compiler on CPU) serves gradient-free calls with the same values."""
    torch.manual_seed(17)
    eager = HashGrid(log2_size=14, init_std=1.0)
    compiled = HashGrid(log2_size=14, init_std=1.0, compile=True)
    compiled.load_state_dict(eager.state_dict())
    for n in (3000, 2000):  # a second size must not break the dynamic-shape graph
        x = _test_points(n // 3, seed=n).float()
        with torch.no_grad():
            torch.testing.assert_close(compiled(x), eager(x), rtol=1e-5, atol=1e-5)
        upstream = torch.randn(x.shape[0], 8)
        for grid in (eager, compiled):
            grid.zero_grad(set_to_none=True)
            (grid(x) * upstream).sum().backward()
        torch.testing.assert_close(compiled.tables.grad, eager.tables.grad, rtol=1e-5, atol=1e-5)


def test_gradients_match_reference() -> None:
    grid = _grid(seed=2)
    x = _test_points(1000, seed=3).requires_grad_()
    upstream = torch.randn(x.shape[0], grid.output_dim, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    grad_tables, grad_x = torch.autograd.grad((grid(x) * upstream).sum(), [grid.tables, x])
    ref = hash_grid_reference(x, grid.tables, BASE_CELL_M, SCALE)
    ref_tables, ref_x = torch.autograd.grad((ref * upstream).sum(), [grid.tables, x])
    torch.testing.assert_close(grad_tables, ref_tables, rtol=0.0, atol=1e-10)
    torch.testing.assert_close(grad_x, ref_x, rtol=1e-9, atol=1e-7)
    assert int((grad_tables != 0).sum()) > 1000  # many entries receive gradient


def test_gradient_wrt_points_with_frozen_tables() -> None:
    grid = _grid(seed=20).requires_grad_(False)
    x = _test_points(300, seed=21).requires_grad_()
    (got,) = torch.autograd.grad(grid(x).square().sum(), x)
    (expected,) = torch.autograd.grad(hash_grid_reference(x, grid.tables, BASE_CELL_M, SCALE).square().sum(), x)
    torch.testing.assert_close(got, expected, rtol=1e-9, atol=1e-7)
    assert got.abs().max() > 1.0


@pytest.mark.parametrize("kernels", KERNELS)
def test_float32_accurate_far_from_origin(kernels: str) -> None:
    """float32 points ~1 km out still get their in-cell fraction right (positions are scaled in float64)."""
    torch.manual_seed(5)
    grid32 = HashGrid(log2_size=16, init_std=1.0, backend=resolve_backend(kernels))
    x32 = _test_points(500, seed=6).float()
    out32 = grid32(x32)
    out64 = hash_grid_reference(x32.double(), grid32.tables.detach().double(), BASE_CELL_M, SCALE)
    torch.testing.assert_close(out32.double(), out64, rtol=0.0, atol=1e-5)


@pytest.mark.parametrize("kernels", KERNELS)
def test_lattice_corner_returns_its_table_entry(kernels: str) -> None:
    grid = _grid(seed=7, kernels=kernels)
    coords = [(0, 0, 0), (3, -7, 12), (-1, -1, -1), (-40000, 25000, 80000), (123, 0, -4567)]
    for level, cell_m in enumerate(grid.cell_sizes_m):
        x = torch.tensor(coords, dtype=torch.float64) * cell_m  # (N,3) exactly on lattice corners
        got = grid(x)[:, level * 2 : (level + 1) * 2]
        rows = [_python_hash(i, j, k, grid.table_size) for i, j, k in coords]
        expected = grid.tables[level, rows]
        torch.testing.assert_close(got, expected, rtol=0.0, atol=1e-12)


@pytest.mark.parametrize("kernels", KERNELS)
def test_continuous_across_cell_faces(kernels: str) -> None:
    grid = _grid(seed=8, kernels=kernels)
    g = torch.Generator().manual_seed(9)
    centre = (torch.rand(300, 3, generator=g, dtype=torch.float64) - 0.5) * 20.0
    for axis, cell_m in [(0, FINEST_CELL_M), (1, BASE_CELL_M), (2, FINEST_CELL_M * 3)]:
        on_face = centre.clone()
        on_face[:, axis] = torch.round(on_face[:, axis] / cell_m) * cell_m
        step = torch.zeros(3, dtype=torch.float64)
        step[axis] = 1e-9
        jump = (grid(on_face + step) - grid(on_face - step)).abs().max()
        assert jump < 1e-5, f"encoding jumps by {jump} across faces normal to axis {axis}"


@pytest.mark.parametrize("kernels", KERNELS)
def test_affine_along_an_axis_inside_a_cell(kernels: str) -> None:
    grid = _grid(seed=10, kernels=kernels)
    corner = torch.tensor([-3.0, 1.5, 7.0], dtype=torch.float64) / FINEST_CELL_M
    for axis in range(3):
        in_cell = torch.tensor([0.4, 0.7, 0.3], dtype=torch.float64)
        in_cell[axis] = 0.05
        start = (torch.floor(corner) + in_cell) * FINEST_CELL_M
        t = torch.linspace(0.0, 0.9 * FINEST_CELL_M, 21, dtype=torch.float64)
        x = start.repeat(21, 1)
        x[:, axis] += t  # the segment stays inside one finest cell, hence inside one cell per level
        finest = grid(x)[:, -2:]  # (21,F)
        second_diff = finest[2:] - 2 * finest[1:-1] + finest[:-2]
        assert second_diff.abs().max() < 1e-12
        assert (finest[-1] - finest[0]).abs().max() > 1e-3  # not trivially constant


def test_hash_indices_in_range_and_spread() -> None:
    grid = HashGrid(log2_size=16)
    g = torch.Generator().manual_seed(11)
    x = torch.cat(
        [
            (torch.rand(20000, 3, generator=g, dtype=torch.float64) - 0.5) * 2e6,  # +-1000 km
            (torch.rand(20000, 3, generator=g, dtype=torch.float64) - 0.5) * 10.0,
        ]
    )
    idx = grid.corner_indices(x)  # (N,L,8)
    assert idx.shape == (x.shape[0], 4, 8) and idx.dtype == torch.int64
    assert int(idx.min()) >= 0 and int(idx.max()) < grid.table_size
    corners = torch.floor(x[:5] / grid.cell_sizes_m[3]).long()  # finest level, lower corner
    expected = [_python_hash(*c.tolist(), grid.table_size) for c in corners]
    assert idx[:5, 3, 0].tolist() == expected
    assert spatial_hash(corners, grid.table_size).tolist() == expected
    # Distinct nearby lower corners share entries no more often than under a uniform random hash.
    lattice = torch.floor(x[20000:] / grid.cell_sizes_m[3]).long()  # (N,3)
    n_corners = torch.unique(lattice, dim=0).shape[0]
    uniform = grid.table_size * (1.0 - math.exp(-n_corners / grid.table_size))
    assert torch.unique(idx[20000:, 3, 0]).numel() > 0.97 * uniform


class _Regressor(nn.Module):
    def __init__(self, grid: HashGrid) -> None:
        super().__init__()
        self.grid = grid
        self.mlp = nn.Sequential(nn.Linear(grid.output_dim, 32), nn.ReLU(), nn.Linear(32, 1))

    def forward(self, x: Tensor) -> Tensor:
        return self.mlp(self.grid(x))[:, 0]


def _fit_error(seed: int = 12, kernels: str = "torch") -> float:
    """RMS error on held-out points after fitting a smooth field on a 1 m cube (300 Adam steps)."""
    torch.manual_seed(seed)
    model = _Regressor(HashGrid(log2_size=16, init_std=1e-4, backend=resolve_backend(kernels)))
    target = lambda p: torch.sin(2 * torch.pi * p[:, 0]) * torch.cos(2 * torch.pi * p[:, 1]) + p[:, 2] ** 2
    offset = torch.tensor([-2.3, 0.6, -0.4])  # the cube straddles no special place
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(300):
        p = torch.rand(2048, 3)
        loss = ((model(p + offset) - target(p)) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    p = torch.rand(4096, 3, generator=torch.Generator().manual_seed(seed + 1))
    with torch.no_grad():
        return float(((model(p + offset) - target(p)) ** 2).mean().sqrt())


@pytest.mark.parametrize("kernels", KERNELS)
def test_fits_a_smooth_field(kernels: str) -> None:
    # Calibrated: correct blend ~0.014 RMS; mirrored ~0.12, y/z-swapped ~0.08, flat 1/8 weights ~0.06.
    assert _fit_error(kernels=kernels) < 0.03


def test_a_broken_blend_does_not_fit(monkeypatch: pytest.MonkeyPatch) -> None:
    """The fit criterion above can fail: the torch path with mirrored corner weights misses it by far."""
    honest = encoding.corners_and_weights

    def mirrored_weights(*args: object) -> tuple[Tensor, Tensor]:
        rows, weights = honest(*args)  # type: ignore[arg-type]
        return rows, weights.flip(0)  # each corner gets the weight of the opposite corner

    monkeypatch.setattr(encoding, "corners_and_weights", mirrored_weights)
    broken = _fit_error(kernels="torch")
    assert broken > 0.045, f"broken blend reached {broken}"


def test_rejects_bad_arguments() -> None:
    with pytest.raises(ConfigError):
        HashGrid(log2_size=0)
    with pytest.raises(ConfigError):
        HashGrid(base_cell_m=0.0)
    with pytest.raises(ConfigError, match="mapping.runtime.kernels"):
        resolve_backend("cuda")
    with pytest.raises(H2vizError):
        HashGrid(log2_size=4)(torch.zeros(5, 2))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu() -> None:
    grid = _grid(seed=13)
    x = _test_points(1000, seed=14)
    cpu = grid(x)
    gpu = grid.cuda()(x.cuda())
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=0.0, atol=1e-12)
    (gpu**2).sum().backward()
    assert grid.tables.grad is not None and grid.tables.grad.is_cuda
