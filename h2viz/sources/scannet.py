"""ScanNet as exported by its SensReader: color/%d.jpg, depth/%d.png (mm), pose/%d.txt (4x4
camera-to-world) and intrinsic/intrinsic_depth.txt (4x4, the top-left 3x3 is K of the depth camera).

Colour is resized onto the depth image (cv2 INTER_AREA). Frames whose pose holds inf/NaN (tracking
lost) are skipped and counted. The export has no timestamps: frame number / 30 s (the sensor's rate).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from pathlib import Path

from h2viz.config import SourceConfig
from h2viz.errors import SourceError
from h2viz.sources.folders import (
    NumberedSource,
    configured_intrinsics,
    depth_scale_m,
    has_numbered_file,
    numbered_files,
    numbered_frame,
    read_intrinsics_file,
    read_pose_file,
    require_folder,
)
from h2viz.types import RgbdFrame

DEPTH_SCALE_M = 1.0 / 1000.0
COLOR_PATTERN = r"(\d+)\.jpg"
DEPTH_PATTERN = r"(\d+)\.png"


class ScanNetSource(NumberedSource):
    """ScanNet scans (depth / 1000 m, colour resized to the depth size, frames sorted numerically)."""

    format_name = "scannet"

    def __init__(self, cfg: SourceConfig) -> None:
        super().__init__(cfg)
        self.root = require_folder(cfg.path, "ScanNet")
        self.colors = numbered_files(self.root / "color", COLOR_PATTERN)
        self.depths = numbered_files(self.root / "depth", DEPTH_PATTERN)
        self.ids = sorted(set(self.colors) | set(self.depths))
        if not self.ids:
            raise SourceError(f"{self.root}: no color/<n>.jpg or depth/<n>.png images found")
        if not (self.root / "pose").is_dir():
            raise SourceError(f"{self.root / 'pose'}: pose folder is missing; ScanNet needs pose/<n>.txt files")
        K = configured_intrinsics(cfg)
        if K is None:
            K = read_intrinsics_file(self.root / "intrinsic" / "intrinsic_depth.txt", (4, 4))
        self.K = K
        self.scale_m = depth_scale_m(cfg, DEPTH_SCALE_M)

    @staticmethod
    def looks_like(path: Path) -> bool:
        """color/<n>.jpg and depth/<n>.png images plus a pose/ folder."""
        root = Path(path)
        return (
            (root / "pose").is_dir()
            and has_numbered_file(root / "color", COLOR_PATTERN)
            and has_numbered_file(root / "depth", DEPTH_PATTERN)
        )

    def keys(self) -> Sequence[Hashable]:
        return self.ids

    def load(self, position: int, key: Hashable) -> RgbdFrame:
        assert isinstance(key, int)
        # Names as listed (zero padding or not); the unpadded name when one of the pair is missing.
        color_path = self.colors.get(key, self.root / "color" / f"{key}.jpg")
        depth_path = self.depths.get(key, self.root / "depth" / f"{key}.png")
        stem = (self.depths.get(key) or color_path).stem
        T = read_pose_file(self.root / "pose" / f"{stem}.txt")
        return numbered_frame(position, key, color_path, depth_path, self.scale_m, self.K, T)
