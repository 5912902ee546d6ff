"""Chunked marching cubes on analytic SDFs: accuracy, watertightness, welding, masks, updates, export."""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import trimesh

from h2viz.errors import ConfigError, H2vizError
from h2viz.mapping.meshing.mesher import ChunkedMesher, MeshingError, export_mesh, merge_chunks
from h2viz.mapping.meshing.passes import kept_faces

VS = 0.1  # voxel size, metres
SPHERE_R = 0.35
PLANE_N = np.array([0.36, -0.48, 0.8])  # unit normal, tilted against every grid axis
PLANE_D = 0.0123
Fn = Callable[[np.ndarray], np.ndarray]


def sphere_sdf(centre: np.ndarray, r: float = SPHERE_R) -> Fn:
    """The sphere's SDF (N,) at points (N,3); like the mapper's field it also takes the points' voxel ids."""
    return lambda p, voxel=None: (np.linalg.norm(p - centre, axis=1) - r).astype(np.float32)


def plane_sdf(p: np.ndarray, voxel: np.ndarray | None = None) -> np.ndarray:
    return (p.astype(np.float64) @ PLANE_N - PLANE_D).astype(np.float32)


def position_color(p: np.ndarray) -> np.ndarray:
    """A colour that varies with position, so a colour taken from the wrong vertex shows up."""
    return (np.floor(np.asarray(p, dtype=np.float64) * 1000.0) % 256).astype(np.uint8)


def voxels_near(sdf: Fn, lo: np.ndarray, n: int, band_m: float = 0.1) -> np.ndarray:
    """Voxel coords (V,3) in the n^3 block from lo (3,) whose centre is within band_m of the surface."""
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3) + lo
    return g[np.abs(sdf((g + 0.5) * VS)) < band_m]


def sphere_voxels(centre: np.ndarray) -> np.ndarray:
    return voxels_near(sphere_sdf(centre), np.floor((centre - 0.6) / VS).astype(np.int64), 13)


def plane_voxels() -> np.ndarray:
    """Voxels within 0.1 m of the tilted plane, over a 1.6 m x 1.6 m patch."""
    return voxels_near(plane_sdf, np.array([-8, -8, -8]), 16)


def sphere_mesh(centre: np.ndarray, chunk_voxels: int) -> tuple[trimesh.Trimesh, dict]:
    mesher = ChunkedMesher(VS, 8, chunk_voxels)
    chunks = mesher.update(sphere_voxels(centre), None, sphere_sdf(centre), position_color, 1)
    return merge_chunks(chunks), chunks


def boundary_edges(mesh: trimesh.Trimesh) -> np.ndarray:
    """Edges (E,2) used by exactly one face."""
    edges = np.sort(mesh.edges, axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    return uniq[counts == 1]


def on_region_border(points: np.ndarray, voxels: np.ndarray) -> np.ndarray:
    """(N,) bool: the closed voxel boxes touching each point include allocated and unallocated voxels."""
    u = points / VS
    lo, hi = np.floor(u - 1e-6).astype(np.int64), np.floor(u + 1e-6).astype(np.int64)
    allocated = {tuple(v) for v in voxels.tolist()}
    out = []
    for a, b in zip(lo.tolist(), hi.tolist(), strict=True):
        touching = {tuple(c) for c in itertools.product(*zip(a, b, strict=True))}
        inside = [t in allocated for t in touching]
        out.append(any(inside) and not all(inside))
    return np.array(out)


def unique_rows(a: np.ndarray) -> int:
    return len(np.unique(a, axis=0))


def test_chunk_keys_floor_negative_coordinates() -> None:
    mesher = ChunkedMesher(VS, 8, 8)
    coords = np.array([[-1, -1, -1], [-8, 0, 7], [-9, 0, 8], [7, 8, -8], [-1, -1, -1]])
    assert mesher.chunks_of(coords) == {(-1, -1, -1), (-1, 0, 0), (-2, 0, 1), (0, 1, -1)}
    assert mesher.chunks_of(np.array([[0, 0, 0]]), halo=True) == set(itertools.product((-1, 0), repeat=3))
    assert mesher.chunks_of(np.zeros((0, 3), dtype=np.int64)) == set()


@pytest.mark.parametrize("centre", [np.array([0.013, -0.021, 0.034]), np.array([-1.234, -0.567, -2.011])])
def test_sphere_is_accurate_watertight_welded_and_outward(centre: np.ndarray) -> None:
    mesh, chunks = sphere_mesh(centre, chunk_voxels=2)
    assert len(chunks) >= 27  # the sphere spans many 0.2 m chunks
    err = np.abs(np.linalg.norm(mesh.vertices - centre, axis=1) - SPHERE_R)
    assert err.max() < 2e-3
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert unique_rows(mesh.vertices) == len(mesh.vertices)
    outward = np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles_center - centre)
    assert (outward > 0).all()
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * SPHERE_R**3, rel=5e-3)
    np.testing.assert_array_equal(mesh.visual.vertex_colors[:, :3], position_color(mesh.vertices.astype(np.float32)))
    for chunk in chunks.values():  # within a chunk, vertices are unique and colours belong to them
        assert unique_rows(chunk.vertices) == len(chunk.vertices)
        assert chunk.faces.dtype == np.int32 and chunk.colors.dtype == np.uint8 and chunk.version == 1


