"""The anytime schedule against a fake clock (no wall-clock time is measured): every frame of a 30 Hz stream is
integrated, optimisation steps fill the time between frames and keep their share when frames come faster than
both fit; continued optimisation after the stream stops once the loss plateaus; the run autosaves on schedule and
at the end of the stream."""

from __future__ import annotations

import math
from collections import deque
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from h2viz.config import AnytimeConfig, AutosaveConfig
from h2viz.errors import ConfigError
from h2viz.mapping.anytime import Action, AnytimeSchedule, FusionStride, Phase, Plateau, check_anytime
from h2viz.mapping.autosave import Autosaver
from h2viz.types import FrameStats
from h2viz.worker.anytime_run import AnytimeRun
from h2viz.worker.feed import END


def simulate(
    n_frames: int,
    rate_hz: float,
    integrate_s: float,
    step_s: float,
    share: float,
    catch_up: int = 3,
    backlog: int = 30,
) -> tuple[AnytimeSchedule, list[str], list[float], int]:
    """Drive the schedule with frames arriving at `rate_hz`, fixed costs and a feed that keeps `backlog` frames
    (older ones dropped, as FrameFeed does); returns the schedule, the actions in order, each integrated frame's
    delay from arrival to the end of its integration, and the frames dropped."""
    schedule = AnytimeSchedule(share, catch_up, backlog)
    arrivals = [i / rate_hz for i in range(n_frames)]
    now, nxt, log, delays, dropped = 0.0, 0, [], [], 0
    while nxt < n_frames:
        arrived = sum(1 for t in arrivals if t <= now)
        if arrived - nxt > backlog:  # the feed pushes the oldest out of a full backlog
            dropped += arrived - nxt - backlog
            nxt = arrived - backlog
        waiting = arrived - nxt
        action = schedule.next(waiting, can_step=nxt > 0)
        if action is Action.INTEGRATE:
            now += integrate_s
            schedule.did_integrate(integrate_s)
            delays.append(now - arrivals[nxt])
            nxt += 1
        elif action is Action.STEP:
            now += step_s
            schedule.did_step(step_s)
        else:  # nothing integrated yet and no frame: wait for the next one
            now = arrivals[nxt]
        log.append(action.value)
    return schedule, log, delays, dropped


def test_every_frame_is_integrated_and_steps_fill_the_time_between() -> None:
    schedule, log, delays, dropped = simulate(300, 30.0, integrate_s=0.02, step_s=0.03, share=0.25)
    assert schedule.integrated == 300 and dropped == 0
    assert max(delays) < 0.02 + 0.03 + 0.02 + 1e-9  # at most one step (and one frame) in the way of a frame
    # 10 s of stream, 6 s of it integration: the other 4 s are steps
    assert 4.0 / 0.03 - 3 <= schedule.steps <= 4.0 / 0.03 + 3
    assert log.count("step") == schedule.steps


def test_a_stream_integration_barely_keeps_up_with_loses_no_frame_and_still_gets_steps() -> None:
    # integration takes 90 % of the stream's time and a step three frame times: the share alone would let the
    # backlog grow until it drops frames; catching up keeps every frame, and steps use the time left
    schedule, log, delays, dropped = simulate(600, 30.0, integrate_s=0.03, step_s=0.1, share=0.25)
    assert schedule.integrated == 600 and dropped == 0
    assert schedule.steps >= 0.8 * (20.0 - 600 * 0.03) / 0.1  # most of the 2 s left over went to steps
    assert max(delays) < 4 * (1 / 30.0) + 0.1 + 0.03 + 1e-9  # catch_up frames and one step in the way at most
    without, _, _, lost = simulate(600, 30.0, integrate_s=0.03, step_s=0.1, share=0.25, catch_up=10**6)
    assert lost > 0  # the share alone drops frames here


def test_optimisation_keeps_a_share_when_integration_alone_cannot_keep_up() -> None:
    # integration takes longer than a frame: catching up fails, the backlog fills and frames are dropped whatever
    # the schedule does; from then on steps come every few frames and keep a real share of the time
    schedule, log, delays, dropped = simulate(600, 30.0, integrate_s=0.04, step_s=0.05, share=0.25)
    assert dropped > 0
    assert 0.1 < schedule.step_s / (schedule.step_s + schedule.integrate_s) <= 0.25 + 1e-9
    runs = [len(r) for r in "".join("i" if a == "integrate" else "s" for a in log).split("s")]
    catching_up = int(np.argmax(runs))  # the stretch spent trying to catch up, until the backlog was full
    assert runs[catching_up] <= 30 / (0.04 * 30.0 - 1) + 1  # as long as the backlog takes to fill, no longer
    assert max(runs[catching_up + 1 : -2]) <= 8  # never starved after it (until the stream ends: the backlog drains)


