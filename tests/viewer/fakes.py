"""Small stand-ins for tests: an analytic box room as a FrameSource, and a mapper with the Mapper
API whose map is the union of voxels the depth hit, meshed as one cube per voxel."""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh

from h2viz.config import MappingConfig, SourceConfig
from h2viz.errors import FrameError
from h2viz.geometry import camera_rays, look_at
from h2viz.sources.base import FrameSource
from h2viz.types import FrameStats, KeyframeInfo, KeyframeState, MapSnapshot, MeshChunk, RgbdFrame

ROOM_MIN = np.array([-2.0, -1.5, 0.0])
ROOM_MAX = np.array([2.0, 1.5, 2.5])


def intrinsics(width: int, height: int, fov_deg: float = 70.0) -> np.ndarray:
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def room_pose(i: int, n: int) -> np.ndarray:
    """T_world_camera of frame i of n: a slow turn in the middle of the room."""
    a = 2 * np.pi * i / max(n, 1) * 0.75
    eye = np.array([0.3 * np.cos(a), 0.3 * np.sin(a), 1.3])
    return look_at(eye, eye + np.array([np.cos(a), np.sin(a), -0.25]))


def trace_room(K: np.ndarray, T_world_camera: np.ndarray, height: int, width: int) -> tuple[np.ndarray, ...]:
    """z-depth (H,W), world hit points (H,W,3) and face normals (H,W,3) of the room's inside."""
    d_cam = camera_rays(K, height, width)  # (H,W,3), z = 1
    d = d_cam @ T_world_camera[:3, :3].T
    o = T_world_camera[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_axes = np.where(d > 0, (ROOM_MAX - o) / d, (ROOM_MIN - o) / d)  # (H,W,3)
    t_axes = np.where(np.isfinite(t_axes) & (t_axes > 0), t_axes, np.inf)
    axis = np.argmin(t_axes, axis=-1)  # (H,W)
    t = np.take_along_axis(t_axes, axis[..., None], -1)[..., 0]
    hits = o + d * t[..., None]
    normals = np.zeros_like(hits)
    np.put_along_axis(normals, axis[..., None], -np.sign(np.take_along_axis(d, axis[..., None], -1)), -1)
    return t.astype(np.float32), hits, normals


def room_color(points: np.ndarray) -> np.ndarray:
    """Checker texture (...,3) uint8 of world points."""
    cells = np.floor(points * 2.0).astype(np.int64)
    checker = (cells.sum(axis=-1) % 2)[..., None]
    base = np.clip(np.abs(points) / 3.0, 0, 1)
    return (255 * (0.35 + 0.4 * base + 0.25 * checker) / 1.0).clip(0, 255).astype(np.uint8)


class BoxRoomSource(FrameSource):
    """n frames of the analytic room at width x height; `fail_keys` raise FrameError on load."""

    format_name = "box-room"

    def __init__(self, n: int = 12, width: int = 64, height: int = 48, fail_keys: Sequence[int] = ()) -> None:
        super().__init__(SourceConfig(format="synthetic"))
        self.n, self.width, self.height, self.fail_keys = n, width, height, set(fail_keys)

    def keys(self) -> Sequence[Hashable]:
        return list(range(self.n))

    def timestamp(self, position: int, key: Hashable) -> float:
        return int(key) / 30.0  # type: ignore[call-overload]

    def load(self, position: int, key: Hashable) -> RgbdFrame:
        i = int(key)  # type: ignore[call-overload]
        if i in self.fail_keys:
            raise FrameError(f"room frame {i}: unreadable on purpose")
        K = intrinsics(self.width, self.height)
        T = room_pose(i, self.n)
        depth, hits, _ = trace_room(K, T, self.height, self.width)
        return RgbdFrame(i, self.timestamp(position, key), room_color(hits), depth, K, T, name=f"room/{i}")

    def ground_truth_mesh(self) -> trimesh.Trimesh:
        return trimesh.creation.box(bounds=np.stack([ROOM_MIN, ROOM_MAX]))


def cube_mesh(voxels: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8V,3) and faces (12V,3) of one cube per voxel (V,3)."""
    box = trimesh.creation.box(bounds=[[0, 0, 0], [1, 1, 1]])
    verts = (voxels[:, None, :] + np.asarray(box.vertices)[None]) * size  # (V,8,3)
    faces = np.asarray(box.faces)[None] + 8 * np.arange(len(voxels))[:, None, None]  # (V,12,3)
    return verts.reshape(-1, 3).astype(np.float32), faces.reshape(-1, 3).astype(np.int32)


class FakeMapper:
    """The Mapper API over a voxel set; `delay_s` mimics optimisation time, `fail_frames` raise."""

    def __init__(self, voxel_size_m: float = 0.2, chunk_voxels: int = 4, delay_s: float = 0.0) -> None:
        self.voxel_size_m, self.chunk_voxels, self.delay_s = voxel_size_m, chunk_voxels, delay_s
        self.fail_frames: set[int] = set()
        self.mesh_calls = 0
        self._voxels = np.zeros((0, 3), dtype=np.int32)
        self._chunks: dict[tuple[int, int, int], MeshChunk] = {}
        self._dirty: set[tuple[int, int, int]] = set()
        self._keyframes: list[KeyframeInfo] = []
        self._version = 0
        self._mesh_resolution = 8
        self.resolution_caps: list[int] = []  # each mesh_resolution_cap set, in order
        self._cap = 0
        self._observed_only = True
        self.rendered: list[tuple[int, int, str]] = []
        self.steps_per_frame = 3
        self.steps_done = 0
        self.in_frame = False  # inside integrate(), between optimisation steps
        self.refine_calls: list[int] = []  # steps asked of each refine() call
        self.on_iteration: Callable[[], None] | None = None
        self.frames_done = 0
        self.add_delay_s = 0.0  # real-time mode: seconds `add_frame` takes...
        self.step_delay_s = 0.0  # ...and each live or refinement step
        self.live_steps = self.refine_steps = 0
        # ("warm_up", -1) / ("add", frame index) / ("live", frame) / ("refine", -1), in order
        self.events: list[tuple[str, int]] = []
        self.warm_up_s = 0.0  # seconds `warm_up` takes (loading kernels)
        self.prepared_ahead: list[int] = []  # frames the reader thread prepared (real-time mode)
        self.fused_all: list[bool] = []  # real-time mode: each add_frame's fuse_all

    def prepare_ahead(self, frame: RgbdFrame) -> None:
        self.prepared_ahead.append(frame.index)

    def warm_up(self) -> float:
        time.sleep(self.warm_up_s)
        self.events.append(("warm_up", -1))
        return self.warm_up_s

    @property
    def mesh_resolution(self) -> int:
        return self._mesh_resolution

    @mesh_resolution.setter
    def mesh_resolution(self, value: int) -> None:
        self._mesh_resolution = int(value)
        self._dirty |= set(self._chunks)

    @property
    def mesh_resolution_cap(self) -> int:
        return self._cap

    @mesh_resolution_cap.setter
    def mesh_resolution_cap(self, value: int) -> None:
        self._cap = int(value)
        self.resolution_caps.append(self._cap)
        self._dirty |= set(self._chunks)

    @property
    def meshing_resolution(self) -> int:
        return min(self._mesh_resolution, self._cap) if self._cap else self._mesh_resolution

    @property
    def mesh_observed_only(self) -> bool:
        return self._observed_only

    @mesh_observed_only.setter
    def mesh_observed_only(self, value: bool) -> None:
        self._observed_only = bool(value)
        self._dirty |= set(self._chunks)

    @property
    def keyframe_rays(self) -> list[KeyframeInfo]:
        return self._keyframes

    def add_frame(
        self, frame: RgbdFrame, color_points: int = 0, observed_points: int = 0, fuse_all: bool = True
    ) -> FrameStats:
        """Real-time integration: the frame's voxels, no steps."""
        self.fused_all.append(fuse_all)
        if frame.index in self.fail_frames:
            raise RuntimeError(f"mapping frame {frame.index} failed on purpose")
        time.sleep(self.add_delay_s)
        self.events.append(("add", frame.index))
        return replace(self._add(frame), iterations=0, map_time_s=self.add_delay_s)

    def live_step(self) -> float:
        time.sleep(self.step_delay_s)
        self.live_steps += 1
        self.events.append(("live", self.frames_done - 1))
        return 1.0 / self.live_steps

    def refine_step(self) -> float:
        """A loss that falls, then stays flat from the 100th step on."""
        time.sleep(self.step_delay_s)
        self.refine_steps += 1
        self.events.append(("refine", -1))
        return 0.5 + 1.0 / min(self.refine_steps, 100)

    def integrate(self, frame: RgbdFrame) -> FrameStats:
        if frame.index in self.fail_frames:
            raise RuntimeError(f"mapping frame {frame.index} failed on purpose")
        self.in_frame = True
        try:
            for _ in range(self.steps_per_frame):  # the optimisation steps, the worker's hook after each
                time.sleep(self.delay_s / self.steps_per_frame)
                self.steps_done += 1
                if self.on_iteration is not None:
                    self.on_iteration()
        finally:
            self.in_frame = False
        return self._add(frame)

    def _add(self, frame: RgbdFrame) -> FrameStats:
        self._version += 1
        self.frames_done += 1
        v, u = np.nonzero(frame.depth_m[::2, ::2] > 0)
        z = frame.depth_m[::2, ::2][v, u]
        p = np.stack([(2 * u - frame.K[0, 2]) / frame.K[0, 0] * z, (2 * v - frame.K[1, 2]) / frame.K[1, 1] * z, z], 1)
        pw = p @ frame.T_world_camera[:3, :3].T + frame.T_world_camera[:3, 3]
        cells = np.floor(pw / self.voxel_size_m).astype(np.int32)
        merged = np.unique(np.concatenate([self._voxels, cells]), axis=0)
        new = merged[~_rows_in(merged, self._voxels)]
        self._voxels = merged
        self._dirty |= {tuple(int(c) for c in k) for k in np.unique(new // self.chunk_voxels, axis=0)}
        self._update_keyframes(frame)
        n = self._version
        losses = {"rgb": 0.5 / n, "depth": 1.0 / n, "sdf": 0.1 / n**0.5}
        n_voxels, n_keyframes = len(self._voxels), len(self._keyframes)
        return FrameStats(frame.index, self.delay_s, self.steps_per_frame, n_voxels, n_keyframes, losses)

    def _update_keyframes(self, frame: RgbdFrame) -> None:
        if frame.index % 4 == 0:
            thumb = np.ascontiguousarray(frame.rgb[::4, ::4])
            self._keyframes.append(
                KeyframeInfo(
                    frame.index,
                    frame.T_world_camera,
                    frame.K,
                    frame.width,
                    frame.height,
                    thumb,
                    KeyframeState.UNCOVERED,
                )
            )
        sel = self._version % max(1, len(self._keyframes))
        states = [KeyframeState.COVERED if i < sel else KeyframeState.UNCOVERED for i in range(len(self._keyframes))]
        if self._keyframes:
            states[sel] = KeyframeState.SELECTED
        self._keyframes = [
            kf
            if kf.state == s
            else KeyframeInfo(kf.index, kf.T_world_camera, kf.K, kf.width, kf.height, kf.thumbnail, s)
            for kf, s in zip(self._keyframes, states, strict=True)
        ]

    def mesh_job(self, refresh_s: float = 0.0, whole: bool = False) -> FakeMeshJob | None:
        """The dirty chunks' voxels, frozen now (None when nothing changed), meshed by `run` on any thread."""
        if not self._dirty:
            return None
        chunk_of = self._voxels // self.chunk_voxels
        parts = {key: self._voxels[np.all(chunk_of == np.array(key), axis=1)] for key in sorted(self._dirty)}
        self._dirty = set()
        return FakeMeshJob(self, parts, self._version)

    def refine(self, iterations: int, on_step: object = None) -> int:
        """Refinement steps over the keyframes: none before a frame was mapped; every voxel re-meshed after."""
        self.refine_calls.append(iterations)
        if not self._version:
            return 0
        chunk_of = self._voxels // self.chunk_voxels
        self._dirty |= {tuple(int(i) for i in k) for k in np.unique(chunk_of, axis=0)}
        return iterations

    def update_mesh(self) -> None:
        job = self.mesh_job()
        if job is not None:
            job.run()

    def mesh_chunks(self) -> dict[tuple[int, int, int], MeshChunk]:
        return dict(self._chunks)  # the dict is replaced whole by mesh jobs, never changed in place

    def voxel_coords(self) -> np.ndarray:
        return self._voxels.copy()

    def octree_levels(self, level: int) -> np.ndarray:
        return np.unique(self._voxels >> level, axis=0).astype(np.int32)

    def keyframe_infos(self) -> tuple[KeyframeInfo, ...]:
        return tuple(self._keyframes)

    def render(self, K: np.ndarray, T_world_camera: np.ndarray, height: int, width: int, mode: str) -> np.ndarray:
        self.rendered.append((height, width, mode))
        depth, hits, normals = trace_room(K, T_world_camera, height, width)
        known = _rows_in(np.floor(hits.reshape(-1, 3) / self.voxel_size_m).astype(np.int32), self._voxels)
        known = known.reshape(height, width)
        if mode in ("depth", "prior"):
            return np.where(known, depth, 0).astype(np.float32)
        if mode == "normal":
            return np.where(known[..., None], normals, 0).astype(np.float32)
        return np.where(known[..., None], room_color(hits) / 255.0, 0).astype(np.float32)

    def mesh(self, resolution: int | None = None) -> trimesh.Trimesh:
        parts = [
            trimesh.Trimesh(c.vertices, c.faces, vertex_colors=c.colors, process=False) for c in self._chunks.values()
        ]
        return trimesh.util.concatenate(parts) if parts else trimesh.Trimesh()

    def export_mesh(self, path: Path) -> None:
        self.mesh().export(path)

    def save_checkpoint(self, path: Path) -> None:
        np.savez(path, voxels=self._voxels)


class FakeMeshJob:
    """A FakeMapper mesh job: one cube per voxel of the dirty chunks, colours from `room_color`."""

    def __init__(self, mapper: FakeMapper, parts: dict[tuple[int, int, int], np.ndarray], version: int) -> None:
        self.mapper, self.parts, self.version, self.field_version = mapper, parts, version, version

    def run(self, stop: object = None, on_pass: object = None, hurry: object = None) -> None:
        m = self.mapper
        m.mesh_calls += 1
        chunks = dict(m._chunks)
        for key, vox in self.parts.items():
            verts, faces = cube_mesh(vox, m.voxel_size_m)
            chunks[key] = MeshChunk(key, verts, faces, room_color(verts.astype(np.float64)), self.version)
        m._chunks = chunks
        if callable(on_pass):
            on_pass(list(self.parts), True)

    def after(self, older: FakeMeshJob) -> FakeMeshJob:
        return FakeMeshJob(self.mapper, {**older.parts, **self.parts}, self.version)


def _rows_in(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Which rows of int array a (N,3) occur in b (M,3)."""
    if len(b) == 0:
        return np.zeros(len(a), dtype=bool)
    off = 1 << 20
    key = lambda x: (
        ((x[:, 0].astype(np.int64) + off) << 42) | ((x[:, 1].astype(np.int64) + off) << 21) | (x[:, 2] + off)
    )
    return np.isin(key(a), key(b))


def snapshot(
    version: int = 1,
    chunks: dict[tuple[int, int, int], MeshChunk] | None = None,
    voxels: np.ndarray | None = None,
    keyframes: tuple[KeyframeInfo, ...] = (),
    trajectory: np.ndarray | None = None,
    frame: RgbdFrame | None = None,
    stats: tuple[FrameStats, ...] = (),
    voxel_size_m: float = 0.1,
) -> MapSnapshot:
    """A MapSnapshot with only the given parts filled in."""
    return MapSnapshot(
        version=version,
        frames_done=len(stats),
        frames_total=10,
        chunks=chunks or {},
        voxel_size_m=voxel_size_m,
        voxel_coords=np.zeros((0, 3), np.int32) if voxels is None else voxels.astype(np.int32),
        keyframes=keyframes,
        trajectory=np.zeros((0, 4, 4)) if trajectory is None else trajectory,
        current_frame=frame,
        stats=stats,
    )


def chunk(key: tuple[int, int, int], version: int = 1, n_voxels: int = 1) -> MeshChunk:
    """A mesh chunk of `n_voxels` unit cubes in a row inside chunk `key` (4-voxel chunks of 0.1 m)."""
    voxels = np.array(key) * 4 + np.stack([np.arange(n_voxels), np.zeros(n_voxels), np.zeros(n_voxels)], 1)
    verts, faces = cube_mesh(voxels.astype(np.int32), 0.1)
    colors = np.full((len(verts), 3), 200, np.uint8)
    return MeshChunk(key, verts, faces, colors, version)


def tiny_mapping_config() -> MappingConfig:
    """A MappingConfig small enough for the real Mapper to take ~0.1 s per 64x48 frame on a CPU."""
    return MappingConfig().updated(
        device="cpu",
        voxel_size_m=0.2,
        truncation_m=0.1,
        min_points_per_voxel=2,
        hash_log2_size=12,
        rays_per_iter=256,
        max_iters=2,
        n_keyframes=2,
        step_m=0.04,
        mesh_resolution=4,
        chunk_voxels=4,
        threads=1,
    )


def recording_mapper(cfg: MappingConfig, delay_s: float = 0.0):  # noqa: ANN201 (torch-backed class)
    """The real Mapper, noting the size and mode of every render and sleeping `delay_s` per frame."""
    from h2viz.mapping.mapper import Mapper

    class RecordingMapper(Mapper):
        def __init__(self) -> None:
            super().__init__(cfg)
            self.rendered: list[tuple[int, int, str]] = []

        def integrate(self, frame: RgbdFrame) -> FrameStats:
            time.sleep(delay_s)
            return super().integrate(frame)

        def render(self, K: np.ndarray, T_world_camera: np.ndarray, height: int, width: int, mode: str = "rgb"):  # noqa: ANN202
            self.rendered.append((height, width, mode))
            return super().render(K, T_world_camera, height, width, mode)

    return RecordingMapper()
