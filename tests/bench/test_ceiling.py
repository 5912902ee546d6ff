"""bench/ceiling.py on the tiny synthetic room: one row per colour grid, with its curve and the grid it fitted."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench import ceiling
from h2viz.cli import main as h2viz_main
from tests.test_cli import TINY as CLI_TINY

TINY = [*CLI_TINY, "--set", "source.synthetic.n_frames=20"]  # the tiny run of tests/test_cli.py, fewer frames


def test_ceiling_fits_each_variant_and_prints_one_row(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--steps", "60", "--batch", "2048", "--variant", "mapping.representation.hash_levels=2", *TINY]
    assert ceiling.main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines if line.startswith("| synthetic")]
    assert [r[1] for r in rows] == ["L=4, finest 12.5 mm, T=2^15", "L=2, finest 50 mm, T=2^15"]
    for row in rows:
        curve = [float(v) for v in row[2].split(" -> ")]
        assert len(curve) == 4 and curve[-1] == float(row[3])
        assert 8.0 < curve[-1] < 40.0 and curve[-1] > curve[0]  # it learns, and stays a real image error
    assert float(rows[0][3]) > float(rows[1][3])  # four levels fit the room's texture better than two
    assert any(line.startswith("command: .venv/bin/python bench/ceiling.py") for line in lines)


def test_ceiling_of_a_run_scores_its_own_field_first(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run"
    assert h2viz_main(["map", "--frames", "4", "--stride", "5", "--out", str(run), "-q", *TINY]) == 0
    capsys.readouterr()
    assert ceiling.main(["--run", str(run), "--steps", "40", "--batch", "2048"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines if line.startswith("| run ")]
    assert [r[1] for r in rows] == ["L=4, finest 12.5 mm, T=2^15, mapped", "L=4, finest 12.5 mm, T=2^15"]
    mapped, fitted = rows
    assert mapped[2] == "-" and 5.0 < float(mapped[3]) < 40.0  # the run's field, not fitted again
    assert 5.0 < float(fitted[3]) < 40.0


def test_ceiling_names_a_run_without_checkpoint(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert ceiling.main(["--run", str(tmp_path)]) == 2
    assert "checkpoint.pt is missing" in capsys.readouterr().out


def test_ceiling_skips_an_unreadable_source_by_name(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--steps", "1", "--set", "source.format=tum", "--set", "source.path=/nonexistent/h2viz-data"]
    assert ceiling.main(args) == 0
    out = capsys.readouterr().out
    assert "synthetic: skipped (/nonexistent/h2viz-data does not exist" in out
