"""Choosing the colour, depth, CameraInfo and pose topics of a bag (by message type, encoding and name,
or from the configured overrides) and the human-readable `bag_info` report."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from h2viz.config import RosbagConfig
from h2viz.errors import SourceError
from h2viz.sources.rosbag.bag_file import BagFile, TopicInfo
from h2viz.sources.rosbag.decode import CAMERA_INFO_TYPE, IMAGE_TYPES, image_encoding, is_depth_message
from h2viz.sources.rosbag.poses import POSE_TYPES, TF_TYPE

log = logging.getLogger("h2viz.sources.rosbag")

_COLOR_WORDS = ("rgb", "color", "colour")
_NOT_COLOR_WORDS = ("depth", "infra", "/ir", "ir/", "disparity", "mask", "label", "confidence")
_COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8uc3", "compressed")  # compressed: jpeg/png
_POSE_WORDS = ("ground", "truth", "gt", "mocap", "vicon", "optitrack", "camera", "pose")


@dataclass
class TopicChoice:
    """The topics h2viz reads, and one line per choice saying why."""

    rgb: str = ""
    depth: str = ""
    camera_info: str = ""
    pose: str = ""
    tf: bool = False  # poses come from /tf (+ /tf_static)
    notes: list[str] = field(default_factory=list)


def _namespace(topic: str) -> str:
    return topic.rsplit("/", 1)[0] if "/" in topic.strip("/") else ""


def _score_depth(topic: TopicInfo, msg: Any) -> float:
    """Depth encodings first; else 'depth' in the name when the pixels are not colour (-1 = not depth)."""
    name, enc = topic.name.lower(), image_encoding(msg)
    if is_depth_message(msg):
        score = 4.0
    elif "depth" in name and enc not in _COLOR_ENCODINGS:
        score = 1.0
    else:
        return -1
    score += 2.0 * ("depth" in name) + 1.0 * ("aligned" in name or "registered" in name)
    return score + 0.5 * topic.msgtype.endswith("/Image") - 0.5 * ("compressed" in name)


def _score_color(topic: TopicInfo, msg: Any) -> float:
    """Colour encodings, preferring rgb/color names and 3-channel raw images (-1 = not colour)."""
    name, enc = topic.name.lower(), image_encoding(msg)
    named_color = any(w in name for w in _COLOR_WORDS)
    if is_depth_message(msg) or enc not in _COLOR_ENCODINGS:
        return -1
    if any(w in name for w in _NOT_COLOR_WORDS) and not named_color:
        return -1
    score = 2.0 * named_color + 1.0 * ("image" in name) + 2.0 * (enc != "mono8")
    return score + 0.5 * topic.msgtype.endswith("/Image")


def _best(scores: dict[str, float], topics: dict[str, TopicInfo]) -> str:
    good = [(s, topics[t].count, t) for t, s in scores.items() if s >= 0]
    return max(good)[2] if good else ""


def _checked(bag: BagFile, topic: str, types: tuple[str, ...], option: str, what: str) -> str:
    info = bag.topics.get(topic)
    if info is None or info.msgtype not in types:
        have = [f"{t} ({i.msgtype})" for t, i in bag.topics.items() if i.msgtype in types]
        found = "not in the bag" if info is None else f"of type {info.msgtype}"
        raise SourceError(
            f"{bag.path}: {what} topic '{topic}' is {found}; topics of a usable type: "
            f"{', '.join(have) or 'none'}. Set {option}=<topic>"
        )
    return topic


def _pick_images(bag: BagFile, cfg: RosbagConfig, choice: TopicChoice) -> None:
    images = {t: i for t, i in bag.topics.items() if i.msgtype in IMAGE_TYPES and i.count > 0}
    firsts = {t: bag.first(t) for t in images if not (cfg.rgb_topic and cfg.depth_topic)}
    firsts = {t: m for t, m in firsts.items() if m is not None}
    if cfg.depth_topic:
        choice.depth = _checked(
            bag, cfg.depth_topic, tuple(IMAGE_TYPES), "source.rosbag.depth_topic", "depth"
        )
        choice.notes.append(f"depth: {choice.depth} (source.rosbag.depth_topic)")
    else:
        choice.depth = _best({t: _score_depth(images[t], m) for t, m in firsts.items()}, bag.topics)
        if choice.depth:
            choice.notes.append(f"depth: {choice.depth} ({image_encoding(firsts[choice.depth])})")
    if cfg.rgb_topic:
        choice.rgb = _checked(bag, cfg.rgb_topic, tuple(IMAGE_TYPES), "source.rosbag.rgb_topic", "colour")
        choice.notes.append(f"colour: {choice.rgb} (source.rosbag.rgb_topic)")
    else:
        scores = {t: _score_color(images[t], m) for t, m in firsts.items() if t != choice.depth}
        choice.rgb = _best(scores, bag.topics)
        if choice.rgb:
            choice.notes.append(f"colour: {choice.rgb} ({image_encoding(firsts[choice.rgb])})")


def _pick_camera_info(bag: BagFile, cfg: RosbagConfig, choice: TopicChoice) -> None:
    if cfg.camera_info_topic:
        choice.camera_info = _checked(
            bag, cfg.camera_info_topic, (CAMERA_INFO_TYPE,), "source.rosbag.camera_info_topic", "CameraInfo"
        )
        choice.notes.append(f"intrinsics: {choice.camera_info} (source.rosbag.camera_info_topic)")
        return
    infos = [t for t, i in bag.topics.items() if i.msgtype == CAMERA_INFO_TYPE and i.count > 0]
    for image in (choice.depth, choice.rgb):
        ns = _namespace(image) if image else None
        while ns is not None and not choice.camera_info:
            match = sorted(t for t in infos if _namespace(t) == ns)
            choice.camera_info = match[0] if match else ""
            ns = _namespace(ns) if ns else None
        if choice.camera_info:
            break
    if not choice.camera_info and len(infos) == 1:
        choice.camera_info = infos[0]
    if choice.camera_info:
        choice.notes.append(f"intrinsics: {choice.camera_info} (CameraInfo)")


def _pick_pose(bag: BagFile, cfg: RosbagConfig, choice: TopicChoice) -> None:
    if cfg.pose_topic:
        choice.pose = _checked(bag, cfg.pose_topic, POSE_TYPES, "source.rosbag.pose_topic", "pose")
        choice.notes.append(f"poses: {choice.pose} (source.rosbag.pose_topic)")
        return
    poses = {t: i for t, i in bag.topics.items() if i.msgtype in POSE_TYPES and i.count > 0}
    if poses:
        scores = {t: float(sum(w in t.lower() for w in _POSE_WORDS)) for t in poses}
        choice.pose = _best(scores, bag.topics)
        choice.notes.append(f"poses: {choice.pose} ({poses[choice.pose].msgtype.rsplit('/', 1)[-1]})")
    elif any(i.msgtype == TF_TYPE and t.lstrip("/") == "tf" for t, i in bag.topics.items()):
        choice.tf = True
        choice.notes.append(f"poses: /tf + /tf_static, world frame '{cfg.world_frame}'")


def discover(bag: BagFile, cfg: RosbagConfig) -> TopicChoice:
    """The topics to read: configured ones (checked) or the best candidates; logged at INFO."""
    choice = TopicChoice()
    _pick_images(bag, cfg, choice)
    _pick_camera_info(bag, cfg, choice)
    _pick_pose(bag, cfg, choice)
    for note in choice.notes:
        log.info("%s: %s", bag.path.name, note)
    return choice


def require(choice: TopicChoice, bag: BagFile) -> None:
    """SourceError naming the missing stream and the option that selects it."""
    images = ", ".join(t for t, i in bag.topics.items() if i.msgtype in IMAGE_TYPES) or "none"
    if not choice.depth:
        raise SourceError(
            f"{bag.path}: no depth image topic found (image topics: {images}); "
            "set source.rosbag.depth_topic=<topic>"
        )
    if not choice.rgb:
        raise SourceError(
            f"{bag.path}: no colour image topic found (image topics: {images}); "
            "set source.rosbag.rgb_topic=<topic>"
        )
    if not choice.pose and not choice.tf:
        raise SourceError(
            f"{bag.path}: no poses: no PoseStamped / Odometry / TransformStamped topic and no /tf; "
            "record the camera trajectory or set source.rosbag.pose_topic=<topic>"
        )


def bag_info(path: Path, cfg: RosbagConfig) -> str:
    """Printable report: every topic with type, count and mean rate, then what h2viz would read."""
    bag = BagFile(Path(path))
    try:
        first, last = bag.time_range_ns
        duration_s = max(0.0, (last - first) * 1e-9)
        kind = "ROS 2" if bag.ros2 else "ROS 1"
        lines = [
            f"{path}: {kind} bag, {duration_s:.2f} s, {sum(i.count for i in bag.topics.values())} messages"
        ]
        if bag.damage:
            lines.append(f"  damaged: {bag.damage}; only the messages before it are listed")
        width = max([len(t) for t in bag.topics] + [5])
        lines.append(f"  {'topic':<{width}}  {'count':>7}  {'rate Hz':>8}  type")
        for name, info in sorted(bag.topics.items()):
            rate = (info.count - 1) / duration_s if duration_s > 0 and info.count > 1 else 0.0
            lines.append(f"  {name:<{width}}  {info.count:>7}  {rate:>8.2f}  {info.msgtype}")
        choice = discover(bag, cfg)
        lines.append("h2viz would use:")
        lines += [f"  {note}" for note in choice.notes]
        if not choice.camera_info:
            lines.append("  intrinsics: no CameraInfo; set source.intrinsics.fx=... fy=... cx=... cy=...")
        for what, ok, option in (("depth", choice.depth, "depth_topic"), ("colour", choice.rgb, "rgb_topic")):
            if not ok:
                lines.append(f"  {what}: none found; set source.rosbag.{option}=<topic>")
        if not choice.pose and not choice.tf:
            lines.append("  poses: none found; set source.rosbag.pose_topic=<topic>")
        return "\n".join(lines)
    finally:
        bag.close()
