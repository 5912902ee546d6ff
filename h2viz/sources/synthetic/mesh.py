"""Mesh primitives of the procedural room: grid-face boxes, flat quads and lathed solids, each a textured
part, collected by MeshBuilder into one trimesh.Trimesh with shading normals and part ids."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from h2viz.geometry import drop_unused_vertices
from h2viz.sources.synthetic.textures import Material, albedo

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


def _stops(length_m: float, cuts: np.ndarray) -> np.ndarray:
    """Sorted grid positions from 0 to 1: uniform steps <= MAX_EDGE_M plus the `cuts`; uniform stops
    within 2 mm of a cut give way to it, and the ends stay exactly 0 and 1."""
    tol = 2e-3 / length_m
    cuts = np.unique(cuts[(cuts > tol) & (cuts < 1 - tol)])
    cuts = cuts[np.concatenate([[True], np.diff(cuts) > tol])] if len(cuts) else cuts
    inner = np.linspace(0, 1, max(1, int(np.ceil(length_m / MAX_EDGE_M))) + 1)[1:-1]
    if len(cuts):
        inner = inner[np.min(np.abs(inner[:, None] - cuts[None, :]), axis=1) > tol]
    return np.sort(np.concatenate([[0.0], inner, cuts, [1.0]]))


def grid_quad(
    corner: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    cuts_u: np.ndarray | None = None,
    cuts_v: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Grid over the parallelogram corner + a*u + b*v (a, b in [0, 1]) with edges <= MAX_EDGE_M and extra
    grid lines at the fractions `cuts_u`, `cuts_v`. Returns vertices (N,3) and faces (M,3) wound so
    that u x v is the outward normal."""
    empty = np.zeros(0)
    sa = _stops(float(np.linalg.norm(u)), empty if cuts_u is None else cuts_u)
    sb = _stops(float(np.linalg.norm(v)), empty if cuts_v is None else cuts_v)
    nu, nv = len(sa) - 1, len(sb) - 1
    a, b = np.meshgrid(sa, sb, indexing="ij")
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
        self.solid_boxes: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []  # owner, centre, R, half
        self.solid_discs: list[tuple[int, np.ndarray, float]] = []  # owner, base centre, radius
        self.flats: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []  # corner, u, v, part

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
        pid = self._new_part(part, R, corner, np.array([np.linalg.norm(u), np.linalg.norm(v), 0.0]))
        self.flats.append((np.asarray(corner, float), np.asarray(u, float), np.asarray(v, float), pid))
        return pid

    def box(self, center: np.ndarray, size: np.ndarray, yaw: float, part: Part) -> int:
        """A box of full `size` (3,) about `center`, turned by `yaw` about z; it is also a solid that
        buries the surfaces of other parts it touches or encloses."""
        R, half = rot_z(yaw), np.asarray(size, float) / 2.0
        center = np.asarray(center, float)
        pid = self._new_part(part, R, center, half)
        self.solid_boxes.append((pid, center, R, half))
        for name in BOX_FACES:
            c, u, v = (np.array(x, float) * half for x in _BOX_GRIDS[name])
            self.flats.append((center + R @ c, R @ u, R @ v, pid))
        return pid

    def _grid_flats(self) -> None:
        """Mesh every flat face, with extra grid lines where other solids touch it, so that the part of
        a face hidden by a solid (the floor under a cabinet...) is cut out along the contact edge."""
        boxes = self.solid_boxes
        signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, 8).T  # (8,3)
        corners = np.stack([c + (signs * h) @ R.T for _, c, R, h in boxes])  # (S,8,3)
        owners = np.array([o for o, *_ in boxes])
        for corner, u, v, pid in self.flats:
            n = np.cross(u, v)
            n /= np.linalg.norm(n)
            rel = corners - corner  # (S,8,3)
            dist, a, b = rel @ n, rel @ u / (u @ u), rel @ v / (v @ v)  # (S,8) each
            touch = (dist.min(1) <= 2e-3) & (dist.max(1) > 2e-3) & (owners != pid)
            touch &= (a.max(1) > 0) & (a.min(1) < 1) & (b.max(1) > 0) & (b.min(1) < 1)
            cuts_u = np.concatenate([a[touch].min(1), a[touch].max(1)])
            cuts_v = np.concatenate([b[touch].min(1), b[touch].max(1)])
            verts, faces = grid_quad(corner, u, v, cuts_u, cuts_v)
            self._append(verts, faces, np.broadcast_to(n, verts.shape), pid)

    def slab(self, owner: int, lo: np.ndarray, hi: np.ndarray) -> None:
        """An invisible solid box [lo, hi] belonging to part `owner` (the ground or a wall's outside)."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        self.solid_boxes.append((owner, (lo + hi) / 2, np.eye(3), (hi - lo) / 2))

    def solid(
        self, base: np.ndarray, pieces: list[np.ndarray], part: Part, n_seg: int = 48, foot_m: float = 0.0
    ) -> int:
        """A lathed solid standing at `base`; each piece is a (K,2) (r, z) polyline with its own normals.
        `foot_m` > 0: the disc of that radius under it buries what it stands on."""
        base = np.asarray(base, float)
        top = max(float(np.max(p[:, 1])) for p in pieces)
        r_max = max(float(np.max(p[:, 0])) for p in pieces)
        pid = self._new_part(part, np.eye(3), base, np.array([r_max, r_max, top]))
        if foot_m > 0:
            self.solid_discs.append((pid, base, foot_m))
        n_seg = max(n_seg, int(np.ceil(2 * np.pi * r_max / MAX_EDGE_M)))
        for piece in pieces:
            verts, faces, normals = lathe(piece, n_seg)
            self._append(verts + base, faces, normals, pid)
        return pid

    def buried(
        self, verts: np.ndarray, faces: np.ndarray, vert_part: np.ndarray, eps_m: float = 2e-3
    ) -> np.ndarray:
        """Faces (F,) hidden inside one solid of another part: all three corners inside (or on) it and
        the face looking into it, like the floor under a cabinet or the back of a picture on a wall.
        A face on a solid's surface that looks away from it (coplanar neighbours) stays."""
        tri = verts[faces]  # (F,3,3)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        probe = tri.mean(axis=1) + 3e-3 * normal / (np.linalg.norm(normal, axis=1, keepdims=True) + 1e-20)
        out = np.zeros(len(faces), dtype=bool)
        order = np.argsort(verts[:, 0])
        xs = verts[order, 0]
        inside = np.zeros(len(verts), dtype=bool)
        solids = [(o, c, R, h, np.inf) for o, c, R, h in self.solid_boxes]
        solids += [
            (o, c + [0, 0, 5e-3], np.eye(3), np.array([r, r, 5e-3]), r) for o, c, r in self.solid_discs
        ]
        for owner, center, R, half, radius in solids:
            reach = float(np.abs(R[0]) @ half) + eps_m  # half extent of the solid along world x
            idx = order[
                np.searchsorted(xs, center[0] - reach) : np.searchsorted(xs, center[0] + reach, "right")
            ]
            local = (verts[idx] - center) @ R  # (n,3) in the solid's frame
            ok = np.all(np.abs(local) <= half + eps_m, axis=1) & (vert_part[idx] != owner)
            inside[idx] = ok & (np.hypot(local[:, 0], local[:, 1]) <= radius + eps_m)
            cand = np.flatnonzero(np.all(inside[faces], axis=1))
            p = (probe[cand] - center) @ R
            out[cand] |= np.all(np.abs(p) < half, axis=1) & (np.hypot(p[:, 0], p[:, 1]) < radius)
            inside[idx] = False
        return out

    def build(self) -> Geometry:
        """The merged mesh with buried and degenerate faces dropped, its shading normals and part ids."""
        self._grid_flats()
        verts, faces = np.concatenate(self.verts), np.concatenate(self.faces)
        vert_part = np.concatenate(self.vert_part)
        tri = verts[faces]  # (F,3,3)
        area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        keep = (area2 > 1e-10) & ~self.buried(verts, faces, vert_part)
        used, kept_faces = drop_unused_vertices(len(verts), faces[keep])
        return Geometry(
            mesh=trimesh.Trimesh(verts[used], kept_faces, process=False, validate=False),
            normals=np.concatenate(self.normals)[used].astype(np.float64),
            face_part=np.concatenate(self.face_part)[keep],
            vert_part=vert_part[used],
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
        self._float32 = [x.astype(np.float32) for x in (self.color_a, self.color_b, self.size, self.params)]

    def colors(self, points: np.ndarray, pid: np.ndarray) -> np.ndarray:
        """Albedo (N,3) in [0,1] of world points (N,3) on parts pid (N,)."""
        order = np.argsort(pid.astype(np.int16), kind="stable")
        out = np.empty((len(points), 3), dtype=np.float64)
        out[order] = self.colors_grouped(points[order], pid[order])
        return out

    def colors_grouped(self, points: np.ndarray, pid: np.ndarray) -> np.ndarray:
        """Like `colors` for points already grouped by part (pid sorted), one slice per part."""
        out = np.empty((len(points), 3), dtype=np.float64)
        starts = np.flatnonzero(np.diff(pid, prepend=-1))
        for lo, hi in zip(starts, np.append(starts[1:], len(pid)), strict=True):
            k = int(pid[lo])
            local = np.einsum(
                "ij,jk->ik", points[lo:hi] - self.origin[k], self.rotation[k]
            )  # (n,3) part frame
            out[lo:hi] = albedo(
                Material(self.material[k]), local.astype(np.float32), *(x[k] for x in self._float32)
            )
        return out


@dataclass
class Geometry:
    """Everything the builder produced: mesh, shading normals (N,3), face/vertex part ids, part table."""

    mesh: trimesh.Trimesh
    normals: np.ndarray  # (N,3) unit shading normals
    face_part: np.ndarray  # (F,) int32
    vert_part: np.ndarray  # (N,) int32
    parts: PartArrays
