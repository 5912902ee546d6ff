"""Training rays of a frame: the fused kernel against the torch reference, and against back-projection."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from h2viz.geometry import backproject
from h2viz.mapping.sampling.rays import FrameRays, RayBatch, sample_frames
from h2viz.types import RgbdFrame
from tests.mapping.backends import FAST, REFERENCE, needs_numba

pytest.importorskip("numba")


def _frame() -> RgbdFrame:
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.3, 4.0, size=(48, 64)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = 0.0  # holes
    depth[:, -1] = 0.0
    rgb = rng.integers(0, 256, size=(48, 64, 3), dtype=np.uint8)
    K = np.array([[50.0, 0, 31.5], [0, 52.0, 23.5], [0, 0, 1]])
    angle = 0.7
    T = np.eye(4)
    T[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    T[:3, 3] = [1.5, -0.4, 12.0]
    return RgbdFrame(index=7, timestamp=0.0, rgb=rgb, depth_m=depth, K=K, T_world_camera=T)


@needs_numba
def test_fused_frame_rays_match_the_torch_path_and_back_projection() -> None:
    frame = _frame()
    fast, points = FrameRays.with_points(frame, FAST)
    ref, ref_points = FrameRays.with_points(frame, REFERENCE)
    assert torch.equal(fast.valid, ref.valid)
    assert len(fast) == int((frame.depth_m > 0).sum())
    assert torch.equal(fast.depth, ref.depth)
    assert torch.equal(fast.rgb, ref.rgb) and fast.rgb.dtype == torch.uint8
    torch.testing.assert_close(fast.dirs, ref.dirs, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(fast.origin, ref.origin)
    np.testing.assert_allclose(points, ref_points, atol=2e-6 * 15)
    np.testing.assert_allclose(points, backproject(frame.depth_m, frame.K, frame.T_world_camera), atol=2e-5)
    # a ray of z-normalised direction reaches its pixel's point at t = depth
    rebuilt = fast.origin + fast.dirs * fast.depth[:, None]
    np.testing.assert_allclose(rebuilt.numpy(), points, atol=2e-5)
    assert FrameRays(frame, FAST).valid.shape == fast.valid.shape


def test_frame_rays_keep_11_bytes_a_pixel_and_sampled_rays_reach_their_points() -> None:
    frame = _frame()
    rays, points = FrameRays.with_points(frame, FAST)
    kept = [getattr(rays, name) for name in vars(rays) if isinstance(getattr(rays, name), torch.Tensor)]
    per_pixel = [t for t in kept if t.ndim and t.shape[0] == len(rays)]
    assert sum(t.element_size() * t.numel() for t in per_pixel) == 11 * len(rays)  # id int32, depth, rgb
    assert rays.valid.dtype == torch.int32
    batch = rays.sample(500, torch.Generator().manual_seed(0))
    ends = (batch.origins + batch.dirs * batch.depth[:, None]).numpy()  # (500,3)
    # every sampled ray ends on the back-projected point of a valid pixel with the same depth and colour
    world = backproject(frame.depth_m, frame.K, frame.T_world_camera)  # (P,3) in valid-pixel order
    nearest = np.linalg.norm(ends[:, None] - world[None], axis=-1).argmin(1)
    np.testing.assert_allclose(ends, world[nearest], atol=2e-5)
    pixel = rays.valid[nearest].numpy()
    np.testing.assert_allclose(batch.depth.numpy(), frame.depth_m.reshape(-1)[pixel])
    np.testing.assert_allclose(batch.rgb.numpy() * 255, frame.rgb.reshape(-1, 3)[pixel], atol=1e-3)


def test_sampling_several_frames_gives_the_rays_of_the_torch_path() -> None:
    """The compiled gather draws the same picks from the generator and computes the same rays as concatenating
    FrameRays.sample; frames without valid depth give no rays."""
    frames = [_frame()]
    for k, angle in enumerate((0.2, -1.1)):
        f = _frame()
        T = f.T_world_camera.copy()
        T[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
        T[:3, 3] += k
        frames.append(RgbdFrame(index=8 + k, timestamp=0.0, rgb=f.rgb, depth_m=f.depth_m[::-1].copy(), K=f.K,
                                T_world_camera=T))  # fmt: skip
    empty = RgbdFrame(index=20, timestamp=0.0, rgb=frames[0].rgb, depth_m=np.zeros((48, 64), np.float32),
                      K=frames[0].K, T_world_camera=np.eye(4))  # fmt: skip
    rays = [FrameRays(f, FAST) for f in (frames[0], empty, *frames[1:])]
    fast = sample_frames(rays, 300, torch.Generator().manual_seed(5), FAST)
    ref = sample_frames(rays, 300, torch.Generator().manual_seed(5), REFERENCE)
    assert fast.origins.shape == (900, 3) and fast.depth.shape == (900,)
    for name in ("origins", "dirs", "rgb", "depth"):
        torch.testing.assert_close(getattr(fast, name), getattr(ref, name), rtol=1e-6, atol=1e-6)
    by_hand = RayBatch.cat([r.sample(300, g) for g in [torch.Generator().manual_seed(5)] for r in rays if len(r)])
    torch.testing.assert_close(fast.rgb, by_hand.rgb, rtol=0, atol=0)
    assert len(sample_frames([rays[1]], 10, torch.Generator(), FAST).depth) == 0
