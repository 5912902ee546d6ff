"""Training rays: frames kept on the device with their valid pixels computed once, and random ray batches."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from h2viz.types import RgbdFrame


@dataclass
class RayBatch:
    origins: torch.Tensor  # (R,3)
    dirs: torch.Tensor  # (R,3) world, z-normalised in the camera frame
    rgb: torch.Tensor  # (R,3) in [0,1]
    depth: torch.Tensor  # (R,) metres

    @staticmethod
    def cat(batches: list[RayBatch]) -> RayBatch:
        return RayBatch(
            *(torch.cat([getattr(b, f) for b in batches]) for f in ("origins", "dirs", "rgb", "depth"))
        )


class FrameRays:
    """One frame's colour, depth and pixel rays on the device; sampling touches only valid-depth pixels."""

    def __init__(self, frame: RgbdFrame, device: torch.device) -> None:
        self.index = frame.index
        self.K = frame.K
        self.T_world_camera = frame.T_world_camera
        self.shape = frame.depth_m.shape
        depth = torch.from_numpy(frame.depth_m).to(device).reshape(-1)  # (H*W,)
        self.valid = torch.nonzero(depth > 0)[:, 0]  # (P,)
        self.depth = depth[self.valid]  # (P,)
        self.rgb = torch.from_numpy(frame.rgb.reshape(-1, 3)).to(device)[self.valid]  # (P,3) uint8
        h, w = self.shape
        v = (self.valid // w).float()
        u = (self.valid % w).float()
        K = frame.K
        d_cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], 1)
        T = torch.from_numpy(frame.T_world_camera).to(device, torch.float32)
        self.dirs = d_cam @ T[:3, :3].T  # (P,3)
        self.origin = T[:3, 3]  # (3,)

    def __len__(self) -> int:
        return int(self.valid.numel())

    def sample(self, n: int, generator: torch.Generator) -> RayBatch:
        """n random valid-depth rays (with replacement when the frame has fewer)."""
        P = len(self)
        dev = self.depth.device
        pick = (
            torch.randint(P, (n,), generator=generator, device="cpu").to(dev)
            if P
            else torch.zeros(0, dtype=torch.long)
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
    d_cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1).reshape(
        -1, 3
    )
    T = torch.from_numpy(np.asarray(T_world_camera)).to(device, torch.float32)
    dirs = d_cam @ T[:3, :3].T
    return T[:3, 3].expand_as(dirs), dirs
