"""The dashboard: a local-only viser server whose scene and panels follow the worker's snapshots.
One thread turns each new snapshot into layer and panel updates; the render loop serves each
browser's background; GUI callbacks send Commands. `run_view` (what `h2viz view` and `python app.py`
call) composes source + mapper -> MappingWorker -> Dashboard; only it imports the mapper (torch)."""

from __future__ import annotations

import contextlib
import io
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from h2viz.config import Config
from h2viz.sources.base import FrameSource, make_source
from h2viz.types import MapSnapshot
from h2viz.viewer.layers import LayerSet
from h2viz.viewer.panels import Panels
from h2viz.viewer.render_loop import RenderLoop
from h2viz.viewer.shapes import initial_view
from h2viz.viewer.viser_server import make_viser_server
from h2viz.worker import MappingWorker

log = logging.getLogger("h2viz.viewer")
UPDATE_HZ = 5.0  # largest rate of panel refreshes
SCENE_PERIOD_S = 1.0  # scene nodes follow the newest snapshot at least this often, and whenever the mesh changed


class Dashboard:
    """Serve the live map of `worker` at http://host:port (defaults from cfg.viewer)."""

    def __init__(self, worker: MappingWorker, cfg: Config, host: str | None = None, port: int | None = None) -> None:
        self.worker, self.cfg = worker, cfg
        self.server = make_viser_server(host or cfg.viewer.host, cfg.viewer.port if port is None else port)
        self.layers = LayerSet(
            self.server.scene, frustum_scale=max(0.05, 1.0 * cfg.mapping.representation.voxel_size_m)
        )
        self.renders = RenderLoop(self.server, worker, cfg.viewer.render_width)
        self.panels = Panels(self.server, worker, self.layers, self.renders, cfg)
        self.version = 0  # newest snapshot drawn in the panels
        self.scene_version = 0  # newest snapshot drawn in the scene
        self.scene_updates = 0  # scene refreshes sent (each makes every browser render a frame)
        self._scene_t = -np.inf  # time.monotonic() of the last scene refresh
        self._latest: MapSnapshot | None = None
        self.bytes_sent = 0  # geometry bytes sent so far
        self._errors_shown = 0
        self._view_set = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="h2viz-dashboard", daemon=True)
        self.server.on_client_connect(self._count_viewers)
        self.server.on_client_connect(self._greet)
        self.server.on_client_disconnect(self._count_viewers)
        self._count_viewers()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
        return f"http://{shown}:{self.server.get_port()}"

    def start(self) -> Dashboard:
        self._thread.start()
        self.renders.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10.0)
        self.renders.stop()
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()

    def _run(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            version, snap = self.worker.slot.wait_newer(self.version, 0.25)
            try:
                fresh = snap is not None and version != self.version
                if fresh:
                    self.version, self._latest = version, snap
                if self._latest is not None and self.scene_version != self.version:
                    self._draw_scene(self._latest, self.version)  # before the panels: mesh changes wait for less
                if fresh:
                    self.panels.update(snap)
                self._show_errors()
            except Exception:  # keep serving; the next snapshot redraws what failed
                log.exception("dashboard update failed")
            self._pause(max(0.0, 1.0 / UPDATE_HZ - (time.monotonic() - t0)))

    def _pause(self, seconds: float) -> None:
        """Wait until the next panel refresh, or less when a snapshot brings new mesh chunks: the mesh thread
        already limits how often those come, and waiting here would only add to their latency."""
        shown = self._latest.chunks if self._latest is not None else None
        if self.layers.mesh.enabled and shown is not None:
            self.worker.slot.wait_until(lambda snap: snap.chunks is not shown, seconds)
        else:
            self._stop.wait(seconds)

    def _draw_scene(self, snap: MapSnapshot, version: int) -> None:
        """Bring the scene to `snap` when the mesh changed or SCENE_PERIOD_S has passed, in one atomic
        group: a browser renders frames for each group it applies, and a software-rendered browser spent ~2 s
        of CPU on one frame of a 1M-triangle room, so fewer, fuller groups keep the cores for mapping."""
        now = time.monotonic()
        if now - self._scene_t < SCENE_PERIOD_S and not self.layers.mesh.behind(snap):
            return
        if not self._view_set and snap.current_frame is not None:
            self._set_initial_view(snap.current_frame.T_world_camera)
        with self.server.atomic():
            self.bytes_sent += self.layers.update(snap)
        self.scene_version, self._scene_t = version, now
        self.scene_updates += 1

    def _set_initial_view(self, T_world_camera: np.ndarray) -> None:
        up, eye, target = initial_view(T_world_camera)
        self.panels.comforts.up = up
        self.server.scene.set_up_direction(up)
        self.server.initial_camera.up = up
        self.server.initial_camera.position = eye
        self.server.initial_camera.look_at = target
        for client in self.server.get_clients().values():
            client.camera.up_direction, client.camera.position, client.camera.look_at = up, eye, target
        self._view_set = True

    def _show_errors(self) -> None:
        errors = self.worker.errors
        if len(errors) == self._errors_shown:
            return
        self.panels.status.show_errors(errors)
        for message in errors[self._errors_shown :]:
            for client in self.server.get_clients().values():
                client.add_notification("Mapping problem", message, auto_close_seconds=15.0, color="red")
        self._errors_shown = len(errors)

    def _greet(self, client: Any) -> None:
        """Show a newly connected browser the worker's notices (a resumed run, an earlier run's autosave)."""
        for notice in self.worker.notices:
            client.add_notification("Earlier run", notice, auto_close_seconds=30.0, color="blue")

    def _count_viewers(self, _client: Any = None) -> None:
        """Tell the worker how many browsers are connected (it keeps the live mesh only for someone)."""
        self.worker.set_viewers(self.client_count())

    def client_count(self) -> int:
        return len(self.server.get_clients())

    def clients(self) -> dict[int, Any]:
        return self.server.get_clients()


# ------------------------------------------------------------------------------------ composition


@dataclass
class RunningView:
    """A started worker and its dashboard."""

    worker: MappingWorker
    dashboard: Dashboard

    @property
    def url(self) -> str:
        return self.dashboard.url

    def stop(self) -> None:
        self.dashboard.stop()
        self.worker.stop()


def run_folder(cfg: Config) -> Path:
    """Where the dashboard autosaves and saves checkpoints (cfg.out_dir, default outputs/)."""
    return Path(cfg.out_dir or "outputs")


def build_worker(cfg: Config, resume: Path | None = None, source: FrameSource | None = None) -> MappingWorker:
    """Open the configured source (or take `source`) and a fresh mapper, or the mapper of a checkpoint (a file, or
    the newest in a run folder) to continue after its last frame; autosaves go to the run folder (the mapper module
    imports torch). A fresh run keeps the folder's earlier autosave under another name and offers to resume the
    newest checkpoint there (the dashboard shows a button for it)."""
    from h2viz.mapping.autosave import earlier_run, find_checkpoint, keep_earlier_autosave, run_progress
    from h2viz.mapping.checkpoint import load_checkpoint
    from h2viz.mapping.mapper import Mapper

    source = source or make_source(cfg.source)
    folder = run_folder(cfg)
    if resume is None:
        kept = keep_earlier_autosave(folder)
        worker = MappingWorker(source, Mapper(cfg.mapping), cfg, autosave_dir=folder)
        if kept is not None:
            worker.notices.append(f"An earlier run's autosave is kept as {kept}; this run never overwrites it.")
        worker.resume_offer, problem = earlier_run(folder)
        if worker.resume_offer is not None:
            worker.notices.append(worker.resume_offer.notice())
        elif problem is not None:
            worker.notices.append(problem)
        return worker
    path = find_checkpoint(resume)
    mapper, extra = load_checkpoint(path, cfg.mapping)
    last, stats = run_progress(path, extra)
    worker = MappingWorker(source, mapper, cfg, autosave_dir=folder, resumed=(last, stats))
    worker.notices.append(f"Resumed from {path}: {len(stats)} frames were mapped; mapping goes on after frame {last}.")
    return worker


def start_view(cfg: Config, worker: MappingWorker | None = None, resume: Path | None = None) -> RunningView:
    """Start mapping and serve the dashboard on cfg.viewer.host:port; returns at once."""
    worker = worker or build_worker(cfg, resume)
    dashboard = Dashboard(worker, cfg)
    try:
        worker.start()
        dashboard.start()
    except BaseException:
        dashboard.stop()
        worker.stop()
        raise
    log.info("dashboard at %s", dashboard.url)
    return RunningView(worker, dashboard)


def run_view(cfg: Config, on_ready: Callable[[str], None] | None = None, resume: Path | None = None) -> None:
    """Serve the live dashboard until Ctrl-C; `on_ready` receives the URL once it is up; `resume` continues the run of
    a checkpoint or run folder."""
    view = start_view(cfg, resume=resume)
    if on_ready is not None:
        on_ready(view.url)
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        log.info("stopping the dashboard")
    finally:
        view.stop()
