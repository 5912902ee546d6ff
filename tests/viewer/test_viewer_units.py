"""Browser-free tests of the viewer's pieces: snapshot diffing, cube outlines, the GLB writer,
camera conversions, false colours and panel text."""

from __future__ import annotations

import json
import struct
from dataclasses import replace
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import trimesh

from h2viz.geometry import look_at, project
from h2viz.types import FrameStats
from h2viz.viewer.diff import block_signatures, diff_chunks, diff_signatures, group_cells
from h2viz.viewer.glb import mesh_glb, srgb_to_linear_u8
from h2viz.viewer.render_loop import FAR_M, background, client_view
from h2viz.viewer.shapes import (
    MAX_TRAJECTORY_SEGMENTS,
    colorize_depth,
    cube_edges,
    fov_aspect,
    frame_points,
    initial_view,
    pose_from_wxyz,
    to_rgb8,
    trajectory_segments,
    view_intrinsics,
    wxyz_position,
)
from h2viz.viewer.status import StatusPanels, plot_data, progress_markdown
from h2viz.viewer.viser_server import make_viser_server
from h2viz.worker import RenderedView
from tests.viewer.fakes import BoxRoomSource, chunk, snapshot


def test_diff_chunks_uses_identity_not_version() -> None:
    a, b, c = chunk((0, 0, 0)), chunk((1, 0, 0)), chunk((2, 0, 0))
    drawn = {a.key: a, b.key: b, c.key: c}
    b2 = chunk((1, 0, 0), version=1)  # re-meshed at the same map version (e.g. new resolution)
    d = chunk((0, 1, 0))
    diff = diff_chunks(drawn, {a.key: a, b.key: b2, d.key: d})
    assert diff.changed == [(0, 1, 0), (1, 0, 0)]
    assert diff.removed == [(2, 0, 0)]
    assert diff_chunks(drawn, drawn).changed == [] and diff_chunks(drawn, drawn).removed == []


def test_group_cells_floors_negative_coordinates_and_sorts() -> None:
    cells = np.array([[-1, 0, 0], [15, 0, 0], [16, 0, 0], [0, -17, 3], [-16, 0, 0]])
    groups = group_cells(cells[::-1], block=16)
    assert sorted(groups) == [(-1, 0, 0), (0, -2, 0), (0, 0, 0), (1, 0, 0)]
    np.testing.assert_array_equal(groups[(-1, 0, 0)], [[-16, 0, 0], [-1, 0, 0]])
    assert group_cells(np.zeros((0, 3)), 16) == {}


def test_signatures_change_only_for_the_touched_block() -> None:
    cells = np.array([[0, 0, 0], [1, 0, 0], [20, 0, 0]])
    before = block_signatures(group_cells(cells, 16))
    after = block_signatures(group_cells(np.vstack([cells, [[2, 0, 0]]]), 16))
    diff = diff_signatures(before, after)
    assert diff.changed == [(0, 0, 0)] and diff.removed == []
    assert diff_signatures(after, block_signatures(group_cells(cells[2:], 16))).removed == [(0, 0, 0)]


@pytest.mark.parametrize(
    ("cells", "n_edges"),
    [([[0, 0, 0]], 12), ([[0, 0, 0], [1, 0, 0]], 20), ([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], 33)],
)
def test_cube_edges_are_unique_axis_aligned_and_cell_sized(cells: list[list[int]], n_edges: int) -> None:
    seg = cube_edges(np.array(cells) - 3, 0.25)  # shifted into negative coordinates
    assert seg.shape == (n_edges, 2, 3)
    delta = seg[:, 1] - seg[:, 0]
    np.testing.assert_allclose(np.sort(np.abs(delta), axis=1), np.tile([0, 0, 0.25], (n_edges, 1)), atol=1e-6)
    keys = {tuple(np.round(s.ravel(), 4)) for s in seg}
    assert len(keys) == n_edges
    c = np.array(cells) - 3
    assert seg.min() == pytest.approx(0.25 * c.min()) and seg.max() == pytest.approx(0.25 * (c.max() + 1))


