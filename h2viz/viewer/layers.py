"""Scene layers drawn from MapSnapshots: the mesh (one GLB node per chunk, only changed chunks
sent), the octree (line segments per block of cells), keyframe frustums coloured by coverage, the
trajectory, the current camera and its point cloud. Each layer lives under one root node whose
visibility toggles it; a hidden layer stops sending and catches up when shown again."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import viser

from h2viz.types import KeyframeInfo, KeyframeState, MapSnapshot, MeshChunk
from h2viz.viewer.diff import Key, block_signatures, diff_chunks, diff_signatures, group_cells
from h2viz.viewer.glb import mesh_glb
from h2viz.viewer.shapes import cube_edges, fov_aspect, frame_points, trajectory_segments, wxyz_position

STATE_COLORS = {
    KeyframeState.SELECTED: (255, 140, 0),  # optimised in this round
    KeyframeState.COVERED: (40, 170, 255),  # selected earlier in this round
    KeyframeState.UNCOVERED: (150, 150, 150),  # waiting for its turn
}
LEVEL_COLORS = [(110, 200, 255), (255, 190, 60), (255, 100, 100), (200, 120, 255)]
TRAJECTORY_COLOR = (255, 220, 40)
CAMERA_COLOR = (255, 60, 160)
OCTREE_BLOCK = 16  # octree cells per block edge; one line-segment node per block


def _key_name(key: Key) -> str:
    return "_".join(str(int(k)).replace("-", "m") for k in key)


class Layer:
    """A group of scene nodes under `root` that follows snapshots while enabled."""

    root = "/layer"

    def __init__(self, scene: viser.SceneApi, enabled: bool = True) -> None:
        self.scene = scene
        self.enabled = enabled
        self.bytes_sent = 0  # payload bytes of geometry sent by the last sync
        self._root = scene.add_frame(self.root, show_axes=False, visible=enabled)
        self._last: MapSnapshot | None = None

    def set_enabled(self, enabled: bool) -> None:
        self.enabled = enabled
        if enabled and self._last is not None:
            self.sync(self._last)
        self._root.visible = enabled

    def update(self, snap: MapSnapshot) -> None:
        """Remember `snap` and draw it when enabled."""
        self._last = snap
        self.bytes_sent = 0
        if self.enabled:
            self.sync(snap)

    def sync(self, snap: MapSnapshot) -> None:
        raise NotImplementedError


class MeshLayer(Layer):
    root = "/mesh"

    def __init__(self, scene: viser.SceneApi, enabled: bool = True, opacity: float = 1.0) -> None:
        super().__init__(scene, enabled)
        self.opacity = opacity
        self.drawn: dict[Key, MeshChunk] = {}
        self.handles: dict[Key, Any] = {}
        self.on_sent: list[Callable[[MapSnapshot, list[Key], int], None]] = []  # for measurements

    def set_opacity(self, opacity: float) -> None:
        self.opacity = float(np.clip(opacity, 0.05, 1.0))
        self.drawn.clear()  # every chunk is sent again with the new material
        if self.enabled and self._last is not None:
            self.sync(self._last)

    def behind(self, snap: MapSnapshot) -> bool:
        """The shown mesh differs from `snap`'s (only an enabled layer can be behind)."""
        if not self.enabled:
            return False
        diff = diff_chunks(self.drawn, snap.chunks)
        return bool(diff.changed or diff.removed)

    def sync(self, snap: MapSnapshot) -> None:
        diff = diff_chunks(self.drawn, snap.chunks)
        for key in diff.removed:
            self.drawn.pop(key)
            if key in self.handles:
                self.handles.pop(key).remove()
        for key in diff.changed:
            chunk = snap.chunks[key]
            self.drawn[key] = chunk
            if len(chunk.faces) == 0:
                if key in self.handles:
                    self.handles.pop(key).remove()
                continue
            data = mesh_glb(chunk.vertices, chunk.faces, chunk.colors, self.opacity)
            self.handles[key] = self.scene.add_glb(f"{self.root}/c_{_key_name(key)}", data, cast_shadow=False)
            self.bytes_sent += len(data)
        for callback in self.on_sent:
            callback(snap, diff.changed, self.bytes_sent)


