"""numba compilation with an on-disk cache (compiling in every process when no cache directory is writable),
and the thread count its parallel kernels use.

numba's cache only notices edits to the file a cached function is defined in: helpers that a kernel inlines
should live in the kernel's own module.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba
import torch


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


def threads() -> int:
    """Match numba's thread count to torch's (capped at numba's pool size) and return it."""
    n = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(n)
    return n