def _glb_parts(data: bytes) -> tuple[dict, bytes]:
    magic, version, total = struct.unpack_from("<4sII", data, 0)
    assert (magic, version, total) == (b"glTF", 2, len(data))
    json_len, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON" and json_len % 4 == 0
    gltf = json.loads(data[20 : 20 + json_len])
    bin_len, kind = struct.unpack_from("<I4s", data, 20 + json_len)
    assert kind == b"BIN\0"
    return gltf, data[28 + json_len : 28 + json_len + bin_len]


def _accessor(gltf: dict, blob: bytes, i: int, dtype: type, width: int) -> np.ndarray:
    acc = gltf["accessors"][i]
    view = gltf["bufferViews"][acc["bufferView"]]
    stride = view.get("byteStride", width * np.dtype(dtype).itemsize) // np.dtype(dtype).itemsize
    count = acc["count"] * stride if acc["type"] != "SCALAR" else acc["count"]
    raw = np.frombuffer(blob, dtype=dtype, count=count, offset=view["byteOffset"])
    return raw.reshape(-1, stride)[:, :width]


def test_glb_round_trips_quantised_geometry_and_linear_colours() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    colors = np.tile(np.array([[0, 128, 255]], np.uint8), (len(sphere.vertices), 1))
    data = mesh_glb(sphere.vertices + [2.0, -3.0, 0.25], sphere.faces, colors, opacity=0.5)
    gltf, blob = _glb_parts(data)
    assert gltf["extensionsRequired"] == ["KHR_mesh_quantization"]
    node = gltf["nodes"][0]
    q = _accessor(gltf, blob, 0, np.int16, 3)
    assert gltf["accessors"][0]["normalized"] and gltf["accessors"][0]["min"] == q.min(axis=0).tolist()
    decoded = np.asarray(node["translation"]) + np.asarray(node["scale"]) * q / 32767.0
    np.testing.assert_allclose(decoded, sphere.vertices + [2.0, -3.0, 0.25], atol=0.5 / 32767)  # 15 um steps
    primitive = gltf["meshes"][0]["primitives"][0]
    normal = gltf["accessors"][primitive["attributes"]["NORMAL"]]
    assert "bufferView" not in normal and normal["count"] == len(sphere.vertices)  # zeros, recomputed by viser
    assert normal["componentType"] == 5126  # float: three.js accumulates face normals in the attribute's array
    rgba = _accessor(gltf, blob, 1, np.uint8, 4)[0]
    np.testing.assert_array_equal(rgba, [0, 55, 255, 255])  # sRGB 128 -> linear 0.2159 -> 55 / 255
    assert gltf["accessors"][2]["componentType"] == 5123  # 16-bit indices for a small mesh
    np.testing.assert_array_equal(_accessor(gltf, blob, 2, np.uint16, 3), sphere.faces)
    assert gltf["materials"][0]["alphaMode"] == "BLEND"
    assert gltf["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"][3] == 0.5
    assert len(data) < len(sphere.vertices) * 12 + len(sphere.faces) * 6 + 1500  # 12 B / vertex, 6 B / face


def test_glb_of_a_flat_chunk_keeps_its_plane() -> None:
    vertices = np.array([[0.0, 0.0, 1.5], [0.8, 0.0, 1.5], [0.0, 0.8, 1.5]], np.float32)
    gltf, blob = _glb_parts(mesh_glb(vertices, np.array([[0, 1, 2]]), np.zeros((3, 3), np.uint8)))
    node = gltf["nodes"][0]
    decoded = (
        np.asarray(node["translation"]) + np.asarray(node["scale"]) * _accessor(gltf, blob, 0, np.int16, 3) / 32767
    )
    np.testing.assert_allclose(decoded, vertices, atol=1e-5)
    assert node["scale"][2] == 1.0  # no zero scale on the flat axis


def test_srgb_to_linear_end_points() -> None:
    out = srgb_to_linear_u8(np.array([[0, 255, 60]], np.uint8))
    assert out[0, 0] == 0 and out[0, 1] == 255 and out[0, 3] == 255
    assert out[0, 2] == round(((60 / 255 + 0.055) / 1.055) ** 2.4 * 255)


