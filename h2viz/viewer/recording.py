"""Timeline recordings of a mapping run: one step per mapped frame, each step a compressed .npz holding only what
changed since the step before (mesh chunks re-meshed or removed, voxels added or removed, new keyframes and every
keyframe's coverage state, new trajectory poses, the current camera with a thumbnail of its input, the progress
figures). `Recorder` writes them from MapSnapshots, `Recording` reads them back into MapSnapshots at any step.
NumPy only: replaying a recording needs neither torch nor the mapper."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import queue
import threading
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from h2viz.errors import H2vizError
from h2viz.types import FrameStats, KeyframeInfo, KeyframeState, MapSnapshot, MeshChunk, RgbdFrame
from h2viz.viewer.diff import Key, diff_chunks

log = logging.getLogger("h2viz.recording")
FORMAT = "h2viz-recording"
VERSION = 1
META = "recording.json"
THUMB_WIDTH = 160  # width of the current frame's recorded thumbnail
STATES = list(KeyframeState)  # recorded as their position in this list


class RecordingError(H2vizError):
    """A recording folder cannot be read or written."""


def _rows(a: np.ndarray) -> np.ndarray:
    """(N,3) int32 rows as one void value each, for set operations."""
    a = np.ascontiguousarray(a, dtype=np.int32).reshape(-1, 3)
    return a.view(np.dtype((np.void, 12))).ravel()


def _row_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rows of `a` (N,3) not in `b` (M,3)."""
    if len(b) == 0 or len(a) == 0:
        return np.asarray(a, np.int32).reshape(-1, 3)
    return np.asarray(a, np.int32).reshape(-1, 3)[~np.isin(_rows(a), _rows(b))]


