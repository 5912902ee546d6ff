"""Camera sets for image metrics: "interpolate" (training views spread over the trajectory) and
"extrapolate" (novel cameras away from the trajectory that still look at mapped content)."""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from h2viz.eval.metrics import EvalError
from h2viz.geometry import look_at

log = logging.getLogger("h2viz.eval")

_CONE_COS = float(np.cos(np.deg2rad(25.0)))  # half-angle of the cone a trajectory camera "saw"
_MIN_LOOK_DISTANCE_M = 0.3  # a novel camera stays at least this far from the point it looks at
_LOS_STEP_M = 0.05  # spacing of line-of-sight probes
_LOS_CLEARANCE_M = 0.03  # a probe closer than this to a scene point means the view is blocked
_LOS_END_SKIP_M = 0.15  # the last part of the sight line, near the target surface, is not probed
_N_TARGETS = 8  # surface points tried per trajectory camera (the central one first)


def interpolate_views(poses: np.ndarray, n: int) -> list[int]:
    """Indices of `n` training views evenly spread over the trajectory poses (N,4,4), in order
    (all of them when n >= N, none when n <= 0)."""
    count = len(poses)
    if n <= 0 or count == 0:
        return []
    if n >= count:
        return list(range(count))
    return [int(i) for i in np.unique(np.round(np.linspace(0, count - 1, n)).astype(np.int64))]


def estimate_up(poses: np.ndarray) -> np.ndarray:
    """World up (3,) as the mean camera up axis (-y of OpenCV cameras) over poses (N,4,4)."""
    up = -np.asarray(poses)[:, :3, 1].mean(axis=0)
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-6 else np.array([0.0, 0.0, 1.0])


def extrapolate_views(
    poses: np.ndarray,
    n: int,
    scene_bounds_or_points: np.ndarray,
    seed: int = 0,
    offset_m: tuple[float, float] = (0.5, 1.0),
    min_distance_m: float = 0.4,
    margin_m: float = 0.2,
    up: np.ndarray | None = None,
    n_candidates: int = 64,
) -> np.ndarray:
    """`n` novel cameras T_world_camera (n,4,4) away from the trajectory `poses` (N,4,4).

    `scene_bounds_or_points` is either points (P,3) on the observed surface (e.g. back-projected
    depth or GT mesh samples) or, when its shape is (2,3), the scene's bounds [min, max].
    Rule, per novel view:
    1. take a base trajectory camera (`interpolate_views` spread, cycled when n > N);
    2. its targets are the scene point nearest to the median of the points within 25 deg of its
       optical axis, then up to 7 random points of that cone (no point in the cone: the one nearest
       the axis; bounds only: the point of the axis nearest the box centre);
    3. candidate eyes are the base camera moved by a random length in `offset_m` along a random mix of
       world up (weight in [-0.5, 1]), backwards (horizontal, [0, 1]) and sideways ([-1, 1]), drawn
       from `seed`;
    4. an (eye, target) pair is valid when the eye lies inside the scene's bounding box shrunk by
       `margin_m` (grown to hold the trajectory; on sides where the trajectory is outside the scene's
       bounds, as around a scanned object, up to offset_m[1] beyond it), is >= `min_distance_m` from
       every trajectory camera, >= 0.3 m from the target and, with scene points, has a clear line
       of sight to it;
    5. the first valid pair (central target first) gives the view (`look_at`, `up` = world up,
       estimated from the trajectory when None); if none is valid, the pair meeting every other rule
       that is furthest from the trajectory is used and a warning is logged.
    """
    poses = np.asarray(poses, dtype=np.float64)
    scene = np.asarray(scene_bounds_or_points, dtype=np.float64)
    if len(poses) == 0 or n <= 0:
        return np.zeros((0, 4, 4))
    if scene.ndim != 2 or scene.shape[1] != 3 or len(scene) < 2:
        raise EvalError(f"extrapolated views need scene points (P,3) or bounds (2,3), got {scene.shape}")
    up = estimate_up(poses) if up is None else np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    points = None if scene.shape == (2, 3) else scene
    lo, hi = _allowed_box(poses[:, :3, 3], scene, margin_m, offset_m[1])
    tree = cKDTree(points) if points is not None else None
    rng = np.random.default_rng(seed)
    base = interpolate_views(poses, n)
    base = [base[i % len(base)] for i in range(n)]
    views = np.zeros((n, 4, 4))
    for k, i in enumerate(base):
        targets = _targets(poses[i], points, lo, hi, rng)  # (M,3)
        eyes = _candidate_eyes(poses[i], up, offset_m, n_candidates, rng)  # (C,3)
        eye, target = _pick(eyes, targets, poses, (lo, hi), tree, min_distance_m)
        views[k] = look_at(eye, target, up)
    return views


