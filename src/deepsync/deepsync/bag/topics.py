"""Topic names of DeepSync bags and the QoS each is offered with.

``ros2 bag play`` republishes a topic with the QoS recorded in the bag, so the bag must say what
a live publisher would offer: the ADC stream is sensor data (best effort, keep last), ground
truth is reliable. Durations use RMW's "infinite" (what a Jazzy publisher reports for defaults).
"""

from __future__ import annotations

from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)

NAMESPACE = "/deepsync"
"""The namespace our nodes run in (the launch file's default): their relative topic names,
e.g. ``envelope``, resolve to the topics below, so a bag plays straight into the nodes."""
ENVELOPE_TOPIC = "/deepsync/envelope"
TRUTH_POSE_TOPIC = "/deepsync/truth/pose"
TRUTH_CELL_TIMING_TOPIC = "/deepsync/truth/cell_timing"
SYNC_WINDOWS_TOPIC = "/deepsync/sync_windows"  # the sync stage's cells and windows
CELL_TIMING_TOPIC = "/deepsync/cell_timing"  # the timing stage's arrivals
POSE_TOPIC = "/deepsync/pose"  # fusion's fix in map, with covariance
NAV_SAT_FIX_TOPIC = "/deepsync/fix"  # the same fix in WGS84
INITIAL_POSE_TOPIC = "/initialpose"  # an operator's pose (RViz, Nav2): outside our namespace, where they publish it
GNSS_FIX_TOPIC = "/deepsync/gnss/fix"  # a GNSS receiver's NavSatFix, fusion's anchors (remap a driver's onto it)
MAP_SITES_TOPIC = "/deepsync/map_sites"  # the tower sites, heard or not, as GeoJSON for Foxglove's Map panel
ODOMETRY_TOPIC = "/deepsync/odometry"  # a robot's nav_msgs/Odometry, fusion's velocities (remap onto it)

# RMW_DURATION_INFINITE = INT64_MAX ns, as rosbag2 (Jazzy) records it.
_INFINITE = QosTime(sec=9_223_372_036, nsec=854_775_807)


def make_qos(*, reliable: bool, depth: int = 10) -> Qos:
    """Keep-last, volatile, automatic-liveliness profile; reliable or best effort."""
    return Qos(
        history=QosHistory.KEEP_LAST,
        depth=depth,
        reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
        durability=QosDurability.VOLATILE,
        deadline=_INFINITE,
        lifespan=_INFINITE,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=_INFINITE,
        avoid_ros_namespace_conventions=False,
    )


SENSOR_DATA_QOS = make_qos(reliable=False)
"""Best effort, keep last 10, volatile: the ADC stream (late samples are useless, not retried)."""
RELIABLE_QOS = make_qos(reliable=True)
"""Reliable, keep last 10, volatile: ground truth and results (every message counts)."""

TOPIC_QOS: dict[str, Qos] = {
    ENVELOPE_TOPIC: SENSOR_DATA_QOS,
    TRUTH_POSE_TOPIC: RELIABLE_QOS,
    TRUTH_CELL_TIMING_TOPIC: RELIABLE_QOS,
    SYNC_WINDOWS_TOPIC: RELIABLE_QOS,
    CELL_TIMING_TOPIC: RELIABLE_QOS,
    POSE_TOPIC: RELIABLE_QOS,
    NAV_SAT_FIX_TOPIC: RELIABLE_QOS,
}
"""Offered QoS of the topics we know; any other topic is written as reliable."""


def relative_name(topic: str) -> str:
    """A topic of :data:`NAMESPACE` as a node's relative name: ``/deepsync/cell_timing`` -> ``cell_timing``."""
    prefix = NAMESPACE + "/"
    if not topic.startswith(prefix):
        raise ValueError(f"topic {topic!r} is not in the {NAMESPACE} namespace")
    return topic[len(prefix):]