def test_chunk_size_does_not_change_the_merged_mesh() -> None:
    centre = np.array([0.813, 0.779, 0.834])
    small, small_chunks = sphere_mesh(centre, chunk_voxels=2)
    large, large_chunks = sphere_mesh(centre, chunk_voxels=16)
    assert len(large_chunks) == 1 and len(small_chunks) > 27
    np.testing.assert_array_equal(np.sort(small.vertices, axis=0), np.sort(large.vertices, axis=0))
    assert len(small.faces) == len(large.faces)


def test_only_corners_of_allocated_voxels_are_sampled_once() -> None:
    rng = np.random.default_rng(0)
    voxels = np.unique(rng.integers(-6, 6, size=(40, 3)), axis=0)
    seen: list[np.ndarray] = []

    def counting_sdf(p: np.ndarray, voxel: np.ndarray) -> np.ndarray:
        seen.append(p.copy())
        return plane_sdf(p)

    ChunkedMesher(VS, 4, 3).update(voxels, None, counting_sdf, position_color, 1)
    sampled = np.rint(np.concatenate(seen) / (VS / 4)).astype(np.int64)
    expected = {tuple(v * 4 + k) for v in voxels for k in itertools.product(range(5), repeat=3)}
    assert len(sampled) == len(expected)  # each lattice point once, shared faces included
    assert {tuple(p) for p in sampled.tolist()} == expected


def test_tilted_plane_has_no_cracks_across_voxels_and_chunks() -> None:
    voxels = plane_voxels()
    mesh = merge_chunks(ChunkedMesher(VS, 8, 4).update(voxels, None, plane_sdf, position_color, 1))
    assert len(mesh.faces) > 1000
    assert np.abs(mesh.vertices @ PLANE_N - PLANE_D).max() < 1e-4
    assert unique_rows(mesh.vertices) == len(mesh.vertices)
    assert mesh.is_winding_consistent
    assert (mesh.face_normals @ PLANE_N > 0.999).all()  # towards positive SDF
    edges = boundary_edges(mesh)
    assert len(edges) > 0
    assert on_region_border(mesh.vertices[edges].mean(axis=1), voxels).all()


def test_missing_voxels_leave_a_hole_exactly_there() -> None:
    voxels = plane_voxels()
    removed = (voxels[:, 0] >= 0) & (voxels[:, 0] < 2) & (voxels[:, 1] >= 0) & (voxels[:, 1] < 2)
    kept = voxels[~removed]
    full = merge_chunks(ChunkedMesher(VS, 8, 4).update(voxels, None, plane_sdf, position_color, 1))
    holed = merge_chunks(ChunkedMesher(VS, 8, 4).update(kept, None, plane_sdf, position_color, 1))
    cell_of_face = {tuple(c) for c in np.floor(holed.triangles_center / VS).astype(np.int64).tolist()}
    assert not cell_of_face & {tuple(v) for v in voxels[removed].tolist()}
    # the plane crosses the removed 0.2 m x 0.2 m column over an area of 0.04 / n_z
    assert full.area - holed.area == pytest.approx(0.04 / PLANE_N[2], abs=1e-4)
    edges = boundary_edges(holed)
    mid = holed.vertices[edges].mean(axis=1)
    assert on_region_border(mid, kept).all()
    rim = (mid[:, 0] > -1e-6) & (mid[:, 0] < 0.2 + 1e-6) & (mid[:, 1] > -1e-6) & (mid[:, 1] < 0.2 + 1e-6)
    assert rim.sum() >= 4 * 2 * 8  # at least 2 voxels x 8 cells along each side of the hole


