"""The dashboard's demo controls in a real headless chromium over the real Mapper (tiny configuration) on the
analytic room: Record and the HTML download, a fly-through path built from the browser's camera and rendered to an
MP4 of the requested frames and size, following the sensor, the split view and resetting the up direction."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from h2viz.config import Config
from h2viz.viewer.recording import Recording
from h2viz.viewer.server import Dashboard
from h2viz.viewer.video import read_video
from h2viz.worker import MappingWorker
from tests.viewer.browser import dashboard_page, wait_until
from tests.viewer.fakes import BoxRoomSource, recording_mapper, tiny_mapping_config

pytestmark = pytest.mark.browser
sync_api = pytest.importorskip("playwright.sync_api")


@dataclass
class Live:
    worker: MappingWorker
    dashboard: Dashboard
    page: Any

    def client(self) -> Any:
        return next(iter(self.dashboard.clients().values()))


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Live]:
    cfg = Config()
    cfg.out_dir = str(tmp_path_factory.mktemp("out"))
    cfg.viewer.video_width, cfg.viewer.video_fps, cfg.viewer.record_fps = 96, 10, 5.0
    worker = MappingWorker(BoxRoomSource(n=400, width=64, height=48), recording_mapper(tiny_mapping_config(), 0.1), cfg)
    with dashboard_page(worker, cfg) as (dashboard, _, page):
        page.goto(dashboard.url)
        wait_until(page, lambda: dashboard.client_count() == 1, what="the browser")
        yield Live(worker, dashboard, page)


def test_record_switch_and_html_download(live: Live, tmp_path: Path) -> None:
    page = live.page
    page.get_by_role("tab", name="Export").click()
    page.get_by_role("checkbox", name="Record").check()
    wait_until(page, lambda: live.worker.recording is not None, what="recording on")
    start = live.worker.slot.get()[1].frames_done
    wait_until(page, lambda: live.worker.slot.get()[1].frames_done >= start + 4, what="frames recorded")
    with page.expect_download(timeout=120_000) as info:
        page.get_by_role("button", name="Download recording (HTML)").click()
    path = tmp_path / info.value.suggested_filename
    info.value.save_as(path)
    assert path.suffix == ".html" and "__VISER_EMBED_DATA__" in path.read_text()
    assert live.worker.recording is None and not page.get_by_role("checkbox", name="Record").is_checked()
    recording = Recording(live.dashboard.panels.recorded)
    assert len(recording) >= 4
    frames = [recording.snapshot(k).frames_done for k in range(len(recording))]
    assert frames == list(range(frames[0], frames[0] + len(recording)))  # one step per mapped frame


def test_flythrough_from_browser_cameras_renders_the_requested_mp4(live: Live, tmp_path: Path) -> None:
    page, panel = live.page, live.dashboard.panels.flythrough
    live.worker.submit("pause").result(10)  # the map as it is: the renders need not share the cores with mapping
    page.get_by_role("tab", name="Export").click()
    page.get_by_text("Fly-through video").click()
    client = live.client()
    for x in (0.0, 0.4, 0.8):
        client.camera.position, client.camera.look_at = np.array([x, 0.0, 1.3]), np.array([x + 1.0, 0.2, 1.0])
        wait_until(page, lambda x=x: abs(client.camera.position[0] - x) < 1e-3, what="the camera moved")
        page.get_by_role("button", name="Add this view").click()
        wait_until(page, lambda x=x: panel.path.keyframes and abs(panel.path.keyframes[-1].position[0] - x) < 1e-3)
    assert [round(k.position[0], 3) for k in panel.path.keyframes] == [0.0, 0.4, 0.8]
    panel.selected.value = "1"
    page.get_by_role("button", name="Down", exact=True).click()
    wait_until(page, lambda: [round(k.position[0], 3) for k in panel.path.keyframes] == [0.4, 0.0, 0.8])
    panel.duration.value = 1.2  # 12 frames at 10 fps
    with page.expect_download(timeout=300_000) as info:
        page.get_by_role("button", name="Render MP4").click()
    out = tmp_path / info.value.suggested_filename
    info.value.save_as(out)
    frames = read_video(out)
    assert len(frames) == 12 and frames[0].shape == (panel.path.height, 96, 3)
    aspect = live.client().camera.aspect  # the browser's 3D view (the page less the panel)
    assert abs(96 / panel.path.height - aspect) < 0.06  # the height is rounded to an even number
    assert np.mean(frames[0]) > 10  # the room, not an empty frame
    assert out.with_suffix(".json").name in {p.name for p in Path(live.dashboard.panels.out_dir).glob("*.json")}


def test_follow_split_view_and_reset_up(live: Live) -> None:
    page, comforts = live.page, live.dashboard.panels.comforts
    page.get_by_role("tab", name="View").click()
    page.get_by_role("checkbox", name="Follow sensor").check()
    client = live.client()

    def at_sensor() -> bool:
        frame = live.worker.slot.get()[1].current_frame
        return frame is not None and np.linalg.norm(client.camera.position - frame.T_world_camera[:3, 3]) < 0.05

    wait_until(page, at_sensor, what="the camera at the sensor")
    page.get_by_role("checkbox", name="Follow sensor").uncheck()
    page.get_by_role("checkbox", name="Split view").check()
    wait_until(page, lambda: comforts.image.image.shape[1] == 2 * comforts.image.image.shape[0] * 4 // 3, 60.0)
    right = comforts.image.image[:, comforts.image.image.shape[1] // 2 :]
    assert right.std() > 5  # a render of the room, not the backdrop
    client.camera.up_direction = np.array([1.0, 0.0, 0.0])
    page.get_by_role("button", name="Reset up direction").click()
    wait_until(page, lambda: np.allclose(client.camera.up_direction, comforts.up, atol=1e-6), what="up reset")
