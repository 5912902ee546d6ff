"""parallel_region and serial_kernels: the mapping thread's kernels get the cores, a background thread's one."""

from __future__ import annotations

import threading

import numba
import numpy as np
import pytest
import torch

from h2viz.mapping.kernels import jit


@numba.njit(parallel=True, cache=False)
def _parallel_sum(x: np.ndarray) -> float:
    total = 0.0
    for i in numba.prange(x.size):
        total += x[i]
    return total


def _in_thread(fn):  # noqa: ANN001, ANN202
    out: list = []
    t = threading.Thread(target=lambda: out.append(fn()))
    t.start()
    t.join(timeout=10)
    assert not t.is_alive(), "the thread did not finish (blocked on the parallel-kernel lock?)"
    return out[0]


def test_the_mapping_thread_gets_torchs_thread_count_and_a_serial_thread_one() -> None:
    _parallel_sum(np.ones(1000))  # chooses numba's threading layer
    with jit.parallel_region() as n:
        assert n == max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))

    def serial() -> tuple[int, int, float]:
        jit.serial_kernels()
        with jit.parallel_region() as n:
            return n, numba.get_num_threads(), _parallel_sum(np.ones(1000))

    n, threads, total = _in_thread(serial)
    assert (n, threads, total) == (1, 1, 1000.0)
    with jit.parallel_region() as n:  # numba's count is per thread: the caller's is untouched
        assert n == max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))


def test_a_serial_thread_does_not_wait_for_the_lock_when_the_layer_allows_it() -> None:
    _parallel_sum(np.ones(1000))
    if not jit._concurrent_layer():
        pytest.skip(f"numba's {numba.threading_layer()} layer must not be entered from two threads at once")

    def serial() -> float:
        jit.serial_kernels()
        with jit.parallel_region():
            return _parallel_sum(np.ones(10))

    with jit.parallel_region():  # the mapping thread is inside a parallel kernel
        assert _in_thread(serial) == 10.0