def bump_inside_one_chunk(centre: np.ndarray, chunk_m: float) -> tuple[np.ndarray, tuple[int, int, int]]:
    """A point on the sphere at least 6 cm from the faces of its chunk, and that chunk's key."""
    for d in itertools.product(np.linspace(-1, 1, 9), repeat=3):
        if np.linalg.norm(d) == 0:
            continue
        q = centre + SPHERE_R * np.asarray(d) / np.linalg.norm(d)
        key = np.floor(q / chunk_m)
        if min((q - key * chunk_m).min(), ((key + 1) * chunk_m - q).min()) > 0.06:
            return q, (int(key[0]), int(key[1]), int(key[2]))
    raise AssertionError("no sphere point well inside a chunk")


def test_dirty_chunk_update_replaces_only_that_chunk() -> None:
    centre = np.array([0.013, -0.021, 0.034])
    sdf = sphere_sdf(centre)
    voxels = sphere_voxels(centre)
    mesher = ChunkedMesher(VS, 8, 2)
    before = mesher.update(voxels, None, sdf, position_color, 1)
    q, key = bump_inside_one_chunk(centre, 2 * VS)
    assert key in before

    def bumped(p: np.ndarray, voxel: np.ndarray | None = None) -> np.ndarray:
        w = np.clip(1.0 - np.linalg.norm(p - q, axis=1) / 0.04, 0.0, None)
        return (sdf(p) - 0.01 * w).astype(np.float32)

    after = mesher.update(voxels, {key}, bumped, position_color, 2)
    assert after.keys() == before.keys()
    assert after[key] is not before[key] and after[key].version == 2
    assert not np.array_equal(after[key].vertices, before[key].vertices)
    assert all(after[k] is before[k] for k in before if k != key)
    merged = merge_chunks(after)
    fresh = merge_chunks(ChunkedMesher(VS, 8, 2).update(voxels, None, bumped, position_color, 2))
    np.testing.assert_array_equal(np.sort(merged.vertices, axis=0), np.sort(fresh.vertices, axis=0))
    assert merged.is_watertight
    again = mesher.update(voxels, [], bumped, position_color, 3)  # nothing dirty: nothing re-meshed
    assert all(again[k] is after[k] for k in after)


def test_voxel_set_changes_drop_or_remesh_chunks() -> None:
    centre = np.array([0.013, -0.021, 0.034])
    sdf = sphere_sdf(centre)
    voxels = sphere_voxels(centre)
    mesher = ChunkedMesher(VS, 8, 2)
    before = mesher.update(voxels, None, sdf, position_color, 1)
    keys = np.floor_divide(voxels, 2)
    gone = tuple(int(i) for i in keys[0])
    after = mesher.update(voxels[(keys != gone).any(axis=1)], [], sdf, position_color, 2)
    assert gone not in after and len(after) == len(before) - 1
    assert all(after[k] is before[k] for k in after)
    thinned_key = next(k for k in after if (keys == k).all(axis=1).sum() > 1)
    drop = np.flatnonzero((keys == thinned_key).all(axis=1))[0]  # one voxel of a still-present chunk
    thinned = mesher.update(np.delete(voxels, [drop], axis=0), [], sdf, position_color, 3)
    # the chunk whose voxel set changed and the chunk that came back are re-meshed without being asked
    assert {k for k, c in thinned.items() if c.version == 3} == {gone, thinned_key}


def test_resolution_change_remeshes_everything() -> None:
    centre = np.array([0.013, -0.021, 0.034])
    sdf = sphere_sdf(centre)
    voxels = sphere_voxels(centre)
    mesher = ChunkedMesher(VS, 8, 4)
    before = mesher.update(voxels, None, sdf, position_color, 1)
    mesher.resolution = 4
    after = mesher.update(voxels, [], sdf, position_color, 2)
    assert after.keys() == before.keys()
    assert all(after[k] is not before[k] and after[k].version == 2 for k in after)
    coarse, fine = merge_chunks(after), merge_chunks(before)
    assert len(fine.vertices) > 3 * len(coarse.vertices) and coarse.is_watertight
    with pytest.raises(ConfigError):
        mesher.resolution = 0
    with pytest.raises(ConfigError, match="resolution"):
        ChunkedMesher(VS, 200, 8)


