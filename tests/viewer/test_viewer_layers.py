"""Each scene layer against a real (browser-less) viser server: what nodes exist after a snapshot,
and that only what changed is sent again."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import pytest
import viser

from h2viz.geometry import look_at
from h2viz.types import KeyframeInfo, KeyframeState
from h2viz.viewer.diff import group_cells
from h2viz.viewer.glb import mesh_glb
from h2viz.viewer.layers import (
    STATE_COLORS,
    CameraLayer,
    KeyframeLayer,
    MeshLayer,
    OctreeLayer,
    TrajectoryLayer,
)
from h2viz.viewer.server import make_viser_server
from h2viz.viewer.shapes import cube_edges
from tests.viewer.fakes import BoxRoomSource, chunk, snapshot


@pytest.fixture(scope="module")
def server() -> Iterator[viser.ViserServer]:
    s = make_viser_server("127.0.0.1", 0)
    yield s
    s.stop()


def node(server: viser.ViserServer, name: str) -> object | None:
    return server.scene.get_handle_by_name(name)


def test_mesh_layer_sends_only_changed_chunks_and_removes_gone_ones(server: viser.ViserServer) -> None:
    layer = MeshLayer(server.scene)
    a, b, c = chunk((0, 0, 0), n_voxels=2), chunk((1, 0, 0)), chunk((-1, 2, 0))
    layer.update(snapshot(chunks={a.key: a, b.key: b}))
    first = layer.bytes_sent
    assert node(server, "/mesh/c_0_0_0") is not None and node(server, "/mesh/c_1_0_0") is not None
    assert first > 0
    layer.update(snapshot(chunks={a.key: a, b.key: b}))
    assert layer.bytes_sent == 0  # nothing changed, nothing sent
    b2 = chunk((1, 0, 0), version=2)
    layer.update(snapshot(chunks={a.key: a, b.key: b2, c.key: c}))
    assert 0 < layer.bytes_sent < first  # two one-voxel chunks, less than the first two chunks
    assert node(server, "/mesh/c_m1_2_0") is not None
    layer.update(snapshot(chunks={a.key: a}))
    assert node(server, "/mesh/c_1_0_0") is None and node(server, "/mesh/c_m1_2_0") is None
    assert set(layer.handles) == {a.key}


def test_mesh_layer_opacity_resends_and_hidden_layer_catches_up(server: viser.ViserServer) -> None:
    layer = MeshLayer(server.scene)
    a = chunk((5, 0, 0))
    layer.update(snapshot(chunks={a.key: a}))
    sent = layer.bytes_sent
    assert sent == len(mesh_glb(a.vertices, a.faces, a.colors))
    layer.set_opacity(0.4)
    assert layer.bytes_sent == sent + len(mesh_glb(a.vertices, a.faces, a.colors, 0.4))  # again, translucent
    layer.set_enabled(False)
    b = chunk((6, 0, 0))
    layer.update(snapshot(chunks={a.key: a, b.key: b}))
    assert layer.bytes_sent == 0 and node(server, "/mesh/c_6_0_0") is None
    layer.set_enabled(True)
    assert node(server, "/mesh/c_6_0_0") is not None


def test_octree_layer_draws_blocks_and_updates_only_the_touched_block(server: viser.ViserServer) -> None:
    layer = OctreeLayer(server.scene, leaves=True, coarse_levels=0)
    voxels = np.array([[0, 0, 0], [1, 0, 0], [20, 0, 0], [-3, 0, 0]])
    layer.update(snapshot(voxels=voxels, voxel_size_m=0.1))
    assert sorted(b for (_, b) in layer.handles) == [(-1, 0, 0), (0, 0, 0), (1, 0, 0)]
    assert layer.bytes_sent == sum(cube_edges(c, 0.1).nbytes for c in group_cells(voxels, 16).values())
    handle = layer.handles[(0, (0, 0, 0))]
    np.testing.assert_allclose(handle.points, cube_edges(np.array([[0, 0, 0], [1, 0, 0]]), 0.1))
    layer.update(snapshot(voxels=np.vstack([voxels, [[21, 1, 0]]]), voxel_size_m=0.1))
    assert layer.bytes_sent == cube_edges(np.array([[20, 0, 0], [21, 1, 0]]), 0.1).nbytes
    layer.set_levels(leaves=False, coarse_levels=2)
    assert {lv for (lv, _) in layer.handles} == {1, 2}
    coarse = layer.handles[(2, (0, 0, 0))].points  # level-2 cells are 4 voxels wide
    assert np.max(np.abs(coarse[:, 1] - coarse[:, 0])) == pytest.approx(0.4)
    assert node(server, "/octree/l0/b_0_0_0") is None


def _keyframe(index: int, state: KeyframeState) -> KeyframeInfo:
    T = look_at(np.array([index, 0.0, 1.0]), np.array([index, 2.0, 1.0]))
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    return KeyframeInfo(index, T, K, 64, 48, np.zeros((12, 16, 3), np.uint8), state)


def test_keyframe_layer_recolours_in_place(server: viser.ViserServer) -> None:
    layer = KeyframeLayer(server.scene, scale=0.1)
    kfs = (_keyframe(0, KeyframeState.SELECTED), _keyframe(5, KeyframeState.UNCOVERED))
    layer.update(snapshot(keyframes=kfs))
    handle = layer.handles[5]
    assert tuple(handle.color) == STATE_COLORS[KeyframeState.UNCOVERED]
    np.testing.assert_allclose(handle.position, [5.0, 0.0, 1.0])
    assert handle.fov == pytest.approx(2 * np.arctan(24 / 50)) and handle.aspect == pytest.approx(64 / 48)
    layer.update(snapshot(keyframes=(_keyframe(5, KeyframeState.SELECTED),)))
    assert layer.handles[5] is handle and tuple(handle.color) == STATE_COLORS[KeyframeState.SELECTED]
    assert 0 not in layer.handles and node(server, "/keyframes/kf_000000") is None


def test_trajectory_and_camera_layers(server: viser.ViserServer) -> None:
    source = BoxRoomSource(n=5, width=32, height=24)
    frames = [source.load(i, i) for i in range(3)]
    poses = np.stack([f.T_world_camera for f in frames])
    trajectory = TrajectoryLayer(server.scene)
    trajectory.update(snapshot(trajectory=poses))
    np.testing.assert_allclose(trajectory.handle.points[:, 0], poses[:-1, :3, 3], atol=1e-6)
    trajectory.update(snapshot(trajectory=poses))
    assert trajectory.bytes_sent == 0
    camera = CameraLayer(server.scene, points=True)
    camera.update(snapshot(frame=frames[2]))
    np.testing.assert_allclose(camera.frustum.position, frames[2].T_world_camera[:3, 3])
    assert 0 < len(camera.cloud.points) <= 32 * 24
    camera.update(snapshot(frame=frames[1]))
    np.testing.assert_allclose(camera.frustum.position, frames[1].T_world_camera[:3, 3])
    camera.set_points(False)
    assert camera.cloud is None and node(server, "/camera/points") is None


def test_dashboard_sends_the_scene_when_the_mesh_changes_and_otherwise_once_a_period() -> None:
    from h2viz.config import Config
    from h2viz.viewer import server as server_module
    from h2viz.viewer.server import Dashboard
    from h2viz.worker import MappingWorker
    from tests.viewer.fakes import FakeMapper

    dash = Dashboard(MappingWorker(BoxRoomSource(n=2), FakeMapper(), Config()), Config(), port=0)  # type: ignore[arg-type]
    try:
        a, b = chunk((0, 0, 0)), chunk((1, 0, 0))
        path = lambda n: np.stack([np.eye(4)] * n)  # noqa: E731
        dash._draw_scene(snapshot(chunks={a.key: a}, trajectory=path(2)), 1)
        assert dash.scene_updates == 1 and dash.layers.trajectory.n_drawn == 2
        dash._draw_scene(snapshot(chunks={a.key: a}, trajectory=path(3)), 2)  # same mesh, within the period
        assert dash.scene_updates == 1 and dash.scene_version == 1 and dash.layers.trajectory.n_drawn == 2
        dash._draw_scene(snapshot(chunks={a.key: a, b.key: b}, trajectory=path(4)), 3)  # the mesh changed
        assert dash.scene_updates == 2 and dash.scene_version == 3 and dash.layers.trajectory.n_drawn == 4
        assert node(dash.server, "/mesh/c_1_0_0") is not None
        dash._scene_t -= server_module.SCENE_PERIOD_S  # the period has passed: the rest catches up
        dash._draw_scene(snapshot(chunks={a.key: a, b.key: b}, trajectory=path(5)), 4)
        assert dash.scene_updates == 3 and dash.layers.trajectory.n_drawn == 5
    finally:
        dash.server.stop()


def test_dashboard_wakes_for_new_mesh_chunks_but_waits_out_other_changes() -> None:
    from h2viz.config import Config
    from h2viz.viewer.server import Dashboard
    from h2viz.worker import MappingWorker
    from tests.viewer.fakes import FakeMapper

    worker = MappingWorker(BoxRoomSource(n=2), FakeMapper(), Config())  # type: ignore[arg-type]
    dash = Dashboard(worker, Config(), port=0)
    try:
        a, b = chunk((0, 0, 0)), chunk((1, 0, 0))
        shown = snapshot(chunks={a.key: a})
        worker.slot.put(shown)
        dash._latest = shown

        def pause_returns(new: object, join_s: float) -> bool:
            waiter = threading.Thread(target=dash._pause, args=(30.0,), daemon=True)
            waiter.start()
            time.sleep(0.05)
            worker.slot.put(new)
            waiter.join(timeout=join_s)
            return not waiter.is_alive()

        assert not pause_returns(replace(shown, frames_done=7), 0.5)  # same chunks: waits for the panel period
        assert pause_returns(snapshot(chunks={a.key: a, b.key: b}), 10.0)  # new chunks: drawn at once
    finally:
        dash._stop.set()
        dash.server.stop()
