"""bench/budget.py on a tiny real `h2viz map` run: the region table and the Acc split agree with metrics.json."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import budget
from h2viz.cli import main as h2viz_main
from tests.test_cli import TINY as CLI_TINY

TINY = [*CLI_TINY, "--set", "eval.n_extrapolate=0"]  # the tiny run of tests/test_cli.py, no novel views


def _table(lines: list[str], title: str) -> list[list[str]]:
    """Cells of the markdown table that follows the line starting with `title`."""
    start = next(i for i, line in enumerate(lines) if line.startswith(title))
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            if rows:
                break
            continue
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows[2:]  # without the header and its rule


def test_budget_of_a_run_matches_its_metrics(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run"
    assert h2viz_main(["map", "--frames", "4", "--stride", "10", "--out", str(run), "-q", *TINY]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    capsys.readouterr()

    assert budget.main([str(run)]) == 0
    lines = capsys.readouterr().out.splitlines()
    regions = _table(lines, "## PSNR by region")
    assert [r[0] for r in regions] == ["geometry edges", "texture edges", "flat", "all"]
    assert sum(float(r[1]) for r in regions[:3]) == pytest.approx(100.0, abs=0.2)
    assert sum(float(r[2]) for r in regions[:3]) == pytest.approx(100.0, abs=0.2)
    assert 10.0 < float(regions[3][3]) < 40.0
    acc_line = next(line for line in lines if line.startswith("## Acc"))
    assert f"Acc {metrics['mesh']['acc_cm']:.3f} cm" in acc_line  # the same samples and culling as h2viz map
    floor = float(acc_line.split("floor ")[1].split(" cm")[0])
    bins = _table(lines, "## Acc")
    excess = sum(float(b[2]) for b in bins)
    assert excess == pytest.approx(metrics["mesh"]["acc_cm"] - floor, abs=2e-3)
    assert sum(float(b[1]) for b in bins) == pytest.approx(100.0, abs=0.05)
    assert any(line.startswith("command: .venv/bin/python bench/budget.py") for line in lines)


def test_budget_names_what_a_run_directory_lacks(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert budget.main([str(tmp_path)]) == 2
    assert "config.yaml is missing" in capsys.readouterr().out