def test_srgb_to_linear_matches_the_standard_curve_for_every_value() -> None:
    values = np.arange(256, dtype=np.uint8)
    out = srgb_to_linear_u8(np.stack([values, values[::-1], values], axis=1), alpha=0.5)
    c = values / 255.0
    expected = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4) * 255.0
    assert np.abs(out[:, 0].astype(float) - expected).max() <= 0.5 + 1e-9
    assert out[128, 0] == 55 and out[188, 0] == 128  # mid-grey sRGB is about a fifth of the light
    assert (out[:, 1] == out[::-1, 0]).all() and (out[:, 3] == 128).all()


def test_viser_pose_and_intrinsics_round_trip() -> None:
    T = look_at(np.array([1.0, -2.0, 1.5]), np.array([0.0, 0.5, 0.8]))
    wxyz, position = wxyz_position(T)
    np.testing.assert_allclose(pose_from_wxyz(wxyz, position), T, atol=1e-9)
    K = view_intrinsics(np.radians(60.0), 320, 200)
    fov, aspect = fov_aspect(K, 320, 200)
    assert fov == pytest.approx(np.radians(60.0)) and aspect == pytest.approx(1.6)


def test_client_view_matches_the_browser_camera() -> None:
    T = look_at(np.array([0.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]))
    wxyz, position = wxyz_position(T)
    camera = SimpleNamespace(wxyz=wxyz, position=position, fov=np.radians(50), image_width=1000, image_height=500)
    view = client_view(camera, 200)
    assert view is not None and (view.width, view.height) == (200, 100)
    uv, z = project(np.array([[3.0, 0.0, 1.0]]), view.K, view.T_world_camera)  # on the optical axis
    np.testing.assert_allclose(uv[0], [99.5, 49.5], atol=1e-9)
    top = np.array([[3.0, 0.0, 1.0 + 3.0 * np.tan(np.radians(25))]])  # top edge of the vertical fov
    assert project(top, view.K, view.T_world_camera)[0][0, 1] == pytest.approx(-0.5, abs=1e-6)
    moved = SimpleNamespace(**{**camera.__dict__, "position": position + 0.01})
    assert client_view(moved, 200).key() != view.key()  # type: ignore[union-attr]


def test_false_colour_range_of_a_large_image_follows_its_percentiles() -> None:
    depth = np.linspace(0.5, 4.5, 480 * 640, dtype=np.float32).reshape(480, 640)
    depth[:, :40] = 0.0  # no depth
    rgb = colorize_depth(depth)
    lo, hi = np.percentile(depth[depth > 0], [2, 98])  # the exact range, over every pixel
    scaled = np.clip((depth - lo) / (hi - lo), 0, 1)
    exact = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    diff = np.abs(rgb[:, 40:].astype(int) - exact[:, 40:].astype(int))
    assert diff.mean() < 0.5 and (rgb[:, :40] == 0).all()


def test_background_sends_empty_pixels_far_away() -> None:
    depth = np.array([[0.0, 2.0]], np.float32)
    image, bg_depth = background(RenderedView(np.zeros((1, 2, 3), np.float32), depth, "rgb", 0.0))
    np.testing.assert_array_equal(bg_depth, [[FAR_M, 2.0]])
    assert image.dtype == np.uint8 and image.shape == (1, 2, 3)


