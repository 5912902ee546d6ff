"""The mapper on analytic scenes: priors alone put the surface within millimetres; training makes rendered
depth match the input; checkpoints round-trip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from h2viz.config import MappingConfig
from h2viz.geometry import look_at
from h2viz.mapping.checkpoint import load_checkpoint, save_checkpoint
from h2viz.mapping.mapper import Mapper
from h2viz.types import RgbdFrame
from tests.mapping.analytic import Scene, orbit

torch.set_num_threads(2)


def small_cfg(**kw: object) -> MappingConfig:
    base = dict(device="cpu", min_points_per_voxel=3, rays_per_iter=1024, hash_log2_size=14, max_iters=10)
    base.update(kw)
    return MappingConfig().updated(**base)  # type: ignore[arg-type]


def mesh_error(mapper: Mapper, scene: Scene) -> np.ndarray:
    mesh = mapper.mesh()
    assert len(mesh.faces) > 100
    return np.abs(scene.sdf(np.asarray(mesh.vertices)))


def test_priors_alone_put_a_plane_within_millimetres() -> None:
    scene = Scene("plane")
    mapper = Mapper(small_cfg(max_iters=0))
    for i, T in enumerate(orbit(scene, 4, 0.6, 1.2, np.zeros(3))):
        mapper.integrate(scene.frame(i, T))
    err = mesh_error(mapper, scene)
    assert np.median(err) < 0.002 and np.percentile(err, 95) < 0.006


def test_priors_alone_put_a_sphere_within_a_few_millimetres() -> None:
    scene = Scene("sphere", center=np.array([0.03, -0.02, 0.01]), radius=0.5)
    mapper = Mapper(small_cfg(max_iters=0))
    for i, T in enumerate(orbit(scene, 8, 1.6, 0.5, scene.center)):
        mapper.integrate(scene.frame(i, T))
    err = mesh_error(mapper, scene)
    assert np.median(err) < 0.007 and np.percentile(err, 90) < 0.015  # projective priors, oblique views


def room_views(n: int) -> tuple[Scene, list[RgbdFrame]]:
    """The box room seen from n cameras near its middle, each looking at a wall (64x48 frames)."""
    scene = Scene("room", center=np.array([0.0, 0.0, 1.0]))
    target = np.array([0.0, 0.0, 0.9])
    poses = [
        look_at(
            target + 0.3 * np.array([np.cos(a), np.sin(a), 0.3]),
            target + 2 * np.array([np.cos(a + 2), np.sin(a + 2), -0.2]),
        )
        for a in np.linspace(0, 2 * np.pi, n, endpoint=False)
    ]
    return scene, [scene.frame(i, T, width=64, height=48) for i, T in enumerate(poses)]


def test_training_makes_rendered_depth_and_colour_match_a_box_room() -> None:
    scene, frames = room_views(8)
    mapper = Mapper(small_cfg(max_iters=10, early_ending=False, rays_per_iter=768))
    for _ in range(3):  # the sequence seen three times, as a longer scan would
        for f in frames:
            mapper.integrate(f)
    depth_err, psnrs, covered = [], [], []
    for f in frames[::2]:
        d = mapper.render(f.K, f.T_world_camera, f.height, f.width, "depth")
        ok = (d > 0) & (f.depth_m > 0)
        covered.append(ok.mean())
        depth_err.append(np.abs(d - f.depth_m)[ok].mean())
        rgb = mapper.render(f.K, f.T_world_camera, f.height, f.width, "rgb")
        psnrs.append(-10 * np.log10(np.mean((rgb[ok] - f.rgb[ok] / 255.0) ** 2)))
    # renders draw only near observed depth, which 64x48 frames sample ~3 cm apart: a few percent stay empty
    assert min(covered) > 0.85 and np.mean(covered) > 0.92  # measured 0.94 on average
    assert np.mean(depth_err) < 0.006
    assert np.mean(psnrs) > 30.0  # a constant colour scores ~12 dB; the colour priors hold this smooth pattern
    assert np.median(mesh_error(mapper, scene)) < 0.004


def test_refinement_over_the_keyframes_improves_an_undertrained_map() -> None:
    _, frames = room_views(6)
    # every frame a keyframe; corner priors, so that the residual has the geometry to learn
    mapper = Mapper(small_cfg(max_iters=1, rays_per_iter=768, keyframe_iou=1.0, fine_priors=False))
    assert mapper.refine(5) == 0  # nothing to refine yet
    for f in frames:
        mapper.integrate(f)

    def errors() -> tuple[float, float]:
        depth, colour = [], []
        for f in frames:
            d = mapper.render(f.K, f.T_world_camera, f.height, f.width, "depth")
            rgb = mapper.render(f.K, f.T_world_camera, f.height, f.width, "rgb")
            ok = (d > 0) & (f.depth_m > 0)
            depth.append(np.abs(d - f.depth_m)[ok].mean())
            colour.append(np.abs(rgb[ok] - f.rgb[ok] / 255.0).mean())
        return float(np.mean(depth)), float(np.mean(colour))

    depth_before, colour_before = errors()
    mapper.touched[:] = False
    steps: list[int] = []
    assert mapper.refine(60, on_step=lambda: steps.append(1)) == 60 and len(steps) == 60
    depth_after, colour_after = errors()
    assert colour_after < 0.8 * colour_before and depth_after < depth_before
    assert mapper.touched.all()  # everything is re-meshed from the refined field


def test_refinement_called_in_slices_draws_new_keyframe_sets() -> None:
    """The dashboard refines a few steps at a time: each call must go on drawing, not repeat the last call's sets."""
    scene = Scene("sphere", center=np.zeros(3), radius=0.4)
    mapper = Mapper(small_cfg(max_iters=1, rays_per_iter=256, keyframe_iou=1.0, n_keyframes=2))
    for i, T in enumerate(orbit(scene, 6, 1.4, 0.5, scene.center)):
        mapper.integrate(scene.frame(i, T, width=48, height=36))
    assert len(mapper.keyframe_rays) == 6
    drawn: list[tuple[int, ...]] = []
    step = mapper._step

    def recording_step(frames: list, timer: object) -> object:
        drawn.append(tuple(sorted(next(i for i, k in enumerate(mapper.keyframe_rays) if k is f) for f in frames)))
        return step(frames, timer)  # type: ignore[arg-type]

    mapper._step = recording_step  # type: ignore[method-assign]
    assert mapper.refine(4) == 4 and mapper.refine(4) == 4
    assert all(len(set(d)) == 3 for d in drawn)  # K + 1 distinct keyframes a step
    assert drawn[:4] != drawn[4:] and len(set(drawn)) > 4