def voxel_changes(before: np.ndarray, after: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(added, removed) voxel rows between two coordinate lists; a grown list that keeps its prefix is cheap."""
    if len(after) >= len(before) and np.array_equal(after[: len(before)], before):
        return np.asarray(after[len(before) :], np.int32).reshape(-1, 3), np.zeros((0, 3), np.int32)
    return _row_diff(after, before), _row_diff(before, after)


def thumbnail(frame: RgbdFrame, width: int = THUMB_WIDTH) -> tuple[np.ndarray, np.ndarray]:
    """(h,w,3) uint8 colour thumbnail of a frame and its intrinsics K (3,3) at that size."""
    scale = min(1.0, width / frame.width)
    w, h = max(1, round(frame.width * scale)), max(1, round(frame.height * scale))
    rgb = cv2.resize(frame.rgb, (w, h), interpolation=cv2.INTER_AREA) if scale < 1.0 else frame.rgb.copy()
    K = frame.K.copy()
    K[0] *= w / frame.width
    K[1] *= h / frame.height
    return rgb, K


# ------------------------------------------------------------------------------------ writing


class Recorder:
    """Writes one step per mapped frame into `folder`: offer every snapshot; a step is written when a snapshot of a
    later frame arrives (so it holds the mesh meshed for its frame meanwhile) and at `close`."""

    def __init__(self, folder: Path, fps: float = 10.0) -> None:
        self.folder = Path(folder)
        try:
            (self.folder / "steps").mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise RecordingError(f"cannot create the recording folder {self.folder}: {e}") from e
        self.fps = float(fps)
        self.steps = 0
        self.bytes_written = 0
        self._pending: MapSnapshot | None = None
        self._chunks: dict[Key, MeshChunk] = {}
        self._voxels = np.zeros((0, 3), np.int32)
        self._keyframes: set[int] = set()
        self._n_poses = self._n_stats = 0
        self._lock = threading.Lock()
        self._voxel_size_m = 0.0
        self._write_meta(finished=False)

    def offer(self, snap: MapSnapshot) -> None:
        """Note `snap`; writes the step of the frame before when `snap` maps a new one."""
        with self._lock:
            if snap.frames_done == 0:
                return
            if self._pending is not None and snap.frames_done != self._pending.frames_done:
                self._write(self._pending)
            self._pending = snap

    def close(self) -> Path:
        """Write the last step and the metadata; returns the folder."""
        with self._lock:
            if self._pending is not None:
                self._write(self._pending)
                self._pending = None
            self._write_meta(finished=True)
        return self.folder

    def _write(self, snap: MapSnapshot) -> None:
        arrays = self._changes(snap)
        path = self.folder / "steps" / f"{self.steps:06d}.npz"
        partial = path.with_name(path.name + ".partial")  # renamed once whole: a crash leaves no half step
        try:
            with open(partial, "wb") as f:
                np.savez_compressed(f, **arrays)
            os.replace(partial, path)
        except OSError as e:
            raise RecordingError(f"cannot write {path}: {e}; free some disk space or record elsewhere") from e
        self.bytes_written += path.stat().st_size
        self.steps += 1
        self._voxel_size_m = snap.voxel_size_m
        if self.steps % 20 == 0:
            self._write_meta(finished=False)

    def _changes(self, snap: MapSnapshot) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        diff = diff_chunks(self._chunks, snap.chunks)
        out.update(_pack_chunks([snap.chunks[k] for k in diff.changed]))
        out["removed_chunks"] = np.array(diff.removed, np.int32).reshape(-1, 3)
        self._chunks = dict(snap.chunks)
        out["voxels_added"], out["voxels_removed"] = voxel_changes(self._voxels, snap.voxel_coords)
        self._voxels = snap.voxel_coords
        out.update(self._keyframe_changes(snap.keyframes))
        n = len(snap.trajectory)
        start = self._n_poses if n >= self._n_poses else 0
        out["trajectory_start"] = np.array(start, np.int64)
        out["trajectory_new"] = np.asarray(snap.trajectory[start:], np.float64).reshape(-1, 4, 4)
        self._n_poses = n
        if snap.current_frame is not None:
            f = snap.current_frame
            out["current_rgb"], out["current_K"] = thumbnail(f)
            out["current_T"], out["current_index"] = f.T_world_camera, np.array(f.index, np.int64)
            out["current_timestamp"] = np.array(f.timestamp, np.float64)
        new_stats = [dataclasses.asdict(s) for s in snap.stats[self._n_stats :]]
        self._n_stats = len(snap.stats)
        info = {
            "frames_done": snap.frames_done,
            "frames_total": snap.frames_total,
            "voxel_size_m": snap.voxel_size_m,
            "skipped": snap.skipped,
            "dropped": snap.dropped,
            "metrics": snap.metrics,
            "memory_mb": snap.memory_mb,
            "finished": snap.finished,
            "new_stats": new_stats,
        }
        out["info"] = np.frombuffer(json.dumps(info).encode(), np.uint8)
        return out

    def _keyframe_changes(self, keyframes: Iterable[KeyframeInfo]) -> dict[str, np.ndarray]:
        kfs = list(keyframes)
        new = [kf for kf in kfs if kf.index not in self._keyframes]
        self._keyframes = {kf.index for kf in kfs}
        out = {
            "kf_index": np.array([kf.index for kf in kfs], np.int64),
            "kf_state": np.array([STATES.index(kf.state) for kf in kfs], np.int8),
            "kfn_index": np.array([kf.index for kf in new], np.int64),
            "kfn_T": np.array([kf.T_world_camera for kf in new], np.float64).reshape(-1, 4, 4),
            "kfn_K": np.array([kf.K for kf in new], np.float64).reshape(-1, 3, 3),
            "kfn_size": np.array([(kf.width, kf.height) for kf in new], np.int64).reshape(-1, 2),
        }
        for i, kf in enumerate(new):
            out[f"kfn_thumb_{i}"] = np.ascontiguousarray(kf.thumbnail, np.uint8)
        return out

    def _write_meta(self, finished: bool) -> None:
        meta = {
            "format": FORMAT,
            "version": VERSION,
            "steps": self.steps,
            "fps": self.fps,
            "voxel_size_m": self._voxel_size_m,
            "complete": finished,
            "bytes": self.bytes_written,
        }
        (self.folder / META).write_text(json.dumps(meta, indent=1))


def _delta(faces: np.ndarray) -> np.ndarray:
    """Faces (M,3) as the differences of their flattened indices: marching cubes emits neighbouring faces one after
    another, and small differences compress to about half the bytes of the indices themselves (lossless)."""
    return np.diff(faces.reshape(-1).astype(np.int64), prepend=0).astype(np.int32)


def _pack_chunks(chunks: list[MeshChunk]) -> dict[str, np.ndarray]:
    """Changed chunks in five arrays; each chunk's (vertex, face) counts and version in `chunk_n`."""
    return {
        "chunk_keys": np.array([c.key for c in chunks], np.int32).reshape(-1, 3),
        "chunk_n": np.array([(len(c.vertices), len(c.faces), c.version) for c in chunks], np.int64).reshape(-1, 3),
        "vertices": np.concatenate([c.vertices for c in chunks] or [np.zeros((0, 3))]).astype(np.float32),
        "faces_delta": _delta(np.concatenate([c.faces for c in chunks] or [np.zeros((0, 3))]).astype(np.int32)),
        "colors": np.concatenate([c.colors for c in chunks] or [np.zeros((0, 3))]).astype(np.uint8),
    }


# ------------------------------------------------------------------------------------ reading


@dataclass(frozen=True)
class Step:
    """One recorded step, decoded (mesh chunks are built once so that replays can diff them by identity)."""

    chunks: dict[Key, MeshChunk]
    removed_chunks: list[Key]
    voxels_added: np.ndarray  # (A,3) int32
    voxels_removed: np.ndarray  # (B,3) int32
    keyframes: list[tuple[int, KeyframeState]]
    new_keyframes: list[KeyframeInfo]
    trajectory_start: int
    trajectory_new: np.ndarray  # (n,4,4)
    current: RgbdFrame | None
    info: dict[str, Any]


def _unpack_chunks(z: Any) -> dict[Key, MeshChunk]:
    chunks: dict[Key, MeshChunk] = {}
    v0 = f0 = 0
    all_faces = np.cumsum(z["faces_delta"], dtype=np.int64).astype(np.int32).reshape(-1, 3)
    vertices, colors_all = z["vertices"], z["colors"]
    for key, (nv, nf, version) in zip(z["chunk_keys"], z["chunk_n"], strict=True):
        k = (int(key[0]), int(key[1]), int(key[2]))
        verts, faces, colors = vertices[v0 : v0 + nv], all_faces[f0 : f0 + nf], colors_all[v0 : v0 + nv]
        chunks[k] = MeshChunk(k, verts, faces, colors, int(version))
        v0, f0 = v0 + nv, f0 + nf
    return chunks


def read_step(path: Path) -> Step:
    """Decode one step file; RecordingError naming the file when it is damaged."""
    try:
        with np.load(path) as z:
            info = json.loads(bytes(z["info"]).decode())
            n_new = len(z["kfn_index"])
            new = [
                KeyframeInfo(
                    int(z["kfn_index"][i]),
                    z["kfn_T"][i],
                    z["kfn_K"][i],
                    int(z["kfn_size"][i, 0]),
                    int(z["kfn_size"][i, 1]),
                    z[f"kfn_thumb_{i}"],
                    KeyframeState.UNCOVERED,
                )
                for i in range(n_new)
            ]
            current = None
            if "current_rgb" in z:
                rgb = z["current_rgb"]
                depth = np.zeros(rgb.shape[:2], np.float32)  # the recording keeps colour thumbnails only
                index, t = int(z["current_index"]), float(z["current_timestamp"])
                current = RgbdFrame(index, t, rgb, depth, z["current_K"], z["current_T"], name=f"frame {index}")
            return Step(
                chunks=_unpack_chunks(z),
                removed_chunks=[tuple(int(v) for v in k) for k in z["removed_chunks"]],  # type: ignore[misc]
                voxels_added=z["voxels_added"].astype(np.int32),
                voxels_removed=z["voxels_removed"].astype(np.int32),
                keyframes=[(int(i), STATES[int(s)]) for i, s in zip(z["kf_index"], z["kf_state"], strict=True)],
                new_keyframes=new,
                trajectory_start=int(z["trajectory_start"]),
                trajectory_new=z["trajectory_new"],
                current=current,
                info=info,
            )
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, json.JSONDecodeError, EOFError) as e:
        raise RecordingError(
            f"{path}: damaged recording step ({type(e).__name__}: {e}); delete it and the steps after it to replay "
            "the ones before"
        ) from e


