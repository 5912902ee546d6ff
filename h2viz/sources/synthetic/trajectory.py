"""The hand-held-like camera path through the synthetic room: one closed loop around the room centre
at varied height with yaw sweeps between the room's middle and its walls, pitch aimed at varied heights
across the room, small roll, all smooth (integer harmonics of the loop) and deterministic from the seed.

The loop keeps every camera at least CLEARANCE_M from every surface: positions too close to the scene
are pushed away and the correction is smoothed along the loop.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d

from h2viz.geometry import look_at
from h2viz.sources.synthetic.layout import ROOM_X_M, ROOM_Y_M
from h2viz.sources.synthetic.scene import Scene

LOOP_RADII_M = np.array([2.0, 1.5])  # half extents along x and y of the loop around the room centre
LOOP_SQUARENESS = 4.0  # superellipse exponent: 2 = ellipse, larger = closer to the room's corners
HEIGHT_RANGE_M = (1.25, 1.8)
CLEARANCE_M = 0.47  # pushed-to distance between a camera and the nearest surface (sampled)
YAW_SWEEP = (1.1, 3)  # amplitude (rad) and count per loop of the sweeps around "look at the centre"
AIM_HEIGHT_M = (0.4, 1.25, 2)  # height looked at across the room: mean, amplitude, cycles per loop


def _wobble(rng: np.random.Generator, s: np.ndarray, amplitude: float, harmonics: range) -> np.ndarray:
    """Smooth closed-loop noise over s in [0,1): integer harmonics with random phases, amplitude ~ 1/k."""
    out = np.zeros_like(s)
    for k in harmonics:
        out += amplitude / k * np.sin(2 * np.pi * k * s + rng.uniform(0, 2 * np.pi))
    return out


def _distance_to_walls(eyes: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Horizontal distance (n,) from eyes (n,3) along heading `yaw` (n,) to the room's walls."""
    dx, dy = np.cos(yaw), np.sin(yaw)
    with np.errstate(divide="ignore"):
        tx = (np.where(dx > 0, ROOM_X_M / 2, -ROOM_X_M / 2) - eyes[:, 0]) / dx
        ty = (np.where(dy > 0, ROOM_Y_M / 2, -ROOM_Y_M / 2) - eyes[:, 1]) / dy
    return np.minimum(np.abs(tx), np.abs(ty))


def _keep_clear(scene: Scene, eyes: np.ndarray) -> np.ndarray:
    """Eyes (n,3) pushed away from nearby surfaces until they are CLEARANCE_M from the sampled surface;
    the push is smoothed along the loop (over about 4 % of it) so the path stays smooth."""
    tree, surface = scene.surface_samples()
    sigma = max(1.0, 0.04 * len(eyes))
    for _ in range(12):
        dist, idx = tree.query(eyes)
        away = (eyes - surface[idx]) / np.maximum(dist, 1e-9)[:, None]
        push = np.clip(CLEARANCE_M - dist, 0.0, None)[:, None] * away
        eyes = eyes + 2.0 * gaussian_filter1d(push, sigma, axis=0, mode="wrap", truncate=3.0)
    return eyes


def trajectory(scene: Scene, n_frames: int) -> np.ndarray:
    """T_world_camera (n,4,4) of the loop for the scene's seed."""
    rng = np.random.default_rng([scene.seed, 1])
    s = np.arange(n_frames) / max(n_frames, 1)  # (n,) fraction of the loop
    theta = rng.uniform(0, 2 * np.pi) + 2 * np.pi * s
    p, (a, b) = LOOP_SQUARENESS, LOOP_RADII_M
    radius = (np.abs(np.cos(theta) / a) ** p + np.abs(np.sin(theta) / b) ** p) ** (-1.0 / p)
    lo, hi = HEIGHT_RANGE_M
    eyes = np.stack(
        [
            radius * np.cos(theta) + _wobble(rng, s, 0.1, range(2, 6)),
            radius * np.sin(theta) + _wobble(rng, s, 0.1, range(2, 6)),
            (lo + hi) / 2
            + 0.85 * (hi - lo) / 2 * np.sin(4 * np.pi * s + rng.uniform(0, 6))
            + _wobble(rng, s, 0.03, range(3, 7)),
        ],
        axis=1,
    )  # (n,3)
    eyes = _keep_clear(scene, eyes)
    start = np.pi * rng.integers(2, size=2)  # the first frame looks at the room centre at mid height
    sweep = YAW_SWEEP[0] * np.sin(2 * np.pi * YAW_SWEEP[1] * s + start[0])
    yaw = theta + np.pi + sweep + _wobble(rng, s, 0.15, range(4, 8))
    mean, amp, cycles = AIM_HEIGHT_M
    aim_z = mean + amp * np.sin(2 * np.pi * cycles * s + start[1])
    pitch = np.clip(np.arctan2(aim_z - eyes[:, 2], _distance_to_walls(eyes, yaw)), -0.8, 0.2)
    pitch = gaussian_filter1d(pitch, max(1.0, 0.012 * n_frames), mode="wrap")  # no kinks at room corners
    pitch += _wobble(rng, s, 0.04, range(5, 9))
    roll = _wobble(rng, s, 0.06, range(3, 8))
    forward = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], 1)
    poses = np.empty((n_frames, 4, 4))
    for i in range(n_frames):  # one pose per frame, not a per-pixel loop
        T = look_at(eyes[i], eyes[i] + forward[i])
        c, sn = np.cos(roll[i]), np.sin(roll[i])
        T[:3, :2] = T[:3, :2] @ np.array([[c, -sn], [sn, c]])  # roll about the optical axis
        poses[i] = T
    return poses
