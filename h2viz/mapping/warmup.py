"""Compiled kernels loaded before a live stream starts, not while its first frames arrive.

The numba kernels are compiled once and cached on disk, but each process still loads every kernel at its first
call (~1 s for all of them on a 2-core laptop CPU; minutes when the cache is empty). In real-time mode that first
second of a stream would go to loading code while 30 frames arrive, and the frames beyond the backlog would be
dropped. `warm_up` runs what mapping, a live step and a mesh job run, once, on a throw-away map of a small
synthetic frame, before the stream is opened.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from h2viz.config import MappingConfig
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


def warm_up(cfg: MappingConfig) -> float:
    """Load (or compile) the kernels that mapping with `cfg` runs, once per process and configuration: integrate a
    scratch frame in both modes, take a live step, mesh the result whole and update that mesh. Returns the seconds
    it took (0 when this configuration was warmed up before)."""
    from h2viz.mapping.mapper import Mapper  # torch and numba load here, not with the worker

    key = repr(cfg)
    with _LOCK:
        if key in _DONE:
            return 0.0
        start = time.perf_counter()
        mapper = Mapper(cfg)
        frame = scratch_frame()
        mapper.add_frame(frame)
        mapper.live_step()
        mapper.integrate(frame)  # every-frame mode: the same stages with its own steps
        for whole in (True, False):  # a whole mesh, then a live update against it
            mapper.touched[:] = True
            job = mapper.mesh_job(0.03, whole=whole)
            assert job is not None  # voxels were touched
            job.run()
        _DONE.add(key)
        return time.perf_counter() - start
