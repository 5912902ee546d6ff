"""`h2viz map` keeps its work: autosaves on schedule (real-time runs too, and at the end of their stream), resumes a
run folder from its newest checkpoint with the stats appended, and ends a stream cleanly (map kept, saved, message
given) when the source fails mid-stream, the mapper fails, or the output disk is full."""

from __future__ import annotations

import errno
import json
import os
import threading
from collections.abc import Callable
from pathlib import Path

import pytest

from h2viz.cli import main
from h2viz.config import AutosaveConfig
from h2viz.errors import CheckpointError
from h2viz.mapping import checkpoint_format
from h2viz.mapping.autosave import AUTOSAVE_NAME, Autosaver, find_checkpoint
from h2viz.mapping.checkpoint import load_checkpoint
from h2viz.mapping.mapper import Mapper
from h2viz.sources.synthetic import SyntheticSource
from tests.test_cli import TINY

FAST = [*TINY, "--set", "eval.n_points=2000", "--set", "mapping.optimization.max_iters=2", "-q"]


def map_args(out: Path, frames: int, every: int = 2) -> list[str]:
    return [
        "map",
        "--frames",
        str(frames),
        "--stride",
        "10",
        "--out",
        str(out),
        "--set",
        f"autosave.every_frames={every}",
        *FAST,
    ]


def stats_of(out: Path) -> dict:
    return json.loads((out / "stats.json").read_text())


def test_autosave_is_due_every_n_frames_or_m_seconds() -> None:
    now = [0.0]
    saver = Autosaver(Path("/nonexistent"), AutosaveConfig(every_frames=3, every_s=10.0), 5, clock=lambda: now[0])
    assert not saver.due(5) and not saver.due(7) and saver.due(8)  # counted from the 5 frames mapped before
    saver._last_frames = 8
    now[0] = 9.9
    assert not saver.due(9)
    now[0] = 10.0
    assert saver.due(9) and not saver.due(8)  # time alone, but only after a new frame
    assert not Autosaver(Path("."), AutosaveConfig(0, 0.0)).enabled


def test_while_a_stream_plays_autosaves_come_by_time_and_are_written_in_the_background(tmp_path: Path) -> None:
    now, release, written, threads = [0.0], threading.Event(), [], []

    def prepare(mapper: object, extra: dict) -> Callable[[Path], None]:
        taken = dict(extra)  # the state is taken on the calling thread

        def write(path: Path) -> None:
            threads.append(threading.current_thread())
            assert release.wait(5.0)
            if taken.get("fail"):
                raise OSError(28, "No space left on device")
            written.append(taken["frames"])

        return write

    cfg = AutosaveConfig(every_frames=2, every_s=10.0)
    saver = Autosaver(tmp_path, cfg, clock=lambda: now[0], prepare=prepare)
    assert not saver.due(5, streaming=True) and saver.due(5)  # frames alone do not make it due while streaming
    now[0] = 10.0
    assert saver.maybe_save(None, 5, lambda: {"frames": 5}, streaming=True) is None  # returns at once...
    assert saver.writing and written == []  # ...while its write waits on another thread
    now[0] = 30.0
    assert saver.maybe_save(None, 9, lambda: {"frames": 9}, streaming=True) is None and saver.writing
    release.set()
    assert saver.wait() is None and written == [5] and threads[0] is not threading.current_thread()  # one at a time
    assert saver.maybe_save(None, 9, lambda: {"frames": 9, "fail": True}, streaming=True) is None
    saver._thread.join()  # type: ignore[union-attr]
    failed = saver.maybe_save(None, 9, lambda: {"frames": 9}, streaming=True)  # the failure is reported next time
    assert failed is not None and "No space left on device" in failed and "previous autosave is kept" in failed
    now[0] = 40.0
    assert saver.maybe_save(None, 10, lambda: {"frames": 10}, streaming=True) is None  # and saving goes on
    assert saver.wait() is None and written == [5, 10] and saver.saves == 2


