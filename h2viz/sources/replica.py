"""Replica in the NICE-SLAM layout: results/frame%06d.jpg, results/depth%06d.png and traj.txt.

traj.txt holds one row-major 4x4 camera-to-world matrix per line, line k for frame k. The layout has no
intrinsics and no timestamps: K comes from `source.intrinsics` or the renderer's 1200x680 camera
(fx = fy = 600, cx = 599.5, cy = 339.5), and a frame's timestamp is its frame number / 30 s (30 Hz).
"""

from __future__ import annotations

import logging
from collections.abc import Hashable, Sequence
from pathlib import Path

import cv2
import numpy as np

from h2viz.config import SourceConfig
from h2viz.errors import FrameError, SourceError
from h2viz.sources.folders import (
    NumberedSource,
    configured_intrinsics,
    depth_scale_m,
    has_numbered_file,
    numbered_files,
    numbered_frame,
    pinhole,
    require_folder,
)
from h2viz.types import RgbdFrame

log = logging.getLogger("h2viz.sources")

DEPTH_SCALE_M = 1.0 / 6553.5
DEFAULT_SIZE = (1200, 680)  # width, height of the images the default intrinsics belong to
DEFAULT_K = pinhole(600.0, 600.0, 599.5, 339.5)
COLOR_PATTERN = r"frame(\d{6})\.jpg"
DEPTH_PATTERN = r"depth(\d{6})\.png"


def read_trajectory(path: Path) -> list[np.ndarray | None]:
    """One (4,4) pose per non-empty line of traj.txt (pose k = frame k); None where not 16 numbers."""
    if not path.is_file():
        raise SourceError(f"{path}: trajectory file is missing; Replica needs traj.txt next to results/")
    poses: list[np.ndarray | None] = []
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        try:
            values = np.array(line.split(), dtype=np.float64)
        except ValueError:
            values = np.empty(0)
        poses.append(values.reshape(4, 4) if values.size == 16 else None)
    return poses


class ReplicaSource(NumberedSource):
    """Replica sequences as rendered for NICE-SLAM (depth / 6553.5 m, timestamps = index / 30 s)."""

    format_name = "replica"

    def __init__(self, cfg: SourceConfig) -> None:
        super().__init__(cfg)
        self.root = require_folder(cfg.path, "Replica")
        self.results = self.root / "results"
        colors = numbered_files(self.results, COLOR_PATTERN)
        depths = numbered_files(self.results, DEPTH_PATTERN)
        ids = sorted(set(colors) | set(depths))
        if not ids:
            raise SourceError(f"{self.results}: no frame%06d.jpg / depth%06d.png images found")
        self.traj_path = self.root / "traj.txt"
        self.poses = read_trajectory(self.traj_path)
        if len(self.poses) < ids[-1] + 1:
            log.warning(
                "%s has %d poses but results/ has images up to frame %d; using the %d frames that have one",
                self.traj_path,
                len(self.poses),
                ids[-1],
                sum(i < len(self.poses) for i in ids),
            )
        self.ids = [i for i in ids if i < len(self.poses)]
        if not self.ids:
            raise SourceError(f"{self.traj_path}: no pose lines for the images in {self.results}")
        self.K = configured_intrinsics(cfg)
        if self.K is None:
            self.K = DEFAULT_K
            self._check_default_size(colors.get(self.ids[0]))
        self.scale_m = depth_scale_m(cfg, DEPTH_SCALE_M)

    def _check_default_size(self, first_color: Path | None) -> None:
        """SourceError when the images do not have the size the default intrinsics belong to."""
        img = cv2.imread(str(first_color)) if first_color is not None else None
        if img is None:
            return  # unreadable frames are reported one by one when loaded
        if (img.shape[1], img.shape[0]) != DEFAULT_SIZE:
            raise SourceError(
                f"{first_color}: images are {img.shape[1]}x{img.shape[0]} but the default Replica intrinsics "
                f"are for {DEFAULT_SIZE[0]}x{DEFAULT_SIZE[1]}; set source.intrinsics (fx, fy, cx, cy)"
            )

    @staticmethod
    def looks_like(path: Path) -> bool:
        """A results/ folder holding frame%06d.jpg and depth%06d.png images."""
        results = Path(path) / "results"
        return has_numbered_file(results, COLOR_PATTERN) and has_numbered_file(results, DEPTH_PATTERN)

    def keys(self) -> Sequence[Hashable]:
        return self.ids

    def load(self, position: int, key: Hashable) -> RgbdFrame:
        assert isinstance(key, int)
        color_path = self.results / f"frame{key:06d}.jpg"
        depth_path = self.results / f"depth{key:06d}.png"
        T = self.poses[key]
        if T is None or not np.all(np.isfinite(T)):
            raise FrameError(f"{self.traj_path} pose {key + 1}: not 16 finite numbers; frame {key} skipped")
        return numbered_frame(position, key, color_path, depth_path, self.scale_m, self.K, T)
