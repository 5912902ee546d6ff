"""A compact binary glTF (GLB) writer for vertex-coloured triangle meshes: float positions, smooth
normals quantised to bytes (KHR_mesh_quantization), linear-light 8-bit vertex colours, 16-bit
indices when they fit, and one material whose alpha sets the opacity."""

from __future__ import annotations

import json
import struct

import numpy as np

_BYTE, _UBYTE, _UINT16, _UINT32, _FLOAT = 5120, 5121, 5123, 5125, 5126
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (N,3) float32 of a triangle mesh (N,3)/(M,3)."""
    v = vertices.astype(np.float32)
    tri = v[faces]  # (M,3,3)
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (M,3), length = 2 * area
    normals = np.zeros_like(v)
    for corner in range(3):
        np.add.at(normals, faces[:, corner], face_n)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.where(length > 0, normals / np.maximum(length, 1e-12), np.array([0, 0, 1], np.float32))


def srgb_to_linear_u8(colors: np.ndarray, alpha: float = 1.0) -> np.ndarray:
    """sRGB uint8 colours (N,3) as linear-light RGBA uint8 (N,4) (glTF COLOR_0 is linear)."""
    c = colors.astype(np.float32) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    rgba = np.concatenate([lin, np.full((len(c), 1), alpha, np.float32)], axis=1)
    return np.round(rgba * 255.0).astype(np.uint8)


def quantize_normals(normals: np.ndarray) -> np.ndarray:
    """Unit normals (N,3) as normalised int8 padded to 4 bytes a vertex (N,4)."""
    q = np.zeros((len(normals), 4), dtype=np.int8)
    q[:, :3] = np.round(np.clip(normals, -1.0, 1.0) * 127.0).astype(np.int8)
    return q


def _pad(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 4)


def mesh_glb(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, opacity: float = 1.0) -> bytes:
    """GLB bytes of one mesh: vertices (N,3) metres, faces (M,3), sRGB colours (N,3) uint8."""
    pos = np.ascontiguousarray(vertices, dtype=np.float32)
    n = len(pos)
    index_type = np.uint16 if n < 65536 else np.uint32
    idx = np.ascontiguousarray(faces, dtype=index_type).reshape(-1)
    normals = quantize_normals(vertex_normals(pos, faces))  # (N,4) int8
    parts = [pos.tobytes(), normals.tobytes(), srgb_to_linear_u8(colors).tobytes(), idx.tobytes()]
    views, offset = [], 0
    for i, blob in enumerate(parts):
        view = {"buffer": 0, "byteOffset": offset, "byteLength": len(blob)}
        view |= {"target": _ELEMENT_ARRAY_BUFFER} if i == 3 else {"target": _ARRAY_BUFFER}
        views.append(view | ({"byteStride": 4} if i == 1 else {}))
        offset += len(_pad(blob, b"\0"))
    accessors = [
        {"bufferView": 0, "componentType": _FLOAT, "count": n, "type": "VEC3", **_bounds(pos)},
        {"bufferView": 1, "componentType": _BYTE, "normalized": True, "count": n, "type": "VEC3"},
        {"bufferView": 2, "componentType": _UBYTE, "normalized": True, "count": n, "type": "VEC4"},
        {
            "bufferView": 3,
            "componentType": _UINT16 if index_type is np.uint16 else _UINT32,
            "count": len(idx),
            "type": "SCALAR",
        },
    ]
    material = {
        "pbrMetallicRoughness": {
            "baseColorFactor": [1, 1, 1, float(opacity)],
            "metallicFactor": 0.0,
            "roughnessFactor": 0.9,
        },
        "alphaMode": "BLEND" if opacity < 1.0 else "OPAQUE",
        "doubleSided": True,
    }
    gltf = {
        "asset": {"version": "2.0", "generator": "h2viz"},
        "extensionsUsed": ["KHR_mesh_quantization"],
        "extensionsRequired": ["KHR_mesh_quantization"],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [
            {
                "primitives": [
                    {"attributes": {"POSITION": 0, "NORMAL": 1, "COLOR_0": 2}, "indices": 3, "material": 0}
                ]
            }
        ],
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


def _bounds(pos: np.ndarray) -> dict[str, list[float]]:
    if len(pos) == 0:
        return {"min": [0.0, 0.0, 0.0], "max": [0.0, 0.0, 0.0]}
    return {"min": pos.min(axis=0).tolist(), "max": pos.max(axis=0).tolist()}
