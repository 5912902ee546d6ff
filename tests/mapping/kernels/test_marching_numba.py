"""The compiled marching cubes (h2viz.mapping.kernels.marching_numba) against scikit-image's (the reference path), and
its case table on every inside/outside pattern."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from h2viz.mapping.kernels import marching_numba
from h2viz.mapping.meshing import case_table as mc_table
from h2viz.mapping.meshing.case_table import case_table
from h2viz.mapping.meshing.marching import SNAP, ChunkLattice, chunk_lattice, surface_mesh


def lattice_and_values(voxels: np.ndarray, resolution: int, sdf) -> tuple[ChunkLattice, np.ndarray]:
    lat = chunk_lattice((0, 0, 0), voxels, resolution, fast=marching_numba)
    spacing = 0.1 / resolution
    return lat, sdf((lat.points + lat.origin) * spacing).astype(np.float32)


def reference(lat: ChunkLattice, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return surface_mesh(lat, values, 0.1 / 8)  # scikit-image, welded by position


def sphere(centre: np.ndarray, r: float):
    return lambda p: np.linalg.norm(p - centre, axis=1) - r


@pytest.mark.parametrize("masked", [False, True])
def test_sphere_has_the_reference_vertices_and_surface(masked: bool) -> None:
    centre = np.array([0.213, 0.187, 0.241])
    g = np.stack(np.meshgrid(*[np.arange(5)] * 3, indexing="ij"), -1).reshape(-1, 3)
    voxels = g[(g[:, 0] < 3) | (g[:, 2] > 2)] if masked else g  # a masked block cuts the sphere open
    lat, values = lattice_and_values(voxels, 8, sphere(centre, 0.17))
    fast_v, fast_f = surface_mesh(lat, values, 0.1 / 8, marching_numba)
    ref_v, ref_f = reference(lat, values)
    # the same crossings, placed at the same bits
    np.testing.assert_array_equal(np.unique(fast_v, axis=0), np.unique(ref_v, axis=0))
    fast, ref = trimesh.Trimesh(fast_v, fast_f, process=False), trimesh.Trimesh(ref_v, ref_f, process=False)
    assert fast.area == pytest.approx(ref.area, rel=2e-3)
    assert len(np.unique(fast_f)) == len(fast_v)  # every vertex used
    outward = np.einsum("ij,ij->i", fast.face_normals, fast.triangles_center - centre)
    assert (outward > 0).all()
    if not masked:
        assert fast.is_watertight and fast.is_winding_consistent
        assert fast.volume == pytest.approx(ref.volume, rel=1e-3)
        assert fast.volume == pytest.approx(4 / 3 * np.pi * 0.17**3, rel=1e-2)


@pytest.mark.parametrize("seed", range(3))
def test_random_fields_give_closed_consistently_wound_surfaces(seed: int) -> None:
    """Random values exercise every inside/outside pattern, ambiguous faces included; inside a positive border
    every surface is closed, every edge is used once in each direction and normals point out of the inside."""
    rng = np.random.default_rng(seed)
    n = 12
    volume = rng.normal(size=(n + 1,) * 3).astype(np.float32)
    volume[[0, -1]], volume[:, [0, -1]], volume[:, :, [0, -1]] = 1.0, 1.0, 1.0
    cells = np.ones((n,) * 3, dtype=bool)
    vertices, faces, collapsed = marching_numba.march_welded(volume, cells, np.zeros(3, np.int64), 1.0, SNAP)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    patterns = set()
    for x, y, z in np.ndindex(cells.shape):
        corners = volume[x : x + 2, y : y + 2, z : z + 2].reshape(-1)
        patterns.add(int(np.sum((corners < 0) << np.arange(8))))
    assert len(patterns) > 200
    assert mesh.is_watertight and mesh.is_winding_consistent
    edges = np.sort(mesh.edges, axis=1)
    assert len(np.unique(mesh.edges, axis=0)) == len(mesh.edges)  # each directed edge once
    assert len(edges) == 2 * len(np.unique(edges, axis=0))
    assert mesh.volume > 0  # normals point towards positive values
    inside = np.mean(volume[1:-1, 1:-1, 1:-1] < 0) * (n - 2) ** 3  # lattice points inside, about the volume
    assert 0.6 * inside < mesh.volume < 1.4 * inside
    assert not collapsed or len(np.unique(faces)) <= len(vertices)


def test_case_table_uses_every_crossed_edge_and_draws_no_chord_on_a_face() -> None:
    """Each pattern's triangles use exactly its crossed edges; two of a triangle's vertices on one cube face are
    joined on that face's segments only (a chord across a face with four crossings would also be drawn by the
    neighbouring cell, giving an edge of four triangles)."""
    table = case_table()
    for inside in range(256):
        crossed = {
            e
            for e, (c, a) in enumerate(zip(table.edge_corner, table.edge_axis, strict=True))
            if ((inside >> c) & 1) != ((inside >> (c | (1 << (2 - a)))) & 1)
        }
        tris = table.edges[inside, : 3 * table.counts[inside]].reshape(-1, 3)
        assert set(tris.ravel().tolist()) == crossed and (table.edges[inside, 3 * table.counts[inside] :] == -1).all()
        segments = {s for axis in range(3) for side in (0, 1) for s in mc_table._face_segments(inside, axis, side)}
        for tri in tris.tolist():
            for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
                if mc_table._edge_faces(a) & mc_table._edge_faces(b):
                    assert (a, b) in segments or (b, a) in segments
    assert table.counts[0] == table.counts[255] == 0


def test_crossings_that_snap_to_a_lattice_point_share_one_vertex() -> None:
    volume = np.ones((3, 3, 3), np.float32)
    volume[1, 1, 1] = -1e-7  # every edge at the centre point crosses within SNAP of it
    volume[0, 0, 0] = -1.0
    vertices, faces, collapsed = marching_numba.march_welded(
        volume, np.ones((2, 2, 2), bool), np.zeros(3, np.int64), 1.0, SNAP
    )
    assert collapsed
    assert np.sum(np.all(vertices == 1.0, axis=1)) == 1
    assert (
        (faces[:, 0] != faces[:, 1]).all() and (faces[:, 1] != faces[:, 2]).all() and (faces[:, 0] != faces[:, 2]).all()
    )


def test_vertex_matching_agrees_with_the_sorting_reference() -> None:
    """Colours carried over between re-meshings: the hash-table match and numpy's unique give the same indices,
    with repeated rows (first index) and -0.0 equal to 0.0."""
    from h2viz.mapping.meshing import passes
    from h2viz.types import MeshChunk

    rng = np.random.default_rng(1)
    old = rng.normal(size=(3000, 3)).astype(np.float32)
    old[5], old[9, 0] = old[2], -0.0
    new = np.concatenate([old[rng.permutation(3000)[:2000]], rng.normal(size=(1500, 3)).astype(np.float32)])
    new[0], new[0, 0] = old[9], 0.0
    before = MeshChunk((0, 0, 0), old, np.zeros((0, 3), np.int32), np.zeros((3000, 3), np.uint8), 0)
    fast = passes._same_vertex(new, before, marching_numba)
    np.testing.assert_array_equal(fast, passes._same_vertex(new, before))
    assert (fast >= 0).sum() == 2000 and fast[0] == 9 and 5 not in fast


@pytest.mark.parametrize("resolution", [1, 4, 8])
def test_chunk_lattice_matches_the_numpy_reference(resolution: int) -> None:
    rng = np.random.default_rng(resolution)
    voxels = np.unique(rng.integers(-3, 4, size=(60, 3)), axis=0) + np.array([40, -7, 3])
    flags = rng.random(len(voxels)) < 0.3
    fast = chunk_lattice((5, -1, 0), voxels, resolution, flags, marching_numba)
    ref = chunk_lattice((5, -1, 0), voxels, resolution, flags)
    assert fast.key == ref.key
    for name in ("origin", "cells", "points", "point_voxel", "point_flagged"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(ref, name), err_msg=name)
        assert getattr(fast, name).dtype == getattr(ref, name).dtype, name
