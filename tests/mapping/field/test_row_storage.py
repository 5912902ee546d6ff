"""RowStorage: growing per-voxel arrays hand out zero rows, keep the old ones, and copy rarely."""

from __future__ import annotations

import pytest
import torch

from h2viz.mapping.field import row_storage
from h2viz.mapping.field.row_storage import MIN_ROWS, RowStorage


def test_new_rows_are_zero_and_old_rows_kept_across_a_reallocation() -> None:
    store = RowStorage()
    rows = store.grow(torch.zeros(0, 5, 2), 10)
    assert rows.shape == (10, 5, 2) and not rows.any()
    rows[:] = torch.arange(100, dtype=torch.float32).view(10, 5, 2)
    kept = rows.clone()
    rows = store.grow(rows, 3 * MIN_ROWS)  # past the first reservation: moved to new storage
    assert rows.shape[0] == 3 * MIN_ROWS
    assert torch.equal(rows[:10], kept)
    assert not rows[10:].any()


def test_rows_handed_out_are_zeroed_even_where_the_reservation_held_garbage() -> None:
    store = RowStorage()
    rows = store.grow(torch.zeros(0, 3), 4)
    assert store._storage is not None
    store._storage[4:].fill_(7.0)  # what uninitialised memory may hold
    rows[:] = 1.0
    rows = store.grow(rows, 20)
    assert torch.equal(rows[:4], torch.ones(4, 3))
    assert not rows[4:].any()


def test_growth_within_the_reservation_is_a_view_and_reservations_double(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(row_storage, "RESERVE_BYTES", 0)  # the doubling alone
    store = RowStorage()
    rows = store.grow(torch.zeros(0, 2), 1)
    base = rows.data_ptr()
    reallocations = 0
    for n in range(2, 5000):
        ptr = rows.data_ptr()
        rows = store.grow(rows, n)
        reallocations += rows.data_ptr() != ptr
    assert rows.data_ptr() != base and rows.shape == (4999, 2)
    assert reallocations <= 5  # 256 -> 512 -> ... -> 8192: each row copied about once
    assert store.capacity >= 4999


def test_the_first_host_reservation_holds_a_large_map_without_a_copy() -> None:
    store = RowStorage()
    row = torch.zeros(0, 2197, 4)  # a colour lattice row (35 KB)
    rows = store.grow(row, 1)
    base = rows.data_ptr()
    for n in range(1000, 25_001, 1000):  # a 25k-voxel map, grown frame by frame
        rows = store.grow(rows, n)
        assert rows.data_ptr() == base
    assert store.capacity * 2197 * 4 * 4 >= row_storage.RESERVE_BYTES - 2197 * 16


def test_a_refused_reservation_falls_back_to_doubling(monkeypatch: pytest.MonkeyPatch) -> None:
    real_empty = torch.empty

    def strict_empty(shape: tuple[int, ...], **kwargs: object) -> torch.Tensor:
        if shape[0] > 10_000:
            raise RuntimeError("DefaultCPUAllocator: can't allocate memory")
        return real_empty(shape, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(row_storage.torch, "empty", strict_empty)
    store = RowStorage()
    rows = store.grow(torch.zeros(0, 2), 300)
    assert store.capacity == 300  # the large reservation refused: just what is needed
    rows[:] = 5.0
    rows = store.grow(rows, 9000)
    assert rows.shape == (9000, 2) and bool((rows[:300] == 5.0).all()) and not rows[300:].any()


def test_a_foreign_tensor_is_adopted_and_never_written_through() -> None:
    store = RowStorage()
    store.grow(torch.zeros(0, 2), 8)
    loaded = torch.full((8, 2), 3.0)  # e.g. a checkpoint's lattices, same size as the storage's view
    grown = store.grow(loaded, 12)
    assert torch.equal(grown[:8], loaded) and not grown[8:].any()
    assert grown.data_ptr() != loaded.data_ptr()
    assert torch.equal(loaded, torch.full((8, 2), 3.0))


def test_release_forgets_the_storage_and_shrinking_is_a_no_op() -> None:
    store = RowStorage()
    rows = store.grow(torch.zeros(0, 2), 10)
    assert store.grow(rows, 5) is rows
    store.release()
    assert store.capacity == 0
    again = store.grow(rows, 11)
    assert again.shape == (11, 2) and torch.equal(again[:10], rows)
