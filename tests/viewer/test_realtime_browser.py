"""Real-time mode in the dashboard, in a real headless chromium over the real Mapper (tiny configuration) and the
analytic room at 30 Hz: the progress panel counts every frame integrated (none dropped), shows the optimisation
steps and the phase (streaming, then sharpening until the loss settles), and the Real-time checkbox switches the
worker's mode."""

from __future__ import annotations

from dataclasses import replace

import pytest

from h2viz.config import Config
from h2viz.mapping.mapper import Mapper
from h2viz.viewer.server import Dashboard
from h2viz.worker import MappingWorker, WorkerSettings
from tests.viewer.browser import launch, wait_until
from tests.viewer.fakes import BoxRoomSource, tiny_mapping_config

pytestmark = pytest.mark.browser
sync_api = pytest.importorskip("playwright.sync_api")


def test_the_progress_panel_counts_integrated_frames_and_shows_the_phase() -> None:
    cfg = Config()
    cfg.anytime = replace(cfg.anytime, plateau_window=10)
    mapper = Mapper(tiny_mapping_config())
    worker = MappingWorker(BoxRoomSource(n=45, width=64, height=48), mapper, cfg, WorkerSettings(realtime=True))
    dashboard = Dashboard(worker, cfg, port=0)
    worker.start()
    dashboard.start()
    try:
        with sync_api.sync_playwright() as playwright:
            browser = launch(playwright)
            page = browser.new_page(viewport={"width": 900, "height": 650})
            page.goto(dashboard.url)
            panel = lambda: page.locator("table").filter(has_text="Integrated / dropped / skipped")  # noqa: E731
            wait_until(page, lambda: panel().count() > 0, what="the progress panel")
            wait_until(page, lambda: "real time" in panel().first.inner_text(), what="a real-time phase")
            settled = wait_until(
                page,
                lambda: "loss stopped improving" in (text := panel().first.inner_text()) and text,
                timeout_s=120,
                what="the settled phase",
            )
            snap = worker.slot.get()[1]
            assert snap.phase == "settled" and snap.frames_done + snap.dropped == 45 and snap.opt_steps > 45
            assert f"{snap.frames_done} / {snap.dropped} / 0" in settled
            assert f"{snap.opt_steps:,}" in settled
            checkbox = page.get_by_role("checkbox", name="Real-time")
            assert checkbox.is_checked()
            checkbox.click()
            wait_until(page, lambda: not worker.settings.realtime, what="every-frame mode")
            browser.close()
    finally:
        dashboard.stop()
        worker.stop()
