"""Core types <-> ROS messages: every message conversion lives in this one module.

The same builders serve two kinds of message classes, told apart by :class:`MessageTypes`:
rosbags' (bags written and read without ROS: the simulator, replay, the demo) and rclpy's
(the nodes, through ``deepsync_ros.conversions``). They differ only in where a class comes from
and in what a variable-length array field takes: rosbags serialises numpy arrays, only in the
exact dtype of the field, contiguous and little-endian (``int16[]`` wants ``'<i2'``); rclpy's
generated setters take an ``array.array`` of the field's type code (a numpy array fails their
type check). Fixed-size arrays (``float64[36]``) are numpy in both. Scalar fields must be plain
Python ``int`` / ``float`` in both, so every builder normalises its inputs instead of trusting
the caller. Readers accept either kind: ``np.asarray`` reads numpy and ``array.array`` alike.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from rosbags.typesys.store import Typestore

from ..geo import LocalFrame
from ..types import (
    UNMEASURED_VARIANCE,
    CellTiming,
    EnvelopeChunk,
    Fix,
    GnssFix,
    OdometryVelocity,
    PositionPrior,
    StackArrivals,
    StackWindows,
    SyncWindow,
)
from .msgdefs import msgtype, typestore

ENVELOPE_FRAME_ID = "envelope_adc"
"""Frame of the ADC stream; timing results in stream sample indices carry it too."""
MAP_FRAME_ID = "map"
"""REP-105 local ENU frame of the ground-truth pose."""

_NS_PER_S = 1_000_000_000
_MAX_STAMP_NS = (2**31) * _NS_PER_S  # builtin_interfaces/Time.sec is int32

ENVELOPE_SAMPLES = msgtype("EnvelopeSamples")
CELL_TIMING = msgtype("CellTiming")
CELL_TIMING_ARRAY = msgtype("CellTimingArray")
SYNC_WINDOW = msgtype("SyncWindow")
SYNC_WINDOW_ARRAY = msgtype("SyncWindowArray")
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
NAV_SAT_FIX = "sensor_msgs/msg/NavSatFix"
ANTENNA_FRAME_ID = "deepsync_antenna"
"""Frame of the receiver antenna, where a ``NavSatFix`` is measured (REP-105: a child of base_link)."""


@dataclass(frozen=True)
class MessageTypes:
    """Where message classes come from and what their variable-length arrays take.

    ``resolve`` maps a full type name (``deepsync_msgs/msg/CellTiming``) to its class;
    ``sequence`` turns a contiguous little-endian numpy array, already in the field's dtype,
    into the value a ``T[]`` field takes.
    """

    resolve: Callable[[str], type]
    sequence: Callable[[np.ndarray], Any]


def rosbags_types(store: Typestore) -> MessageTypes:
    """rosbags' classes from ``store``; arrays stay numpy."""
    return MessageTypes(store.types.__getitem__, lambda values: values)


Types = Typestore | MessageTypes | None
"""What the builders take: rosbags' store (None: ours, :func:`~deepsync.bag.typestore`) or any
:class:`MessageTypes` (rclpy's, in ``deepsync_ros.conversions``)."""


def _types(store: Types) -> MessageTypes:
    if isinstance(store, MessageTypes):
        return store
    return rosbags_types(typestore() if store is None else store)


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds."""
    return int(stamp.sec) * _NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(stamp_ns: int, store: Types = None) -> Any:
    """Integer nanoseconds -> ``builtin_interfaces/Time``; refuses what int32 sec can't hold."""
    stamp_ns = int(stamp_ns)
    if not 0 <= stamp_ns < _MAX_STAMP_NS:
        raise ValueError(f"stamp {stamp_ns} ns is outside builtin_interfaces/Time [0, 2^31 s)")
    time_cls = _types(store).resolve("builtin_interfaces/msg/Time")
    sec, nanosec = divmod(stamp_ns, _NS_PER_S)
    return time_cls(sec=sec, nanosec=nanosec)


def make_header(stamp_ns: int, frame_id: str, store: Types = None) -> Any:
    """``std_msgs/Header`` with the given stamp (ns) and frame."""
    header_cls = _types(store).resolve("std_msgs/msg/Header")
    return header_cls(stamp=ns_to_stamp(stamp_ns, store), frame_id=str(frame_id))


