"""What the fusion nodes take besides the arrivals, and what they write back, without ROS.

:class:`AidingInputs` turns ``sensor_msgs/NavSatFix`` (``gnss/fix``) and ``nav_msgs/Odometry``
(``odometry``) messages into the fusion stage's GNSS fixes and odometry velocities
(``deepsync.fusion.aiding``), refuses with the reason what cannot be used (a fix with status
``NO_FIX`` is not a refusal: it is skipped and counted), and says in its diagnostics how recent
each input is: odometry older than ``odometry_timeout_s`` against the latest stack's ADC time is
stale, and the tracker then runs on its motion model alone. :class:`LearnedTowers` writes what
the tracker learned of each site as a tower database, atomically, when due and at shutdown; a
write that fails is reported and tried again, nothing learned is lost with it.
"""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path
from typing import Any

from deepsync.bag.convert import gnss_fix_from_msg, odometry_from_msg
from deepsync.fusion.stage import FusionStage
from deepsync.fusion.tracker import OdometryFrame
from deepsync.towers import write_tower_database
from deepsync.types import Health, HealthKind, Severity

from .health import Report


class AidingInputs:
    """GNSS fixes and odometry into one fusion stage, and their diagnostics."""

    def __init__(self, fusion: FusionStage, *, map_frame: str, antenna_frame: str, gnss_frame: str = "",
                 odometry_min_std_mps: float = 0.05, odometry_timeout_s: float = 1.0, use_gnss: bool = False,
                 use_odometry: bool = False, learned: LearnedTowers | None = None) -> None:
        self.fusion = fusion
        self.learned = learned
        self.map_frame = map_frame
        self.antenna_frame = antenna_frame
        self.gnss_frame = gnss_frame
        self.odometry_min_std_mps = odometry_min_std_mps
        self.odometry_timeout_s = odometry_timeout_s
        self.use_gnss = use_gnss
        self.use_odometry = use_odometry
        self.taken: Counter[str] = Counter()
        self.refused: Counter[str] = Counter()
        self.no_fix = 0  # NavSatFix messages saying STATUS_NO_FIX
        self.last_refusal: str | None = None
        self.latest_ns: dict[str, int] = {}  # of the latest GNSS fix and odometry taken
        self.stack_ns: int | None = None  # the latest stack's ADC time

    def gnss(self, message: Any) -> str | None:
        """A NavSatFix: taken (None), skipped for NO_FIX (None, counted), or refused (the reason)."""
        frame = str(message.header.frame_id).lstrip("/")
        if frame == self.antenna_frame:
            return self._refuse("gnss", f"NavSatFix in frame {frame!r} refused: that is this node's own output "
                                "(antenna_frame); gnss/fix must come from a GNSS receiver")
        if self.gnss_frame and frame != self.gnss_frame:
            return self._refuse("gnss", f"NavSatFix in frame {frame!r} refused: gnss_frame is {self.gnss_frame!r}")
        try:
            fix = gnss_fix_from_msg(message)
        except ValueError as error:
            return self._refuse("gnss", str(error))
        if fix is None:
            self.no_fix += 1
            return None
        return self._hand("gnss", fix.stamp_ns, self.fusion.add_gnss(fix))

    def odometry(self, message: Any) -> str | None:
        """An Odometry message: taken (None) or refused (the reason)."""
        try:
            velocity = odometry_from_msg(message, self.map_frame, self.odometry_min_std_mps)
        except ValueError as error:
            return self._refuse("odometry", str(error))
        return self._hand("odometry", velocity.stamp_ns, self.fusion.add_odometry(velocity))

    def stacked(self, stamp_ns: int, events: tuple[Health, ...]) -> None:
        """A stack was fused: its ADC time, and what fusion refused of the aiding since."""
        self.stack_ns = stamp_ns
        for event in events:
            if event.kind is HealthKind.AIDING_REFUSED:
                self.refused["later"] += 1
                self.last_refusal = event.message

    def _hand(self, kind: str, stamp_ns: int, refused: Health | None) -> str | None:
        if refused is not None:
            return self._refuse(kind, refused.message)
        self.taken[kind] += 1
        self.latest_ns[kind] = stamp_ns
        return None

    def _refuse(self, kind: str, why: str) -> str:
        self.refused[kind] += 1
        self.last_refusal = why
        return why

    def _age_s(self, kind: str) -> float:
        """Seconds of ADC time from the latest ``kind`` taken to the latest stack (inf: none yet)."""
        if kind not in self.latest_ns or self.stack_ns is None:
            return math.inf
        return (self.stack_ns - self.latest_ns[kind]) * 1e-9

    def report(self) -> Report:
        values: list[tuple[str, str]] = []
        problems: list[str] = []
        if self.use_gnss:
            age = self._age_s("gnss")
            values += [("GNSS fixes taken", str(self.taken["gnss"])), ("GNSS fixes refused", str(self.refused["gnss"])),
                       ("GNSS NO_FIX messages", str(self.no_fix)),
                       ("last GNSS fix (s before the latest stack)", "none" if math.isinf(age) else f"{age:.1f}")]
        if self.use_odometry:
            age = self._age_s("odometry")
            values += [("odometry taken", str(self.taken["odometry"])),
                       ("odometry refused", str(self.refused["odometry"])),
                       ("last odometry (s before the latest stack)", "none" if math.isinf(age) else f"{age:.2f}")]
            tracker = self.fusion.tracker
            values.append(("odometry frame (yaw from map, scale error)",
                           describe_odometry_frame(None if tracker is None else tracker.odometry_frame())))
            if self.stack_ns is not None and age > self.odometry_timeout_s:
                problems.append("no odometry yet" if math.isinf(age) else
                                f"odometry stale ({age:.1f} s, odometry_timeout_s {self.odometry_timeout_s:g}): "
                                "tracking on the motion model alone")
        values.append(("refused by the tracker (stale, or beyond its innovation test)", str(self.refused["later"])))
        if self.last_refusal is not None:
            values.append(("last refusal", self.last_refusal))
        tracker = self.fusion.tracker
        for name, bias in ({} if tracker is None else tracker.site_biases()).items():
            values.append((f"site {name} learned bias (m)", f"{bias.bias_m:+.1f} +- {bias.std_m:.1f}"))
        if self.learned is not None:
            values += self.learned.values()
            if self.learned.error is not None:
                problems.append(self.learned.error)
        if problems:
            return Report(Severity.WARN, "; ".join(problems), values)
        taken = ", ".join(f"{n} {kind}" for kind, n in self.taken.items()) or "nothing yet"
        return Report(Severity.OK, f"taken: {taken}", values)


