"""Serving viewer Commands on the mapping thread: pause / resume / step, live settings, exports, checkpoints (with
the run state, so that they can be resumed) and taking over an earlier run at once; renders as row-band jobs
advanced round robin within a time budget, so they interleave with mapping instead of stalling it."""

from __future__ import annotations

import logging
import queue
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

from h2viz.config import Config
from h2viz.errors import H2vizError
from h2viz.types import Command, FrameStats
from h2viz.worker import requests
from h2viz.worker.feed import FrameFeed, WorkerSettings

if TYPE_CHECKING:
    from h2viz.mapping.mapper import Mapper

log = logging.getLogger("h2viz.worker")
COMMANDS = ("pause", "resume", "step", "set", "render", "export", "save", "refine", "resume_run")


class CommandServing:
    """The command half of MappingWorker (which provides the state declared here)."""

    mapper: Mapper
    cfg: Config
    settings: WorkerSettings
    _feed: FrameFeed
    _commands: queue.Queue[Command]
    _renders: deque[tuple[Command, Any]]  # (command, row-band generator)
    _steps: deque[Future[Any]]
    _paused: bool
    _finished: bool
    _mesh_dirty: bool
    _last_map_s: float
    _refine_left: int
    _stats: deque[FrameStats]

    def _publish(self) -> None:
        raise NotImplementedError

    def _remesh(self) -> None:
        raise NotImplementedError

    def _idle(self) -> bool:
        raise NotImplementedError

    def _between_steps(self) -> None:
        raise NotImplementedError

    def _autosave_extra(self) -> dict[str, Any]:
        """The run state a checkpoint carries: where to continue and the frames' stats."""
        raise NotImplementedError

    def _resume_run(self, args: dict[str, Any]) -> str:
        """Continue the run of the checkpoint args["path"] instead of this one."""
        raise NotImplementedError

    def _on_request_failure(self, kind: str, error: Exception) -> None:
        """A request failed for a reason other than a bad request (H2vizError): make it visible, keep the work."""
        raise NotImplementedError

    def _queue_refinement(self, args: dict[str, Any]) -> int:
        """Queue `steps` refinement steps (Mapper.refine), run while mapping is paused or finished; the steps
        now queued."""
        steps = int(args.get("steps", 0))
        if steps <= 0:
            raise H2vizError(f"refine: steps must be a positive number, got {args.get('steps')!r}")
        if not self._stats:
            raise H2vizError("refine: nothing is mapped yet; map some frames first")
        self._refine_left += steps
        self._publish()
        return self._refine_left

    def _serve_commands(self, timeout_s: float) -> None:
        try:
            cmd = self._commands.get(timeout=timeout_s) if timeout_s > 0 else self._commands.get_nowait()
        except queue.Empty:
            return
        while True:
            try:
                self._handle(cmd)
            except Exception as e:  # a bad request fails its own Future, never the worker
                log.warning("command %s failed: %s", cmd.kind, e)
                requests.settle(cmd.reply, error=e)
                if not isinstance(e, H2vizError):
                    self._on_request_failure(cmd.kind, e)
            try:
                cmd = self._commands.get_nowait()
            except queue.Empty:
                return

    def _handle(self, cmd: Command) -> None:
        handlers: dict[str, Callable[[dict[str, Any]], Any]] = {
            "pause": lambda a: self._set_paused(True),
            "resume": lambda a: self._set_paused(False),
            "set": self._apply_settings,
            "export": self._export,
            "save": lambda a: requests.save_checkpoint(self.mapper, a["path"], self._autosave_extra()),
            "refine": self._queue_refinement,
            "resume_run": self._resume_run,
        }
        if cmd.kind == "render":
            self._renders.append((cmd, requests.render_bands(self.mapper, cmd.args)))
        elif cmd.kind == "step":
            self._step(cmd.reply)
        elif cmd.kind in handlers:
            requests.settle(cmd.reply, handlers[cmd.kind](cmd.args))
        else:
            raise H2vizError(f"unknown command '{cmd.kind}'; use one of {', '.join(COMMANDS)}")

    def _export(self, args: dict[str, Any]) -> bytes:
        """The mesh at the full resolution of cfg.mapping (the live mesh is re-meshed whole when it has it)."""
        resolution = self.cfg.mapping.meshing.mesh_resolution
        if resolution == self.mapper.meshing_resolution:  # the live mesh is at that resolution now
            self._remesh()
        return requests.export_mesh_bytes(self.mapper, str(args.get("format", "ply")), resolution)

    def _set_paused(self, paused: bool) -> bool:
        self._paused = paused
        self._feed.hold(paused and not self._steps)
        self._publish()
        return paused

    def _step(self, reply: Future[Any]) -> None:
        if self._finished:
            requests.settle(reply, None)
            return
        self._steps.append(reply)
        self._feed.hold(False)

    def _apply_settings(self, args: dict[str, Any]) -> dict[str, Any]:
        if requests.apply_settings(self.settings, self.mapper, args):
            self._mesh_dirty = True
        return requests.settings_reply(self.settings, self.mapper)

    def _render_slices(self) -> None:
        """Advance pending renders band by band (round robin) within a time budget that keeps
        mapping going: about as long as the last frame took to map."""
        # between frames; in real-time mode a short slice, since frames arrive every ~33 ms
        budget = 0.25 if self._idle() else max(0.02 if self.settings.realtime else 0.1, self._last_map_s)
        deadline = time.perf_counter() + budget
        while self._renders and time.perf_counter() < deadline:
            cmd, job = self._renders[0]
            if cmd.reply.cancelled():
                self._renders.popleft()
                continue
            try:
                next(job)
                self._renders.rotate(-1)
                self._between_steps()  # a mesh job waiting for the mesh thread goes now, not after the renders
            except StopIteration as done:
                self._renders.popleft()
                requests.settle(cmd.reply, done.value)
            except Exception as e:
                self._renders.popleft()
                log.warning("render failed: %s", e)
                requests.settle(cmd.reply, error=e)
                if not isinstance(e, H2vizError):
                    self._on_request_failure("render", e)

    def _fail_pending(self, error: BaseException) -> None:
        for cmd, _ in self._renders:
            requests.settle(cmd.reply, error=error)
        self._renders.clear()
        while self._steps:
            requests.settle(self._steps.popleft(), error=error)
        while True:
            try:
                requests.settle(self._commands.get_nowait().reply, error=error)
            except queue.Empty:
                return