def find_recording(run_dir: Path) -> Path:
    """The recording folder of a run folder (RUN_DIR/recording) or the folder itself."""
    run_dir = Path(run_dir)
    for folder in (run_dir, run_dir / "recording"):
        if (folder / META).is_file():
            return folder
    raise RecordingError(
        f"no recording in {run_dir}: expected {run_dir / 'recording' / META}; record one with "
        "`h2viz map --record` or the dashboard's Record switch"
    )


class Recording:
    """A recorded run, read into memory: `snapshot(k)` is the map as it stood at step k (0-based)."""

    def __init__(self, run_dir: Path) -> None:
        self.folder = find_recording(run_dir)
        try:
            self.meta = json.loads((self.folder / META).read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise RecordingError(f"{self.folder / META}: unreadable ({e})") from e
        if self.meta.get("format") != FORMAT:
            raise RecordingError(f"{self.folder / META}: not an h2viz recording (format {self.meta.get('format')})")
        files = sorted((self.folder / "steps").glob("*.npz"))
        if not files:
            raise RecordingError(f"{self.folder}: the recording has no steps yet (map at least one frame)")
        self.steps: list[Step] = []
        self.problem = ""  # why the recording ends before its last file, if it does
        for f in files:
            try:
                self.steps.append(read_step(f))
            except RecordingError as e:
                if not self.steps:
                    raise
                self.problem = f"replaying the {len(self.steps)} steps before it: {e}"
                log.warning("%s", self.problem)
                files = files[: len(self.steps)]
                break
        self.fps = float(self.meta.get("fps", 10.0))
        self.bytes = sum(f.stat().st_size for f in files)
        self._keyframe_info: dict[int, KeyframeInfo] = {}
        for step in self.steps:
            for kf in step.new_keyframes:
                self._keyframe_info.setdefault(kf.index, kf)
        self._stats: list[FrameStats] = []
        for step in self.steps:
            self._stats.extend(FrameStats(**s) for s in step.info.get("new_stats", []))

    def __len__(self) -> int:
        return len(self.steps)

    def snapshot(self, k: int) -> MapSnapshot:
        """The MapSnapshot at step `k` (clamped to the recorded steps)."""
        k = int(np.clip(k, 0, len(self.steps) - 1))
        chunks: dict[Key, MeshChunk] = {}
        voxels: list[np.ndarray] = []
        poses: list[np.ndarray] = []
        n_poses = 0
        current: RgbdFrame | None = None
        for step in self.steps[: k + 1]:
            for key in step.removed_chunks:
                chunks.pop(key, None)
            chunks.update(step.chunks)
            if len(step.voxels_removed):
                voxels = [_row_diff(np.concatenate(voxels), step.voxels_removed)] if voxels else []
            voxels.append(step.voxels_added)
            if step.trajectory_start < n_poses:
                poses = [np.concatenate(poses)[: step.trajectory_start]] if poses else []
            poses.append(step.trajectory_new)
            n_poses = step.trajectory_start + len(step.trajectory_new)
            current = step.current or current
        last = self.steps[k]
        info = last.info
        keyframes = tuple(
            dataclasses.replace(self._keyframe_info[i], state=state)
            for i, state in last.keyframes
            if i in self._keyframe_info
        )
        return MapSnapshot(
            version=k + 1,
            frames_done=int(info["frames_done"]),
            frames_total=info.get("frames_total"),
            chunks=chunks,
            voxel_size_m=float(info["voxel_size_m"]),
            voxel_coords=np.concatenate(voxels).astype(np.int32).reshape(-1, 3),
            keyframes=keyframes,
            trajectory=np.concatenate(poses).reshape(-1, 4, 4),
            current_frame=current,
            stats=tuple(self._stats[: int(info["frames_done"])]),
            finished=bool(info.get("finished", False)) and k == len(self.steps) - 1,
            skipped=int(info.get("skipped", 0)),
            dropped=int(info.get("dropped", 0)),
            metrics=dict(info.get("metrics", {})),
            memory_mb=float(info.get("memory_mb", 0.0)),
        )


class BackgroundRecorder:
    """A Recorder fed from any thread: offered snapshots queue up and are written on a thread of their own, so
    that compressing a step never delays mapping."""

    def __init__(self, recorder: Recorder) -> None:
        self.recorder = recorder
        self.errors: list[str] = []
        self._queue: queue.Queue[MapSnapshot | None] = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="h2viz-recorder", daemon=True)
        self._thread.start()

    @property
    def folder(self) -> Path:
        return self.recorder.folder

    def offer(self, snap: MapSnapshot) -> None:
        self._queue.put(snap)

    def close(self) -> Path:
        """Write everything offered so far, then the last step; returns the folder."""
        self._queue.put(None)
        self._thread.join()
        return self.recorder.close()

    def _run(self) -> None:
        while (snap := self._queue.get()) is not None:
            try:
                self.recorder.offer(snap)
            except RecordingError as e:  # keep mapping; the message reaches the dashboard
                if not self.errors:
                    self.errors.append(str(e))
