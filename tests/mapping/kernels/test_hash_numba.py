"""Fused numba hash-grid kernels: exact hashing, forward and table-gradient parity with the torch path and the
plain reference, HashGrid dispatch, empty input, determinism, threads, and the no-cache fallback."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import torch
from torch import Tensor

from h2viz.errors import H2vizError
from h2viz.mapping.field.encoding import HashGrid, encode, hash_grid_reference, level_cell_sizes
from h2viz.mapping.kernels.jit import njit
from tests.mapping.backends import FAST

numba = pytest.importorskip("numba")
hash_numba = pytest.importorskip("h2viz.mapping.kernels.hash_numba")

SHAPES = [(4, 2, 19, 0.1, 2.0), (3, 4, 12, 0.08, 1.5), (1, 1, 5, 0.5, 2.0), (6, 2, 14, 0.2, 1.7)]
"""(L, F, log2 T, coarsest cell m, scale): the defaults, wider features, a tiny table that collides a lot."""


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _points(n: int, seed: int, cell_m: float) -> Tensor:
    """Points (N,3) float64: a 5 m room around the origin (negative too), ~1e4 m out, and on cell faces."""
    g = torch.Generator().manual_seed(seed)
    room = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 5.0
    far = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 2e4
    faces = torch.round(room / cell_m) * cell_m  # on corners of the coarsest level, faces of all finer
    faces[::2, 1] += 0.37 * cell_m  # half of them on faces only
    return torch.cat([room, far, faces])


def _tables(shape: tuple[int, int, int, float, float], dtype: torch.dtype, seed: int) -> Tensor:
    n_levels, n_feat, log2, _, _ = shape
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n_levels, 1 << log2, n_feat, generator=g).to(dtype).requires_grad_()


def _cells(shape: tuple[int, int, int, float, float]) -> list[float]:
    return level_cell_sizes(shape[0], shape[3], shape[4])


def test_hash_rows_are_exact_for_negative_and_huge_lattice_coordinates() -> None:
    rng = np.random.default_rng(0)
    lattice = np.concatenate(
        [rng.integers(-(2**31) + 2, 2**31 - 2, (300, 3)), rng.integers(-50, 50, (300, 3)), [[0, 0, 0], [-1, -1, -1]]]
    )
    for log2 in (1, 7, 19, 28):
        mask = (1 << log2) - 1
        for i, j, k in lattice.tolist():
            rows, weights = hash_numba._corners(i + 0.25, j + 0.5, k + 0.75, 1.0, mask)
            expected = [
                (a ^ (b * 2654435761) ^ (c * 805459861)) % (1 << log2)  # Python ints: exact, floor modulo
                for a in (i, i + 1)
                for b in (j, j + 1)
                for c in (k, k + 1)
            ]
            assert list(rows) == expected
    assert sum(weights) == pytest.approx(1.0, abs=1e-15)
    assert weights[0] == pytest.approx(0.75 * 0.5 * 0.25, abs=1e-15)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("x_dtype", [torch.float32, torch.float64])
def test_forward_and_table_gradient_match_torch_and_reference(
    shape: tuple[int, int, int, float, float], x_dtype: torch.dtype
) -> None:
    tables = _tables(shape, torch.float32, seed=1)
    cells = _cells(shape)
    x = _points(700, seed=2, cell_m=shape[3]).to(x_dtype)
    upstream = torch.randn(x.shape[0], shape[0] * shape[1], generator=torch.Generator().manual_seed(3))
    fused = hash_numba.fused_encode(x, tables, cells)
    torch_path = encode(x, tables, cells)
    reference64 = hash_grid_reference(x.double(), tables.double(), shape[3], shape[4])  # float64 throughout
    assert fused.shape == torch_path.shape and fused.dtype == torch.float32
    torch.testing.assert_close(fused.double(), reference64, rtol=0.0, atol=1e-6)  # O(1) values
    torch.testing.assert_close(fused, torch_path, rtol=0.0, atol=2e-6)
    assert reference64.abs().max() > 1.0
    grads = [torch.autograd.grad((out * upstream).sum(), tables)[0] for out in (fused, torch_path, reference64)]
    assert grads[0].dtype == torch.float32 and int((grads[0] != 0).sum()) > min(100, tables.numel() // 2)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(grads[0], grads[2], rtol=1e-5, atol=1e-5)  # float64 sums, cast back


@pytest.mark.parametrize("shape", SHAPES[:2])
def test_float64_tables_match_reference_tightly(shape: tuple[int, int, int, float, float]) -> None:
    tables = _tables(shape, torch.float64, seed=4)
    x = _points(500, seed=5, cell_m=shape[3])
    upstream = torch.randn(x.shape[0], shape[0] * shape[1], dtype=torch.float64)
    fused = hash_numba.fused_encode(x, tables, _cells(shape))
    reference = hash_grid_reference(x, tables, shape[3], shape[4])
    assert fused.dtype == torch.float64
    torch.testing.assert_close(fused, reference, rtol=0.0, atol=1e-12)
    (got,) = torch.autograd.grad((fused * upstream).sum(), tables)
    (expected,) = torch.autograd.grad((reference * upstream).sum(), tables)
    torch.testing.assert_close(got, expected, rtol=0.0, atol=1e-11)


def test_hash_grid_auto_and_torch_kernels_agree() -> None:
    torch.manual_seed(6)
    fused, plain = HashGrid(log2_size=15, init_std=1.0, backend=FAST), HashGrid(log2_size=15, init_std=1.0)
    plain.load_state_dict(fused.state_dict())
    x = _points(400, seed=7, cell_m=0.1).float()
    upstream = torch.randn(x.shape[0], fused.output_dim)
    out_fused, out_plain = fused(x), plain(x)
    assert type(out_fused.grad_fn).__name__ == "_FusedEncodeBackward"
    assert type(out_plain.grad_fn).__name__ != "_FusedEncodeBackward"
    torch.testing.assert_close(out_fused, out_plain, rtol=0.0, atol=2e-6)
    (out_fused * upstream).sum().backward()
    (out_plain * upstream).sum().backward()
    torch.testing.assert_close(fused.tables.grad, plain.tables.grad, rtol=1e-5, atol=1e-5)
    with torch.no_grad():  # gradient-free calls (meshing, rendering) use the fused forward too
        torch.testing.assert_close(fused(x), out_plain.detach(), rtol=0.0, atol=2e-6)


def test_points_needing_a_gradient_take_the_torch_path() -> None:
    """Normals differentiate the encoding w.r.t. x; the fused kernels only provide table gradients."""
    torch.manual_seed(8)
    grid = HashGrid(log2_size=12, init_std=1.0, backend=FAST)
    x = _points(100, seed=9, cell_m=0.1).float().requires_grad_()
    out = grid(x)
    assert type(out.grad_fn).__name__ != "_FusedEncodeBackward"
    (grad_x,) = torch.autograd.grad(out.square().sum(), x)
    (expected,) = torch.autograd.grad(encode(x, grid.tables, grid.cell_sizes_m).square().sum(), x)
    torch.testing.assert_close(grad_x, expected)
    assert grad_x.abs().max() > 1.0


def test_fused_encode_refuses_what_it_cannot_do() -> None:
    tables = _tables(SHAPES[1], torch.float32, seed=13)
    with pytest.raises(H2vizError, match="gradient w.r.t. points"):
        hash_numba.fused_encode(torch.zeros(4, 3, requires_grad=True), tables, _cells(SHAPES[1]))
    with pytest.raises(H2vizError, match="power of two"):
        hash_numba.fused_encode(torch.zeros(4, 3), tables[:, :100], _cells(SHAPES[1]))
    with pytest.raises(H2vizError, match=r"\(N,3\)"):
        hash_numba.fused_encode(torch.zeros(4, 2), tables, _cells(SHAPES[1]))
    with pytest.raises(H2vizError, match="upstream gradient"):
        hash_numba.table_gradient(
            torch.zeros(4, 3, dtype=torch.float64), torch.zeros(5, 12), _cells(SHAPES[1]), tables.shape
        )
    with pytest.raises(H2vizError, match="gradient buffer"):
        hash_numba.table_gradient(
            torch.zeros(4, 3, dtype=torch.float64), torch.zeros(4, 12), _cells(SHAPES[1]), tables.shape, torch.zeros(3)
        )


def test_empty_input() -> None:
    tables = _tables(SHAPES[1], torch.float32, seed=10)
    out = hash_numba.fused_encode(torch.zeros(0, 3), tables, _cells(SHAPES[1]))
    assert out.shape == (0, 12)
    (grad,) = torch.autograd.grad(out.sum(), tables)
    assert grad.shape == tables.shape and not grad.any()


def test_table_gradient_is_deterministic_across_threads() -> None:
    shape = SHAPES[0]
    tables = _tables(shape, torch.float32, seed=11)
    x = _points(3000, seed=12, cell_m=shape[3]).float()
    upstream = torch.randn(x.shape[0], shape[0] * shape[1])
    grads, features = [], []
    for threads in (1, 2, 2):
        torch.set_num_threads(threads)
        out = hash_numba.fused_encode(x, tables, _cells(shape))
        assert numba.get_num_threads() == min(threads, numba.config.NUMBA_NUM_THREADS)  # follows torch
        features.append(out.detach())
        grads.append(torch.autograd.grad((out * upstream).sum(), tables)[0])
    for other in range(1, 3):
        assert torch.equal(features[0], features[other]) and torch.equal(grads[0], grads[other])


def test_table_gradient_overwrites_a_given_buffer() -> None:
    shape = SHAPES[1]
    tables = _tables(shape, torch.float32, seed=14)
    x64 = _points(200, seed=15, cell_m=shape[3])
    upstream = torch.randn(x64.shape[0], shape[0] * shape[1])
    fresh = hash_numba.table_gradient(x64, upstream, _cells(shape), tables.shape)
    buffer = torch.full_like(tables, float("nan"))  # stale content must not leak into the result
    got = hash_numba.table_gradient(x64, upstream, _cells(shape), tables.shape, out=buffer)
    assert got is buffer and torch.equal(got, fresh)


def test_level_order_interleaves_coarse_and_fine() -> None:
    assert hash_numba.level_order(4).tolist() == [0, 3, 1, 2]
    assert hash_numba.level_order(5).tolist() == [0, 4, 1, 3, 2]
    assert hash_numba.level_order(1).tolist() == [0]


def test_kernels_compile_without_a_writable_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    """When numba finds no cache directory, the decorator falls back to compiling in every process."""
    from numba.core import caching

    impl = getattr(caching, "CacheImpl", None) or caching._CacheImpl  # renamed in numba 0.61
    monkeypatch.setattr(impl, "_locator_classes", [])

    def double_all(a: np.ndarray) -> np.ndarray:
        out = np.empty_like(a)
        for i in numba.prange(a.shape[0]):
            out[i] = 2 * a[i]
        return out

    with pytest.raises(RuntimeError, match="cannot cache"):
        numba.njit(cache=True)(double_all)
    kernel = njit(parallel=True)(double_all)
    assert kernel(np.arange(4.0)).tolist() == [0.0, 2.0, 4.0, 6.0]


def test_warmup_compiles_both_kernels() -> None:
    assert hash_numba.warmup() >= 0.0
    assert len(hash_numba._forward_kernel.signatures) >= 1
    assert len(hash_numba._table_grad_kernel.signatures) >= 1


def test_table_gradient_buffer_is_reused_only_when_no_gradient_holds_it() -> None:
    shape = SHAPES[2]
    tables = _tables(shape, torch.float32, seed=21)
    x = _points(100, seed=22, cell_m=shape[3]).float()
    kept = []
    for scale in (1.0, 2.0):  # gradients kept alive: each pass gets its own memory
        kept.append(torch.autograd.grad((hash_numba.fused_encode(x, tables, _cells(shape)) * scale).sum(), tables)[0])
    torch.testing.assert_close(kept[1], 2.0 * kept[0])
    pointers = set()
    for _ in range(3):  # the optimiser pattern: grad dropped before every pass, one buffer serves them all
        tables.grad = None
        hash_numba.fused_encode(x, tables, _cells(shape)).sum().backward()
        pointers.add(tables.grad.data_ptr())
        torch.testing.assert_close(tables.grad, kept[0])
    assert len(pointers) == 1
