"""Procedural surface colours of the synthetic room: one albedo function per material, evaluated at
surface points in the part's own frame, so colour depends on the point only (never on the camera).

Patterns have edges and smooth variation at >= 2-3 cm plus a few thin lines, which a neural colour
field can fit; there is no per-pixel noise.
"""

from __future__ import annotations

from collections.abc import Callable
from enum import IntEnum

import numpy as np

WHITE = np.float32([0.93, 0.92, 0.88])
BOOK_COLORS = np.float32(
    [[0.62, 0.16, 0.14], [0.16, 0.30, 0.52], [0.20, 0.45, 0.32], [0.85, 0.66, 0.22], [0.30, 0.22, 0.40],
     [0.90, 0.86, 0.76], [0.12, 0.14, 0.16], [0.78, 0.40, 0.22], [0.45, 0.62, 0.70]]
)  # fmt: skip
BALL_COLORS = np.float32(
    [[0.86, 0.18, 0.16], [0.95, 0.95, 0.92], [0.15, 0.38, 0.75], [0.96, 0.78, 0.15], [0.95, 0.95, 0.92],
     [0.20, 0.62, 0.30]]
)  # fmt: skip


class Material(IntEnum):
    FLOOR = 0  # wooden planks with a rug; params = rug centre x, y and half sizes (floor frame)
    WALL = 1  # baseboard, panelled wainscot, rail and striped paint; a = paint, b = wainscot
    WOOD = 2  # grain along local x
    PAINT = 3  # painted surface with gentle variation
    FABRIC = 4  # woven check, a = base colour
    CARDBOARD = 5  # brown box with tape and a label
    CERAMIC = 6  # glazed bands, a and b alternate
    METAL = 7  # dark brushed metal
    SHADE = 8  # pleated lamp shade
    BOOK = 9  # spine colour from params[0], gold bands
    PAINTING = 10  # framed picture; params[0] = style (0 landscape, 1 colour blocks)
    BALL = 11  # six coloured segments
    LEAF = 12  # foliage with veins
    WINDOW = 13  # window frame with sky panes
    CABINET = 14  # doors with gaps and knobs; params[0] = number of doors


def _hash(i: np.ndarray, j: np.ndarray, salt: int = 0) -> np.ndarray:
    """Deterministic pseudo-random value in [0,1) per integer cell (i, j)."""
    h = (i.astype(np.int64) * 73856093) ^ (j.astype(np.int64) * 19349663) ^ (salt * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF) / 65536.0


def _line(x: np.ndarray, period: float, half_width: float) -> np.ndarray:
    """1 on thin lines at multiples of `period`, 0 elsewhere, with a 1 mm soft edge."""
    d = np.abs(x - period * np.round(x / period))
    return np.clip((half_width + 0.001 - d) / 0.001, 0.0, 1.0)


def _smooth(p: np.ndarray, scale_m: float, salt: float) -> np.ndarray:
    """Smooth deterministic field in [-1,1] varying over about `scale_m`."""
    k = 2 * np.pi / scale_m
    a = np.sin(k * (0.8 * p[:, 0] + 0.6 * p[:, 1] + 0.3 * p[:, 2]) + salt)
    b = np.sin(k * (-0.5 * p[:, 0] + 0.7 * p[:, 1] + 0.9 * p[:, 2]) * 1.37 + 2.1 * salt)
    c = np.sin(k * (0.3 * p[:, 0] - 0.9 * p[:, 1] + 0.6 * p[:, 2]) * 0.71 + 3.3 * salt)
    return (a + b + c) / 3.0


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a + (b - a) * t[:, None]


