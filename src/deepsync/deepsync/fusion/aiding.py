"""What the tracker takes besides the sites: absolute positions and odometry velocities.

A receiver that knows where it is, even briefly (a GNSS fix, a surveyed start, an operator's
pose), or how it moves (a robot's wheel or visual odometry), makes each heard site's range bias
observable: with the position pinned, what is left of a site's range is its bias (relative to
the receiver clock, which absorbs what all sites share). The tracker carries the biases on
after the anchor is gone (``fusion.tracker``); these are the measurements and their models, on
the tracker's time base (seconds after the fusion stage's reference instant).

**Positions** (:class:`PositionAid`): a direct measurement of the horizontal position (2-D; in
3-D the height too), with the source's covariance, tested against the track before use.

**Velocities** (:class:`VelocityAid`): odometry gives the velocity along its own frame's axes.
A ``map``-aligned velocity (an INS, a filter in ``map``) is a direct measurement. An odometry
frame (``odom``) is turned from ``map`` by a yaw ``psi`` nobody states, and wheel odometry has
a scale error ``s`` (tyre wear, slip): the measured velocity is ``(1 + s) R(-psi) v``, ``v`` the
map-frame velocity, with ``psi`` and ``s`` tracker states once the track's displacement over a
stretch of odometry says where the odometry frame points (:func:`heading_offset`), or two
fixes and the odometry between them do (:func:`frame_offset`). Before that, a standstill (zero
velocity in every frame) is still a measurement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from deepsync.types import wrap_angle


@dataclass(frozen=True)
class PositionAid:
    """An absolute position at ``time_s``: ``map`` ENU metres and their covariance (m^2)."""

    time_s: float
    position_enu: np.ndarray  # (3,)
    covariance: np.ndarray  # (3, 3)
    source: str = "GNSS fix"


@dataclass(frozen=True)
class VelocityAid:
    """A horizontal velocity at ``time_s`` (m/s) along the axes of ``map`` (``in_map_frame``) or
    of an odometry frame, and its covariance (m^2/s^2)."""

    time_s: float
    velocity: np.ndarray  # (2,)
    covariance: np.ndarray  # (2, 2)
    in_map_frame: bool = False
    heading_rad: float | None = None  # the body's heading in the velocity's frame, where known


def rotation(angle: float) -> np.ndarray:
    """The 2-D rotation by ``angle`` (rad, counter-clockwise)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def odometry_velocity(v_map: np.ndarray, psi: float, scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                           np.ndarray]:
    """What an odometry frame turned by ``psi`` from ``map``, with scale error ``scale``, reads
    for the map-frame velocity ``v_map``; and its Jacobians by ``v_map`` (2x2), ``psi`` and
    ``scale`` (2,): ``h = (1 + s) R(-psi) v``."""
    turn = rotation(-psi)
    seen = turn @ v_map
    # d R(-psi) / d psi = R(-psi) @ [[0, 1], [-1, 0]]
    by_psi = turn @ np.array([v_map[1], -v_map[0]])
    return (1 + scale) * seen, (1 + scale) * turn, (1 + scale) * by_psi, seen


def heading_offset(in_map: np.ndarray, in_odometry: np.ndarray, odometry_covariance: np.ndarray
                   ) -> tuple[float, np.ndarray, float]:
    """The odometry frame's yaw from ``map``, from one vector seen in both (the track's
    displacement over a stretch, ``in_map``, and the odometry's over the same stretch): ``psi``
    (rad, wrapped to +-pi), its gradient by ``in_map`` (to carry the track's uncertainty into
    ``psi`` with its correlations) and the variance the odometry's own noise adds."""
    values, by_map, covariance = frame_offset(in_map, in_odometry, odometry_covariance)
    return float(values[0]), by_map[0], float(covariance[0, 0])


def frame_offset(in_map: np.ndarray, in_odometry: np.ndarray, odometry_covariance: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The odometry frame's yaw ``psi`` and scale error ``s`` from one vector seen in both:
    the angle between them (wrapped to +-pi), and ``s = |in_odometry| / |in_map| - 1`` (the
    odometry reads ``(1 + s) R(-psi)`` of the map's vector, and a rotation keeps its length);
    their Jacobian by ``in_map`` (2x2, rows psi and s) and the covariance (2x2) the odometry's
    own noise adds."""
    map_length2, odometry_length2 = float(in_map @ in_map), float(in_odometry @ in_odometry)
    psi = wrap_angle(math.atan2(in_map[1], in_map[0]) - math.atan2(in_odometry[1], in_odometry[0]))
    ratio = math.sqrt(odometry_length2 / map_length2)
    by_map = np.array([[-in_map[1], in_map[0]], [-ratio * in_map[0], -ratio * in_map[1]]]) / map_length2
    by_odometry = np.array([np.array([in_odometry[1], -in_odometry[0]]) / odometry_length2,
                            in_odometry / math.sqrt(odometry_length2 * map_length2)])
    return np.array([psi, ratio - 1.0]), by_map, by_odometry @ odometry_covariance @ by_odometry.T
