"""Training rays: frames kept on the device with their valid pixels computed once, and random ray batches."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from h2viz.types import RgbdFrame

if TYPE_CHECKING:
    from h2viz.mapping.backend import Backend


@dataclass
class RayBatch:
    origins: torch.Tensor  # (R,3)
    dirs: torch.Tensor  # (R,3) world, z-normalised in the camera frame
    rgb: torch.Tensor  # (R,3) in [0,1]
    depth: torch.Tensor  # (R,) metres

    @staticmethod
    def empty() -> RayBatch:
        """A batch of no rays."""
        return RayBatch(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0))

    @staticmethod
    def cat(batches: list[RayBatch]) -> RayBatch:
        return RayBatch(*(torch.cat([getattr(b, f) for b in batches]) for f in ("origins", "dirs", "rgb", "depth")))


class FrameRays:
    """One frame's valid-depth pixels kept compactly for training: pixel ids (int32), depth and colour, 11 bytes a
    pixel. Ray directions are computed for the pixels a batch samples, not stored: keyframes accumulate over a
    run, and (P,3) float directions and int64 ids would take 27 bytes a pixel (8 MB a 640x480 keyframe)."""

    def __init__(self, frame: RgbdFrame, backend: Backend) -> None:
        self._build(frame, backend)

    @staticmethod
    def with_points(frame: RgbdFrame, backend: Backend) -> tuple[FrameRays, np.ndarray]:
        """The frame's rays on the backend's device and its valid pixels' world points (P,3) float32 (for voxel
        allocation), in one pass."""
        rays = FrameRays.__new__(FrameRays)
        return rays, rays._build(frame, backend)

    def _build(self, frame: RgbdFrame, backend: Backend) -> np.ndarray:
        """Fill the fields; returns the world points (P,3). The backend's fused kernel, else this torch code."""
        device = backend.device
        self.index = frame.index
        self.K = frame.K
        self.T_world_camera = frame.T_world_camera
        self.shape = frame.depth_m.shape
        T = torch.from_numpy(np.asarray(frame.T_world_camera)).to(device, torch.float32)
        self.origin = T[:3, 3]  # (3,)
        self.rotation = T[:3, :3]  # (3,3) camera axes in world coordinates (columns)
        kernels = backend.tensor_kernels
        if kernels is not None:
            arrays = kernels.frame.frame_rays(frame.depth_m, frame.rgb, frame.K, frame.T_world_camera)
            valid, depth, rgb, points = arrays
            self.valid, self.depth, self.rgb = (torch.from_numpy(a) for a in (valid, depth, rgb))
            return points
        depth_all = torch.from_numpy(frame.depth_m).to(device, torch.float32).reshape(-1)  # (H*W,)
        self.valid = torch.nonzero(depth_all > 0)[:, 0].to(torch.int32)  # (P,)
        self.depth = depth_all[self.valid]  # (P,)
        self.rgb = torch.from_numpy(frame.rgb.reshape(-1, 3)).to(device)[self.valid]  # (P,3) uint8
        return (self.origin + self.directions(self.valid) * self.depth[:, None]).cpu().numpy()

    def __len__(self) -> int:
        return int(self.valid.numel())

    @property
    def nbytes(self) -> int:
        """Memory held by the pixel ids, depth and colour, bytes."""
        return sum(t.numel() * t.element_size() for t in (self.valid, self.depth, self.rgb))

    def thin(self, step: int = 2) -> None:
        """Keep every `step`-th valid pixel (the rest of the image stays out of training): a keyframe's rays in 1/step
        of the memory, still spread over the whole image."""
        self.valid, self.depth, self.rgb = (t[::step].clone() for t in (self.valid, self.depth, self.rgb))

    def directions(self, pixels: torch.Tensor) -> torch.Tensor:
        """World ray directions (N,3), z-normalised in the camera frame, of pixel ids (N,) (row-major, v * W + u)."""
        w = self.shape[1]
        K = np.asarray(self.K, dtype=np.float32)
        x = ((pixels % w).float() - float(K[0, 2])) / float(K[0, 0])  # (N,)
        y = (torch.div(pixels, w, rounding_mode="floor").float() - float(K[1, 2])) / float(K[1, 1])  # (N,)
        R = self.rotation
        return x[:, None] * R[:, 0] + y[:, None] * R[:, 1] + R[:, 2]

    @property
    def dirs(self) -> torch.Tensor:
        """Directions (P,3) of every valid pixel (computed on each access)."""
        return self.directions(self.valid)

    def sample(self, n: int, generator: torch.Generator) -> RayBatch:
        """n random valid-depth rays (with replacement when the frame has fewer)."""
        P = len(self)
        dev = self.depth.device
        pick = (
            torch.randint(P, (n,), generator=generator, device="cpu").to(dev) if P else torch.zeros(0, dtype=torch.long)
        )
        return RayBatch(
            origins=self.origin.expand(pick.numel(), 3),
            dirs=self.directions(self.valid[pick]),
            rgb=self.rgb[pick].float() / 255.0,
            depth=self.depth[pick],
        )

    def kernel_arrays(self) -> tuple[np.ndarray, ...]:
        """(valid, depth, rgb, K, rotation, origin) as the CPU arrays `frame_numba.gather_rays` reads."""
        K = np.asarray(self.K, dtype=np.float32)
        return self.valid.numpy(), self.depth.numpy(), self.rgb.numpy(), K, self.rotation.numpy(), self.origin.numpy()

    def voxel_points(self, stride: int = 4) -> np.ndarray:
        """A subsample of this frame's world points (N,3) for visibility bookkeeping."""
        pts = self.origin + self.directions(self.valid[::stride]) * self.depth[::stride, None]
        return pts.cpu().numpy()


def pixel_rays(
    K: np.ndarray, T_world_camera: np.ndarray, height: int, width: int, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """Origins and z-normalised world directions (H*W,3) of every pixel of a camera."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=torch.float32),
        torch.arange(width, device=device, dtype=torch.float32),
        indexing="ij",
    )
    d_cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1).reshape(-1, 3)
    T = torch.from_numpy(np.asarray(T_world_camera)).to(device, torch.float32)
    dirs = d_cam @ T[:3, :3].T
    return T[:3, 3].expand_as(dirs), dirs


def sample_frames(frames: list[FrameRays], n: int, generator: torch.Generator, backend: Backend) -> RayBatch:
    """n random valid-depth rays from each frame that has any, one frame after the other: the same rays as
    concatenating `FrameRays.sample` (same generator draws), gathered by one compiled call per frame with the
    backend's tensor kernels (else through that torch code)."""
    frames = [f for f in frames if len(f)]
    if not frames:
        return RayBatch.empty()
    kernels = backend.cpu_kernels(*(f.depth for f in frames))
    if kernels is None:
        return RayBatch.cat([f.sample(n, generator) for f in frames])
    picks = [torch.randint(len(f), (n,), generator=generator).numpy() for f in frames]
    arrays = kernels.frame.gather_rays(picks, [f.kernel_arrays() for f in frames], [f.shape[1] for f in frames])
    return RayBatch(*(torch.from_numpy(a) for a in arrays))
