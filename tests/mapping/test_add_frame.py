"""Integration without optimisation (real-time mode's `Mapper.add_frame`) on analytic scenes: every frame's
voxels and priors are in the map and the surface the priors alone put there lies within millimetres; live and
refinement steps then optimise what was integrated."""

from __future__ import annotations

import threading
from dataclasses import replace

import cv2
import numpy as np
import torch

from h2viz.mapping.mapper import AHEAD_KEPT, INTEGRATION_STAGES, THUMBNAIL_HEIGHT, Mapper, keyframe_thumbnail
from h2viz.mapping.sampling.rays import FrameRays
from h2viz.types import RgbdFrame
from tests.mapping.analytic import Scene, orbit
from tests.mapping.backends import REFERENCE
from tests.mapping.test_mapper import mesh_error, room_views, small_cfg

torch.set_num_threads(2)


def world_points(frame: RgbdFrame) -> np.ndarray:
    """World points (N,3) of a frame's valid depth pixels, rounded as the mapper computes them (the room's walls
    lie on voxel faces, where float32 rounding decides the side)."""
    return FrameRays.with_points(frame, REFERENCE)[1]


def parameters(mapper: Mapper) -> list[torch.Tensor]:
    return [p.detach().clone() for p in mapper.field.parameters()]


def check_frames_in_map(mapper: Mapper, frames: list[RgbdFrame]) -> None:
    """Every voxel holding more than min_points of a frame's depth points is allocated, most of them with all 8
    corner priors set (a voxel at the edge of the view waits for a frame that sees all its corners), and nearly all
    of the frame's points lie in allocated voxels."""
    initialised = mapper.priors.initialised(mapper.octree.n_voxels)
    vs, n_min = mapper.octree.voxel_size_m, mapper.octree.min_points
    for frame in frames:
        points = world_points(frame)
        cells, counts = np.unique(np.floor(points / vs).astype(np.int64), axis=0, return_counts=True)
        dense = torch.from_numpy((cells[counts > n_min] + 0.5) * vs).float()
        ids = mapper.octree.lookup_points(dense).numpy()
        assert (ids >= 0).all(), f"frame {frame.index}: {(ids < 0).sum()} of its voxels are not allocated"
        assert initialised[ids].mean() > 0.75, f"frame {frame.index}: priors missing"  # edge voxels wait
        point_ids = mapper.octree.lookup_points(torch.from_numpy(points).float()).numpy()
        assert (point_ids >= 0).mean() > 0.98  # the rest: in voxels with too few points


def test_add_frame_keeps_every_frames_plane_within_millimetres_without_a_step() -> None:
    scene = Scene("plane")
    mapper = Mapper(small_cfg())  # max_iters = 10: add_frame must not run any of them
    before = parameters(mapper)
    frames = [scene.frame(i, T) for i, T in enumerate(orbit(scene, 4, 0.6, 1.2, np.zeros(3)))]
    stats = [mapper.add_frame(f) for f in frames]
    assert [s.iterations for s in stats] == [0, 0, 0, 0] and mapper.frames_done == 4
    assert all(torch.equal(a, b) for a, b in zip(before, parameters(mapper), strict=True))  # no optimisation
    check_frames_in_map(mapper, frames)
    twin = Mapper(small_cfg(max_iters=0))  # every-frame mode without its steps integrates the same map
    for f in frames:
        twin.integrate(f)
    assert np.array_equal(twin.octree.voxels.keys, mapper.octree.voxels.keys)
    assert torch.equal(twin.field.priors, mapper.field.priors)
    assert torch.equal(twin.field.color_prior.sums, mapper.field.color_prior.sums)
    err = mesh_error(mapper, scene)
    assert np.median(err) < 0.002 and np.percentile(err, 95) < 0.006


def same_map(a: Mapper, b: Mapper) -> bool:
    """The two maps hold the same voxels, corner priors, fine lattices, colour lattices, keyframes (with their
    thumbnails) and stored colour views."""
    return (
        np.array_equal(a.octree.voxels.keys, b.octree.voxels.keys)
        and torch.equal(a.field.priors, b.field.priors)
        and torch.equal(a.field.fine_prior.state, b.field.fine_prior.state)
        and torch.equal(a.field.color_prior.sums, b.field.color_prior.sums)
        and [k.index for k in a.keyframe_infos()] == [k.index for k in b.keyframe_infos()]
        and all(np.array_equal(x, y) for x, y in zip(a.thumbnails, b.thumbnails, strict=True))
        and [v.index for v in a.color_views.views] == [v.index for v in b.color_views.views]
        and all(
            np.array_equal(x.rgb_half, y.rgb_half) and np.array_equal(x.depth_half, y.depth_half)
            for x, y in zip(a.color_views.views, b.color_views.views, strict=True)
        )
    )


def test_frames_prepared_ahead_on_a_reader_thread_integrate_exactly_as_frames_prepared_inline() -> None:
    _, frames = room_views(6)
    ahead, inline = Mapper(small_cfg(min_points_per_voxel=2)), Mapper(small_cfg(min_points_per_voxel=2))
    for frame in frames:
        reader = threading.Thread(target=ahead.prepare_ahead, args=(frame,), name="h2viz-frames")
        reader.start()
        reader.join()
        assert frame.index in ahead._ahead  # waiting for add_frame
        ahead.add_frame(frame, color_points=500, observed_points=500)
        inline.add_frame(frame, color_points=500, observed_points=500)
        assert not ahead._ahead  # taken
    assert same_map(ahead, inline) and ahead.octree.n_voxels > 50


