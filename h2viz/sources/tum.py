"""TUM RGB-D: rgb.txt and depth.txt ("timestamp filename" lines) and groundtruth.txt ("timestamp tx ty
tz qx qy qz qw", the colour camera's optical frame in the motion-capture world).

Each depth image is one frame. It takes the colour image nearest in time and a pose interpolated
between the two bracketing ground-truth samples (linear translation, slerp rotation) when both lie
within `source.tum.max_time_gap_s`, else the nearest sample within that gap. Frames with no colour or
no pose that close are skipped and counted. Depth is / 5000 m; no undistortion is applied.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Hashable, Sequence
from pathlib import Path

import numpy as np

from h2viz.config import SourceConfig
from h2viz.errors import FrameError, SourceError
from h2viz.geometry import pose_from_tq, slerp
from h2viz.sources.base import FrameSource, read_color, read_depth
from h2viz.sources.folders import (
    configured_intrinsics,
    depth_scale_m,
    fit_color_to_depth,
    pinhole,
    require_folder,
)
from h2viz.types import RgbdFrame

log = logging.getLogger("h2viz.sources")

DEPTH_SCALE_M = 1.0 / 5000.0
PRESETS: dict[str, tuple[float, float, float, float]] = {  # fx, fy, cx, cy of the colour camera
    "fr1": (517.3, 516.5, 318.6, 255.3),
    "fr2": (520.9, 521.0, 325.1, 249.7),
    "fr3": (535.4, 539.2, 320.1, 247.6),
}
_PRESET_IN_NAME = re.compile(r"(?<![a-z])(?:freiburg|fr)_?([123])(?![0-9])")


def _data_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, fields) of every non-empty, non-comment line; SourceError when the file is missing."""
    if not path.is_file():
        raise SourceError(
            f"{path}: file is missing; a TUM RGB-D folder needs rgb.txt, depth.txt and groundtruth.txt"
        )
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.split()
        if fields and not fields[0].startswith("#"):
            rows.append((n, fields))
    return rows


def _bad_line(path: Path, n: int, expected: str) -> SourceError:
    return SourceError(f"{path} line {n}: expected {expected}; fix or remove the line")


def read_image_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """Timestamps (N,) sorted ascending and the matching relative file names of rgb.txt / depth.txt."""
    times, names = [], []
    for n, fields in _data_lines(path):
        try:
            times.append(float(fields[0]))
            names.append(fields[1])
        except (ValueError, IndexError):
            raise _bad_line(path, n, "'timestamp filename'") from None
    order = np.argsort(np.array(times, dtype=np.float64), kind="stable")
    return np.array(times, dtype=np.float64)[order], [names[i] for i in order]


