"""MappingWorker: the mapping thread's frame order, real-time dropping, commands, render bands,
exports, failures and shutdown, against the analytic room and a stand-in mapper; then the real
Mapper (tiny configuration) on the room and on real 7-Scenes frames."""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from h2viz.config import Config
from h2viz.errors import ConfigError, H2vizError
from h2viz.sources.base import make_source
from h2viz.types import KeyframeState, RgbdFrame
from h2viz.worker import LatestSlot, MappingWorker, RenderedView, WorkerSettings
from h2viz.worker.feed import FrameFeed
from h2viz.worker.mesh_thread import MeshThread
from h2viz.worker.requests import scaled_intrinsics
from tests.viewer.fakes import (
    BoxRoomSource,
    FakeMapper,
    intrinsics,
    recording_mapper,
    room_pose,
    tiny_mapping_config,
    trace_room,
)

Factory = Callable[..., MappingWorker]


@pytest.fixture
def make_worker() -> Iterator[Factory]:
    workers: list[MappingWorker] = []

    def make(
        source: object, mapper: object, paused: bool = False, cfg: Config | None = None, **settings: object
    ) -> MappingWorker:
        cfg = cfg or Config()
        cfg.viewer.start_paused = paused
        worker = MappingWorker(source, mapper, cfg, WorkerSettings(**settings))  # type: ignore[arg-type]
        workers.append(worker.start())
        return worker

    yield make
    for w in workers:
        w.stop()


def wait_for(worker: MappingWorker, predicate: Callable[..., bool], timeout_s: float = 10.0):  # noqa: ANN201
    deadline, version = time.monotonic() + timeout_s, 0
    while time.monotonic() < deadline:
        version, snap = worker.slot.wait_newer(version, 0.1)
        if snap is not None and predicate(snap):
            return snap
    raise AssertionError("the worker never reached the expected state")


def test_latest_slot_keeps_the_newest_value() -> None:
    slot: LatestSlot[int] = LatestSlot()
    assert slot.get() == (0, None)
    slot.put(1)
    assert slot.put(2) == 2 and slot.get() == (2, 2)
    assert slot.wait_newer(2, 0.05) == (2, 2)  # times out, returns the current pair
    assert slot.wait_until(lambda v: v == 2, 0.0) and not slot.wait_until(lambda v: v > 2, 0.05)
    threading.Timer(0.05, slot.put, args=(3,)).start()
    assert slot.wait_until(lambda v: v > 2, 10.0)


def test_every_frame_mode_maps_all_frames_in_order(make_worker: Factory) -> None:
    source, mapper = BoxRoomSource(n=9), FakeMapper()
    worker = make_worker(source, mapper)
    assert worker.wait_finished(10)
    snap = worker.slot.get()[1]
    assert [s.index for s in snap.stats] == list(range(9))
    assert snap.frames_done == snap.frames_total == 9 and snap.finished and snap.dropped == 0
    np.testing.assert_allclose(snap.trajectory, [room_pose(i, 9) for i in range(9)])
    assert snap.current_frame is not None and snap.current_frame.index == 8
    assert len(snap.voxel_coords) == len(mapper.voxel_coords()) > 0
    assert set(snap.chunks) == set(mapper.mesh_chunks()) and snap.chunks  # final re-mesh included
    assert snap.metrics["comp_ratio"] > 0  # the room has a ground-truth mesh
    assert snap.memory_mb > 0


def test_stride_and_skipped_frames(make_worker: Factory) -> None:
    source = BoxRoomSource(n=10, fail_keys=[4])
    worker = make_worker(source, FakeMapper(), stride=2)
    assert worker.wait_finished(10)
    snap = worker.slot.get()[1]
    assert [s.index for s in snap.stats] == [0, 2, 6, 8] and snap.skipped == 1 and snap.frames_total == 5


def anytime_cfg(**anytime: object) -> Config:
    cfg = Config()
    cfg.anytime = replace(cfg.anytime, **{"plateau_window": 10, **anytime})  # type: ignore[arg-type]
    return cfg


class RoomAt15Hz(BoxRoomSource):
    """Room frames 1/15 s apart: on a busy two-core machine a 30 Hz reader thread now and then passes over a frame
    it was late to read (counted, as the next test's are); here every frame must arrive."""

    def timestamp(self, position: int, key: object) -> float:
        return int(key) / 15.0  # type: ignore[call-overload]


def test_realtime_mode_integrates_every_frame_steps_between_them_and_sharpens_after(make_worker: Factory) -> None:
    source, mapper = RoomAt15Hz(n=40), FakeMapper()
    mapper.add_delay_s, mapper.step_delay_s = 0.005, 0.004
    worker = make_worker(source, mapper, cfg=anytime_cfg(), realtime=True)
    assert worker.wait_finished(20)
    snap = wait_for(worker, lambda s: s.phase == "settled")  # the fake loss is flat from its 100th step
    assert [s.index for s in snap.stats] == list(range(40)) and snap.dropped == 0  # every frame integrated
    adds = [i for i, (kind, _) in enumerate(mapper.events) if kind == "add"]
    assert len(adds) == 40 and mapper.live_steps > 40
    between = [sum(k == "live" for k, _ in mapper.events[a:b]) for a, b in zip(adds, adds[1:], strict=False)]
    # the time between frames went to optimisation, except while catching up after the metrics refresh (at
    # frame 20, ~1 s): the frames that waited meanwhile are integrated back to back, then the steps resume
    assert sum(n >= 1 for n in between) >= 15
    zero_runs = "".join("0" if n == 0 else "s" for n in between).split("s")
    assert max(len(r) for r in zero_runs) <= 20 and sum(between[-3:]) >= 1
    assert all(f == adds_frame for (k, f), adds_frame in _live_frames(mapper.events) if k == "live")
    assert 100 <= mapper.refine_steps <= 200  # sharpened after the stream until the loss was flat
    assert snap.opt_steps == mapper.live_steps + mapper.refine_steps
    assert sum(s.iterations for s in snap.stats) == mapper.live_steps  # steps counted on the frame they served
    time.sleep(0.3)
    assert mapper.refine_steps == snap.opt_steps - mapper.live_steps  # settled: nothing more runs


