"""The procedural indoor scene: built once per seed (cached), ray cast with Embree, lit by light baked
per vertex (sun with soft shadows, fill light, ambient occlusion) and coloured procedurally at the hits.

Colour is a function of the surface point only: albedo(point, part) x baked light interpolated over the
triangle, so a view-independent colour field can fit every image exactly.
"""

from __future__ import annotations

import threading
from functools import lru_cache

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from trimesh.ray.ray_pyembree import RayMeshIntersector

from h2viz.geometry import camera_rays
from h2viz.sources.synthetic.layout import layout, load_recipe
from h2viz.sources.synthetic.mesh import Geometry

BACKGROUND_RGB = np.array([226, 232, 240], dtype=np.uint8)  # what rays that leave the open-top room see
SUN_DIR = np.array([0.45, -0.35, 0.82]) / np.linalg.norm([0.45, -0.35, 0.82])
FILL_DIR = np.array([-0.5, 0.6, 0.35]) / np.linalg.norm([-0.5, 0.6, 0.35])
AO_RADIUS_M = 0.5  # occluders farther than this do not darken a point
N_AO, N_SUN = 16, 8  # rays per vertex for ambient occlusion and soft sun shadows


def _cone(axis: np.ndarray, n: int, half_angle_rad: float) -> np.ndarray:
    """n directions (n,3) spread evenly (golden spiral) inside a cone around a unit axis."""
    k = np.arange(n) + 0.5
    cos_t = 1.0 - (1.0 - np.cos(half_angle_rad)) * k / n
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    sin_t = np.sqrt(1.0 - cos_t**2)
    local = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], 1)
    ref = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(axis, ref)
    x /= np.linalg.norm(x)
    return local @ np.stack([x, np.cross(axis, x), axis])


def _hemisphere(normals: np.ndarray, n: int) -> np.ndarray:
    """n cosine-weighted directions (N,n,3) around each unit normal (N,3), rotated per vertex."""
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    phi = k * np.pi * (3.0 - np.sqrt(5.0)) + np.random.default_rng(0).uniform(0, 2 * np.pi, (len(normals), 1))
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.broadcast_to(np.sqrt(1 - r**2), phi.shape)], -1)
    ref = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    x = np.cross(normals, ref)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(normals, x)
    return local[..., :1] * x[:, None] + local[..., 1:2] * y[:, None] + local[..., 2:] * normals[:, None]


