"""Receiver trajectory: a fixed point or a constant-speed walk along waypoints in the map frame.

Segments are straight lines in the local ENU frame (at the scales of a campus, the difference
from a geodesic is far below a millimetre). The walk starts at the first waypoint at t = 0 and,
unless it loops, stops at the last waypoint after ``length / speed`` seconds; before t = 0 the
receiver waits at the first waypoint. A looping route returns from the last waypoint to the
first and starts over. Speed changes at corners are instantaneous.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from deepsync.geo import LocalFrame


class Trajectory:
    """Receiver position and velocity over time, in a :class:`LocalFrame`."""

    def __init__(self, frame: LocalFrame, waypoints_enu: ArrayLike, speed_mps: float = 0.0,
                 loop: bool = False) -> None:
        points = np.asarray(waypoints_enu, dtype=np.float64).reshape(-1, 3)
        if not np.all(np.isfinite(points)):
            raise ValueError("waypoints contain NaN or inf")
        if not (np.isfinite(speed_mps) and speed_mps >= 0):
            raise ValueError(f"speed_mps must be >= 0, got {speed_mps!r}")
        self.frame = frame
        self.loop = bool(loop) and len(points) > 1
        if self.loop:
            points = np.vstack([points, points[:1]])
        self._points = points
        self._segments = np.diff(points, axis=0)
        lengths = np.linalg.norm(self._segments, axis=1)
        self._lengths = lengths
        self._starts = np.concatenate(([0.0], np.cumsum(lengths)))
        if len(points) > 1 and not (self.length_m > 0 and speed_mps > 0):
            raise ValueError("a route needs a positive length and a positive speed")
        self.speed_mps = float(speed_mps) if len(points) > 1 else 0.0

    @classmethod
    def fixed(cls, frame: LocalFrame, position_enu: ArrayLike) -> Trajectory:
        """A receiver that never moves."""
        return cls(frame, [position_enu])

    @property
    def waypoints_enu(self) -> np.ndarray:
        """(K, 3) waypoints in ENU (for a loop, the first one repeated at the end)."""
        return self._points.copy()

    @property
    def length_m(self) -> float:
        """Path length of one pass (0 for a fixed receiver)."""
        return float(self._starts[-1])

    @property
    def duration_s(self) -> float:
        """Time to walk one pass (0 for a fixed receiver)."""
        return self.length_m / self.speed_mps if self.speed_mps > 0 else 0.0

    def distance_along(self, t: ArrayLike) -> np.ndarray:
        """Where on the route the receiver is at time(s) ``t``: metres from the first waypoint
        along the path, in [0, length_m] (a loop starts over at 0; a fixed receiver is at 0)."""
        t = np.asarray(t, dtype=np.float64)
        s = self.speed_mps * np.maximum(t, 0.0)
        return np.mod(s, self.length_m) if self.loop else np.minimum(s, self.length_m)

    def _locate(self, t: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(segment index, distance along it, moving?) at times ``t``."""
        t = np.asarray(t, dtype=np.float64)
        s = self.distance_along(t)
        walked = self.speed_mps * np.maximum(t, 0.0)
        moving = (t >= 0) if self.loop else (t >= 0) & (walked < self.length_m)
        index = np.clip(np.searchsorted(self._starts, s, side="right") - 1,
                        0, len(self._segments) - 1)
        return index, s - self._starts[index], moving

    def position_enu(self, t: ArrayLike) -> np.ndarray:
        """ENU position (m) at time(s) ``t`` (s): shape ``np.shape(t) + (3,)``."""
        if len(self._points) == 1:
            return np.broadcast_to(self._points[0], np.shape(t) + (3,)).copy()
        index, along, _ = self._locate(t)
        lengths = self._lengths[index]
        fraction = np.divide(along, lengths, out=np.zeros_like(along), where=lengths > 0)
        return self._points[index] + fraction[..., None] * self._segments[index]

    def velocity_enu(self, t: ArrayLike) -> np.ndarray:
        """ENU velocity (m/s) at time(s) ``t``: shape ``np.shape(t) + (3,)``."""
        if len(self._points) == 1:
            return np.zeros(np.shape(t) + (3,))
        index, _, moving = self._locate(t)
        lengths = self._lengths[index]
        scale = np.divide(self.speed_mps, lengths, out=np.zeros_like(lengths),
                          where=(lengths > 0) & moving)
        return scale[..., None] * self._segments[index]

    def position_llh(self, t: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(latitude_deg, longitude_deg, ellipsoidal height_m) at time(s) ``t``."""
        return self.frame.enu_to_geodetic(self.position_enu(t))