def test_while_a_realtime_stream_arrives_mesh_jobs_come_at_the_update_rate(make_worker: Factory) -> None:
    """A job per frame at the stream's rate would keep the mesh thread busy on the cores integration needs: while
    frames arrive, jobs are handed over at most mesh_update_hz times a second, and the mesh still follows."""
    source, mapper = RoomAt15Hz(n=45), FakeMapper()
    mapper.add_delay_s, mapper.step_delay_s = 0.005, 0.004
    jobs: list[tuple[float, int]] = []  # (time, frames integrated) of every job frozen
    frozen = mapper.mesh_job

    def timed_job(refresh_s: float = 0.0, whole: bool = False) -> object:
        jobs.append((time.monotonic(), mapper.frames_done))
        return frozen(refresh_s, whole)

    mapper.mesh_job = timed_job  # type: ignore[method-assign]
    worker = make_worker(source, mapper, cfg=anytime_cfg(), realtime=True, mesh_update_hz=2.0)
    assert worker.wait_finished(20)
    streaming = [t for t, done in jobs if 1 <= done < 45]  # after the first frame, before the last
    assert len(streaming) >= 3  # the mesh followed the stream (3 s of it)
    assert all(b - a >= 0.5 - 0.02 for a, b in zip(streaming, streaming[1:], strict=False))  # at most 2 a second
    assert worker.slot.get()[1].dropped == 0


@pytest.mark.parametrize("cap", [3, 0])
def test_while_a_realtime_stream_arrives_the_live_mesh_is_extracted_at_most_at_the_stream_resolution(
    make_worker: Factory, cap: int
) -> None:
    """Mesh jobs while frames arrive mesh at viewer.stream_mesh_resolution (0: no cap); the resolution people chose
    (live_mesh_resolution, the slider) is what settings report and what the mesh returns to after the stream."""
    source, mapper = RoomAt15Hz(n=30), FakeMapper()
    mapper.add_delay_s, mapper.step_delay_s = 0.005, 0.004
    jobs: list[tuple[int, int]] = []  # (frames integrated, resolution meshed at) of every job frozen
    frozen = mapper.mesh_job

    def recorded_job(refresh_s: float = 0.0, whole: bool = False) -> object:
        jobs.append((mapper.frames_done, mapper.meshing_resolution))
        return frozen(refresh_s, whole)

    mapper.mesh_job = recorded_job  # type: ignore[method-assign]
    cfg = anytime_cfg()
    cfg.viewer = replace(cfg.viewer, live_mesh_resolution=4, stream_mesh_resolution=cap)
    worker = make_worker(source, mapper, cfg=cfg, realtime=True, mesh_update_hz=4.0)
    wait_for(worker, lambda s: s.frames_done >= 10)
    chosen = worker.submit("set", mesh_resolution=6).result(5)
    assert chosen["mesh_resolution"] == 6  # as chosen, whatever the stream meshes at
    assert worker.wait_finished(20)
    streaming = [res for done, res in jobs if 1 <= done < 30]
    assert len(streaming) >= 3 and set(streaming) <= ({4, 6} if cap == 0 else {3})
    assert jobs[-1] == (30, 6) and mapper.meshing_resolution == 6  # the chosen resolution after the stream


def test_the_last_frames_of_a_realtime_stream_are_meshed_at_the_stream_resolution_before_the_whole_map(
    make_worker: Factory,
) -> None:
    """Frames integrated since the last live update get their own job at the stream's resolution when the stream
    ends; only then is every chunk re-meshed at the live resolution (a job that takes several times longer)."""
    source, mapper = RoomAt15Hz(n=20), FakeMapper()
    mapper.add_delay_s = 0.005
    jobs: list[tuple[int, int, bool]] = []  # (frames integrated, resolution, whole) of every job frozen
    frozen = mapper.mesh_job

    def recorded_job(refresh_s: float = 0.0, whole: bool = False) -> object:
        jobs.append((mapper.frames_done, mapper.meshing_resolution, whole))
        return frozen(refresh_s, whole)

    mapper.mesh_job = recorded_job  # type: ignore[method-assign]
    cfg = anytime_cfg()
    cfg.viewer = replace(cfg.viewer, live_mesh_resolution=4, stream_mesh_resolution=3)
    worker = make_worker(source, mapper, cfg=cfg, realtime=True, mesh_update_hz=0.5)  # next job due after the end
    assert worker.wait_finished(20)
    ends = [job for job in jobs if job[0] == 20]
    assert ends[:2] == [(20, 3, False), (20, 4, True)]  # the last frames' own job first, then the whole map
    assert all(res == 3 for done, res, _ in jobs if done < 20)


def test_mesh_jobs_leave_their_refresh_passes_out_while_frames_of_a_stream_wait(make_worker: Factory) -> None:
    """Integration is slower than the stream here, so frames wait: the mesh thread's jobs are told to hurry (their
    optional refresh passes would take the cores integration needs); after the stream they are not."""
    source, mapper = RoomAt15Hz(n=24), FakeMapper()
    mapper.add_delay_s = 0.1
    hurried: list[tuple[int, bool]] = []  # (frames integrated when it ran, hurry() then)
    make_job = mapper.mesh_job

    def mesh_job(refresh_s: float = 0.0, whole: bool = False) -> object:
        job = make_job(refresh_s, whole)
        if job is None:
            return job
        inner_run, done = job.run, mapper.frames_done

        def run(stop: object = None, on_pass: object = None, hurry: Callable[[], bool] | None = None) -> None:
            assert hurry is not None
            hurried.append((done, hurry()))
            inner_run(stop, on_pass, hurry)

        job.run = run  # type: ignore[method-assign]
        return job

    mapper.mesh_job = mesh_job  # type: ignore[method-assign]
    worker = make_worker(source, mapper, cfg=anytime_cfg(), realtime=True, mesh_update_hz=4.0)
    assert worker.wait_finished(30)
    snap = worker.slot.get()[1]
    streaming = [h for done, h in hurried if done < snap.frames_done]
    assert any(streaming)
    assert not hurried[-1][1]  # the re-mesh after the stream