def describe_odometry_frame(frame: OdometryFrame | None) -> str:
    """The odometry frame the tracker has aligned, or what would align it, in words."""
    if frame is None:
        return ("not aligned yet: the track's own displacement over 20 m, two GNSS fixes with odometry between "
                "them, or an /initialpose with a heading aligns it")
    return (f"{frame.yaw_rad:+.3f} +- {frame.yaw_std_rad:.3f} rad, {100 * frame.scale:+.1f} +- "
            f"{100 * frame.scale_std:.1f} %")


class LearnedTowers:
    """Writes the fusion stage's learned tower database to ``path`` every ``period_s`` (steady
    time, passed in) and when asked at shutdown; a failed write is kept as ``error`` and tried
    again at the next period."""

    def __init__(self, path: str, period_s: float) -> None:
        self.path = Path(path)
        self.period_s = period_s
        self.written = 0
        self.error: str | None = None
        self._last_s: float | None = None

    def due(self, now_s: float) -> bool:
        if self._last_s is None:
            self._last_s = now_s
        return now_s - self._last_s >= self.period_s

    def save(self, fusion: FusionStage, now_s: float) -> str | None:
        """Write now; None when written (or nothing learned yet), else why not."""
        self._last_s = now_s
        database = fusion.learned_database()
        if database is None:
            return None
        try:
            write_tower_database(database, self.path)
        except (OSError, ValueError) as error:
            self.error = f"could not write the learned tower database {str(self.path)!r}: {error}"
            return self.error
        self.written += 1
        self.error = None
        return None

    def values(self) -> list[tuple[str, str]]:
        out = [("learned towers file", str(self.path)), ("learned towers written", str(self.written))]
        if self.error is not None:
            out.append(("learned towers error", self.error))
        return out
