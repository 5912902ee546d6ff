"""Compiled kernels loaded before a live stream starts, not while its first frames arrive.

The numba kernels are compiled once and cached on disk, but each process still loads every kernel at its first
call (~1 s for all of them on a 2-core laptop CPU; minutes when the cache is empty). In real-time mode that first
second of a stream would go to loading code while 30 frames arrive, and the frames beyond the backlog would be
dropped. `Mapper.warm_up` runs what mapping, a live step and mesh jobs run, once per configuration, on a throw-away
map of `scratch_frame`, before the stream is opened; `once` keeps the count.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from h2viz.types import RgbdFrame

_DONE: set[str] = set()  # configurations warmed up in this process (their kernels stay loaded)
_LOCK = threading.Lock()


def scratch_frame(width: int = 160, height: int = 120) -> RgbdFrame:
    """A small frame of a plane tilted across the view 1-2 m ahead, with a colour gradient."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    depth = 1.0 + u / width + 0.25 * v / height  # (H,W) metres
    rgb = np.stack([u / width * 255, v / height * 255, np.full_like(u, 128.0)], axis=-1).astype(np.uint8)
    K = np.array([[width, 0.0, width / 2], [0.0, width, height / 2], [0.0, 0.0, 1.0]])
    return RgbdFrame(0, 0.0, rgb, depth.astype(np.float32), K, np.eye(4))


def once(key: str, run: Callable[[], None]) -> float:
    """`run()` unless it ran for `key` before in this process; the seconds it took (0 when it had)."""
    with _LOCK:
        if key in _DONE:
            return 0.0
        start = time.perf_counter()
        run()
        _DONE.add(key)
        return time.perf_counter() - start