def test_a_negative_stream_mesh_resolution_is_refused_before_mapping_starts() -> None:
    cfg = anytime_cfg()
    cfg.viewer = replace(cfg.viewer, stream_mesh_resolution=-1)
    with pytest.raises(ConfigError, match="viewer.stream_mesh_resolution must be >= 0"):
        MappingWorker(BoxRoomSource(n=2), FakeMapper(), cfg, WorkerSettings(realtime=True))  # type: ignore[arg-type]


def test_while_a_realtime_stream_arrives_metrics_are_refreshed_off_the_mapping_thread(make_worker: Factory) -> None:
    """Ground-truth metrics are due every metrics_every frames; the mesh thread computes them with its next publish
    (the mapping thread a 30 Hz stream keeps busy never does), and the snapshots carry them while frames arrive."""
    source, mapper = RoomAt15Hz(n=45), FakeMapper()
    mapper.add_delay_s, mapper.step_delay_s = 0.005, 0.004
    threads: set[str] = set()
    worker = make_worker(source, mapper, cfg=anytime_cfg(), realtime=True, mesh_update_hz=4.0, metrics_every=5)
    refresh = worker._refresh_metrics

    def recorded(voxel_coords: object = None) -> None:
        threads.add(threading.current_thread().name)
        refresh(voxel_coords)  # type: ignore[arg-type]

    worker._refresh_metrics = recorded  # type: ignore[method-assign]
    published_first: list[bool] = []  # at each refresh by the mesh thread: the slot already holds the new chunks

    def recorded_on_mesh_thread(voxel_coords: object = None) -> None:
        if threading.current_thread().name == "h2viz-meshing":
            shown = worker.slot.get()[1].chunks
            published_first.append(
                {k: id(c) for k, c in shown.items()} == {k: id(c) for k, c in mapper.mesh_chunks().items()}
            )
        recorded(voxel_coords)

    worker._refresh_metrics = recorded_on_mesh_thread  # type: ignore[method-assign]
    seen: list[float] = []  # comp ratios of snapshots published while the stream arrived
    deadline = time.monotonic() + 20
    snap = None
    while not (snap is not None and snap.finished) and time.monotonic() < deadline:
        snap = worker.slot.get()[1]
        if snap is not None and snap.metrics and 0 < snap.frames_done < 45:
            seen.append(snap.metrics["comp_ratio"])
        time.sleep(0.02)
    assert worker.wait_finished(20)
    assert seen and all(0 < c <= 100 for c in seen)
    assert "h2viz-meshing" in threads  # refreshed by the mesh thread while streaming ...
    assert published_first and all(published_first)  # ... after publishing the chunks, which never wait for them
    assert worker.slot.get()[1].metrics["comp_ratio"] > 0  # ... and once more at the end


def _live_frames(events: list[tuple[str, int]]) -> Iterator[tuple[tuple[str, int], int]]:
    """Each event with the newest frame integrated before it."""
    newest = -1
    for kind, frame in events:
        if kind == "add":
            newest = frame
        yield (kind, frame), newest


def test_realtime_mode_counts_frames_integration_cannot_keep_up_with(make_worker: Factory) -> None:
    source, mapper = BoxRoomSource(n=40), FakeMapper()
    mapper.add_delay_s = 0.1  # three frame periods per frame
    worker = make_worker(source, mapper, cfg=anytime_cfg(backlog_frames=4), realtime=True)
    behind = wait_for(worker, lambda s: s.phase == "streaming" and s.waiting >= 2, 20)  # what the panel shows
    assert 2 <= behind.waiting <= 4 and behind.lag_s > 0.05  # a full backlog waits; a frame waited > a period
    assert worker.wait_finished(30)
    snap = worker.slot.get()[1]
    mapped = [s.index for s in snap.stats]
    assert snap.dropped > 10 and snap.frames_done + snap.dropped == 40  # every frame integrated or counted
    assert mapped == sorted(mapped) and mapped[-1] == 39
    thinned = [not whole for whole in mapper.fused_all]  # fine lattices of new voxels only while frames wait ...
    runs = "".join("t" if t else "w" for t in thinned).split("w")  # ... every 4th frame fused whole
    assert sum(thinned) >= 5 and max(len(r) for r in runs) <= 3


def test_pausing_stops_the_sharpening_and_resuming_continues_it(make_worker: Factory) -> None:
    source, mapper = BoxRoomSource(n=10), FakeMapper()
    mapper.step_delay_s = 0.01
    worker = make_worker(source, mapper, cfg=anytime_cfg(plateau_window=1000), realtime=True)
    assert worker.wait_finished(20)
    wait_for(worker, lambda s: s.phase == "sharpening" and mapper.refine_steps > 5)
    worker.submit("pause").result(5)
    stopped = mapper.refine_steps
    time.sleep(0.3)
    assert mapper.refine_steps == stopped and worker.slot.get()[1].paused
    worker.submit("resume").result(5)
    wait_for(worker, lambda s: mapper.refine_steps > stopped + 5)


class SlowRoomSource(BoxRoomSource):
    """Room frames at 30 Hz timestamps that take 0.1 s each to read: a stream faster than its reader."""

    def __init__(self, n: int) -> None:
        super().__init__(n=n)
        self.loaded: list[int] = []

    def load(self, position: int, key: object) -> RgbdFrame:
        time.sleep(0.1)
        self.loaded.append(int(key))  # type: ignore[call-overload]
        return super().load(position, key)  # type: ignore[arg-type]


def test_a_realtime_stream_starts_once_the_kernels_are_loaded_and_prepares_frames_as_they_arrive(
    make_worker: Factory,
) -> None:
    source, mapper = BoxRoomSource(n=8), FakeMapper()  # 30 Hz: the stream lasts 0.27 s
    mapper.warm_up_s = 0.6  # longer than the stream: frames read meanwhile would overflow the backlog
    worker = make_worker(source, mapper, cfg=anytime_cfg(backlog_frames=4), realtime=True)
    assert worker.wait_finished(20)
    snap = worker.slot.get()[1]
    assert [s.index for s in snap.stats] == list(range(8)) and snap.dropped == 0
    assert mapper.events[0] == ("warm_up", -1) and [k for k, _ in mapper.events].count("warm_up") == 1
    assert mapper.prepared_ahead == list(range(8))  # each on the reader thread as it arrived
    every_frame = FakeMapper()  # its first frame loads them as well as a warm-up would
    assert make_worker(BoxRoomSource(n=3), every_frame).wait_finished(20)
    assert ("warm_up", -1) not in every_frame.events and not every_frame.prepared_ahead