def envelope_to_msg(chunk: EnvelopeChunk, *, frame_id: str = ENVELOPE_FRAME_ID, store: Types = None) -> Any:
    """:class:`EnvelopeChunk` -> ``deepsync_msgs/msg/EnvelopeSamples`` (stamp = first sample)."""
    types = _types(store)
    return types.resolve(ENVELOPE_SAMPLES)(
        header=make_header(chunk.stamp_ns, frame_id, types),
        sample_rate=float(chunk.sample_rate),
        first_sample_index=int(chunk.first_sample_index),
        adc_bits=int(chunk.adc_bits),
        volts_per_code=float(chunk.volts_per_code),
        samples=types.sequence(np.ascontiguousarray(chunk.samples, dtype="<i2")),
    )


def envelope_from_msg(msg: Any) -> EnvelopeChunk:
    """``deepsync_msgs/msg/EnvelopeSamples`` -> :class:`EnvelopeChunk` (samples copied, owned)."""
    return EnvelopeChunk(
        stamp_ns=stamp_to_ns(msg.header.stamp),
        sample_rate=float(msg.sample_rate),
        first_sample_index=int(msg.first_sample_index),
        adc_bits=int(msg.adc_bits),
        volts_per_code=float(msg.volts_per_code),
        samples=np.array(msg.samples, dtype="<i2"),
    )


def _optional_drift(drift: float | None) -> float:
    return math.nan if drift is None else float(drift)


def _drift_from_msg(value: float) -> float | None:
    drift = float(value)
    return None if math.isnan(drift) else drift


def cell_timing_array_to_msg(arrivals: StackArrivals, *, frame_id: str = ENVELOPE_FRAME_ID,
                             store: Types = None) -> Any:
    """One stack's arrivals -> ``deepsync_msgs/msg/CellTimingArray`` (every header at the stack's
    stamp; 0 / NaN for unknowns)."""
    types = _types(store)
    header = make_header(arrivals.stamp_ns, frame_id, types)
    cells = [
        types.resolve(CELL_TIMING)(
            header=header,
            pci=int(r.pci),
            toa=float(r.toa),
            toa_std=float(r.toa_std),
            snr_db=float(r.snr_db),
            earfcn=0 if r.earfcn is None else int(r.earfcn),
            amplitude=float(r.amplitude),
            estimator=str(r.estimator),
        )
        for r in arrivals.cells
    ]
    return types.resolve(CELL_TIMING_ARRAY)(
        header=header, first_sample_index=int(arrivals.first_sample_index), sample_rate=float(arrivals.sample_rate),
        clock_drift_ppm=_optional_drift(arrivals.clock_drift_ppm), cells=cells, **_stack_fields(arrivals.stack))


def cell_timing_array_from_msg(msg: Any) -> StackArrivals:
    """``deepsync_msgs/msg/CellTimingArray`` -> the stack's arrivals; ValueError on a value no
    arrival can have (the message names which)."""
    cells = tuple(
        CellTiming(
            pci=int(c.pci),
            toa=float(c.toa),
            toa_std=float(c.toa_std),
            snr_db=float(c.snr_db),
            estimator=str(c.estimator),
            earfcn=int(c.earfcn) or None,
            amplitude=float(c.amplitude),
        )
        for c in msg.cells
    )
    return StackArrivals(stamp_to_ns(msg.header.stamp), int(msg.first_sample_index), float(msg.sample_rate), cells,
                         _drift_from_msg(msg.clock_drift_ppm), _stack_from_msg(msg))


def sync_window_array_to_msg(stack: StackWindows, *, frame_id: str = ENVELOPE_FRAME_ID, store: Types = None) -> Any:
    """One stack's cells -> ``deepsync_msgs/msg/SyncWindowArray`` (0 / -1 / empty / NaN for unknowns)."""
    types = _types(store)
    cells = [
        types.resolve(SYNC_WINDOW)(
            header=make_header(w.stamp_ns, frame_id, types),
            pci=int(w.pci),
            earfcn=0 if w.earfcn is None else int(w.earfcn),
            carrier_frequency=0.0 if w.carrier_hz is None else float(w.carrier_hz),
            coarse_index=int(w.coarse_index),
            peak_metric=float(w.peak_metric),
            snr_db=float(w.snr_db),
            n_frames=int(w.n_frames),
            window_length=int(w.window_length),
            windows=types.sequence(np.ascontiguousarray(w.windows, dtype="<f4").ravel()),
            cosited_pci=-1 if w.cosited_pci is None else int(w.cosited_pci),
            site_coefficients=types.sequence(np.asarray(w.site_coefficients or (), dtype="<f4")),
            bandwidth_mhz=0.0 if w.bandwidth_mhz is None else float(w.bandwidth_mhz),
        )
        for w in stack.windows
    ]
    frame = np.zeros(0, dtype="<f4") if stack.frame is None else np.ascontiguousarray(stack.frame, dtype="<f4")
    return types.resolve(SYNC_WINDOW_ARRAY)(
        header=make_header(stack.stamp_ns, frame_id, types), first_sample_index=int(stack.first_sample_index),
        sample_rate=float(stack.sample_rate), clock_drift_ppm=_optional_drift(stack.clock_drift_ppm), cells=cells,
        frame=types.sequence(frame), frame_delay=float(stack.frame_delay), **_stack_fields(stack.stack))


