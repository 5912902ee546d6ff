"""The live mesh as a real headless chromium draws it: a mesh chunk sent by MeshLayer to a dashboard-lit viser
server must come out evenly shaded. A grey plane under the dashboard's lights has one shade everywhere;
normals the browser failed to compute show up as black or speckled pixels."""

from __future__ import annotations

from collections.abc import Iterator
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
from skimage.measure import marching_cubes

from h2viz.types import MeshChunk
from h2viz.viewer.layers import MeshLayer
from h2viz.viewer.viser_server import make_viser_server
from tests.viewer.browser import launch, wait_until

pytestmark = pytest.mark.browser
sync_api = pytest.importorskip("playwright.sync_api")

CHUNK_M = 0.8
CELL_M = 0.025  # the live mesh's marching-cubes cell
NORMAL = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])
CENTRE = np.full(3, CHUNK_M / 2)
EMPTY_GRAY = 20  # the dashboard's dark background


def slab_chunk() -> MeshChunk:
    """Marching cubes of a tilted plane through one 0.8 m chunk: the irregular triangles, tiny ones included,
    of a real live-mesh chunk."""
    n = int(round(CHUNK_M / CELL_M)) + 1
    grid = np.stack(np.meshgrid(*[np.linspace(0.0, CHUNK_M, n)] * 3, indexing="ij"), -1)  # (n,n,n,3)
    sdf = (grid - CENTRE) @ NORMAL
    vertices, faces, _, _ = marching_cubes(sdf, 0.0, spacing=(CELL_M,) * 3)
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    if np.median(np.cross(b - a, c - a) @ NORMAL) < 0:  # wind them towards positive SDF, as h2viz's mesher does
        faces = faces[:, ::-1]
    colors = np.full((len(vertices), 3), 170, np.uint8)
    return MeshChunk((0, 0, 0), vertices.astype(np.float32), faces.astype(np.int32), colors, version=1)


@pytest.fixture()
def slab_page() -> Iterator[Any]:
    server = make_viser_server("127.0.0.1", 0)
    chunk = slab_chunk()
    MeshLayer(server.scene).sync(SimpleNamespace(chunks={chunk.key: chunk}))
    eye = CENTRE + 0.6 * NORMAL
    up = np.cross(NORMAL, [1.0, 0.0, 0.0])

    @server.on_client_connect
    def _(client: Any) -> None:
        client.camera.up_direction = tuple(up / np.linalg.norm(up))
        client.camera.position = tuple(eye)
        client.camera.look_at = tuple(CENTRE)

    try:
        with sync_api.sync_playwright() as playwright:
            browser = launch(playwright)
            page = browser.new_page(viewport={"width": 1280, "height": 720})
            page.goto(f"http://127.0.0.1:{server.get_port()}")
            yield page
            browser.close()
    finally:
        server.stop()


def _slab_pixels(page: Any) -> np.ndarray:
    """Grey levels (N,) of the middle of the view (left of the panel), which the plane fills."""
    png = page.screenshot()
    gray = cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2GRAY)
    h, w = gray.shape
    return gray[int(0.3 * h) : int(0.8 * h), int(0.35 * w) : int(0.6 * w)].ravel()


def test_mesh_chunks_are_evenly_lit(slab_page: Any) -> None:
    page = slab_page
    drawn = lambda: abs(float(np.median(_slab_pixels(page))) - EMPTY_GRAY) > 3  # noqa: E731
    wait_until(page, drawn, timeout_s=60.0, what="the plane drawn in the page")
    page.wait_for_timeout(1000)  # a few more frames
    pixels = _slab_pixels(page)
    level = float(np.median(pixels))
    assert level > 80, f"the grey plane is drawn at grey level {level:.0f}: unlit (normals not computed?)"
    dark = float(np.mean(pixels < 0.5 * level))
    assert dark < 0.005, f"{dark:.1%} of the plane is dark: speckled normals"
    assert np.percentile(pixels, 95) - np.percentile(pixels, 5) < 25, "a plane should have one shade"
