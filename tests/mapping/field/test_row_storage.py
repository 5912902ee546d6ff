"""RowStorage: growing per-voxel arrays hand out zero rows, keep the old ones, and copy rarely."""

from __future__ import annotations

import torch

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


def test_growth_within_the_reservation_is_a_view_and_reservations_double() -> None:
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