class OctreeLayer(Layer):
    """Leaf voxels (level 0) and up to `coarse_levels` coarser octree levels as cube outlines."""

    root = "/octree"

    def __init__(
        self, scene: viser.SceneApi, enabled: bool = True, leaves: bool = True, coarse_levels: int = 0
    ):
        super().__init__(scene, enabled)
        self.leaves, self.coarse_levels = leaves, coarse_levels
        self.drawn: dict[tuple[int, Key], int] = {}  # (level, block) -> signature
        self.handles: dict[tuple[int, Key], Any] = {}

    def set_levels(self, leaves: bool, coarse_levels: int) -> None:
        self.leaves, self.coarse_levels = leaves, int(coarse_levels)
        if self.enabled and self._last is not None:
            self.sync(self._last)

    def shown_levels(self) -> list[int]:
        return ([0] if self.leaves else []) + list(range(1, self.coarse_levels + 1))

    def sync(self, snap: MapSnapshot) -> None:
        for level in range(0, len(LEVEL_COLORS)):
            cells = snap.voxel_coords >> level if level in self.shown_levels() else np.zeros((0, 3), np.int32)
            groups = group_cells(cells, OCTREE_BLOCK)
            drawn = {b: s for (lv, b), s in self.drawn.items() if lv == level}
            diff = diff_signatures(drawn, block_signatures(groups))
            for block in diff.removed:
                self.handles.pop((level, block)).remove()
                self.drawn.pop((level, block))
            for block in diff.changed:
                self._draw_block(level, block, groups[block], snap.voxel_size_m * 2**level)

    def _draw_block(self, level: int, block: Key, cells: np.ndarray, size_m: float) -> None:
        segments = cube_edges(cells, size_m)  # (E,2,3)
        name = f"{self.root}/l{level}/b_{_key_name(block)}"
        thickness = 1.0 + level
        self.handles[(level, block)] = self.scene.add_line_segments(
            name, segments, LEVEL_COLORS[level], thickness=thickness, thickness_units="screen"
        )
        self.drawn[(level, block)] = hash(cells.tobytes())
        self.bytes_sent += segments.nbytes


class KeyframeLayer(Layer):
    """One frustum per keyframe with its thumbnail, coloured by coverage state."""

    root = "/keyframes"

    def __init__(self, scene: viser.SceneApi, enabled: bool = True, scale: float = 0.1) -> None:
        super().__init__(scene, enabled)
        self.scale = scale
        self.states: dict[int, KeyframeState] = {}
        self.handles: dict[int, Any] = {}

    def sync(self, snap: MapSnapshot) -> None:
        current = {kf.index: kf for kf in snap.keyframes}
        for index in set(self.handles) - set(current):
            self.handles.pop(index).remove()
            self.states.pop(index)
        for index, kf in current.items():
            if index not in self.handles:
                self.handles[index] = self._add(kf)
            elif self.states[index] != kf.state:
                self.handles[index].color = STATE_COLORS[kf.state]
            self.states[index] = kf.state

    def _add(self, kf: KeyframeInfo) -> Any:
        fov, aspect = fov_aspect(kf.K, kf.width, kf.height)
        wxyz, position = wxyz_position(kf.T_world_camera)
        self.bytes_sent += kf.thumbnail.nbytes
        return self.scene.add_camera_frustum(
            f"{self.root}/kf_{kf.index:06d}",
            fov=fov,
            aspect=aspect,
            scale=self.scale,
            color=STATE_COLORS[kf.state],
            image=kf.thumbnail,
            jpeg_quality=80,
            thickness=1.5,
            thickness_units="screen",
            wxyz=wxyz,
            position=position,
            cast_shadow=False,
        )