def test_integration_is_never_held_up_by_free_steps() -> None:
    schedule = AnytimeSchedule(0.5)
    for _ in range(100):  # a long quiet stretch of steps banks nothing
        schedule.did_step(0.05)
    assert schedule.next(1, can_step=True) is Action.INTEGRATE
    schedule.did_integrate(0.04)
    assert schedule.next(1, can_step=True) is Action.STEP  # 0.04 s owed at a half share
    schedule.did_step(0.05)
    assert schedule.next(1, can_step=True) is Action.INTEGRATE
    assert schedule.next(0, can_step=False) is Action.WAIT


def test_plateau_waits_while_the_loss_falls_and_stops_once_it_is_flat() -> None:
    rng = np.random.default_rng(0)
    plateau = Plateau(window=20, patience=3, tol=0.01)
    steps = 0
    for t in range(4000):
        loss = (1.0 + 2.0 * math.exp(-t / 150.0)) * (1.0 + 0.05 * rng.standard_normal())  # noisy, then flat
        steps += 1
        if plateau.add(loss):
            break
    # the mean falls by >1 % a window until t ~ 150 * ln(2 * 20 / (0.01 * 1.0 * 150)) ~ 500, then three windows
    assert 400 <= steps <= 1100


class CountingMapper:
    """What AnytimeRun.sharpen calls: refinement steps whose loss falls to a floor."""

    def __init__(self, keyframes: int = 3) -> None:
        self.keyframe_rays = list(range(keyframes))
        self.steps = 0

    def refine_step(self) -> float:
        self.steps += 1
        return float("nan") if not self.keyframe_rays else 1.0 + 10.0 / self.steps


class FakeClock:
    def __init__(self, tick_s: float) -> None:
        self.now, self.tick_s = 0.0, tick_s

    def __call__(self) -> float:
        self.now += self.tick_s  # every reading advances: each step "takes" two ticks
        return self.now


def sharpener(mapper: CountingMapper, **cfg: float) -> AnytimeRun:
    run = AnytimeRun(mapper, feed=None, cfg=AnytimeConfig(plateau_window=10, **cfg), clock=FakeClock(0.01))  # type: ignore[arg-type]
    run.totals.phase = Phase.SHARPENING.value
    return run


def test_sharpening_after_the_stream_stops_when_the_loss_plateaus() -> None:
    mapper = CountingMapper()
    run = sharpener(mapper)
    assert not run.sharpen(seconds=0.5)  # still improving after 0.5 s (fake): goes on when asked again
    assert run.totals.phase == Phase.SHARPENING.value and 0 < mapper.steps < 100
    assert run.sharpen()  # until the plateau
    assert run.settled and run.plateau.settled
    assert 100 < mapper.steps < 3000 and run.totals.sharpen_steps == mapper.steps
    assert run.sharpen() and mapper.steps == run.totals.sharpen_steps  # settled: no more steps


def test_sharpening_stops_at_its_time_limit_the_user_or_without_keyframes() -> None:
    limited = sharpener(CountingMapper(), sharpen_max_s=1.0)
    assert limited.sharpen() and limited.totals.sharpen_s == pytest.approx(1.0, abs=0.05)
    stopped = sharpener(CountingMapper())
    assert not stopped.sharpen(stop=lambda: True) and stopped.totals.phase == Phase.STOPPED.value
    empty = sharpener(CountingMapper(keyframes=0))
    assert empty.sharpen() and empty.totals.sharpen_steps == 1


def test_bad_settings_name_the_field() -> None:
    with pytest.raises(ConfigError, match="anytime.opt_share"):
        check_anytime(AnytimeConfig(opt_share=1.0))
    with pytest.raises(ConfigError, match="anytime.backlog_frames"):
        check_anytime(AnytimeConfig(backlog_frames=0))
    with pytest.raises(ConfigError, match="anytime.fine_prior_stride"):
        check_anytime(AnytimeConfig(fine_prior_stride=0))


