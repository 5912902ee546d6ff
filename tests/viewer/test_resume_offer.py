"""The dashboard offers to resume the earlier run its folder holds: a "Resume earlier run (N frames, saved ...)"
button on the real viser server, which makes the worker take over that run's map and go on after its last frame
(with its stats, even when this run has mapped past it already) and then disappears; no button without a
checkpoint; a damaged checkpoint is named in a message and the fresh run goes on."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import viser

from h2viz.config import Config
from h2viz.mapping.autosave import AUTOSAVE_NAME
from h2viz.mapping.checkpoint import load_checkpoint
from h2viz.viewer import server
from h2viz.viewer.server import Dashboard
from h2viz.worker import MappingWorker
from tests.viewer.fakes import BoxRoomSource, recording_mapper, tiny_mapping_config


class Browser:
    """Stands in for the client a GUI event comes from: notes the notifications it is shown."""

    def __init__(self) -> None:
        self.notes: list[tuple[str, str, str]] = []  # (title, body, colour)

    def add_notification(self, title: str, body: str, **kwargs: Any) -> None:
        self.notes.append((title, body, str(kwargs.get("color"))))


def config(folder: Path) -> Config:
    cfg = Config()
    cfg.mapping = tiny_mapping_config()
    cfg.out_dir = str(folder)
    cfg.autosave.every_frames, cfg.autosave.every_s = 3, 0.0
    return cfg


def earlier_run(folder: Path) -> list[dict]:
    """A finished short run that autosaved into `folder` after its frames 0-2; the stats it saved."""
    cfg = config(folder)
    worker = MappingWorker(BoxRoomSource(n=4), recording_mapper(cfg.mapping), cfg, autosave_dir=folder)
    worker.start()
    try:
        assert worker.wait_finished(120)
    finally:
        worker.stop()
    extra = load_checkpoint(folder / AUTOSAVE_NAME)[1]
    assert extra["last_index"] == 2
    return extra["stats"]


@contextmanager
def dashboard(worker: MappingWorker, cfg: Config) -> Iterator[Dashboard]:
    """The worker and its dashboard on a free port, started; both stopped afterwards."""
    dash = Dashboard(worker, cfg, port=0)
    worker.start()
    dash.start()
    try:
        yield dash
    finally:
        dash.stop()
        worker.stop()


def buttons(dash: Dashboard) -> list[str]:
    """Labels of the buttons the dashboard's GUI holds now."""
    handles = dash.server.gui._gui_input_handle_from_uuid.values()
    return [h.label for h in handles if isinstance(h, viser.GuiButtonHandle)]


def click(button: viser.GuiButtonHandle, client: Browser) -> None:
    """What viser does when a browser presses `button`."""
    for callback in list(button._impl.update_cb):
        callback(viser.GuiEvent(client=client, client_id=0, target=button))  # type: ignore[arg-type]


def test_the_resume_button_continues_the_earlier_run_after_this_one_mapped_past_it(tmp_path: Path) -> None:
    saved = earlier_run(tmp_path)
    cfg = config(tmp_path)
    worker = server.build_worker(cfg, source=BoxRoomSource(n=8))
    offer = worker.resume_offer
    assert offer is not None and offer.frames == 3 and offer.last_index == 2 and offer.path.name.startswith("autosave_")
    assert worker.notices == [
        f"An earlier run's autosave is kept as {offer.path}; this run never overwrites it.",
        offer.notice(),
    ]
    with dashboard(worker, cfg) as dash:
        label = [b for b in buttons(dash) if b.startswith("Resume earlier run")]
        assert label == [offer.label()] and label[0].startswith("Resume earlier run (3 frames, saved 20")
        assert worker.wait_finished(120)  # the fresh run mapped all 8 frames: the stream must go back to frame 3
        browser = Browser()
        click(dash.panels.resume_earlier, browser)
        assert browser.notes == [
            (
                "Earlier run resumed",
                f"Resumed from {offer.path}: 3 frames were mapped; mapping goes on after frame 2. The 8 frames this "
                "run had mapped were replaced by that map.",
                "green",
            )
        ]
        assert not [b for b in buttons(dash) if b.startswith("Resume earlier run") or b == "Dismiss"]
        assert worker.resume_offer is None and worker.notices == [browser.notes[0][1]]
        assert worker.wait_finished(120)
        snap = worker.slot.get()[1]
    assert [s.index for s in snap.stats] == list(range(8)) and snap.frames_done == 8 and not worker.errors
    assert [dataclasses.asdict(s) for s in snap.stats[:3]] == saved  # the earlier run's own stats
    assert len(snap.trajectory) == 8 and worker.mapper.frames_done == 8
    autosave = load_checkpoint(tmp_path / AUTOSAVE_NAME)[1]  # replaced at once, then autosaved as the run went on
    assert autosave["stats"][:3] == saved and autosave["last_index"] == 5


def test_resuming_before_this_run_mapped_anything_passes_over_the_earlier_frames(tmp_path: Path) -> None:
    saved = earlier_run(tmp_path)
    cfg = config(tmp_path)
    cfg.viewer.start_paused = True
    source = BoxRoomSource(n=6)
    worker = server.build_worker(cfg, source=source)
    with dashboard(worker, cfg):
        message = worker.submit("resume_run", path=str(tmp_path)).result(60)  # the folder: its newest checkpoint
        assert message.endswith("mapping goes on after frame 2.") and "replaced" not in message
        worker.submit("resume").result(10)
        assert worker.wait_finished(120)
        saved_path = tmp_path / "checkpoint_test.pt"
        worker.submit("save", path=str(saved_path)).result(60)
    snap = worker.slot.get()[1]
    assert [s.index for s in snap.stats] == list(range(6)) and snap.frames_done == 6
    assert [dataclasses.asdict(s) for s in snap.stats[:3]] == saved
    extra = load_checkpoint(saved_path)[1]  # the dashboard's own checkpoints carry the run state too
    assert extra["last_index"] == 5 and len(extra["stats"]) == 6


