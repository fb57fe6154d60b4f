"""What the nodes' diagnostics say, computed without ROS.

The nodes that process stacks (``cell_sync``, ``cell_timing``, ``tdoa_fusion``, the pipeline)
feed a :class:`StageHealth` and hand its :class:`Report` (a level, a message for people, key/value
strings) to a ``diagnostic_updater`` task: stacks seen, the cells and sites heard in the last stack
and over a window of stacks, the fix rate over that window and why the last stack had no fix,
processing latency, the stream's typed :class:`~deepsync.types.Health` events counted by kind
(with the last message of each), input messages that could not be converted, and stacks that
never arrived (:class:`StackSequence`: gaps in the stacks' sample indices). The nodes that play a
source report through :class:`deepsync_ros.playback.Playback` the same way.

:class:`CellTable` also draws the tower database's sites for Foxglove's Map panel
(:func:`sites_geojson`), heard or not.

The level is the worst of what happened *recently* (within the window), so a node that recovers
from a gap goes back to OK while its counts keep the history.
"""

from __future__ import annotations

import json
import statistics
from collections import Counter, deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import NamedTuple

from deepsync.pipeline import StackResult
from deepsync.towers import TowerDatabase
from deepsync.fusion.anchors import SiteArrival
from deepsync.types import SPEED_OF_LIGHT_M_S, Fix, Health, HealthKind, NoFix, Severity, StackArrivals

# 50 stacks of 10 frames are 5 s: long enough for a rate to mean something, short enough to
# follow a walk into and out of coverage.
WINDOW_STACKS = 50


class Report(NamedTuple):
    """One diagnostic status: its level, a line for people and the details as strings."""

    level: Severity
    message: str
    values: list[tuple[str, str]]


@dataclass(frozen=True)
class _Stack:
    pcis: tuple[int, ...]
    sites: tuple[str, ...] | None  # None: no fusion behind this node
    fix: Fix | NoFix | None


def _ms(values: Iterable[float]) -> str:
    return f"{statistics.median(values) * 1e3:.1f}"


class StackSequence:
    """Stacks lost on the way to a node, told from the ones that arrive: stacks start every hop
    (``hop_frames`` frames) of stream samples, so a step of k hops between two consecutive
    arrivals means k - 1 stacks never came. The hop is the smallest step seen, so stacks lost
    before it is known are counted once it is; a step back (the stream started again, e.g.
    ``ros2 bag play --loop``) starts a new sequence. What is lost before the first stack
    arrives cannot be told from the stacks."""

    def __init__(self) -> None:
        self.seen = 0  # stacks that arrived, over every sequence
        self.lost_before = 0  # in sequences that ended with a restart
        self._first: int | None = None
        self._last: int | None = None
        self._arrived = 0
        self._hop: int | None = None

    def arrived(self, first_sample_index: int) -> None:
        """The next stack that arrived, by the stream index of its first sample."""
        if self._last is not None and first_sample_index <= self._last:
            self.lost_before = self.lost
            self._first = self._last = self._hop = None
            self._arrived = 0
        if self._last is not None:
            step = first_sample_index - self._last
            self._hop = step if self._hop is None else min(self._hop, step)
        if self._first is None:
            self._first = first_sample_index
        self._last = first_sample_index
        self._arrived += 1
        self.seen += 1

    @property
    def lost(self) -> int:
        """Stacks missing between the first and the last that arrived, over every sequence."""
        if self._hop is None:
            return self.lost_before
        expected = round((self._last - self._first) / self._hop) + 1
        return self.lost_before + max(0, expected - self._arrived)


