"""The fused CPU kernel modules (numba), imported on first use: None when numba is not installed, and the
pure-torch reference paths run instead."""

from __future__ import annotations

import functools
import importlib
from types import ModuleType


@functools.cache
def kernel_module(name: str) -> ModuleType | None:
    """h2viz.mapping.`name` (hash_numba, prior_numba, decoder_numba, frame_numba, loss_numba, optim_numba, band,
    marching_numba, support_numba), or None when numba cannot be imported."""
    try:
        return importlib.import_module(f"h2viz.mapping.{name}")
    except ImportError:
        return None
