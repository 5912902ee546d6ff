"""View-dependent colour: rendered surface points take their colour from the nearest stored views' images.

Averaging every frame's colours into a lattice (h2viz.mapping.field.color_prior) blurs texture twice over: by the
lattice spacing and by the pixel-level misregistration of real poses, which the average turns into blur. Image-
based rendering avoids both. Each mapped frame's colour image is kept (with a half-resolution copy and a half-
resolution depth for visibility) under a memory budget; a render picks the stored views nearest its camera
(position and viewing direction), projects every surface point into each, keeps the views whose depth there agrees
with the point's (it is not occluded), samples their colour at the pyramid level matching the render's pixel
footprint, and blends them with weights that favour rays close to the render's ray (unstructured lumigraph
weights). Points no view sees keep the colour field's colour, which is also mixed in with a small weight: it
averages out per-frame noise and aliasing that a few views keep.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from h2viz.types import RgbdFrame

ROTATION_M = 0.5
"""Metres of camera distance that a full turn of viewing direction (1 - cos) counts as, when ranking views."""
MIN_SPACING = 0.005
"""A frame closer than this (in the ranking's metres) to a stored view is not stored: a camera that stands still
does not fill the store with copies (further apart, the nearest frames matter: storing views 2 cm apart instead
of every frame costs 2.1 dB on held-out views of 7-Scenes redkitchen; the budget bounds the store)."""
DEPTH_TOL_M = 0.03
"""A view sees a point when its depth at the point's pixel is within max(this, DEPTH_TOL_REL x depth)..."""
DEPTH_TOL_REL = 0.02
"""...of the point's depth in that view."""
JPEG_QUALITY = 95
"""Stored views' colour in checkpoints (~0.1 MB a 640x480 view instead of 0.9)..."""
JPEG_FLAGS = [
    cv2.IMWRITE_JPEG_QUALITY,
    JPEG_QUALITY,
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444,
]
"""...with full-resolution chroma (4:2:0 would blur colour edges by a pixel)."""
HALF_AT = 1.5
"""Sample the half-resolution image where a render pixel covers at least this many of the view's pixels."""


@dataclass(frozen=True)
class StoredView:
    """One frame kept for its colour: pose, intrinsics, full and half-resolution colour, half-resolution depth."""

    index: int
    T_world_camera: np.ndarray  # (4,4) float64
    K: np.ndarray  # (3,3) float64, full resolution
    rgb: np.ndarray  # (H,W,3) uint8
    rgb_half: np.ndarray  # (H/2,W/2,3) uint8, area-averaged
    depth_half: np.ndarray  # (H/2,W/2) float32 metres, 0 where any of the 2x2 block is invalid

    @staticmethod
    def of(index: int, T_world_camera: np.ndarray, K: np.ndarray, rgb: np.ndarray, depth_m: np.ndarray) -> StoredView:
        h, w = depth_m.shape[0] // 2, depth_m.shape[1] // 2
        half = cv2.resize(rgb[: 2 * h, : 2 * w], (w, h), interpolation=cv2.INTER_AREA)
        d = np.asarray(depth_m, np.float32)
        corners = (d[0 : 2 * h : 2, 0 : 2 * w : 2], d[0 : 2 * h : 2, 1 : 2 * w : 2],
                   d[1 : 2 * h : 2, 0 : 2 * w : 2], d[1 : 2 * h : 2, 1 : 2 * w : 2])  # fmt: skip  # 4 x (h,w)
        valid = (corners[0] > 0) & (corners[1] > 0) & (corners[2] > 0) & (corners[3] > 0)  # (h,w)
        mean = (corners[0] + corners[1] + corners[2] + corners[3]) * np.float32(0.25)
        depth = np.where(valid, mean, np.float32(0.0))
        return StoredView(index, np.asarray(T_world_camera, np.float64), np.asarray(K, np.float64), rgb, half, depth)

    @property
    def nbytes(self) -> int:
        return self.rgb.nbytes + self.rgb_half.nbytes + self.depth_half.nbytes

    def record(self) -> dict[str, Any]:
        """Plain arrays for a checkpoint: the colour as a JPEG (quality JPEG_QUALITY), depth as float16."""
        return {
            "index": self.index,
            "T_world_camera": self.T_world_camera,
            "K": self.K,
            "jpeg": self._jpeg,
            "depth_half": self.depth_half.astype(np.float16),
        }

    @functools.cached_property
    def _jpeg(self) -> np.ndarray:
        """The colour as a JPEG (N,) uint8, encoded once: every autosave writes every stored view."""
        ok, jpeg = cv2.imencode(".jpg", self.rgb[..., ::-1], JPEG_FLAGS)
        if not ok:
            raise ValueError(f"could not encode stored view {self.index} as JPEG")
        return jpeg.reshape(-1)

    @staticmethod
    def from_record(rec: dict[str, Any]) -> StoredView:
        """The view a checkpoint's `record` holds."""
        bgr = cv2.imdecode(np.asarray(rec["jpeg"], np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"stored view {rec['index']}: its JPEG colour does not decode")
        rgb = np.ascontiguousarray(bgr[..., ::-1])
        depth = np.asarray(rec["depth_half"], np.float32)
        h, w = depth.shape
        if (rgb.shape[0] // 2, rgb.shape[1] // 2) != (h, w):
            raise ValueError(f"stored view {rec['index']}: colour {rgb.shape[:2]} and depth {depth.shape} differ")
        half = cv2.resize(rgb[: 2 * h, : 2 * w], (w, h), interpolation=cv2.INTER_AREA)
        T, K = np.asarray(rec["T_world_camera"], np.float64), np.asarray(rec["K"], np.float64)
        return StoredView(int(rec["index"]), T, K, rgb, half, depth)


def view_distances(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """Ranking distances (...) of camera poses T_a and T_b (...,4,4), broadcast against each other: centre
    distance plus ROTATION_M x (1 - cos) of their viewing axes."""
    centres = np.linalg.norm(T_a[..., :3, 3] - T_b[..., :3, 3], axis=-1)
    return centres + ROTATION_M * (1.0 - np.sum(T_a[..., :3, 2] * T_b[..., :3, 2], axis=-1))


def _poses(views: tuple[StoredView, ...] | list[StoredView]) -> np.ndarray:
    """The views' T_world_camera (n,4,4)."""
    return np.stack([v.T_world_camera for v in views])


def _sample(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear colour (N,3) float32 in [0,1] of a uint8 image (H,W,3) at pixel coordinates u, v (N,) (pixel
    centres at integers)."""
    n = u.shape[0]
    side = max(1, int(np.ceil(np.sqrt(n))))  # cv2.remap wants a map under 32767 on each side
    pad = side * side - n
    mu = np.concatenate([u, np.zeros(pad)]).astype(np.float32).reshape(side, side)
    mv = np.concatenate([v, np.zeros(pad)]).astype(np.float32).reshape(side, side)
    out = cv2.remap(image, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, 3)[:n].astype(np.float32) / np.float32(255.0)


class ColorViews:
    """The stored views, within a memory budget, and their blend at rendered surface points."""

    def __init__(self, n_blend: int, budget_mb: float, field_weight: float) -> None:
        if n_blend < 0 or budget_mb < 0 or not 0.0 <= field_weight <= 1.0:
            raise ValueError(
                "mapping.rendering.color_views must be >= 0, mapping.rendering.color_views_mb >= 0 and "
                f"mapping.rendering.color_views_field in [0, 1]; got {n_blend}, {budget_mb}, {field_weight}"
            )
        self.n_blend = int(n_blend)
        self.budget_bytes = int(budget_mb * 2**20)
        self.field_weight = float(field_weight)
        self.views: tuple[StoredView, ...] = ()  # replaced, never changed in place: renders may read it meanwhile

    @property
    def enabled(self) -> bool:
        return self.n_blend > 0

    @property
    def nbytes(self) -> int:
        return sum(v.nbytes for v in self.views)

    @staticmethod
    def view_of(frame: RgbdFrame) -> StoredView:
        """`frame` as the store keeps it (its half-resolution colour and depth: ~1.5 ms; `add` takes it made)."""
        T = np.asarray(frame.T_world_camera, np.float64)
        return StoredView.of(frame.index, T, frame.K, frame.rgb, frame.depth_m)

    def add(self, frame: RgbdFrame, view: StoredView | None = None) -> None:
        """Keep `frame`'s colour (unless a stored view is within MIN_SPACING of its camera), then retire the most
        redundant views (those nearest another) until the store fits its budget. `view`: `view_of(frame)`, made
        ahead (on a reader thread)."""
        if not self.enabled:
            return
        T = np.asarray(frame.T_world_camera, np.float64)
        if self.views and float(view_distances(_poses(self.views), T).min()) < MIN_SPACING:
            return
        self.replace((*self.views, view if view is not None else self.view_of(frame)))

    def replace(self, views: tuple[StoredView, ...]) -> None:
        """Store `views`, retiring the most redundant ones past the budget (a checkpoint's, or after `add`)."""
        views = list(views)
        while self.budget_bytes and len(views) > 1 and sum(v.nbytes for v in views) > self.budget_bytes:
            views.pop(self._most_redundant(views))
        self.views = tuple(views)

    @staticmethod
    def _most_redundant(views: list[StoredView]) -> int:
        """Position of the view nearest to another one (the older of the pair)."""
        poses = _poses(views)  # (n,4,4)
        d = view_distances(poses[:, None], poses[None])  # (n,n)
        np.fill_diagonal(d, np.inf)
        a, b = np.unravel_index(int(np.argmin(d)), d.shape)
        return int(min(a, b))

    def nearest(self, T_world_camera: np.ndarray) -> list[StoredView]:
        """The n_blend stored views nearest a camera (4,4), nearest first."""
        views = self.views
        if not views:
            return []
        d = view_distances(_poses(views), np.asarray(T_world_camera, np.float64))  # (n,)
        return [views[i] for i in np.argsort(d, kind="stable")[: self.n_blend]]

    def blend(self, points: np.ndarray, field_rgb: np.ndarray, T_world_camera: np.ndarray, K: np.ndarray) -> np.ndarray:
        """Colour (N,3) float32 in [0,1] of surface points (N,3) rendered by a camera (4,4) with intrinsics K (3,3)
        at the render's resolution: the nearest views' colours where some view sees a point, mixed with the colour
        field's field_rgb (N,3) by field_weight; field_rgb alone where none does."""
        views = self.nearest(T_world_camera)
        if not views or points.shape[0] == 0:
            return field_rgb
        pts = points.astype(np.float64)
        centre = T_world_camera[:3, 3]
        ray = pts - centre  # (N,3)
        dist = np.linalg.norm(ray, axis=1)  # (N,)
        ray /= np.maximum(dist, 1e-9)[:, None]
        footprint = (ray @ T_world_camera[:3, 2]) * dist / K[0, 0]  # (N,) metres a render pixel covers
        acc = np.zeros((pts.shape[0], 3))
        total = np.zeros(pts.shape[0])
        for view in views:
            rgb, weight = self._view_colour(view, pts, ray, dist, footprint)
            acc += rgb * weight[:, None]
            total += weight
        seen = total > 0
        out = field_rgb.astype(np.float32, copy=True)
        mixed = acc[seen] / total[seen, None]
        out[seen] = (1.0 - self.field_weight) * mixed + self.field_weight * field_rgb[seen]
        return out

    @staticmethod
    def _view_colour(
        view: StoredView, pts: np.ndarray, ray: np.ndarray, dist: np.ndarray, footprint: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """One view's colour (N,3) at points (N,3) and its blending weight (N,) (0 where it does not see them)."""
        T = view.T_world_camera
        local = (pts - T[:3, 3]) @ T[:3, :3]  # (N,3) in the view's camera frame
        z = local[:, 2]
        front = z > 1e-3
        zs = np.where(front, z, 1.0)
        u = local[:, 0] / zs * view.K[0, 0] + view.K[0, 2]  # full-resolution pixel coordinates, corners at 0
        v = local[:, 1] / zs * view.K[1, 1] + view.K[1, 2]
        hh, hw = view.depth_half.shape
        ui, vi = np.floor(u / 2.0).astype(np.int64), np.floor(v / 2.0).astype(np.int64)
        inside = front & (ui >= 0) & (vi >= 0) & (ui < hw) & (vi < hh)
        depth = view.depth_half[np.clip(vi, 0, hh - 1), np.clip(ui, 0, hw - 1)]  # (N,)
        seen = inside & (depth > 0) & (np.abs(depth - z) < np.maximum(DEPTH_TOL_M, DEPTH_TOL_REL * z))
        half = footprint >= HALF_AT * zs / view.K[0, 0]  # a render pixel spans >= 1.5 of the view's pixels
        rgb = np.empty((pts.shape[0], 3), np.float32)
        full = seen & ~half
        coarse = seen & half
        rgb[full] = _sample(view.rgb, u[full] - 0.5, v[full] - 0.5)
        rgb[coarse] = _sample(view.rgb_half, u[coarse] / 2.0 - 0.5, v[coarse] / 2.0 - 0.5)
        view_ray = pts - T[:3, 3]
        view_dist = np.linalg.norm(view_ray, axis=1)
        cos = np.einsum("ij,ij->i", ray, view_ray) / np.maximum(view_dist, 1e-9)
        angle = np.arccos(np.clip(cos, -1.0, 1.0))  # (N,) between the render's and the view's ray
        weight = seen / (0.01 + angle + 0.1 * np.abs(view_dist - dist))
        return np.where(seen[:, None], rgb, 0.0), weight
