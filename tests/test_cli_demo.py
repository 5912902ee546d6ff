"""`h2viz map --record`, `h2viz export-html` and `h2viz render-path` end to end on the synthetic scene, and their
clear errors on bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from h2viz.cli import main
from h2viz.viewer.camera_path import trajectory_path
from h2viz.viewer.recording import Recording
from h2viz.viewer.video import read_video
from tests.test_cli import TINY

N_FRAMES = 4


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("run")
    assert main(["map", "--frames", str(N_FRAMES), "--stride", "10", "--out", str(out), "-q", "--record", *TINY]) == 0
    return out


def test_map_record_writes_a_step_per_frame(run_dir: Path) -> None:
    rec = Recording(run_dir)
    assert len(rec) == N_FRAMES and rec.meta["complete"]
    snaps = [rec.snapshot(k) for k in range(N_FRAMES)]
    assert [s.frames_done for s in snaps] == list(range(1, N_FRAMES + 1))
    assert [s.current_frame.index for s in snaps if s.current_frame is not None] == [0, 10, 20, 30]
    assert snaps[-1].finished and not snaps[0].finished
    faces = [sum(len(c.faces) for c in s.chunks.values()) for s in snaps]
    assert faces[0] > 0 and faces[-1] > faces[0]  # the mesh grows with the map
    assert len(snaps[-1].keyframes) >= 2 and len(snaps[-1].voxel_coords) > len(snaps[0].voxel_coords)
    stats = json.loads((run_dir / "stats.json").read_text())
    assert [s.index for s in snaps[-1].stats] == [f["index"] for f in stats["frames"]]


def test_export_html_and_viser_file(run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export-html", str(run_dir)]) == 0
    html = run_dir / "recording.html"
    assert "wrote" in capsys.readouterr().out
    text = html.read_text()
    assert text.startswith("<!") and "__VISER_EMBED_DATA__" in text and "<script" in text
    assert main(["export-html", str(run_dir), "--out", str(tmp_path / "run.viser"), "--fps", "2"]) == 0
    data = (tmp_path / "run.viser").read_bytes()
    assert int.from_bytes(data[:8], "little") > len(data)  # the uncompressed size, then zstd data


def test_render_path_writes_the_requested_video(run_dir: Path, tmp_path: Path) -> None:
    last = Recording(run_dir).snapshot(N_FRAMES - 1)
    assert last.current_frame is not None
    path = trajectory_path(last.trajectory, last.current_frame.K, last.current_frame.height)
    path.fps, path.duration_s = 10, 0.5
    path_file = path.save(tmp_path / "path.json")
    out = tmp_path / "fly.mp4"
    args = ["render-path", str(run_dir), str(path_file), "--out", str(out), "--width", "64", "--height", "48", "-q"]
    assert main(args) == 0
    frames = read_video(out)
    assert len(frames) == 5 and frames[0].shape == (48, 64, 3)
    assert np.mean(frames[0]) > 10  # the room


def test_bad_input_names_the_file(run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export-html", str(tmp_path)]) == 2
    assert "no recording in" in capsys.readouterr().err
    bad = tmp_path / "path.json"
    bad.write_text('{"keyframes": [{"wxyz": [1, 0, 0, 0]}]}')
    assert main(["render-path", str(run_dir), str(bad)]) == 2
    assert "path.json: not a camera path" in capsys.readouterr().err
    assert main(["render-path", str(tmp_path), str(bad)]) == 2
    assert "checkpoint.pt not found" in capsys.readouterr().err
    assert main(["replay", str(tmp_path), "--port", "0"]) == 2
    assert "no recording in" in capsys.readouterr().err
