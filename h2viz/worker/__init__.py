"""The mapping worker: source -> mapper on one thread, Commands in, MapSnapshots out (no torch here)."""

from h2viz.worker.commands import COMMANDS
from h2viz.worker.feed import END, FrameFeed, WorkerSettings, settings_from_config
from h2viz.worker.mapping_worker import MappingWorker, rss_mb
from h2viz.worker.requests import RenderedView
from h2viz.worker.slot import LatestSlot

__all__ = [
    "COMMANDS",
    "END",
    "FrameFeed",
    "LatestSlot",
    "MappingWorker",
    "RenderedView",
    "WorkerSettings",
    "rss_mb",
    "settings_from_config",
]
