"""MappingWorker: the one thread that owns the mapper (all torch state). It maps frames from the
feed, serves Commands between frames (render bands are interleaved with mapping under a time
budget) and publishes a frozen MapSnapshot into its LatestSlot after every change. Mesh extraction
runs beside it on a MeshThread, from a frozen copy of the field taken after each frame. A Command can also make it
take over an earlier run's checkpoint and map on after that run's last frame (the dashboard's resume offer).

In real-time mode it maps anytime (h2viz.mapping.anytime): every frame the feed delivers is integrated, single
optimisation steps fill the time between frames, and when the stream ends (or no frame came for STREAM_PAUSE_S)
the map keeps sharpening over its keyframes until the loss plateaus or the user pauses."""

from __future__ import annotations

import logging
import math
import os
import queue
import threading
import time
from collections import deque
from concurrent.futures import Future
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from h2viz.config import Config
from h2viz.errors import ConfigError, H2vizError
from h2viz.mapping.anytime import Action, AnytimeSchedule, FusionStride, Phase, check_anytime, plateau_from
from h2viz.mapping.autosave import Autosaver, ResumeOffer, run_state
from h2viz.types import Command, FrameStats, MapSnapshot, RgbdFrame
from h2viz.worker import requests
from h2viz.worker.commands import CommandServing
from h2viz.worker.feed import END, FrameFeed, WorkerSettings, settings_from_config
from h2viz.worker.mesh_thread import MeshThread
from h2viz.worker.slot import LatestSlot

if TYPE_CHECKING:
    from h2viz.mapping.mapper import Mapper
    from h2viz.sources.base import FrameSource

log = logging.getLogger("h2viz.worker")
MAX_CONSECUTIVE_FAILURES = 3
# Each frame's mesh job also refreshes dirty voxels and stale chunks for up to this long (with 0.1 s, meshing cost
# mapping 26 % instead of 16 % on two cores, for chunks brought up to date sooner). The budget is checked between
# passes of ~30 ms, so 0.015 s meshed as much as 0.03 s. Everything is brought up to date once mapping pauses or ends.
REFRESH_S = 0.03
IDLE_REFRESH_S = 1.0  # same while mapping is paused or finished (until every chunk is up to date)
REFINE_SLICE = 5  # refinement steps between two looks at commands, renders and the mesh
MESH_DEADLINE_S = 0.3  # a mesh job still on its required chunks this long after submission gets the cores to itself
MESH_WAIT_MAX_S = 2.0  # ... for at most this long at a time
STREAM_MESH_WAIT_S = 0.03  # ... or, while a real-time stream arrives and no frame waits, this long (a frame's time)
REQUEST_FAULT_AUTOSAVE_S = 60.0  # a failing render or export autosaves at most this often (renders come in streams)
STATS_KEPT = 2000  # per-frame stats the snapshots carry (the plots show the latest); older ones are counted only
STREAM_PAUSE_S = 1.0  # real-time mode: no frame for this long, and the steps sharpen every keyframe instead


