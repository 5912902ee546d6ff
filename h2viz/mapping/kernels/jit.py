"""numba compilation with an on-disk cache (compiling in every process when no cache directory is writable),
and `parallel_region`, under which every parallel kernel of the package is entered.

numba's cache only notices edits to the file a cached function is defined in: helpers that a kernel inlines
should live in the kernel's own module (`prefetch`, a fixed hint that never changes a result, is the exception).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from typing import Any

import numba
import torch
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

_PARALLEL = threading.Lock()
_LOCAL = threading.local()  # .serial: this thread runs every kernel on one thread (see `serial_kernels`)
_CONCURRENT_LAYERS = ("omp", "tbb")  # numba threading layers that may be entered from several threads at once


def njit(
    fn: Callable[..., Any] | None = None,
    *,
    parallel: bool = False,
    fastmath: bool = False,
    inline: bool = False,
    nogil: bool = True,
) -> Any:
    """numba.njit(cache=True, nogil=True, ...); usable as `@njit` or `@njit(parallel=True)`.

    Kernels release the GIL: the meshing thread's kernels then never hold up the mapping thread's Python.
    """
    opts: dict[str, Any] = {"parallel": parallel, "fastmath": fastmath, "nogil": nogil}
    if inline:
        opts["inline"] = "always"

    def wrap(f: Callable[..., Any]) -> Any:
        try:
            return numba.njit(cache=True, **opts)(f)
        except RuntimeError:  # numba found no writable place for its cache
            return numba.njit(cache=False, **opts)(f)

    return wrap(fn) if fn is not None else wrap


@intrinsic
def prefetch(typingctx: Any, array: Any, row: Any) -> Any:
    """(in a kernel) Ask the CPU to start loading the cache line of array[row, 0] of a 2-D array: a hint, results
    do not change. Scattered reads and writes (hash tables, lattices) issued a few items ahead overlap their cache
    misses instead of waiting for each in turn."""

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        array_type = signature.args[0]
        data = context.make_array(array_type)(context, builder, args[0])
        index = [args[1], context.get_constant(types.intp, 0)]
        item = cgutils.get_item_pointer(context, builder, array_type, data, index, wraparound=False)
        address = builder.bitcast(item, cgutils.voidptr_t)
        i32 = ir.IntType(32)
        signature_ir = ir.FunctionType(ir.VoidType(), [address.type, i32, i32, i32])
        llvm_prefetch = builder.module.declare_intrinsic("llvm.prefetch", [address.type], signature_ir)
        builder.call(llvm_prefetch, [address, i32(0), i32(3), i32(1)])  # read, keep in all cache levels, data
        return context.get_dummy_value()

    return types.void(array, row), codegen


def serial_kernels() -> None:
    """Make the calling thread (a background one, e.g. meshing) run every kernel on one thread, so that it takes
    at most one core from the mapping thread's kernels. With a threading layer that may be entered from several
    threads at once (OpenMP, TBB) its kernels no longer wait for `parallel_region`'s lock either."""
    _LOCAL.serial = True
    numba.set_num_threads(1)  # thread-local in numba: kernels entered without `parallel_region` follow it too


def _concurrent_layer() -> bool:
    """numba's threading layer (chosen at the first parallel kernel) may be entered from several threads."""
    try:
        return numba.threading_layer() in _CONCURRENT_LAYERS
    except ValueError:  # no parallel kernel has run yet: the layer is not chosen
        return False


@contextlib.contextmanager
def parallel_region() -> Iterator[int]:
    """Hold the package's one parallel-kernel lock, with numba's thread count matched to torch's (capped at
    numba's pool size); yields that count. numba's workqueue threading layer (used when neither OpenMP nor TBB
    is available) must not be entered from two threads at once, and the mapping and meshing threads both run
    parallel kernels. A thread under `serial_kernels` yields 1, without the lock when the layer allows it."""
    if getattr(_LOCAL, "serial", False):
        with contextlib.nullcontext() if _concurrent_layer() else _PARALLEL:
            numba.set_num_threads(1)
            yield 1
        return
    with _PARALLEL:
        n = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
        numba.set_num_threads(n)
        yield n
