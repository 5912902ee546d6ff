"""bench/realtime.py end to end on a tiny synthetic room: every played frame integrated in real time, the anytime
rows scored at the end of the stream and after more optimisation (which improves held-out depth), every-frame mode
beside it, and no held-out frame played."""

from __future__ import annotations

import pytest

from bench import realtime

TINY = ["source.synthetic.width=96", "source.synthetic.height=72", "mapping.representation.min_points_per_voxel=1"]
TINY += ["mapping.representation.hash_log2_size=15", "mapping.sampling.rays_per_iter=1024", "eval.n_points=20000"]


def test_the_anytime_rows_integrate_every_frame_and_sharpen_after_the_stream(capsys: pytest.CaptureFixture) -> None:
    args = ["--datasets", "synthetic", "--frames", "40", "--after", "3", "--methods", "anytime,every-frame"]
    for item in TINY:
        args += ["--set", item]
    assert realtime.main(args) == 0
    out = capsys.readouterr().out
    rows = [[c.strip() for c in line.split("|")[1:-1]] for line in out.splitlines() if line.startswith("| synth")]
    by = {(r[1], r[2].split(" (")[0]): r for r in rows}
    assert set(by) == {("anytime", "end of stream"), ("anytime", "+3 s"), ("every-frame", "after the last frame")}
    for row in rows:
        assert row[3] == "36 / 36"  # 4 of 40 frames held out; reading from memory drops none
    end, after = by["anytime", "end of stream"], by["anytime", "+3 s"]
    assert int(after[5]) > int(end[5]) > 0  # steps between frames, then more after the stream
    # sharpening keeps the held-out depth (the fine priors set it: it moves by a hundredth of a cm at most here)
    assert float(after[10]) <= float(end[10]) + 0.02
    assert 80.0 < float(after[8]) <= 100.0  # comp ratio against the room's exact mesh
    assert "command: .venv/bin/python bench/realtime.py" in out


def test_replay_source_plays_frames_as_given() -> None:
    from h2viz.config import SourceConfig
    from h2viz.sources.base import make_source

    frames = list(make_source(SourceConfig(format="synthetic", max_frames=3)))
    source = realtime.ReplaySource(frames)
    assert len(source) == 3 and [source.timestamp(i, i) for i in range(3)] == [f.timestamp for f in frames]
    assert source.get(1, 1) is frames[1]  # no second post-processing
