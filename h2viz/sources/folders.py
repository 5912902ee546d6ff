"""Pieces shared by the dataset-folder sources (Replica, ScanNet, TUM RGB-D, 7-Scenes / 3DMatch):
intrinsics and depth-scale overrides, numbered-file listing, pose files and colour/depth alignment."""

from __future__ import annotations

import logging
import re
from collections.abc import Hashable
from pathlib import Path

import cv2
import numpy as np

from h2viz.config import SourceConfig
from h2viz.errors import FrameError, SourceError
from h2viz.sources.base import FrameSource, read_color, read_depth, read_matrix
from h2viz.types import RgbdFrame

log = logging.getLogger("h2viz.sources")

# Largest relative difference between the colour and depth aspect ratios that resizing may absorb
# (ScanNet's 1296x968 colour against its 640x480 depth differs by 0.4 %).
MAX_ASPECT_MISMATCH = 0.02
NUMBERED_FPS = 30.0  # numbered-file layouts carry no timestamps: file number / the sensors' rate


class NumberedSource(FrameSource):
    """A layout of numbered files whose keys are the file numbers (timestamp = number / NUMBERED_FPS)."""

    def timestamp(self, position: int, key: Hashable) -> float | None:
        return int(key) / NUMBERED_FPS  # type: ignore[call-overload]


def pinhole(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(3,3) pinhole intrinsics matrix."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def configured_intrinsics(cfg: SourceConfig) -> np.ndarray | None:
    """K (3,3) from `source.intrinsics` when fx and fy are set, else None."""
    i = cfg.intrinsics
    return pinhole(i.fx, i.fy, i.cx, i.cy) if i.is_set() else None


def depth_scale_m(cfg: SourceConfig, default_m: float) -> float:
    """Metres per depth unit: `source.depth_scale` when > 0, else the format's `default_m`."""
    return float(cfg.depth_scale) if cfg.depth_scale > 0 else default_m


def require_folder(path: str | Path, fmt: str) -> Path:
    """`path` as an existing directory, SourceError otherwise."""
    root = Path(path)
    if not root.is_dir():
        raise SourceError(f"{root}: the {fmt} source needs a dataset folder, and this is not a directory")
    return root


def numbered_files(folder: Path, pattern: str) -> dict[int, Path]:
    """Files in `folder` whose name fully matches `pattern` (one integer group), keyed by that integer."""
    regex = re.compile(pattern)
    if not folder.is_dir():
        return {}
    found: dict[int, Path] = {}
    for p in folder.iterdir():
        m = regex.fullmatch(p.name)
        if m is not None:
            found[int(m.group(1))] = p
    return found


def has_numbered_file(folder: Path, pattern: str) -> bool:
    """True when at least one file in `folder` fully matches `pattern` (cheap: stops at the first)."""
    if not folder.is_dir():
        return False
    regex = re.compile(pattern)
    return any(regex.fullmatch(p.name) for p in folder.iterdir())


def read_intrinsics_file(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """The top-left 3x3 of a `shape` intrinsics matrix file, SourceError naming the file when unusable."""
    try:
        K = read_matrix(path, shape)[:3, :3]
    except FrameError as e:
        raise SourceError(f"{e}; fix the file or set source.intrinsics (fx, fy, cx, cy)") from e
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise SourceError(f"{path}: intrinsics need finite values with fx, fy > 0; set source.intrinsics")
    return K


def read_pose_file(path: Path) -> np.ndarray:
    """A (4,4) camera-to-world matrix file, FrameError naming the file when missing or non-finite."""
    T = read_matrix(path, (4, 4))
    if not np.all(np.isfinite(T)):
        raise FrameError(f"{path}: pose contains inf/NaN (tracking lost); the frame is skipped")
    return T


def fit_color_to_depth(rgb: np.ndarray, depth_shape: tuple[int, int], color_path: Path) -> np.ndarray:
    """Resize colour (H,W,3) to the depth size (cv2 INTER_AREA when shrinking); FrameError when the
    aspect ratios differ too much for a resize to register them."""
    h, w = depth_shape
    ch, cw = rgb.shape[:2]
    if (ch, cw) == (h, w):
        return rgb
    if abs((cw / ch) / (w / h) - 1.0) > MAX_ASPECT_MISMATCH:
        raise FrameError(
            f"{color_path}: colour is {cw}x{ch} but depth is {w}x{h}; the aspect ratios differ, so the "
            "colour cannot be resized onto the depth. Use registered colour images"
        )
    interp = cv2.INTER_AREA if cw > w else cv2.INTER_LINEAR
    return cv2.resize(rgb, (w, h), interpolation=interp)


def numbered_frame(
    position: int,
    number: int,
    color_path: Path,
    depth_path: Path,
    scale_m: float,
    K: np.ndarray,
    T_world_camera: np.ndarray,
    invalid: int | None = None,
    fps: float = NUMBERED_FPS,
) -> RgbdFrame:
    """A frame of a numbered-file layout: depth in metres, colour fitted to the depth size,
    timestamp = file number / fps (these layouts carry no timestamps)."""
    depth_m = read_depth(depth_path, scale_m, invalid=invalid)
    rgb = fit_color_to_depth(read_color(color_path), depth_m.shape, color_path)
    return RgbdFrame(position, number / fps, rgb, depth_m, K, T_world_camera, name=str(depth_path))
