"""The marching-cubes case table, built from the cube's faces rather than written out.

Corner i of a cell sits at offset ((i >> 2) & 1, (i >> 1) & 1, i & 1); edge e joins corner EDGE_CORNER[e] to
its neighbour along axis EDGE_AXIS[e]. For each of the 256 inside/outside patterns (bit i set: corner i is
inside, SDF < 0), every cube face with crossings contributes segments between its crossed edges; a face with
four crossings (two inside corners on a diagonal) cuts each inside corner off on its own. That rule depends on
the face's four corners only, so two cells sharing a face draw the same segments there and the surface has no
cracks. The segments, oriented with the inside on their left seen from outside the cube, chain into closed
loops, and each loop is fanned into triangles wound counter-clockwise seen from outside the surface (normals
point towards positive SDF).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

MAX_TRIANGLES = 5  # the most any pattern needs


def corner_offset(i: int) -> np.ndarray:
    """(3,) offset of cube corner i."""
    return np.array([(i >> 2) & 1, (i >> 1) & 1, i & 1], dtype=np.float64)


EDGES = [(i, axis) for axis in range(3) for i in range(8) if not (i >> (2 - axis)) & 1]
"""The 12 cube edges as (lower corner, axis)."""
EDGE_CORNER = np.array([i for i, _ in EDGES], dtype=np.int64)
EDGE_AXIS = np.array([a for _, a in EDGES], dtype=np.int64)


def _edge_midpoint(e: int) -> np.ndarray:
    i, axis = EDGES[e]
    return corner_offset(i) + 0.5 * np.eye(3)[axis]


def _edge_corners(e: int) -> tuple[int, int]:
    i, axis = EDGES[e]
    return i, i | (1 << (2 - axis))


def _face_segments(inside: int, axis: int, side: int) -> list[tuple[int, int]]:
    """Directed segments (edge, edge) of one face for the pattern `inside`, the inside on their left seen from
    outside the cube."""
    corners = [i for i in range(8) if ((i >> (2 - axis)) & 1) == side]
    edges = [e for e in range(12) if all(c in corners for c in _edge_corners(e))]
    is_in = {c: bool((inside >> c) & 1) for c in corners}
    crossed = [e for e in edges if is_in[_edge_corners(e)[0]] != is_in[_edge_corners(e)[1]]]
    normal = (1.0 if side else -1.0) * np.eye(3)[axis]
    inside_corners = [c for c in corners if is_in[c]]
    if len(crossed) == 2:  # every inside corner lies on the same side of the one segment
        pairs = [(crossed[0], crossed[1], inside_corners[0])]
    elif len(crossed) == 4:  # inside corners on a diagonal: each is cut off by the two crossed edges at it
        pairs = []
        for c in inside_corners:
            at = [e for e in crossed if c in _edge_corners(e)]
            pairs.append((at[0], at[1], c))
    else:
        return []
    segments = []
    for a, b, reference in pairs:
        pa, pb = _edge_midpoint(a), _edge_midpoint(b)
        left = np.cross(normal, pb - pa)
        inside_left = float(np.dot(left, corner_offset(reference) - pa)) > 0
        segments.append((a, b) if inside_left else (b, a))
    return segments


def _triangles(inside: int) -> list[tuple[int, int, int]]:
    """Triangles (edge ids) of one inside/outside pattern, wound counter-clockwise seen from outside."""
    following: dict[int, int] = {}
    for axis in range(3):
        for side in (0, 1):
            for a, b in _face_segments(inside, axis, side):
                following[a] = b
    triangles = []
    while following:
        start = min(following)
        loop = [start]
        while following[loop[-1]] != start:
            loop.append(following.pop(loop[-1]))
        following.pop(loop[-1])
        loop = _fan_apex_first(loop)
        triangles += [(loop[0], loop[k], loop[k + 1]) for k in range(1, len(loop) - 1)]
    return triangles


def _edge_faces(e: int) -> set[tuple[int, int]]:
    """The two cube faces (axis, side) that edge e lies on."""
    i, axis = EDGES[e]
    return {(a, (i >> (2 - a)) & 1) for a in range(3) if a != axis}


def _fan_apex_first(loop: list[int]) -> list[int]:
    """The loop rotated so that no fan diagonal from its first vertex lies on a cube face: on a face with four
    crossings, the neighbouring cell would draw the same diagonal and the edge would belong to four triangles."""
    for r in range(len(loop)):
        turned = loop[r:] + loop[:r]
        if all(not (_edge_faces(turned[0]) & _edge_faces(turned[k])) for k in range(2, len(loop) - 1)):
            return turned
    return loop  # not reached for any of the 256 patterns (checked by the tests)


@dataclass(frozen=True)
class CaseTable:
    """Triangles per inside/outside pattern of a cell's 8 corners."""

    counts: np.ndarray  # (256,) int64 triangles of each pattern
    edges: np.ndarray  # (256, MAX_TRIANGLES * 3) int64 edge ids of its triangles, -1 after the last
    edge_corner: np.ndarray  # (12,) int64 lower corner of each edge
    edge_axis: np.ndarray  # (12,) int64 axis of each edge


@functools.cache
def case_table() -> CaseTable:
    """The table for all 256 patterns. Loops come out with the inside on their left; the winding is checked
    against one corner's triangle and reversed everywhere if it points inwards."""
    cases = [_triangles(inside) for inside in range(256)]
    a, b, c = (_edge_midpoint(e) for e in cases[1][0])  # pattern 1: only corner 0 (at the origin) is inside
    if float(np.dot(np.cross(b - a, c - a), (a + b + c) / 3)) < 0:
        cases = [[(t[0], t[2], t[1]) for t in tris] for tris in cases]
    counts = np.array([len(t) for t in cases], dtype=np.int64)
    edges = np.full((256, MAX_TRIANGLES * 3), -1, dtype=np.int64)
    for inside, tris in enumerate(cases):
        flat = [e for t in tris for e in t]
        edges[inside, : len(flat)] = flat
    return CaseTable(counts, edges, EDGE_CORNER, EDGE_AXIS)
