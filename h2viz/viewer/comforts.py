"""Viewing comforts of the dashboard (View tab, folder Camera): follow the sensor camera, a split view of the input
frame beside the map's render at the sensor's pose, and resetting the up direction after orbiting."""

from __future__ import annotations

import logging
from concurrent.futures import Future
from typing import Any

import numpy as np
import viser

from h2viz.types import MapSnapshot, RgbdFrame
from h2viz.viewer.flythrough import fly_client
from h2viz.viewer.recording import thumbnail
from h2viz.viewer.render_loop import BACKDROP
from h2viz.viewer.shapes import initial_view, to_rgb8
from h2viz.worker import MappingWorker

log = logging.getLogger("h2viz.viewer")
SPLIT_WIDTH = 200  # width of each half of the split view


def split_image(frame_rgb: np.ndarray, render_rgb: np.ndarray | None) -> np.ndarray:
    """(h,2w,3) uint8: the input thumbnail on the left, the render (or the backdrop) on the right."""
    right = np.empty_like(frame_rgb)
    right[:] = BACKDROP
    if render_rgb is not None and render_rgb.shape == frame_rgb.shape:
        right = render_rgb
    return np.concatenate([frame_rgb, right], axis=1)


class CameraComforts:
    """Follow-sensor, split view and reset-up controls; `update` after every snapshot."""

    def __init__(self, server: viser.ViserServer, worker: MappingWorker) -> None:
        self.server, self.worker = server, worker
        self.up: np.ndarray | None = None
        self._followed: int | None = None
        self._split_frame: int | None = None
        self._pending: Future[Any] | None = None
        gui = server.gui
        with gui.add_folder("Camera"):
            self.follow = gui.add_checkbox("Follow sensor", False, hint="Your camera rides with the sensor")
            self.split = gui.add_checkbox("Split view", False, hint="Input frame | render at the sensor's pose")
            reset = gui.add_button("Reset up direction", icon=viser.Icon.ARROW_BIG_UP)
            self.image = gui.add_image(np.zeros((8, 16, 3), np.uint8), label="input | render", visible=False)
        self.split.on_update(lambda _: self._on_toggle())
        self.follow.on_update(lambda _: self._on_toggle())
        reset.on_click(self._reset_up)

    def _reset_up(self, event: Any) -> None:
        snap = self.worker.slot.get()[1]
        up = self.up
        if up is None and snap is not None and snap.current_frame is not None:
            up = initial_view(snap.current_frame.T_world_camera)[0]
        if up is None:
            return
        self.server.scene.set_up_direction(up)
        clients = [event.client] if event.client is not None else list(self.server.get_clients().values())
        for client in clients:
            client.camera.up_direction = up

    def update(self, snap: MapSnapshot) -> None:
        """Follow the sensor and refresh the split view when `snap` brings a new frame."""
        frame = snap.current_frame
        if frame is None:
            return
        if self.follow.value and frame.index != self._followed:
            self._followed = frame.index
            for client in self.server.get_clients().values():
                fly_client(client, frame.T_world_camera)
        if self.split.value and frame.index != self._split_frame and self._pending is None:
            self._request_split(frame)

    def _on_toggle(self) -> None:
        """Act on a switched-on control at once (mapping may be paused or finished: no new snapshot would come)."""
        self._followed = self._split_frame = None
        self.image.visible = self.split.value
        snap = self.worker.slot.get()[1]
        if snap is not None:
            self.update(snap)

    def _request_split(self, frame: RgbdFrame) -> None:
        """Render the map at the sensor's pose at thumbnail size; the split view shows it when done."""
        self._split_frame = frame.index
        rgb, K = thumbnail(frame, SPLIT_WIDTH)
        h, w = rgb.shape[:2]
        reply = self.worker.submit("render", K=K, T_world_camera=frame.T_world_camera, height=h, width=w, mode="rgb")
        self._pending = reply
        reply.add_done_callback(lambda future: self._show_split(future, rgb))

    def _show_split(self, future: Future[Any], rgb: np.ndarray) -> None:
        render = None
        if not future.cancelled() and future.exception() is None:
            render = to_rgb8(future.result().image, "rgb", BACKDROP)
        self.image.image = split_image(rgb, render)
        self._pending = None
