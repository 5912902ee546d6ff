"""`h2viz replay RUN_DIR`: serve a recording with play / pause / scrub / step / speed, every browser on its own
timeline (its own scene layers and controls). NumPy and viser only: no torch, no mapper."""

from __future__ import annotations

import contextlib
import io
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import viser

from h2viz.viewer.layers import LayerSet
from h2viz.viewer.panels import build_layer_controls
from h2viz.viewer.recording import Recording
from h2viz.viewer.shapes import initial_view
from h2viz.viewer.status import progress_markdown
from h2viz.viewer.viser_server import make_viser_server

log = logging.getLogger("h2viz.replay")
SPEEDS = ("0.25x", "0.5x", "1x", "2x", "4x", "8x")
TICK_S = 0.02


class ReplaySession:
    """One browser's timeline: its own layers on its own scene, its own controls."""

    def __init__(self, client: Any, recording: Recording) -> None:
        self.client, self.recording = client, recording
        self.step = -1
        self.playing = False
        self.speed = 1.0
        self._due = 0.0  # time.monotonic() of the next step while playing
        self._lock = threading.RLock()  # moving the slider from here calls show() again
        scale = max(0.05, recording.snapshot(0).voxel_size_m)
        self.layers = LayerSet(client.scene, frustum_scale=scale)
        self._set_view()
        gui = client.gui
        n = len(recording)
        with gui.add_folder("Replay"):
            self.play = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
            self.slider = gui.add_slider("Step", 1, n, 1, 1, hint="Drag to scrub through the mapped frames")
            self.back = gui.add_button("Step back", icon=viser.Icon.PLAYER_TRACK_PREV)
            self.forward = gui.add_button("Step forward", icon=viser.Icon.PLAYER_TRACK_NEXT)
            self.speed_dropdown = gui.add_dropdown("Speed", SPEEDS, initial_value="1x")
            self.progress = gui.add_markdown("")
        build_layer_controls(gui, self.layers, points=False)
        self.play.on_click(lambda _: self.set_playing(not self.playing))
        self.slider.on_update(lambda _: self.show(int(self.slider.value) - 1))
        self.back.on_click(lambda _: self._nudge(-1))
        self.forward.on_click(lambda _: self._nudge(+1))
        self.speed_dropdown.on_update(lambda _: self._set_speed(self.speed_dropdown.value))
        self.show(0)

    def _set_view(self) -> None:
        first = next((s.current for s in self.recording.steps if s.current is not None), None)
        if first is None:
            return
        up, eye, target = initial_view(first.T_world_camera)
        self.client.scene.set_up_direction(up)
        self.client.camera.up_direction, self.client.camera.position, self.client.camera.look_at = up, eye, target

    def show(self, k: int) -> None:
        """Bring this browser's scene to step `k` (0-based, clamped)."""
        k = int(np.clip(k, 0, len(self.recording) - 1))
        with self._lock:
            if k == self.step:
                return
            snap = self.recording.snapshot(k)
            with self.client.atomic():
                self.layers.update(snap)
            self.step = k
            note = f"\n\n*{self.recording.problem}*" if self.recording.problem else ""
            self.progress.content = f"**Step {k + 1} / {len(self.recording)}**{note}\n\n{progress_markdown(snap)}"
            if int(self.slider.value) != k + 1:
                self.slider.value = k + 1

    def _nudge(self, delta: int) -> None:
        self.set_playing(False)
        self.show(self.step + delta)

    def _set_speed(self, label: str) -> None:
        self.speed = float(label.rstrip("x"))

    def set_playing(self, playing: bool) -> None:
        if playing and self.step >= len(self.recording) - 1:
            self.show(0)  # play again from the start
        self.playing = playing
        self._due = time.monotonic() + self.period
        self.play.label = "Pause" if playing else "Play"
        self.play.icon = viser.Icon.PLAYER_PAUSE if playing else viser.Icon.PLAYER_PLAY

    @property
    def period(self) -> float:
        return 1.0 / max(1e-3, self.recording.fps * self.speed)

    def tick(self, now: float) -> None:
        """Advance a playing timeline by the steps due at `now`; stop at the last step."""
        if not self.playing or now < self._due:
            return
        steps = 1 + int((now - self._due) / self.period)
        self._due += steps * self.period
        self.show(self.step + steps)
        if self.step >= len(self.recording) - 1:
            self.set_playing(False)


class ReplayServer:
    """Serves `recording` at http://host:port; each connecting browser gets a ReplaySession."""

    def __init__(self, recording: Recording, host: str = "127.0.0.1", port: int = 8080) -> None:
        self.recording = recording
        self.server = make_viser_server(host, port, label="h2viz replay")
        self.sessions: dict[int, ReplaySession] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="h2viz-replay", daemon=True)
        self.server.on_client_connect(self._attach)
        self.server.on_client_disconnect(lambda client: self.sessions.pop(client.client_id, None))
        self._thread.start()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.server.get_port()}"

    def _attach(self, client: Any) -> None:
        try:
            self.sessions[client.client_id] = ReplaySession(client, self.recording)
        except Exception:  # one browser's failure must not stop the others
            log.exception("replay for browser %d failed", client.client_id)

    def _run(self) -> None:
        while not self._stop.wait(TICK_S):
            now = time.monotonic()
            for session in list(self.sessions.values()):
                try:
                    session.tick(now)
                except Exception:
                    log.exception("replay step failed")
                    session.playing = False

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()


def run_replay(
    run_dir: Path, host: str = "127.0.0.1", port: int = 8080, on_ready: Callable[[str], None] | None = None
) -> None:
    """Serve RUN_DIR's recording until Ctrl-C."""
    replay = ReplayServer(Recording(run_dir), host, port)
    if on_ready is not None:
        on_ready(replay.url)
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        log.info("stopping the replay")
    finally:
        replay.stop()
