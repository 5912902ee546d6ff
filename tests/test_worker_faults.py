"""The dashboard's worker keeps its work: it autosaves on schedule (in real-time mode too, and when the stream ends),
autosaves before reporting a failed frame or a failed mesh update with a message that says what happened and what
goes on, resumes a run folder after its last frame, and never overwrites an earlier run's autosave."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import pytest

from h2viz.config import Config
from h2viz.errors import H2vizError
from h2viz.mapping import checkpoint_format
from h2viz.mapping.autosave import AUTOSAVE_NAME
from h2viz.mapping.checkpoint import load_checkpoint
from h2viz.mapping.meshing.job import MeshJob
from h2viz.viewer import server
from h2viz.worker import END, FrameFeed, MappingWorker, WorkerSettings
from tests.viewer.fakes import BoxRoomSource, intrinsics, recording_mapper, room_pose, tiny_mapping_config


def config(folder: Path, every: int = 2) -> Config:
    cfg = Config()
    cfg.mapping = tiny_mapping_config()
    cfg.out_dir = str(folder)
    cfg.autosave.every_frames, cfg.autosave.every_s = every, 0.0
    return cfg


def run(worker: MappingWorker, timeout_s: float = 120.0) -> MappingWorker:
    worker.start()
    try:
        assert worker.wait_finished(timeout_s)
    finally:
        worker.stop()
    return worker


def test_the_worker_autosaves_before_reporting_a_failed_frame_and_maps_the_rest(tmp_path: Path) -> None:
    cfg = config(tmp_path, every=5)
    mapper = recording_mapper(cfg.mapping)
    integrate = mapper.integrate

    def failing(frame: Any) -> Any:
        if frame.index == 2:
            raise RuntimeError("injected mapper failure")
        return integrate(frame)

    mapper.integrate = failing  # type: ignore[method-assign]
    worker = run(MappingWorker(BoxRoomSource(n=7), mapper, cfg, autosave_dir=tmp_path))
    assert len(worker.errors) == 1
    message = worker.errors[0]
    assert message.startswith("frame 2 (") and "RuntimeError: injected mapper failure; the frame was skipped" in message
    assert f"the map so far is saved in {tmp_path / AUTOSAVE_NAME}; mapping goes on" in message
    snap = worker.slot.get()[1]
    assert snap.frames_done == 6 and snap.skipped == 1  # the rest was mapped
    again, extra = load_checkpoint(tmp_path / AUTOSAVE_NAME)
    assert extra["last_index"] == 1 and again.frames_done == 2  # saved at the failure (the next one is due at 7)
    assert [s["index"] for s in extra["stats"]] == [0, 1]


def test_a_failed_mesh_update_is_reported_after_an_autosave_and_mapping_goes_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = config(tmp_path, every=0)
    original, failed = MeshJob.run, []

    def broken(self: MeshJob, *args: Any, **kwargs: Any) -> Any:
        if not failed:
            failed.append(time.monotonic())
            raise MemoryError("injected mesh failure")
        return original(self, *args, **kwargs)

    monkeypatch.setattr(MeshJob, "run", broken)
    worker = run(MappingWorker(BoxRoomSource(n=4), recording_mapper(cfg.mapping), cfg, autosave_dir=tmp_path))
    notice = [e for e in worker.errors if e.startswith("the live mesh could not be updated; the map so far is saved")]
    assert len(notice) == 1 and notice[0].endswith("mapping goes on and the next update retries")
    assert any("mesh extraction failed: MemoryError: injected mesh failure" in e for e in worker.errors)
    snap = worker.slot.get()[1]
    assert snap.frames_done == 4 and sum(len(c.faces) for c in snap.chunks.values()) > 0  # meshed after all
    assert load_checkpoint(tmp_path / AUTOSAVE_NAME)[0].frames_done >= 1


def test_the_dashboard_resumes_a_run_folder_after_its_last_frame_and_keeps_earlier_autosaves(tmp_path: Path) -> None:
    cfg = config(tmp_path, every=3)
    source = BoxRoomSource(n=8)
    first = MappingWorker(BoxRoomSource(n=4), recording_mapper(cfg.mapping), cfg, autosave_dir=tmp_path)
    run(first)
    assert load_checkpoint(tmp_path / AUTOSAVE_NAME)[1]["last_index"] == 2  # after frames 0-2

    resumed = run(server.build_worker(cfg, resume=tmp_path, source=source))
    fresh = server.build_worker(cfg, source=BoxRoomSource(n=2))
    assert resumed.notices == [
        f"Resumed from {tmp_path / AUTOSAVE_NAME}: 3 frames were mapped; mapping goes on after frame 2."
    ]
    snap = resumed.slot.get()[1]
    assert [s.index for s in snap.stats] == list(range(8)) and snap.frames_done == 8 and not resumed.errors
    kept = sorted(tmp_path.glob("autosave_*.pt"))
    assert len(kept) == 1 and not (tmp_path / AUTOSAVE_NAME).exists()  # renamed before the fresh run writes one
    assert fresh.resume_offer is not None and fresh.resume_offer.path == kept[0]  # the dashboard offers to resume it
    assert fresh.notices == [
        f"An earlier run's autosave is kept as {kept[0]}; this run never overwrites it.",
        f"The run folder holds an earlier run's checkpoint, {kept[0]} (6 frames). This run starts fresh; press "
        '"Resume earlier run" in the Mapping tab to continue that one instead.',
    ]
    assert load_checkpoint(kept[0])[1]["last_index"] == 5  # the resumed run's last autosave, after frames 3-5


def test_a_failed_render_or_export_is_reported_after_an_autosave_and_mapping_goes_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from h2viz.worker import requests

    cfg = config(tmp_path, every=0)
    mapper = recording_mapper(cfg.mapping)
    worker = MappingWorker(BoxRoomSource(n=4), mapper, cfg, autosave_dir=tmp_path)
    worker.start()
    try:
        assert worker.wait_finished(120)

        def broken_render(*args: Any, **kwargs: Any) -> Any:
            raise RuntimeError("injected render failure")

        monkeypatch.setattr(mapper, "render", broken_render)
        K, T = intrinsics(64, 48), room_pose(2, 5)
        with pytest.raises(RuntimeError, match="injected render failure"):
            worker.submit("render", K=K, T_world_camera=T, height=48, width=64, mode="rgb").result(30)
        monkeypatch.setattr(requests, "export_mesh_bytes", lambda *a: (_ for _ in ()).throw(OSError(28, "No space")))
        with pytest.raises(OSError, match="No space"):
            worker.submit("export", format="ply").result(30)
        with pytest.raises(H2vizError, match="unknown mode"):  # a bad request is the asker's error only
            worker.submit("render", K=K, T_world_camera=T, height=48, width=64, mode="bogus").result(30)
        assert worker.alive and worker.submit("pause").result(10)  # still serving
    finally:
        worker.stop()
    assert worker.errors[0].startswith(
        f"a view render failed (RuntimeError: injected render failure); the map so far is saved in {tmp_path}"
    )
    assert worker.errors[0].endswith("mapping goes on; try it again, or with a smaller image or another format")
    assert worker.errors[1].startswith("a mesh export failed (OSError: [Errno 28] No space); mapping goes on")
    assert len(worker.errors) == 2  # autosaved once: the export came within a minute of the render
    assert load_checkpoint(tmp_path / AUTOSAVE_NAME)[0].frames_done == 4


def test_the_dashboard_writes_its_autosaves_in_the_background_at_the_frames_they_are_due(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    write, writes = checkpoint_format.write, []

    def noting(state: dict, path: Path) -> None:
        writes.append((state["frames_done"], state["extra"]["last_index"], threading.current_thread().name))
        write(state, path)

    monkeypatch.setattr(checkpoint_format, "write", noting)
    cfg = config(tmp_path, every=2)
    worker = run(MappingWorker(BoxRoomSource(n=5), recording_mapper(cfg.mapping), cfg, autosave_dir=tmp_path))
    mapped = [s.index for s in worker.slot.get()[1].stats]
    assert [(n, last) for n, last, _ in writes] == [(2, mapped[1]), (4, mapped[3])]  # every 2 frames, none skipped
    assert {name for _, _, name in writes} == {"h2viz-autosave"} and not worker.errors  # off the mapping thread
    assert load_checkpoint(tmp_path / AUTOSAVE_NAME)[0].frames_done == 4  # written before the worker stopped


def test_the_worker_autosaves_a_realtime_run_and_resumes_it_after_its_last_integrated_frame(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    write, autosaves = checkpoint_format.write, []

    def noting(state: dict, path: Path) -> None:
        autosaves.append((state["frames_done"], state["extra"]["last_index"]))
        write(state, path)

    monkeypatch.setattr(checkpoint_format, "write", noting)
    cfg = config(tmp_path, every=2)
    cfg.autosave.every_s = 1e-6  # due after every frame: while the stream plays, by time alone
    cfg.source.realtime, cfg.anytime.sharpen_max_s = True, 0.0
    first = run(MappingWorker(BoxRoomSource(n=5), recording_mapper(cfg.mapping), cfg, autosave_dir=tmp_path))
    mapped = [s.index for s in first.slot.get()[1].stats]
    n = len(mapped)
    assert n >= 3 and autosaves[0] == (1, mapped[0]) and autosaves[-1] == (n, mapped[-1])  # and at the end
    assert all(a[0] < b[0] for a, b in zip(autosaves, autosaves[1:], strict=False))  # in the background, one at a time
    assert all(last == mapped[frames - 1] for frames, last in autosaves)  # each of one moment
    assert load_checkpoint(tmp_path / AUTOSAVE_NAME)[0].frames_done == n  # the stream's end was autosaved

    resumed = run(server.build_worker(cfg, resume=tmp_path, source=BoxRoomSource(n=8)))
    indices = [s.index for s in resumed.slot.get()[1].stats]
    assert indices[:n] == mapped and indices[n:] and min(indices[n:]) > mapped[-1] and not resumed.errors


def test_a_feed_passes_over_the_frames_a_resumed_run_mapped_without_reading_them() -> None:
    class Counting(BoxRoomSource):
        loaded: list[int] = []

        def load(self, position: int, key: Any) -> Any:
            self.loaded.append(position)
            return super().load(position, key)

    source = Counting(n=9)
    feed = FrameFeed(source, WorkerSettings(stride=2), 0, start_after=4)
    assert feed.total() == 5 and feed.read == 3  # 0, 2, 4 passed over, 6 and 8 to come
    feed.start()
    frames = [feed.take(10.0) for _ in range(3)]
    feed.stop()
    assert [f.index for f in frames[:2]] == [6, 8] and frames[2] is END and source.loaded == [6, 8]


def test_in_real_time_a_feed_prepares_each_frame_on_its_reader_thread_before_queueing_it() -> None:
    prepared: list[tuple[int, str]] = []

    def prepare(frame: Any) -> None:
        prepared.append((frame.index, threading.current_thread().name))
        if frame.index == 2:
            raise ValueError("a frame its preparation fails on")  # delivered anyway: integrating it reports it

    feed = FrameFeed(BoxRoomSource(n=4), WorkerSettings(realtime=True), 0, prepare=prepare)
    feed.start()
    taken = [feed.take(10.0) for _ in range(5)]
    feed.stop()
    assert [f.index for f in taken[:4]] == [0, 1, 2, 3] and taken[4] is END
    assert [i for i, _ in prepared] == [0, 1, 2, 3] and {name for _, name in prepared} == {"h2viz-frames"}
    every_frame = FrameFeed(BoxRoomSource(n=2), WorkerSettings(), 0, prepare=prepare)  # mapped as it comes
    every_frame.start()
    assert [every_frame.take(10.0).index for _ in range(2)] == [0, 1]
    every_frame.stop()
    assert len(prepared) == 4
