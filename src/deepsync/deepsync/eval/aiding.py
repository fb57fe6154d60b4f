"""Simulated anchors and odometry for a route evaluation, drawn from the route's ground truth.

What ``evaluate-route --gnss-interval S --gnss-std M --odometry-std F`` gives the tracker:

* **GNSS fixes** every ``S`` seconds of the recording from its first stack (``S`` = 0: one, at
  the start), the true antenna position off by N(0, M^2) per horizontal axis (3 M up), each
  claiming that covariance: a receiver that runs its GNSS for a moment now and then.
* **Odometry** at ``rate_hz``: the true horizontal velocity seen from an odometry frame turned
  by a yaw nobody states (drawn once, then wandering as a gyro's drift does), scaled by a
  scale error (drawn with sigma ``F``, then wandering slowly), plus white noise of ``F`` times
  the speed and a 2 cm/s floor; the message claims ``(F |v|)^2 + 0.02^2`` per axis, the white
  noise alone: the scale and the yaw are the slow bias a wheel's odometry carries, for the
  tracker to estimate. With ``odometry_in_map``, the same velocities turned back into ``map`` by
  the frame's first yaw (a robot that turns its wheel odometry into map by a compass): the
  yaw's wander and the scale error stay in them. Each velocity carries the body's heading in
  its frame (the odometry pose's yaw), the body facing the way it moves.

Everything is drawn from ``seed``: the same plan gives the same fixes for the same route. A set
of routes evaluated with one plan takes each recording's own seed (:meth:`AidingPlan.for_recording`),
so its routes' draws are independent of each other.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from deepsync.geo import LocalFrame
from deepsync.types import GnssFix, OdometryVelocity, wrap_angle

ODOMETRY_NOISE_FLOOR_MPS = 0.02
ODOMETRY_YAW_WANDER_RAD_PER_SQRT_S = 0.002  # a MEMS gyro's yaw drift, ~0.7 deg per minute
ODOMETRY_SCALE_WANDER_PER_SQRT_S = 1e-4
STANDING_MPS = 0.1  # slower than this the body's heading is not read from its motion


@dataclass(frozen=True)
class AidingPlan:
    """Which aiding a route evaluation simulates: GNSS fixes every ``gnss_interval_s`` (None:
    none; 0: only at the start) with ``gnss_std_m`` per horizontal axis, and odometry with a
    fractional error ``odometry_std`` (None: none) at ``odometry_rate_hz``, in its own frame or
    (``odometry_in_map``) in ``map``."""

    gnss_interval_s: float | None = None
    gnss_std_m: float = 5.0
    odometry_std: float | None = None
    odometry_rate_hz: float = 10.0
    seed: int = 0
    odometry_in_map: bool = False

    def __post_init__(self) -> None:
        checks = {
            "gnss_interval_s": self.gnss_interval_s is None or (_number(self.gnss_interval_s)
                                                               and 0 <= self.gnss_interval_s <= 86_400),
            "gnss_std_m": _number(self.gnss_std_m) and 0 < self.gnss_std_m <= 1e4,
            "odometry_std": self.odometry_std is None or (_number(self.odometry_std) and 0 < self.odometry_std <= 1),
            "odometry_rate_hz": _number(self.odometry_rate_hz) and 0.1 <= self.odometry_rate_hz <= 1000,
            "seed": isinstance(self.seed, int) and not isinstance(self.seed, bool) and 0 <= self.seed < 2**63,
            "odometry_in_map": isinstance(self.odometry_in_map, bool),
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"{name}: {getattr(self, name)!r} is out of range")

    def for_recording(self, recording: str) -> AidingPlan:
        """The plan with the draws of the recording named ``recording`` (:func:`recording_seed`)."""
        return dataclasses.replace(self, seed=recording_seed(self.seed, recording))

    @property
    def describes(self) -> str:
        """The plan in words, for a report."""
        parts = []
        if self.gnss_interval_s is not None:
            when = "at the start" if self.gnss_interval_s == 0 else f"every {self.gnss_interval_s:g} s"
            parts.append(f"GNSS {when} ({self.gnss_std_m:g} m)")
        if self.odometry_std is not None:
            parts.append(f"odometry{' in map' if self.odometry_in_map else ''} ({self.odometry_std:.0%} error)")
        return ", ".join(parts) or "no aiding"

    def gnss_fixes(self, start_ns: int, end_ns: int, position_at: Callable[[int], np.ndarray],
                   frame: LocalFrame) -> list[GnssFix]:
        """Fixes from ``start_ns`` to ``end_ns`` along a true track (``position_at``: ENU in ``frame``)."""
        if self.gnss_interval_s is None:
            return []
        rng = np.random.default_rng([self.seed, 1])
        step = round(self.gnss_interval_s * 1e9)
        times = [start_ns] if step == 0 else range(start_ns, end_ns + 1, step)
        fixes = []
        for stamp in times:
            noisy = position_at(stamp) + rng.normal(0.0, self.gnss_std_m, 3) * np.array([1.0, 1.0, 3.0])
            latitude, longitude, height = frame.enu_to_geodetic(noisy)
            covariance = np.diag([self.gnss_std_m**2, self.gnss_std_m**2, (3 * self.gnss_std_m) ** 2])
            fixes.append(GnssFix(int(stamp), float(latitude), float(longitude), float(height), covariance, "gnss"))
        return fixes

    def odometry(self, start_ns: int, end_ns: int, stamps_ns: np.ndarray, positions: np.ndarray) -> list[OdometryVelocity]:
        """Odometry velocities from ``start_ns`` to ``end_ns`` along a true track (its poses at
        ``stamps_ns``), in an odometry frame (see the module docstring)."""
        if self.odometry_std is None:
            return []
        rng = np.random.default_rng([self.seed, 2])
        period = 1.0 / self.odometry_rate_hz
        times = np.arange(float(start_ns), float(end_ns), period * 1e9)
        n = len(times)
        yaw = rng.uniform(-math.pi, math.pi) + np.cumsum(
            rng.normal(0.0, ODOMETRY_YAW_WANDER_RAD_PER_SQRT_S * math.sqrt(period), n))
        scale = self.odometry_std * rng.standard_normal() + np.cumsum(
            rng.normal(0.0, ODOMETRY_SCALE_WANDER_PER_SQRT_S * math.sqrt(period), n))
        velocities = _velocities(stamps_ns, positions, times)
        into_map = yaw[0] if self.odometry_in_map else 0.0
        out = []
        facing = None  # the body faces the way it moves, and keeps facing it when it stops
        for stamp, v, turn, s in zip(times, velocities, yaw, scale):
            sigma = math.hypot(self.odometry_std * float(np.hypot(*v)), ODOMETRY_NOISE_FLOOR_MPS)
            c, si = math.cos(turn - into_map), math.sin(turn - into_map)
            seen = (1 + s) * np.array([c * v[0] + si * v[1], -si * v[0] + c * v[1]]) + rng.normal(0.0, sigma, 2)
            if (moving := true_heading(v)) is not None:
                facing = moving
            out.append(OdometryVelocity(int(stamp), (float(seen[0]), float(seen[1])), np.eye(2) * sigma**2,
                                        self.odometry_in_map,
                                        None if facing is None else wrap_angle(facing - turn + into_map)))
        return out


def recording_seed(seed: int, recording: str) -> int:
    """``seed`` made particular to the recording named ``recording``: the same for the same
    name, independent from one recording to the next, so that a set of routes evaluated with one
    plan does not give every route the same GNSS errors, odometry errors and start offset."""
    return int(np.random.SeedSequence([seed, zlib.crc32(recording.encode())]).generate_state(1)[0])


def true_heading(velocity: np.ndarray) -> float | None:
    """The way a body moving at ``velocity`` (m/s, horizontal) faces, rad from east; None for one
    that stands (slower than ``STANDING_MPS``)."""
    if float(np.hypot(velocity[0], velocity[1])) < STANDING_MPS:
        return None
    return math.atan2(velocity[1], velocity[0])


def _number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _velocities(stamps_ns: np.ndarray, positions: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The true horizontal velocity at ``times`` (the track's piecewise-linear slope)."""
    t = (np.asarray(stamps_ns) - stamps_ns[0]).astype(np.float64) * 1e-9
    slopes = np.diff(positions[:, :2], axis=0) / np.diff(t)[:, None]
    segment = np.clip(np.searchsorted(t, (times - stamps_ns[0]) * 1e-9, side="right") - 1, 0, len(slopes) - 1)
    return slopes[segment]
