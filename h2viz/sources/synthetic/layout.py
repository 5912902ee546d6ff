"""The room recipe: a 5 x 4 m living room with 2.6 m walls (z up, floor at z = 0, centred on the origin)
and furniture placed, sized and coloured from a seed. The room has no ceiling, so the map can be
looked into from above. Furniture along the walls stands flush against them (its back and the wall
behind it are buried, see MeshBuilder.buried) and tall things stay out of the middle, where the
camera walks."""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TypeVar

import numpy as np
import yaml

from h2viz.errors import SourceError
from h2viz.sources.synthetic.mesh import Geometry, MeshBuilder, Part
from h2viz.sources.synthetic.textures import Material as M

ROOM_X_M, ROOM_Y_M, ROOM_HEIGHT_M = 5.0, 4.0, 2.6
HX, HY = ROOM_X_M / 2, ROOM_Y_M / 2

Color = tuple[float, float, float]
T = TypeVar("T")
RECIPE = resources.files("h2viz") / "assets" / "synthetic_room.yaml"
"""The palettes the room is painted with, shipped with h2viz (assets/synthetic_room.yaml in a clone)."""


@dataclass(frozen=True)
class Recipe:
    """The room's palettes (see assets/synthetic_room.yaml); each seed picks one entry of each list."""

    wall_paints: list[tuple[Color, Color]]  # (upper paint, wainscot)
    floor_woods: list[Color]
    rugs: list[Color]
    sofas: list[Color]
    furniture_woods: list[Color]
    chair_paints: list[Color]
    ceramics: list[tuple[Color, Color]]  # (glaze, second glaze)
    cardboard: Color
    metal: Color
    lampshade: Color


def _color(value: object, where: str) -> Color:
    ok = isinstance(value, list) and len(value) == 3 and all(isinstance(v, int | float) for v in value)
    if not ok or not all(0.0 <= float(v) <= 1.0 for v in value):  # type: ignore[union-attr]
        raise SourceError(f"{where} must be a colour [r, g, b] of numbers in [0, 1], got {value!r}")
    r, g, b = (float(v) for v in value)  # type: ignore[union-attr]
    return (r, g, b)


def _entries(data: dict, key: str, where: str, pairs: bool) -> list:
    items = data.get(key)
    if not isinstance(items, list) or not items:
        raise SourceError(f"{where}: '{key}' must be a non-empty list")
    if pairs:
        bad = [i for i, item in enumerate(items) if not isinstance(item, list) or len(item) != 2]
        if bad:
            raise SourceError(f"{where}: every entry of '{key}' is a pair of colours; entry {bad[0]} is not")
        return [tuple(_color(c, f"{where}: {key}[{i}]") for c in item) for i, item in enumerate(items)]
    return [_color(c, f"{where}: {key}[{i}]") for i, c in enumerate(items)]


