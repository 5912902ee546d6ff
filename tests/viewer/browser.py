"""Driving Debian's headless chromium with Playwright, and recording what the page's websocket
actually received from the viser server (decoded messages with their arrival times)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import pytest
from playwright import sync_api

from h2viz.config import Config
from h2viz.viewer.chromium import CHROMIUM, launch_chromium
from h2viz.viewer.server import Dashboard
from h2viz.viewer.wire import WireMessage, decode_frame
from h2viz.worker import MappingWorker


def launch(playwright: Any) -> Any:
    """Headless chromium from /usr/bin (skips the test when it is not installed)."""
    if not CHROMIUM.exists():
        pytest.skip("chromium is not installed (apt-get install chromium)")
    return launch_chromium(playwright)


@contextmanager
def dashboard_page(worker: MappingWorker, cfg: Config) -> Iterator[tuple[Dashboard, Any, Any]]:
    """The worker and a dashboard on a free port started, and a 900x650 chromium page not yet on it:
    (dashboard, browser, page); all of it stopped afterwards."""
    dashboard = Dashboard(worker, cfg, port=0)
    worker.start()
    dashboard.start()
    try:
        with sync_api.sync_playwright() as playwright:
            browser = launch(playwright)
            page = browser.new_page(viewport={"width": 900, "height": 650}, accept_downloads=True)
            try:
                yield dashboard, browser, page
            finally:
                browser.close()
    finally:
        dashboard.stop()
        worker.stop()


@dataclass
class WireRecorder:
    """Every message the page's websockets received, with time.time() of arrival."""

    messages: list[tuple[float, WireMessage]] = field(default_factory=list)

    def attach(self, page: Any) -> WireRecorder:
        page.on("websocket", lambda ws: ws.on("framereceived", self._on_frame))
        return self

    def _on_frame(self, payload: Any) -> None:
        now = time.time()
        if isinstance(payload, bytes):
            self.messages.extend((now, m) for m in decode_frame(payload))

    def names(self, kind: str, prefix: str = "/") -> set[str]:
        """Scene nodes of message type `kind` under `prefix` that were added and not removed since."""
        alive: set[str] = set()
        for _, m in self.messages:
            if m.name is None or not m.name.startswith(prefix):
                continue
            if m.type == kind:
                alive.add(m.name)
            elif m.type == "RemoveSceneNodeMessage":
                alive.discard(m.name)
        return alive

    def of_type(self, kind: str, since: float = 0.0) -> list[WireMessage]:
        return [m for t, m in self.messages if m.type == kind and t >= since]


def wait_until(page: Any, predicate: Callable[[], Any], timeout_s: float = 60.0, what: str = "condition") -> Any:
    """Poll `predicate` while letting Playwright deliver page events; fail after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        page.wait_for_timeout(100)
    raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