def test_dismissing_the_offer_removes_the_button_and_keeps_the_fresh_run(tmp_path: Path) -> None:
    earlier_run(tmp_path)
    cfg = config(tmp_path)
    cfg.viewer.start_paused = True
    worker = server.build_worker(cfg, source=BoxRoomSource(n=3))
    with dashboard(worker, cfg) as dash:
        assert "Dismiss" in buttons(dash)
        click(dash.panels.dismiss_earlier, Browser())
        assert worker.resume_offer is None and worker.notices == [worker.notices[0]]
        assert not [b for b in buttons(dash) if b.startswith("Resume earlier run") or b == "Dismiss"]


def test_a_folder_without_a_checkpoint_shows_no_button(tmp_path: Path) -> None:
    cfg = config(tmp_path)
    worker = server.build_worker(cfg, source=BoxRoomSource(n=2))
    assert worker.resume_offer is None and worker.notices == []
    dash = Dashboard(worker, cfg, port=0)
    try:
        assert "Pause" in buttons(dash) and not [b for b in buttons(dash) if b.startswith("Resume earlier")]
    finally:
        dash.server.stop()


def test_a_damaged_checkpoint_is_named_and_the_fresh_run_goes_on(tmp_path: Path) -> None:
    (tmp_path / AUTOSAVE_NAME).write_bytes(b"not a checkpoint, cut short by a crash")
    cfg = config(tmp_path)
    worker = server.build_worker(cfg, source=BoxRoomSource(n=4))
    kept = next(tmp_path.glob("autosave_*.pt"))
    assert worker.resume_offer is None and len(worker.notices) == 2
    assert worker.notices[1].startswith(f"An earlier run's checkpoint cannot be resumed: {kept} is not a readable")
    assert worker.notices[1].endswith("This run starts fresh; the file is left as it is.")
    with dashboard(worker, cfg) as dash:
        assert not [b for b in buttons(dash) if b.startswith("Resume earlier")]
        assert worker.wait_finished(120)
    assert worker.slot.get()[1].frames_done == 4 and not worker.errors


def test_a_checkpoint_damaged_after_the_offer_leaves_the_fresh_run_as_it_was(tmp_path: Path) -> None:
    earlier_run(tmp_path)
    cfg = config(tmp_path)
    worker = server.build_worker(cfg, source=BoxRoomSource(n=5))
    assert worker.resume_offer is not None
    path = worker.resume_offer.path
    path.write_bytes(b"\0" * 64)  # overwritten after the dashboard started
    with dashboard(worker, cfg) as dash:
        assert worker.wait_finished(120)
        browser = Browser()
        click(dash.panels.resume_earlier, browser)
        ((title, body, colour),) = browser.notes
        assert (title, colour) == ("Cannot resume the earlier run", "red")
        assert body.startswith(f"{path} is not a readable h2viz checkpoint") and body.endswith("goes on as it was.")
        assert not [b for b in buttons(dash) if b.startswith("Resume earlier run")]
        snap = worker.slot.get()[1]
    assert [s.index for s in snap.stats] == list(range(5)) and snap.frames_done == 5 and not worker.errors


@pytest.mark.browser
def test_the_button_in_a_real_browser_resumes_the_earlier_run_and_disappears(tmp_path: Path) -> None:
    pytest.importorskip("playwright.sync_api")
    from tests.viewer.browser import dashboard_page, wait_until

    saved = earlier_run(tmp_path)
    cfg = config(tmp_path)
    cfg.viewer.start_paused = True
    worker = server.build_worker(cfg, source=BoxRoomSource(n=6))
    with dashboard_page(worker, cfg) as (dash, _, page):
        page.goto(dash.url)
        button = page.get_by_role("button", name="Resume earlier run (3 frames, saved")
        wait_until(page, lambda: button.count() == 1, what="the resume button")
        assert page.get_by_text("Earlier run", exact=True).count() >= 1  # the folder's title, and the notification's
        button.click()
        wait_until(page, lambda: worker.resume_offer is None and button.count() == 0, what="the button to go")
        wait_until(page, lambda: page.get_by_text("Earlier run resumed").count() == 1, what="the notification")
        page.get_by_role("button", name="Resume", exact=True).click()  # the fresh run started paused
        assert worker.wait_finished(120)
        snap = worker.slot.get()[1]
    assert [s.index for s in snap.stats] == list(range(6)) and snap.frames_done == 6
    assert [dataclasses.asdict(s) for s in snap.stats[:3]] == saved


def test_a_checkpoint_that_does_not_say_where_its_run_ended_is_not_offered(tmp_path: Path) -> None:
    from h2viz.mapping.autosave import earlier_run as offer_of
    from h2viz.mapping.checkpoint import save_checkpoint

    earlier_run(tmp_path)
    mapper, _ = load_checkpoint(tmp_path / AUTOSAVE_NAME)
    save_checkpoint(mapper, tmp_path / "checkpoint_old.pt")  # as the dashboard's Save checkpoint wrote them before
    os.utime(tmp_path / "checkpoint_old.pt", (2e9, 2e9))  # the newest
    offer, problem = offer_of(tmp_path)
    assert offer is None and problem == (
        f"An earlier run's checkpoint cannot be resumed: {tmp_path / 'checkpoint_old.pt'} does not say which frame its "
        "run ended at, so it cannot be continued. This run starts fresh; the file is left as it is."
    )