def test_bad_callbacks_and_inputs_raise_meshing_errors() -> None:
    voxels = plane_voxels()
    mesher = ChunkedMesher(VS, 4, 4)
    with pytest.raises(MeshingError, match="sdf_fn"):
        mesher.update(voxels, None, lambda p, v: plane_sdf(p)[:, None].repeat(2, 1), position_color, 1)
    with pytest.raises(MeshingError, match="uint8"):
        mesher.update(voxels, None, plane_sdf, lambda p: position_color(p) / 255.0, 1)
    with pytest.raises(MeshingError, match="integer"):
        mesher.update(voxels.astype(np.float64), None, plane_sdf, position_color, 1)


def test_non_finite_sdf_values_leave_cells_out(caplog: pytest.LogCaptureFixture) -> None:
    def partial(p: np.ndarray, voxel: np.ndarray) -> np.ndarray:
        s = plane_sdf(p)
        s[p[:, 0] > 0.3] = np.nan
        return s

    with caplog.at_level(logging.WARNING):
        chunks = ChunkedMesher(VS, 8, 4).update(plane_voxels(), None, partial, position_color, 1)
    mesh = merge_chunks(chunks)
    assert len(mesh.faces) > 100 and mesh.vertices[:, 0].max() <= 0.3 + 1e-6
    assert "non-finite" in caplog.text


def test_export_round_trips(tmp_path: Path) -> None:
    mesh, _ = sphere_mesh(np.array([0.013, -0.021, 0.034]), chunk_voxels=4)
    colors = mesh.visual.vertex_colors[:, :3]
    export_mesh(mesh, tmp_path / "out" / "map.ply")
    ply = trimesh.load(tmp_path / "out" / "map.ply", process=False)
    assert (tmp_path / "out" / "map.ply").read_bytes().startswith(b"ply\nformat binary")
    np.testing.assert_array_equal(ply.vertices, mesh.vertices)
    np.testing.assert_array_equal(ply.faces, mesh.faces)
    np.testing.assert_array_equal(ply.visual.vertex_colors[:, :3], colors)
    for name in ("map.GLB", "map.obj"):  # suffix case does not matter
        export_mesh(mesh, tmp_path / name)
        back = trimesh.load(tmp_path / name, force="mesh", process=False)
        np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-6)
        np.testing.assert_array_equal(back.faces, mesh.faces)
        np.testing.assert_array_equal(back.visual.vertex_colors[:, :3], colors)
    with pytest.raises(MeshingError, match=r"\.ply") as err:
        export_mesh(mesh, tmp_path / "map.stl")
    assert isinstance(err.value, H2vizError)
    with pytest.raises(MeshingError, match="empty"):
        export_mesh(merge_chunks({}), tmp_path / "empty.ply")


# ------------------------------------------------------------------------------- incremental updates


class Counting:
    """An SDF callback that records the lattice points (global indices) and voxel ids it was asked for."""

    def __init__(self, sdf: Fn, resolution: int) -> None:
        self.sdf, self.resolution = sdf, resolution
        self.points: list[np.ndarray] = []
        self.ids: list[np.ndarray] = []

    def __call__(self, p: np.ndarray, voxel: np.ndarray) -> np.ndarray:
        self.points.append(np.rint(p / (VS / self.resolution)).astype(np.int64))
        self.ids.append(np.asarray(voxel).copy())
        return self.sdf(p)

    def seen(self) -> set[tuple[int, ...]]:
        return {tuple(q) for q in np.concatenate(self.points).tolist()} if self.points else set()


def lattice_points(voxels: np.ndarray, resolution: int) -> set[tuple[int, ...]]:
    """Global lattice indices of every corner of every cell of the voxels (V,3)."""
    steps = np.array(list(itertools.product(range(resolution + 1), repeat=3)))  # (K,3)
    return {tuple(q) for q in (voxels[:, None] * resolution + steps[None]).reshape(-1, 3).tolist()}