def test_a_frame_prepared_ahead_is_used_only_for_that_frame_and_unclaimed_ones_are_let_go() -> None:
    _, frames = room_views(3)
    mapper, twin = Mapper(small_cfg(min_points_per_voxel=2)), Mapper(small_cfg(min_points_per_voxel=2))
    impostor = replace(frames[1], index=frames[0].index)  # another frame with the same index (a replaced source)
    reader = threading.Thread(target=mapper.prepare_ahead, args=(impostor,))
    reader.start()
    reader.join()
    mapper.add_frame(frames[0])
    twin.add_frame(frames[0])
    assert same_map(mapper, twin)  # frames[0] was prepared for itself, not taken from the impostor's
    reader = threading.Thread(target=lambda: [mapper.prepare_ahead(replace(frames[2], index=i)) for i in range(40)])
    reader.start()
    reader.join()
    assert len(mapper._ahead) == AHEAD_KEPT and min(mapper._ahead) == 40 - AHEAD_KEPT  # the newest kept


def test_add_frame_times_each_part_of_integration_without_counting_any_twice() -> None:
    _, frames = room_views(2)
    mapper = Mapper(small_cfg(min_points_per_voxel=2))
    for frame in frames:
        stats = mapper.add_frame(frame)
        assert set(stats.timings) == set(INTEGRATION_STAGES) and stats.iterations == 0
        assert all(s >= 0.0 for s in stats.timings.values())
        assert 0.0 < sum(stats.timings.values()) <= stats.map_time_s
        assert stats.timings["fine_prior"] > 0.0 and stats.timings["voxels"] > 0.0


def test_keyframe_thumbnails_keep_the_aspect_and_match_one_area_resize() -> None:
    """Halving first (exact 2x2 averages) then area-resizing gives the picture one area resize would, to a few
    levels, at any size (a frame smaller than twice the thumbnail is resized once)."""
    for h, w in ((480, 640), (968, 1296), (120, 160), (50, 60)):
        yy, xx = np.mgrid[0:h, 0:w]
        rgb = np.stack([255 * xx / w, 255 * yy / h, 127 + 100 * np.sin(xx / 9.0) * np.cos(yy / 13.0)], -1)
        rgb = rgb.astype(np.uint8)
        thumb = keyframe_thumbnail(rgb)
        width = round(w * THUMBNAIL_HEIGHT / h)
        assert thumb.shape == (THUMBNAIL_HEIGHT, width, 3) and thumb.dtype == np.uint8
        once = cv2.resize(rgb, (width, THUMBNAIL_HEIGHT), interpolation=cv2.INTER_AREA)
        diff = np.abs(thumb.astype(int) - once.astype(int))
        assert diff.mean() < 2.5 and diff.max() <= 16


def test_add_frame_keeps_a_box_rooms_walls_within_millimetres() -> None:
    scene, frames = room_views(12)
    mapper = Mapper(small_cfg(min_points_per_voxel=2))
    for frame in frames:
        mapper.add_frame(frame, color_points=500, observed_points=500)
    check_frames_in_map(mapper, frames)
    assert len(mapper.keyframes) >= 2  # the keyframe decision is part of integration
    err = mesh_error(mapper, scene)
    assert np.median(err) < 0.004 and np.percentile(err, 90) < 0.012


def test_a_frame_fused_into_its_new_voxels_only_leaves_older_lattices_and_integrates_the_rest_whole() -> None:
    """fuse_all=False (real-time mode while frames wait): the frame's depth reaches the fine lattices of the voxels
    it allocates and no others; voxels, corner priors and the colour prior are what a whole frame puts there, and
    the walls from the priors alone still lie within millimetres."""
    scene, frames = room_views(12)
    thin, whole = Mapper(small_cfg(min_points_per_voxel=2)), Mapper(small_cfg(min_points_per_voxel=2))
    for i, frame in enumerate(frames):
        older = thin.octree.n_voxels
        before = thin.field.fine_prior.state.clone()
        thin.add_frame(frame, color_points=500, observed_points=500, fuse_all=i % 2 == 0)
        whole.add_frame(frame, color_points=500, observed_points=500)
        lattices = thin.field.fine_prior.state
        if i % 2:
            assert torch.equal(lattices[:older], before)  # older voxels: untouched
        else:
            assert not torch.equal(lattices[:older], before) or older == 0
        new = lattices[older:, :, 1]  # (new voxels, P): weights
        assert new.shape[0] > 0 and (new.amax(1) > 0).float().mean() > 0.9  # nearly every new voxel fused
        assert np.array_equal(thin.octree.voxels.keys, whole.octree.voxels.keys)
        assert torch.equal(thin.field.priors, whole.field.priors)
        assert torch.equal(thin.field.color_prior.sums, whole.field.color_prior.sums)
    assert thin.field.fine_prior.state[..., 1].sum() < whole.field.fine_prior.state[..., 1].sum()
    err = mesh_error(thin, scene)
    assert np.median(err) < 0.004 and np.percentile(err, 90) < 0.012


def test_live_steps_optimise_the_newest_frame_and_refinement_steps_the_keyframes() -> None:
    scene, frames = room_views(8)
    mapper = Mapper(small_cfg(min_points_per_voxel=2, fine_priors=False))  # the residual carries the geometry
    assert np.isnan(mapper.live_step()) and np.isnan(mapper.refine_step())  # nothing integrated yet
    for frame in frames:
        mapper.add_frame(frame)
    before = parameters(mapper)
    mapper.touched[:] = False
    losses = [mapper.live_step() for _ in range(40)]
    assert not all(torch.equal(a, b) for a, b in zip(before, parameters(mapper), strict=True))
    assert mapper.touched.any() and not mapper.touched.all()  # the newest frame's voxels are re-meshed
    assert np.mean(losses[-10:]) < 0.8 * np.mean(losses[:5])
    refined = [mapper.refine_step() for _ in range(40)]
    assert mapper.touched.all() and np.all(np.isfinite(refined))
