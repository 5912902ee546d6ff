"""ROS 1 / ROS 2 bags as a frame source (no ROS install: the `rosbags` library).

- source.py: `RosbagSource`, frames of a bag with their poses and intrinsics;
- bag_file.py: one opened bag behind a small lazy interface; recover.py: what survives of a damaged bag;
- topics.py: choosing the colour, depth, CameraInfo and pose topics (and `bag_info`);
- decode.py: image and CameraInfo messages into arrays; frames.py: depth and colour paired by stamp;
- poses.py, trajectory.py: pose tracks, the tf tree and the camera trajectory at the depth stamps.
"""

from h2viz.sources.rosbag.source import RosbagSource
from h2viz.sources.rosbag.topics import bag_info

__all__ = ["RosbagSource", "bag_info"]