def test_realtime_mode_passes_over_overdue_frames_without_reading_them(make_worker: Factory) -> None:
    source = SlowRoomSource(n=120)  # 4 s of stream; reading every frame would take 12 s
    worker = make_worker(source, FakeMapper(), cfg=anytime_cfg(backlog_frames=4), realtime=True)
    assert worker.wait_finished(40)
    snap = worker.slot.get()[1]
    assert snap.frames_done + snap.dropped == 120
    # frames a whole backlog behind the stream's clock are passed over unread (about two in three here)...
    assert len(source.loaded) < 60 and worker._feed.passed_over > 50
    assert source.loaded == sorted(source.loaded) and source.loaded[-1] == 119
    assert snap.stats[-1].index == 119


class RenderedRoomSource(SlowRoomSource):
    """A slow reader (0.1 s a frame) until `prepare_playback` has prepared a frame, like the synthetic room
    before it has rendered a frame into its cache."""

    def __init__(self, n: int) -> None:
        super().__init__(n=n)
        self.prepared: set[int] = set()
        self.asked: list[list[int]] = []

    def prepare_playback(self, keys, progress=None, stop=None) -> None:  # noqa: ANN001
        self.asked.append([int(k) for k in keys])
        for done, key in enumerate(keys, 1):
            if stop is not None and stop():
                return
            time.sleep(0.01)
            self.prepared.add(int(key))
            if progress is not None:
                progress(done, len(keys))

    def load(self, position: int, key: object) -> RgbdFrame:
        if int(key) in self.prepared:  # type: ignore[call-overload]
            self.loaded.append(int(key))  # type: ignore[call-overload]
            return BoxRoomSource.load(self, position, key)  # type: ignore[arg-type]
        return super().load(position, key)


def test_realtime_playback_has_the_source_prepare_the_frames_it_will_play_before_its_clock_starts(
    make_worker: Factory,
) -> None:
    source = RenderedRoomSource(n=90)  # 3 s of stream; unprepared, reading it would take 9 s
    worker = make_worker(source, FakeMapper(), cfg=anytime_cfg(backlog_frames=4), realtime=True)
    seen: list[tuple[int, int]] = []
    snap = wait_for(worker, lambda s: seen.append(s.preparing) or s.finished, 40)  # type: ignore[func-returns-value]
    assert source.asked == [list(range(90))]  # once, every frame still to play
    progress = [p for p in seen if p is not None]
    assert progress and all(total == 90 for _, total in progress) and seen[-1] is None  # shown, then cleared
    assert snap.frames_done == 90 and snap.dropped == 0 and worker._feed.passed_over == 0


def test_switching_realtime_off_ends_the_preparation_and_switching_it_on_prepares_what_is_left() -> None:
    source, settings = RenderedRoomSource(n=60), WorkerSettings(realtime=True)
    feed = FrameFeed(source, settings, 0, backlog=4)
    feed.start()
    try:
        deadline = time.monotonic() + 10
        while (feed.preparing is None or feed.preparing[0] < 5) and time.monotonic() < deadline:
            time.sleep(0.002)
        settings.realtime = False  # every-frame mode: frames are read as mapping takes them
        taken = [feed.take(5.0).index for _ in range(3)]
        assert len(source.asked) == 1 and len(source.prepared) < 30 and feed.preparing is None
        settings.realtime = True
        while len(source.asked) < 2 and time.monotonic() < deadline:
            feed.take(0.05)
        assert len(source.asked) == 2 and source.asked[1][0] > taken[-1] and source.asked[1][-1] == 59
    finally:
        feed.stop()


def test_a_late_reader_still_delivers_every_frame_within_the_backlog(make_worker: Factory) -> None:
    source = SlowRoomSource(n=20)  # ...while a reader less than a backlog behind reads them all
    worker = make_worker(source, FakeMapper(), cfg=anytime_cfg(backlog_frames=30), realtime=True)
    assert worker.wait_finished(40)
    snap = worker.slot.get()[1]
    assert snap.dropped == 0 and [s.index for s in snap.stats] == list(range(20))


def test_pause_step_resume(make_worker: Factory) -> None:
    worker = make_worker(BoxRoomSource(n=6), FakeMapper(), paused=True)
    time.sleep(0.4)
    assert worker.slot.get()[1].frames_done == 0
    stats = worker.submit("step").result(5)
    assert stats.index == 0
    assert wait_for(worker, lambda s: s.frames_done == 1 and s.paused and bool(s.chunks))  # re-meshed while idle
    time.sleep(0.3)
    assert worker.slot.get()[1].frames_done == 1
    worker.submit("resume").result(5)
    assert worker.wait_finished(10) and worker.slot.get()[1].frames_done == 6
    assert worker.submit("step").result(5) is None  # nothing left to step over


