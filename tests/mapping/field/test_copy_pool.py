"""CopyPool: copies whose storage is reused once their owner is gone, never while it lives."""

from __future__ import annotations

import gc

import torch

from h2viz.mapping.field import copy_pool
from h2viz.mapping.field.copy_pool import CopyPool


class Owner:
    """Stands for a frozen field."""


def big(n: int = 400_000, value: float = 1.0) -> torch.Tensor:
    return torch.full((n // 4, 2, 2), value)  # 1.6 MB at the default n: pooled


def test_a_copy_is_equal_and_independent_of_its_source() -> None:
    pool, owner, src = CopyPool(), Owner(), torch.arange(400_000, dtype=torch.float32).view(-1, 4)
    dst = pool.copy(src, owner)
    assert torch.equal(dst, src) and dst.data_ptr() != src.data_ptr() and dst.is_contiguous()
    src += 1
    assert torch.equal(dst + 1, src)


def test_storage_returns_to_the_pool_when_its_owner_is_collected_and_is_reused() -> None:
    pool = CopyPool()
    first = Owner()
    ptr = pool.copy(big(), first).data_ptr()
    alive = Owner()
    other = pool.copy(big(value=2.0), alive)
    assert other.data_ptr() != ptr and pool.allocated == 2 and pool.reused == 0  # in use: never handed out twice
    del first
    gc.collect()
    again = pool.copy(big(value=3.0), Owner())  # its owner dies at once: the storage comes back next time
    assert again.data_ptr() == ptr and bool((again == 3.0).all()) and pool.reused == 1
    assert bool((other == 2.0).all())  # the live owner's copy is untouched


def test_a_grown_source_gets_new_storage_and_a_smaller_one_the_smallest_that_fits() -> None:
    pool = CopyPool()
    small_owner, large_owner = Owner(), Owner()
    small_ptr = pool.copy(big(400_000), small_owner).data_ptr()
    pool.copy(big(2_000_000), large_owner)
    del small_owner, large_owner
    gc.collect()
    grown = pool.copy(big(1_000_000), Owner())  # beyond the small storage's headroom: the large one
    assert grown.data_ptr() != small_ptr and pool.reused == 1
    fits = pool.copy(big(440_000), Owner())  # within the small one's headroom: the smallest that fits
    assert fits.data_ptr() == small_ptr and pool.reused == 2


def test_small_tensors_are_cloned_and_the_pool_keeps_a_bounded_number_of_storages() -> None:
    pool = CopyPool()
    tiny = pool.copy(torch.ones(10), Owner())
    assert torch.equal(tiny, torch.ones(10)) and pool.allocated == pool.reused == 0
    owners = [Owner() for _ in range(copy_pool.MAX_FREE + 3)]
    for owner in owners:
        pool.copy(big(), owner)
    del owners, owner
    gc.collect()
    assert pool.free_bytes <= copy_pool.MAX_FREE * int(big().numel() * copy_pool.HEADROOM) * 4
