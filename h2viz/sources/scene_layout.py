"""The room recipe: a 5 x 4 m living room with 2.6 m walls (z up, floor at z = 0, centred on the origin)
and furniture placed, sized and coloured from a seed. The room has no ceiling, so the map can be
looked into from above. Furniture along the walls stands flush against them (its back and the wall
behind it are buried, see MeshBuilder.buried) and tall things stay out of the middle, where the
camera walks."""

from __future__ import annotations

from typing import TypeVar

import numpy as np

from h2viz.sources.scene_mesh import Geometry, MeshBuilder, Part
from h2viz.sources.scene_textures import Material as M

ROOM_X_M, ROOM_Y_M, ROOM_HEIGHT_M = 5.0, 4.0, 2.6
HX, HY = ROOM_X_M / 2, ROOM_Y_M / 2

Color = tuple[float, float, float]
T = TypeVar("T")
WALL_PAINTS: list[tuple[Color, Color]] = [  # (upper paint, wainscot)
    ((0.92, 0.89, 0.82), (0.55, 0.66, 0.60)),
    ((0.86, 0.89, 0.90), (0.38, 0.48, 0.60)),
    ((0.93, 0.86, 0.80), (0.70, 0.52, 0.45)),
    ((0.90, 0.90, 0.84), (0.78, 0.70, 0.55)),
]
FLOOR_WOODS: list[Color] = [(0.74, 0.55, 0.36), (0.62, 0.43, 0.27), (0.80, 0.67, 0.50)]
RUGS: list[Color] = [(0.62, 0.20, 0.18), (0.18, 0.30, 0.52), (0.28, 0.46, 0.36)]
SOFAS: list[Color] = [(0.25, 0.40, 0.56), (0.55, 0.55, 0.52), (0.58, 0.32, 0.24), (0.36, 0.46, 0.33)]
FURNITURE_WOODS: list[Color] = [(0.48, 0.30, 0.16), (0.66, 0.48, 0.30), (0.36, 0.22, 0.13)]
CHAIR_PAINTS: list[Color] = [(0.92, 0.90, 0.84), (0.20, 0.22, 0.25), (0.80, 0.58, 0.22), (0.45, 0.60, 0.62)]
CERAMICS: list[tuple[Color, Color]] = [
    ((0.20, 0.35, 0.60), (0.92, 0.90, 0.84)),
    ((0.75, 0.35, 0.20), (0.95, 0.85, 0.60)),
    ((0.25, 0.50, 0.45), (0.90, 0.88, 0.80)),
]
CARDBOARD: Color = (0.70, 0.54, 0.36)
METAL: Color = (0.22, 0.22, 0.24)
LAMPSHADE: Color = (0.95, 0.90, 0.78)


def _pick(rng: np.random.Generator, options: list[T]) -> T:
    return options[int(rng.integers(len(options)))]


def _room(b: MeshBuilder, rng: np.random.Generator, rug: tuple[float, float, float, float]) -> None:
    """Floor with a rug and four inward-facing walls, each backed by a solid slab outside the room."""
    rug_prm = (rug[0] + HX, rug[1] + HY, rug[2], rug[3])
    floor = Part(M.FLOOR, _pick(rng, FLOOR_WOODS), _pick(rng, RUGS), rug_prm, occluder=False)
    fid = b.quad(
        np.array([-HX, -HY, 0.0]), np.array([ROOM_X_M, 0, 0]), np.array([0, ROOM_Y_M, 0]), np.eye(3), floor
    )
    b.slab(fid, [-HX - 0.2, -HY - 0.2, -0.2], [HX + 0.2, HY + 0.2, 0.0])
    paint, wainscot = _pick(rng, WALL_PAINTS)
    up = np.array([0.0, 0.0, ROOM_HEIGHT_M])
    walls = [  # corner, along-wall vector (u x up points into the room), outside slab lo, hi
        ((HX, -HY), (-ROOM_X_M, 0), (-HX - 0.2, -HY - 0.2), (HX + 0.2, -HY)),
        ((-HX, HY), (ROOM_X_M, 0), (-HX - 0.2, HY), (HX + 0.2, HY + 0.2)),
        ((-HX, -HY), (0, ROOM_Y_M), (-HX - 0.2, -HY - 0.2), (-HX, HY + 0.2)),
        ((HX, HY), (0, -ROOM_Y_M), (HX, -HY - 0.2), (HX + 0.2, HY + 0.2)),
    ]
    for corner, along, lo, hi in walls:
        u = np.array([along[0], along[1], 0.0])
        inward = np.cross(u, up) / np.linalg.norm(np.cross(u, up))
        R = np.stack([u / np.linalg.norm(u), inward, [0.0, 0.0, 1.0]], axis=1)
        wid = b.quad(
            np.array([corner[0], corner[1], 0.0]), u, up, R, Part(M.WALL, paint, wainscot, occluder=False)
        )
        b.slab(wid, [lo[0], lo[1], -0.2], [hi[0], hi[1], ROOM_HEIGHT_M])


