"""A recording as one standalone HTML file: the steps are drawn, in order, by the dashboard's own layers into a
scene that no browser watches while viser's scene serializer notes every message, one step per 1/fps seconds of
its timeline; viser's client, inlined in the page, plays that timeline back (play / pause / scrub / speed) with no
server and no network. Also the same timeline as a `.viser` file for viser's own player."""

from __future__ import annotations

import contextlib
import io
from collections.abc import Callable
from pathlib import Path

import numpy as np

from h2viz.viewer.layers import LayerSet
from h2viz.viewer.recording import Recording, RecordingError
from h2viz.viewer.shapes import initial_view
from h2viz.viewer.viser_server import make_viser_server

STEP_LABEL = "/replay/step"  # a label naming the step shown ("step k / N"), which the page also shows


def step_text(k: int, n: int) -> str:
    return f"step {k + 1} / {n}"


def _serializer(
    recording: Recording, fps: float | None, on_step: Callable[[int], None] | None
) -> tuple[object, Callable[[], None]]:
    """A scene serializer holding the whole timeline, and the function that stops its server."""
    server = make_viser_server("127.0.0.1", 0, label="h2viz recording")
    first = next((s.current for s in recording.steps if s.current is not None), None)
    if first is not None:
        up, eye, target = initial_view(first.T_world_camera)
        server.scene.set_up_direction(up)
        server.initial_camera.up, server.initial_camera.position, server.initial_camera.look_at = up, eye, target
    serializer = server.get_scene_serializer()
    layers = LayerSet(server.scene, frustum_scale=max(0.05, recording.snapshot(0).voxel_size_m))
    period = 1.0 / max(1e-3, fps or recording.fps)
    n = len(recording)
    for k in range(n):
        snap = recording.snapshot(k)
        layers.update(snap)
        anchor = snap.current_frame.T_world_camera[:3, 3] if snap.current_frame is not None else np.zeros(3)
        server.scene.add_label(STEP_LABEL, step_text(k, n), position=anchor)
        serializer.insert_sleep(period)  # type: ignore[attr-defined]
        if on_step is not None:
            on_step(k)

    def stop() -> None:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()

    return serializer, stop


def recording_html(recording: Recording, fps: float | None = None, on_step: Callable[[int], None] | None = None) -> str:
    """The recording as a standalone HTML document (`fps` steps per second of playback at 1x)."""
    serializer, stop = _serializer(recording, fps, on_step)
    try:
        return serializer.as_html(dark_mode=True)  # type: ignore[attr-defined]
    finally:
        stop()


def recording_viser(recording: Recording, fps: float | None = None) -> bytes:
    """The recording as a `.viser` file (viser's own player opens it with ?playbackPath=...)."""
    serializer, stop = _serializer(recording, fps, None)
    try:
        return serializer.serialize()  # type: ignore[attr-defined]
    finally:
        stop()


def export_html(run_dir: Path, out: Path | None = None, fps: float | None = None) -> Path:
    """Write RUN_DIR's recording as one HTML file (default: RUN_DIR/recording.html); returns its path."""
    recording = Recording(run_dir)
    out = Path(out) if out is not None else recording.folder.parent / "recording.html"
    if out.suffix.lower() == ".viser":
        data = recording_viser(recording, fps)
    else:
        data = recording_html(recording, fps).encode()
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(data)
    except OSError as e:
        raise RecordingError(f"cannot write {out}: {e}") from e
    return out