def test_render_is_served_between_frames_and_bands_are_stitched(make_worker: Factory) -> None:
    mapper = FakeMapper(delay_s=0.15)
    worker = make_worker(BoxRoomSource(n=40), mapper)
    wait_for(worker, lambda s: s.frames_done >= 2)
    K, T = intrinsics(200, 150), room_pose(3, 40)
    before = worker.slot.get()[1].frames_done
    view = worker.submit("render", K=K, T_world_camera=T, height=150, width=200, mode="rgb", with_depth=True).result(10)
    assert worker.slot.get()[1].frames_done - before <= 2  # served within about one frame's mapping
    wait_for(worker, lambda s: s.frames_done >= before + 3)  # and mapping goes on
    assert isinstance(view, RenderedView) and view.image.shape == (150, 200, 3) and view.depth_m.shape == (150, 200)
    worker.submit("pause").result(5)
    bands = worker.submit("render", K=K, T_world_camera=T, height=150, width=200, mode="depth").result(10)
    assert [h for h, w, m in mapper.rendered[-2:]] == [96, 54]  # two row bands
    whole = mapper.render(K, T, 150, 200, "depth")
    np.testing.assert_array_equal(bands.image, whole)
    assert bands.depth_m is None and (whole > 0).mean() > 0.5
    coarse = worker.submit(
        "render", K=K, T_world_camera=T, height=150, width=200, mode="rgb", with_depth=True, depth_downscale=2
    ).result(10)
    assert mapper.rendered[-1] == (75, 100, "depth")  # depth at half resolution
    half = mapper.render(scaled_intrinsics(K, 2), T, 75, 100, "depth")
    np.testing.assert_array_equal(coarse.depth_m[::2, ::2], half)
    np.testing.assert_array_equal(coarse.depth_m[1::2, 1::2], half)
    assert np.median(np.abs(coarse.depth_m - whole)[whole > 0]) < 0.05  # close to the full-resolution depth


def test_bad_render_requests_fail_their_own_future(make_worker: Factory) -> None:
    worker = make_worker(BoxRoomSource(n=3), FakeMapper())
    K, T = intrinsics(20, 10), room_pose(0, 3)
    with pytest.raises(H2vizError, match="unknown mode"):
        worker.submit("render", K=K, T_world_camera=T, height=10, width=20, mode="xray").result(5)
    with pytest.raises(H2vizError, match="unknown command"):
        worker.submit("fly").result(5)
    assert worker.wait_finished(10)


def test_export_and_save(make_worker: Factory, tmp_path) -> None:  # noqa: ANN001
    mapper = FakeMapper()
    worker = make_worker(BoxRoomSource(n=4), mapper)
    assert worker.wait_finished(10)
    expected = mapper.mesh()
    for fmt in ("ply", "glb"):
        data = worker.submit("export", format=fmt).result(10)
        mesh = trimesh.load(io.BytesIO(data), file_type=fmt, force="mesh", process=False)
        assert len(mesh.faces) == len(expected.faces) > 0
    with pytest.raises(H2vizError, match="unknown mesh format"):
        worker.submit("export", format="stl").result(5)
    path = worker.submit("save", path=str(tmp_path / "sub" / "map.npz")).result(5)
    np.testing.assert_array_equal(np.load(path)["voxels"], mapper.voxel_coords())


def test_mesh_is_extracted_every_n_frames(make_worker: Factory) -> None:
    mapper = FakeMapper()
    worker = make_worker(BoxRoomSource(n=9), mapper, mesh_every=3, mesh_update_hz=0.0)
    assert worker.wait_finished(10)
    assert mapper.mesh_calls == 3  # after frames 3, 6 and 9; nothing left to re-mesh at the end


def test_settings_apply_live_and_resolution_remeshes(make_worker: Factory) -> None:
    mapper = FakeMapper()
    worker = make_worker(BoxRoomSource(n=3), mapper)
    before = worker.wait_finished(10) and worker.slot.get()[1].chunks
    reply = worker.submit("set", mesh_resolution=5, mesh_update_hz=1.5, stride=3).result(5)
    assert reply["mesh_resolution"] == 5 and reply["stride"] == 3 and worker.settings.mesh_update_hz == 1.5
    after = wait_for(worker, lambda s: any(s.chunks[k] is not before[k] for k in before)).chunks
    assert all(after[k] is not before[k] for k in before)  # every chunk re-meshed
    with pytest.raises(H2vizError, match="unknown setting 'speed'"):
        worker.submit("set", speed=2).result(5)
    with pytest.raises(H2vizError, match="stride must be"):
        worker.submit("set", stride=0).result(5)
    assert worker.settings.stride == 3
    before = after
    reply = worker.submit("set", mesh_observed_only=False).result(5)
    assert reply["mesh_observed_only"] is False and mapper.mesh_observed_only is False
    wait_for(worker, lambda s: all(s.chunks[k] is not before[k] for k in before))  # every chunk re-meshed
    with pytest.raises(H2vizError, match="must be true or false"):
        worker.submit("set", mesh_observed_only="no").result(5)
    assert mapper.mesh_observed_only is False


def test_refinement_runs_in_slices_once_mapping_is_finished(make_worker: Factory) -> None:
    from h2viz.worker.mapping_worker import REFINE_SLICE

    mapper = FakeMapper()
    worker = make_worker(BoxRoomSource(n=4), mapper, paused=True)
    with pytest.raises(H2vizError, match="nothing is mapped"):
        worker.submit("refine", steps=12).result(10)
    assert worker.submit("step").result(10) is not None  # one frame mapped; still paused: refinement runs
    assert worker.submit("refine", steps=12).result(10) == 12
    snap = wait_for(worker, lambda s: s.refined == 12 and s.refine_left == 0)
    assert sum(mapper.refine_calls) == 12 and max(mapper.refine_calls) <= REFINE_SLICE
    assert snap.paused and snap.frames_done == 1
    with pytest.raises(H2vizError, match="positive"):
        worker.submit("refine", steps=0).result(10)


def test_mapping_failures_are_reported_and_pause_after_three_in_a_row(make_worker: Factory) -> None:
    mapper = FakeMapper()
    mapper.fail_frames = {1, 4, 5, 6}
    worker = make_worker(BoxRoomSource(n=10), mapper)
    snap = wait_for(worker, lambda s: s.paused)
    assert [s.index for s in snap.stats] == [0, 2, 3] and snap.skipped == 4
    assert len(worker.errors) == 5 and "frame 1" in worker.errors[0] and "paused" in worker.errors[-1]
    mapper.fail_frames = set()
    worker.submit("resume").result(5)
    assert worker.wait_finished(10) and worker.slot.get()[1].frames_done == 6 and worker.alive


def test_stop_joins_and_refuses_new_commands(make_worker: Factory) -> None:
    worker = make_worker(BoxRoomSource(n=200), FakeMapper(delay_s=0.05))
    wait_for(worker, lambda s: s.frames_done >= 1)
    worker.stop()
    assert not worker.alive
    with pytest.raises(H2vizError, match="not running"):
        worker.submit("pause").result(1)