def _table(b: MeshBuilder, xy: np.ndarray, yaw: float, size: tuple[float, float, float], wood: Color) -> None:
    """Top of `size` (length, depth, height) on four 4 cm square legs."""
    length, depth, height = size
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    b.box([*xy, height - 0.02], [length, depth, 0.04], yaw, Part(M.WOOD, wood, params=(0, 0, 0, 1.0)))
    for sx in (-1, 1):
        for sy in (-1, 1):
            c = xy + R @ np.array([sx * (length / 2 - 0.07), sy * (depth / 2 - 0.07)])
            b.box([*c, (height - 0.04) / 2], [0.04, 0.04, height - 0.04], yaw, Part(M.WOOD, wood))


def _chair(b: MeshBuilder, xy: np.ndarray, yaw: float, paint: Color) -> None:
    """Seat on 3.5 cm legs with a slatted back; the back is on the chair's local -y side."""
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    part = Part(M.PAINT, paint)
    b.box(
        [*xy, 0.45], [0.42, 0.42, 0.04], yaw, Part(M.WOOD, tuple(0.9 * np.array(paint)), params=(0, 0, 0, 2))
    )
    for sx in (-1, 1):
        for sy in (-1, 1):
            b.box([*(xy + R @ np.array([sx * 0.18, sy * 0.18])), 0.215], [0.035, 0.035, 0.43], yaw, part)
        b.box([*(xy + R @ np.array([sx * 0.18, -0.18])), 0.65], [0.035, 0.035, 0.36], yaw, part)
    for z in (0.6, 0.76):
        b.box([*(xy + R @ np.array([0.0, -0.18])), z], [0.325, 0.025, 0.07], yaw, part)


def _sofa(b: MeshBuilder, xy: np.ndarray, fabric: Color) -> None:
    """A three-seater facing +y with its back against the wall behind it."""
    x, y = xy
    dark = tuple(0.8 * np.array(fabric))
    b.box([x, y, 0.2], [2.0, 0.85, 0.4], 0.0, Part(M.FABRIC, dark))
    b.box([x, y - 0.31, 0.6], [2.0, 0.23, 0.4], 0.0, Part(M.FABRIC, dark))
    for sx in (-1, 1):
        b.box([x + sx * 0.905, y + 0.02, 0.53], [0.19, 0.81, 0.26], 0.0, Part(M.FABRIC, dark))
    for k in range(3):  # cushions touch each other and the armrests: no hidden slots
        cx = x - 0.54 + 0.54 * k
        b.box([cx, y + 0.09, 0.47], [0.54, 0.62, 0.14], 0.0, Part(M.FABRIC, fabric))
        b.box([cx, y - 0.14, 0.66], [0.54, 0.14, 0.34], 0.0, Part(M.FABRIC, fabric))


def _shelf(b: MeshBuilder, rng: np.random.Generator, x: float, wood: Color, paint: Color) -> None:
    """Against the +y wall: a closed two-door cabinet with an open shelf of books above it."""
    d = 0.33
    y = HY - d / 2
    b.box([x, y, 0.4], [1.0, d, 0.8], 0.0, Part(M.CABINET, paint, params=(2,)))
    for sx in (-1, 1):
        b.box([x + sx * 0.4875, y, 1.2], [0.025, d, 0.8], 0.0, Part(M.WOOD, wood))
    for z in (0.8125, 1.5875):
        b.box([x, y, z], [0.95, d, 0.025], 0.0, Part(M.WOOD, wood, params=(0, 0, 0, z)))
    u = x - 0.475 + 0.02 * rng.random()
    while u < x + 0.3 + 0.1 * rng.random():  # a row of books standing on the cabinet, against the wall
        w, h, dep = rng.uniform(0.025, 0.05), rng.uniform(0.25, 0.43), rng.uniform(0.17, 0.24)
        book = Part(M.BOOK, (0.5, 0.5, 0.5), params=(float(rng.integers(9)),))
        b.box([u + w / 2, HY - dep / 2, 0.825 + h / 2], [w, dep, h], 0.0, book)
        u += w + (0.1 if rng.random() < 0.1 else 0.0)  # books touch, with the odd gap


