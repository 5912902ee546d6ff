"""Composition of the live dashboard: source + mapper -> MappingWorker -> Dashboard. `run_view` is
what `h2viz view` and `python app.py` call; `start_view` is its non-blocking core."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

from h2viz.config import Config
from h2viz.sources.base import make_source
from h2viz.viewer.server import Dashboard
from h2viz.worker import MappingWorker

log = logging.getLogger("h2viz.viewer")


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


def build_worker(cfg: Config) -> MappingWorker:
    """Open the configured source and a fresh mapper (the mapper module imports torch)."""
    from h2viz.mapping.mapper import Mapper

    source = make_source(cfg.source)
    return MappingWorker(source, Mapper(cfg.mapping), cfg)


def start_view(cfg: Config, worker: MappingWorker | None = None) -> RunningView:
    """Start mapping and serve the dashboard on cfg.viewer.host:port; returns at once."""
    worker = worker or build_worker(cfg)
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


def run_view(cfg: Config, on_ready: Callable[[str], None] | None = None) -> None:
    """Serve the live dashboard until Ctrl-C; `on_ready` receives the URL once it is up."""
    view = start_view(cfg)
    if on_ready is not None:
        on_ready(view.url)
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        log.info("stopping the dashboard")
    finally:
        view.stop()
