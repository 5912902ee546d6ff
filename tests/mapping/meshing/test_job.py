"""Mesh jobs beside mapping: the frozen field matches the live one and ignores later training, jobs run on
another thread while frames are integrated, and after any sequence of partial jobs a full refresh gives
exactly the mesh a fresh mesher makes from the same field."""

from __future__ import annotations

import gc
import threading
from dataclasses import replace

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from h2viz.config import MappingConfig
from h2viz.errors import ConfigError
from h2viz.geometry import backproject
from h2viz.mapping.field import copy_pool
from h2viz.mapping.field.copy_pool import CopyPool
from h2viz.mapping.field.octree import encode
from h2viz.mapping.mapper import Mapper
from h2viz.mapping.meshing.job import FrozenField, keep_prior_sign
from h2viz.mapping.meshing.mesher import ChunkedMesher, merge_chunks
from tests.mapping.analytic import Scene, orbit

torch.set_num_threads(2)


def small_cfg(**kw: object) -> MappingConfig:
    base = dict(device="cpu", min_points_per_voxel=3, rays_per_iter=512, hash_log2_size=14, max_iters=3)
    base.update(kw)
    return MappingConfig().updated(**base)  # type: ignore[arg-type]


def sphere_mapper(n_frames: int, **kw: object) -> tuple[Mapper, Scene, list[np.ndarray]]:
    scene = Scene("sphere", center=np.array([0.03, -0.02, 0.01]), radius=0.4)
    mapper = Mapper(small_cfg(**kw))
    poses = orbit(scene, 8, 1.4, 0.5, scene.center)
    for i, T in enumerate(poses[:n_frames]):
        mapper.integrate(scene.frame(i, T))
    return mapper, scene, poses


