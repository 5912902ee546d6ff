"""Microsoft 7-Scenes and 3DMatch RGB-D sequences: frame-%06d.color.{png,jpg}, frame-%06d.depth.png
(millimetres, 65535 = invalid), frame-%06d.pose.txt (4x4 camera-to-world) and camera-intrinsics.txt (3x3).

3DMatch keeps camera-intrinsics.txt in the scene folder above its seq-XX folders, so the parent is
searched too. The original 7-Scenes has no intrinsics file: its Kinect's fx = fy = 585, cx = 320,
cy = 240 are used with a warning. Colour is resized onto the depth image when their sizes differ.
Timestamps are frame number / 30 s (the Kinect's rate).
"""

from __future__ import annotations

import logging
from collections.abc import Hashable, Sequence
from pathlib import Path

import numpy as np

from h2viz.config import SourceConfig
from h2viz.errors import SourceError
from h2viz.sources.folders import (
    NumberedSource,
    configured_intrinsics,
    depth_scale_m,
    has_numbered_file,
    numbered_files,
    numbered_frame,
    pinhole,
    read_intrinsics_file,
    read_pose_file,
    require_folder,
)
from h2viz.types import RgbdFrame

log = logging.getLogger("h2viz.sources")

DEPTH_SCALE_M = 1.0 / 1000.0
INVALID_DEPTH = 65535
DEFAULT_K = pinhole(585.0, 585.0, 320.0, 240.0)
INTRINSICS_FILE = "camera-intrinsics.txt"
FRAME_PATTERN = r"frame-(\d{6})\.(?:color\.(?:png|jpg)|depth\.png|pose\.txt)"
DEPTH_PATTERN = r"frame-(\d{6})\.depth\.png"
POSE_PATTERN = r"frame-(\d{6})\.pose\.txt"


def find_intrinsics(root: Path) -> np.ndarray | None:
    """K (3,3) from camera-intrinsics.txt in `root` or its parent (3DMatch), None when there is none."""
    for folder in (root, root.resolve().parent):
        path = folder / INTRINSICS_FILE
        if path.is_file():
            return read_intrinsics_file(path, (3, 3))
    return None


class SevenScenesSource(NumberedSource):
    """7-Scenes / 3DMatch sequence folders (depth / 1000 m, 65535 = invalid)."""

    format_name = "7scenes"

    def __init__(self, cfg: SourceConfig) -> None:
        super().__init__(cfg)
        self.root = require_folder(cfg.path, "7-Scenes")
        self.ids = sorted(numbered_files(self.root, FRAME_PATTERN))
        if not self.ids:
            seqs = sorted(p.name for p in self.root.glob("seq-*") if p.is_dir())
            hint = f"; pass one of its sequence folders ({', '.join(seqs)})" if seqs else ""
            raise SourceError(f"{self.root}: no frame-%06d.depth.png / .color.png / .pose.txt files found{hint}")
        if not has_numbered_file(self.root, POSE_PATTERN):
            raise SourceError(f"{self.root}: no frame-%06d.pose.txt files; 7-Scenes frames need their poses")
        K = configured_intrinsics(cfg)
        if K is None:
            K = find_intrinsics(self.root)
        if K is None:
            log.warning(
                "%s: no %s here or in the parent folder; using the 7-Scenes Kinect defaults "
                "fx = fy = 585, cx = 320, cy = 240 (set source.intrinsics to override)",
                self.root,
                INTRINSICS_FILE,
            )
            K = DEFAULT_K
        self.K = K
        self.scale_m = depth_scale_m(cfg, DEPTH_SCALE_M)

    @staticmethod
    def looks_like(path: Path) -> bool:
        """frame-%06d.depth.png images in the folder."""
        return has_numbered_file(Path(path), DEPTH_PATTERN)

    def keys(self) -> Sequence[Hashable]:
        return self.ids

    def load(self, position: int, key: Hashable) -> RgbdFrame:
        assert isinstance(key, int)
        stem = self.root / f"frame-{key:06d}"
        color_path = stem.with_name(stem.name + ".color.png")
        if not color_path.is_file() and stem.with_name(stem.name + ".color.jpg").is_file():
            color_path = stem.with_name(stem.name + ".color.jpg")
        depth_path = stem.with_name(stem.name + ".depth.png")
        T = read_pose_file(stem.with_name(stem.name + ".pose.txt"))
        return numbered_frame(position, key, color_path, depth_path, self.scale_m, self.K, T, invalid=INVALID_DEPTH)
