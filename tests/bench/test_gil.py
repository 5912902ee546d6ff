"""bench/gil.py: the former NumPy decoding and the torch one agree bit for bit, and a short run prints every row."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from bench import gil


def test_numpy_and_torch_sums_agree_on_any_bits() -> None:
    rng = np.random.default_rng(3)
    second = rng.integers(0, 2**32, (7, 33), dtype=np.uint64).astype(np.uint32)
    second[:, :3] = np.uint32(2**32 - 1)  # sums that wrap
    assert np.array_equal(gil.numpy_sums(second), gil.undo_row_differences(second))


def test_a_short_run_prints_every_row(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    interval = sys.getswitchinterval()
    monkeypatch.setattr(sys, "argv", ["gil.py", "--seconds", "0.05"])
    gil.main()
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ") and "---" not in line]
    assert len(rows) == 1 + 6  # the header and six rows
    assert all(int(row.rsplit("|", 2)[1].replace(",", "")) > 0 for row in rows[1:])  # every thread made progress
    assert sys.getswitchinterval() == interval  # put back
