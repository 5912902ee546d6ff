"""The camera trajectory of a bag: T_world_camera at the depth stamps, from a pose topic (PoseStamped,
Odometry, TransformStamped) or the tf tree, followed by the body->camera link when poses describe a body."""

from __future__ import annotations

import logging

import numpy as np

from h2viz.config import RosbagConfig
from h2viz.errors import SourceError
from h2viz.sources.rosbag.bag_file import BagFile
from h2viz.sources.rosbag.poses import TF_TYPE, PoseTrack, TfTree, pose_sample
from h2viz.sources.rosbag.topics import TopicChoice

log = logging.getLogger("h2viz.sources.rosbag")


def read_tf(bag: BagFile, dynamic: bool, origin_ns: int) -> TfTree:
    """/tf_static, and /tf too when `dynamic`, as a tree with times in seconds after `origin_ns`."""
    tree = TfTree()
    names = {t: t.lstrip("/") for t, i in bag.topics.items() if i.msgtype == TF_TYPE}
    wanted = [t for t, n in names.items() if n == "tf_static" or (dynamic and n == "tf")]
    for raw in bag.messages(wanted):
        tree.add(bag.decode(raw), names[raw.topic] == "tf_static", origin_ns)
    return tree


def _world_frame(bag: BagFile, tree: TfTree, world: str, described: str) -> str:
    """`world` when tf links it to `described`, else the root of `described`'s tree (logged)."""
    if described not in tree.frames:
        raise SourceError(
            f"{bag.path}: frame '{described}' is not in /tf (frames: {', '.join(sorted(tree.frames))}); "
            "set source.rosbag.camera_frame (or body_frame) to one of them"
        )
    world = world.lstrip("/")
    if world in tree.frames and tree.connected(world, described):
        return world
    root = tree.root(described)
    log.info("%s: world frame '%s' is not linked to '%s' in /tf; using the root '%s' of its tree "
             "(set source.rosbag.world_frame)", bag.path.name, world, described, root)  # fmt: skip
    return root


def _body_camera(bag: BagFile, cfg: RosbagConfig, tree: TfTree, described: str, camera: str) -> np.ndarray:
    """T_body_camera from the config, else from /tf_static, else identity (poses are the camera's)."""
    if cfg.T_body_camera:
        if len(cfg.T_body_camera) != 16:
            raise SourceError("source.rosbag.T_body_camera must hold 16 numbers (a row-major 4x4 matrix)")
        return np.asarray(cfg.T_body_camera, dtype=np.float64).reshape(4, 4)
    if described == camera:
        return np.eye(4)
    T = tree.static_lookup(described, camera)
    if T is not None:
        log.info(
            "%s: poses describe '%s'; camera '%s' attached through /tf_static",
            bag.path.name,
            described,
            camera,
        )
        return T
    if cfg.body_frame:
        raise SourceError(
            f"{bag.path}: no static transform from body frame '{described}' to camera frame '{camera}' in "
            "/tf_static; set source.rosbag.T_body_camera=[16 numbers, row-major]"
        )
    log.info("%s: poses describe '%s'; taken as the camera pose (set source.rosbag.body_frame and "
             "T_body_camera if they are not)", bag.path.name, described)  # fmt: skip
    return np.eye(4)


def camera_trajectory(
    bag: BagFile, topics: TopicChoice, cfg: RosbagConfig, camera: str, times_ns: np.ndarray, origin_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """T_world_camera (N,4,4) at the depth stamps `times_ns` (N,) and validity (N,)."""
    gap, span = cfg.max_time_gap_s, cfg.max_pose_gap_s
    times_s = (times_ns - origin_ns) * 1e-9  # (N,) small numbers keep float64 at ns precision
    tree = read_tf(bag, topics.tf, origin_ns)
    if topics.tf:
        if cfg.T_body_camera and not cfg.body_frame:
            raise SourceError(
                "source.rosbag.T_body_camera needs source.rosbag.body_frame when poses come from /tf"
            )
        described = cfg.body_frame.lstrip("/") or camera
        world = _world_frame(bag, tree, cfg.world_frame, described)
        T, ok = tree.lookup(world, described, times_s, gap, span)
    else:
        samples = [pose_sample(bag.decode(r), r.msgtype) for r in bag.messages([topics.pose])]
        if not samples:
            raise SourceError(
                f"{bag.path}: pose topic {topics.pose} has no readable messages; set source.rosbag.pose_topic"
            )
        track = PoseTrack.build([((s.stamp_ns - origin_ns) * 1e-9, s.t_xyz, s.q_xyzw) for s in samples])
        T, ok = track.sample(times_s, gap, span)
        described = cfg.body_frame.lstrip("/") or samples[0].child or camera
    return T @ _body_camera(bag, cfg, tree, described, camera), ok
