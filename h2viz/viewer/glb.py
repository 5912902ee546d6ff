"""A compact binary glTF (GLB) writer for vertex-coloured triangle meshes, sized for streaming to viser:
positions quantised to 16 bits over the mesh's bounding box (KHR_mesh_quantization, undone by the node's
translation and scale: 12 um steps over a 0.8 m chunk), linear-light 8-bit vertex colours, 16-bit indices
when they fit, and one single-sided material whose alpha sets the opacity. Normals are not sent: viser's client
recomputes smooth vertex normals for every mesh it loads, into the NORMAL attribute the file declares. That
accessor has no data (glTF reads it as zeros; without it the loader would switch to flat shading) and is
FLOAT: three.js accumulates unnormalised face normals into the attribute's own array, and in an 8-bit one
they round to zero (black, speckled shading). About 16 bytes a vertex plus 6 a triangle.
"""

from __future__ import annotations

import json
import struct

import numpy as np

_UBYTE, _SHORT, _UINT16, _UINT32, _FLOAT = 5121, 5122, 5123, 5125, 5126
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


def _srgb_to_linear_table() -> np.ndarray:
    """(256,) uint8: the linear-light value of each 8-bit sRGB value (IEC 61966-2-1), rounded."""
    c = np.arange(256, dtype=np.float64) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return np.round(lin * 255.0).astype(np.uint8)


_SRGB_TO_LINEAR = _srgb_to_linear_table()


def srgb_to_linear_u8(colors: np.ndarray, alpha: float = 1.0) -> np.ndarray:
    """sRGB uint8 colours (N,3) as linear-light RGBA uint8 (N,4) (glTF COLOR_0 is linear)."""
    rgba = np.empty((len(colors), 4), dtype=np.uint8)
    rgba[:, :3] = _SRGB_TO_LINEAR[np.asarray(colors, dtype=np.uint8)]
    rgba[:, 3] = np.uint8(round(float(np.clip(alpha, 0.0, 1.0)) * 255.0))
    return rgba


def _pad(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 4)


def quantize_positions(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions (N,3) as normalised int16 (N,4) (padded to 8 bytes a vertex) with the translation (3,) and
    scale (3,) that map them back: p = translation + scale * q / 32767."""
    pos = np.asarray(vertices, dtype=np.float32)  # float32 arithmetic: 16-bit output, the dashboard thread's time
    axes = np.ascontiguousarray(pos.T)  # (3,N): reducing rows is ~20x faster than reducing axis 0 of (N,3)
    lo, hi = (axes.min(axis=1), axes.max(axis=1)) if len(pos) else (np.zeros(3), np.zeros(3))
    lo, hi = lo.astype(np.float64), hi.astype(np.float64)
    centre, half = (lo + hi) / 2.0, (hi - lo) / 2.0
    half = np.where(half > 0, half, 1.0)  # a flat axis: any scale maps q = 0 back to the centre
    axes -= centre.astype(np.float32)[:, None]
    axes *= (32767.0 / half).astype(np.float32)[:, None]
    np.clip(np.rint(axes, out=axes), -32767, 32767, out=axes)
    q = np.zeros((len(pos), 4), dtype=np.int16)
    q[:, :3] = axes.T
    return q, centre, half


def mesh_glb(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, opacity: float = 1.0) -> bytes:
    """GLB bytes of one mesh: vertices (N,3) metres, faces (M,3), sRGB colours (N,3) uint8."""
    q, centre, half = quantize_positions(vertices)
    n = len(q)
    index_type = np.uint16 if n < 65536 else np.uint32
    idx = np.ascontiguousarray(faces, dtype=index_type).reshape(-1)
    parts = [q.tobytes(), srgb_to_linear_u8(colors).tobytes(), idx.tobytes()]
    views, offset = [], 0
    for i, blob in enumerate(parts):
        view = {"buffer": 0, "byteOffset": offset, "byteLength": len(blob)}
        view |= {"target": _ELEMENT_ARRAY_BUFFER} if i == 2 else {"target": _ARRAY_BUFFER}
        views.append(view | ({"byteStride": 8} if i == 0 else {}))
        offset += len(_pad(blob, b"\0"))
    accessors = [
        {"bufferView": 0, "componentType": _SHORT, "normalized": True, "count": n, "type": "VEC3", **_bounds(q)},
        {"bufferView": 1, "componentType": _UBYTE, "normalized": True, "count": n, "type": "VEC4"},
        {
            "bufferView": 2,
            "componentType": _UINT16 if index_type is np.uint16 else _UINT32,
            "count": len(idx),
            "type": "SCALAR",
        },
        {"componentType": _FLOAT, "count": n, "type": "VEC3"},  # no data (zeros): the client computes normals here
    ]
    material = {
        "pbrMetallicRoughness": {
            "baseColorFactor": [1, 1, 1, float(opacity)],
            "metallicFactor": 0.0,
            "roughnessFactor": 0.9,
        },
        "alphaMode": "BLEND" if opacity < 1.0 else "OPAQUE",
        "doubleSided": False,  # faces point into free space: from outside a room, its near walls are not drawn
    }
    primitive = {"attributes": {"POSITION": 0, "NORMAL": 3, "COLOR_0": 1}, "indices": 2, "material": 0}
    gltf = {
        "asset": {"version": "2.0", "generator": "h2viz"},
        "extensionsUsed": ["KHR_mesh_quantization"],
        "extensionsRequired": ["KHR_mesh_quantization"],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": centre.tolist(), "scale": half.tolist()}],
        "meshes": [{"primitives": [primitive]}],
        "materials": [material],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": offset}],
    }
    json_chunk = _pad(json.dumps(gltf, separators=(",", ":")).encode(), b" ")
    bin_chunk = b"".join(_pad(p, b"\0") for p in parts)
    total = 12 + 8 + len(json_chunk) + 8 + len(bin_chunk)
    return b"".join(
        [
            struct.pack("<4sII", b"glTF", 2, total),
            struct.pack("<I4s", len(json_chunk), b"JSON"),
            json_chunk,
            struct.pack("<I4s", len(bin_chunk), b"BIN\0"),
            bin_chunk,
        ]
    )


def _bounds(q: np.ndarray) -> dict[str, list[int]]:
    """POSITION's required min / max (of the stored int16 values)."""
    if len(q) == 0:
        return {"min": [0, 0, 0], "max": [0, 0, 0]}
    axes = np.ascontiguousarray(q[:, :3].T)  # (3,N): see quantize_positions
    return {"min": axes.min(axis=1).tolist(), "max": axes.max(axis=1).tolist()}