@functools.cache
def load_recipe(path: str = "") -> Recipe:
    """The recipe at `path` (empty: the packaged one); SourceError naming the file and what is wrong."""
    source = RECIPE if not path else Path(path)
    where = str(source)
    try:
        data = yaml.safe_load(source.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise SourceError(f"synthetic room recipe {where} cannot be read ({e}); pass a YAML file like "
                          "assets/synthetic_room.yaml to source.synthetic.recipe") from e  # fmt: skip
    if not isinstance(data, dict):
        raise SourceError(f"{where}: the recipe must be a mapping of palettes (wall_paints:, rugs:, ...)")
    fields = [f.name for f in dataclasses.fields(Recipe)]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise SourceError(f"{where}: unknown recipe key(s) {', '.join(unknown)}; the keys are {', '.join(fields)}")
    lists = {k: _entries(data, k, where, k in ("wall_paints", "ceramics")) for k in fields[:7]}
    singles = {k: _color(data.get(k), f"{where}: {k}") for k in fields[7:]}
    return Recipe(**lists, **singles)


def _pick(rng: np.random.Generator, options: list[T]) -> T:
    return options[int(rng.integers(len(options)))]


def _room(b: MeshBuilder, rng: np.random.Generator, rug: tuple[float, float, float, float], r: Recipe) -> None:
    """Floor with a rug and four inward-facing walls, each backed by a solid slab outside the room."""
    rug_prm = (rug[0] + HX, rug[1] + HY, rug[2], rug[3])
    floor = Part(M.FLOOR, _pick(rng, r.floor_woods), _pick(rng, r.rugs), rug_prm, occluder=False)
    fid = b.quad(
        np.array([-HX, -HY, 0.0]), np.array([ROOM_X_M, 0, 0]), np.array([0, ROOM_Y_M, 0]), np.eye(3), floor
    )
    b.slab(fid, [-HX - 0.2, -HY - 0.2, -0.2], [HX + 0.2, HY + 0.2, 0.0])
    paint, wainscot = _pick(rng, r.wall_paints)
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


def _lamp(b: MeshBuilder, base: np.ndarray, pole_m: float, shade_r: float, r: Recipe) -> None:
    """Floor or table lamp standing at `base`: metal disc base, thin pole, pleated shade."""
    b.solid(
        base,
        [np.array([[0.13, 0.0], [0.13, 0.02], [0.1, 0.035], [0.0, 0.035]])],
        Part(M.METAL, r.metal),
        foot_m=0.13,
    )
    b.solid(base, [np.array([[0.0125, 0.03], [0.0125, pole_m + 0.05]])], Part(M.METAL, r.metal), n_seg=24)
    shade = np.array([[0.0, 0.0], [shade_r, 0.0], [0.7 * shade_r, 0.27], [0.0, 0.27]])
    b.solid(
        base + [0, 0, pole_m - 0.12],
        [shade[:2], shade[1:3], shade[2:]],
        Part(M.SHADE, r.lampshade, (0.8, 0.65, 0.35)),
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


def layout(seed: int, recipe: Recipe | None = None) -> Geometry:
    """Build the whole room for `seed`, painted from `recipe` (None: the packaged one)."""
    r = load_recipe() if recipe is None else recipe
    rng = np.random.default_rng(seed)
    j = lambda s: float(rng.uniform(-s, s))  # noqa: E731 - small placement jitter
    b = MeshBuilder()
    _room(b, rng, (-0.45 + j(0.08), -0.35 + j(0.08), 1.1, 0.72), r)
    wood, paint = _pick(rng, r.furniture_woods), _pick(rng, r.chair_paints)
    _sofa(b, np.array([-0.45 + j(0.1), -HY + 0.425]), _pick(rng, r.sofas))
    chest = np.array([-0.45 + j(0.08), -0.4 + j(0.05)])
    b.box([*chest, 0.19], [0.9, 0.5, 0.38], j(0.1), Part(M.WOOD, wood, params=(0, 0, 0, 3)))
    _plant(b, rng, np.array([chest[0] + 0.2, chest[1], 0.38]))
    _lamp(b, np.array([-1.85 + j(0.05), -1.55 + j(0.05), 0.0]), 1.5, 0.2, r)
    table = np.array([1.0 + j(0.08), 0.45 + j(0.06)])
    _table(b, table, j(0.05), (1.05, 0.7, 0.75), wood)
    _chair(b, table + [-0.25 + j(0.05), 0.56 + j(0.04)], np.pi + j(0.15), paint)
    _chair(b, table + [-0.2 + j(0.05), -0.56 + j(0.04)], j(0.15), paint)
    _vase(b, np.array([*table, 0.75]), 0.7, _pick(rng, r.ceramics))
    shelf_x = -0.6 + j(0.08)
    _shelf(b, rng, shelf_x, wood, paint)
    _vase(b, np.array([shelf_x + 0.25, HY - 0.17, 1.6]), 0.8, _pick(rng, r.ceramics))
    side = np.array([HX - 0.225, -0.25 + j(0.08)])
    b.box([*side, 0.375], [1.1, 0.45, 0.75], -np.pi / 2, Part(M.CABINET, paint, params=(3,)))
    b.box([side[0] - 0.01, side[1], 0.765], [1.14, 0.47, 0.03], -np.pi / 2, Part(M.WOOD, wood))
    _lamp(b, np.array([side[0], side[1] - 0.33, 0.78]), 0.45, 0.14, r)
    _vase(b, np.array([side[0], side[1] + 0.3, 0.78]), 1.0, _pick(rng, r.ceramics))
    _box_stack(b, rng, r)
    b.solid(np.array([0.95 + j(0.1), -0.8 + j(0.08), 0.0]), [_sphere(0.12)], Part(M.BALL, (1.0, 1.0, 1.0)))
    stool = np.array([[0.17, 0.0], [0.17, 0.44], [0.0, 0.44]])
    b.solid(
        np.array([-1.25 + j(0.05), 0.35 + j(0.05), 0.0]),
        [stool[:2], stool[1:]],
        Part(M.CERAMIC, *_pick(rng, r.ceramics)),
        foot_m=0.17,
    )
    _wall_frame(b, "-x", 0.1 + j(0.2), 1.5, 1.0, 0.7, Part(M.PAINTING, params=(0, j(3)), **_art(rng, r)))
    _wall_frame(b, "-y", -0.45, 1.45, 0.9, 0.6, Part(M.PAINTING, params=(1, 0), **_art(rng, r)))
    _wall_frame(b, "+x", side[1], 1.55, 0.6, 0.75, Part(M.PAINTING, params=(0, j(3)), **_art(rng, r)))
    _wall_frame(
        b, "+y", 0.9 + j(0.1), 1.55, 1.2, 1.1, Part(M.WINDOW, r.wall_paints[0][0], params=(0, 0, 0, j(3)))
    )
    return b.build()


def _art(rng: np.random.Generator, r: Recipe) -> dict[str, Color]:
    """Two colours for a picture: a glaze colour and a random muted one."""
    a, _ = _pick(rng, r.ceramics)
    return {"color_a": a, "color_b": tuple(float(v) for v in rng.uniform(0.2, 0.6, 3))}


def _box_stack(b: MeshBuilder, rng: np.random.Generator, r: Recipe) -> None:
    """Two or three cardboard boxes stacked into the +x,+y corner (flush with both walls)."""
    z = 0.0
    for k in range(2 + int(rng.integers(2))):
        size = np.array([0.5 - 0.08 * k, 0.4 - 0.05 * k, 0.34 - 0.04 * k]) * rng.uniform(0.9, 1.1)
        b.box([HX - size[0] / 2, HY - size[1] / 2, z + size[2] / 2], size, 0.0, Part(M.CARDBOARD, r.cardboard))
        z += size[2]
