"""Core types <-> rosbags message objects: every bag conversion lives in this one module.

rosbags serialises numpy arrays only in the exact dtype of the field, contiguous and
little-endian (``int16[]`` wants ``'<i2'``), and scalar float fields as plain Python floats, so
every builder here normalises its inputs instead of trusting the caller.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np
from rosbags.typesys.store import Typestore

from ..geo import LocalFrame
from ..types import UNMEASURED_VARIANCE, CellTiming, EnvelopeChunk, Fix, StackArrivals, SyncWindow
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


def _store(store: Typestore | None) -> Typestore:
    return typestore() if store is None else store


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds."""
    return int(stamp.sec) * _NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(stamp_ns: int, store: Typestore | None = None) -> Any:
    """Integer nanoseconds -> ``builtin_interfaces/Time``; refuses what int32 sec can't hold."""
    stamp_ns = int(stamp_ns)
    if not 0 <= stamp_ns < _MAX_STAMP_NS:
        raise ValueError(f"stamp {stamp_ns} ns is outside builtin_interfaces/Time [0, 2^31 s)")
    time_cls = _store(store).types["builtin_interfaces/msg/Time"]
    sec, nanosec = divmod(stamp_ns, _NS_PER_S)
    return time_cls(sec=sec, nanosec=nanosec)


def make_header(stamp_ns: int, frame_id: str, store: Typestore | None = None) -> Any:
    """``std_msgs/Header`` with the given stamp (ns) and frame."""
    header_cls = _store(store).types["std_msgs/msg/Header"]
    return header_cls(stamp=ns_to_stamp(stamp_ns, store), frame_id=str(frame_id))


