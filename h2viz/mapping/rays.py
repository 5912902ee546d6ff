"""Training rays: frames kept on the device with their valid pixels computed once, and random ray batches."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from h2viz.mapping.kernels import kernel_module
from h2viz.types import RgbdFrame


@dataclass
class RayBatch:
    origins: torch.Tensor  # (R,3)
    dirs: torch.Tensor  # (R,3) world, z-normalised in the camera frame
    rgb: torch.Tensor  # (R,3) in [0,1]
    depth: torch.Tensor  # (R,) metres

    @staticmethod
    def cat(batches: list[RayBatch]) -> RayBatch:
        return RayBatch(*(torch.cat([getattr(b, f) for b in batches]) for f in ("origins", "dirs", "rgb", "depth")))


class FrameRays:
    """One frame's colour, depth and pixel rays on the device; sampling touches only valid-depth pixels."""

    def __init__(self, frame: RgbdFrame, device: torch.device) -> None:
        self._build(frame, device)

    @staticmethod
    def with_points(frame: RgbdFrame, device: torch.device) -> tuple[FrameRays, np.ndarray]:
        """The frame's rays and its valid pixels' world points (P,3) float32 (for voxel allocation), in one pass."""
        rays = FrameRays.__new__(FrameRays)
        return rays, rays._build(frame, device)

    def _build(self, frame: RgbdFrame, device: torch.device) -> np.ndarray:
        """Fill the fields; returns the world points (P,3). The fused kernel on the CPU, else this torch code."""
        self.index = frame.index
        self.K = frame.K
        self.T_world_camera = frame.T_world_camera
        self.shape = frame.depth_m.shape
        T = torch.from_numpy(frame.T_world_camera).to(device, torch.float32)
        self.origin = T[:3, 3]  # (3,)
        fused = kernel_module("frame_numba") if device.type == "cpu" else None
        if fused is not None:
            valid, depth, rgb, dirs, points = fused.frame_rays(frame.depth_m, frame.rgb, frame.K, frame.T_world_camera)
            self.valid, self.depth, self.rgb, self.dirs = (torch.from_numpy(a) for a in (valid, depth, rgb, dirs))
            return points
        depth_all = torch.from_numpy(frame.depth_m).to(device, torch.float32).reshape(-1)  # (H*W,)
        self.valid = torch.nonzero(depth_all > 0)[:, 0]  # (P,)
        self.depth = depth_all[self.valid]  # (P,)
        self.rgb = torch.from_numpy(frame.rgb.reshape(-1, 3)).to(device)[self.valid]  # (P,3) uint8
        w = self.shape[1]
        v = (self.valid // w).float()
        u = (self.valid % w).float()
        K = torch.from_numpy(np.asarray(frame.K)).to(torch.float32)
        d_cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], 1)
        self.dirs = d_cam @ T[:3, :3].T  # (P,3)
        return (self.origin + self.dirs * self.depth[:, None]).cpu().numpy()

    def __len__(self) -> int:
        return int(self.valid.numel())

    def sample(self, n: int, generator: torch.Generator) -> RayBatch:
        """n random valid-depth rays (with replacement when the frame has fewer)."""
        P = len(self)
        dev = self.depth.device
        pick = (
            torch.randint(P, (n,), generator=generator, device="cpu").to(dev) if P else torch.zeros(0, dtype=torch.long)
        )
        return RayBatch(
            origins=self.origin.expand(pick.numel(), 3),
            dirs=self.dirs[pick],
            rgb=self.rgb[pick].float() / 255.0,
            depth=self.depth[pick],
        )

    def voxel_points(self, stride: int = 4) -> np.ndarray:
        """A subsample of this frame's world points (N,3) for visibility bookkeeping."""
        pts = self.origin + self.dirs[::stride] * self.depth[::stride, None]
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