def test_checkpoint_round_trip_reproduces_renders_and_continues(tmp_path: Path) -> None:
    scene = Scene("sphere", radius=0.4)
    mapper = Mapper(small_cfg(max_iters=3))
    poses = orbit(scene, 6, 1.4, 0.4, scene.center)
    for i, T in enumerate(poses[:4]):
        mapper.integrate(scene.frame(i, T))
    save_checkpoint(mapper, tmp_path / "ck.pt", {"last_index": 3})
    again, extra = load_checkpoint(tmp_path / "ck.pt")
    assert extra == {"last_index": 3}
    f = scene.frame(0, poses[0])
    a = mapper.render(f.K, f.T_world_camera, f.height, f.width, "depth")
    b = again.render(f.K, f.T_world_camera, f.height, f.width, "depth")
    np.testing.assert_allclose(a, b, atol=1e-6)
    assert [v.index for v in again.color_views.views] == [v.index for v in mapper.color_views.views] == [0, 1, 2, 3]
    rgb_a = mapper.render(f.K, f.T_world_camera, f.height, f.width, "rgb")
    rgb_b = again.render(f.K, f.T_world_camera, f.height, f.width, "rgb")
    assert np.abs(rgb_a - rgb_b).mean() < 0.01  # the stored views' colour went through JPEG
    assert again.octree.n_voxels == mapper.octree.n_voxels and len(again.keyframes) == len(mapper.keyframes)
    np.testing.assert_array_equal(again.observed.words, mapper.observed.words)  # meshing's observed cells
    s1 = mapper.integrate(scene.frame(4, poses[4]))
    s2 = again.integrate(scene.frame(4, poses[4]))
    assert s1.n_voxels == s2.n_voxels and s1.iterations == s2.iterations
    assert s1.losses["total"] == pytest.approx(s2.losses["total"], rel=1e-4)


def test_render_modes_shapes() -> None:
    scene = Scene("plane")
    mapper = Mapper(small_cfg(max_iters=2))
    T = orbit(scene, 1, 0.5, 1.0, np.zeros(3))[0]
    f = scene.frame(0, T)
    mapper.integrate(f)
    assert mapper.render(f.K, T, 24, 32, "rgb").shape == (24, 32, 3)
    n = mapper.render(f.K, T, 24, 32, "normal")
    hit = np.linalg.norm(n, axis=2) > 0
    assert hit.mean() > 0.5
    assert np.median(n[hit][:, 2]) > 0.9  # the plane's normal is +z
    assert mapper.render(f.K, T, 24, 32, "prior").shape == (24, 32)


def test_the_iteration_hook_runs_after_every_optimisation_step() -> None:
    scene = Scene("plane")
    mapper = Mapper(small_cfg(max_iters=4))
    seen: list[int] = []
    mapper.on_iteration = lambda: seen.append(mapper.frames_done)
    stats = [mapper.integrate(scene.frame(i, T)) for i, T in enumerate(orbit(scene, 2, 0.6, 1.2, np.zeros(3)))]
    assert seen == [0] * stats[0].iterations + [1] * stats[1].iterations  # during each frame, once a step
    assert stats[0].iterations >= 1


def test_a_checkpoint_without_observed_cells_rebuilds_them_from_its_keyframes(tmp_path: Path) -> None:
    scene = Scene("sphere", radius=0.4)
    mapper = Mapper(small_cfg(max_iters=2))
    for i, T in enumerate(orbit(scene, 6, 1.4, 0.4, scene.center)[:3]):
        mapper.integrate(scene.frame(i, T))
    save_checkpoint(mapper, tmp_path / "ck.pt")
    state = torch.load(tmp_path / "ck.pt", weights_only=True)
    del state["observed"]  # as saved before meshing kept observed cells
    torch.save(state, tmp_path / "old.pt")
    again, _ = load_checkpoint(tmp_path / "old.pt")
    bits = lambda m: int(np.unpackbits(m.observed.words.view(np.uint8)).sum())  # noqa: E731
    assert bits(again) > 0.5 * bits(mapper)  # the keyframes' depth (every point of it) marks most cells again
    assert len(again.mesh().faces) > 0.8 * len(mapper.mesh().faces)
