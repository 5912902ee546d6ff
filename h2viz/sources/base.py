"""The FrameSource interface, the common options (stride, max frames, depth range, downscale),
format detection and `make_source`."""

from __future__ import annotations

import importlib
import logging
from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from h2viz.config import SourceConfig
from h2viz.errors import FrameError, SourceError
from h2viz.types import RgbdFrame

if TYPE_CHECKING:
    import trimesh

log = logging.getLogger("h2viz.sources")
Progress = Callable[[int, int], None] | None  # progress(done, total)
StopCheck = Callable[[], bool] | None  # True: end the work early


@dataclass(frozen=True)
class SkippedFrame:
    """A frame the source could not use, and why."""

    key: str
    reason: str


class FrameSource(ABC):
    """An ordered sequence of RGB-D frames. Subclasses list frame keys and load one key at a time;
    this base applies stride / max_frames / depth range / downscale and skips bad frames."""

    format_name: str = "?"

    def __init__(self, cfg: SourceConfig) -> None:
        self.cfg = cfg
        self.skipped: list[SkippedFrame] = []

    # -- to implement ------------------------------------------------------------------------------
    @abstractmethod
    def keys(self) -> Sequence[Hashable]:
        """Identifiers of every frame in order, before stride and max_frames."""

    @abstractmethod
    def load(self, position: int, key: Hashable) -> RgbdFrame:
        """Read one frame; raise FrameError (naming the file) when it cannot be used."""

    def ground_truth_mesh(self) -> trimesh.Trimesh | None:
        """The scene's ground-truth mesh when the source has one."""
        return None

    def timestamp(self, position: int, key: Hashable) -> float | None:
        """A frame's timestamp in seconds when the source knows it without loading the frame (None: only loading
        tells). Real-time playback passes over frames already overdue without reading them."""
        return None

    def describe(self) -> str:
        return f"{self.format_name} {self.cfg.path}"

    def prepare_playback(self, keys: Sequence[Hashable], progress: Progress = None, stop: StopCheck = None) -> None:
        """Before real-time playback of the frames of `keys`: make them readable at the stream's rate where reading
        one is slower than that (the synthetic room renders those it has not cached). `progress(done, total)`
        reports the work; `stop()` ends it early. Sources that read files have nothing to do."""
        return None

    # -- common behaviour --------------------------------------------------------------------------
    def selected(self) -> list[tuple[int, Hashable]]:
        """(position, key) pairs after stride and max_frames."""
        stride = max(1, self.cfg.stride)
        picked = list(enumerate(self.keys()))[::stride]
        return picked[: self.cfg.max_frames] if self.cfg.max_frames > 0 else picked

    def __len__(self) -> int:
        return len(self.selected())

    def __iter__(self) -> Iterator[RgbdFrame]:
        for position, key in self.selected():
            frame = self.get(position, key)
            if frame is not None:
                yield frame

    def get(self, position: int, key: Hashable) -> RgbdFrame | None:
        """Load and post-process one frame, or record why it was skipped and return None."""
        try:
            return self.postprocess(self.load(position, key))
        except FrameError as e:
            self.skip(str(key), str(e))
            return None

    def skip(self, key: str, reason: str) -> None:
        self.skipped.append(SkippedFrame(key, reason))
        log.warning("skipped %s: %s", key, reason)

    def postprocess(self, frame: RgbdFrame) -> RgbdFrame:
        """Clip depth to [depth_min_m, depth_max_m] (outside = 0) and apply the downscale factor."""
        depth = frame.depth_m.copy()
        depth[~np.isfinite(depth)] = 0.0
        depth[(depth < self.cfg.depth_min_m) | (depth > self.cfg.depth_max_m)] = 0.0
        rgb, K = frame.rgb, frame.K
        s = max(1, int(self.cfg.downscale))
        if s > 1:
            h, w = depth.shape[0] // s, depth.shape[1] // s
            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
            depth = shrink_depth(depth, s)
            K = K.copy()
            K[0, 0] /= s
            K[1, 1] /= s
            K[0, 2] = (K[0, 2] + 0.5) / s - 0.5
            K[1, 2] = (K[1, 2] + 0.5) / s - 0.5
        return replace(frame, rgb=rgb, depth_m=depth.astype(np.float32), K=K)


def shrink_depth(depth_m: np.ndarray, s: int) -> np.ndarray:
    """Depth (H,W) shrunk by s: the mean of each s x s block whose pixels are all valid and agree within 5 %
    (so no flying pixels appear across depth edges), else 0; it is the block centre's depth, like INTER_AREA colour."""
    h, w = depth_m.shape[0] // s, depth_m.shape[1] // s
    blocks = depth_m[: h * s, : w * s].reshape(h, s, w, s)  # (h,s,w,s)
    lo, hi = blocks.min(axis=(1, 3)), blocks.max(axis=(1, 3))
    ok = (lo > 0) & (hi - lo <= 0.05 * lo)
    return np.where(ok, blocks.mean(axis=(1, 3)), 0.0).astype(np.float32)


