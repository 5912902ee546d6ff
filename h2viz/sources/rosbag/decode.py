"""Decoding of sensor_msgs/Image, sensor_msgs/CompressedImage (jpeg/png colour, compressedDepth) and
sensor_msgs/CameraInfo into NumPy colour (H,W,3) uint8, depth (H,W) float32 metres and K (3,3)."""

from __future__ import annotations

import struct
from typing import Any

import cv2
import numpy as np

from h2viz.errors import FrameError, SourceError

COLOR_ENCODINGS = {"rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8uc3"}
DEPTH_ENCODINGS = {"16uc1", "mono16", "32fc1"}
IMAGE_TYPES = {"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"}
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
_CHANNELS = {
    "rgb8": 3,
    "bgr8": 3,
    "8uc3": 3,
    "rgba8": 4,
    "bgra8": 4,
    "mono8": 1,
    "16uc1": 1,
    "mono16": 1,
    "32fc1": 1,
}
_DTYPES = {"16uc1": "u2", "mono16": "u2", "32fc1": "f4"}


def image_encoding(msg: Any) -> str:
    """Lower-case pixel encoding of an Image, or of a CompressedImage from its format string."""
    if hasattr(msg, "encoding"):
        return str(msg.encoding).lower()
    fmt = str(msg.format).lower()
    if "compresseddepth" in fmt:
        return (fmt.split(";")[0].strip() or "16uc1") if ";" in fmt else "16uc1"
    return "compressed"


def is_depth_message(msg: Any) -> bool:
    """True for 16UC1 / 32FC1 / mono16 images and compressedDepth images."""
    if hasattr(msg, "format"):
        return "compresseddepth" in str(msg.format).lower()
    return image_encoding(msg) in DEPTH_ENCODINGS


def image_size(msg: Any) -> tuple[int, int]:
    """(width, height) of an Image; a CompressedImage is decoded once to find out."""
    if hasattr(msg, "width"):
        return int(msg.width), int(msg.height)
    arr = _imdecode(_compressed_payload(msg), cv2.IMREAD_UNCHANGED, "image")
    return int(arr.shape[1]), int(arr.shape[0])


def _raw_pixels(msg: Any, topic: str) -> np.ndarray:
    """(H,W) or (H,W,C) array of an Image honouring `step` row padding and is_bigendian."""
    enc = image_encoding(msg)
    if enc not in _CHANNELS:
        raise FrameError(
            f"{topic}: image encoding '{msg.encoding}' is not supported (supported: rgb8, bgr8, rgba8, "
            "bgra8, mono8, 16UC1, mono16, 32FC1); choose another topic with source.rosbag.rgb_topic / "
            "source.rosbag.depth_topic"
        )
    h, w, c = int(msg.height), int(msg.width), _CHANNELS[enc]
    base = _DTYPES.get(enc, "u1")
    dtype = np.dtype((">" if msg.is_bigendian else "<") + base) if base != "u1" else np.dtype(np.uint8)
    row_bytes = w * c * dtype.itemsize
    step = int(msg.step) or row_bytes
    buf = np.frombuffer(memoryview(msg.data), dtype=np.uint8)
    if step < row_bytes or buf.size < step * (h - 1) + row_bytes:
        raise FrameError(
            f"{topic}: image data holds {buf.size} bytes, too few for {w}x{h} {enc} with step {step}"
        )
    if buf.size < step * h:  # the last row may come without its padding
        buf = np.concatenate([buf, np.zeros(step * h - buf.size, np.uint8)])
    rows = np.ascontiguousarray(buf[: step * h].reshape(h, step)[:, :row_bytes])  # (H, W*C*bytes)
    pixels = rows.view(dtype).reshape(h, w, c) if c > 1 else rows.view(dtype).reshape(h, w)
    return pixels.astype(dtype.newbyteorder("="), copy=False)


def _imdecode(data: bytes | np.ndarray, flags: int, topic: str) -> np.ndarray:
    arr = cv2.imdecode(np.frombuffer(memoryview(data), dtype=np.uint8), flags)
    if arr is None:
        raise FrameError(f"{topic}: compressed image cannot be decoded (corrupt data or unknown format)")
    return arr


def _compressed_payload(msg: Any) -> bytes:
    data = bytes(memoryview(msg.data))
    return data[12:] if "compresseddepth" in str(msg.format).lower() else data


def decode_color(msg: Any, topic: str) -> np.ndarray:
    """Colour (H,W,3) uint8 RGB from an Image or a jpeg/png CompressedImage."""
    if hasattr(msg, "format"):
        bgr = _imdecode(msg.data, cv2.IMREAD_COLOR, topic)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    enc = image_encoding(msg)
    if enc not in COLOR_ENCODINGS:
        raise FrameError(
            f"{topic}: '{msg.encoding}' is not a colour encoding (supported: rgb8, bgr8, rgba8, bgra8, "
            "mono8); choose the colour topic with source.rosbag.rgb_topic"
        )
    px = _raw_pixels(msg, topic)
    if enc == "mono8":
        return np.repeat(px[:, :, None], 3, axis=2)
    if enc in ("bgr8", "8uc3", "bgra8"):
        return np.ascontiguousarray(px[:, :, 2::-1])
    return np.ascontiguousarray(px[:, :, :3])