def sorted_vertices(chunks: dict) -> np.ndarray:
    v = merge_chunks(chunks).vertices
    return v[np.lexsort(v.T[::-1])]


def test_sdf_fn_gets_the_id_of_a_voxel_holding_each_point() -> None:
    voxels = plane_voxels()
    ids = 1000 + 7 * np.arange(len(voxels))
    counting = Counting(plane_sdf, 4)
    ChunkedMesher(VS, 4, 4).update(voxels, None, counting, position_color, 1, voxel_ids=ids)
    points, got = np.concatenate(counting.points), np.concatenate(counting.ids)
    owner = voxels[(got - 1000) // 7]  # (N,3) voxel coordinates of the ids handed over
    assert np.isin(got, ids).all()
    assert ((points >= owner * 4) & (points <= owner * 4 + 4)).all()  # the point lies in that voxel's box


def test_new_voxels_evaluate_only_their_new_points_and_match_a_fresh_mesh() -> None:
    voxels = plane_voxels()
    later = (voxels[:, 0] >= 3) & (voxels[:, 1] >= -2)  # a block of voxels added by a later frame
    mesher = ChunkedMesher(VS, 4, 4)
    before = mesher.update(voxels[~later], [], plane_sdf, position_color, 1)
    counting = Counting(plane_sdf, 4)
    coloured: list[np.ndarray] = []
    color_fn = lambda p: (coloured.append(p), position_color(p))[1]  # noqa: E731
    after = mesher.update(voxels, [], counting, color_fn, 2)
    assert counting.seen() == lattice_points(voxels[later], 4) - lattice_points(voxels[~later], 4)
    merged = merge_chunks(after)
    np.testing.assert_array_equal(
        merged.visual.vertex_colors[:, :3], position_color(merged.vertices.astype(np.float32))
    )
    old_vertices = {tuple(v) for c in before.values() for v in c.vertices.tolist()}
    assert not any(tuple(v) in old_vertices for v in np.concatenate(coloured).tolist())  # only new vertices
    changed = mesher.chunks_of(voxels[later])
    assert {k for k, c in after.items() if c is not before.get(k)} == changed & set(after)
    fresh = ChunkedMesher(VS, 4, 4).update(voxels, None, plane_sdf, position_color, 1)
    np.testing.assert_array_equal(sorted_vertices(after), sorted_vertices(fresh))
    assert len(merge_chunks(after).faces) == len(merge_chunks(fresh).faces)


def bumped_sdf(centre: np.ndarray, q: np.ndarray) -> Fn:
    sdf = sphere_sdf(centre)
    return lambda p, voxel=None: (sdf(p) - 0.01 * np.clip(1 - np.linalg.norm(p - q, axis=1) / 0.04, 0, None)).astype(
        np.float32
    )


def test_dirty_voxels_are_refreshed_within_the_budget_only() -> None:
    centre = np.array([0.013, -0.021, 0.034])
    voxels = sphere_voxels(centre)
    q, key = bump_inside_one_chunk(centre, 2 * VS)
    mesher = ChunkedMesher(VS, 8, 2)
    before = mesher.update(voxels, None, sphere_sdf(centre), position_color, 1)
    dirty = np.linalg.norm((voxels + 0.5) * VS - q, axis=1) < 0.13  # every voxel the 4 cm bump reaches
    bumped = Counting(bumped_sdf(centre, q), 8)
    same = mesher.update(voxels, [], bumped, position_color, 2, dirty_voxels=dirty, refresh_s=0.0)
    assert bumped.points == [] and all(same[k] is before[k] for k in before)  # optional work, no budget
    after = mesher.update(voxels, [], bumped, position_color, 3, dirty_voxels=dirty, refresh_s=60.0)
    assert bumped.seen() == lattice_points(voxels[dirty], 8)
    assert {k for k in after if after[k] is not before[k]} == mesher.chunks_of(voxels[dirty]) & set(after)
    fresh = ChunkedMesher(VS, 8, 2).update(voxels, None, bumped_sdf(centre, q), position_color, 1)
    np.testing.assert_array_equal(sorted_vertices(after), sorted_vertices(fresh))  # the bump lies inside


def test_small_passes_weld_exactly(monkeypatch: pytest.MonkeyPatch) -> None:
    import h2viz.mapping.meshing.passes as passes

    centre = np.array([0.013, -0.021, 0.034])
    one_pass = ChunkedMesher(VS, 8, 2).update(sphere_voxels(centre), None, sphere_sdf(centre), position_color, 1)
    monkeypatch.setattr(passes, "POINTS_PER_PASS", 2000)  # about one chunk a pass
    seen: list[list] = []
    mesher = ChunkedMesher(VS, 8, 2)
    many = mesher.update(
        sphere_voxels(centre), None, sphere_sdf(centre), position_color, 1, on_pass=lambda k, r: seen.append(k)
    )
    assert len(seen) > 20
    mesh = merge_chunks(many)
    assert mesh.is_watertight
    np.testing.assert_array_equal(sorted_vertices(many), sorted_vertices(one_pass))


def edges_on_plane_x(mesh: trimesh.Trimesh, x_m: float) -> int:
    """Boundary edges lying in the plane x = x_m (where two chunks meet)."""
    edges = boundary_edges(mesh)
    return int(np.all(np.abs(mesh.vertices[edges][:, :, 0] - x_m) < 1e-6, axis=1).sum())


def test_chunks_meshed_from_different_fields_agree_once_meshed_together() -> None:
    voxels = plane_voxels()
    keys = np.floor_divide(voxels, 4)
    mesher = ChunkedMesher(VS, 4, 4)
    mesher.update(voxels, None, plane_sdf, position_color, 1)
    a = next(k for k in sorted(mesher.chunks) if (k[0] + 1, k[1], k[2]) in mesher.chunks)
    b = (a[0] + 1, a[1], a[2])
    face_x = (a[0] + 1) * 4 * VS
    pair = lambda: merge_chunks({k: mesher.chunks[k] for k in (a, b)})  # noqa: E731
    assert edges_on_plane_x(pair(), face_x) == 0  # one field: welded
    shifted = lambda p, voxel=None: (plane_sdf(p) + 0.003).astype(np.float32)  # noqa: E731
    mesher.update(voxels, [a], shifted, position_color, 2)  # chunk A alone sees a new field
    assert edges_on_plane_x(pair(), face_x) > 0  # a hairline crack until B is re-meshed too
    far = ((keys == a).all(axis=1) & (voxels[:, 0] == 4 * a[0])) | (
        (keys == b).all(axis=1) & (voxels[:, 0] == 4 * b[0] + 3)
    )
    counting = Counting(shifted, 4)
    mesher.update(voxels, [], counting, position_color, 3, dirty_voxels=far, refresh_s=60.0)
    assert any(abs(q[0] - (a[0] + 1) * 16) == 0 for q in counting.seen())  # the common face was re-evaluated
    assert edges_on_plane_x(pair(), face_x) == 0  # their caches disagreed there, so both took fresh values


def test_stale_chunks_are_refreshed_oldest_first_until_stopped(monkeypatch: pytest.MonkeyPatch) -> None:
    import h2viz.mapping.meshing.passes as passes

    monkeypatch.setattr(passes, "REFRESH_POINTS_PER_PASS", 2000)  # a few chunks a pass
    voxels = plane_voxels()
    mesher = ChunkedMesher(VS, 4, 4)
    mesher.update(voxels, None, plane_sdf, position_color, 1, field_version=1)
    n = len(mesher.chunks_of(voxels))
    assert mesher.stale(1) == 0 and mesher.stale(2) == n
    mesher.update(voxels, sorted(mesher.chunks_of(voxels))[:3], plane_sdf, position_color, 2, field_version=2)
    assert mesher.stale(2) == n - 3
    passes: list[list] = []
    mesher.update(
        voxels, [], plane_sdf, position_color, 3, field_version=3, refresh_s=60.0, on_pass=lambda k, r: passes.append(k)
    )
    order = [k for p in passes for k in p]
    assert set(order[-3:]) == set(sorted(mesher.chunks_of(voxels))[:3])  # meshed at version 2: refreshed last
    assert mesher.stale(3) == 0
    calls = []
    mesher.update(
        voxels,
        [],
        plane_sdf,
        position_color,
        4,
        field_version=4,
        refresh_s=60.0,
        stop=lambda: calls.append(1) or len(calls) > 1,
    )
    assert 0 < mesher.stale(4) < n  # one pass, then stopped


def test_refresh_passes_wait_while_another_thread_hurries_but_new_voxels_are_meshed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import h2viz.mapping.meshing.passes as passes

    monkeypatch.setattr(passes, "REFRESH_POINTS_PER_PASS", 2000)  # a few chunks a pass
    voxels = plane_voxels()
    grown = np.concatenate([voxels, voxels[:1] + [0, 0, 40]])  # one voxel in a chunk of its own
    mesher = ChunkedMesher(VS, 4, 4)
    mesher.update(voxels, None, plane_sdf, position_color, 1, field_version=1)
    n = len(mesher.chunks_of(voxels))
    asked: list[bool] = []
    meshed: list[tuple[list, bool]] = []
    mesher.update(
        grown,
        [],
        plane_sdf,
        position_color,
        2,
        field_version=2,
        refresh_s=60.0,
        on_pass=lambda k, r: meshed.append((k, r)),
        hurry=lambda: asked.append(True) or True,
    )
    assert asked and [r for _, r in meshed] == [True]  # the new voxel's chunk only: no refresh pass
    assert meshed[0][0] == sorted(mesher.chunks_of(grown[-1:]))
    assert mesher.stale(2) == n
    hurried = iter([False, False, True])  # a frame arrives after two refresh passes
    mesher.update(grown, [], plane_sdf, position_color, 3, field_version=2, refresh_s=60.0, hurry=lambda: next(hurried))
    assert 0 < mesher.stale(2) < n


def test_other_threads_always_read_a_complete_chunk_dict() -> None:
    import threading

    centre = np.array([0.013, -0.021, 0.034])
    voxels = sphere_voxels(centre)
    mesher = ChunkedMesher(VS, 8, 2)
    first = mesher.update(voxels, None, sphere_sdf(centre), position_color, 1)
    slow = lambda p, voxel=None: (time.sleep(0.002), sphere_sdf(centre)(p))[1]  # noqa: E731
    done = threading.Event()
    worker = threading.Thread(
        target=lambda: (mesher.update(voxels, None, slow, position_color, 2), done.set()), daemon=True
    )
    worker.start()
    seen = []
    while not done.is_set():
        chunks = mesher.chunks
        assert set(chunks) == set(first)  # never a chunk missing while it is re-meshed
        seen.append(sum(c.version == 2 for c in chunks.values()))
        time.sleep(0.0005)  # a reader that spins holds the GIL the re-meshing thread needs
    worker.join()
    assert seen == sorted(seen) and max(seen) <= len(first)
    assert len(seen) > 10 and seen[0] == 0  # read all through the update


def test_packed_rows_unpack_to_themselves() -> None:
    from h2viz.mapping.meshing.marching import pack_rows, unpack_rows

    rows = np.random.default_rng(2).integers(-(10**5), 10**5, size=(1000, 3))
    lo, hi = rows.min(axis=0), rows.max(axis=0)
    keys = pack_rows(rows, lo, hi)
    assert keys is not None
    np.testing.assert_array_equal(unpack_rows(keys, lo, hi), rows)


def test_kept_faces_filters_every_surface_of_a_pass_in_one_call() -> None:
    """Three strips of two triangles at x = 0, 10, 20: all kept, one face kept, none kept."""
    square = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    faces = np.array([[0, 1, 2], [1, 3, 2]], np.int64)
    surfaces = [((i, 0, 0), square + np.float32([10 * i, 0, 0]), faces) for i in range(3)]
    calls: list[int] = []

    def keep(centroids: np.ndarray) -> np.ndarray:
        calls.append(len(centroids))
        return (centroids[:, 0] < 10) | ((centroids[:, 0] < 20) & (centroids[:, 1] < 0.5))

    out = kept_faces(surfaces, keep)
    assert calls == [6]
    assert [key for key, _, _ in out] == [(0, 0, 0), (1, 0, 0)]
    assert out[0] is surfaces[0]
    _, vertices, kept = out[1]
    np.testing.assert_array_equal(vertices, square[:3] + np.float32([10, 0, 0]))  # the vertex only face 2 used goes
    np.testing.assert_array_equal(kept, [[0, 1, 2]])
    assert kept_faces([], keep) == []