# ------------------------------------------------------------------------------------ registration


@dataclass(frozen=True)
class FormatInfo:
    name: str
    module: str  # module path holding the class
    cls: str  # class name
    looks_for: str  # what detection checks, for the "nothing matched" message


FORMATS: dict[str, FormatInfo] = {
    "synthetic": FormatInfo("synthetic", "h2viz.sources.synthetic", "SyntheticSource", "an empty path"),
    "replica": FormatInfo(
        "replica",
        "h2viz.sources.replica",
        "ReplicaSource",
        "results/frame000000.jpg + results/depth000000.png + traj.txt",
    ),
    "scannet": FormatInfo(
        "scannet",
        "h2viz.sources.scannet",
        "ScanNetSource",
        "color/, depth/, pose/ and intrinsic/intrinsic_depth.txt",
    ),
    "tum": FormatInfo("tum", "h2viz.sources.tum", "TumSource", "rgb.txt + depth.txt + groundtruth.txt"),
    "7scenes": FormatInfo(
        "7scenes",
        "h2viz.sources.sevenscenes",
        "SevenScenesSource",
        "frame-000000.depth.png + frame-000000.pose.txt",
    ),
    "rosbag": FormatInfo(
        "rosbag",
        "h2viz.sources.rosbag",
        "RosbagSource",
        "a .bag file, a .mcap/.db3 file or a folder with metadata.yaml",
    ),
}

Detector = Callable[[Path], bool]


def _detector(fmt: str) -> Detector:
    info = FORMATS[fmt]
    return getattr(importlib.import_module(info.module), info.cls).looks_like


def detect_format(path: str | Path) -> str:
    """Name of the layout at `path`; SourceError listing what was looked for when nothing matches."""
    if not str(path):
        return "synthetic"
    p = Path(path)
    if not p.exists():
        raise SourceError(f"{p} does not exist; pass a dataset folder or bag file to --data")
    for fmt in FORMATS:
        if fmt != "synthetic" and _detector(fmt)(p):
            return fmt
    looked = "\n".join(f"  - {f}: {i.looks_for}" for f, i in FORMATS.items() if f != "synthetic")
    raise SourceError(
        f"could not recognise the layout of {p}. Looked for:\n{looked}\nPass --format to choose one."
    )


def make_source(cfg: SourceConfig) -> FrameSource:
    """Open the source described by `cfg` (format 'auto' detects the layout)."""
    fmt = cfg.format.lower()
    if fmt == "auto":
        fmt = detect_format(cfg.path)
    if fmt not in FORMATS:
        raise SourceError(f"unknown format '{cfg.format}'; choose one of auto, {', '.join(FORMATS)}")
    if fmt != "synthetic" and not cfg.path:
        raise SourceError(f"format '{fmt}' needs a path; pass --data PATH")
    if cfg.path and not Path(cfg.path).exists():
        raise SourceError(f"{cfg.path} does not exist; pass a dataset folder or bag file to --data")
    info = FORMATS[fmt]
    cls = getattr(importlib.import_module(info.module), info.cls)
    return cls(replace(cfg, format=fmt))


def read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """Read a whitespace-separated matrix file, FrameError naming the file when it is malformed."""
    try:
        values = np.array(path.read_text().split(), dtype=np.float64)
    except FileNotFoundError as e:
        raise FrameError(f"{path}: file is missing") from e
    except (OSError, UnicodeDecodeError) as e:
        raise FrameError(f"{path}: file cannot be read as text ({e})") from e
    except ValueError as e:
        raise FrameError(f"{path}: not a whitespace-separated matrix of numbers") from e
    n = shape[0] * shape[1]
    if values.size < n:
        raise FrameError(
            f"{path}: expected {n} numbers for a {shape[0]}x{shape[1]} matrix, found {values.size}"
        )
    return values[:n].reshape(shape)


def read_color(path: Path) -> np.ndarray:
    """Colour image as (H,W,3) uint8 RGB, FrameError naming the file when unreadable."""
    if not path.is_file():
        raise FrameError(f"{path}: colour image is missing")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise FrameError(f"{path}: colour image cannot be decoded (corrupt or not an image)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: Path, scale_m: float, invalid: int | None = None) -> np.ndarray:
    """16-bit depth PNG as (H,W) float32 metres (0 = invalid), FrameError naming the file when unreadable."""
    if not path.is_file():
        raise FrameError(f"{path}: depth image is missing")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise FrameError(f"{path}: depth image cannot be decoded (corrupt or not an image)")
    if raw.ndim != 2:
        raise FrameError(f"{path}: depth must be a single-channel image, got {raw.shape[2]} channels")
    depth = raw.astype(np.float32) * np.float32(scale_m)
    if invalid is not None:
        depth[raw == invalid] = 0.0
    return depth