def sync_window_array_from_msg(msg: Any) -> StackWindows:
    """``deepsync_msgs/msg/SyncWindowArray`` -> the stack's cells; ValueError if a cell's window
    array does not hold n_frames x window_length values, or on a time base no stack can have."""
    windows = []
    for c in msg.cells:
        values = np.array(c.windows, dtype=np.float32)
        if values.size != int(c.n_frames) * int(c.window_length):
            raise ValueError(f"SyncWindow of PCI {c.pci}: {values.size} window values, but n_frames x "
                             f"window_length = {c.n_frames} x {c.window_length}")
        coefficients = tuple(float(x) for x in c.site_coefficients)
        windows.append(SyncWindow(
            stamp_ns=stamp_to_ns(c.header.stamp),
            pci=int(c.pci),
            coarse_index=int(c.coarse_index),
            windows=values.reshape(int(c.n_frames), int(c.window_length)),
            peak_metric=float(c.peak_metric),
            snr_db=float(c.snr_db),
            earfcn=int(c.earfcn) or None,
            carrier_hz=float(c.carrier_frequency) or None,
            cosited_pci=None if c.cosited_pci < 0 else int(c.cosited_pci),
            site_coefficients=coefficients or None,
            bandwidth_mhz=float(c.bandwidth_mhz) or None,
        ))
    frame = np.array(msg.frame, dtype=np.float32)
    return StackWindows(stamp_to_ns(msg.header.stamp), int(msg.first_sample_index), float(msg.sample_rate),
                        tuple(windows), _drift_from_msg(msg.clock_drift_ppm), frame if frame.size else None,
                        float(msg.frame_delay), _stack_from_msg(msg))


def _stack_fields(stack: tuple[int, int] | None) -> dict[str, int]:
    """A stack's (n_frames, hop_frames) as a message's ``stack_frames``, ``stack_hop_frames`` (0: not said)."""
    frames, hop = stack or (0, 0)
    return {"stack_frames": int(frames), "stack_hop_frames": int(hop)}


def _stack_from_msg(msg: Any) -> tuple[int, int] | None:
    """(n_frames, hop_frames) of a message's stacks; None where it does not say (0: a ground truth)."""
    frames, hop = int(msg.stack_frames), int(msg.stack_hop_frames)
    if frames == hop == 0:
        return None
    if not 1 <= hop <= frames:
        raise ValueError(f"stack_frames {frames} and stack_hop_frames {hop}: a stack of n frames starts 1 to n "
                         "frames after the last (0 and 0: not said)")
    return frames, hop


