"""The worker's live settings and the frame feed: a reader thread that loads frames ahead of the
mapper, either every frame in order or, in real-time mode, each frame at the stream's own rate (every one kept
until it is integrated, up to a backlog; frames beyond it, and those a slow reader passes over, are counted).
Before real-time playback starts, the source prepares the frames it will play (the synthetic room renders them
once)."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from h2viz.config import Config
from h2viz.types import RgbdFrame

if TYPE_CHECKING:
    from h2viz.sources.base import FrameSource

log = logging.getLogger("h2viz.worker")
END = object()  # marks the end of the frame stream


@dataclass
class WorkerSettings:
    """What Commands of kind `set` may change while the worker runs."""

    realtime: bool = False  # play at the stream's rate; integrate every frame, optimise between frames
    stride: int = 1  # use every k-th frame of the source
    mesh_every: int = 5  # with mesh_update_hz = 0: mesh every this many frames (0 = when idle and at the end)
    mesh_update_hz: float = 4.0  # mesh after every frame; publish mesh changes at most this often (0 = no live)
    metrics_every: int = 20  # refresh ground-truth metrics every this many frames (0 = at the end)
    metrics_points: int = 20_000  # surface samples per mesh for the periodic metrics


class FrameFeed:
    """Reads frames on its own thread; every-frame mode queues two ahead, real-time mode plays at
    the frames' timestamp rate and keeps every frame that arrives until it is taken, up to `backlog` waiting
    frames: when that many wait, the oldest is dropped (counted in `dropped`, as are frames the reader was too
    slow to read in time). `start_after`: the source positions up to it are passed over without reading them (a
    resumed run mapped them; a frame's index is its position in the source), but count as read."""

    def __init__(
        self,
        source: FrameSource,
        settings: WorkerSettings,
        max_frames: int,
        backlog: int = 30,
        start_after: int = -1,
        prepare: Callable[[RgbdFrame], None] | None = None,
    ) -> None:
        """`prepare(frame)`: called on the reader thread for each frame that arrives in real-time mode, before it
        is queued (`Mapper.prepare_ahead`: the mapping thread then integrates it faster)."""
        self._source, self._settings, self._max_frames = source, settings, max_frames
        self._prepare = prepare
        self._backlog = max(1, int(backlog))
        self._items = list(enumerate(source.keys()))  # (position, key) before stride
        self._cond = threading.Condition()
        self._frames: deque[Any] = deque()
        self._stop = threading.Event()
        self._hold = threading.Event()  # set while mapping is paused (real-time clock stops)
        self.dropped = 0  # frames not delivered: passed_over + overflowed
        self.passed_over = 0  # real-time mode: due before the reader got to them (a slow source)
        self.overflowed = 0  # real-time mode: pushed out of a full backlog (integration fell behind)
        self.read = 0  # frames read or skipped so far
        self.arrived_at: dict[int, float] = {}  # real-time mode: frame index -> time.time() it joined the backlog
        self.preparing: tuple[int, int] | None = None  # (done, total) while the source prepares real-time playback
        self._prepared_stride = 0  # the stride real-time playback was prepared for (0: not prepared)
        self._position = 0
        self._pass_mapped(start_after)
        self._thread = threading.Thread(target=self._run, name="h2viz-frames", daemon=True)

    def _pass_mapped(self, last: int) -> None:
        """Move past the source positions up to `last` in steps of the stride, counting them as read."""
        stride = max(1, self._settings.stride)
        while self._position <= last and self._position < len(self._items):
            self._position += stride
            self.read += 1

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self._thread.join(timeout=5.0)

    def hold(self, on: bool) -> None:
        (self._hold.set if on else self._hold.clear)()

    def total(self) -> int:
        """Frames the stream will have read at the end with the current stride."""
        stride = max(1, self._settings.stride)
        remaining = math.ceil(max(0, len(self._items) - self._position) / stride)
        total = self.read + remaining
        return min(total, self._max_frames) if self._max_frames > 0 else total

    def ready(self) -> bool:
        """A frame (or the end of the stream) is waiting to be taken."""
        with self._cond:
            return bool(self._frames)

    def waiting(self) -> int:
        """How many frames (and the end of the stream) wait to be taken."""
        with self._cond:
            return len(self._frames)

    def frames_waiting(self) -> int:
        """How many frames wait to be taken (the end of the stream not counted)."""
        with self._cond:
            return len(self._frames) - (1 if self._frames and self._frames[-1] is END else 0)

    def take(self, timeout_s: float) -> Any:
        """The next frame, END when the stream is over, or None when nothing arrived in time."""
        with self._cond:
            if not self._cond.wait_for(lambda: bool(self._frames), timeout=timeout_s):
                return None
            item = self._frames.popleft()
            self._cond.notify_all()
            return item

    def _run(self) -> None:
        clock: tuple[float, float] | None = None  # (wall, stream) time pair of the last anchor
        try:
            while self._position < len(self._items) and not self._stop.is_set():
                if 0 < self._max_frames <= self.read:
                    break
                if self._prepare_playback():
                    clock = None  # the stream's clock starts after the preparation
                overdue = self._overdue(clock)  # behind the stream's clock: the next frame is due already
                item = self._items[self._position]
                self._position += max(1, self._settings.stride)
                self.read += 1
                if overdue:  # passed over without reading it
                    with self._cond:
                        self.dropped += 1
                        self.passed_over += 1
                    continue
                frame = self._source.get(*item)
                if frame is not None:
                    clock = self._deliver(frame, clock)
        except Exception:  # a broken source ends the stream; the worker reports it
            log.exception("reading frames failed; the stream ends here")
        with self._cond:
            self._frames.append(END)
            self._cond.notify_all()

    def _prepare_playback(self) -> bool:
        """Real-time mode, once per stride: have the source make the frames still to be played readable at the
        stream's rate (`FrameSource.prepare_playback`; `preparing` says how far it is). True when it prepared."""
        stride = max(1, self._settings.stride)
        if not self._settings.realtime or self._prepared_stride == stride:
            return False
        self._prepared_stride = stride
        keys = [key for _, key in self._items[self._position :: stride]]
        if self._max_frames > 0:
            keys = keys[: max(0, self._max_frames - self.read)]

        def progress(done: int, total: int) -> None:
            self.preparing = (done, total)

        def stop() -> bool:  # the feed stops, or real-time mode was switched off (prepared again when back on)
            return self._stop.is_set() or not self._settings.realtime

        try:
            self._source.prepare_playback(keys, progress, stop)
        except Exception:  # frames are then read as the stream goes: slower, never lost silently
            log.exception("preparing real-time playback failed; frames are read as they are due")
        finally:
            self.preparing = None
        if not self._settings.realtime:
            self._prepared_stride = 0
        return True

    def _overdue(self, clock: tuple[float, float] | None) -> bool:
        """Real-time playback whose reading fell behind (a slow source, or a rendered one): when the frame a whole
        backlog after the current one is due already by the stream's clock, the current one would be pushed out of
        the backlog anyway, and is passed over without reading it (sources that know timestamps before loading; the
        others are read and then dropped). A reader that is merely late (its thread waited for the CPU) still
        delivers every frame."""
        if not self._settings.realtime or clock is None or self._hold.is_set():
            return False
        following = self._position + self._backlog * max(1, self._settings.stride)
        if following >= len(self._items):
            return False
        due = self._source.timestamp(*self._items[following])
        return due is not None and due <= clock[1] + (time.monotonic() - clock[0])

    def _deliver(self, frame: RgbdFrame, clock: tuple[float, float] | None) -> tuple[float, float] | None:
        if not self._settings.realtime:
            with self._cond:
                self._cond.wait_for(lambda: len(self._frames) < 2 or self._stop.is_set())
                self._frames.append(frame)
                self._cond.notify_all()
            return None
        while self._hold.is_set() and not self._stop.is_set():
            clock = None
            self._stop.wait(0.05)
        if clock is None:
            clock = (time.monotonic(), frame.timestamp)
        self._stop.wait(max(0.0, clock[0] + (frame.timestamp - clock[1]) - time.monotonic()))
        if self._prepare is not None:  # the frame has arrived: its preparation overlaps the frames before it
            try:
                self._prepare(frame)
            except Exception:  # integrating it reports the problem with the frame's name
                log.debug("preparing frame %d ahead failed", frame.index, exc_info=True)
        with self._cond:
            while len(self._frames) >= self._backlog and self._frames[0] is not END:
                self._frames.popleft()  # integration fell a whole backlog behind the stream
                self.dropped += 1
                self.overflowed += 1
            self._frames.append(frame)
            self.arrived_at[frame.index] = time.time()
            self._cond.notify_all()
        return clock


def realtime_from_config(cfg: Config) -> bool:
    """Real-time mode (source.realtime; `--realtime` and the dashboard's toggle set it)."""
    return cfg.source.realtime


def settings_from_config(cfg: Config) -> WorkerSettings:
    return WorkerSettings(
        realtime=realtime_from_config(cfg),
        stride=max(1, cfg.source.stride),
        mesh_every=cfg.mapping.meshing.mesh_every,
        mesh_update_hz=cfg.viewer.mesh_update_hz,
    )