def test_frames_fuse_every_lattice_unless_others_wait_and_then_every_kth() -> None:
    waiting = [0, 0, 3, 2, 5, 4, 3, 0, 1, 1, 1, 1, 0]
    assert [FusionStride(1).fuse_all(w) for w in waiting] == [True] * len(waiting)
    two = FusionStride(2)
    assert [two.fuse_all(w) for w in waiting] == [
        True, True, False, True, False, True, False, True, False, True, False, True, True,
    ]  # fmt: skip
    assert two.thinned == 5
    three = FusionStride(3)
    assert [three.fuse_all(w) for w in waiting] == [
        True, True, False, False, True, False, False, True, False, False, True, False, True,
    ]  # fmt: skip


class ArrivedFeed:
    """A FrameFeed stand-in whose frames have all arrived: each is there to take, then the end of the stream."""

    dropped = passed_over = overflowed = 0

    def __init__(self, indices: range) -> None:
        self.items: deque[object] = deque([*(SimpleNamespace(index=i) for i in indices), END])

    def ready(self) -> bool:
        return bool(self.items)

    def waiting(self) -> int:
        return len(self.items)

    def frames_waiting(self) -> int:
        return len(self.items) - (1 if self.items and self.items[-1] is END else 0)

    def take(self, timeout_s: float) -> object:
        return self.items.popleft() if self.items else None


class IntegratingMapper(CountingMapper):
    """What AnytimeRun.stream calls: frames integrated at once and live steps."""

    def __init__(self) -> None:
        super().__init__()
        self.fused_all: list[bool] = []  # each frame's add_frame(fuse_all=...)

    def add_frame(
        self, frame: SimpleNamespace, color_points: int, observed_points: int, fuse_all: bool = True
    ) -> FrameStats:
        self.fused_all.append(fuse_all)
        return FrameStats(frame.index, 0.01, 0, 1, 1)

    def live_step(self) -> float:
        self.steps += 1
        return 1.0


def autosaved_run(every_s: float, fail: bool = False) -> tuple[AnytimeRun, list[tuple[int, int, float]]]:
    """A resumed run (frames 0-2 mapped before) streaming frames 3-22 under a fake clock, autosaving every `every_s`
    (fake) seconds; the run and its autosaves: (frames in it, its last frame, when). `fail`: every write fails."""
    clock = FakeClock(0.01)
    saves: list[tuple[int, int, float]] = []

    def writer(mapper: object, path: Path, extra: dict) -> None:
        if fail:
            raise OSError(28, "No space left on device")
        saves.append((len(extra["stats"]), extra["last_index"], clock.now))

    earlier = [FrameStats(i, 0.01, 0, 1, 1) for i in range(3)]
    saver = Autosaver(Path("/nonexistent"), AutosaveConfig(every_frames=0, every_s=every_s), 3, clock, writer)
    run = AnytimeRun(IntegratingMapper(), ArrivedFeed(range(3, 23)), AnytimeConfig(), clock, saver, earlier)  # type: ignore[arg-type]
    run.stream()
    return run, saves


def test_a_realtime_run_autosaves_every_m_seconds_and_when_the_stream_ends() -> None:
    run, saves = autosaved_run(0.1)
    assert run.totals.integrated == 20 and not run.errors
    assert len(saves) >= 3 and saves[-1][:2] == (23, 22)  # the last autosave holds every frame, the earlier ones too
    assert all(last == n - 1 for n, last, _ in saves)  # each holds the frames up to the one just integrated
    assert (np.diff([n for n, _, _ in saves]) > 0).all()  # never twice the same frames
    assert (np.diff([t for _, _, t in saves[:-1]]) >= 0.1 - 1e-9).all()  # due by time; the last one at the end


def test_frames_integrated_while_others_wait_fuse_every_lattice_every_fourth_frame() -> None:
    run = AnytimeRun(IntegratingMapper(), ArrivedFeed(range(9)), AnytimeConfig(), FakeClock(0.01))  # type: ignore[arg-type]
    run.stream()
    assert AnytimeConfig().fine_prior_stride == 4
    assert run.mapper.fused_all == [False, False, False, True] * 2 + [True]  # the last: no frame waits
    assert run.totals.thinned == 6 and run.totals.integrated == 9


def test_a_failing_autosave_of_a_realtime_run_is_reported_once_and_mapping_goes_on() -> None:
    run, _ = autosaved_run(0.05, fail=True)
    assert run.totals.integrated == 20 and len(run.stats) == 20
    assert run.errors == [
        "autosave failed: [Errno 28] No space left on device; mapping goes on, the previous autosave is kept"
    ]