def rss_mb() -> float:
    """Resident memory of this process in MB (0 when /proc is unavailable)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, ValueError, IndexError):
        return 0.0
    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


class MappingWorker(CommandServing):
    """Runs `mapper` over `source` on one background thread; talk to it with `submit` and read
    its state from `slot` (a LatestSlot of MapSnapshot)."""

    def __init__(
        self,
        source: FrameSource,
        mapper: Mapper,
        cfg: Config,
        settings: WorkerSettings | None = None,
        autosave_dir: Path | None = None,
        resumed: tuple[int, list[FrameStats]] | None = None,
    ) -> None:
        """`autosave_dir`: where autosave.pt is written (cfg.autosave; None = no autosave); `resumed`: the last
        frame index a resumed mapper mapped (frames up to it are passed over) and its frames' stats."""
        self.source, self.mapper, self.cfg = source, mapper, cfg
        self.mapper.mesh_resolution = cfg.viewer.live_mesh_resolution  # downloads use cfg.mapping.mesh_resolution
        if (cap := cfg.viewer.stream_mesh_resolution) < 0:  # refused now, not at the stream's first mesh job
            raise ConfigError(f"viewer.stream_mesh_resolution must be >= 0 (0 = no cap), got {cap}")
        self.mapper.on_iteration = self._between_steps
        self.settings = settings or settings_from_config(cfg)
        self.slot: LatestSlot[MapSnapshot] = LatestSlot()
        self.mapped_at: dict[int, float] = {}  # frame index -> time.time() when its mapping finished
        check_anytime(cfg.anytime)
        self._resume_after, earlier = resumed or (-1, [])
        self._feed = self._open_feed(self._resume_after)
        self._schedule = AnytimeSchedule(cfg.anytime.opt_share, cfg.anytime.catch_up_frames, cfg.anytime.backlog_frames)
        self._plateau = plateau_from(cfg.anytime)
        self._rss_t, self._rss = -math.inf, 0.0  # when resident memory was last read, and what it was
        self._fusion = FusionStride(cfg.anytime.fine_prior_stride)  # while frames wait: every k-th fused whole
        self._phase = ""  # real-time mode: a Phase value ("" in every-frame mode)
        self._opt_steps = self._newest_steps = 0  # real-time steps in all, and on the newest frame
        self._sharpen_s = 0.0
        self._last_frame_t = time.monotonic()
        self._mesh_submitted_t = 0.0  # time.monotonic() of the last mesh job handed over
        self._commands: queue.Queue[Command] = queue.Queue()
        self._stop = threading.Event()
        self._paused = cfg.viewer.start_paused
        self._finished = False
        self._steps: deque[Future[Any]] = deque()
        self._renders: deque[tuple[Command, Any]] = deque()  # (command, band generator)
        self._stats: deque[FrameStats] = deque(earlier, maxlen=STATS_KEPT)
        self._n_mapped = len(earlier)  # frames mapped, with those of the run resumed
        self._n_resumed = len(earlier)  # ... of which the run resumed mapped
        self._last_index = self._resume_after
        self._autosave = (
            Autosaver(
                autosave_dir,
                cfg.autosave,
                self._n_mapped,
                writer=requests.save_checkpoint,
                prepare=requests.prepare_checkpoint,
            )
            if autosave_dir is not None
            else None
        )
        self._mesh_errors_seen = 0
        self._request_fault_t = -np.inf  # time.monotonic() of the last autosave after a failed request
        self.notices: list[str] = []  # what the dashboard tells each browser that connects (an earlier run...)
        self.resume_offer: ResumeOffer | None = None  # an earlier run's checkpoint the dashboard offers to continue
        self._poses: list[np.ndarray] = list(getattr(mapper, "trajectory", ()))
        self._current: RgbdFrame | None = None
        self._metrics: dict[str, float] = {}
        self._errors: list[str] = []
        self._failures = self._consecutive = self._unmeshed = self._version = 0
        self._mesh_dirty = False
        self._refine_left = self._refined = 0
        self._viewers: int | None = None  # connected browsers; None: unknown, keep the live mesh up to date
        self._last_map_s = 0.0
        self._lag_s = 0.0  # real-time mode: how long the newest integrated frame waited after it arrived
        self._publish_lock = threading.Lock()
        self._chunks_out: dict = {}  # the chunks snapshots carry (changed only by the mesh thread's publish)
        self._last_snap: MapSnapshot | None = None
        self._live_metrics: Any = None  # a LiveMeshMetrics against the ground truth, made at the first refresh
        self._metrics_lock = threading.Lock()  # the mapping and meshing threads both refresh metrics
        self._metrics_due = False  # the meshing thread refreshes the metrics at its next publish
        backend = getattr(mapper, "backend", None)  # the mesh thread's kernels run on one core beside mapping's
        serial = None if backend is None else backend.serial_thread
        self.meshing = MeshThread(self._publish_mesh, lambda: self.settings.mesh_update_hz, serial, self._frames_wait)
        self._recorder: Any = None  # a BackgroundRecorder while the run is recorded
        self._gt: Any = None
        self._fatal: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="h2viz-mapping", daemon=True)

    # -- public API (any thread) ---------------------------------------------------------------
    def start(self) -> MappingWorker:
        self.meshing.start()
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 30.0) -> None:
        """Stop mapping, join the thread and fail the commands nobody will serve."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout_s)
        self.meshing.stop(timeout_s)
        if self._autosave is not None and (failed := self._autosave.wait()) is not None:  # a write in progress
            self._errors.append(failed)
        self.stop_recording()
        self._fail_pending(H2vizError("the mapping worker stopped before serving this request"))

    def submit(self, kind: str, **args: Any) -> Future[Any]:
        """Queue a Command (kind is one of COMMANDS); the returned Future holds the reply."""
        cmd = Command(kind, dict(args))
        if self._fatal is not None or self._stop.is_set():
            cmd.reply.set_exception(H2vizError(f"mapping is not running ({self._fatal or 'stopped'})"))
        else:
            self._commands.put(cmd)
        return cmd.reply

    def set_viewers(self, count: int) -> None:
        """How many browsers watch the map. With none, frames are not meshed or scored while mapping (nobody
        would see it, and it costs the mapper a quarter of the CPU); the first job after one connects covers
        every voxel changed meanwhile."""
        self._viewers = max(0, int(count))

    @property
    def live(self) -> bool:
        """The live mesh and metrics are kept up to date while mapping (someone watches, nobody said, or the run
        is recorded)."""
        return self._viewers is None or self._viewers > 0 or self._recorder is not None

    @property
    def recording(self) -> Path | None:
        """The folder being recorded into, or None."""
        return None if self._recorder is None else self._recorder.folder

    def start_recording(self, folder: str | Path, fps: float = 10.0) -> Path:
        """Record one step per mapped frame from now on into `folder` (see h2viz.viewer.recording)."""
        from h2viz.viewer.recording import BackgroundRecorder, Recorder

        with self._publish_lock:
            if self._recorder is not None:
                return self._recorder.folder
            self._recorder = BackgroundRecorder(Recorder(Path(folder), fps))
            if self._last_snap is not None:
                self._recorder.offer(self._last_snap)
        return Path(folder)

    def stop_recording(self) -> Path | None:
        """Finish the recording (its last step is the newest snapshot); returns its folder."""
        with self._publish_lock:
            recorder, self._recorder = self._recorder, None
        return None if recorder is None else recorder.close()

    @property
    def errors(self) -> tuple[str, ...]:
        """Messages of every mapping or meshing failure so far (mapping ones first, each oldest first)."""
        recorder = self._recorder
        return tuple(self._errors + self.meshing.errors + (recorder.errors if recorder is not None else []))

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def wait_finished(self, timeout_s: float | None = None) -> bool:
        """Block until the source is exhausted and the final snapshot is published."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        version = 0
        while deadline is None or time.monotonic() < deadline:
            version, snap = self.slot.wait_newer(version, 0.2)
            if (snap is not None and snap.finished) or not self._thread.is_alive():
                return snap is not None and snap.finished
        return False

    # -- the thread ----------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._gt = self.source.ground_truth_mesh()
            if self.settings.realtime:  # kernels loaded at the first frames would cost a live stream ~30 of them
                log.info("kernels ready in %.1f s", self.mapper.warm_up())
            self._feed.hold(self._paused)
            self._feed.start()
            self._publish()
            while not self._stop.is_set():
                busy = self._renders or self._refine_left or self._sharpening()
                self._serve_commands(0.05 if self._idle() and not busy else 0.0)
                self._render_slices()
                if not self._idle():
                    self._map_next()
                elif self._refine_left:
                    self._refine_slice()
                elif self._sharpening():
                    self._sharpen_slice()
                elif not self.meshing.busy:  # bring stale chunks up to date while nothing maps
                    self._submit_mesh(IDLE_REFRESH_S)
                self._after_mesh_failure()
        except Exception as e:  # keep the process alive, make the failure visible
            log.exception("the mapping worker failed")
            self._fatal = e
            saved = self._autosave_now()
            self._errors.append(f"mapping stopped: {type(e).__name__}: {e}; {saved}restart the dashboard to go on")
            self._fail_pending(e)
        finally:
            self._feed.stop()

    # -- mapping -------------------------------------------------------------------------------
    def _idle(self) -> bool:
        return self._finished or (self._paused and not self._steps)

    def _map_next(self) -> None:
        if self.settings.realtime and not self._steps:
            self._map_anytime()
            return
        item = self._feed.take(0.05)
        if item is END:
            self._end_stream()
        elif item is not None and item.index > self._resume_after:  # a resumed run passes over what it mapped
            self._integrate(item)

    def _open_feed(self, start_after: int) -> FrameFeed:
        """A frame feed over the source that passes over the positions up to `start_after` (a resumed run's)."""
        cfg = self.cfg
        return FrameFeed(  # real-time frames are prepared on the reader thread as they arrive
            self.source,
            self.settings,
            cfg.source.max_frames,
            cfg.anytime.backlog_frames,
            start_after,
            self.mapper.prepare_ahead,
        )

    def _end_stream(self) -> None:
        self._finished = True
        self._resolve_steps(None)
        if self.settings.realtime:
            self._close_newest()
            self._mesh_unmeshed()  # while the stream's mesh resolution holds (then every chunk at the live one)
            self._phase = Phase.SHARPENING.value
            self._plateau.reset()
            self._autosave_stream_end()
        self._remesh()
        if self._gt is not None:
            self._refresh_metrics()
        self._publish()

    # -- anytime mapping (real-time mode) --------------------------------------------------------
    def _map_anytime(self) -> None:
        """Integrate the waiting frame, or take one optimisation step (AnytimeSchedule decides)."""
        if not self._phase:
            self._phase = Phase.STREAMING.value
        action = self._schedule.next(self._feed.waiting(), self.mapper.frames_done > 0)
        if action is Action.STEP and time.monotonic() - self._last_frame_t < STREAM_PAUSE_S:
            self._timed_step(self.mapper.live_step)
            self._newest_steps += 1
            return
        if action is Action.STEP and self._phase != Phase.SETTLED.value:  # the stream paused: sharpen
            self._phase = Phase.SHARPENING.value
            self._sharpen_slice()
            return
        item = self._feed.take(0.05 if action is not Action.INTEGRATE else 0.0)
        if item is None and self._feed.preparing != (self._last_snap.preparing if self._last_snap else None):
            self._publish()  # the source's preparation went on (the progress panel shows it)
        if item is END:
            self._end_stream()
        elif item is not None and item.index > self._resume_after:
            self._integrate(item, anytime=True)

    def _timed_step(self, step: Any) -> float:
        t0 = time.perf_counter()
        loss = float(step())
        seconds = time.perf_counter() - t0
        self._schedule.did_step(seconds)
        self._opt_steps += 1
        self._between_steps()
        return loss if np.isfinite(loss) else float("nan")

    def _sharpen_step(self) -> None:
        """One step over random keyframes after (or during a pause of) the stream; settles on a loss plateau."""
        t0 = time.perf_counter()
        loss = self._timed_step(self.mapper.refine_step)
        self._sharpen_s += time.perf_counter() - t0
        limit = self.cfg.anytime.sharpen_max_s
        if self._plateau.add(loss) or not self.mapper.keyframe_rays or limit <= 0 or self._sharpen_s >= limit:
            self._phase = Phase.SETTLED.value
            if self._gt is not None:
                self._refresh_metrics()
            self._publish()

    def _sharpening(self) -> bool:
        """Real-time mode after the stream: optimisation goes on until it settles or the user pauses."""
        return self._finished and not self._paused and self._phase == Phase.SHARPENING.value

    def _sharpen_slice(self) -> None:
        """A few sharpening steps (fewer when it settles or a frame arrives), then the mesh follows."""
        for _ in range(REFINE_SLICE):
            self._sharpen_step()
            if self._phase != Phase.SHARPENING.value or self._feed.ready() or self._paused:
                break
        if self.live and not self.meshing.busy:
            self._submit_mesh(REFRESH_S)
        self._publish()

    def _close_newest(self) -> None:
        """The newest frame's stats get the live steps taken while it was the newest."""
        if self._stats and self._newest_steps:
            self._stats[-1] = replace(self._stats[-1], iterations=self._newest_steps)
        self._newest_steps = 0

    def _integrate(self, frame: RgbdFrame, anytime: bool = False) -> None:
        """Map one frame: with all its optimisation steps, or (`anytime`) integrate it alone."""
        t0 = time.perf_counter()
        try:
            if anytime:
                self._close_newest()
                a = self.cfg.anytime
                fuse_all = self._fusion.fuse_all(self._feed.frames_waiting())
                stats = self.mapper.add_frame(frame, a.color_points, a.observed_points, fuse_all)
            else:
                stats = self.mapper.integrate(frame)
        except Exception as e:
            self._on_failure(frame, e)
            return
        self._last_map_s = time.perf_counter() - t0
        if anytime:
            self._schedule.did_integrate(self._last_map_s)
            self._last_frame_t = time.monotonic()
            if self._phase != Phase.STREAMING.value:  # frames again after a pause
                self._phase = Phase.STREAMING.value
                self._plateau.reset()
        self.mapped_at[frame.index] = time.time()
        if (arrived := self._feed.arrived_at.get(frame.index)) is not None:
            self._lag_s = max(0.0, self.mapped_at[frame.index] - arrived)
        self._consecutive = 0
        self._unmeshed += 1
        self._stats.append(stats)
        self._n_mapped += 1
        self._last_index = frame.index
        self._poses.append(frame.T_world_camera)
        self._current = frame
        every = self.settings.metrics_every
        if self.live and self._gt is not None and every > 0 and self._n_mapped % every == 0:
            self._metrics_due = True  # the meshing thread refreshes them with its next publish
        if self.live and self._mesh_due() and (self._mesh_dirty or not self.meshing.busy):
            self._submit_mesh(REFRESH_S)  # not while a job runs: freezing the field costs ~15 ms a frame
        self._resolve_steps(stats)
        if self._autosave is not None:
            failed = self._autosave.maybe_save(self.mapper, self._n_mapped, self._autosave_extra, streaming=anytime)
            if failed is not None:
                self._errors.append(failed)
        self._publish()

    # -- resuming an earlier run (the dashboard's offer) -----------------------------------------
    def dismiss_resume_offer(self) -> None:
        """(any thread) Drop the offer to resume an earlier run, and the notice that tells browsers about it."""
        offer, self.resume_offer = self.resume_offer, None
        if offer is not None and offer.notice() in self.notices:
            self.notices.remove(offer.notice())

    def _resume_run(self, args: dict[str, Any]) -> str:
        """(mapping thread) Replace the map by the one of the checkpoint args["path"] (a file, or a run folder's
        newest) and continue mapping after its last frame, as `h2viz view --resume` does; the stream goes back to
        the frame after it (every source reads frames by position). Frames this run mapped are dropped. A checkpoint
        that cannot be loaded leaves this run as it is. Returns what happened, for the user."""
        from h2viz.mapping.autosave import find_checkpoint, run_progress
        from h2viz.mapping.checkpoint import load_checkpoint

        self.dismiss_resume_offer()
        try:
            path = find_checkpoint(args["path"])
            mapper, extra = load_checkpoint(path, self.cfg.mapping)
            last, stats = run_progress(path, extra)
        except H2vizError as e:
            raise H2vizError(f"{e}. This run goes on as it was.") from None
        replaced = self._n_mapped - self._n_resumed
        self._take_over(mapper, last, stats)
        message = f"Resumed from {path}: {len(stats)} frames were mapped; mapping goes on after frame {last}."
        if replaced:
            message += f" The {replaced} frames this run had mapped were replaced by that map."
        self.notices[:] = [message]
        return message

    def _take_over(self, mapper: Mapper, last: int, stats: list[FrameStats]) -> None:
        """Map on with `mapper` after frame `last`, its run's `stats` appended to: the live settings carry over, the
        stream restarts after `last`, the mesh is rebuilt and the run folder's autosave is replaced at once."""
        self.meshing.wait_idle()
        self._feed.stop()
        for key in requests.MAPPER_SETTINGS:
            setattr(mapper, key, getattr(self.mapper, key))
        mapper.on_iteration = self._between_steps
        self.mapper = mapper
        self._resume_after = self._last_index = last
        self._stats = deque(stats, maxlen=STATS_KEPT)
        self._n_mapped = self._n_resumed = len(stats)
        self._poses = list(getattr(mapper, "trajectory", ()))
        self._reset_progress()
        self._feed = self._open_feed(last)
        self._feed.hold(self._paused and not self._steps)
        self._feed.start()
        if self._autosave is not None:
            self._autosave.restart(self._n_mapped)
            if self._autosave.path.exists():  # it holds the map just replaced
                failed = self._autosave.save(mapper, self._n_mapped, self._autosave_extra())
                if failed is not None:
                    self._errors.append(failed)
        self._publish()  # before the mesh follows: no snapshot pairs the new map with the old run's progress
        self._remesh()

    def _reset_progress(self) -> None:
        """Forget what the replaced map's run did: its frames, failures, queued refinement and real-time phase."""
        self._finished = False
        self._current = None
        self.mapped_at.clear()
        self._metrics = {}
        self._failures = self._consecutive = self._unmeshed = self._newest_steps = 0
        self._refine_left = self._refined = 0
        self._mesh_dirty = self._metrics_due = False
        self._phase = ""
        self._plateau.reset()
        self._sharpen_s = 0.0
        self._last_frame_t = time.monotonic()

    # -- keeping the work ----------------------------------------------------------------------
    def _autosave_stream_end(self) -> None:
        """Real-time mode: autosave the frames mapped since the last autosave when the stream ends, since
        sharpening may go on for anytime.sharpen_max_s and maps no frames that would make an autosave due."""
        if self._autosave is not None and self._autosave.behind(self._n_mapped):
            failed = self._autosave.save(self.mapper, self._n_mapped, self._autosave_extra())
            if failed is not None:
                self._errors.append(failed)

    def _autosave_extra(self) -> dict[str, Any]:
        """A checkpoint's run state: where to continue and the frames' stats (as `h2viz map` writes them)."""
        return run_state(self._last_index, self._stats)

    def _autosave_now(self) -> str:
        """Autosave after a failure; the words that say so for the failure's message ('' without autosave)."""
        if self._autosave is None or self._n_mapped == 0:
            return ""
        try:
            failed = self._autosave.save(self.mapper, self._n_mapped, self._autosave_extra())
        except Exception as e:  # noqa: BLE001 - a mapper broken beyond saving: say so, keep the old autosave
            failed = f"autosave failed ({type(e).__name__}: {e})"
        if failed is not None:
            return f"{failed}; "
        return f"the map so far is saved in {self._autosave.path}; "

    def _on_request_failure(self, kind: str, error: Exception) -> None:
        """(mapping thread) A render, export or save that failed unexpectedly: autosave (at most once a minute) and
        say what failed and what goes on; the browser that asked was told through its request."""
        now = time.monotonic()
        saved = ""
        if now - self._request_fault_t >= REQUEST_FAULT_AUTOSAVE_S:
            self._request_fault_t = now
            saved = self._autosave_now()
        what = {"render": "a view render", "export": "a mesh export", "save": "saving a checkpoint"}.get(kind, kind)
        self._errors.append(
            f"{what} failed ({type(error).__name__}: {error}); {saved}mapping goes on; try it again, or with a smaller "
            "image or another format"
        )

    def _after_mesh_failure(self) -> None:
        """(mapping thread) Autosave once after the mesh thread reported new failures, and say what to do."""
        errors = self.meshing.errors
        if len(errors) > self._mesh_errors_seen:
            self._mesh_errors_seen = len(errors)
            saved = self._autosave_now()
            self._errors.append(
                f"the live mesh could not be updated; {saved}mapping goes on and the next update retries"
            )

    def _between_steps(self) -> None:
        """(mapping thread, between optimisation steps and render bands) A mesh job that is late with a frame's
        changes gets the cores until it has them (on two cores, mapping beside a large job such as the first
        frame's would double its time; while a real-time stream arrives, only when no frame waits and for a frame's
        time at most); frames that ended while the mesh thread was busy go to it as soon as it is
        free, not at the end of the next frame or after the renders served between frames: those waits were the
        tail of the mesh latency."""
        if self.live and not self._streaming():
            self.meshing.catch_up(MESH_DEADLINE_S, MESH_WAIT_MAX_S)
        elif self.live and self._feed.waiting() == 0:  # a live stream: only the slack, never a waiting frame's time
            self.meshing.catch_up(MESH_DEADLINE_S, STREAM_MESH_WAIT_S)
        if self._unmeshed and self.live and self._mesh_due() and not self.meshing.busy:
            self._submit_mesh(REFRESH_S)

    def _refine_slice(self) -> None:
        """A few queued refinement steps; the live mesh follows the refined field (every voxel is re-meshed)."""
        steps = min(REFINE_SLICE, self._refine_left)
        done = self.mapper.refine(steps)
        self._refine_left = 0 if done < steps else self._refine_left - steps  # no keyframes: nothing to refine
        self._refined += done
        if self.live and not self.meshing.busy:
            self._submit_mesh(REFRESH_S)
        self._publish()

    def _on_failure(self, frame: RgbdFrame, e: Exception) -> None:
        log.exception("mapping frame %d failed", frame.index)
        self._failures += 1
        self._consecutive += 1
        saved = self._autosave_now() if self._consecutive == 1 else ""
        self._errors.append(
            f"frame {frame.index} ({frame.name or 'no name'}): {type(e).__name__}: {e}; the frame was skipped; {saved}"
            "mapping goes on"
        )
        if self._consecutive >= MAX_CONSECUTIVE_FAILURES and not self._paused:
            n = self._consecutive
            self._errors.append(f"mapping paused after {n} failures in a row; press Resume to retry")
            self._set_paused(True)
        self._resolve_steps(None)
        self._publish()

    def _resolve_steps(self, stats: FrameStats | None) -> None:
        if self._steps:
            requests.settle(self._steps.popleft(), stats)
            self._feed.hold(self._paused and not self._steps)

    def _frames_wait(self) -> bool:
        """(mesh thread) A real-time stream arrives and frames wait to be integrated: mesh jobs leave out their
        optional refresh passes (re-evaluating chunks from the newer field), so that integration gets the cores."""
        return self._streaming() and self._feed.frames_waiting() > 0

    def _streaming(self) -> bool:
        """Real-time mode while frames arrive."""
        return self._phase == Phase.STREAMING.value

    def _mesh_due(self) -> bool:
        """After a frame: live updates (mesh_update_hz > 0) mesh every frame, else every mesh_every frames. While
        a real-time stream arrives, live updates come at most mesh_update_hz times a second: a job per frame at
        30 Hz would keep the mesh thread busy and take the cores integration needs."""
        s = self.settings
        if self._mesh_dirty:
            return True
        if s.mesh_update_hz > 0:
            return not self._streaming() or time.monotonic() - self._mesh_submitted_t >= 1.0 / s.mesh_update_hz
        return s.mesh_every > 0 and self._unmeshed >= s.mesh_every

    def _submit_mesh(self, refresh_s: float, whole: bool = False) -> None:
        """Freeze the field and hand the mesh thread a job (nothing when the mesh is up to date). While a real-time
        stream arrives the job meshes at most at viewer.stream_mesh_resolution (a change re-meshes every chunk)."""
        cap = self.cfg.viewer.stream_mesh_resolution if self._streaming() else 0
        if self.mapper.mesh_resolution_cap != cap:
            self.mapper.mesh_resolution_cap = cap
        try:
            job = self.mapper.mesh_job(refresh_s, whole)
        except Exception as e:  # keep mapping; the next job retries the same chunks
            log.exception("preparing a mesh update failed")
            self._errors.append(f"mesh extraction failed: {type(e).__name__}: {e}")
            return
        self._unmeshed, self._mesh_dirty = 0, False
        if job is not None:
            self._mesh_submitted_t = time.monotonic()
            self.meshing.submit(job)

    def _remesh(self) -> None:
        """Re-mesh every chunk from the field now and publish it (waits for the mesh thread). The job still
        running finishes first, and frames not yet meshed get a job of their own: otherwise the last frames' changes
        would reach the browsers only with the whole map."""
        self._mesh_unmeshed()
        self._submit_mesh(0.0, whole=True)
        self.meshing.wait_idle()

    def _mesh_unmeshed(self) -> None:
        """After the running job, the frames integrated since the last job get their own (small) one; waits for it."""
        self.meshing.wait_idle()
        if self._unmeshed and self.live:
            self._submit_mesh(0.0)
            self.meshing.wait_idle()

    def _refresh_metrics(self, voxel_coords: np.ndarray | None = None) -> None:
        """Ground-truth metrics of the mesh as it is now (the live chunks, no re-meshing), the ground truth culled
        to `voxel_coords` (V,3) (default: the mapper's voxels; the meshing thread passes the last snapshot's)."""
        from h2viz.eval.live_metrics import LiveMeshMetrics

        with self._metrics_lock:
            try:
                if self._live_metrics is None:
                    n, thr = self.settings.metrics_points, self.cfg.eval.threshold_m
                    self._live_metrics = LiveMeshMetrics(self._gt, n, thr)
                coords = self.mapper.voxel_coords() if voxel_coords is None else voxel_coords
                self._metrics = self._live_metrics(self.mapper.mesh_chunks(), coords, self.mapper.voxel_size_m)
            except Exception as e:  # metrics are informative; mapping goes on
                log.warning("ground-truth metrics failed: %s", e)

    def _publish(self) -> None:
        m = self.mapper
        with self._publish_lock:
            self._version += 1
            snap = MapSnapshot(
                version=self._version,
                frames_done=self._n_mapped,
                frames_total=self._feed.total(),
                chunks=self._chunks_out,
                voxel_size_m=float(m.voxel_size_m),
                voxel_coords=np.asarray(m.voxel_coords(), dtype=np.int32).reshape(-1, 3),
                keyframes=tuple(m.keyframe_infos()),
                trajectory=np.asarray(self._poses, dtype=np.float64).reshape(-1, 4, 4),
                current_frame=self._current,
                stats=tuple(self._stats),
                paused=self._paused,
                finished=self._finished,
                skipped=len({s.key for s in self.source.skipped}) + self._failures,  # once, when read again on resume
                dropped=self._feed.dropped,
                metrics=dict(self._metrics),
                memory_mb=self._rss_mb(),
                refine_left=self._refine_left,
                refined=self._refined,
                phase=self._phase,
                opt_steps=self._opt_steps,
                preparing=self._feed.preparing,
                waiting=self._feed.frames_waiting() if self.settings.realtime else 0,
                lag_s=self._lag_s,
            )
            self._last_snap = snap
            self.slot.put(snap)
            if self._recorder is not None:
                self._recorder.offer(snap)

    def _rss_mb(self) -> float:
        """The process's resident memory, read at most once a second (snapshots come at up to 30 a second)."""
        now = time.monotonic()
        if now - self._rss_t >= 1.0:
            self._rss_t, self._rss = now, rss_mb()
        return self._rss

    def _publish_mesh(self) -> None:
        """(mesh thread) The last snapshot again with the mapper's current chunks, then, when they are due, with
        fresh ground-truth metrics (off the mapping thread, which a 30 Hz stream keeps busy; after the chunks went
        out, which would otherwise wait for them)."""
        self._put_chunks(self.mapper.mesh_chunks())
        last = self._last_snap
        if self._metrics_due and self._gt is not None and last is not None:
            self._metrics_due = False
            self._refresh_metrics(last.voxel_coords)
            self._put_chunks(self._chunks_out)

    def _put_chunks(self, chunks: dict) -> None:
        """(mesh thread) Publish the last snapshot with `chunks` and the current metrics."""
        with self._publish_lock:
            self._chunks_out = chunks
            if self._last_snap is None:
                return
            self._version += 1
            snap = replace(self._last_snap, version=self._version, chunks=chunks, metrics=dict(self._metrics))
            self._last_snap = snap
            self.slot.put(snap)
            if self._recorder is not None:
                self._recorder.offer(snap)
