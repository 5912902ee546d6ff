"""Novel views: each browser's camera is rendered by the mapping worker (render Commands, served in
row bands between optimisation steps) and shown as that browser's background image with depth, so
mesh, frustums and lines composite with it. Low resolution while the camera moves, refined when it
rests, refreshed now and then while the map grows; plus full-resolution renders for download."""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import viser

from h2viz.errors import H2vizError
from h2viz.viewer.shapes import pose_from_wxyz, to_rgb8, view_intrinsics
from h2viz.worker import MappingWorker, RenderedView

log = logging.getLogger("h2viz.viewer")
MODES = ("off", "rgb", "depth", "normal", "prior")
BACKDROP = (28, 30, 36)  # colour of pixels where the map has nothing
FAR_M = 160.0  # depth given to empty pixels (the background's depth encoding tops out at 167 m)


@dataclass(frozen=True)
class ViewRequest:
    """One camera to render: pose, intrinsics and size (OpenCV axes)."""

    T_world_camera: np.ndarray
    K: np.ndarray
    width: int
    height: int

    def key(self) -> tuple[float, ...]:
        return tuple(np.round(self.T_world_camera[:3].ravel(), 4)) + (
            round(float(self.K[1, 1]), 2),
            self.width,
        )


def client_view(camera: Any, width: int) -> ViewRequest | None:
    """The browser camera as a ViewRequest `width` pixels wide (None before its first report)."""
    try:
        wxyz, position, fov = camera.wxyz, camera.position, camera.fov
        aspect = camera.image_width / max(camera.image_height, 1)
    except AssertionError:  # no camera message received yet
        return None
    width = max(8, int(width))
    height = max(8, int(round(width / max(aspect, 1e-3))))
    return ViewRequest(pose_from_wxyz(wxyz, position), view_intrinsics(fov, width, height), width, height)


def background(view: RenderedView) -> tuple[np.ndarray, np.ndarray]:
    """(H,W,3) uint8 image and (H,W) depth for set_background_image; empty pixels go far away."""
    image = to_rgb8(view.image, view.mode, BACKDROP)
    depth = view.depth_m if view.depth_m is not None else np.zeros(image.shape[:2], np.float32)
    return image, np.where(depth > 0, depth, FAR_M).astype(np.float32)


@dataclass
class _ClientState:
    client: Any
    camera_key: tuple[float, ...] | None = None
    camera_t: float = 0.0  # when the camera last moved
    pending: Future[Any] | None = None
    pending_info: tuple[tuple[float, ...], str, bool] | None = None  # (camera key, mode, refined)
    shown: tuple[tuple[float, ...], str, bool] | None = None
    shown_version: int = 0
    shown_t: float = 0.0


class RenderLoop:
    """Keeps every connected browser's background in step with its camera and the chosen mode."""

    def __init__(self, server: viser.ViserServer, worker: MappingWorker, render_width: int = 640) -> None:
        self.server, self.worker = server, worker
        self.mode = "off"
        self.refined_width = render_width
        self.moving_width = max(32, render_width // 4)
        self.rest_s = 0.3  # the camera counts as resting after this long without motion
        self.refresh_s = 5.0  # re-render a resting view this often while the map changes (0 = never)
        self.renders_shown = 0
        self._states: dict[int, _ClientState] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="h2viz-renders", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        for state in self._states.values():
            if state.pending is not None:
                state.pending.cancel()

    def set_mode(self, mode: str) -> None:
        self.mode = mode if mode in MODES else "off"

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            clients = self.server.get_clients()
            for cid in set(self._states) - set(clients):
                self._states.pop(cid)
            for cid, client in clients.items():
                state = self._states.setdefault(cid, _ClientState(client))
                try:
                    self._tick(state, time.monotonic())
                except Exception:  # one browser's failure must not stop the others
                    log.exception("background render for client %d failed", cid)
                    state.pending = None

    def _tick(self, st: _ClientState, now: float) -> None:
        if self.mode == "off":
            if st.shown is not None:
                st.client.scene.set_background_image(None)
                st.shown = None
            return
        view = client_view(st.client.camera, self.refined_width)
        if view is None:
            return
        key = view.key()
        if key != st.camera_key:
            st.camera_key, st.camera_t = key, now
        if st.pending is not None and not self._collect(st, key, now):
            return
        version = self.worker.slot.get()[0]
        resting = now - st.camera_t >= self.rest_s
        if st.shown is None or st.shown[0] != key or st.shown[1] != self.mode:
            self._submit(st, view, key, refined=resting)
        elif resting and not st.shown[2]:
            self._submit(st, view, key, refined=True)
        elif resting and 0 < self.refresh_s <= now - st.shown_t and version > st.shown_version:
            self._submit(st, view, key, refined=True)

    def _collect(self, st: _ClientState, key: tuple[float, ...], now: float) -> bool:
        """Show a finished render; cancel a refined one the camera has left. True when free."""
        assert st.pending is not None and st.pending_info is not None
        if not st.pending.done():
            if st.pending_info[2] and st.pending_info[0] != key:
                st.pending.cancel()
                st.pending = None
                return True
            return False
        future, info = st.pending, st.pending_info
        st.pending = None
        if future.cancelled() or future.exception() is not None:
            return True
        if info[1] == self.mode:
            image, depth = background(future.result())
            st.client.scene.set_background_image(image, format="jpeg", jpeg_quality=85, depth=depth)
            st.shown, st.shown_t = info, now
            self.renders_shown += 1
        return True

    def _submit(self, st: _ClientState, view: ViewRequest, key: tuple[float, ...], refined: bool) -> None:
        width = self.refined_width if refined else self.moving_width
        scale = width / view.width
        height = max(8, int(round(view.height * scale)))
        K = view_intrinsics(2 * np.arctan2(0.5 * view.height, view.K[1, 1]), width, height)
        st.shown_version = self.worker.slot.get()[0]
        st.pending_info = (key, self.mode, refined)
        st.pending = self.worker.submit(
            "render",
            K=K,
            T_world_camera=view.T_world_camera,
            height=height,
            width=width,
            mode=self.mode,
            with_depth=True,
            depth_downscale=2,  # the depth only places the image among the scene nodes
        )


def render_png(
    worker: MappingWorker, camera: Any, mode: str, max_width: int = 1920, timeout_s: float = 600.0
) -> bytes:
    """A full-resolution render of a browser's view as PNG bytes (mode 'off' renders colour)."""
    width = min(max_width, int(camera.image_width))
    view = client_view(camera, width)
    if view is None:
        raise H2vizError("render: the browser has not reported its camera yet; try again in a moment")
    mode = "rgb" if mode == "off" else mode
    reply = worker.submit(
        "render",
        K=view.K,
        T_world_camera=view.T_world_camera,
        height=view.height,
        width=view.width,
        mode=mode,
    )
    image = to_rgb8(reply.result(timeout=timeout_s).image, mode, BACKDROP)
    ok, png = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]))
    if not ok:
        raise H2vizError("render: PNG encoding of the rendered view failed")
    return png.tobytes()
