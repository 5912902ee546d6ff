"""bench/speed.py: the summary statistics on known numbers, and a tiny end-to-end run whose table has every row,
whose warm-up frame is kept apart and whose stage breakdown stays inside each frame's time."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

import bench.common
from bench import speed
from bench.speed_run import STAGES, Run

TINY = [
    "source.synthetic.width=160",
    "source.synthetic.height=120",
    "mapping.optimization.max_iters=2",
    "mapping.representation.hash_log2_size=14",
    "eval.n_points=20000",
    "eval.n_interpolate=2",
]


def test_summary_of_known_times() -> None:
    run = Run("h2viz", "synthetic", mesh_every=5, frame_s=[float(t) for t in range(1, 11)], mesh_s=[0.5, 1.5])
    run.stage_s = {stage: [0.1 * k] * 10 for k, stage in enumerate(STAGES)}
    run.iterations = [10, 10, 4, 6]
    s = speed.summary(run)
    assert s["median_frame_s"] == pytest.approx(5.5) and s["p90_frame_s"] == pytest.approx(9.1)
    assert s["median_mesh_s"] == pytest.approx(1.0) and s["mesh_s_per_frame"] == pytest.approx(0.2)
    forward_s = 0.1 * STAGES.index("forward")
    assert s["mean_iterations"] == pytest.approx(7.5) and s["median_forward_s"] == pytest.approx(forward_s)
    cells = speed.cells(run)
    assert len(cells) == len(speed.COLUMNS) and cells[2] == "-"  # no warm-up recorded: the frames cell says so


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("open3d") is None, reason="open3d is not installed")
def test_speed_table_and_json(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    monkeypatch.setattr(bench.common, "SHARED_DATA", tmp_path / "absent")  # the real sequences are "missing"
    argv = ["--datasets", "synthetic,redkitchen", "--methods", "h2viz,tsdf", "--frames", "4", "--mesh-every", "2"]
    argv += [arg for item in TINY for arg in ("--set", item)]
    argv += ["--threads", "1", "--json", str(tmp_path / "rows.json")]
    assert speed.main(argv) == 0

    out = capsys.readouterr().out
    table = [line.split("|")[1:-1] for line in out.splitlines() if line.startswith("| ")]
    assert [c.strip() for c in table[0]] == speed.COLUMNS
    assert [(r[0].strip(), r[1].strip()) for r in table[1:]] == [
        ("h2viz", "synthetic"),
        ("tsdf", "synthetic"),
        ("h2viz", "redkitchen"),
        ("tsdf", "redkitchen"),
    ]
    assert "redkitchen did not run" in out and "command: .venv/bin/python bench/speed.py" in out

    rows = {(r["method"], r["dataset"]): r for r in json.loads((tmp_path / "rows.json").read_text())["rows"]}
    for method in ("h2viz", "tsdf"):
        row = rows[(method, "synthetic")]
        assert row["note"] == "" and row["threads"] == 1
        assert row["warmup_map_s"] > 0 and row["warmup_mesh_s"] > 0  # frame 0 and its mesh update, kept apart
        assert len(row["frame_s"]) == len(row["cpu_s"]) == 3  # frames 1-3 (frame 0 is the warm-up)
        assert len(row["mesh_s"]) == 1  # the mesh update after frame 2 (the one after frame 0 is the warm-up)
        assert row["peak_rss_mb"] >= row["start_rss_mb"] > 0
        assert set(row["metrics"]) == {"mesh", "interpolate"}  # no extrapolated views: the bench does not use them
        assert np.isfinite(row["metrics"]["interpolate"]["depth_l1_cm"]) and row["metrics"]["mesh"]["comp_ratio"] > 0
        assert "not found" in rows[(method, "redkitchen")]["note"]
    h2viz = rows[("h2viz", "synthetic")]
    assert h2viz["kernels"] and h2viz["iterations"] and all(1 <= i <= 2 for i in h2viz["iterations"])
    stage_sum = np.sum([h2viz["stage_s"][stage] for stage in STAGES], axis=0)  # (frames,)
    assert np.all(stage_sum <= np.array(h2viz["frame_s"]) + 1e-6)  # the breakdown lies inside each frame's time
    tsdf = rows[("tsdf", "synthetic")]
    assert tsdf["iterations"] == [] and tsdf["stage_s"] == {}
    assert tsdf["metrics"]["interpolate"]["depth_l1_cm"] < 3.0  # exact depth fused: evaluated on reloaded frames