def _floor(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    x, y = p[:, 0], p[:, 1]
    row = np.floor(y / 0.16)
    xs = x + _hash(row, row, 7) * 1.2
    col = np.floor(xs / 1.2)
    tone = _hash(row, col, 1)
    v = y - row * 0.16
    grain = np.sin(2 * np.pi * (v / 0.035 + 0.5 * np.sin(2 * np.pi * xs / 0.9 + 6 * tone)))
    out = a * (0.86 + 0.24 * tone + 0.05 * grain)[:, None]
    seam = np.maximum(_line(y, 0.16, 0.0025), _line(xs, 1.2, 0.0025))
    out = _mix(out, a * 0.45, seam)
    rug = (np.abs(x - prm[:, 0]) < prm[:, 2]) & (np.abs(y - prm[:, 1]) < prm[:, 3])
    if np.any(rug):
        out[rug] = _rug(x[rug] - prm[:, 0], y[rug] - prm[:, 1], prm[:, 2:4], b)
    return out


def _rug(u: np.ndarray, v: np.ndarray, half: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rug pattern at (u, v) from its centre: bound edge, border band, diamond field, medallion."""
    cream = np.float32([0.90, 0.84, 0.70])
    edge = np.minimum(half[:, 0] - np.abs(u), half[:, 1] - np.abs(v))
    fu, fv = u / 0.3 - np.round(u / 0.3), v / 0.3 - np.round(v / 0.3)
    d = np.abs(fu) + np.abs(fv)  # 0 at lattice points, 1 between them
    out = np.tile(cream, (len(u), 1))
    out = _mix(out, b * 0.9 + 0.08, (d < 0.28).astype(np.float32))
    out = _mix(out, b * 0.6, (np.abs(d - 0.5) < 0.05).astype(np.float32))
    ell = (u / (half[:, 0] * 0.42)) ** 2 + (v / (half[:, 1] * 0.42)) ** 2
    out = _mix(out, b, (ell < 1.0).astype(np.float32))
    out = _mix(out, cream * 0.95, (np.abs(ell - 0.55) < 0.08).astype(np.float32))
    out = _mix(out, b * 0.85, ((edge > 0.03) & (edge < 0.17)).astype(np.float32))
    out = _mix(out, cream, ((edge > 0.185) & (edge < 0.2)).astype(np.float32))
    return _mix(out, b * 0.45, (edge <= 0.03).astype(np.float32))


def _wall(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    u, z = p[:, 0], p[:, 2]
    stripe = np.floor(u / 0.12) % 2
    out = a * (0.97 + 0.05 * stripe)[:, None]
    dots = (
        (u / 0.24 - np.round(u / 0.24)) ** 2 + ((z - 0.12) / 0.24 - np.round((z - 0.12) / 0.24)) ** 2
    ) * 0.0576
    out = _mix(out, a * 0.82, (dots < 0.018**2).astype(np.float32))
    panel = (z < 0.9) * (1.0 - 0.35 * _line(u, 0.15, 0.003))
    out = np.where((z < 0.9)[:, None], b * panel[:, None], out)
    trim = (z < 0.1) | ((z > 0.9) & (z < 0.95)) | (z > 2.52)
    out = np.where(trim[:, None], WHITE, out)
    grooves = _line(z, 0.05, 0.002) * (trim & ((np.abs(z - 0.1) < 0.01) | (np.abs(z - 0.925) < 0.03)))
    return _mix(out, WHITE * 0.6, grooves)


def _wood(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    w = 0.8 * p[:, 1] + 0.6 * p[:, 2]
    rings = np.sin(2 * np.pi * (w / 0.02 + 0.3 * np.sin(2 * np.pi * p[:, 0] / 0.35 + prm[:, 3])))
    return a * (1.0 + 0.07 * rings + 0.06 * _smooth(p, 0.25, 1.0))[:, None]


def _paint(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    return a * (1.0 + 0.03 * _smooth(p, 0.4, 0.5))[:, None]


def _fabric(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    check = (np.floor(p[:, 0] / 0.03) + np.floor(p[:, 1] / 0.03) + np.floor(p[:, 2] / 0.03)) % 2
    edge = np.min(size - np.abs(p), axis=1)  # distance to the nearest box face, metres
    piping = (edge < 0.012) & (np.sum(size - np.abs(p) < 0.012, axis=1) >= 2)
    out = a * (0.97 + 0.06 * check + 0.05 * _smooth(p, 0.5, 2.0))[:, None]
    return _mix(out, a * 0.7, piping.astype(np.float32))


def _cardboard(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    out = a * (1.0 + 0.04 * _smooth(p, 0.3, 0.2))[:, None]
    tape = (np.abs(p[:, 0]) < 0.03) & (p[:, 2] > size[:, 2] - 0.12)
    out = _mix(out, np.float32([0.82, 0.70, 0.48]), tape.astype(np.float32))
    lx, lz = np.abs(p[:, 0] + 0.3 * size[:, 0]), np.abs(p[:, 2] + 0.1 * size[:, 2])
    label = (p[:, 1] < -size[:, 1] + 0.002) & (lx < 0.45 * size[:, 0]) & (lz < 0.3 * size[:, 2])
    out = _mix(out, WHITE, label.astype(np.float32))
    text = label & (lx < 0.35 * size[:, 0]) & (_line(lz, 0.03, 0.004) > 0.5) & (lz < 0.2 * size[:, 2])
    return _mix(out, np.float32([0.15, 0.15, 0.15]), text.astype(np.float32))


def _ceramic(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    ang = np.arctan2(p[:, 1], p[:, 0])
    wave = p[:, 2] + 0.012 * np.sin(5 * ang)
    band = np.floor(wave / 0.045) % 2
    out = _mix(a, b, band)
    return _mix(out, np.float32([0.80, 0.62, 0.25]), _line(wave, 0.045, 0.0025))


def _metal(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    return a * (0.9 + 0.1 * np.sin(2 * np.pi * p[:, 2] / 0.5) + 0.04 * _smooth(p, 0.1, 0.7))[:, None]


def _shade(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    pleat = 0.5 + 0.5 * np.cos(36 * np.arctan2(p[:, 1], p[:, 0]))
    trim = (np.abs(p[:, 2] - size[:, 2] + 0.02) < 0.012) | (np.abs(p[:, 2] - size[:, 2] * 0.63) < 0.012)
    return _mix(a * (1.0 - 0.08 * pleat)[:, None], b, trim.astype(np.float32))


def _book(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    base = BOOK_COLORS[prm[:, 0].astype(int) % len(BOOK_COLORS)]
    zr = p[:, 2] / size[:, 2]  # -1 bottom .. 1 top
    gold = (np.abs(np.abs(zr) - 0.78) < 0.05).astype(np.float32)
    title = ((np.abs(zr - 0.2) < 0.22) & (np.abs(p[:, 0]) < 0.6 * size[:, 0])).astype(np.float32)
    return _mix(_mix(base, base * 0.55, title), np.float32([0.85, 0.7, 0.3]), gold)


def _painting(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    x, z = p[:, 0], p[:, 2]
    frame = np.minimum(size[:, 0] - np.abs(x), size[:, 2] - np.abs(z)) < 0.045
    ridge = np.sin(np.pi * np.minimum(size[:, 0] - np.abs(x), size[:, 2] - np.abs(z)) / 0.045)
    wood = np.float32([0.36, 0.23, 0.13]) * (0.8 + 0.35 * ridge)[:, None]
    horizon = -0.1 * size[:, 2] + 0.15 * size[:, 2] * np.sin(x / size[:, 0] * 4.0 + prm[:, 1])
    sky = _mix(np.float32([0.98, 0.85, 0.62]), np.float32([0.45, 0.65, 0.85]), np.clip(z / size[:, 2], 0, 1))
    sun = (x - 0.4 * size[:, 0]) ** 2 + (z - 0.45 * size[:, 2]) ** 2 < (0.12 * size[:, 2]) ** 2
    land = _mix(b, b * 0.55, np.clip((horizon - z) / size[:, 2], 0, 1))
    scape = np.where((z < horizon)[:, None], land, np.where(sun[:, None], [0.99, 0.93, 0.7], sky))
    cell = _hash(np.floor((x + 1) / (0.27 * size[:, 0])), np.floor((z + 1) / (0.3 * size[:, 2])), 3)
    blocks = np.where((cell < 0.2)[:, None], a, np.where((cell > 0.8)[:, None], b, WHITE))
    grid = np.maximum(_line(x, 0.27 * size[:, 0], 0.006), _line(z, 0.3 * size[:, 2], 0.006))
    blocks = _mix(blocks, np.float32([0.1, 0.1, 0.1]), grid)
    canvas = np.where((prm[:, 0] > 0.5)[:, None], blocks, scape)
    return np.where(frame[:, None], wood, canvas)


def _ball(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    seg = np.floor((np.arctan2(p[:, 1], p[:, 0]) + np.pi) / (2 * np.pi) * 6).astype(int) % 6
    cap = np.abs(p[:, 2] - size[:, 2] / 2) > 0.85 * size[:, 2] / 2
    return np.where(cap[:, None], WHITE, BALL_COLORS[seg])


def _leaf(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    out = _mix(a, b, 0.5 + 0.5 * _smooth(p, 0.12, prm[:, 3]))
    return _mix(out, a * 0.6, _line(p[:, 2] + 0.3 * np.abs(p[:, 0] + p[:, 1]), 0.04, 0.002))


def _window(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    x, z = p[:, 0], p[:, 2]
    border = np.minimum(size[:, 0] - np.abs(x), size[:, 2] - np.abs(z)) < 0.06
    mullion = (np.abs(x) < 0.02) | (np.abs(z - 0.15 * size[:, 2]) < 0.02)
    t = np.clip(0.5 + 0.5 * z / size[:, 2], 0, 1)
    sky = _mix(np.float32([0.85, 0.92, 0.97]), np.float32([0.50, 0.70, 0.92]), t)
    cloud = np.clip(2.5 * (_smooth(p * np.float32([1.0, 1.0, 2.5]), 0.6, prm[:, 3]) - 0.25), 0, 1)
    sky = _mix(sky, np.float32([0.97, 0.97, 0.97]), cloud)
    return np.where((border | mullion)[:, None], WHITE, sky)


def _cabinet(p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, prm: np.ndarray) -> np.ndarray:
    out = _paint(p, a, b, size, prm)
    front = p[:, 1] < -size[:, 1] + 0.002
    door_w = 2 * size[:, 0] / np.maximum(prm[:, 0], 1)
    u = p[:, 0] + size[:, 0]
    gap = (_line(u, door_w, 0.002) > 0) | (np.abs(p[:, 2] - 0.5 * size[:, 2]) < 0.003)
    out = _mix(out, a * 0.5, (front & gap).astype(np.float32))
    du = u - door_w * (np.floor(u / door_w) + 0.5)
    knob = front & ((np.abs(du) - 0.3 * door_w) ** 2 + (p[:, 2] - 0.2 * size[:, 2]) ** 2 < 0.015**2)
    return _mix(out, np.float32([0.75, 0.6, 0.3]), knob.astype(np.float32))


Albedo = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]
_FUNCS: dict[Material, Albedo] = {
    Material.FLOOR: _floor, Material.WALL: _wall, Material.WOOD: _wood, Material.PAINT: _paint,
    Material.FABRIC: _fabric, Material.CARDBOARD: _cardboard, Material.CERAMIC: _ceramic,
    Material.METAL: _metal, Material.SHADE: _shade, Material.BOOK: _book, Material.PAINTING: _painting,
    Material.BALL: _ball, Material.LEAF: _leaf, Material.WINDOW: _window, Material.CABINET: _cabinet,
}  # fmt: skip


def albedo(
    material: Material, p: np.ndarray, a: np.ndarray, b: np.ndarray, size: np.ndarray, params: np.ndarray
) -> np.ndarray:
    """Albedo (N,3) in [0,1] of points p (N,3) in the frame of one part with this material, colours
    a, b (3,), half extents `size` (3,) and material parameters (4,)."""
    out = _FUNCS[material](p, a[None], b[None], size[None], params[None])
    return np.clip(np.broadcast_to(out, p.shape), 0.0, 1.0)
