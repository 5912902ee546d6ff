"""The dashboard's fly-through panel: camera keyframes taken from the browser's camera (add / remove / reorder /
go to), a duration, the recorded-trajectory preset, a preview that flies the browser's camera along the path, and
an MP4 rendered from the neural field through the mapping worker with a progress bar (also saved as JSON for
`h2viz render-path`). The path is drawn in the scene: a line through the sampled cameras and one frustum per
keyframe."""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import viser

from h2viz.errors import H2vizError
from h2viz.viewer.camera_path import CameraPath, trajectory_path
from h2viz.viewer.shapes import pose_from_wxyz, trajectory_segments, wxyz_position
from h2viz.viewer.status import notify
from h2viz.viewer.video import render_path_video
from h2viz.worker import MappingWorker

log = logging.getLogger("h2viz.viewer")
PATH_COLOR = (120, 255, 140)
FRAME_TIMEOUT_S = 600.0


def fly_client(client: Any, T_world_camera: np.ndarray) -> None:
    """Put a browser's camera at a pose (OpenCV axes), looking where the pose looks."""
    wxyz, position = wxyz_position(T_world_camera)
    with client.atomic():
        client.camera.wxyz = wxyz
        client.camera.position = position


class FlythroughPanel:
    """Builds the fly-through folder on `gui` (inside the caller's tab) and owns the path."""

    def __init__(self, server: viser.ViserServer, worker: MappingWorker, out_dir: Path, width: int, fps: int) -> None:
        self.server, self.worker, self.out_dir = server, worker, out_dir
        self.path = CameraPath(fps=fps, width=width, height=_even(width * 3 / 4))
        self.videos: list[Path] = []
        self._busy = threading.Lock()
        self._handles: list[Any] = []
        gui = server.gui
        with gui.add_folder("Fly-through video", expand_by_default=False):
            self.add = gui.add_button("Add this view", icon=viser.Icon.CAMERA_PLUS, hint="Your camera as a keyframe")
            self.selected = gui.add_dropdown("Keyframe", ("none",), hint="The keyframe the buttons below act on")
            row = gui.add_button_group("Edit", ("Go to", "Up", "Down", "Remove"))
            self.duration = gui.add_number("Duration (s)", self.path.duration_s, min=0.5, max=600.0, step=0.5)
            widths = tuple(str(w) for w in sorted({320, 640, 1280, 1920, width}))
            self.width = gui.add_dropdown("Width", widths, initial_value=str(width), hint="Video width in pixels")
            preset = gui.add_button("Use recorded trajectory", icon=viser.Icon.ROUTE, hint="Fly along the sensor")
            preview = gui.add_button("Preview", icon=viser.Icon.PLAYER_PLAY, hint="Fly your camera along the path")
            self.render = gui.add_button("Render MP4", icon=viser.Icon.MOVIE, hint="From the neural field")
            self.progress = gui.add_progress_bar(0.0, visible=False)
            self.info = gui.add_markdown("No keyframes yet.")
        self.add.on_click(self._add)
        row.on_click(lambda e: self._edit(e, row.value))
        self.duration.on_update(lambda _: self._set(duration_s=float(self.duration.value)))
        self.width.on_update(lambda _: self._set(width=int(self.width.value)))
        preset.on_click(self._preset)
        preview.on_click(self._preview)
        self.render.on_click(self._render)

    # -- editing -------------------------------------------------------------------------------
    def _set(self, **values: Any) -> None:
        if "width" in values:
            aspect = self.path.width / self.path.height
            values["height"] = _even(values["width"] / aspect)
        for key, value in values.items():
            setattr(self.path, key, value)
        self._refresh()

    def _add(self, event: Any) -> None:
        client = event.client
        if client is None:
            return
        cam = client.camera
        if not self.path.keyframes:  # the first keyframe fixes the field of view and the aspect
            self.path.fov_deg = float(np.rad2deg(cam.fov))
            aspect = cam.image_width / max(1, cam.image_height)
            self.path.height = _even(self.path.width / aspect)
        at = self._index() + 1 if self._index() is not None else None
        self.path.add(cam.wxyz, cam.position, at)
        self._refresh(select=len(self.path.keyframes) - 1 if at is None else at)

    def _index(self) -> int | None:
        value = self.selected.value
        return int(value) - 1 if value.isdigit() and int(value) <= len(self.path.keyframes) else None

    def _edit(self, event: Any, action: str) -> None:
        i = self._index()
        if i is None:
            return
        if action == "Remove":
            self.path.keyframes.pop(i)
            self._refresh(select=min(i, len(self.path.keyframes) - 1))
        elif action in ("Up", "Down"):
            self.path.move(i, -1 if action == "Up" else 1)
            self._refresh(select=int(np.clip(i + (-1 if action == "Up" else 1), 0, len(self.path.keyframes) - 1)))
        elif action == "Go to" and event.client is not None:
            kf = self.path.keyframes[i]
            fly_client(event.client, pose_from_wxyz(np.array(kf.wxyz), np.array(kf.position)))

    def _preset(self, event: Any) -> None:
        snap = self.worker.slot.get()[1]
        try:
            if snap is None or snap.current_frame is None:
                raise H2vizError("no frames mapped yet")
            frame = snap.current_frame
            preset = trajectory_path(snap.trajectory, frame.K, frame.height)
        except H2vizError as e:
            notify(event, "No trajectory", str(e), error=True)
            return
        preset.fps, preset.width = self.path.fps, self.path.width
        preset.height = _even(self.path.width * frame.height / frame.width)
        self.path = preset
        self.duration.value = preset.duration_s
        self._refresh(select=0)

    def _refresh(self, select: int | None = None) -> None:
        n = len(self.path.keyframes)
        options = tuple(str(i + 1) for i in range(n)) or ("none",)
        self.selected.options = options
        if select is not None and n:
            self.selected.value = str(select + 1)
        p = self.path
        self.info.content = (
            f"{n} keyframes, {p.n_frames} frames at {p.fps} fps, {p.width}x{p.height}" if n else "No keyframes yet."
        )
        self._draw()

    def _draw(self) -> None:
        """The path in the scene: its sampled cameras as a line, a frustum per keyframe."""
        for handle in self._handles:
            handle.remove()
        self._handles = []
        if not self.path.keyframes:
            return
        scene = self.server.scene
        poses = self.path.poses(max(2, min(self.path.n_frames, 300)))
        segments = trajectory_segments(poses)
        self._handles.append(scene.add_line_segments("/flythrough/path", segments, PATH_COLOR, thickness=3.0))
        aspect = self.path.width / self.path.height
        for i, kf in enumerate(self.path.keyframes):
            frustum = scene.add_camera_frustum(
                f"/flythrough/kf_{i:03d}",
                np.deg2rad(self.path.fov_deg),
                aspect,
                scale=0.15,
                color=PATH_COLOR,
                wxyz=np.array(kf.wxyz),
                position=np.array(kf.position),
            )
            self._handles.append(frustum)

    # -- preview and render --------------------------------------------------------------------
    def _preview(self, event: Any) -> None:
        client = event.client
        if client is None or not self.path.keyframes:
            return
        period = 1.0 / self.path.fps
        for T in self.path.poses():
            fly_client(client, T)
            time.sleep(period)

    def _render(self, event: Any) -> None:
        if not self.path.keyframes or not self._busy.acquire(blocking=False):
            return
        self.render.disabled, self.progress.visible, self.progress.value = True, True, 0.0
        out = self.out_dir / f"flythrough_{time.strftime('%Y%m%d-%H%M%S')}.mp4"
        try:
            render_path_video(self._render_frame, self.path, out, self._on_frame)
            self.path.save(out.with_suffix(".json"))
            self.videos.append(out)
            if event.client is not None:
                event.client.send_file_download(out.name, out.read_bytes(), save_immediately=True)
            notify(event, "Video rendered", f"{out} ({self.path.n_frames} frames)")
        except Exception as e:
            log.warning("fly-through video failed: %s", e)
            notify(event, "Video failed", str(e), error=True)
        finally:
            self.render.disabled, self.progress.visible = False, False
            self._busy.release()

    def _render_frame(self, K: np.ndarray, T: np.ndarray, height: int, width: int) -> np.ndarray:
        reply = self.worker.submit("render", K=K, T_world_camera=T, height=height, width=width, mode="rgb")
        return reply.result(timeout=FRAME_TIMEOUT_S).image

    def _on_frame(self, done: int, total: int) -> None:
        self.progress.value = 100.0 * done / total


def _even(x: float) -> int:
    return max(16, 2 * int(round(x / 2)))
