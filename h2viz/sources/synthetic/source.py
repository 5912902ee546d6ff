"""The built-in synthetic source: a procedural living room (see scene.py) seen by a hand-held-like
camera that circles the room centre, rendered by ray casting with exact z-depth.

Everything is deterministic from `source.synthetic.seed`: the room, its textures, the trajectory and
the depth noise (seeded per frame). Frames can be rendered ahead in a background thread, and rendered
frames are kept on disk (frame_cache.py): iterating the source yields exactly the same frames either way.
Real-time playback has the frames it will play rendered first (`prepare_playback`), so that the room
plays at 30 Hz like a camera.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Hashable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, as_completed
from pathlib import Path

import numpy as np
import trimesh

from h2viz.config import SourceConfig
from h2viz.errors import FrameError, SourceError
from h2viz.sources.base import FrameSource, Progress, StopCheck
from h2viz.sources.synthetic.frame_cache import FrameCache
from h2viz.sources.synthetic.scene import Scene, build_scene
from h2viz.sources.synthetic.trajectory import trajectory
from h2viz.types import RgbdFrame

FPS = 30.0  # timestamps are frame index / FPS
log = logging.getLogger("h2viz.sources")


def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """Pinhole K (3,3) with square pixels from the horizontal field of view, principal point at the centre."""
    f = (width / 2.0) / np.tan(np.radians(fov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


class SyntheticSource(FrameSource):
    """Frames of the procedural room along the built-in trajectory (the default source)."""

    format_name = "synthetic"

    def __init__(self, cfg: SourceConfig) -> None:
        super().__init__(cfg)
        sc = cfg.synthetic
        if sc.width < 8 or sc.height < 8 or not 1.0 < sc.fov_deg < 170.0:
            raise SourceError(
                f"synthetic source: image {sc.width}x{sc.height} with fov {sc.fov_deg} deg is not usable; "
                "set source.synthetic.width/height >= 8 and 1 < fov_deg < 170"
            )
        if sc.n_frames < 1 or sc.depth_noise_m < 0 or sc.prefetch < 0:
            raise SourceError("synthetic source: n_frames must be >= 1, depth_noise_m and prefetch >= 0")
        self.scene: Scene = build_scene(sc.seed, sc.recipe)
        self.K = intrinsics(sc.width, sc.height, sc.fov_deg)
        self.poses = trajectory(self.scene, sc.n_frames)  # (n,4,4)
        self.cache = FrameCache.for_config(sc)  # None: source.synthetic.cache is off
        self._pending: dict[int, Future[RgbdFrame]] = {}
        self._expected: int | None = None  # the key a sequential reader asks for next
        self._pool: ThreadPoolExecutor | None = None
        self._lock = threading.Lock()

    @staticmethod
    def looks_like(path: Path) -> bool:
        """The synthetic scene is never detected from a path (it is chosen by an empty path)."""
        return False

    def describe(self) -> str:
        sc = self.cfg.synthetic
        return f"synthetic room (seed {sc.seed}, {sc.n_frames} frames, {sc.width}x{sc.height})"

    def keys(self) -> Sequence[Hashable]:
        return range(self.cfg.synthetic.n_frames)

    def timestamp(self, position: int, key: Hashable) -> float | None:
        return int(key) / FPS  # type: ignore[call-overload]

    def load(self, position: int, key: Hashable) -> RgbdFrame:
        if not isinstance(key, int) or not 0 <= key < len(self.poses):
            raise FrameError(f"synthetic frame {key!r}: no such frame (0..{len(self.poses) - 1})")
        with self._lock:
            future = self._pending.pop(key, None)
        frame = future.result() if future is not None else self.render_frame(key)
        self._prefetch_after(key)
        return frame

    def render_frame(self, index: int) -> RgbdFrame:
        """Frame `index` of the trajectory, with the configured depth noise (seeded by seed and index)."""
        sc = self.cfg.synthetic
        rgb, depth = self._rendered(index)
        if sc.depth_noise_m > 0:
            rng = np.random.default_rng([sc.seed, index])
            valid = depth > 0
            noise = rng.normal(0.0, sc.depth_noise_m, depth.shape).astype(np.float32)
            depth = np.where(valid, np.maximum(depth + noise, 1e-3), 0.0).astype(np.float32)
        return RgbdFrame(
            index=index,
            timestamp=index / FPS,
            rgb=rgb,
            depth_m=depth,
            K=self.K.copy(),
            T_world_camera=self.poses[index].copy(),
            name=f"synthetic frame {index}",
        )

    def _rendered(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """The noise-free rgb (H,W,3) uint8 and depth (H,W) float32 of frame `index`: from the cache, else rendered
        (and cached)."""
        cached = self.cache.get(index) if self.cache is not None else None
        if cached is not None:
            return cached
        sc = self.cfg.synthetic
        rgb, depth = self.scene.render(self.K, self.poses[index], sc.height, sc.width)
        if self.cache is not None:
            self.cache.put(index, rgb, depth)
        return rgb, depth

    def prepare_playback(self, keys: Sequence[Hashable], progress: Progress = None, stop: StopCheck = None) -> None:
        """Render the frames of `keys` not cached yet (on every core), so that real-time playback reads each in a few
        milliseconds instead of rendering it in ~0.2 s, which would pass over most of a 30 Hz stream. Nothing to do
        once they are cached, or when the cache is off or cannot be written (frames are then rendered as read)."""
        cache = self.cache
        if cache is None or not cache.writable:
            return
        missing = [k for k in keys if isinstance(k, int) and 0 <= k < len(self.poses) and not cache.has(k)]
        if not missing:
            return
        log.info("rendering %d synthetic frames for real-time playback, once: cached in %s", len(missing), cache.folder)
        with ThreadPoolExecutor(max_workers=os.cpu_count() or 1, thread_name_prefix="h2viz-synthetic") as pool:
            pending = [pool.submit(self._render_missing, k, stop) for k in missing]
            for done, future in enumerate(as_completed(pending), 1):
                future.result()
                if progress is not None:
                    progress(done, len(missing))
                if stop is not None and stop():
                    for f in pending:
                        f.cancel()
                    break

    def _render_missing(self, index: int, stop: StopCheck) -> None:
        if (stop is None or not stop()) and self.cache is not None and not self.cache.has(index):
            self._rendered(index)

    def _prefetch_after(self, key: int) -> None:
        """Start rendering the next `prefetch` selected frames after `key` in the background, while frames are
        read in order (a reader passing over frames, as real-time playback does, would not use them)."""
        n = self.cfg.synthetic.prefetch
        if n <= 0:
            return
        upcoming = [k for _, k in self.selected() if isinstance(k, int) and k > key][:n]
        with self._lock:
            jumped = self._expected is not None and key != self._expected
            self._expected = upcoming[0] if upcoming else None
            for stale in [k for k in self._pending if k <= key or jumped]:
                self._pending.pop(stale).cancel()
            if jumped:
                return
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="h2viz-synthetic")
            for k in upcoming:
                if k not in self._pending:
                    self._pending[k] = self._pool.submit(self.render_frame, k)

    def close(self) -> None:
        """Stop background rendering (pending frames are dropped; they are re-rendered on demand)."""
        with self._lock:
            for future in self._pending.values():
                future.cancel()
            self._pending.clear()
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)

    def ground_truth_mesh(self) -> trimesh.Trimesh:
        """The whole room as one mesh with vertex colours (a copy; safe to modify)."""
        return self.scene.mesh.copy()

    def render_view(
        self, K: np.ndarray, T_world_camera: np.ndarray, height: int, width: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free rgb (H,W,3) uint8 and z-depth (H,W) float32 (0 = nothing hit) for any pinhole camera."""
        return self.scene.render(K, T_world_camera, height, width)

    def scene_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Min and max corners (3,) of the scene in world metres."""
        return self.scene.bounds()