class TrajectoryLayer(Layer):
    root = "/trajectory"

    def __init__(self, scene: viser.SceneApi, enabled: bool = True) -> None:
        super().__init__(scene, enabled)
        self.n_drawn = 0
        self.handle: Any = None

    def sync(self, snap: MapSnapshot) -> None:
        n = len(snap.trajectory)
        if n == self.n_drawn or n < 2:
            return
        segments = trajectory_segments(snap.trajectory)
        self.handle = self.scene.add_line_segments(
            f"{self.root}/path", segments, TRAJECTORY_COLOR, thickness=2.5, thickness_units="screen"
        )
        self.n_drawn = n
        self.bytes_sent += segments.nbytes


class CameraLayer(Layer):
    """The frame being mapped: a frustum with its colour image, and optionally its point cloud."""

    root = "/camera"

    def __init__(
        self, scene: viser.SceneApi, enabled: bool = True, points: bool = False, scale: float = 0.15
    ):
        super().__init__(scene, enabled)
        self.points, self.scale = points, scale
        self.frame_index: int | None = None
        self.frustum: Any = None
        self.cloud: Any = None

    def set_points(self, points: bool) -> None:
        self.points = points
        if self.cloud is not None and not points:
            self.cloud.remove()
            self.cloud = None
        self.frame_index = None
        if self.enabled and self._last is not None:
            self.sync(self._last)

    def sync(self, snap: MapSnapshot) -> None:
        frame = snap.current_frame
        if frame is None or frame.index == self.frame_index:
            return
        self.frame_index = frame.index
        fov, aspect = fov_aspect(frame.K, frame.width, frame.height)
        wxyz, position = wxyz_position(frame.T_world_camera)
        step = max(1, frame.width // 160)
        thumb = np.ascontiguousarray(frame.rgb[::step, ::step])
        if self.frustum is None:
            self.frustum = self.scene.add_camera_frustum(
                f"{self.root}/current",
                fov=fov,
                aspect=aspect,
                scale=self.scale,
                color=CAMERA_COLOR,
                image=thumb,
                jpeg_quality=75,
                thickness=3.0,
                thickness_units="screen",
                wxyz=wxyz,
                position=position,
                cast_shadow=False,
            )
        else:
            self.frustum.wxyz, self.frustum.position = wxyz, position
            self.frustum.fov, self.frustum.aspect, self.frustum.image = fov, aspect, thumb
        self.bytes_sent += thumb.nbytes
        if self.points:
            pts, colors = frame_points(frame)
            size = 0.25 * snap.voxel_size_m
            self.cloud = self.scene.add_point_cloud(f"{self.root}/points", pts, colors, point_size=size)
            self.bytes_sent += pts.nbytes // 2 + colors.nbytes


class LayerSet:
    """Every layer of the dashboard, updated together from one snapshot."""

    def __init__(self, scene: viser.SceneApi, frustum_scale: float = 0.1) -> None:
        self.mesh = MeshLayer(scene)
        self.octree = OctreeLayer(scene, enabled=False)
        self.keyframes = KeyframeLayer(scene, scale=frustum_scale)
        self.trajectory = TrajectoryLayer(scene)
        self.camera = CameraLayer(scene, scale=1.5 * frustum_scale)

    def all(self) -> list[Layer]:
        return [self.mesh, self.octree, self.keyframes, self.trajectory, self.camera]

    def update(self, snap: MapSnapshot, mesh_due: bool = True) -> int:
        """Draw `snap` (the mesh only when `mesh_due`); returns the geometry bytes sent."""
        updated = [layer for layer in self.all() if layer is not self.mesh or mesh_due]
        for layer in updated:
            layer.update(snap)
        return sum(layer.bytes_sent for layer in updated)