class Scene:
    """One built room: the mesh (with vertex colours), its parts and the ray caster."""

    def __init__(self, seed: int, geo: Geometry) -> None:
        self.seed = seed
        self.mesh = geo.mesh
        self.parts = geo.parts
        self.face_part = geo.face_part  # (F,)
        faces = np.asarray(geo.mesh.faces)  # (F,3)
        verts = np.asarray(geo.mesh.vertices, dtype=np.float64)  # (N,3)
        self._lock = threading.Lock()
        self._samples: tuple[cKDTree, np.ndarray] | None = None
        self._caster = RayMeshIntersector(geo.mesh)
        occ = self.parts.occluder[geo.face_part]
        self._occluders = RayMeshIntersector(trimesh.Trimesh(verts, faces[occ], process=False))
        normal = np.asarray(geo.mesh.face_normals, dtype=np.float64)  # (F,3)
        corner0 = verts[faces[:, 0]]  # (F,3)
        self._plane = np.column_stack([normal, np.einsum("ij,ij->i", corner0, normal)])  # (F,4) n and n.a
        light = self._bake_light(verts, geo.normals)  # (N,)
        light_a, light_grad = _linear_on_faces(verts, faces, light)
        # (F,7) first corner, in-plane light gradient, light at the first corner
        self._face_light = np.column_stack([corner0, light_grad, light_a]).astype(np.float32)
        rgb = self.parts.colors(verts, geo.vert_part) * light[:, None]
        geo.mesh.visual.vertex_colors = _to_uint8(rgb)

    def surface_samples(self) -> tuple[cKDTree, np.ndarray]:
        """A KD-tree over dense points (N,3) sampled evenly on every surface (about 1.5 cm apart)."""
        with self._lock:
            if self._samples is None:
                n = int(self.mesh.area / 0.015**2)
                pts, _ = trimesh.sample.sample_surface(self.mesh, n, seed=self.seed)
                self._samples = (cKDTree(pts), pts)
            return self._samples

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Min and max corners (3,) of everything in the scene, metres."""
        lo, hi = self.mesh.bounds
        return lo.copy(), hi.copy()

    def first_hits(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Index (R,) of the first triangle each ray hits, -1 where it hits nothing."""
        with self._lock:  # Embree queries from several threads are serialised
            return self._caster.intersects_first(origins, dirs)

    def hit_t(self, origin: np.ndarray, dirs: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """Exact ray parameter t (N,) where rays origin (3,) or (N,3) + t * dirs (N,3) meet the planes of
        triangles tri (N,), in float64 (Embree itself is float32)."""
        plane = self._plane[tri]  # (N,4) normal and offset
        n = plane[:, :3]
        o_dot_n = np.einsum("ij,j->i", n, origin) if origin.ndim == 1 else np.einsum("ij,ij->i", origin, n)
        return (plane[:, 3] - o_dot_n) / np.einsum("ij,ij->i", dirs, n)

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First triangle (R,) hit by each ray (-1 = miss) and the hit parameter t (R,) along `dirs`
        (not normalised); NaN where nothing is hit."""
        tri = self.first_hits(origins, dirs)
        t = np.full(len(tri), np.nan)
        hit = tri >= 0
        t[hit] = self.hit_t(origins[hit], dirs[hit], tri[hit])
        return tri, t

    def shade(self, points: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """Colour (N,3) in [0,1] of surface points (N,3) lying on triangles tri (N,), grouped by part."""
        f = self._face_light[tri]  # (N,7)
        light = f[:, 6] + np.einsum("ij,ij->i", (points - f[:, :3]).astype(np.float32), f[:, 3:6])
        return self.parts.colors_grouped(points, self.face_part[tri]) * light[:, None]

    def render(
        self, K: np.ndarray, T_world_camera: np.ndarray, height: int, width: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """rgb (H,W,3) uint8 and z-depth (H,W) float32 in metres (0 = nothing hit) of a pinhole camera."""
        T = np.asarray(T_world_camera, dtype=np.float64)
        rays = _camera_dirs(np.asarray(K, np.float64).tobytes(), height, width)  # (R,3), camera z = 1
        dirs = np.einsum("ij,kj->ik", rays, T[:3, :3])  # (R,3) world directions
        tri = self.first_hits(np.broadcast_to(T[:3, 3], dirs.shape), dirs)
        hit = np.flatnonzero(tri >= 0)
        hit = hit[np.argsort(self.face_part[tri[hit]].astype(np.int16), kind="stable")]  # group by part
        tri, dirs = tri[hit], dirs[hit]
        t = self.hit_t(T[:3, 3], dirs, tri)  # the z-depth, since the camera z of every ray is 1
        rgb = np.broadcast_to(BACKGROUND_RGB, (height * width, 3)).copy()
        depth = np.zeros(height * width, dtype=np.float32)
        rgb[hit] = _to_uint8(self.shade(T[:3, 3] + t[:, None] * dirs, tri))
        depth[hit] = t
        return rgb.reshape(height, width, 3), depth.reshape(height, width)

    def _bake_light(self, verts: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Per-vertex light factor (N,): ambient x occlusion + sun x soft shadow + fill."""
        origins = verts + 2e-3 * normals
        faces = np.asarray(self.mesh.faces)
        occ = self._occlusion(origins, _hemisphere(normals, N_AO), self._caster, AO_RADIUS_M)
        ao = 1.0 - _smooth_on_mesh(occ, faces, 4)
        sun_dirs = np.broadcast_to(_cone(SUN_DIR, N_SUN, np.radians(6.0)), (len(origins), N_SUN, 3))
        shadow = self._occlusion(origins, sun_dirs, self._occluders, np.inf)
        sun = np.clip(normals @ SUN_DIR, 0.0, None) * (1.0 - _smooth_on_mesh(shadow, faces, 2))
        fill = np.clip(normals @ FILL_DIR, 0.0, None)
        return 0.5 * (0.3 + 0.7 * ao) + 0.55 * sun + 0.15 * fill * ao

    @staticmethod
    def _occlusion(
        origins: np.ndarray, dirs: np.ndarray, caster: RayMeshIntersector, radius: float
    ) -> np.ndarray:
        """Share (N,) of the unit directions (N,D,3) from origins (N,3) that hit within `radius`."""
        n, d = dirs.shape[:2]
        o = np.repeat(origins, d, axis=0)
        v = dirs.reshape(-1, 3)
        tri = caster.intersects_first(o, v)
        mesh = caster.mesh
        hit = tri >= 0
        dist = np.full(len(tri), np.inf)
        normal = mesh.face_normals[tri[hit]]
        v0 = mesh.vertices[mesh.faces[tri[hit], 0]]
        dist[hit] = np.einsum("ij,ij->i", v0 - o[hit], normal) / np.einsum("ij,ij->i", v[hit], normal)
        return (dist < radius).reshape(n, d).mean(axis=1)


def _smooth_on_mesh(values: np.ndarray, faces: np.ndarray, iterations: int) -> np.ndarray:
    """Average per-vertex values (N,) with their edge neighbours a few times (softens sampling noise)."""
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)  # (3F,2) directed edges
    n = len(values)
    count = np.bincount(e[:, 0], minlength=n) + np.bincount(e[:, 1], minlength=n)
    for _ in range(iterations):
        total = np.bincount(e[:, 0], values[e[:, 1]], n) + np.bincount(e[:, 1], values[e[:, 0]], n)
        values = 0.5 * values + 0.5 * total / np.maximum(count, 1)
    return values


@lru_cache(maxsize=8)
def _camera_dirs(K_bytes: bytes, height: int, width: int) -> np.ndarray:
    """Camera-frame ray directions (H*W,3) with z = 1 for the intrinsics K (3,3) given as bytes."""
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    dirs = camera_rays(K, height, width).reshape(-1, 3)
    dirs.flags.writeable = False
    return dirs


def _linear_on_faces(
    verts: np.ndarray, faces: np.ndarray, values: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-face value at the first corner (F,) and gradient (F,3) in the face plane, so that
    value(p) = a + (p - corner0) . grad interpolates the per-vertex `values` (N,) linearly."""
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    e1, e2 = b - a, c - a
    d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    den = (d11 * d22 - d12 * d12)[:, None]
    g1 = (d22[:, None] * e1 - d12[:, None] * e2) / den  # dual basis: g1.e1 = 1, g1.e2 = 0
    g2 = (d11[:, None] * e2 - d12[:, None] * e1) / den
    v0, v1, v2 = values[faces[:, 0]], values[faces[:, 1]], values[faces[:, 2]]
    return v0, (v1 - v0)[:, None] * g1 + (v2 - v0)[:, None] * g2


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)


@lru_cache(maxsize=4)
def build_scene(seed: int, recipe: str = "") -> Scene:
    """The room for `seed` painted from the recipe file `recipe` (empty: the packaged one), built once and then
    shared: same seed and recipe, same scene."""
    return Scene(seed, layout(seed, load_recipe(recipe)))
