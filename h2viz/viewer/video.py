"""Fly-through videos: each camera of a CameraPath rendered from the neural field by a render function and written
as H.264 MP4 with PyAV. `render_path_video` serves both the dashboard (renders through the mapping worker) and
`h2viz render-path` (a mapper loaded from a run's checkpoint)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import av
import numpy as np

from h2viz.viewer.camera_path import CameraPath, CameraPathError
from h2viz.viewer.shapes import to_rgb8

# (K (3,3), T_world_camera (4,4), height, width) -> colour image (H,W,3) float in [0,1]
RenderFn = Callable[[np.ndarray, np.ndarray, int, int], np.ndarray]
BACKDROP = (28, 30, 36)


class VideoWriter:
    """An H.264 MP4 written frame by frame from (H,W,3) uint8 images."""

    def __init__(self, path: Path, width: int, height: int, fps: int, crf: int = 18) -> None:
        try:
            self._container = av.open(str(path), mode="w")
        except (OSError, av.error.FFmpegError) as e:
            raise CameraPathError(f"cannot write the video {path}: {e}") from e
        self._stream = self._container.add_stream("libx264", rate=int(fps))
        self._stream.width, self._stream.height, self._stream.pix_fmt = width, height, "yuv420p"
        self._stream.options = {"crf": str(crf), "preset": "medium"}
        self.frames = 0

    def write(self, image: np.ndarray) -> None:
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image, dtype=np.uint8), format="rgb24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()


def render_path_video(
    render: RenderFn,
    path: CameraPath,
    out: Path,
    on_frame: Callable[[int, int], None] | None = None,
    stop: Callable[[], bool] | None = None,
) -> Path:
    """Render every frame of `path` with `render` into the MP4 `out`; `on_frame(done, total)` after each."""
    poses = path.poses()
    K = path.K()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    writer = VideoWriter(out, path.width, path.height, path.fps)
    try:
        for i, T in enumerate(poses):
            if stop is not None and stop():
                raise CameraPathError("video rendering was cancelled")
            writer.write(to_rgb8(render(K, T, path.height, path.width), "rgb", BACKDROP))
            if on_frame is not None:
                on_frame(i + 1, len(poses))
    finally:
        writer.close()
    return out


def read_video(path: Path) -> list[np.ndarray]:
    """Every frame of a video as (H,W,3) uint8 (for checks and previews)."""
    with av.open(str(path)) as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
