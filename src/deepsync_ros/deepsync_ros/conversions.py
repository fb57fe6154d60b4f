"""Core types <-> rclpy messages: the one module the nodes convert through.

The field-by-field mapping lives once, in :mod:`deepsync.bag.convert`, which bag replay and the
simulator use with rosbags' message classes; here it is bound to rclpy's generated classes
(imported from their packages, e.g. ``deepsync_msgs.msg``), whose variable-length arrays take an
``array.array`` of the field's type code. So a node publishes exactly what ``deepsync replay``
writes into a bag, and what it reads from a topic becomes the same core types. Importing this
module needs no ROS; building a message needs the built message packages on the path.
"""

from __future__ import annotations

import array
import functools
import importlib
from typing import Any

import numpy as np

from deepsync.bag import convert
from deepsync.bag.convert import (  # readers work on rclpy's messages as on rosbags'
    ANTENNA_FRAME_ID,
    ENVELOPE_FRAME_ID,
    MAP_FRAME_ID,
    MessageTypes,
    cell_timing_array_from_msg,
    envelope_from_msg,
    position_from_pose_msg,
    prior_from_pose_msg,
    stamp_to_ns,
    sync_window_array_from_msg,
)
from deepsync.geo import LocalFrame
from deepsync.types import EnvelopeChunk, Fix, StackArrivals, StackWindows

# array.array type codes of the ROS primitive types our T[] fields use (native order: every
# platform ROS 2 Jazzy supports is little-endian, the order the core hands the values in)
_TYPECODES = {np.dtype("<i2"): "h", np.dtype("<f4"): "f", np.dtype("<f8"): "d"}


@functools.cache
def message_class(name: str) -> type:
    """rclpy's class of the ROS type ``pkg/msg/Name``, e.g. ``deepsync_msgs/msg/CellTiming``."""
    package, kind, type_name = name.split("/")
    module = importlib.import_module(f"{package}.{kind}")
    return getattr(module, type_name)


def to_array(values: np.ndarray) -> array.array:
    """A little-endian numpy array -> the ``array.array`` a generated ``T[]`` setter takes."""
    try:
        code = _TYPECODES[values.dtype]
    except KeyError:
        raise ValueError(f"no ROS sequence type for numpy dtype {values.dtype}") from None
    return array.array(code, np.ascontiguousarray(values).tobytes())


RCLPY_TYPES = MessageTypes(message_class, to_array)
"""rclpy's message classes, for :mod:`deepsync.bag.convert`'s builders."""


def envelope_to_msg(chunk: EnvelopeChunk, frame_id: str = ENVELOPE_FRAME_ID) -> Any:
    """``deepsync_msgs/EnvelopeSamples`` of one ADC chunk."""
    return convert.envelope_to_msg(chunk, frame_id=frame_id, store=RCLPY_TYPES)


def sync_window_array_to_msg(stack: StackWindows, frame_id: str = ENVELOPE_FRAME_ID) -> Any:
    """``deepsync_msgs/SyncWindowArray`` of one stack's cells."""
    return convert.sync_window_array_to_msg(stack, frame_id=frame_id, store=RCLPY_TYPES)


def cell_timing_array_to_msg(arrivals: StackArrivals, frame_id: str = ENVELOPE_FRAME_ID) -> Any:
    """``deepsync_msgs/CellTimingArray`` of one stack's arrivals."""
    return convert.cell_timing_array_to_msg(arrivals, frame_id=frame_id, store=RCLPY_TYPES)


def fix_to_pose_msg(fix: Fix, frame_id: str = MAP_FRAME_ID) -> Any:
    """``geometry_msgs/PoseWithCovarianceStamped`` of a fix in ``map``."""
    return convert.fix_to_pose_msg(fix, frame_id=frame_id, store=RCLPY_TYPES)


def no_fix_to_navsat_msg(stamp_ns: int, frame_id: str = ANTENNA_FRAME_ID) -> Any:
    """``sensor_msgs/NavSatFix`` saying ``STATUS_NO_FIX`` for a stack without a fix."""
    return convert.no_fix_to_navsat_msg(stamp_ns, frame_id=frame_id, store=RCLPY_TYPES)


def fix_to_navsat_msg(fix: Fix, frame: LocalFrame, frame_id: str = ANTENNA_FRAME_ID) -> Any:
    """``sensor_msgs/NavSatFix`` of a fix, through the map origin ``frame``."""
    return convert.fix_to_navsat_msg(fix, frame, frame_id=frame_id, store=RCLPY_TYPES)


__all__ = [
    "ANTENNA_FRAME_ID",
    "ENVELOPE_FRAME_ID",
    "MAP_FRAME_ID",
    "RCLPY_TYPES",
    "cell_timing_array_from_msg",
    "cell_timing_array_to_msg",
    "envelope_from_msg",
    "envelope_to_msg",
    "fix_to_navsat_msg",
    "fix_to_pose_msg",
    "message_class",
    "no_fix_to_navsat_msg",
    "position_from_pose_msg",
    "prior_from_pose_msg",
    "stamp_to_ns",
    "sync_window_array_from_msg",
    "sync_window_array_to_msg",
    "to_array",
]
