"""Message types of the normalised recording: standard ROS 2 types plus two uwbcal_msgs types."""

from __future__ import annotations

from functools import cache

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

UWB_RANGE = "uwbcal_msgs/msg/UwbRange"
FEATURE_TRACKS = "uwbcal_msgs/msg/FeatureTracks"
IMU = "sensor_msgs/msg/Imu"
IMAGE = "sensor_msgs/msg/Image"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POINT_STAMPED = "geometry_msgs/msg/PointStamped"
ODOMETRY = "nav_msgs/msg/Odometry"

UWB_RANGE_MSG = """\
# One UWB two-way range between a tag antenna on the robot and a fixed anchor.
std_msgs/Header header
uint32 tag_id
uint8 antenna
uint32 anchor_id
float64 distance
"""

FEATURE_TRACKS_MSG = """\
# Feature tracks of one camera frame: persistent track ids and raw (distorted) pixel coordinates.
std_msgs/Header header
uint32[] ids
float64[] u
float64[] v
"""


@cache
def typestore() -> Typestore:
    store = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    types.update(get_types_from_msg(UWB_RANGE_MSG, UWB_RANGE))
    types.update(get_types_from_msg(FEATURE_TRACKS_MSG, FEATURE_TRACKS))
    store.register(types)
    return store


@cache
def schema_text(msgtype: str) -> str:
    """The ros2msg schema (main definition followed by every dependency) for MCAP."""
    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return text
