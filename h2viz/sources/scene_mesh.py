"""Mesh primitives of the procedural room: grid-face boxes, flat quads and lathed solids, each a textured
part, collected by MeshBuilder into one trimesh.Trimesh with shading normals and part ids."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from h2viz.sources.scene_textures import Material, albedo

MAX_EDGE_M = 0.05  # longest grid edge, so vertex colours and baked light are fine enough
BOX_FACES = ("+x", "-x", "+y", "-y", "+z", "-z")
_BOX_GRIDS = {  # face -> (corner, u axis, v axis) in half-size units; u x v points out of the box
    "+x": ((1, -1, -1), (0, 2, 0), (0, 0, 2)),
    "-x": ((-1, -1, -1), (0, 0, 2), (0, 2, 0)),
    "+y": ((-1, 1, -1), (0, 0, 2), (2, 0, 0)),
    "-y": ((-1, -1, -1), (2, 0, 0), (0, 0, 2)),
    "+z": ((-1, -1, 1), (2, 0, 0), (0, 2, 0)),
    "-z": ((-1, -1, -1), (0, 2, 0), (2, 0, 0)),
}


def rot_z(yaw_rad: float) -> np.ndarray:
    """Rotation (3,3) about the world z axis."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def grid_quad(corner: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Regular grid over the parallelogram corner + a*u + b*v (a, b in [0, 1]) with edges <= MAX_EDGE_M.
    Returns vertices (N,3) and faces (M,3) wound so that u x v is the outward normal."""
    nu = max(1, int(np.ceil(np.linalg.norm(u) / MAX_EDGE_M)))
    nv = max(1, int(np.ceil(np.linalg.norm(v) / MAX_EDGE_M)))
    a, b = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    verts = corner + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    v00 = (i * (nv + 1) + j).ravel()
    v10, v01 = v00 + nv + 1, v00 + 1
    faces = np.concatenate([np.stack([v00, v10, v10 + 1], 1), np.stack([v00, v10 + 1, v01], 1)])
    return verts, faces


def resample_polyline(points: np.ndarray) -> np.ndarray:
    """Insert points so that no segment of the polyline (K,2) is longer than MAX_EDGE_M."""
    out = [points[:1]]
    for p, q in zip(points[:-1], points[1:], strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(q - p) / MAX_EDGE_M)))
        out.append(p + (q - p) * np.linspace(0, 1, n + 1)[1:, None])
    return np.concatenate(out)


def lathe(profile_rz: np.ndarray, n_seg: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface of revolution about +z of a (K,2) polyline of (radius, z), bottom to top.
    Returns vertices (N,3), faces (M,3) and smooth outward vertex normals (N,3)."""
    rz = resample_polyline(np.asarray(profile_rz, dtype=np.float64))
    k = len(rz)
    phi = np.linspace(0.0, 2.0 * np.pi, n_seg + 1)
    r, z = rz[:, 0:1], rz[:, 1:2]
    verts = np.stack([r * np.cos(phi), r * np.sin(phi), np.broadcast_to(z, (k, n_seg + 1))], -1)
    dr, dz = np.gradient(rz[:, 0]), np.gradient(rz[:, 1])
    length = np.hypot(dr, dz)[:, None] + 1e-12
    nr, nz = (dz[:, None] / length), (-dr[:, None] / length)
    normals = np.stack([nr * np.cos(phi), nr * np.sin(phi), np.broadcast_to(nz, (k, n_seg + 1))], -1)
    i, j = np.meshgrid(np.arange(k - 1), np.arange(n_seg), indexing="ij")
    v00 = (i * (n_seg + 1) + j).ravel()
    v01, v10 = v00 + 1, v00 + n_seg + 1
    faces = np.concatenate([np.stack([v00, v01, v10 + 1], 1), np.stack([v00, v10 + 1, v10], 1)])
    return verts.reshape(-1, 3), faces, normals.reshape(-1, 3)


@dataclass
class PartTable:
    """Per-part texture frame and parameters; a part is one primitive with one material."""

    material: list[int] = field(default_factory=list)
    rotation: list[np.ndarray] = field(default_factory=list)  # (3,3) part -> world
    origin: list[np.ndarray] = field(default_factory=list)  # (3,) part origin in world
    color_a: list[tuple[float, float, float]] = field(default_factory=list)
    color_b: list[tuple[float, float, float]] = field(default_factory=list)
    size: list[np.ndarray] = field(default_factory=list)  # (3,) half extents (boxes) or (r, r, h)
    params: list[tuple[float, ...]] = field(default_factory=list)  # (4,) material specific
    occluder: list[bool] = field(default_factory=list)  # casts baked shadows


@dataclass
class Part:
    """How to colour one primitive."""

    material: Material
    color_a: tuple[float, float, float]
    color_b: tuple[float, float, float] = (0.5, 0.5, 0.5)
    params: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)
    occluder: bool = True