def envelope_to_msg(
    chunk: EnvelopeChunk, *, frame_id: str = ENVELOPE_FRAME_ID, store: Typestore | None = None
) -> Any:
    """:class:`EnvelopeChunk` -> ``deepsync_msgs/msg/EnvelopeSamples`` (stamp = first sample)."""
    cls = _store(store).types[ENVELOPE_SAMPLES]
    return cls(
        header=make_header(chunk.stamp_ns, frame_id, store),
        sample_rate=float(chunk.sample_rate),
        first_sample_index=int(chunk.first_sample_index),
        adc_bits=int(chunk.adc_bits),
        volts_per_code=float(chunk.volts_per_code),
        samples=np.ascontiguousarray(chunk.samples, dtype="<i2"),
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


def cell_timing_array_to_msg(
    arrivals: StackArrivals,
    *,
    frame_id: str = ENVELOPE_FRAME_ID,
    store: Typestore | None = None,
) -> Any:
    """One stack's arrivals -> ``deepsync_msgs/msg/CellTimingArray`` (every header at the stack's
    stamp; 0 / NaN for unknowns)."""
    types = _store(store).types
    header = make_header(arrivals.stamp_ns, frame_id, store)
    cells = [
        types[CELL_TIMING](
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
    drift = math.nan if arrivals.clock_drift_ppm is None else float(arrivals.clock_drift_ppm)
    return types[CELL_TIMING_ARRAY](header=header, first_sample_index=int(arrivals.first_sample_index),
                                    sample_rate=float(arrivals.sample_rate), clock_drift_ppm=drift, cells=cells)


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
    drift = float(msg.clock_drift_ppm)
    return StackArrivals(stamp_to_ns(msg.header.stamp), int(msg.first_sample_index), float(msg.sample_rate), cells,
                         None if math.isnan(drift) else drift)


def sync_window_array_to_msg(
    stamp_ns: int,
    windows: Iterable[SyncWindow],
    *,
    frame_id: str = ENVELOPE_FRAME_ID,
    store: Typestore | None = None,
) -> Any:
    """One stack's cells -> ``deepsync_msgs/msg/SyncWindowArray`` (0 / -1 / empty for unknowns)."""
    types = _store(store).types
    cells = [
        types[SYNC_WINDOW](
            header=make_header(w.stamp_ns, frame_id, store),
            pci=int(w.pci),
            earfcn=0 if w.earfcn is None else int(w.earfcn),
            carrier_frequency=0.0 if w.carrier_hz is None else float(w.carrier_hz),
            coarse_index=int(w.coarse_index),
            peak_metric=float(w.peak_metric),
            snr_db=float(w.snr_db),
            n_frames=int(w.n_frames),
            window_length=int(w.window_length),
            windows=np.ascontiguousarray(w.windows, dtype="<f4").ravel(),
            cosited_pci=-1 if w.cosited_pci is None else int(w.cosited_pci),
            site_coefficients=np.asarray(w.site_coefficients or (), dtype="<f4"),
        )
        for w in windows
    ]
    return types[SYNC_WINDOW_ARRAY](header=make_header(stamp_ns, frame_id, store), cells=cells)


def sync_window_array_from_msg(msg: Any) -> list[SyncWindow]:
    """``deepsync_msgs/msg/SyncWindowArray`` -> one :class:`SyncWindow` per cell; ValueError if
    a cell's window array does not hold n_frames x window_length values."""
    out = []
    for c in msg.cells:
        values = np.array(c.windows, dtype=np.float32)
        if values.size != int(c.n_frames) * int(c.window_length):
            raise ValueError(f"SyncWindow of PCI {c.pci}: {values.size} window values, but n_frames x "
                             f"window_length = {c.n_frames} x {c.window_length}")
        coefficients = tuple(float(x) for x in c.site_coefficients)
        out.append(SyncWindow(
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
        ))
    return out


def pose_to_msg(
    stamp_ns: int,
    x: float,
    y: float,
    z: float,
    *,
    frame_id: str = MAP_FRAME_ID,
    store: Typestore | None = None,
) -> Any:
    """Receiver position (ENU metres in ``map``) -> ``geometry_msgs/msg/PoseStamped``.

    Orientation is the identity quaternion: the truth we simulate is a position only.
    """
    types = _store(store).types
    for name, value in (("x", x), ("y", y), ("z", z)):
        if not math.isfinite(value):
            raise ValueError(f"pose {name}={value!r} must be finite")
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(z)),
        orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    return types[POSE_STAMPED](header=make_header(stamp_ns, frame_id, store), pose=pose)


def position_from_pose_msg(msg: Any) -> tuple[float, float, float]:
    """``geometry_msgs/msg/PoseStamped`` -> (x, y, z) in metres of ``msg.header.frame_id``."""
    p = msg.pose.position
    return float(p.x), float(p.y), float(p.z)


def fix_to_pose_msg(fix: Fix, *, frame_id: str = MAP_FRAME_ID, store: Typestore | None = None) -> Any:
    """A fix -> ``geometry_msgs/msg/PoseWithCovarianceStamped`` in ``map`` (ENU, REP-103/105).

    The covariance is 6x6 row-major over (x, y, z, roll, pitch, yaw): the fix's ENU block, and
    :data:`~deepsync.types.UNMEASURED_VARIANCE` on the orientation a position fix does not
    measure (the identity quaternion stands in for it).
    """
    types = _store(store).types
    covariance = np.zeros((6, 6))
    covariance[:3, :3] = fix.covariance
    covariance[3:, 3:] = np.eye(3) * UNMEASURED_VARIANCE
    x, y, z = (float(v) for v in fix.position_enu)
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    return types[POSE_WITH_COVARIANCE_STAMPED](
        header=make_header(fix.stamp_ns, frame_id, store),
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.ascontiguousarray(
            covariance.ravel(), dtype="<f8")),
    )


def fix_to_navsat_msg(fix: Fix, frame: LocalFrame, *, frame_id: str = ANTENNA_FRAME_ID,
                      store: Typestore | None = None) -> Any:
    """A fix -> ``sensor_msgs/msg/NavSatFix``: WGS84 latitude, longitude and ellipsoidal altitude of
    the ``map`` position, the ENU covariance as ``COVARIANCE_TYPE_KNOWN``, status ``STATUS_FIX``
    (no GNSS service: the bits name satellite systems)."""
    types = _store(store).types
    latitude, longitude, height = frame.enu_to_geodetic(np.asarray(fix.position_enu, dtype=np.float64))
    status = types["sensor_msgs/msg/NavSatStatus"](status=0, service=0)  # STATUS_FIX
    return types[NAV_SAT_FIX](
        header=make_header(fix.stamp_ns, frame_id, store),
        status=status,
        latitude=float(latitude),
        longitude=float(longitude),
        altitude=float(height),
        position_covariance=np.ascontiguousarray(np.asarray(fix.covariance, dtype=np.float64).ravel(), dtype="<f8"),
        position_covariance_type=3,  # COVARIANCE_TYPE_KNOWN
    )