def _compressed_depth(msg: Any, topic: str, depth_scale: float) -> np.ndarray:
    """compressedDepth: a 12-byte header (int32 format, float32 quant A, B) then a 16-bit PNG."""
    fmt = str(msg.format).lower()
    if "rvl" in fmt:
        raise FrameError(
            f"{topic}: compressedDepth 'rvl' is not supported; record the png variant or raw depth"
        )
    data = bytes(memoryview(msg.data))
    if len(data) <= 12:
        raise FrameError(f"{topic}: compressedDepth message is too short ({len(data)} bytes)")
    raw = _imdecode(data[12:], cv2.IMREAD_UNCHANGED, topic)
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise FrameError(f"{topic}: compressedDepth payload is not a single-channel 16-bit PNG")
    if image_encoding(msg) == "32fc1":  # quantised inverse depth: d = A / (q - B), q = 0 invalid
        quant_a, quant_b = struct.unpack_from("<ff", data, 4)
        q = raw.astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.where(raw > 0, np.float32(quant_a) / (q - np.float32(quant_b)), 0.0)
        return depth.astype(np.float32)
    return raw.astype(np.float32) * np.float32(depth_scale)


def decode_depth(msg: Any, topic: str, depth_scale: float) -> np.ndarray:
    """Depth (H,W) float32 metres (0 = invalid): 16UC1/mono16 times depth_scale, 32FC1 as metres."""
    if hasattr(msg, "format"):
        if "compresseddepth" in str(msg.format).lower():
            return _compressed_depth(msg, topic, depth_scale)
        raw = _imdecode(msg.data, cv2.IMREAD_UNCHANGED, topic)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise FrameError(f"{topic}: compressed depth must be a 16-bit single-channel PNG")
        return raw.astype(np.float32) * np.float32(depth_scale)
    enc = image_encoding(msg)
    if enc not in DEPTH_ENCODINGS:
        raise FrameError(
            f"{topic}: '{msg.encoding}' is not a depth encoding (supported: 16UC1, mono16, 32FC1); "
            "choose the depth topic with source.rosbag.depth_topic"
        )
    px = _raw_pixels(msg, topic)
    if enc == "32fc1":
        depth = px.astype(np.float32)
        depth[~np.isfinite(depth)] = 0.0
        return depth
    return px.astype(np.float32) * np.float32(depth_scale)


def camera_info_K(msg: Any, topic: str) -> tuple[np.ndarray, int, int]:
    """(K (3,3), width, height) of a CameraInfo (ROS 1 field `K`, ROS 2 field `k`)."""
    k = getattr(msg, "k", None)
    k = getattr(msg, "K", None) if k is None else k
    K = np.asarray(k, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise SourceError(
            f"{topic}: CameraInfo has no valid intrinsics (fx={K[0, 0]}, fy={K[1, 1]}); "
            "set source.intrinsics.fx=... fy=... cx=... cy=..."
        )
    return K, int(msg.width), int(msg.height)


def fit_K(
    K: np.ndarray, info_size: tuple[int, int], image_size_wh: tuple[int, int], topic: str
) -> np.ndarray:
    """K for the image size: unchanged when sizes agree (or the CameraInfo has none), scaled when the
    image is an exact uniform scaling of the calibrated size; SourceError naming `topic` otherwise."""
    (wi, hi), (w, h) = info_size, image_size_wh
    if wi <= 0 or hi <= 0 or (wi, hi) == (w, h):
        return K
    s = w / wi
    if w * hi != h * wi or round(wi * s) != w or round(hi * s) != h:
        raise SourceError(
            f"{topic}: CameraInfo is for {wi}x{hi} images but the depth images are {w}x{h}; choose the "
            "CameraInfo of the depth camera with source.rosbag.camera_info_topic or set "
            "source.intrinsics.fx=... fy=... cx=... cy=..."
        )
    out = K.copy()
    out[0, 0] *= s
    out[1, 1] *= s
    out[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    out[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    return out


def match_color_size(rgb: np.ndarray, shape_hw: tuple[int, int], topic: str) -> np.ndarray:
    """Colour resized to the depth size when both share the aspect ratio; FrameError otherwise."""
    h, w = shape_hw
    hc, wc = rgb.shape[:2]
    if (hc, wc) == (h, w):
        return rgb
    if wc * h != hc * w:
        raise FrameError(
            f"{topic}: colour is {wc}x{hc} but depth is {w}x{h} (different aspect ratio); record colour "
            "registered to depth (e.g. aligned_depth_to_color) or choose other topics"
        )
    return cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