def read_groundtruth(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Timestamps (M,) sorted ascending, translations (M,3) and quaternions (M,4) xyzw of groundtruth.txt."""
    rows = []
    for n, fields in _data_lines(path):
        try:
            rows.append([float(f) for f in fields[:8]])
        except ValueError:
            raise _bad_line(path, n, "8 numbers 'timestamp tx ty tz qx qy qz qw'") from None
        if len(rows[-1]) != 8:
            raise _bad_line(path, n, "8 numbers 'timestamp tx ty tz qx qy qz qw'")
    if not rows:
        raise SourceError(f"{path}: no poses; TUM frames need ground truth to be mapped")
    gt = np.array(rows, dtype=np.float64)  # (M,8)
    gt = gt[np.argsort(gt[:, 0], kind="stable")]
    return gt[:, 0], gt[:, 1:4], gt[:, 4:8]


def nearest(times: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index (N,) of the nearest entry of sorted `times` (M,) to each query (N,) and its |gap| (N,)."""
    j = np.minimum(np.searchsorted(times, queries), len(times) - 1)
    lo = np.maximum(j - 1, 0)
    pick = np.where(np.abs(times[lo] - queries) <= np.abs(times[j] - queries), lo, j)
    return pick, np.abs(times[pick] - queries)


def interpolate_poses(
    gt_t: np.ndarray, gt_xyz: np.ndarray, gt_q: np.ndarray, queries: np.ndarray, max_gap_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Translations (N,3), quaternions (N,4) and a found mask (N,) at `queries`: interpolated between
    the bracketing samples when both are within `max_gap_s`, else the nearest one within it."""
    m = len(gt_t)
    j = np.searchsorted(gt_t, queries)  # (N,) first sample at or after the query
    lo, hi = np.clip(j - 1, 0, m - 1), np.clip(j, 0, m - 1)
    lo_ok = (j > 0) & (queries - gt_t[lo] <= max_gap_s)
    hi_ok = (j < m) & (gt_t[hi] - queries <= max_gap_s)
    both = lo_ok & hi_ok
    span = gt_t[hi] - gt_t[lo]
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha = np.where(both & (span > 0), (queries - gt_t[lo]) / span, 0.0)
    near, _ = nearest(gt_t, queries)
    lo, hi = np.where(both, lo, near), np.where(both, hi, near)
    xyz = (1.0 - alpha)[:, None] * gt_xyz[lo] + alpha[:, None] * gt_xyz[hi]
    return xyz, slerp(gt_q[lo], gt_q[hi], alpha), lo_ok | hi_ok


def resolve_preset(preset: str, root: Path) -> str:
    """fr1 / fr2 / fr3 from `preset`, or for 'auto' from the folder name (fr1 with a warning if absent)."""
    preset = preset.lower()
    if preset in PRESETS:
        return preset
    if preset != "auto":
        raise SourceError(f"source.tum.preset '{preset}' is unknown; choose auto, {', '.join(PRESETS)}")
    m = _PRESET_IN_NAME.search(root.resolve().name.lower())
    if m is not None:
        return f"fr{m.group(1)}"
    log.warning(
        "%s: no freiburg1/2/3 (fr1/fr2/fr3) in the folder name; using fr1 intrinsics. Set source.tum.preset",
        root,
    )
    return "fr1"


class TumSource(FrameSource):
    """TUM RGB-D sequences (depth / 5000 m, fr1/fr2/fr3 intrinsics presets, depth image timestamps)."""

    format_name = "tum"

    def __init__(self, cfg: SourceConfig) -> None:
        super().__init__(cfg)
        self.root = require_folder(cfg.path, "TUM RGB-D")
        self.rgb_t, self.rgb_names = read_image_list(self.root / "rgb.txt")
        self.depth_t, self.depth_names = read_image_list(self.root / "depth.txt")
        if len(self.depth_t) == 0 or len(self.rgb_t) == 0:
            raise SourceError(f"{self.root}: rgb.txt or depth.txt lists no images")
        self.gt_path = self.root / "groundtruth.txt"
        gt_t, gt_xyz, gt_q = read_groundtruth(self.gt_path)
        gap = cfg.tum.max_time_gap_s
        self.rgb_idx, self.rgb_gap = nearest(self.rgb_t, self.depth_t)  # (N,), (N,)
        self.xyz, self.quat, self.has_pose = interpolate_poses(gt_t, gt_xyz, gt_q, self.depth_t, gap)
        self.K = configured_intrinsics(cfg)
        if self.K is None:
            self.K = pinhole(*PRESETS[resolve_preset(cfg.tum.preset, self.root)])
        self.scale_m = depth_scale_m(cfg, DEPTH_SCALE_M)

    @staticmethod
    def looks_like(path: Path) -> bool:
        """rgb.txt and depth.txt lists side by side."""
        root = Path(path)
        return (root / "rgb.txt").is_file() and (root / "depth.txt").is_file()

    def keys(self) -> Sequence[Hashable]:
        return list(range(len(self.depth_t)))

    def timestamp(self, position: int, key: Hashable) -> float | None:
        return float(self.depth_t[int(key)])  # type: ignore[call-overload]

    def load(self, position: int, key: Hashable) -> RgbdFrame:
        assert isinstance(key, int)
        depth_path = self.root / self.depth_names[key]
        t, gap = self.depth_t[key], self.cfg.tum.max_time_gap_s
        if self.rgb_gap[key] > gap:
            raise FrameError(
                f"{depth_path} (t={t:.6f}): nearest colour image in {self.root / 'rgb.txt'} is "
                f"{self.rgb_gap[key]:.3f} s away (> source.tum.max_time_gap_s={gap}); frame skipped"
            )
        if not self.has_pose[key]:
            raise FrameError(
                f"{depth_path} (t={t:.6f}): no pose in {self.gt_path} within {gap} s "
                "(source.tum.max_time_gap_s); frame skipped"
            )
        if not (np.all(np.isfinite(self.xyz[key])) and np.all(np.isfinite(self.quat[key]))):
            raise FrameError(
                f"{depth_path} (t={t:.6f}): pose from {self.gt_path} holds inf/NaN; frame skipped"
            )
        color_path = self.root / self.rgb_names[self.rgb_idx[key]]
        depth_m = read_depth(depth_path, self.scale_m)
        rgb = fit_color_to_depth(read_color(color_path), depth_m.shape, color_path)
        return RgbdFrame(
            index=position,
            timestamp=float(t),
            rgb=rgb,
            depth_m=depth_m,
            K=self.K,
            T_world_camera=pose_from_tq(self.xyz[key], self.quat[key]),
            name=str(depth_path),
        )
