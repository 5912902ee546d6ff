"""Rendered frames of the synthetic room kept on disk, so that the room plays like a recorded sequence.

Ray casting and shading a 640x480 frame takes ~0.2 s of one core: far slower than the 30 Hz camera the room
stands for. A real-time stream of it (the dashboard's Real-time toggle, `h2viz map --realtime`) would pass over
most frames, and every run would pay the renderer's CPU beside mapping. Each rendered frame is therefore written
once to a cache folder and read back (~4 ms) by every later run with the same room, image size and trajectory.

A frame is stored losslessly: the colour (H,W,3) uint8, and the depth's float32 bits differenced twice along
each row (about zero across a plane), each zstd-compressed (~0.36 MB a 640x480 frame, ~110 MB for the 300
default frames). The folder's name is a hash of everything the pixels depend on (the room's seed and recipe,
image size, field of view, number of frames, the renderer's source code and trimesh's version), so a change to any
of them renders afresh. Files are written atomically; an unreadable one is rendered again and replaced. Depth noise
is added after reading, as after rendering: a frame is the same whether it was rendered or read.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import struct
import threading
from pathlib import Path

import numpy as np
import torch
import trimesh
import zstandard

import h2viz
from h2viz.config import SyntheticConfig
from h2viz.sources.synthetic.layout import RECIPE

log = logging.getLogger("h2viz.sources")

FORMAT = 2  # bump when the file layout changes
MAGIC = b"H2SF"
HEADER = "<4sIIQ"  # magic, height, width, bytes of compressed colour; then the colour, then the depth
LEVEL = 9  # zstd level: ~30 ms to write a frame (rendering it took ~200), ~3 ms to read it back
ENV_DIR = "H2VIZ_CACHE_DIR"  # overrides the user cache folder (tests point it at a temporary one)
MASK_32 = 0xFFFFFFFF
_CODE = (*sorted(Path(__file__).parent.glob("*.py")), Path(__file__).parents[2] / "geometry.py")


def cache_root(configured: str = "") -> Path:
    """Where cached data lives: `configured`, else $H2VIZ_CACHE_DIR, else $XDG_CACHE_HOME/h2viz or ~/.cache/h2viz."""
    if configured:
        return Path(configured).expanduser()
    if os.environ.get(ENV_DIR):
        return Path(os.environ[ENV_DIR]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "h2viz"


def room_key(sc: SyntheticConfig) -> str:
    """A hash of everything a rendered frame's pixels depend on."""
    h = hashlib.sha256(f"{FORMAT} {sc.seed} {sc.width} {sc.height} {sc.fov_deg!r} {sc.n_frames}".encode())
    h.update(f"{trimesh.__version__} {h2viz.__version__}".encode())
    for path in _CODE:
        with contextlib.suppress(OSError):  # an install without sources: the package version stands for them
            h.update(path.read_bytes())
    h.update((Path(sc.recipe) if sc.recipe else RECIPE).read_bytes())  # readable: the scene was built from it
    return h.hexdigest()[:20]


def undo_row_differences(second: np.ndarray) -> np.ndarray:
    """The (H,W) uint32 whose second differences along each row (mod 2^32) are `second` (H,W) uint32: the depth's
    bits as written. Summed in torch, which releases the GIL while it sums: NumPy's cumsum holds it, and the mapping
    thread, which takes the GIL back after each of its hundreds of small kernels a frame, waited for it."""
    sums = torch.from_numpy(second.astype(np.int64))  # (H,W) a row's sums of values < 2^32 fit in 64 bits
    sums = torch.cumsum(sums, dim=1).bitwise_and_(MASK_32)  # first differences, mod 2^32
    sums = torch.cumsum(sums, dim=1).bitwise_and_(MASK_32)  # the bits
    return sums.numpy().astype(np.uint32)


class FrameCache:
    """The rendered (noise-free) frames of one room configuration, one file each in `folder`."""

    def __init__(self, folder: Path, height: int, width: int) -> None:
        self.folder, self.shape = folder, (height, width)
        self.writable = True  # False after a failed write: the run goes on rendering without the cache
        self._lock = threading.Lock()

    @classmethod
    def for_config(cls, sc: SyntheticConfig) -> FrameCache | None:
        """The cache for `sc`'s room (None when source.synthetic.cache is off)."""
        if not sc.cache:
            return None
        return cls(cache_root(sc.cache_dir) / "synthetic" / room_key(sc), sc.height, sc.width)

    def path(self, index: int) -> Path:
        return self.folder / f"{index:05d}.frame"

    def has(self, index: int) -> bool:
        return self.path(index).is_file()

    def get(self, index: int) -> tuple[np.ndarray, np.ndarray] | None:
        """rgb (H,W,3) uint8 and depth (H,W) float32 of frame `index`, or None when it is not cached (or its file
        cannot be read: it is rendered and written again)."""
        path = self.path(index)
        h, w = self.shape
        try:
            blob = path.read_bytes()
            magic, height, width, n_rgb = struct.unpack_from(HEADER, blob)
            if magic != MAGIC or (height, width) != (h, w):
                raise ValueError(f"not a {w}x{h} frame of this cache")
            start = struct.calcsize(HEADER)
            unpack = zstandard.ZstdDecompressor().decompress
            rgb = np.frombuffer(unpack(blob[start : start + n_rgb]), np.uint8).reshape(h, w, 3).copy()
            second = np.frombuffer(unpack(blob[start + n_rgb :]), np.uint32).reshape(h, w)
        except FileNotFoundError:
            return None
        except Exception as e:  # truncated, corrupt or from another layout: render it again
            log.info("cached synthetic frame %s cannot be read (%s); rendering it again", path, e)
            return None
        return rgb, undo_row_differences(second).view(np.float32)

    def put(self, index: int, rgb: np.ndarray, depth: np.ndarray) -> None:
        """Store frame `index` (rgb (H,W,3) uint8, depth (H,W) float32); a failed write turns the cache off for
        this run with one warning naming the folder."""
        if not self.writable:
            return
        bits = np.ascontiguousarray(depth, dtype=np.float32).view(np.uint32)  # (H,W)
        first = np.diff(bits, axis=1, prepend=np.uint32(0))  # wraps mod 2^32, exact once summed back
        second = np.diff(first, axis=1, prepend=np.uint32(0))  # ~0 along planes: depth is linear in x there
        pack = zstandard.ZstdCompressor(level=LEVEL).compress
        rgb_z = pack(np.ascontiguousarray(rgb, np.uint8).tobytes())
        depth_z = pack(second.tobytes())
        header = struct.pack(HEADER, MAGIC, *self.shape, len(rgb_z))
        path = self.path(index)
        tmp = path.with_name(f".{path.stem}.{os.getpid()}.{threading.get_ident()}.tmp")
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            tmp.write_bytes(header + rgb_z + depth_z)
            os.replace(tmp, path)
        except OSError as e:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            with self._lock:
                if self.writable:
                    self.writable = False
                    log.warning(
                        "cannot cache synthetic frames in %s (%s); frames are rendered each time they are read. "
                        "Set source.synthetic.cache_dir to a writable folder, or source.synthetic.cache=false",
                        self.folder,
                        e,
                    )
