"""Autosave of a run: the mapping state written to <run folder>/autosave.pt every N frames or M seconds (atomically,
so a process killed mid-write leaves the previous autosave intact), finding the newest checkpoint of a run
folder to resume from, and the dashboard's offer to resume the earlier run a folder holds."""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from h2viz.config import AutosaveConfig
from h2viz.errors import CheckpointError
from h2viz.types import FrameStats

if TYPE_CHECKING:
    from h2viz.mapping.mapper import Mapper

log = logging.getLogger("h2viz.autosave")
Writer = Callable[[Any, Path, dict[str, Any]], Any]
Preparer = Callable[[Any, dict[str, Any]], Callable[[Path], Any]]
AUTOSAVE_NAME = "autosave.pt"


def find_checkpoint(path: str | Path) -> Path:
    """`path` itself when it is a checkpoint file; for a run folder, its newest checkpoint (*.pt: autosave.pt,
    checkpoint.pt, the dashboard's checkpoint_<time>.pt), by modification time."""
    path = Path(path)
    if path.is_file():
        return path
    if not path.is_dir():
        raise CheckpointError(f"{path} does not exist; pass a run folder or a checkpoint .pt file to --resume")
    found = sorted(path.glob("*.pt"), key=lambda p: (p.stat().st_mtime, p.name))
    if not found:
        raise CheckpointError(f"{path} holds no checkpoint (*.pt); pass the folder of a run that autosaved")
    return found[-1]


def run_progress(path: Path, extra: dict[str, Any]) -> tuple[int, list[FrameStats]]:
    """From a checkpoint's `extra`: the index of the last frame mapped (-1: none) and the stats of the frames mapped."""
    try:
        stats = [FrameStats(**s) for s in extra.get("stats", [])]
        return int(extra.get("last_index", -1)), stats
    except (TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: its frame statistics do not match this version ({e})") from None


def run_state(last_index: int, stats: list[FrameStats] | Iterable[FrameStats]) -> dict[str, Any]:
    """The `extra` of a run's checkpoint: where to continue and the frames' stats (the inverse of run_progress)."""
    return {"last_index": int(last_index), "stats": [dataclasses.asdict(s) for s in stats]}


def keep_earlier_autosave(folder: str | Path) -> Path | None:
    """Before a fresh run autosaves into `folder`: rename an earlier run's autosave.pt there to
    autosave_<its time>.pt, so the new run never overwrites it; the new name, or None when there was none."""
    path = Path(folder) / AUTOSAVE_NAME
    if not path.is_file():
        return None
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(path.stat().st_mtime))
    kept = path.with_name(f"autosave_{stamp}.pt")
    n = 1
    while kept.exists():
        kept, n = path.with_name(f"autosave_{stamp}_{n}.pt"), n + 1
    path.rename(kept)
    return kept


@dataclasses.dataclass(frozen=True)
class ResumeOffer:
    """An earlier run's checkpoint in the run folder, which the dashboard offers to continue."""

    path: Path
    frames: int  # frames that run mapped
    last_index: int  # the index of its last mapped frame: mapping goes on after it
    saved_at: float  # the file's modification time (time.time())

    def label(self) -> str:
        """The resume button's text."""
        saved = time.strftime("%Y-%m-%d %H:%M", time.localtime(self.saved_at))
        return f"Resume earlier run ({self.frames} frames, saved {saved})"

    def notice(self) -> str:
        """What a browser that connects is told while the offer stands."""
        return (
            f"The run folder holds an earlier run's checkpoint, {self.path} ({self.frames} frames). This run starts "
            'fresh; press "Resume earlier run" in the Mapping tab to continue that one instead.'
        )


def earlier_run(folder: str | Path) -> tuple[ResumeOffer | None, str | None]:
    """The newest checkpoint in `folder` as a ResumeOffer (None when it holds none, or one of no frames); or, when that
    checkpoint cannot be resumed (damaged, of another format, without the frame it ended at), None and the message
    that says so."""
    from h2viz.mapping.checkpoint import peek_checkpoint

    try:
        path = find_checkpoint(folder)
    except CheckpointError:
        return None, None
    try:
        frames, extra = peek_checkpoint(path)
        last_index, _ = run_progress(path, extra)
        if frames > 0 and "last_index" not in extra:
            raise CheckpointError(f"{path} does not say which frame its run ended at, so it cannot be continued")
    except CheckpointError as e:
        log.warning("the earlier run cannot be resumed: %s", e)
        return (
            None,
            f"An earlier run's checkpoint cannot be resumed: {e}. This run starts fresh; the file is left as it is.",
        )
    if frames == 0:  # nothing to continue
        return None, None
    return ResumeOffer(path, frames, last_index, path.stat().st_mtime), None


