"""Headless anytime mapping of a live-paced stream (`h2viz map --realtime`, bench/realtime.py): every frame the
feed delivers is integrated, optimisation steps fill the time between frames, and after the stream ends the map
keeps sharpening until its loss plateaus (h2viz.mapping.anytime). The run autosaves as every-frame runs do
(autosave.*), and once more when the stream ends, before the sharpening. The dashboard's worker runs the same
schedule inside its own loop, between commands and renders."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from h2viz.config import AnytimeConfig
from h2viz.mapping.anytime import Action, AnytimeSchedule, FusionStride, Phase, check_anytime, plateau_from
from h2viz.mapping.autosave import Autosaver, run_state
from h2viz.types import FrameStats, RgbdFrame
from h2viz.worker.feed import END, FrameFeed

if TYPE_CHECKING:
    from h2viz.mapping.mapper import Mapper

Clock = Callable[[], float]


@dataclass
class AnytimeTotals:
    """What an anytime run did: frames integrated and dropped, optimisation steps and their seconds."""

    integrated: int = 0
    dropped: int = 0  # passed_over + overflowed
    passed_over: int = 0  # due before the reader could read them (a slow source)
    overflowed: int = 0  # pushed out of a full backlog (integration fell behind)
    thinned: int = 0  # integrated while others waited: fused into their new voxels' fine lattices only
    stream_steps: int = 0  # steps while the stream ran
    sharpen_steps: int = 0  # steps after it ended
    sharpen_s: float = 0.0
    phase: str = Phase.STREAMING.value

    @property
    def arrived(self) -> int:
        return self.integrated + self.dropped


class AnytimeRun:
    """Runs `mapper` over `feed` (a started FrameFeed in real-time mode) under the anytime schedule."""

    def __init__(
        self,
        mapper: Mapper,
        feed: FrameFeed,
        cfg: AnytimeConfig,
        clock: Clock = time.perf_counter,
        autosave: Autosaver | None = None,
        earlier: list[FrameStats] | None = None,
    ) -> None:
        """`autosave`: writes the run folder's autosave (None: none); `earlier`: the stats of the frames a resumed
        run mapped before, which the autosaves carry ahead of this run's."""
        check_anytime(cfg)
        self.mapper, self.feed, self.cfg, self.clock = mapper, feed, cfg, clock
        self.autosave, self.earlier = autosave, list(earlier or [])
        self.schedule = AnytimeSchedule(cfg.opt_share, cfg.catch_up_frames, cfg.backlog_frames)
        self.fusion = FusionStride(cfg.fine_prior_stride)
        self.plateau = plateau_from(cfg)
        self.stats: list[FrameStats] = []
        self.totals = AnytimeTotals()
        self.losses: list[float] = []  # every step's loss, in order
        self.errors: list[str] = []  # failed autosaves (mapping went on)
        self._newest_steps = 0

    def stream(self, on_frame: Callable[[RgbdFrame], bool] | None = None) -> None:
        """Integrate every frame until the stream ends (or Ctrl-C), stepping in between; `on_frame` sees each frame
        as it arrives and returns whether to integrate it (a resumed run passes over frames it mapped before). The
        frames integrated since the last autosave are autosaved at the end."""
        try:
            while True:
                action = self.schedule.next(self.feed.waiting(), bool(self.stats))
                if action is Action.STEP:
                    self._step(self.mapper.live_step)
                    continue
                item = self.feed.take(0.05 if action is Action.WAIT else 1.0)
                if item is END:
                    break
                if item is None:
                    continue
                if on_frame is None or on_frame(item):
                    self._integrate(item)
        finally:
            self._close_newest()
            self.totals.dropped = self.feed.dropped
            self.totals.passed_over, self.totals.overflowed = self.feed.passed_over, self.feed.overflowed
            self.totals.phase = Phase.SHARPENING.value
            self._autosave(at_end=True)

    def sharpen(self, seconds: float | None = None, stop: Callable[[], bool] | None = None) -> bool:
        """Optimise over the keyframes after the stream, for up to `seconds` more (None: until the loss plateaus,
        anytime.sharpen_max_s is reached or `stop` says so). True once the optimisation has settled."""
        start = self.clock()
        while not self.settled:
            if seconds is not None and self.clock() - start >= seconds:
                return False
            if stop is not None and stop():
                self.totals.phase = Phase.STOPPED.value
                return False
            t0 = self.clock()
            loss = self._step(self.mapper.refine_step)
            self.totals.sharpen_steps += 1
            self.totals.sharpen_s += self.clock() - t0
            if not math.isfinite(loss) and not self.mapper.keyframe_rays:
                self.totals.phase = Phase.SETTLED.value  # nothing to optimise
            elif self.plateau.add(loss) or self._out_of_time():
                self.totals.phase = Phase.SETTLED.value
        return True

    @property
    def settled(self) -> bool:
        return self.totals.phase == Phase.SETTLED.value

    def _out_of_time(self) -> bool:
        return self.cfg.sharpen_max_s <= 0 or self.totals.sharpen_s >= self.cfg.sharpen_max_s

    def _integrate(self, frame: RgbdFrame) -> None:
        self._close_newest()
        t0 = self.clock()
        fuse_all = self.fusion.fuse_all(self.feed.frames_waiting())
        stats = self.mapper.add_frame(frame, self.cfg.color_points, self.cfg.observed_points, fuse_all)
        self.schedule.did_integrate(self.clock() - t0)
        self.stats.append(stats)
        self.totals.integrated += 1
        self.totals.thinned = self.fusion.thinned
        self._autosave()

    @property
    def frames_done(self) -> int:
        """Frames mapped, with those of the run resumed."""
        return len(self.earlier) + len(self.stats)

    def run_state(self) -> dict[str, Any]:
        """A checkpoint's run state: the last integrated frame and every frame's stats (as `h2viz map` writes)."""
        return run_state(self.stats[-1].index, [*self.earlier, *self.stats])

    def _autosave(self, at_end: bool = False) -> None:
        """Autosave when one is due, or (`at_end`) when frames were integrated since the last one; a failed write
        is noted in `errors`."""
        saver = self.autosave
        if saver is None or not self.stats:
            return
        if not at_end:  # frames arriving: by time, written in the background
            failed = saver.maybe_save(self.mapper, self.frames_done, self.run_state, streaming=True)
        elif saver.behind(self.frames_done):
            failed = saver.save(self.mapper, self.frames_done, self.run_state())
        else:
            failed = saver.wait()
        if failed is not None and failed not in self.errors:
            self.errors.append(failed)

    def _step(self, step: Callable[[], float]) -> float:
        t0 = self.clock()
        loss = step()
        self.schedule.did_step(self.clock() - t0)
        self.losses.append(loss)
        if self.totals.phase == Phase.STREAMING.value:
            self.totals.stream_steps += 1
            self._newest_steps += 1
        return loss

    def _close_newest(self) -> None:
        """The newest frame's stats get the steps taken while it was the newest."""
        if self.stats and self._newest_steps:
            self.stats[-1] = replace(self.stats[-1], iterations=self._newest_steps)
        self._newest_steps = 0
