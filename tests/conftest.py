"""Test-wide helpers: where the real RGB-D sequences live (../shared/data) and skipping without them."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

import h2viz  # noqa: F401  (sets the thread-pool policy before NumPy and torch load)
from h2viz.sources.synthetic.frame_cache import ENV_DIR


@pytest.fixture(scope="session", autouse=True)
def frame_cache_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The synthetic room's frame cache in a folder of this test session (never the user's ~/.cache), shared
    by its tests and the processes they start."""
    folder = tmp_path_factory.mktemp("h2viz-cache")
    before = os.environ.get(ENV_DIR)
    os.environ[ENV_DIR] = str(folder)
    yield folder
    if before is None:
        os.environ.pop(ENV_DIR, None)
    else:
        os.environ[ENV_DIR] = before


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
