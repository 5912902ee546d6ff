"""Test-wide helpers: where the real RGB-D sequences live (../shared/data) and skipping without them."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

import h2viz  # noqa: F401  (sets the thread-pool policy before NumPy and torch load)


def shared_data(name: str) -> Path:
    """Path of a real dataset folder (or file) in ../shared/data relative to the repository root."""
    return Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / name


@pytest.fixture
def shared_dataset() -> Callable[[str], Path]:
    """Call with a dataset name to get its path; the test is skipped when it is absent."""

    def get(name: str) -> Path:
        path = shared_data(name)
        if not path.exists():
            pytest.skip(f"real data {name} not found in ../shared/data")
        return path

    return get