class MeshBuilder:
    """Collects primitives (vertices, faces, shading normals, part ids) and their part table."""

    def __init__(self) -> None:
        self.verts: list[np.ndarray] = []
        self.faces: list[np.ndarray] = []
        self.normals: list[np.ndarray] = []
        self.face_part: list[np.ndarray] = []
        self.vert_part: list[np.ndarray] = []
        self.parts = PartTable()
        self.n_verts = 0

    def _new_part(self, part: Part, R: np.ndarray, origin: np.ndarray, size: np.ndarray) -> int:
        t = self.parts
        t.material.append(int(part.material))
        t.rotation.append(R)
        t.origin.append(np.asarray(origin, dtype=np.float64))
        t.color_a.append(part.color_a)
        t.color_b.append(part.color_b)
        t.size.append(np.asarray(size, dtype=np.float64))
        t.params.append(tuple(part.params) + (0.0,) * (4 - len(part.params)))
        t.occluder.append(part.occluder)
        return len(t.material) - 1

    def _append(self, verts: np.ndarray, faces: np.ndarray, normals: np.ndarray, pid: int) -> None:
        self.verts.append(verts)
        self.faces.append(faces + self.n_verts)
        self.normals.append(normals)
        self.face_part.append(np.full(len(faces), pid, dtype=np.int32))
        self.vert_part.append(np.full(len(verts), pid, dtype=np.int32))
        self.n_verts += len(verts)

    def quad(self, corner: np.ndarray, u: np.ndarray, v: np.ndarray, R: np.ndarray, part: Part) -> int:
        """A flat rectangle (walls, floor); its texture frame has origin `corner` and rotation R."""
        verts, faces = grid_quad(np.asarray(corner, float), np.asarray(u, float), np.asarray(v, float))
        pid = self._new_part(part, R, corner, np.array([np.linalg.norm(u), np.linalg.norm(v), 0.0]))
        n = np.cross(u, v) / np.linalg.norm(np.cross(u, v))
        self._append(verts, faces, np.broadcast_to(n, verts.shape), pid)
        return pid

    def box(
        self, center: np.ndarray, size: np.ndarray, yaw: float, part: Part, omit: tuple[str, ...] = ()
    ) -> int:
        """An axis-aligned (then yawed) box; `omit` drops faces nobody can see (e.g. '-z' on the floor)."""
        R, half = rot_z(yaw), np.asarray(size, float) / 2.0
        center = np.asarray(center, float)
        pid = self._new_part(part, R, center, half)
        for name in BOX_FACES:
            if name in omit:
                continue
            c, u, v = (np.array(x, float) * half for x in _BOX_GRIDS[name])
            verts, faces = grid_quad(center + R @ c, R @ u, R @ v)
            n = np.cross(R @ u, R @ v)
            self._append(verts, faces, np.broadcast_to(n / np.linalg.norm(n), verts.shape), pid)
        return pid

    def solid(self, base: np.ndarray, pieces: list[np.ndarray], part: Part, n_seg: int = 48) -> int:
        """A lathed solid standing at `base`; each piece is a (K,2) (r, z) polyline with its own normals."""
        base = np.asarray(base, float)
        top = max(float(np.max(p[:, 1])) for p in pieces)
        r_max = max(float(np.max(p[:, 0])) for p in pieces)
        pid = self._new_part(part, np.eye(3), base, np.array([r_max, r_max, top]))
        n_seg = max(n_seg, int(np.ceil(2 * np.pi * r_max / MAX_EDGE_M)))
        for piece in pieces:
            verts, faces, normals = lathe(piece, n_seg)
            self._append(verts + base, faces, normals, pid)
        return pid

    def build(self) -> Geometry:
        """The merged mesh (degenerate faces dropped) with its shading normals and part ids."""
        verts, faces = np.concatenate(self.verts), np.concatenate(self.faces)
        tri = verts[faces]  # (F,3,3)
        area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        keep = area2 > 1e-10
        return Geometry(
            mesh=trimesh.Trimesh(verts, faces[keep], process=False, validate=False),
            normals=np.concatenate(self.normals).astype(np.float64),
            face_part=np.concatenate(self.face_part)[keep],
            vert_part=np.concatenate(self.vert_part),
            parts=PartArrays(self.parts),
        )


class PartArrays:
    """The part table as stacked arrays, indexed by part id."""

    def __init__(self, t: PartTable) -> None:
        self.material = np.array(t.material, dtype=np.int32)  # (P,)
        self.rotation = np.stack(t.rotation)  # (P,3,3)
        self.origin = np.stack(t.origin)  # (P,3)
        self.color_a = np.array(t.color_a, dtype=np.float64)  # (P,3)
        self.color_b = np.array(t.color_b, dtype=np.float64)  # (P,3)
        self.size = np.stack(t.size)  # (P,3)
        self.params = np.array(t.params, dtype=np.float64)  # (P,4)
        self.occluder = np.array(t.occluder, dtype=bool)  # (P,)

    def colors(self, points: np.ndarray, pid: np.ndarray) -> np.ndarray:
        """Albedo (N,3) in [0,1] of world points (N,3) on parts pid (N,)."""
        local = np.einsum("nji,nj->ni", self.rotation[pid], points - self.origin[pid])
        return albedo(self.material[pid], local, self.color_a[pid], self.color_b[pid], self.size[pid],
                      self.params[pid])


@dataclass
class Geometry:
    """Everything the builder produced: mesh, shading normals (N,3), face/vertex part ids, part table."""

    mesh: trimesh.Trimesh
    normals: np.ndarray  # (N,3) unit shading normals
    face_part: np.ndarray  # (F,) int32
    vert_part: np.ndarray  # (N,) int32
    parts: PartArrays