def _pose(types: MessageTypes, x: float, y: float, z: float) -> Any:
    """A ``geometry_msgs/Pose`` at (x, y, z) with the identity quaternion (no orientation measured)."""
    return types.resolve("geometry_msgs/msg/Pose")(
        position=types.resolve("geometry_msgs/msg/Point")(x=float(x), y=float(y), z=float(z)),
        orientation=types.resolve("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0),
    )


def pose_to_msg(stamp_ns: int, x: float, y: float, z: float, *, frame_id: str = MAP_FRAME_ID,
                store: Types = None) -> Any:
    """Receiver position (ENU metres in ``map``) -> ``geometry_msgs/msg/PoseStamped``.

    Orientation is the identity quaternion: the truth we simulate is a position only.
    """
    for name, value in (("x", x), ("y", y), ("z", z)):
        if not math.isfinite(value):
            raise ValueError(f"pose {name}={value!r} must be finite")
    types = _types(store)
    return types.resolve(POSE_STAMPED)(header=make_header(stamp_ns, frame_id, types), pose=_pose(types, x, y, z))


def position_from_pose_msg(msg: Any) -> tuple[float, float, float]:
    """``geometry_msgs/msg/PoseStamped`` or ``PoseWithCovarianceStamped`` -> (x, y, z) in metres
    of ``msg.header.frame_id``."""
    pose = msg.pose.pose if hasattr(msg.pose, "covariance") else msg.pose
    p = pose.position
    return float(p.x), float(p.y), float(p.z)


def _yaw(orientation: Any) -> float | None:
    """The yaw (rad) of a ``geometry_msgs/Quaternion``; None where it is not a finite unit
    quaternion."""
    x, y, z, w = (float(orientation.x), float(orientation.y), float(orientation.z), float(orientation.w))
    norm2 = x * x + y * y + z * z + w * w
    if not (math.isfinite(norm2) and abs(norm2 - 1.0) < 1e-3):
        return None
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def prior_from_pose_msg(msg: Any) -> PositionPrior:
    """``geometry_msgs/msg/PoseWithCovarianceStamped`` (an operator's initial pose: RViz's "2D
    Pose Estimate" on ``/initialpose``) -> the tracker's :class:`PositionPrior` in the message's
    frame. The position block of the 6x6 covariance is kept; an axis given no variance (RViz
    sends none for z) is unmeasured. The heading is the orientation's yaw where the yaw has a
    variance (RViz: (pi/12)^2) and the orientation is a unit quaternion, else none. ValueError
    for a covariance no tracker can start from (not finite, not symmetric, x or y without a
    variance)."""
    full = np.asarray(msg.pose.covariance, dtype=np.float64)[:36].reshape(6, 6)
    covariance = np.array(full[:3, :3])
    if not np.all(np.isfinite(covariance)):
        raise ValueError("initial pose: its covariance is not finite")
    if not (covariance[0, 0] > 0 and covariance[1, 1] > 0):
        raise ValueError(f"initial pose: x and y need a variance > 0 m^2, got {covariance[0, 0]!r} and "
                         f"{covariance[1, 1]!r} (the pose's covariance says how far off the position may be)")
    if not covariance[2, 2] > 0:
        covariance[2, :] = covariance[:, 2] = 0.0
        covariance[2, 2] = UNMEASURED_VARIANCE
    heading = _yaw(msg.pose.pose.orientation) if math.isfinite(full[5, 5]) and 0 < full[5, 5] <= math.pi**2 else None
    try:
        return PositionPrior(position_from_pose_msg(msg), covariance, heading,
                             None if heading is None else math.sqrt(full[5, 5]))
    except ValueError as error:
        raise ValueError(f"initial pose: {error}") from None


def fix_to_pose_msg(fix: Fix, *, frame_id: str = MAP_FRAME_ID, store: Types = None) -> Any:
    """A fix -> ``geometry_msgs/msg/PoseWithCovarianceStamped`` in ``map`` (ENU, REP-103/105).

    The covariance is 6x6 row-major over (x, y, z, roll, pitch, yaw): the fix's ENU block, and
    :data:`~deepsync.types.UNMEASURED_VARIANCE` on the orientation a position fix does not
    measure (the identity quaternion stands in for it).
    """
    types = _types(store)
    covariance = np.zeros((6, 6))
    covariance[:3, :3] = fix.covariance
    covariance[3:, 3:] = np.eye(3) * UNMEASURED_VARIANCE
    x, y, z = fix.position_enu
    return types.resolve(POSE_WITH_COVARIANCE_STAMPED)(
        header=make_header(fix.stamp_ns, frame_id, types),
        pose=types.resolve("geometry_msgs/msg/PoseWithCovariance")(
            pose=_pose(types, x, y, z), covariance=np.ascontiguousarray(covariance.ravel(), dtype="<f8")),
    )


NAV_SAT_STATUS_NO_FIX = -1  # sensor_msgs/NavSatStatus.STATUS_NO_FIX
NAV_SAT_COVARIANCE_UNKNOWN = 0  # sensor_msgs/NavSatFix.COVARIANCE_TYPE_UNKNOWN


def no_fix_to_navsat_msg(stamp_ns: int, *, frame_id: str = ANTENNA_FRAME_ID, store: Types = None) -> Any:
    """A stack without a fix -> ``sensor_msgs/msg/NavSatFix`` as a GNSS driver says it has none:
    ``STATUS_NO_FIX``, covariance type ``COVARIANCE_TYPE_UNKNOWN``, latitude, longitude and
    altitude NaN (no position, rather than a plausible-looking 0, 0)."""
    types = _types(store)
    status = types.resolve("sensor_msgs/msg/NavSatStatus")(status=NAV_SAT_STATUS_NO_FIX, service=0)
    return types.resolve(NAV_SAT_FIX)(
        header=make_header(stamp_ns, frame_id, types),
        status=status,
        latitude=math.nan,
        longitude=math.nan,
        altitude=math.nan,
        position_covariance=np.zeros(9, dtype="<f8"),
        position_covariance_type=NAV_SAT_COVARIANCE_UNKNOWN,
    )


def fix_to_navsat_msg(fix: Fix, frame: LocalFrame, *, frame_id: str = ANTENNA_FRAME_ID, store: Types = None) -> Any:
    """A fix -> ``sensor_msgs/msg/NavSatFix``: WGS84 latitude, longitude and ellipsoidal altitude of
    the ``map`` position, the ENU covariance as ``COVARIANCE_TYPE_KNOWN``, status ``STATUS_FIX``
    (no GNSS service: the bits name satellite systems)."""
    types = _types(store)
    latitude, longitude, height = frame.enu_to_geodetic(np.asarray(fix.position_enu, dtype=np.float64))
    status = types.resolve("sensor_msgs/msg/NavSatStatus")(status=0, service=0)  # STATUS_FIX
    return types.resolve(NAV_SAT_FIX)(
        header=make_header(fix.stamp_ns, frame_id, types),
        status=status,
        latitude=float(latitude),
        longitude=float(longitude),
        altitude=float(height),
        position_covariance=np.ascontiguousarray(np.asarray(fix.covariance, dtype=np.float64).ravel(), dtype="<f8"),
        position_covariance_type=3,  # COVARIANCE_TYPE_KNOWN
    )




def gnss_fix_from_msg(msg: Any) -> GnssFix | None:
    """``sensor_msgs/msg/NavSatFix`` -> :class:`GnssFix`; None for ``STATUS_NO_FIX`` (a receiver
    saying it has none). Its ENU covariance where the message states one (approximated,
    diagonal or full), else None. ValueError naming what is not a position (NaN latitude, a
    covariance that is not one)."""
    if int(msg.status.status) == NAV_SAT_STATUS_NO_FIX:
        return None
    covariance = None
    if int(msg.position_covariance_type) != NAV_SAT_COVARIANCE_UNKNOWN:
        covariance = np.asarray(msg.position_covariance, dtype=np.float64)[:9].reshape(3, 3)
    try:
        return GnssFix(stamp_to_ns(msg.header.stamp), float(msg.latitude), float(msg.longitude), float(msg.altitude),
                       covariance, str(msg.header.frame_id))
    except ValueError as error:
        raise ValueError(f"NavSatFix in frame {msg.header.frame_id!r}: {error}") from None


def odometry_from_msg(msg: Any, map_frame: str, min_std_mps: float) -> OdometryVelocity:
    """``nav_msgs/msg/Odometry`` -> the horizontal velocity along the axes of its frame
    (``header.frame_id``; the twist is in ``child_frame_id``, the body, turned into the frame by
    the pose's yaw), its covariance turned alike and no axis taken as better than
    ``min_std_mps`` (an odometry that states none, zeros, gets that). ``in_map_frame`` when the
    frame is ``map_frame``; ``heading_rad`` the pose's yaw. ValueError naming what is not a
    velocity it can use."""
    q = msg.pose.pose.orientation
    twist = msg.twist.twist.linear
    body = np.array([float(twist.x), float(twist.y)])
    covariance = np.asarray(msg.twist.covariance, dtype=np.float64)[:36].reshape(6, 6)[:2, :2]
    where = f"Odometry in frame {msg.header.frame_id!r}"
    yaw = _yaw(q)
    if yaw is None:
        raise ValueError(f"{where}: its orientation {[float(q.x), float(q.y), float(q.z), float(q.w)]} is not a unit "
                         "quaternion")
    if not (np.all(np.isfinite(body)) and np.all(np.isfinite(covariance))):
        raise ValueError(f"{where}: its twist or twist covariance is not finite")
    turn = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    variances, axes = np.linalg.eigh(0.5 * (covariance + covariance.T))
    floored = (axes * np.maximum(variances, min_std_mps**2)) @ axes.T
    try:
        return OdometryVelocity(stamp_to_ns(msg.header.stamp), tuple(turn @ body), turn @ floored @ turn.T,
                                str(msg.header.frame_id).lstrip("/") == map_frame, yaw)
    except ValueError as error:
        raise ValueError(f"{where}: {error}") from None