def _allowed_box(
    positions: np.ndarray, scene: np.ndarray, margin_m: float, reach_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where novel eyes may go: per axis side, the scene's bounds shrunk by the margin (to the centre
    at most) and grown to hold the trajectory; where the trajectory lies outside the scene's bounds
    (an object filmed from outside), up to `reach_m` beyond the trajectory instead."""
    scene_lo, scene_hi = scene.min(axis=0), scene.max(axis=0)
    shrink = np.minimum(margin_m, (scene_hi - scene_lo) / 2.0)
    pos_lo, pos_hi = positions.min(axis=0), positions.max(axis=0)
    lo = np.where(pos_lo < scene_lo, pos_lo - reach_m, np.minimum(scene_lo + shrink, pos_lo))
    hi = np.where(pos_hi > scene_hi, pos_hi + reach_m, np.maximum(scene_hi - shrink, pos_hi))
    return lo, hi


def _targets(
    T: np.ndarray, points: np.ndarray | None, lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Surface points (M,3) near what the camera T_world_camera (4,4) looked at, best first."""
    eye, forward = T[:3, 3], T[:3, 2]
    if points is None:
        t = max(float((0.5 * (lo + hi) - eye) @ forward), _MIN_LOOK_DISTANCE_M)
        return (eye + t * forward)[None]
    rel = points - eye  # (P,3)
    along = rel @ forward  # (P,)
    in_cone = along > _CONE_COS * np.maximum(np.linalg.norm(rel, axis=1), 1e-9)
    if not in_cone.any():
        off_axis = np.linalg.norm(rel - along[:, None] * forward, axis=1) + np.where(along > 0, 0.0, np.inf)
        return points[np.argmin(off_axis)][None]
    seen = points[in_cone]  # (Q,3)
    central = seen[np.argmin(np.linalg.norm(seen - np.median(seen, axis=0), axis=1))]
    others = seen[rng.choice(len(seen), size=min(_N_TARGETS - 1, len(seen)), replace=False)]
    return np.concatenate([central[None], others])


def _candidate_eyes(
    T: np.ndarray, up: np.ndarray, offset_m: tuple[float, float], count: int, rng: np.random.Generator
) -> np.ndarray:
    """Camera centre moved up / back / sideways by a random length in `offset_m`: eyes (C,3)."""
    forward = T[:3, 2] - (T[:3, 2] @ up) * up
    if np.linalg.norm(forward) < 1e-6:  # looking straight up or down: use the camera's image-up
        forward = -T[:3, 1] - (-T[:3, 1] @ up) * up
    back = -forward / np.linalg.norm(forward)
    side = np.cross(up, back)
    w = rng.uniform([-0.5, 0.0, -1.0], [1.0, 1.0, 1.0], size=(count, 3))  # (C,3) up, back, side weights
    dirs = w[:, :1] * up + w[:, 1:2] * back + w[:, 2:] * side
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-9)
    return T[:3, 3] + dirs * rng.uniform(offset_m[0], offset_m[1], size=(count, 1))


def _pick(
    eyes: np.ndarray,
    targets: np.ndarray,
    poses: np.ndarray,
    box: tuple[np.ndarray, np.ndarray],
    tree: cKDTree | None,
    min_distance_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The first valid (eye, target) pair over eyes (C,3) x targets (M,3), best target first; else
    the clear pair furthest from the trajectory; else the eye furthest from it."""
    eye = np.tile(eyes, (len(targets), 1))  # (M*C,3)
    target = np.repeat(targets, len(eyes), axis=0)  # (M*C,3)
    gap = np.linalg.norm(eye[:, None, :] - poses[None, :, :3, 3], axis=2).min(axis=1)  # (M*C,)
    usable = np.all((eye >= box[0]) & (eye <= box[1]), axis=1)
    usable &= np.linalg.norm(eye - target, axis=1) >= _MIN_LOOK_DISTANCE_M
    if tree is not None:
        usable &= _clear_line_of_sight(eye, target, tree)
    valid = usable & (gap >= min_distance_m)
    if valid.any():
        best = int(np.argmax(valid))
    else:
        log.warning("extrapolated view: no camera far enough from the trajectory; using the furthest one")
        best = int(np.argmax(np.where(usable, gap, -1.0))) if usable.any() else int(np.argmax(gap))
    return eye[best], target[best]


def _clear_line_of_sight(eyes: np.ndarray, targets: np.ndarray, tree: cKDTree) -> np.ndarray:
    """Whether each segment eye (C,3) -> target (C,3) passes no scene point: (C,) bool."""
    length = np.linalg.norm(targets - eyes, axis=1)  # (C,)
    steps = np.arange(0.0, float(length.max()), _LOS_STEP_M)  # (S,)
    dirs = (targets - eyes) / np.maximum(length, 1e-9)[:, None]
    used = steps[None, :] < (length - _LOS_END_SKIP_M)[:, None]  # (C,S)
    probes = eyes[:, None, :] + steps[None, :, None] * dirs[:, None, :]  # (C,S,3)
    dist, _ = tree.query(probes[used], distance_upper_bound=_LOS_CLEARANCE_M, workers=-1)
    blocked = np.zeros(used.shape, dtype=bool)
    blocked[used] = np.isfinite(dist)
    return ~blocked.any(axis=1)
