"""The live dashboard in a real headless chromium (Playwright, Debian's /usr/bin/chromium) over the
real Mapper (tiny configuration) and the analytic room: the scene streams and grows, the GUI buttons
drive the worker, camera motion brings a rendered background with depth, exports download, a second
browser gets the same scene, nothing leaves the machine."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import trimesh

from h2viz.config import Config
from h2viz.viewer.server import Dashboard
from h2viz.worker import MappingWorker
from tests.viewer.browser import WireRecorder, dashboard_page, wait_until
from tests.viewer.fakes import BoxRoomSource, recording_mapper, tiny_mapping_config

pytestmark = pytest.mark.browser
sync_api = pytest.importorskip("playwright.sync_api")


@dataclass
class Live:
    worker: MappingWorker
    mapper: Any  # the real Mapper (tiny configuration) noting its renders
    dashboard: Dashboard
    browser: Any
    page: Any
    wire: WireRecorder
    requests: list[str]


@pytest.fixture(scope="module")
def live() -> Iterator[Live]:
    cfg = Config()
    cfg.viewer.render_width = 240
    mapper = recording_mapper(tiny_mapping_config(), delay_s=0.1)
    worker = MappingWorker(BoxRoomSource(n=400, width=64, height=48), mapper, cfg)
    with dashboard_page(worker, cfg) as (dashboard, browser, page):
        requests: list[str] = []
        page.on("request", lambda r: requests.append(r.url))
        wire = WireRecorder().attach(page)
        assert not worker.live  # no browser yet: nothing is meshed while mapping
        page.goto(dashboard.url)
        yield Live(worker, mapper, dashboard, browser, page, wire, requests)


def test_scene_reaches_the_browser_and_grows(live: Live) -> None:
    page, wire = live.page, live.wire
    first = wait_until(page, lambda: len(wire.names("GlbMessage", "/mesh/")), what="mesh chunks in the page")
    wait_until(page, lambda: len(wire.names("GlbMessage", "/mesh/")) > first, what="more mesh chunks")
    wait_until(page, lambda: len(wire.names("CameraFrustumMessage", "/keyframes/")) >= 2, what="keyframe frustums")
    assert wire.names("LineSegmentsMessage", "/trajectory/") == {"/trajectory/path"}
    # viser streams the scene to a page before it lists the page among its clients
    wait_until(page, lambda: live.dashboard.client_count() == 1, what="the page counted as a client")
    assert live.worker.live
    page.get_by_role("tab", name="View").click()
    page.get_by_role("checkbox", name="Octree leaves").click()
    blocks = wait_until(page, lambda: len(wire.names("LineSegmentsMessage", "/octree/l0/")), what="octree blocks")
    voxels = len(live.worker.slot.get()[1].voxel_coords)
    wait_until(page, lambda: len(live.worker.slot.get()[1].voxel_coords) > voxels, what="new voxels")
    sent = len(wire.of_type("LineSegmentsMessage"))
    wait_until(page, lambda: len(wire.of_type("LineSegmentsMessage")) > sent + 1, what="octree updates")
    assert len(wire.names("LineSegmentsMessage", "/octree/l0/")) >= blocks
    page.get_by_role("checkbox", name="Octree leaves").click()  # off again: keep the page light
    page.get_by_role("tab", name="Mapping").click()


def test_the_title_bar_shows_the_shipped_logo(live: Live) -> None:
    logo = live.page.get_by_role("img", name="h2viz")
    wait_until(live.page, lambda: logo.count() == 1, what="the logo in the title bar")
    assert logo.get_attribute("src").startswith("data:image/svg+xml;base64,")  # inline: no request for it
    assert logo.bounding_box()["height"] > 10  # laid out, not an empty placeholder


def test_pause_and_resume_buttons_drive_the_worker(live: Live) -> None:
    page, slot = live.page, live.worker.slot
    page.get_by_role("button", name="Pause").click()
    paused = wait_until(page, lambda: slot.get()[1] if slot.get()[1].paused else None, what="paused snapshot")
    page.wait_for_timeout(1200)
    assert slot.get()[1].frames_done == paused.frames_done
    wait_until(page, lambda: page.get_by_role("button", name="Resume").is_enabled(), what="Resume enabled")
    page.get_by_role("button", name="Resume").click()
    wait_until(page, lambda: slot.get()[1].frames_done >= paused.frames_done + 2, what="mapping to go on")
    assert not slot.get()[1].paused
    live.worker.submit("pause").result(10)  # a still map keeps the software-rendered page light


def test_camera_motion_brings_a_rendered_background_with_depth(live: Live) -> None:
    page, wire = live.page, live.wire
    page.get_by_role("tab", name="View").click()
    page.get_by_role("combobox", name="Render").click()
    page.get_by_role("option", name="rgb", exact=True).click()
    wait_until(page, lambda: live.dashboard.renders.mode == "rgb", what="render mode rgb")
    start = time.time()
    page.mouse.move(250, 350)
    page.mouse.down()
    page.mouse.move(330, 360, steps=4)
    page.mouse.up()
    with_depth = lambda: [m for m in wire.of_type("BackgroundImageMessage", since=start) if m.fields.get("depth_data")]
    wait_until(page, with_depth, what="a background image with depth")
    # a quick low-resolution view first, then the refined one once the camera rests
    widths = lambda: {w for _, w, _ in live.mapper.rendered}
    assert 60 in widths()
    wait_until(page, lambda: 240 in widths(), what="the refined 240-pixel render")
    image_widths = lambda: {jpeg_width(m.fields["rgb_data"]) for m in with_depth()}
    wait_until(page, lambda: {60, 240} <= image_widths(), what="the refined background in the page")
    page.get_by_role("combobox", name="Render").click()
    page.get_by_role("option", name="off", exact=True).click()
    page.get_by_role("tab", name="Mapping").click()


def jpeg_width(data: bytes) -> int:
    return int(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED).shape[1])


def test_export_downloads_a_valid_mesh(live: Live, tmp_path: Path) -> None:
    page = live.page
    page.get_by_role("tab", name="Export").click()
    with page.expect_download(timeout=60_000) as info:
        page.get_by_role("button", name="Download mesh (PLY)").click()
    path = tmp_path / info.value.suggested_filename
    info.value.save_as(path)
    assert path.suffix == ".ply"
    mesh = trimesh.load(path, force="mesh", process=False)
    assert len(mesh.faces) > 0 and len(mesh.vertices) > 0
    assert (mesh.bounds[0] > [-2.5, -2.0, -0.5]).all() and (mesh.bounds[1] < [2.5, 2.0, 3.0]).all()  # the room
    page.get_by_role("tab", name="Mapping").click()


def test_refine_button_refines_the_paused_map(live: Live) -> None:
    page, slot = live.page, live.worker.slot
    live.worker.submit("pause").result(10)
    done = slot.get()[1].refined
    page.get_by_role("tab", name="Export").click()
    page.get_by_role("button", name="Refine map (500 steps)").click()
    wait_until(page, lambda: slot.get()[1].refined > done, what="refinement steps")
    page.get_by_role("tab", name="Mapping").click()
    wait_until(page, lambda: f"refined {done + 500} steps" in page.inner_text("body"), what="the refinement done")
    assert slot.get()[1].paused and not live.worker.errors


def test_second_browser_sees_the_same_scene(live: Live) -> None:
    page2 = live.browser.new_page(viewport={"width": 640, "height": 480})
    wire2 = WireRecorder().attach(page2)
    page2.goto(live.dashboard.url)
    try:
        wait_until(page2, lambda: live.dashboard.client_count() == 2, what="two connected browsers")
        drawn = {
            f"/mesh/c_{'_'.join(str(k).replace('-', 'm') for k in key)}" for key in live.dashboard.layers.mesh.handles
        }
        wait_until(page2, lambda: drawn <= wire2.names("GlbMessage", "/mesh/"), what="the same chunks in page 2")
        keyframes = live.wire.names("CameraFrustumMessage", "/keyframes/")
        assert keyframes <= wire2.names("CameraFrustumMessage", "/keyframes/")
        assert page2.get_by_role("button", name="Pause").count() == 1
    finally:
        page2.close()


def test_nothing_is_fetched_from_outside(live: Live) -> None:
    origin = live.dashboard.url
    outside = [u for u in live.requests if not u.startswith((origin, "data:", "blob:"))]
    assert live.requests and not outside
    assert live.dashboard.server.get_host() == "127.0.0.1"