def test_a_run_folder_resumes_from_its_newest_checkpoint(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="holds no checkpoint"):
        find_checkpoint(tmp_path)
    for age, name in enumerate(["checkpoint_1.pt", "autosave.pt", "checkpoint.pt"]):
        (tmp_path / name).write_bytes(b"x")
        os.utime(tmp_path / name, (1000 + age, 1000 + (2 - age if name != "autosave.pt" else 5)))
    assert find_checkpoint(tmp_path).name == "autosave.pt"
    assert find_checkpoint(tmp_path / "checkpoint.pt").name == "checkpoint.pt"
    with pytest.raises(CheckpointError, match="does not exist"):
        find_checkpoint(tmp_path / "missing")


def test_a_source_failing_mid_stream_keeps_the_map_and_resume_appends_to_its_stats(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    render = SyntheticSource.load

    def failing(self: SyntheticSource, position: int, key: object) -> object:
        if key == 50:
            raise OSError(errno.EIO, "Input/output error", "frame_000050.png")  # as a file deleted under the reader
        return render(self, position, key)

    monkeypatch.setattr(SyntheticSource, "load", failing)
    out = tmp_path / "run"
    assert main(map_args(out, 8)) == 0
    stats = stats_of(out)
    assert [f["index"] for f in stats["frames"]] == [0, 10, 20, 30, 40]
    assert (
        "the source failed after frame 40 (OSError" in stats["errors"][0] and "frame_000050.png" in stats["errors"][0]
    )
    mapper, extra = load_checkpoint(out / "checkpoint.pt")
    assert extra["last_index"] == 40 and mapper.frames_done == 5 and (out / "mesh.ply").is_file()
    _, auto = load_checkpoint(out / "autosave.pt")
    assert auto["last_index"] == 30  # autosaved after every two frames: 10, 30
    monkeypatch.setattr(SyntheticSource, "load", render)
    assert main(["map", "--resume", str(out), "--frames", "8", "--stride", "10", *FAST]) == 0  # outputs in place
    stats = stats_of(out)
    assert [f["index"] for f in stats["frames"]] == [0, 10, 20, 30, 40, 50, 60, 70] and stats["errors"] == []
    assert load_checkpoint(out / "checkpoint.pt")[0].frames_done == 8


def test_a_failing_frame_is_skipped_with_a_message_and_repeated_failures_stop_the_run_with_the_map_saved(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    integrate = Mapper.integrate

    def flaky(self: Mapper, frame: object) -> object:
        if frame.index in (20, 40, 50, 60):  # type: ignore[attr-defined]
            raise RuntimeError("injected failure")
        return integrate(self, frame)  # type: ignore[arg-type]

    monkeypatch.setattr(Mapper, "integrate", flaky)
    out = tmp_path / "run"
    assert main(map_args(out, 8)) == 0
    stats = stats_of(out)
    assert [f["index"] for f in stats["frames"]] == [0, 10, 30]
    assert stats["errors"][0] == "mapping frame 20 failed (RuntimeError: injected failure); the frame was skipped"
    assert stats["errors"][-1] == "stopped after 3 failed frames in a row; the map so far is saved"
    assert load_checkpoint(out / "checkpoint.pt")[1]["last_index"] == 30


def test_a_full_disk_keeps_mapping_and_the_previous_autosave(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    write = checkpoint_format.write
    calls = [0]

    def filling(state: dict, path: Path) -> None:
        calls[0] += 1
        if calls[0] > 1:  # the first autosave fits, then the disk is full
            raise CheckpointError(f"cannot write checkpoint {path}: {os.strerror(errno.ENOSPC)}")
        write(state, path)

    monkeypatch.setattr(checkpoint_format, "write", filling)
    out = tmp_path / "run"
    assert main(map_args(out, 6)) == 0
    stats = stats_of(out)
    assert [f["index"] for f in stats["frames"]] == [0, 10, 20, 30, 40, 50]  # mapping went on
    assert any("autosave failed" in e and "No space left on device" in e for e in stats["errors"])
    assert any("checkpoint.pt" in e and "the last autosave" in e for e in stats["errors"])
    assert not (out / "checkpoint.pt").exists() and not list(out.glob("*.tmp"))
    assert load_checkpoint(out / "autosave.pt")[1]["last_index"] == 10


def test_h2viz_map_writes_its_autosaves_in_the_background_at_the_frames_they_are_due(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    write, writes = checkpoint_format.write, []

    def noting(state: dict, path: Path) -> None:
        writes.append((state["frames_done"], state["extra"]["last_index"], threading.current_thread().name, path.name))
        write(state, path)

    monkeypatch.setattr(checkpoint_format, "write", noting)
    out = tmp_path / "run"
    assert main(map_args(out, 6)) == 0
    autosaves = [(n, last, thread) for n, last, thread, name in writes if name == AUTOSAVE_NAME]
    assert [(n, last) for n, last, _ in autosaves] == [(2, 10), (4, 30), (6, 50)]  # every 2 frames, none skipped
    assert {thread for _, _, thread in autosaves} == {"h2viz-autosave"}  # off the mapping thread
    assert writes[-1][3] == "checkpoint.pt" and not stats_of(out)["errors"]  # after the last autosave
    assert load_checkpoint(out / AUTOSAVE_NAME)[1]["last_index"] == 50


def test_a_realtime_run_autosaves_and_resuming_it_goes_on_after_its_last_integrated_frame(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    write, writes = checkpoint_format.write, []

    def noting(state: dict, path: Path) -> None:
        writes.append((path.name, state["frames_done"], state["extra"]["last_index"]))
        write(state, path)

    monkeypatch.setattr(checkpoint_format, "write", noting)
    out = tmp_path / "run"
    realtime = ["--realtime", "--set", "anytime.sharpen_max_s=0"]
    every_frame = ["--set", "autosave.every_s=1e-6"]  # due after every frame: by time (frames do not count)
    assert main([*map_args(out, 6), *realtime, *every_frame]) == 0
    mapped = [f["index"] for f in stats_of(out)["frames"]]
    n = len(mapped)
    assert n == stats_of(out)["realtime"]["integrated"] >= 4  # a frame the reader was late for may be passed over
    autosaves = [(frames, last) for name, frames, last in writes if name == AUTOSAVE_NAME]
    assert autosaves[0][0] == 1 and autosaves[-1] == (n, mapped[-1])  # from the first frame, and at the end
    assert all(a[0] < b[0] for a, b in zip(autosaves, autosaves[1:], strict=False))  # one at a time
    assert all(last == mapped[frames - 1] for frames, last in autosaves)  # each of one moment
    mapper, extra = load_checkpoint(out / AUTOSAVE_NAME)
    assert mapper.frames_done == n and [s["index"] for s in extra["stats"]] == mapped

    (out / "checkpoint.pt").unlink()  # as after a crash: the autosave is the newest checkpoint
    assert main(["map", "--resume", str(out), "--frames", "8", "--stride", "10", *realtime, *FAST]) == 0
    resumed = [f["index"] for f in stats_of(out)["frames"]]
    assert resumed[:n] == mapped and resumed[n:] and set(resumed[n:]) <= {60, 70}  # only frames after the last
    assert stats_of(out)["realtime"]["integrated"] == len(resumed) - n
    assert load_checkpoint(out / AUTOSAVE_NAME)[1]["last_index"] == resumed[-1]


def test_ctrl_c_during_a_realtime_run_keeps_and_saves_the_map(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    add_frame = Mapper.add_frame

    def interrupted(self: Mapper, frame: object, *args: object) -> object:
        if frame.index == 30:  # type: ignore[attr-defined]
            raise KeyboardInterrupt
        return add_frame(self, frame, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(Mapper, "add_frame", interrupted)
    out = tmp_path / "run"
    assert main([*map_args(out, 6, every=50), "--realtime"]) == 0
    stats = stats_of(out)
    mapped = [f["index"] for f in stats["frames"]]
    assert (
        mapped
        and max(mapped) < 30
        and stats["errors"] == [f"interrupted after frame {mapped[-1]}; the map so far is saved"]
    )
    assert load_checkpoint(out / AUTOSAVE_NAME)[1]["last_index"] == mapped[-1]  # saved when the stream ended
    assert load_checkpoint(out / "checkpoint.pt")[0].frames_done == len(mapped)