def _lamp(b: MeshBuilder, base: np.ndarray, pole_m: float, shade_r: float) -> None:
    """Floor or table lamp standing at `base`: metal disc base, thin pole, pleated shade."""
    b.solid(
        base,
        [np.array([[0.13, 0.0], [0.13, 0.02], [0.1, 0.035], [0.0, 0.035]])],
        Part(M.METAL, METAL),
        foot_m=0.13,
    )
    b.solid(base, [np.array([[0.0125, 0.03], [0.0125, pole_m + 0.05]])], Part(M.METAL, METAL), n_seg=24)
    shade = np.array([[0.0, 0.0], [shade_r, 0.0], [0.7 * shade_r, 0.27], [0.0, 0.27]])
    b.solid(
        base + [0, 0, pole_m - 0.12],
        [shade[:2], shade[1:3], shade[2:]],
        Part(M.SHADE, LAMPSHADE, (0.8, 0.65, 0.35)),
    )


def _vase(b: MeshBuilder, base: np.ndarray, scale: float, glaze: tuple[Color, Color]) -> None:
    """A closed glazed vase about 27 cm x `scale` tall standing at `base`."""
    side = np.array([[0.05, 0.0], [0.085, 0.06], [0.09, 0.12], [0.05, 0.21], [0.035, 0.24], [0.05, 0.27]])
    top = np.array([[0.05, 0.27], [0.03, 0.262], [0.0, 0.26]])
    b.solid(base, [side * scale, top * scale], Part(M.CERAMIC, *glaze), foot_m=0.05 * scale)


def _plant(b: MeshBuilder, rng: np.random.Generator, base: np.ndarray) -> None:
    """Small terracotta pot, thin stem and a crown of leafy spheres."""
    pot = np.array([[0.07, 0.0], [0.09, 0.15], [0.1, 0.16], [0.1, 0.18]])
    b.solid(
        base,
        [pot, np.array([[0.1, 0.18], [0.0, 0.18]])],
        Part(M.CERAMIC, (0.72, 0.38, 0.24), (0.66, 0.34, 0.2)),
        foot_m=0.07,
    )
    b.solid(base, [np.array([[0.008, 0.18], [0.008, 0.36]])], Part(M.WOOD, (0.4, 0.3, 0.2)), n_seg=16)
    for k in range(3):
        ang = 2 * np.pi * k / 3 + rng.uniform(0, 1)
        r = rng.uniform(0.07, 0.095)
        c = base + [0.06 * np.cos(ang), 0.06 * np.sin(ang), 0.3 + 0.05 * k]
        b.solid(c, [_sphere(r)], Part(M.LEAF, (0.25, 0.48, 0.22), (0.45, 0.62, 0.25), params=(0, 0, 0, k)))


def _sphere(r: float) -> np.ndarray:
    """Lathe profile (K,2) of a sphere of radius r resting on z = 0."""
    t = np.linspace(-np.pi / 2, np.pi / 2, 24)
    return np.stack([r * np.cos(t), r + r * np.sin(t)], 1)


def _wall_frame(b: MeshBuilder, wall: str, along: float, z: float, w: float, h: float, part: Part) -> None:
    """A thin framed rectangle (picture or window) hung flat on a wall, centred `along` the wall."""
    t = 0.03
    centers = {
        "-y": (along, -HY + t / 2, 0.0),
        "+y": (along, HY - t / 2, np.pi),
        "-x": (-HX + t / 2, along, -np.pi / 2),
        "+x": (HX - t / 2, along, np.pi / 2),
    }
    cx, cy, yaw = centers[wall]
    b.box([cx, cy, z], [w, t, h], yaw, part)