def probe_points(mapper: Mapper, n: int = 20_000) -> tuple[np.ndarray, np.ndarray]:
    """Points (N,3) inside allocated voxels, a quarter of them on voxel faces or corners, and the voxel ids."""
    rng = np.random.default_rng(0)
    coords = mapper.octree.voxel_coords()
    ids = rng.integers(0, len(coords), n)
    local = rng.random((n, 3))
    local[: n // 4] = np.round(local[: n // 4])  # on faces, edges and corners
    return ((coords[ids] + local) * mapper.voxel_size_m).astype(np.float32), ids


@pytest.mark.parametrize("geo_layers", [1, 2])  # the compiled decoder, and the networks' own path
def test_frozen_field_matches_the_live_one(geo_layers: int) -> None:
    mapper, _, _ = sphere_mapper(2, geo_layers=geo_layers)
    with torch.no_grad():  # a residual large enough that the bound shapes it
        mapper.field.geo_mlp[-1].bias += 0.8
    frozen = FrozenField(mapper.field, mapper.cfg.representation.truncation_m, backend=mapper.backend)
    points, ids = probe_points(mapper)
    with torch.no_grad():
        live = (
            mapper.field.sdf(torch.from_numpy(points), torch.from_numpy(ids)).numpy()
            * mapper.cfg.representation.truncation_m
        )
        live_prior = mapper.field.prior_sdf(torch.from_numpy(points), torch.from_numpy(ids)).numpy()
    np.testing.assert_allclose(frozen.prior(points, ids), live_prior, atol=1e-6)
    np.testing.assert_allclose(frozen.sdf_m(points, ids), live, atol=2e-7)
    assert np.abs(live).max() > 0.01  # a non-trivial field
    residual = live / mapper.cfg.representation.truncation_m - live_prior
    assert 0.5 < np.abs(residual).max() < mapper.cfg.representation.residual_bound
    np.testing.assert_array_equal(frozen.color_u8(points), mapper.color_u8(points))


def test_frozen_field_ignores_later_training() -> None:
    # colour from the network alone here; the colour priors are shared, not frozen (next test)
    mapper, scene, poses = sphere_mapper(2, color_prior=False, color_supervision="surface")
    frozen = FrozenField(mapper.field, mapper.cfg.representation.truncation_m, backend=mapper.backend)
    points, ids = probe_points(mapper, 5000)
    sdf, rgb = frozen.sdf_m(points, ids), frozen.color_u8(points)
    mapper.integrate(scene.frame(2, poses[2]))  # trains the live field in place
    with torch.no_grad():
        mapper.field.priors.add_(0.5)
    np.testing.assert_array_equal(frozen.sdf_m(points, ids), sdf)
    np.testing.assert_array_equal(frozen.color_u8(points), rgb)
    assert not np.allclose(mapper.sdf_m(points), sdf)


def test_frozen_fields_reuse_the_memory_of_those_gone_and_still_ignore_later_training(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(copy_pool, "MIN_BYTES", 100_000)  # pool the small test tables too (512 kB)
    mapper, _, _ = sphere_mapper(2, color_prior=False, color_supervision="surface")
    tr = mapper.cfg.representation.truncation_m
    pool = CopyPool()
    first = FrozenField(mapper.field, tr, backend=mapper.backend, pool=pool)
    points, ids = probe_points(mapper, 5000)
    sdf = first.sdf_m(points, ids)
    mapper.refine(3)  # trains the hash tables, decoders and priors in place
    np.testing.assert_array_equal(first.sdf_m(points, ids), sdf)  # pooled copies are copies
    copies = pool.allocated
    assert copies == 3  # the two hash tables and the fine lattices
    del first
    gc.collect()
    second = FrozenField(mapper.field, tr, backend=mapper.backend, pool=pool)
    assert pool.allocated == copies and pool.reused == copies  # every copy into the memory of the first
    fresh = FrozenField(mapper.field, tr, backend=mapper.backend)
    np.testing.assert_array_equal(second.sdf_m(points, ids), fresh.sdf_m(points, ids))
    assert not np.array_equal(second.sdf_m(points, ids), sdf)


def test_mesh_jobs_take_their_frozen_fields_from_the_mappers_pool() -> None:
    mapper, scene, poses = sphere_mapper(2, hash_log2_size=18)  # tables of 2 MB: pooled
    mapper.mesh_job(whole=True).run()  # type: ignore[union-attr]
    mapper.integrate(scene.frame(2, poses[2]))
    job = mapper.mesh_job(0.0)
    assert job is not None and mapper.copy_pool.reused >= 2  # the first job's storages, the tables at least
    job.run()


def test_frozen_field_shares_the_colour_priors_instead_of_copying_them() -> None:
    mapper, scene, poses = sphere_mapper(2)
    live = mapper.field.color_prior
    frozen = FrozenField(mapper.field, mapper.cfg.representation.truncation_m, backend=mapper.backend)
    assert live is not None and frozen.field.color_prior is not None and mapper.field.color_prior is live
    assert frozen.field.color_prior.sums.data_ptr() == live.sums.data_ptr()  # no copy of ~12 kB a voxel
    points, ids = probe_points(mapper, 5000)
    sdf = frozen.sdf_m(points, ids)
    for i in range(2, 5):  # new voxels the frozen field does not know, and more colour splatted
        mapper.integrate(scene.frame(i, poses[i]))
    np.testing.assert_array_equal(frozen.sdf_m(points, ids), sdf)  # geometry stays frozen
    far = np.concatenate([points, np.asarray(mapper.mesh().vertices)])  # also points in voxels added since
    assert frozen.color_u8(far).shape == (len(far), 3)  # lookups beyond the frozen voxels are skipped


def test_jobs_on_another_thread_then_a_full_refresh_equal_a_fresh_mesh() -> None:
    mapper, scene, poses = sphere_mapper(2)
    for i, T in enumerate(poses[2:6], start=2):
        job = mapper.mesh_job(refresh_s=0.05)
        assert job is not None and job.dirty_voxels.any()
        runner = threading.Thread(target=job.run)
        runner.start()
        mapper.integrate(scene.frame(i, T))  # mapping goes on while the job meshes
        runner.join()
        assert mapper.mesh_chunks()
    assert mapper.mesher.stale(mapper.frames_done) > 0
    mesh = mapper.mesh()  # every chunk brought up to the current field
    assert mapper.mesher.stale(mapper.frames_done) == 0 and mapper.mesh_job() is None
    frozen = FrozenField(mapper.field, mapper.cfg.representation.truncation_m, backend=mapper.backend)
    meshable = np.arange(mapper.octree.n_voxels)  # every voxel, as the mapper's jobs with the filter on
    cfg = mapper.cfg
    fresh_mesher = ChunkedMesher(
        mapper.voxel_size_m, cfg.meshing.mesh_resolution, cfg.meshing.chunk_voxels, mapper.backend
    )
    coords = mapper.octree.voxel_coords()[meshable]
    strict = ~mapper.priors.initialised(mapper.octree.n_voxels)
    keep = mapper.observed.snapshot(mapper.octree, strict).contains  # faces near measured depth
    fresh = merge_chunks(
        fresh_mesher.update(coords, None, frozen.sdf_m, frozen.color_u8, 1, voxel_ids=meshable, keep_fn=keep)
    )
    order = lambda m: np.lexsort(np.asarray(m.vertices).T[::-1])  # noqa: E731
    np.testing.assert_array_equal(np.asarray(mesh.vertices)[order(mesh)], np.asarray(fresh.vertices)[order(fresh)])
    np.testing.assert_array_equal(mesh.visual.vertex_colors[order(mesh)], fresh.visual.vertex_colors[order(fresh)])
    assert len(mesh.faces) == len(fresh.faces) > 1000
    assert np.median(np.abs(scene.sdf(np.asarray(mesh.vertices)))) < 0.01


def test_a_job_replacing_a_waiting_one_keeps_its_dirty_voxels() -> None:
    mapper, scene, poses = sphere_mapper(2)
    older = mapper.mesh_job()
    mapper.integrate(scene.frame(2, poses[2]))
    newer = mapper.mesh_job()
    assert older is not None and newer is not None
    merged = newer.after(older)
    had = set(older.voxel_ids[older.dirty_voxels]) | set(newer.voxel_ids[newer.dirty_voxels])
    assert set(merged.voxel_ids[merged.dirty_voxels]) == had
    assert merged.field is newer.field and merged.version == newer.version
    assert replace(merged, refresh_s=0.0).refresh_s == 0.0


def test_surfaces_away_from_measured_depth_are_left_out_of_the_mesh() -> None:
    mapper, scene, poses = sphere_mapper(2, fine_priors=False)  # the residual moves the corner priors' surface
    seen = np.concatenate([_points(scene, i, T) for i, T in enumerate(poses[:2])])  # (N,3) measured depth
    on_depth = mapper.mesh()
    assert np.median(np.abs(scene.sdf(np.asarray(on_depth.vertices)))) < 0.005
    shift_residual(mapper, 1.2)  # 6 cm from every depth point measured: beyond the cells around observed ones
    moved = mapper.mesh()
    assert len(moved.faces) < 0.1 * len(on_depth.faces)
    if len(moved.faces):
        gap, _ = cKDTree(seen).query(moved.triangles_center)
        vs = mapper.cfg.representation.voxel_size_m
        assert gap.max() < 2 * np.sqrt(3) * vs / 8  # within the 3x3x3 cells of an observed one
    mapper.mesh_observed_only = False  # nothing else changed: the toggle alone re-meshes every chunk
    assert len(mapper.mesh().faces) > 0.5 * len(on_depth.faces)  # the same surface, kept when the filter is off


def test_edge_voxels_keep_only_faces_on_measured_depth() -> None:
    """Voxels at the sphere's silhouette have corners no depth reached (their priors are pending): with the
    filter on, their faces are kept where depth was measured in the face's own cell; with it off, they are not
    meshed at all."""
    mapper, scene, poses = sphere_mapper(1)
    seen = _points(scene, 0, poses[0])  # (N,3)
    edge = ~mapper.priors.initialised(mapper.octree.n_voxels)  # (V,)
    assert edge.sum() > 10

    def in_edge_voxels(mesh: trimesh.Trimesh) -> np.ndarray:
        cells = np.floor(mesh.triangles_center / mapper.voxel_size_m).astype(np.int64)
        return edge[mapper.octree.voxels.lookup(encode(cells))]

    kept = mapper.mesh()
    at_edge = in_edge_voxels(kept)
    assert at_edge.sum() > 50  # measured surface in edge voxels is meshed
    gap, _ = cKDTree(seen).query(kept.triangles_center[at_edge])
    assert gap.max() < np.sqrt(3) * mapper.cfg.representation.voxel_size_m / 8  # within the face's own observed cell
    off = np.abs(scene.sdf(kept.triangles_center[at_edge]))  # grazing views after one frame: mm, not a skirt's cm
    assert np.median(off) < 0.005 and np.percentile(off, 90) < 0.01
    mapper.mesh_observed_only = False
    unfiltered = mapper.mesh()
    assert not in_edge_voxels(unfiltered).any()
    assert unfiltered.area < kept.area


def _points(scene: Scene, i: int, T: np.ndarray) -> np.ndarray:
    f = scene.frame(i, T)
    return backproject(f.depth_m, f.K, f.T_world_camera)


def crossings(values: np.ndarray) -> np.ndarray:
    """Indices i where values (N,) change sign between i and i+1."""
    return np.flatnonzero(np.sign(values[:-1]) != np.sign(values[1:]))


def test_meshing_keeps_the_prior_sign_beyond_the_band() -> None:
    """Along a ray through a surface (prior = signed distance, tr units): a residual bubble 1.8 tr behind the
    surface would add a sheet there; beyond the band it is gone, while a residual shifting the surface by 0.8 tr
    (a correction within the band) is kept as it is."""
    prior = np.linspace(-3.0, 3.0, 600, dtype=np.float32)  # ~0.01 tr steps, none exactly 0
    bubble = prior + 2.0 * np.exp(-(((prior + 1.8) / 0.1) ** 2)).astype(np.float32)
    assert len(crossings(bubble)) == 3  # the surface and both sides of the spurious sheet
    kept = keep_prior_sign(bubble, prior, 1.5)
    assert list(crossings(kept)) == list(crossings(prior))  # only the measured surface is left
    shifted = prior + np.float32(0.8)
    np.testing.assert_array_equal(keep_prior_sign(shifted, prior, 1.5), shifted)
    assert abs(prior[crossings(shifted)[0]] + 0.8) < 0.02  # the corrected surface, 0.8 tr in front
    np.testing.assert_array_equal(keep_prior_sign(bubble, prior, 10.0), bubble)  # a wide band changes nothing


def shift_residual(mapper: Mapper, tr_units: float) -> None:
    """Make the residual the same everywhere: the surface moves that far (truncation units) into the sphere."""
    with torch.no_grad():
        last = mapper.field.geo_mlp[-1]
        last.weight.zero_()
        b = mapper.cfg.representation.residual_bound
        last.bias.fill_(float(b * np.arctanh(tr_units / b)))
    mapper.touched[:] = True


def test_mesh_jobs_use_the_configured_band_and_moved_surfaces_within_it_are_meshed() -> None:
    mapper, scene, _ = sphere_mapper(2, mesh_observed_only=False, fine_priors=False)  # 4 cm off: not observed cells
    job = mapper.mesh_job()
    assert job is not None and job.field.prior_band == mapper.cfg.meshing.mesh_prior_band == 3.0
    shift_residual(mapper, 0.8)  # 4 cm into the sphere
    mesh = mapper.mesh()
    inside = np.median(scene.sdf(np.asarray(mesh.vertices)))
    assert abs(inside + 0.8 * mapper.cfg.representation.truncation_m) < 0.01, inside
    assert len(mesh.faces) > 1000
    off, _, _ = sphere_mapper(1, priors=False)
    job = off.mesh_job()
    assert job is not None and job.field.prior_band == 0.0  # without priors there is no band


def test_a_resolution_cap_meshes_coarser_until_it_is_lifted_and_keeps_the_chosen_resolution() -> None:
    """A real-time stream caps the live mesh's resolution (viewer.stream_mesh_resolution): jobs mesh at the cap,
    the chosen resolution stays what `mesh_resolution` says, and lifting the cap re-meshes every chunk at it."""
    mapper, _, _ = sphere_mapper(2)
    mapper.mesh_resolution = 4
    mapper.mesh_resolution_cap = 2
    assert (mapper.mesh_resolution, mapper.meshing_resolution) == (4, 2)
    mapper.update_mesh()
    coarse = merge_chunks(mapper.mesh_chunks())
    mapper.mesh_resolution = 6  # chosen while capped: the cap still holds
    assert (mapper.mesh_resolution, mapper.meshing_resolution) == (6, 2)
    mapper.mesh_resolution_cap = 8  # above the chosen resolution: no effect
    assert mapper.meshing_resolution == 6
    mapper.mesh_resolution_cap = 0
    mapper.mesh_resolution = 4
    job = mapper.mesh_job(0.0)
    assert job is not None  # every chunk is stale at the new resolution
    job.run()
    fine = merge_chunks(mapper.mesh_chunks())
    assert len(fine.faces) > 3 * len(coarse.faces)  # ~(4/2)^2 as many faces
    with pytest.raises(ConfigError, match="resolution cap"):
        mapper.mesh_resolution_cap = -1
    with pytest.raises(ConfigError, match="resolution 10000 is out of range"):
        mapper.mesh_resolution = 10_000  # refused, nothing changed
    assert (mapper.mesh_resolution, mapper.mesh_resolution_cap, mapper.meshing_resolution) == (4, 0, 4)
