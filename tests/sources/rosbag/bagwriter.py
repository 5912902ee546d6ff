"""Writers of small real bags (ROS 1 .bag, ROS 2 sqlite3 and mcap) with the rosbags writers, and a
synthetic RGB-D sequence with known colour, depth and poses to put in them."""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

KINDS = ("ros1", "sqlite3", "mcap")


@dataclass
class Frame:
    stamp_ns: int
    rgb: np.ndarray  # (H,W,3) uint8
    depth_m: np.ndarray  # (H,W) float32, whole millimetres so 16UC1 stores it exactly
    T_world_camera: np.ndarray  # (4,4)


def body_offset(R_body_camera: np.ndarray, lever_m: float) -> np.ndarray:
    """T_body_camera whose body origin sits on the camera's y axis (the synthetic path's yaw axis), so
    body poses stay linear in time and lerp + slerp between samples reproduce them exactly."""
    T = np.eye(4)
    T[:3, :3] = R_body_camera
    T[:3, 3] = -R_body_camera @ np.array([0.0, lever_m, 0.0])
    return T


def look_along_z(x: float, y: float, yaw_rad: float) -> np.ndarray:
    """Camera at (x, y, 0) looking along +z (world), turned by yaw about the camera's y axis."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", yaw_rad).as_matrix()
    T[:3, 3] = [x, y, 0.0]
    return T


def synthetic_frames(
    n: int = 10, width: int = 160, height: int = 120, rate_hz: float = 30.0
) -> tuple[list[Frame], np.ndarray]:
    """A textured plane z = 2 m seen by a camera sliding and turning; (frames, K (3,3))."""
    K = np.array([[140.0, 0.0, 79.5], [0.0, 140.0, 59.5], [0.0, 0.0, 1.0]])
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)  # (H,W,3)
    frames = []
    for i in range(n):
        T = look_along_z(0.02 * i, -0.01 * i, 0.03 * i)
        d = rays @ T[:3, :3].T  # (H,W,3) world directions with camera z = 1
        t = (2.0 - T[2, 3]) / d[..., 2]  # (H,W) camera depth to the plane
        hit = T[:3, 3] + t[..., None] * d  # (H,W,3)
        checker = (np.floor(hit[..., 0] / 0.2) + np.floor(hit[..., 1] / 0.2)) % 2  # (H,W) 0 / 1
        wave_x, wave_y = 60 * np.sin(hit[..., 0] * 8.0), 60 * np.cos(hit[..., 1] * 6.0)  # smooth colour
        rgb = np.stack(
            [
                88 + 120 * checker + 0.3 * wave_x,
                114 + 100 * checker + 0.5 * wave_x,
                104 + 80 * checker + 0.5 * wave_y,
            ],
            axis=-1,
        )
        rgb = rgb.clip(0, 255).astype(np.uint8)  # (H,W,3) a luminance checker (0.2 m) under smooth colour
        depth = (np.round(t * 1000.0) / 1000.0).astype(np.float32)
        depth[:4, :6] = 0.0  # a patch of invalid depth
        frames.append(Frame(1_700_000_000 * 10**9 + round(i * 1e9 / rate_hz), rgb, depth, T))
    return frames, K


@dataclass
class BagOptions:
    rgb: str = "rgb8"  # rgb8 | bgr8 | rgba8 | bgra8 | mono8 | png | jpeg
    depth: str = "16UC1"  # 16UC1 | 32FC1 | cd16 | cd32 (compressedDepth)
    camera_info: bool = True
    info_size: tuple[int, int] | None = None  # (w, h) written into CameraInfo (default: the image size)
    poses: str = "pose"  # pose (PoseStamped) | odom | transform (TransformStamped) | tf | none
    body_offset: np.ndarray | None = (
        None  # T_body_camera: poses/tf describe the body, tf_static links the camera
    )
    row_padding: int = 0  # extra bytes per image row (step > width * bytes per pixel)
    bigendian: bool = False
    depth_delay_ns: int = 12_000_000
    pose_times_ns: list[int] = field(default_factory=list)  # default: every frame stamp +- 5 ms
    rgb_topic: str = "/camera/color/image_raw"
    depth_topic: str = "/camera/depth/image_rect_raw"
    ros1_compression: str = ""  # "" | lz4 | bz2 chunks in ROS 1 bags
    chunk_bytes: int = 0  # ROS 1 chunk size threshold (0 = the writer's 1 MiB)
    corrupt_depth_at: int = -1  # frame whose depth message is cut short (its data misses rows)
    extra_topics: bool = True  # add an IMU-like distraction: an infrared mono8 image topic


class BagBuilder:
    """Message construction for one ROS generation on top of a rosbags writer."""

    def __init__(self, path: Path, kind: str, opt: BagOptions) -> None:
        self.ros2 = kind != "ros1"
        self.ts = get_typestore(Stores.ROS2_HUMBLE if self.ros2 else Stores.ROS1_NOETIC)
        if "tf2_msgs/msg/TFMessage" not in self.ts.types:
            self.ts.register(
                get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
            )
        if self.ros2:
            plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
            self.writer: Any = Writer2(path, version=9, storage_plugin=plugin)
        else:
            self.writer = Writer1(path)
            if opt.ros1_compression:
                self.writer.set_compression(Writer1.CompressionFormat[opt.ros1_compression.upper()])
            if opt.chunk_bytes:
                self.writer.chunk_threshold = opt.chunk_bytes
        self.conns: dict[str, Any] = {}
        self.pending: list[tuple[int, int, str, Any]] = []

    def __enter__(self) -> BagBuilder:
        self.writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        """Messages go to the file in log-time order, as a recorder writes them."""
        for log_ns, _, topic, msg in sorted(self.pending, key=lambda m: m[:2]):
            self._write(topic, msg, log_ns)
        self.writer.close()

    def msg(self, typename: str, **kw: Any) -> Any:
        return self.ts.types[typename](**kw)

    def header(self, stamp_ns: int, frame: str) -> Any:
        time = self.msg("builtin_interfaces/msg/Time", sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        extra = {} if self.ros2 else {"seq": 0}
        return self.msg("std_msgs/msg/Header", stamp=time, frame_id=frame, **extra)

    def write(self, topic: str, msg: Any, log_ns: int) -> None:
        self.pending.append((log_ns, len(self.pending), topic, msg))

    def _write(self, topic: str, msg: Any, log_ns: int) -> None:
        typename = msg.__msgtype__
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, typename, typestore=self.ts)
        conn = self.conns[topic]
        data = self.ts.serialize_cdr(msg, typename) if self.ros2 else self.ts.serialize_ros1(msg, typename)
        self.writer.write(conn, log_ns, data)

    def image(self, stamp_ns: int, frame: str, pixels: np.ndarray, enc: str, opt: BagOptions) -> Any:
        h, w = pixels.shape[:2]
        row = pixels.reshape(h, -1).view(np.uint8) if pixels.dtype == np.uint8 else None
        if row is None:
            dtype = pixels.dtype.newbyteorder(">" if opt.bigendian else "<")
            row = pixels.astype(dtype).reshape(h, w, -1).view(np.uint8).reshape(h, -1)
        data = np.concatenate([row, np.full((h, opt.row_padding), 7, np.uint8)], axis=1)
        return self.msg(
            "sensor_msgs/msg/Image", header=self.header(stamp_ns, frame), height=h, width=w, encoding=enc,
            is_bigendian=int(opt.bigendian), step=data.shape[1], data=data.reshape(-1),
        )  # fmt: skip

    def compressed(self, stamp_ns: int, frame: str, fmt: str, data: bytes) -> Any:
        buf = np.frombuffer(data, np.uint8)
        return self.msg(
            "sensor_msgs/msg/CompressedImage", header=self.header(stamp_ns, frame), format=fmt, data=buf
        )

    def camera_info(self, stamp_ns: int, frame: str, K: np.ndarray, size: tuple[int, int]) -> Any:
        roi = self.msg(
            "sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        P = np.concatenate([K, np.zeros((3, 1))], axis=1).reshape(-1)
        mats = {"d": np.zeros(5), "k": K.reshape(-1).astype(np.float64), "r": np.eye(3).reshape(-1), "p": P}
        mats = mats if self.ros2 else {k.upper(): v for k, v in mats.items()}
        return self.msg(
            "sensor_msgs/msg/CameraInfo", header=self.header(stamp_ns, frame), width=size[0], height=size[1],
            distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi, **mats,
        )  # fmt: skip

    def pose(self, T: np.ndarray) -> Any:
        x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
        point = self.msg("geometry_msgs/msg/Point", x=T[0, 3], y=T[1, 3], z=T[2, 3])
        quat = self.msg("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w)
        return self.msg("geometry_msgs/msg/Pose", position=point, orientation=quat)

    def transform(self, stamp_ns: int, parent: str, child: str, T: np.ndarray) -> Any:
        p = self.pose(T)
        vec = self.msg("geometry_msgs/msg/Vector3", x=p.position.x, y=p.position.y, z=p.position.z)
        tr = self.msg("geometry_msgs/msg/Transform", translation=vec, rotation=p.orientation)
        return self.msg(
            "geometry_msgs/msg/TransformStamped",
            header=self.header(stamp_ns, parent),
            child_frame_id=child,
            transform=tr,
        )

    def odometry(self, stamp_ns: int, parent: str, child: str, T: np.ndarray) -> Any:
        zero = self.msg("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)
        twist = self.msg("geometry_msgs/msg/Twist", linear=zero, angular=zero)
        return self.msg(
            "nav_msgs/msg/Odometry", header=self.header(stamp_ns, parent), child_frame_id=child,
            pose=self.msg("geometry_msgs/msg/PoseWithCovariance", pose=self.pose(T), covariance=np.zeros(36)),
            twist=self.msg("geometry_msgs/msg/TwistWithCovariance", twist=twist, covariance=np.zeros(36)),
        )  # fmt: skip


def compressed_depth(depth_m: np.ndarray, encoding: str) -> bytes:
    """compressedDepth payload: 12-byte header (format, quant A, quant B) then a 16-bit PNG."""
    if encoding == "16UC1":
        png = np.round(depth_m * 1000).astype(np.uint16)
        quant_a = quant_b = 0.0
    else:  # inverse-depth quantisation of compressed_depth_image_transport (depth_max 10 m, quantisation 100)
        quant_a = 100.0 * 101.0
        quant_b = 1.0 - quant_a / 10.0
        with np.errstate(divide="ignore"):
            inv = np.where(depth_m > 0, quant_a / depth_m + quant_b, 0.0)
        png = np.round(inv).astype(np.uint16)
    ok, buf = cv2.imencode(".png", png)
    assert ok
    return struct.pack("<iff", 0, quant_a, quant_b) + buf.tobytes()


def _write_rgb(bag: BagBuilder, f: Frame, opt: BagOptions) -> None:
    if opt.rgb in ("png", "jpeg"):
        ok, buf = cv2.imencode(
            "." + ("jpg" if opt.rgb == "jpeg" else "png"), cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR)
        )
        msg = bag.compressed(
            f.stamp_ns, "camera_color_optical_frame", f"rgb8; {opt.rgb} compressed bgr8", buf.tobytes()
        )
        bag.write(opt.rgb_topic.rstrip("/") + "/compressed", msg, f.stamp_ns)
        return
    px = {
        "rgb8": f.rgb, "bgr8": f.rgb[..., ::-1], "mono8": f.rgb[..., 0],
        "rgba8": np.dstack([f.rgb, np.full(f.rgb.shape[:2], 255, np.uint8)]),
        "bgra8": np.dstack([f.rgb[..., ::-1], np.full(f.rgb.shape[:2], 255, np.uint8)]),
    }[opt.rgb]  # fmt: skip
    bag.write(
        opt.rgb_topic,
        bag.image(f.stamp_ns, "camera_color_optical_frame", np.ascontiguousarray(px), opt.rgb, opt),
        f.stamp_ns,
    )


def _write_depth(bag: BagBuilder, f: Frame, opt: BagOptions, corrupt: bool = False) -> None:
    stamp = f.stamp_ns + opt.depth_delay_ns
    frame = "camera_depth_optical_frame"
    if opt.depth in ("cd16", "cd32"):
        enc = "16UC1" if opt.depth == "cd16" else "32FC1"
        msg = bag.compressed(stamp, frame, f"{enc}; compressedDepth png", compressed_depth(f.depth_m, enc))
        bag.write(opt.depth_topic + "/compressedDepth", msg, stamp)
        return
    px = np.round(f.depth_m * 1000).astype(np.uint16) if opt.depth == "16UC1" else f.depth_m
    msg = bag.image(stamp, frame, px, opt.depth, opt)
    if corrupt:
        msg.data = msg.data[: msg.data.size // 2]
    bag.write(opt.depth_topic, msg, stamp)


def _write_poses(bag: BagBuilder, frames: list[Frame], opt: BagOptions, K: np.ndarray) -> None:
    body = np.eye(4) if opt.body_offset is None else opt.body_offset
    child = "camera_depth_optical_frame" if opt.body_offset is None else "base_link"
    if opt.body_offset is not None:
        static = bag.transform(frames[0].stamp_ns, child, "camera_depth_optical_frame", body)
        bag.write("/tf_static", bag.msg("tf2_msgs/msg/TFMessage", transforms=[static]), frames[0].stamp_ns)
    times = opt.pose_times_ns or [f.stamp_ns + d for f in frames for d in (-5_000_000, 5_000_000)]
    stamps = [f.stamp_ns + opt.depth_delay_ns for f in frames]
    for t in times:
        T_world_body = interpolate_truth(frames, stamps, t) @ np.linalg.inv(body)
        if opt.poses == "pose":
            msg = bag.msg(
                "geometry_msgs/msg/PoseStamped", header=bag.header(t, "world"), pose=bag.pose(T_world_body)
            )
            bag.write("/camera_pose", msg, t)
        elif opt.poses == "odom":
            bag.write("/odom", bag.odometry(t, "odom", child, T_world_body), t)
        elif opt.poses == "transform":
            bag.write("/vicon/rig", bag.transform(t, "vicon", child, T_world_body), t)
        elif opt.poses == "tf":
            msg = bag.msg(
                "tf2_msgs/msg/TFMessage", transforms=[bag.transform(t, "world", child, T_world_body)]
            )
            bag.write("/tf", msg, t)


def interpolate_truth(frames: list[Frame], stamps_ns: list[int], t_ns: int) -> np.ndarray:
    """The synthetic camera path is linear in (x, y, yaw) over time: the exact pose at any time."""
    i = (t_ns - stamps_ns[0]) / (stamps_ns[1] - stamps_ns[0])  # integer differences keep ns precision
    return look_along_z(0.02 * i, -0.01 * i, 0.03 * i)


def write_bag(
    path: Path, kind: str, frames: list[Frame], K: np.ndarray, opt: BagOptions | None = None
) -> Path:
    """Write `frames` into a new bag at `path` (a .bag file for ros1, a folder for ROS 2); returns it."""
    opt = opt or BagOptions()
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames[0].depth_m.shape
    with BagBuilder(path, kind, opt) as bag:
        for i, f in enumerate(frames):
            if opt.camera_info:
                info = bag.camera_info(f.stamp_ns, "camera_depth_optical_frame", K, opt.info_size or (w, h))
                bag.write("/camera/depth/camera_info", info, f.stamp_ns)
            _write_rgb(bag, f, opt)
            _write_depth(bag, f, opt, corrupt=i == opt.corrupt_depth_at)
            if opt.extra_topics:
                ir = bag.image(
                    f.stamp_ns, "camera_infra1_optical_frame", f.rgb[..., 1].copy(), "mono8", BagOptions()
                )
                bag.write("/camera/infra1/image_rect_raw", ir, f.stamp_ns)
        if opt.poses != "none":
            _write_poses(bag, frames, opt, K)
    return path


def storage_file(bag_dir: Path) -> Path:
    """The single .db3 / .mcap file inside a ROS 2 bag folder."""
    (f,) = [p for p in bag_dir.iterdir() if p.suffix in (".db3", ".mcap")]
    return f
