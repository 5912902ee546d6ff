"""Ray-cast ground-truth images of meshes: exact depth of a known plane, interpolated vertex colours."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from h2viz.eval.mesh_render import MeshRenderer
from h2viz.eval.metrics import EvalError
from h2viz.geometry import look_at
from tests.eval.scenes import grid_plane, plane_texture, render_textured_plane

K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])  # 64 x 48


def test_depth_of_a_fronto_parallel_plane_and_its_edges() -> None:
    plane = grid_plane(-1.0, 1.0, -1.0, 1.0, z=2.0, cells=20)
    depth = MeshRenderer(plane)(K, np.eye(4), 48, 64, "depth")
    assert depth.shape == (48, 64) and depth.dtype == np.float32
    # x = +-1 m at 2 m projects to u = 31.5 +- 25: columns 7..56 see the plane, the others nothing
    hit_cols = np.nonzero(depth[24] > 0)[0]
    assert hit_cols.min() == 7 and hit_cols.max() == 56
    np.testing.assert_allclose(depth[depth > 0], 2.0, atol=1e-5)


def test_tilted_camera_depth_is_camera_z_and_colours_follow_the_vertices() -> None:
    plane = grid_plane(-3.0, 3.0, -3.0, 3.0, z=2.0, cells=300)  # 2 cm cells
    colours = plane_texture(plane.vertices[:, 0], plane.vertices[:, 1])  # (N,3) in [0.1, 0.9]
    plane.visual.vertex_colors = np.round(colours * 255).astype(np.uint8)
    T = look_at(np.array([0.6, -0.4, 0.0]), np.array([0.1, 0.2, 2.0]), np.array([0.0, -1.0, 0.0]))
    render = MeshRenderer(plane)
    depth, rgb = render(K, T, 48, 64, "depth"), render(K, T, 48, 64, "rgb")
    exact_depth = render_textured_plane(K, T, 48, 64, "depth")
    exact_rgb = render_textured_plane(K, T, 48, 64, "rgb")
    assert np.all(depth > 0)
    np.testing.assert_allclose(depth, exact_depth, atol=1e-4)  # not the ray length
    assert np.abs(rgb - exact_rgb).max() < 0.01  # linear interpolation of a smooth texture + uint8


def test_uncoloured_mesh_is_grey_and_misses_are_black() -> None:
    plane = grid_plane(-0.2, 0.2, -0.2, 0.2, z=1.0, cells=2)
    rgb = MeshRenderer(plane)(K, np.eye(4), 48, 64, "rgb")
    assert rgb.shape == (48, 64, 3) and rgb.dtype == np.float32
    np.testing.assert_allclose(rgb[24, 32], 0.5)
    np.testing.assert_array_equal(rgb[0, 0], 0.0)


def test_bad_mode_and_empty_mesh_are_errors() -> None:
    plane = grid_plane(-0.2, 0.2, -0.2, 0.2, z=1.0, cells=2)
    with pytest.raises(EvalError, match="unknown mode"):
        MeshRenderer(plane)(K, np.eye(4), 48, 64, "normal")
    with pytest.raises(EvalError, match="without faces"):
        MeshRenderer(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int)))
