"""Recording a headless run (`h2viz map --record`): after each frame the changed chunks are meshed on the mapping
thread and the map's snapshot goes to a Recorder, one step per frame (the live worker records from its own
snapshots instead)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from h2viz.types import FrameStats, MapSnapshot, RgbdFrame
from h2viz.viewer.recording import BackgroundRecorder, Recorder
from h2viz.worker.mapping_worker import REFRESH_S, rss_mb

if TYPE_CHECKING:
    from h2viz.mapping.mapper import Mapper


class RunRecorder:
    """Follows `mapper` through a run and records it into `folder`."""

    def __init__(self, mapper: Mapper, folder: Path, frames_total: int | None, fps: float = 10.0) -> None:
        self.mapper, self.frames_total = mapper, frames_total
        self.recorder = BackgroundRecorder(Recorder(folder, fps))
        self.stats: list[FrameStats] = []
        self.poses: list[np.ndarray] = []
        self.current: RgbdFrame | None = None
        self.seconds = 0.0  # spent meshing and handing over steps (the recording's cost to the run)

    def after_frame(self, frame: RgbdFrame, stats: FrameStats) -> None:
        """Mesh what the frame changed (for up to REFRESH_S more of the stalest chunks) and record the map."""
        t0 = time.perf_counter()
        self.stats.append(stats)
        self.poses.append(frame.T_world_camera)
        self.current = frame
        job = self.mapper.mesh_job(REFRESH_S)
        if job is not None:
            job.run()
        self.recorder.offer(self.snapshot(finished=False))
        self.seconds += time.perf_counter() - t0

    def finish(self) -> Path:
        """Record the final map (every chunk re-meshed) as the last frame's step; returns the folder."""
        self.mapper.update_mesh()
        if self.stats:
            self.recorder.offer(self.snapshot(finished=True))
        return self.recorder.close()

    def snapshot(self, finished: bool) -> MapSnapshot:
        m = self.mapper
        return MapSnapshot(
            version=len(self.stats),
            frames_done=len(self.stats),
            frames_total=self.frames_total,
            chunks=dict(m.mesh_chunks()),
            voxel_size_m=float(m.voxel_size_m),
            voxel_coords=np.asarray(m.voxel_coords(), dtype=np.int32).reshape(-1, 3),
            keyframes=tuple(m.keyframe_infos()),
            trajectory=np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4),
            current_frame=self.current,
            stats=tuple(self.stats),
            finished=finished,
            memory_mb=rss_mb(),
        )