# ------------------------------------------------------------------------------- the real Mapper


def test_real_mapper_in_the_worker(make_worker: Factory, tmp_path) -> None:  # noqa: ANN001
    from h2viz.mapping.checkpoint import load_checkpoint

    cfg = tiny_mapping_config()
    worker = make_worker(BoxRoomSource(n=5), recording_mapper(cfg))
    assert worker.wait_finished(60) and not worker.errors
    snap = worker.slot.get()[1]
    assert snap.frames_done == 5 and sum(len(c.faces) for c in snap.chunks.values()) > 0
    assert snap.keyframes and {kf.state for kf in snap.keyframes} <= set(KeyframeState)
    assert 0 <= snap.metrics["acc_cm"] < 50  # against the room's ground-truth box
    K, T = intrinsics(64, 48), room_pose(2, 5)
    shapes = {"rgb": (48, 64, 3), "depth": (48, 64), "normal": (48, 64, 3), "prior": (48, 64)}
    for mode, shape in shapes.items():
        view = worker.submit("render", K=K, T_world_camera=T, height=48, width=64, mode=mode).result(30)
        assert view.image.shape == shape and np.isfinite(view.image).all()
    depth = worker.submit("render", K=K, T_world_camera=T, height=48, width=64, mode="depth").result(30).image
    truth = trace_room(K, T, 48, 64)[0]
    hit = depth > 0
    assert hit.mean() > 0.5 and np.median(np.abs(depth[hit] - truth[hit])) < 0.1
    mesh = trimesh.load(io.BytesIO(worker.submit("export", format="glb").result(30)), file_type="glb", force="mesh")
    assert len(mesh.faces) > 0
    assert worker.submit("refine", steps=8).result(30) == 8  # the finished map, refined in slices
    refined = wait_for(worker, lambda s: s.refined == 8 and s.refine_left == 0, 60)
    assert refined.chunks and not worker.errors
    path = worker.submit("save", path=str(tmp_path / "room.pt")).result(30)
    restored, _ = load_checkpoint(path, cfg)
    np.testing.assert_array_equal(restored.voxel_coords(), snap.voxel_coords)


def test_real_mapper_on_real_data(make_worker: Factory, shared_dataset: Callable[[str], object]) -> None:
    cfg = Config()
    cfg.source.path = str(shared_dataset("redkitchen_50"))
    cfg.source.max_frames, cfg.source.downscale = 3, 4
    source = make_source(cfg.source)
    mcfg = tiny_mapping_config().updated(voxel_size_m=0.1, truncation_m=0.05, step_m=0.02, max_iters=4)
    worker = make_worker(source, recording_mapper(mcfg), cfg=cfg, stride=5)
    assert worker.wait_finished(120) and not worker.errors
    snap = worker.slot.get()[1]
    assert [s.index for s in snap.stats] == [0, 5, 10] and snap.chunks
    frame = snap.current_frame
    view = worker.submit(
        "render",
        K=frame.K,
        T_world_camera=frame.T_world_camera,
        height=frame.height,
        width=frame.width,
        mode="depth",
    ).result(60)
    both = (view.image > 0) & (frame.depth_m > 0)
    assert both.mean() > 0.5 and np.median(np.abs(view.image[both] - frame.depth_m[both])) < 0.05


# ------------------------------------------------------------------------------- meshing beside mapping


class ScriptedJob:
    """A mesh job for MeshThread tests: runs `passes` passes, each waiting for `gate` (when given)."""

    def __init__(self, name: str, passes: int = 1, gate: threading.Event | None = None) -> None:
        self.name, self.passes, self.gate = name, passes, gate
        self.version = self.field_version = 0
        self.names = [name]
        self.ran: list[int] = []
        self.stopped = False
        self.started = threading.Event()

    def run(self, stop: Callable[[], bool], on_pass: Callable[[list, bool], None], hurry: object = None) -> None:
        self.started.set()
        for i in range(self.passes):
            if i and stop():
                self.stopped = True
                return
            if self.gate is not None:
                assert self.gate.wait(10)
            if self.name == "broken":
                raise RuntimeError("meshing failed on purpose")
            self.ran.append(i)
            on_pass([(i, 0, 0)], i == 0)

    def after(self, older: ScriptedJob) -> ScriptedJob:
        self.names = self.names + older.names
        return self


def test_mesh_thread_merges_waiting_jobs_and_cuts_the_running_one_short() -> None:
    published: list[float] = []
    thread = MeshThread(lambda: published.append(time.monotonic()), lambda: 0.0).start()
    try:
        gate = threading.Event()
        first = ScriptedJob("first", passes=50, gate=gate)
        thread.submit(first)
        assert first.started.wait(10)
        second, third = ScriptedJob("second"), ScriptedJob("third")
        thread.submit(second)
        thread.submit(third)  # replaces the waiting second job, covering both
        gate.set()
        assert thread.wait_idle(10)
        assert first.stopped and len(first.ran) < 50  # the waiting job cut the running one short
        assert third.names == ["third", "second"] and third.ran == [0] and second.ran == []
        assert published and not thread.errors
        nothing = ScriptedJob("nothing to re-mesh", passes=0)
        thread.submit(nothing)
        assert thread.wait_idle(10)
        records = list(thread.jobs)  # what measurements read: every job run, passes and whether cut short
        assert [(r.passes, r.cut_short) for r in records] == [(len(first.ran), True), (1, False), (0, False)]
        assert all(r.submitted <= r.finished for r in records)
    finally:
        thread.stop()