class StageHealth:
    """What a stack-processing node reports (see the module docstring)."""

    def __init__(self, window: int = WINDOW_STACKS) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1 stack, got {window!r}")
        self.window = window
        self.stacks = 0
        self.fixes = 0
        self.rejected = 0
        self.last_rejection: str | None = None
        self.last_no_fix: NoFix | None = None
        self.event_counts: Counter[HealthKind] = Counter()
        self.last_event: dict[HealthKind, str] = {}
        self._recent: deque[_Stack] = deque(maxlen=window)
        # (stack count when it happened, severity, kind, text): recent while the count is within the window
        self._problems: deque[tuple[int, Severity, str, str]] = deque(maxlen=16 * window)
        self._latency_s: deque[float] = deque(maxlen=window)
        self._stage_s: deque[float] = deque(maxlen=window)
        self.sequence = StackSequence()
        self._lost_seen = 0

    def stack(self, pcis: Iterable[int], *, events: Iterable[Health] = (), sites: Iterable[str] | None = None,
              fix: Fix | NoFix | None = None, latency_s: float | None = None, stage_s: float | None = None) -> None:
        """One stack processed: the cells heard in it, what the stages reported, the sites and
        fix (nodes with fusion), the time from the input's arrival to publishing, and the time
        the stage itself took (s)."""
        self.stacks += 1
        self._recent.append(_Stack(tuple(pcis), None if sites is None else tuple(sites), fix))
        for event in events:
            self.event_counts[event.kind] += 1
            self.last_event[event.kind] = event.message
            self._problems.append((self.stacks, event.severity, event.kind.value, str(event)))
        if isinstance(fix, Fix):
            self.fixes += 1
        elif isinstance(fix, NoFix):
            self.last_no_fix = fix
        if latency_s is not None:
            self._latency_s.append(latency_s)
        if stage_s is not None:
            self._stage_s.append(stage_s)

    def result(self, result: StackResult, *, latency_s: float | None = None, stage_s: float | None = None) -> None:
        """One stack of the whole chain (the pipeline node)."""
        fusion = result.fusion
        self.stack(result.sync.pcis, events=result.health,
                   sites=None if fusion is None else [site.site for site in fusion.sites],
                   fix=None if fusion is None else fusion.published, latency_s=latency_s, stage_s=stage_s)

    def arrived(self, first_sample_index: int) -> None:
        """A stack message arrived (before it is converted or processed): its first sample's
        stream index, for the stacks lost on the way (:class:`StackSequence`)."""
        self.sequence.arrived(first_sample_index)
        lost = self.sequence.lost
        if lost > self._lost_seen:
            self._problems.append((self.stacks, Severity.WARN, "lost",
                                   f"{lost} input stacks never arrived (a gap in the stacks' sample indices)"))
            self._lost_seen = lost

    def reject(self, error: Exception | str) -> None:
        """An input message that could not be used (it failed conversion to core types)."""
        self.rejected += 1
        self.last_rejection = str(error)
        self._problems.append((self.stacks, Severity.WARN, "rejected", f"input rejected: {error}"))

    def _recent_problems(self) -> list[tuple[Severity, str]]:
        """The latest problem of each kind within the window."""
        latest: dict[str, tuple[Severity, str]] = {}
        for count, severity, label, text in reversed(self._problems):
            if count <= self.stacks - self.window:
                break
            latest.setdefault(label, (severity, text))
        return list(latest.values())

    def report(self) -> Report:
        values = [("stacks", str(self.stacks))]
        problems = self._recent_problems()
        recent = list(self._recent)
        summary = []
        if not recent:
            problems.append((Severity.WARN, "no stack yet: waiting for input"))
        else:
            heard = sorted({pci for stack in recent for pci in stack.pcis})
            values += [("cells heard (last stack)", " ".join(map(str, recent[-1].pcis)) or "none"),
                       (f"cells heard (last {len(recent)} stacks)", " ".join(map(str, heard)) or "none")]
            summary.append(f"{len(recent[-1].pcis)} cells")
            if not heard:
                problems.append((Severity.WARN, f"no cell heard in the last {len(recent)} stacks"))
            with_sites = [stack for stack in recent if stack.sites is not None]
            if with_sites:
                sites = sorted({site for stack in with_sites for site in stack.sites})
                values += [("sites heard (last stack)", " ".join(with_sites[-1].sites) or "none"),
                           (f"sites heard (last {len(with_sites)} stacks)", " ".join(sites) or "none")]
                summary.append(f"{len(with_sites[-1].sites)} sites")
            decided = [stack.fix for stack in recent if stack.fix is not None]
            if decided:
                rate = sum(isinstance(fix, Fix) for fix in decided) / len(decided)
                values += [(f"fix rate (last {len(decided)} stacks)", f"{rate:.2f}"), ("fixes", str(self.fixes))]
                summary.append(f"fix rate {rate:.0%}")
                if rate == 0:
                    reason = decided[-1]
                    problems.append((Severity.WARN, f"no fix in the last {len(decided)} stacks "
                                                    f"({reason.reason.value}: {reason.message})"))
        if self.last_no_fix is not None:
            values.append(("last no-fix reason", f"{self.last_no_fix.reason.value}: {self.last_no_fix.message}"))
        if self._latency_s:
            values += [("latency median (ms)", _ms(self._latency_s)),
                       ("latency max (ms)", f"{max(self._latency_s) * 1e3:.1f}")]
        if self._stage_s:
            values.append(("stage time median (ms)", _ms(self._stage_s)))
        values.append(("rejected input messages", str(self.rejected)))
        if self.sequence.seen:  # a node fed stacks by another node
            values.append(("lost input stacks", str(self.sequence.lost)))
        if self.last_rejection is not None:
            values.append(("last rejection", self.last_rejection))
        for kind in HealthKind:
            if self.event_counts[kind]:
                values += [(f"events: {kind.value}", str(self.event_counts[kind])),
                           (f"last {kind.value}", self.last_event[kind])]
        level = max((severity for severity, _ in problems), default=Severity.OK)
        worst = [text for severity, text in problems if severity == level]
        return Report(level, "; ".join(worst) if worst else ", ".join(summary), values)


