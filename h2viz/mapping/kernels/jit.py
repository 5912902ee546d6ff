"""numba compilation with an on-disk cache (compiling in every process when no cache directory is writable),
and `parallel_region`, under which every parallel kernel of the package is entered.

numba's cache only notices edits to the file a cached function is defined in: helpers that a kernel inlines
should live in the kernel's own module.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from typing import Any

import numba
import torch

_PARALLEL = threading.Lock()


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


@contextlib.contextmanager
def parallel_region() -> Iterator[int]:
    """Hold the package's one parallel-kernel lock, with numba's thread count matched to torch's (capped at
    numba's pool size); yields that count. numba's workqueue threading layer (used when neither OpenMP nor TBB
    is available) must not be entered from two threads at once, and the mapping and meshing threads both run
    parallel kernels."""
    with _PARALLEL:
        n = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
        numba.set_num_threads(n)
        yield n