class Autosaver:
    """Writes the run folder's autosave.pt when `autosave.every_frames` frames or `autosave.every_s` seconds have
    passed since the last one. A failed write (disk full, folder gone) is logged and reported, never raised: the
    map stays in memory and the previous autosave stays valid.

    Due autosaves (`maybe_save`) are written in the background: the mapping thread only takes the state
    (`prepare_checkpoint`), a thread writes it while mapping goes on. While a live stream plays (`streaming`), they
    come by time alone (every_frames counts frames at the pace of every-frame mapping: at 30 Hz, 50 frames pass in
    under 2 s, less than a write takes). One write runs at a time; any other save waits for it first."""

    def __init__(
        self,
        folder: Path,
        cfg: AutosaveConfig,
        frames_done: int = 0,
        clock: Callable[[], float] = time.monotonic,
        writer: Writer | None = None,
        prepare: Preparer | None = None,
    ) -> None:
        """`frames_done`: the frames mapped before this run (a resumed run's), where counting starts; `writer`
        (mapper, path, extra) writes the checkpoint (default: save_checkpoint); `prepare` (mapper, extra) takes
        the state and returns what writes it to a path, on another thread (default: prepare_checkpoint; with only a
        `writer`, the writer itself runs on that thread)."""
        self.path = Path(folder) / AUTOSAVE_NAME
        self.cfg, self._clock, self._writer, self._prepare = cfg, clock, writer, prepare
        self._last_frames = frames_done
        self._last_t = clock()
        self.saves = 0
        self.last_error: str | None = None
        self._thread: threading.Thread | None = None  # a background write in progress
        self._unreported: str | None = None  # a background write's failure, until maybe_save reports it

    @property
    def enabled(self) -> bool:
        return self.cfg.every_frames > 0 or self.cfg.every_s > 0

    @property
    def writing(self) -> bool:
        """A background write is in progress."""
        return self._thread is not None and self._thread.is_alive()

    def restart(self, frames_done: int) -> None:
        """Count from `frames_done` mapped frames and from now (the worker took over another run's map)."""
        self._last_frames, self._last_t = frames_done, self._clock()

    def behind(self, frames_done: int) -> bool:
        """Frames were mapped since the last autosave (or since the start): saving now would keep them."""
        return self.enabled and frames_done > self._last_frames

    def due(self, frames_done: int, streaming: bool = False) -> bool:
        """Whether an autosave is due after `frames_done` mapped frames (by time alone while `streaming`)."""
        by_frames = (
            not streaming and self.cfg.every_frames > 0 and frames_done - self._last_frames >= self.cfg.every_frames
        )
        by_time = self.cfg.every_s > 0 and self._clock() - self._last_t >= self.cfg.every_s
        return frames_done > self._last_frames and (by_frames or by_time)

    def save(self, mapper: Mapper, frames_done: int, extra: dict[str, Any], background: bool = False) -> str | None:
        """Write the autosave now (`background`: take the state now, write it on a thread); None, or the message of
        a failed write (a background one's comes from a later `maybe_save`). Waits for a write in progress."""
        from h2viz.mapping.checkpoint import prepare_checkpoint, save_checkpoint

        earlier = self.wait()  # the previous write's failure, if it failed
        self._last_frames, self._last_t = frames_done, self._clock()
        try:
            if not background:
                (self._writer or save_checkpoint)(mapper, self.path, extra)
                return self._done(None)
            write = self._preparer(prepare_checkpoint)(mapper, extra)
        except (CheckpointError, OSError) as e:
            return self._done(e)
        self._thread = threading.Thread(target=self._write, args=(write,), name="h2viz-autosave", daemon=True)
        self._thread.start()
        return earlier

    def _preparer(self, default: Preparer) -> Preparer:
        """`prepare`; else, with a `writer`, one that leaves the writing to it; else `default`."""
        if self._prepare is not None:
            return self._prepare
        writer = self._writer
        if writer is not None:
            return lambda mapper, extra: lambda path: writer(mapper, path, extra)
        return default

    def _write(self, write: Callable[[Path], Any]) -> None:
        """(autosave thread) Write a prepared state; a failure waits for `maybe_save` to report it."""
        try:
            write(self.path)
            self._done(None)
        except Exception as e:  # noqa: BLE001 - the thread must not die silently: report whatever failed
            self._unreported = self._done(e)

    def _done(self, error: Exception | None) -> str | None:
        if error is None:
            self.saves += 1
            self.last_error = None
            return None
        self.last_error = f"autosave failed: {error}; mapping goes on, the previous autosave is kept"
        log.error("%s", self.last_error)
        return self.last_error

    def wait(self) -> str | None:
        """Wait for a background write in progress; None, or the message of its failure (once)."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        failed, self._unreported = self._unreported, None
        return failed

    def maybe_save(
        self,
        mapper: Mapper,
        frames_done: int,
        extra: Callable[[], dict[str, Any]],
        streaming: bool = False,
    ) -> str | None:
        """`save` in the background when one is due (`extra` is called only then); None, or the message of a failed
        write (a finished background write's first). `streaming`: due by time alone, and none while a write is in
        progress (the stream must not wait for it). Outside a stream a due autosave waits for a write in progress,
        so autosaves come at the same frames either way."""
        if not self.writing and self._unreported is not None:
            return self.wait()
        if not self.enabled or (streaming and self.writing) or not self.due(frames_done, streaming):
            return None
        return self.save(mapper, frames_done, extra(), background=True)