def test_false_colours() -> None:
    depth = np.array([[0.0, 1.0, 2.0, 3.0]], np.float32)
    rgb = colorize_depth(depth, backdrop=(1, 2, 3))
    assert tuple(rgb[0, 0]) == (1, 2, 3) and len({tuple(p) for p in rgb[0, 1:]}) == 3
    normal = to_rgb8(np.array([[[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]], np.float32), "normal", backdrop=(9, 9, 9))
    assert tuple(normal[0, 0]) == (128, 128, 255) and tuple(normal[0, 1]) == (9, 9, 9)


def test_frame_points_lie_on_the_depth() -> None:
    frame = BoxRoomSource(n=4, width=40, height=30).load(1, 1)
    points, colors = frame_points(frame, max_points=300)
    assert 100 < len(points) <= 300 and colors.shape == (len(points), 3)
    uv, z = project(points.astype(np.float64), frame.K, frame.T_world_camera)
    u, v = np.round(uv).astype(int).T
    np.testing.assert_allclose(z, frame.depth_m[v, u], rtol=1e-5)
    np.testing.assert_array_equal(colors, frame.rgb[v, u])


def test_initial_view_snaps_up_and_looks_at_the_scene() -> None:
    T = look_at(np.array([1.0, 1.0, 1.4]), np.array([3.0, 1.2, 1.3]))  # nearly level camera, world z up
    up, eye, target = initial_view(T)
    np.testing.assert_allclose(up, [0, 0, 1])
    assert eye[2] > T[2, 3] and np.dot(target - eye, T[:3, 2]) > 0


def test_panel_text_and_plot_data() -> None:
    stats = tuple(
        FrameStats(i, 0.1 * (i + 1), 5, 100, 2, {"rgb": 0.5, "sdf": 0.0 if i == 1 else 0.1}) for i in range(3)
    )
    snap = snapshot(stats=stats, voxels=np.zeros((7, 3)))
    text = progress_markdown(snap)
    assert "| Frames | 3 / 10 |" in text and "| Voxels | 7 |" in text and "200 ms" in text
    (x, rgb, sdf), (_, ms) = plot_data(snap, ["rgb", "sdf"])
    np.testing.assert_array_equal(x, [0, 1, 2])
    assert np.isnan(sdf[1]) and sdf[0] == 0.1  # the log plot cannot show zero
    np.testing.assert_allclose(ms, [100, 200, 300])
    assert "| State | mapping |" in text
    assert "| State | refining (40 steps left) |" in progress_markdown(replace(snap, paused=True, refine_left=40))
    assert "| State | mapping, 40 refinement steps queued |" in progress_markdown(replace(snap, refine_left=40))
    assert "| State | finished, refined 500 steps |" in progress_markdown(replace(snap, finished=True, refined=500))
    preparing = progress_markdown(replace(snap, phase="streaming", preparing=(40, 300)))
    assert "rendering the frames to play, 40 / 300" in preparing and "optimising between frames" not in preparing
    assert "Behind the stream" not in text  # every-frame mode: no stream to be behind
    behind = progress_markdown(replace(snap, phase="streaming", waiting=12, lag_s=0.43))
    assert "| Behind the stream | 0.4 s (12 frames waiting) |" in behind
    assert "(1 frame waiting)" in progress_markdown(replace(snap, phase="streaming", waiting=1))
    assert "Behind the stream" not in progress_markdown(replace(snap, phase="sharpening", waiting=0, lag_s=0.43))


def test_both_plots_are_logarithmic() -> None:
    """The first frame (kernel warm-up) takes seconds: on a linear axis it flattens every later frame."""
    server = make_viser_server("127.0.0.1", 0)
    try:
        panels = StatusPanels(server.gui)
        stats = tuple(FrameStats(i, 30.0 if i == 0 else 0.5, 5, 100, 2, {"rgb": 0.5}) for i in range(3))
        panels.update(snapshot(stats=stats, voxels=np.zeros((7, 3))))
        assert panels.time_plot.scales["y"]["distr"] == 3  # uPlot's log scale
        assert panels.loss_plot is not None and panels.loss_plot.scales["y"]["distr"] == 3
        np.testing.assert_allclose(panels.time_plot.data[1], [30000, 500, 500])
    finally:
        server.stop()


def test_a_long_trajectory_is_drawn_with_a_bounded_number_of_segments() -> None:
    poses = np.tile(np.eye(4), (10_001, 1, 1))
    poses[:, 0, 3] = np.arange(10_001) * 0.01  # a straight walk of 100 m, 1 cm a frame
    short = trajectory_segments(poses[:50])
    assert short.shape == (49, 2, 3) and np.allclose(short[:, 1, 0] - short[:, 0, 0], 0.01)
    seg = trajectory_segments(poses)
    assert len(seg) <= MAX_TRAJECTORY_SEGMENTS and len(seg) > MAX_TRAJECTORY_SEGMENTS // 2
    assert seg[0, 0, 0] == 0.0 and seg[-1, 1, 0] == pytest.approx(100.0)  # from the first pose to the newest
    np.testing.assert_allclose(seg[1:, 0], seg[:-1, 1])  # one connected path
