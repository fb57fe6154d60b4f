"""Bag IO for the core: rosbag2 MCAP bags (``rosbags``, ROS 2 Jazzy types), no rclpy needed.

Simulated runs are recorded, and recordings replayed, through the same messages a live robot
uses (``deepsync_msgs`` parsed from its ``.msg`` files), so a bag written here plays with
``ros2 bag play`` and a bag recorded on a robot replays through the core stages.
"""

from .convert import (
    ENVELOPE_FRAME_ID,
    MAP_FRAME_ID,
    cell_timing_array_from_msg,
    cell_timing_array_to_msg,
    envelope_from_msg,
    envelope_to_msg,
    fix_to_navsat_msg,
    fix_to_pose_msg,
    make_header,
    ns_to_stamp,
    pose_to_msg,
    position_from_pose_msg,
    prior_from_pose_msg,
    stamp_to_ns,
    sync_window_array_from_msg,
    sync_window_array_to_msg,
)
from .errors import BagError, BagExistsError, MsgDefsNotFoundError
from .info import BagInfo, bag_info
from .msgdefs import MSG_NAMES, find_msg_dir, load_typestore, msgtype, typestore
from .mcapfile import CrcStatus
from .reader import BagInconsistency, BagMessage, BagReader, SalvageReader, read_envelope, read_messages
from .topics import (
    CELL_TIMING_TOPIC,
    ENVELOPE_TOPIC,
    NAMESPACE,
    NAV_SAT_FIX_TOPIC,
    POSE_TOPIC,
    RELIABLE_QOS,
    SENSOR_DATA_QOS,
    SYNC_WINDOWS_TOPIC,
    TOPIC_QOS,
    TRUTH_CELL_TIMING_TOPIC,
    TRUTH_POSE_TOPIC,
    relative_name,
)
from .writer import PROVENANCE_KEY, BagWriter, provenance_document

__all__ = [
    "CELL_TIMING_TOPIC",
    "ENVELOPE_FRAME_ID",
    "ENVELOPE_TOPIC",
    "MAP_FRAME_ID",
    "NAMESPACE",
    "MSG_NAMES",
    "NAV_SAT_FIX_TOPIC",
    "POSE_TOPIC",
    "PROVENANCE_KEY",
    "RELIABLE_QOS",
    "SENSOR_DATA_QOS",
    "SYNC_WINDOWS_TOPIC",
    "TOPIC_QOS",
    "TRUTH_CELL_TIMING_TOPIC",
    "TRUTH_POSE_TOPIC",
    "BagError",
    "BagExistsError",
    "BagInconsistency",
    "BagInfo",
    "BagMessage",
    "BagReader",
    "BagWriter",
    "CrcStatus",
    "MsgDefsNotFoundError",
    "SalvageReader",
    "bag_info",
    "cell_timing_array_from_msg",
    "cell_timing_array_to_msg",
    "envelope_from_msg",
    "envelope_to_msg",
    "find_msg_dir",
    "fix_to_navsat_msg",
    "fix_to_pose_msg",
    "load_typestore",
    "make_header",
    "msgtype",
    "ns_to_stamp",
    "pose_to_msg",
    "position_from_pose_msg",
    "prior_from_pose_msg",
    "provenance_document",
    "read_envelope",
    "read_messages",
    "relative_name",
    "stamp_to_ns",
    "sync_window_array_from_msg",
    "sync_window_array_to_msg",
    "typestore",
]
