"""`h2viz` end to end: map the synthetic scene with real outputs, resume, eval, and clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from h2viz.cli import main
from h2viz.mapping.mapper import INTEGRATION_STAGES

TINY = [
    "--set", "source.synthetic.width=96", "--set", "source.synthetic.height=72",
    "--set", "source.synthetic.n_frames=80", "--set", "mapping.representation.min_points_per_voxel=1",
    "--set", "mapping.representation.hash_log2_size=15", "--set", "mapping.sampling.rays_per_iter=1024", "--set",
    "mapping.optimization.max_iters=5",
    "--set", "mapping.runtime.device=cpu", "--set", "eval.n_points=20000", "--set", "eval.n_interpolate=3",
    "--set", "eval.n_extrapolate=2", "--set", "eval.render_downscale=1",
]  # fmt: skip


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("run")
    assert main(["map", "--frames", "6", "--stride", "10", "--out", str(out), "-q", *TINY]) == 0
    return out


def test_map_writes_mesh_checkpoint_config_stats_and_metrics(run_dir: Path) -> None:
    mesh = trimesh.load(run_dir / "mesh.ply", process=False)
    assert len(mesh.faces) > 1000 and mesh.visual.vertex_colors.shape[0] == len(mesh.vertices)
    assert (run_dir / "checkpoint.pt").is_file()
    cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert cfg["mapping"]["optimization"]["max_iters"] == 5 and cfg["source"]["format"] == "synthetic"
    stats = json.loads((run_dir / "stats.json").read_text())
    frames = stats["frames"]
    assert [f["index"] for f in frames] == [0, 10, 20, 30, 40, 50]
    for f in frames:
        assert (
            f["map_time_s"] > 0 and 1 <= f["iterations"] <= 5 and f["n_voxels"] > 0 and f["n_keyframes"] >= 1
        )
        stages = {*INTEGRATION_STAGES, "sampling", "forward", "backward", "optimiser"}
        assert set(f["timings"]) == stages and sum(f["timings"].values()) <= f["map_time_s"]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    # six low-resolution frames with five iterations each: a coarse map, but a real one
    assert metrics["mesh"]["acc_cm"] < 5.0 and metrics["mesh"]["comp_ratio"] > 60, metrics["mesh"]
    assert metrics["interpolate"]["depth_l1_cm"] < 5.0 and np.isfinite(metrics["interpolate"]["psnr_db"])
    assert "extrapolate" in metrics


def test_resume_continues_after_the_last_frame(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "resumed"
    args = ["map", "--frames", "8", "--stride", "10", "--out", str(out), "-q", *TINY]
    assert main([*args, "--resume", str(run_dir / "checkpoint.pt")]) == 0
    stats = json.loads((out / "stats.json").read_text())
    assert [f["index"] for f in stats["frames"]] == [0, 10, 20, 30, 40, 50, 60, 70]  # 0-50: the checkpoint's stats
    assert stats["frames"][6]["n_keyframes"] > 1


def test_refinement_runs_after_the_last_frame_and_is_timed_apart(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "refined"
    args = ["map", "--frames", "6", "--stride", "10", "--out", str(out), "-q", *TINY]
    assert main([*args, "--set", "mapping.optimization.refine_iters=20"]) == 0
    stats = json.loads((out / "stats.json").read_text())
    plain = json.loads((run_dir / "stats.json").read_text())
    assert stats["summary"]["refine_s"] > 0 and plain["summary"]["refine_s"] == 0
    assert [f["iterations"] for f in stats["frames"]] == [f["iterations"] for f in plain["frames"]]
    refined = json.loads((out / "metrics.json").read_text())["interpolate"]
    before = json.loads((run_dir / "metrics.json").read_text())["interpolate"]
    # with fine priors the geometry is fused and colour comes from the colour prior: refinement trains only the
    # residual where the fine lattice is missing, so it must not cost quality (tests/mapping/test_mapper.py checks
    # that it improves a map whose residual carries the geometry)
    assert refined["psnr_db"] > before["psnr_db"] - 0.3


def test_run_summary_without_frames_gives_no_times_and_names_the_refinement(tmp_path: Path) -> None:
    from h2viz.pipeline import RunResult

    text = RunResult(tmp_path, [], refine_s=12.3).summary()
    assert text.splitlines()[0] == "mapped 0 frames (0 skipped, 0 dropped)"
    assert "refined the map for 12.3 s" in text


def test_realtime_integrates_every_frame_and_reports_the_counts(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "realtime"
    settle = ["--set", "anytime.plateau_window=5", "--set", "anytime.sharpen_max_s=20"]
    assert main(["map", "--realtime", "--frames", "30", "--out", str(out), "-q", *TINY, *settle]) == 0
    stats = json.loads((out / "stats.json").read_text())
    mapped = [f["index"] for f in stats["frames"]]
    realtime = stats["realtime"]
    assert mapped == sorted(set(mapped)) and mapped[-1] == 29  # in order, and the newest frame is never lost
    assert realtime["integrated"] == len(mapped) and realtime["arrived"] == 30
    assert len(mapped) + realtime["dropped"] == 30 and stats["summary"]["dropped_frames"] == realtime["dropped"]
    assert realtime["overflowed"] == 0  # 96x72 frames integrate in a few ms: integration never fell behind...
    assert realtime["passed_over"] == realtime["dropped"] < 15  # ...but rendering the scene may (counted)
    assert realtime["stream_steps"] > 0 and realtime["sharpen_steps"] > 0 and realtime["phase"] == "settled"
    assert sum(f["iterations"] for f in stats["frames"]) == realtime["stream_steps"]
    assert 0 <= realtime["thinned"] <= realtime["integrated"]  # fused into their new voxels only (frames waited)
    text = capsys.readouterr().out
    assert f"integrated {len(mapped)} of 30 frames" in text and "after it" in text
    assert f"{realtime['thinned']} fused into their new voxels' fine lattices only" in text


def test_eval_prints_a_table_and_writes_metrics(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    plane = trimesh.creation.box(extents=[0.5, 0.5, 0.001]).subdivide().subdivide().subdivide()
    shifted = plane.copy()
    shifted.apply_translation([0, 0, 0.01])
    plane.export(tmp_path / "gt.ply")
    shifted.export(tmp_path / "rec.ply")
    assert (
        main(
            [
                "eval",
                "--mesh",
                str(tmp_path / "rec.ply"),
                "--gt",
                str(tmp_path / "gt.ply"),
                "--points",
                "20000",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "acc_cm" in out and "comp_ratio" in out
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["acc_cm"] == pytest.approx(1.0, abs=0.15) and m["comp_ratio"] > 99


def test_unrecognised_folder_lists_what_was_looked_for(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "notes.txt").write_text("nothing here")
    assert main(["map", "--data", str(tmp_path), "-q"]) == 2
    err = capsys.readouterr().err
    assert "could not recognise" in err and "rgb.txt" in err and "traj.txt" in err


def test_unknown_config_key_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("mapping:\n  max_iter: 3\n")
    assert main(["map", "--config", str(bad), "-q"]) == 2
    err = capsys.readouterr().err
    assert "max_iter" in err and "max_iters" in err and str(bad) in err


def test_config_docs_lists_every_field(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["config", "--docs"]) == 0
    out = capsys.readouterr().out
    assert "mapping.representation.voxel_size_m = 0.1" in out and "Edge of an octree leaf voxel." in out
    assert "# mapping.sampling: Training rays and samples." in out  # each group says what it holds
