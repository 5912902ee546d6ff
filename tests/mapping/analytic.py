"""Analytic scenes for mapping tests: exact depth, colour and signed distance of a plane, a sphere and a box
room, seen by pinhole cameras."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from h2viz.geometry import look_at, world_rays
from h2viz.types import RgbdFrame


def intrinsics(width: int, height: int, fov_deg: float = 70.0) -> np.ndarray:
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])


@dataclass(frozen=True)
class Scene:
    kind: str  # plane | sphere | room
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radius: float = 0.5
    half: np.ndarray = field(default_factory=lambda: np.array([1.5, 1.2, 1.0]))  # room half extents

    def hit_t(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Ray parameter (N,) of the first hit of rays o + t d, inf when missed."""
        t = np.full(len(d), np.inf)
        if self.kind == "plane":  # z = 0
            with np.errstate(divide="ignore", invalid="ignore"):
                tp = -o[:, 2] / d[:, 2]
            return np.where(tp > 0, tp, np.inf)
        if self.kind == "sphere":
            oc = o - self.center
            b = np.sum(oc * d, 1)
            a = np.sum(d * d, 1)
            c = np.sum(oc * oc, 1) - self.radius**2
            disc = b * b - a * c
            ok = disc >= 0
            t[ok] = (-b[ok] - np.sqrt(disc[ok])) / a[ok]
            return np.where(t > 0, t, np.inf)
        lo, hi = self.center - self.half, self.center + self.half  # inside an axis-aligned room
        with np.errstate(divide="ignore", invalid="ignore"):
            t_hi = np.where(d > 0, (hi - o) / d, np.where(d < 0, (lo - o) / d, np.inf))
        return t_hi.min(axis=1)

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (N,) positive in free space."""
        if self.kind == "plane":
            return p[:, 2]
        if self.kind == "sphere":
            return np.linalg.norm(p - self.center, axis=1) - self.radius
        q = np.abs(p - self.center) - self.half
        return -np.max(q, axis=1)  # exact inside the box (the only side the cameras see)

    def color(self, p: np.ndarray) -> np.ndarray:
        """A smooth colour pattern (N,3) uint8 on the surface."""
        c = 0.5 + 0.35 * np.stack(
            [np.sin(4 * p[:, 0]), np.cos(3 * p[:, 1]), np.sin(2.5 * (p[:, 0] + p[:, 2]))], 1
        )
        return (255 * np.clip(c, 0, 1)).astype(np.uint8)

    def frame(self, index: int, T_world_camera: np.ndarray, width: int = 96, height: int = 72) -> RgbdFrame:
        K = intrinsics(width, height)
        o, d = world_rays(K, T_world_camera, height, width)  # z-normalised directions: t = camera depth
        t = self.hit_t(o, d)
        hit = np.isfinite(t)
        pts = o + d * np.where(hit, t, 0)[:, None]
        rgb = np.where(hit[:, None], self.color(pts), 0).astype(np.uint8)
        depth = np.where(hit, t, 0).astype(np.float32)
        return RgbdFrame(
            index, index / 30, rgb.reshape(height, width, 3), depth.reshape(height, width), K, T_world_camera
        )


def orbit(scene: Scene, n: int, radius: float, height: float, target: np.ndarray) -> list[np.ndarray]:
    """Camera poses on a circle around `target`, looking at it (world z up)."""
    poses = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = target + np.array([radius * np.cos(a), radius * np.sin(a), height])
        poses.append(look_at(eye, target))
    return poses