@dataclass(frozen=True)
class _Cell:
    site: str | None
    snr_db: float
    std_samples: float
    std_m: float
    stamp_ns: int


class CellTable:
    """Every cell a node has heard, for a "cells" diagnostic in diagnostic_updater's key/value
    style: one key per PCI (``PCI 301``), its value the cell's site (where the tower database
    names it), SNR, timing 1-sigma (samples and metres) and how long before the latest stack it
    was last heard (stream time, so a paused bag does not age it)."""

    def __init__(self) -> None:
        self.cells: dict[int, _Cell] = {}
        self.latest_ns: int | None = None
        self.in_latest: tuple[int, ...] = ()

    def heard(self, arrivals: StackArrivals, sites: Iterable[SiteArrival] = ()) -> None:
        """One stack's arrivals, and the sites fusion placed them at (none: not known here)."""
        site_of = {pci: site.site for site in sites for pci in site.pcis}
        for cell in arrivals.cells:
            known = self.cells.get(cell.pci)
            site = site_of.get(cell.pci, None if known is None else known.site)
            self.cells[cell.pci] = _Cell(site, cell.snr_db, cell.toa_std,
                                         cell.toa_std * SPEED_OF_LIGHT_M_S / arrivals.sample_rate, arrivals.stamp_ns)
        self.latest_ns = arrivals.stamp_ns
        self.in_latest = tuple(cell.pci for cell in arrivals.cells)

    def report(self) -> Report:
        if self.latest_ns is None:
            return Report(Severity.OK, "no stack yet", [])
        values = []
        for pci in sorted(self.cells):
            cell = self.cells[pci]
            age_s = (self.latest_ns - cell.stamp_ns) * 1e-9
            values.append((f"PCI {pci}", f"site {cell.site or 'unknown'}, SNR {cell.snr_db:.1f} dB, sigma "
                                         f"{cell.std_m:.1f} m ({cell.std_samples:.3f} samples), last heard "
                                         f"{age_s:.1f} s before the latest stack"))
        return Report(Severity.OK, f"{len(self.in_latest)} of {len(self.cells)} cells heard in the latest stack",
                      values)


# A site is drawn as heard on the map while one of its cells was heard this recently (stream s).
HEARD_RECENTLY_S = 5.0
HEARD_COLOR = "#2f9e44"
SILENT_COLOR = "#868e96"


def sites_geojson(towers: TowerDatabase, cells: CellTable) -> str:
    """The tower database's placed sites as a GeoJSON FeatureCollection for Foxglove's Map panel
    (``foxglove_msgs/msg/GeoJSON``): one point per site, named with its PCIs, green while one of
    its cells was heard within :data:`HEARD_RECENTLY_S` of the latest stack (with the best SNR
    heard), grey otherwise."""
    features = []
    for site in towers.sites:
        if not site.has_position:
            continue
        heard = [cells.cells[cell.pci] for cell in site.cells if cell.pci in cells.cells]
        recent = [cell for cell in heard
                  if cells.latest_ns is not None and (cells.latest_ns - cell.stamp_ns) * 1e-9 <= HEARD_RECENTLY_S]
        name = f"{site.name} (PCI {' '.join(str(cell.pci) for cell in site.cells)})"
        if recent:
            name += f": heard, SNR {max(cell.snr_db for cell in recent):.1f} dB"
        features.append({
            "type": "Feature",
            "geometry": {"type": "Point", "coordinates": [site.longitude_deg, site.latitude_deg]},
            "properties": {"name": name, "heard": bool(recent),
                           "style": {"color": HEARD_COLOR if recent else SILENT_COLOR}},
        })
    return json.dumps({"type": "FeatureCollection", "features": features}, separators=(",", ":"))
