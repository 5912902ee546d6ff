"""bench/quality.py end to end on a tiny synthetic run: h2viz, the TSDF baseline and the ground-truth row
produce evaluated rows, held-out frames are scored but not mapped, a missing dataset becomes a note, and the
table and JSON hold what was measured."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import pytest

import bench.common
from bench import quality

pytestmark = pytest.mark.skipif(importlib.util.find_spec("open3d") is None, reason="open3d is not installed")

TINY = [
    "source.synthetic.width=160",
    "source.synthetic.height=120",
    "mapping.optimization.max_iters=2",
    "mapping.representation.hash_log2_size=14",
    "eval.n_points=20000",
    "eval.n_interpolate=2",
    "eval.n_extrapolate=2",
]


@pytest.mark.slow
def test_quality_table_and_json(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    monkeypatch.setattr(bench.common, "SHARED_DATA", tmp_path / "absent")  # the real sequences are "missing"
    argv = ["--datasets", "synthetic,fountain", "--methods", "h2viz,tsdf,gt", "--frames", "5", "--heldout-k", "4"]
    argv += [arg for item in TINY for arg in ("--set", item)]
    argv += ["--out", str(tmp_path / "runs"), "--json", str(tmp_path / "rows.json")]
    assert quality.main(argv) == 0

    out = capsys.readouterr().out
    table = [line for line in out.splitlines() if line.startswith("| ")]
    assert len(table) == 1 + 6 and table[0].split("|")[3].strip() == "Acc (cm)"
    assert "held-out PSNR (dB)" in table[0] and "held-out depth L1 (cm)" in table[0]
    assert "fountain did not run" in out and "command: .venv/bin/python bench/quality.py" in out

    rows = {(r["method"], r["dataset"]): r for r in json.loads((tmp_path / "rows.json").read_text())["rows"]}
    for method in ("h2viz", "tsdf"):
        row = rows[(method, "synthetic")]
        assert row["frames"] == 4 and len(row["frame_times_s"]) == 4 and row["median_frame_s"] > 0  # frame 2 held out
        assert set(row["metrics"]) == {"mesh", "interpolate", "extrapolate", "heldout"}
        held = row["metrics"]["heldout"]
        assert held["n_views"] == 1 and math.isfinite(held["psnr_db"]) and math.isfinite(held["depth_l1_cm"])
        assert math.isfinite(row["metrics"]["mesh"]["acc_cm"]) and row["note"] == ""
        assert (tmp_path / "runs" / "synthetic" / method / "mesh.ply").is_file()
        assert "not found" in rows[(method, "fountain")]["note"] and rows[(method, "fountain")]["frames"] == 0
    gt = rows[("gt", "synthetic")]["metrics"]  # the perfect mesh: only Comp and captured views are kept
    assert (
        "acc_cm" not in gt["mesh"] and "extrapolate" not in gt and rows[("gt", "synthetic")]["median_frame_s"] is None
    )
    assert gt["heldout"]["depth_l1_cm"] < gt["interpolate"]["depth_l1_cm"] + 1.0  # the room's mesh needs no mapping
    tsdf = rows[("tsdf", "synthetic")]["metrics"]  # exact depth: the fused mesh is as complete as the room itself
    assert tsdf["mesh"]["comp_cm"] < gt["mesh"]["comp_cm"] + 0.5
    assert tsdf["mesh"]["comp_ratio"] > gt["mesh"]["comp_ratio"] - 5.0
    assert tsdf["interpolate"]["depth_l1_cm"] < gt["interpolate"]["depth_l1_cm"] + 1.5
    assert tsdf["heldout"]["depth_l1_cm"] < gt["heldout"]["depth_l1_cm"] + 1.5