def test_a_late_mesh_job_holds_the_caller_until_its_required_chunks_are_done() -> None:
    thread = MeshThread(lambda: None, lambda: 0.0).start()
    try:
        assert thread.catch_up(0.0, 1.0) == 0.0  # nothing runs
        gate = threading.Event()
        job = ScriptedJob("late", passes=3, gate=gate)
        thread.submit(job)
        assert job.started.wait(10)
        assert thread.catch_up(60.0, 1.0) == 0.0  # running, but not late
        assert thread.catch_up(0.0, 0.2) > 0.0 and job.ran == []  # late: waits, but no longer than told
        threading.Timer(0.2, gate.set).start()
        assert thread.catch_up(0.0, 10.0) > 0.0
        assert job.ran[:1] == [0]  # released once the required pass was done
        assert thread.wait_idle(10) and thread.catch_up(0.0, 1.0) == 0.0
    finally:
        thread.stop()


def test_mesh_thread_publishes_at_most_at_the_update_rate() -> None:
    published: list[float] = []
    thread = MeshThread(lambda: published.append(time.monotonic()), lambda: 5.0).start()
    try:
        for i in range(6):
            thread.submit(ScriptedJob(f"job{i}", passes=3))
            time.sleep(0.05)
        assert thread.wait_idle(10)
        gaps = np.diff(published)
        assert len(published) >= 2 and (gaps >= 0.2 - 1e-3).all()  # 5 Hz
        assert len(thread.passes) == 18  # every pass ran; their results went out together
    finally:
        thread.stop()


def test_refresh_results_wait_for_the_next_required_pass_instead_of_delaying_it() -> None:
    published: list[float] = []
    thread = MeshThread(lambda: published.append(time.monotonic()), lambda: 2.0).start()  # a 0.5 s period
    try:
        first = ScriptedJob("first", passes=2)  # its required pass, then a refresh pass
        thread.submit(first)
        assert first.started.wait(10)
        time.sleep(0.1)
        thread.submit(ScriptedJob("second"))
        assert thread.wait_idle(10)
        assert len(published) == 2  # the refresh result went out with the second job's required chunks
        assert published[1] - published[0] < 0.9  # one period after the first update, not two
        time.sleep(0.6)  # a period later: the next required pass goes out at once
        thread.submit(ScriptedJob("third", passes=2))
        assert thread.wait_idle(10) and len(published) == 4  # with no job after it, a refresh result goes alone
    finally:
        thread.stop()


def test_mesh_errors_are_reported_and_later_jobs_still_run() -> None:
    thread = MeshThread(lambda: None, lambda: 0.0).start()
    try:
        thread.submit(ScriptedJob("broken"))
        assert thread.wait_idle(10)
        ok = ScriptedJob("ok")
        thread.submit(ok)
        assert thread.wait_idle(10)
        assert ok.ran == [0] and "meshing failed on purpose" in thread.errors[0]
    finally:
        thread.stop()


class SlowMeshMapper(FakeMapper):
    """A FakeMapper whose mesh jobs last until `frames_while_meshing` more frames were mapped (or all `n_frames`
    of the source: no more will come)."""

    def __init__(self, frames_while_meshing: int, n_frames: int = 16) -> None:
        super().__init__()
        self.frames_while_meshing, self.n_frames = frames_while_meshing, n_frames
        self.mapped_during: list[int] = []

    def mesh_job(self, refresh_s: float = 0.0, whole: bool = False) -> object:
        job = super().mesh_job(refresh_s, whole)
        if job is None or whole:
            return job
        inner_run = job.run

        def run(stop: object = None, on_pass: object = None, hurry: object = None) -> None:
            start = self._version
            deadline = time.monotonic() + 10
            until = min(start + self.frames_while_meshing, self.n_frames)
            while self._version < until and time.monotonic() < deadline:
                time.sleep(0.01)
            self.mapped_during.append(self._version - start)
            inner_run(stop, on_pass, hurry)

        job.run = run  # type: ignore[method-assign]
        return job


def test_meshing_never_stalls_mapping(make_worker: Factory) -> None:
    mapper = SlowMeshMapper(frames_while_meshing=3)
    worker = make_worker(BoxRoomSource(n=16), mapper, mesh_update_hz=50.0)
    assert worker.wait_finished(30)
    assert mapper.mapped_during and max(mapper.mapped_during) >= 3  # frames went on being mapped meanwhile
    snap = worker.slot.get()[1]
    assert snap.frames_done == 16 and set(snap.chunks) == set(mapper.mesh_chunks())


def test_no_mesh_job_is_frozen_while_one_runs(make_worker: Factory) -> None:
    """Freezing the field for a job costs the mapping thread; it happens only when the mesh thread is free."""
    mapper = SlowMeshMapper(frames_while_meshing=3)
    frozen_at: list[int] = []
    make_job = mapper.mesh_job

    def mesh_job(refresh_s: float = 0.0, whole: bool = False) -> object:
        frozen_at.append(mapper._version)
        return make_job(refresh_s, whole)

    mapper.mesh_job = mesh_job  # type: ignore[method-assign]
    worker = make_worker(BoxRoomSource(n=16), mapper, mesh_update_hz=50.0)
    assert worker.wait_finished(30)
    while_mapping = [v for v in frozen_at if v < 16]
    assert 2 <= len(while_mapping) <= 16 // 3 + 2  # one job per ~3 frames, not one per frame
    assert set(worker.slot.get()[1].chunks) == set(mapper.mesh_chunks())


class StepMeshMapper(FakeMapper):
    """Frames of 4 optimisation steps and mesh jobs that last 6 steps: a job handed over at the end of a frame
    is still running when the next frame ends, and ends in the middle of the frame after."""

    def __init__(self) -> None:
        super().__init__(delay_s=0.04)
        self.steps_per_frame = 4
        self.freezes: list[tuple[int, bool]] = []  # (frames mapped, frozen between a frame's steps)

    def mesh_job(self, refresh_s: float = 0.0, whole: bool = False) -> object:
        self.freezes.append((self._version, self.in_frame))
        job = super().mesh_job(refresh_s, whole)
        if job is None or whole:
            return job
        inner_run, start = job.run, self.steps_done

        def run(stop: object = None, on_pass: object = None, hurry: object = None) -> None:
            deadline = time.monotonic() + 0.5  # the last jobs: no more steps come
            while self.steps_done < start + 6 and time.monotonic() < deadline:
                time.sleep(0.002)
            inner_run(stop, on_pass, hurry)

        job.run = run  # type: ignore[method-assign]
        return job