def layout(seed: int) -> Geometry:
    """Build the whole room for `seed`."""
    rng = np.random.default_rng(seed)
    j = lambda s: float(rng.uniform(-s, s))  # noqa: E731 - small placement jitter
    b = MeshBuilder()
    _room(b, rng, (-0.45 + j(0.08), -0.35 + j(0.08), 1.1, 0.72))
    wood, paint = _pick(rng, FURNITURE_WOODS), _pick(rng, CHAIR_PAINTS)
    _sofa(b, np.array([-0.45 + j(0.1), -HY + 0.425]), _pick(rng, SOFAS))
    chest = np.array([-0.45 + j(0.08), -0.4 + j(0.05)])
    b.box([*chest, 0.19], [0.9, 0.5, 0.38], j(0.1), Part(M.WOOD, wood, params=(0, 0, 0, 3)))
    _plant(b, rng, np.array([chest[0] + 0.2, chest[1], 0.38]))
    _lamp(b, np.array([-1.85 + j(0.05), -1.55 + j(0.05), 0.0]), 1.5, 0.2)
    table = np.array([1.0 + j(0.08), 0.45 + j(0.06)])
    _table(b, table, j(0.05), (1.05, 0.7, 0.75), wood)
    _chair(b, table + [-0.25 + j(0.05), 0.56 + j(0.04)], np.pi + j(0.15), paint)
    _chair(b, table + [-0.2 + j(0.05), -0.56 + j(0.04)], j(0.15), paint)
    _vase(b, np.array([*table, 0.75]), 0.7, _pick(rng, CERAMICS))
    shelf_x = -0.6 + j(0.08)
    _shelf(b, rng, shelf_x, wood, paint)
    _vase(b, np.array([shelf_x + 0.25, HY - 0.17, 1.6]), 0.8, _pick(rng, CERAMICS))
    side = np.array([HX - 0.225, -0.25 + j(0.08)])
    b.box([*side, 0.375], [1.1, 0.45, 0.75], -np.pi / 2, Part(M.CABINET, paint, params=(3,)))
    b.box([side[0] - 0.01, side[1], 0.765], [1.14, 0.47, 0.03], -np.pi / 2, Part(M.WOOD, wood))
    _lamp(b, np.array([side[0], side[1] - 0.33, 0.78]), 0.45, 0.14)
    _vase(b, np.array([side[0], side[1] + 0.3, 0.78]), 1.0, _pick(rng, CERAMICS))
    _box_stack(b, rng)
    b.solid(np.array([0.95 + j(0.1), -0.8 + j(0.08), 0.0]), [_sphere(0.12)], Part(M.BALL, (1.0, 1.0, 1.0)))
    stool = np.array([[0.17, 0.0], [0.17, 0.44], [0.0, 0.44]])
    b.solid(
        np.array([-1.25 + j(0.05), 0.35 + j(0.05), 0.0]),
        [stool[:2], stool[1:]],
        Part(M.CERAMIC, *_pick(rng, CERAMICS)),
        foot_m=0.17,
    )
    _wall_frame(b, "-x", 0.1 + j(0.2), 1.5, 1.0, 0.7, Part(M.PAINTING, params=(0, j(3)), **_art(rng)))
    _wall_frame(b, "-y", -0.45, 1.45, 0.9, 0.6, Part(M.PAINTING, params=(1, 0), **_art(rng)))
    _wall_frame(b, "+x", side[1], 1.55, 0.6, 0.75, Part(M.PAINTING, params=(0, j(3)), **_art(rng)))
    _wall_frame(
        b, "+y", 0.9 + j(0.1), 1.55, 1.2, 1.1, Part(M.WINDOW, WALL_PAINTS[0][0], params=(0, 0, 0, j(3)))
    )
    return b.build()


def _art(rng: np.random.Generator) -> dict[str, Color]:
    """Two colours for a picture: a glaze colour and a random muted one."""
    a, _ = _pick(rng, CERAMICS)
    return {"color_a": a, "color_b": tuple(float(v) for v in rng.uniform(0.2, 0.6, 3))}


def _box_stack(b: MeshBuilder, rng: np.random.Generator) -> None:
    """Two or three cardboard boxes stacked into the +x,+y corner (flush with both walls)."""
    z = 0.0
    for k in range(2 + int(rng.integers(2))):
        size = np.array([0.5 - 0.08 * k, 0.4 - 0.05 * k, 0.34 - 0.04 * k]) * rng.uniform(0.9, 1.1)
        b.box([HX - size[0] / 2, HY - size[1] / 2, z + size[2] / 2], size, 0.0, Part(M.CARDBOARD, CARDBOARD))
        z += size[2]
