"""The backends the mapping tests run the stages with: the compiled kernels when numba imports, and the reference."""

from __future__ import annotations

import pytest

from h2viz.mapping.backend import resolve_backend

FAST = resolve_backend("auto", "cpu")
"""numba on the CPU (the torch backend when numba is not installed)."""
REFERENCE = resolve_backend("torch", "cpu")
needs_numba = pytest.mark.skipif(FAST.tensor_kernels is None, reason="numba is not installed")