def test_frames_that_end_while_meshing_go_to_the_mesh_thread_as_soon_as_it_is_free(make_worker: Factory) -> None:
    """Without the between-steps hand-over such a frame waits for the end of the next frame: up to a whole frame
    more of mesh latency."""
    mapper = StepMeshMapper()
    worker = make_worker(BoxRoomSource(n=12), mapper, mesh_update_hz=50.0)
    assert worker.wait_finished(30)
    while_mapping = [(v, during) for v, during in mapper.freezes if v < 12]
    handed_between_steps = [v for v, during in while_mapping if during]
    assert len(handed_between_steps) >= 2
    assert len(while_mapping) <= 12  # still at most one freeze of the field per frame
    assert set(worker.slot.get()[1].chunks) == set(mapper.mesh_chunks())


def test_a_frame_left_unmeshed_goes_to_the_mesh_thread_between_render_bands() -> None:
    """Renders are served between frames for up to a frame's time: a frame that ended while the mesh thread was
    busy must not wait for them."""
    from concurrent.futures import Future

    from h2viz.types import Command

    mapper = FakeMapper()
    worker = MappingWorker(BoxRoomSource(n=2), mapper, Config())  # type: ignore[arg-type]  # not started
    mapper.integrate(BoxRoomSource(n=2).get(0, 0))  # a frame mapped, its mesh job not handed over yet
    worker._unmeshed = 1
    events: list[str] = []
    make_job = mapper.mesh_job

    def mesh_job(refresh_s: float = 0.0, whole: bool = False) -> object:
        events.append("mesh job")
        return make_job(refresh_s, whole)

    def bands() -> Iterator[None]:
        for _ in range(3):
            events.append("band")
            yield

    mapper.mesh_job = mesh_job  # type: ignore[method-assign]
    worker._renders.append((Command("render", {}, Future()), bands()))
    worker._last_map_s = 10.0  # a budget that covers every band
    worker._render_slices()
    assert events == ["band", "mesh job", "band", "band"]


def test_each_frame_reaches_the_snapshots_through_the_mesh_thread(make_worker: Factory) -> None:
    mapper = FakeMapper(delay_s=0.1)
    worker = make_worker(BoxRoomSource(n=8), mapper, mesh_update_hz=20.0)
    seen_versions: set[int] = set()
    version = 0
    while not (worker.slot.get()[1] is not None and worker.slot.get()[1].finished):
        version, snap = worker.slot.wait_newer(version, 0.5)
        if snap is not None:
            seen_versions |= {c.version for c in snap.chunks.values()}
    assert len(seen_versions) >= 4  # chunk updates streamed while mapping, not only at the end
    records = list(worker.meshing.passes)
    assert records and all(r.finished >= r.submitted for r in records)


def test_no_live_mesh_without_viewers_and_the_first_viewer_gets_every_change() -> None:
    mapper = FakeMapper(delay_s=0.05)
    worker = MappingWorker(BoxRoomSource(n=14), mapper, Config(), WorkerSettings(mesh_update_hz=20.0))  # type: ignore[arg-type]
    worker.set_viewers(0)
    assert not worker.live
    try:
        worker.start()
        snap = wait_for(worker, lambda s: s.frames_done >= 6)
        assert not worker.meshing.passes and not snap.chunks  # mapped, but nobody watches: nothing meshed
        chunks_so_far = {tuple(int(c) for c in k) for k in np.unique(mapper._voxels // mapper.chunk_voxels, axis=0)}
        worker.set_viewers(1)
        assert worker.live
        wait_for(worker, lambda s: bool(s.chunks))
        assert chunks_so_far <= set(worker.meshing.passes[0].chunks)  # the backlog, in the first job
        assert worker.wait_finished(20)
        assert set(worker.slot.get()[1].chunks) == set(mapper.mesh_chunks())
    finally:
        worker.stop()


def test_live_mesh_is_coarse_and_downloads_use_the_mapping_resolution(make_worker: Factory) -> None:
    cfg = Config()
    cfg.mapping = tiny_mapping_config()  # mesh_resolution 4: what downloads use
    cfg.viewer.live_mesh_resolution = 2  # the live mesh
    mapper = recording_mapper(cfg.mapping)
    worker = make_worker(BoxRoomSource(n=5), mapper, cfg=cfg)
    assert worker.wait_finished(60) and not worker.errors
    assert mapper.mesh_resolution == 2
    live = worker.slot.get()[1].chunks
    live_faces = sum(len(c.faces) for c in live.values())
    data = worker.submit("export", format="ply").result(60)
    full = trimesh.load(io.BytesIO(data), file_type="ply", force="mesh", process=False)
    # twice the samples per voxel edge: about four times the triangles of the same surface
    assert 3.0 < len(full.faces) / live_faces < 5.0
    assert all(mapper.mesh_chunks()[k] is c for k, c in live.items())  # the live chunks are left as they were


class StallingRoomSource(BoxRoomSource):
    """Room frames at 30 Hz with a 2.5 s gap in the stream after frame 9 (a camera that stops sending)."""

    def timestamp(self, position: int, key: object) -> float:
        i = int(key)  # type: ignore[call-overload]
        return i / 30.0 + (2.5 if i >= 10 else 0.0)


def test_a_paused_stream_sharpens_the_map_and_frames_after_it_are_integrated(make_worker: Factory) -> None:
    source, mapper = StallingRoomSource(n=20), FakeMapper()
    mapper.step_delay_s = 0.005
    worker = make_worker(source, mapper, cfg=anytime_cfg(), realtime=True)
    wait_for(worker, lambda s: s.frames_done == 10 and s.phase in ("sharpening", "settled"))
    assert mapper.refine_steps > 0 and not worker.slot.get()[1].finished  # the gap: keyframes sharpened
    assert worker.wait_finished(20)
    snap = worker.slot.get()[1]
    assert [s.index for s in snap.stats] == list(range(20)) and snap.dropped == 0
    kinds = [k for k, _ in mapper.events]
    first_after = kinds.index("add", kinds.index("refine"))
    assert "live" in kinds[first_after:]  # back to live steps on the new frames
