"""The fusion stage: one stack's arrivals in, a snapshot fix and the tracker's fix out.

``FusionStage.process(arrivals)`` takes exactly what a ``CellTimingArray`` message carries
(:class:`~deepsync.types.StackArrivals`), so the fusion node and the pipeline call it alike.
The cells become site ranges through the tower database (``fusion.anchors``); the stack is
solved on its own (``fusion.snapshot``: needs 3 sites in 2-D) and fed to the tracker
(``fusion.tracker``: one site is enough). Cells the database cannot place are reported as
``UNANCHORED`` events and left out; the stage never raises on what it is fed.

Time: ranges are read on the receiver clock counted from the first stack's frame-aligned
stamp; a stream that starts over (stamps going back) starts the tracker afresh (the sync
stage reports the restart; fusion does not report it twice).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

from deepsync.fusion.anchors import Anchors, SiteArrival, frame_reference_ns
from deepsync.fusion.snapshot import SnapshotConfig, solve_snapshot
from deepsync.fusion.tracker import Tracker, TrackerConfig
from deepsync.geo import LocalFrame
from deepsync.towers import TowerDatabase
from deepsync.types import Fix, Health, HealthKind, NoFix, NoFixReason, PositionPrior, StackArrivals


@dataclass(frozen=True)
class FusionConfig:
    """``track``: run the tracker besides the snapshot solver; ``min_std_m`` floors each
    arrival's 1-sigma: the timing stage's sigma measures noise, but as the receiver moves, the
    multipath under a site's arrival fades from stack to stack and scatters it around the
    site's bias by more than that noise (on the dense walk, 10-frame stacks, full-frame timing:
    0.05-0.1 samples, 8-15 m, at sigmas of 0.01-0.04 samples), which the fusion, taking the
    arrival's sigma as its white noise, must be told; ``multipath_std_m``
    is the range bias multipath and NLOS add to a site, beyond the timing stage's sigma (which
    measures noise, not where the channel moved the envelope's peak). Measured along the
    simulated routes (docs/fusion.md): LOS sites 0-15 m, NLOS 40-90 m in the dense scenario,
    about 200 m (common to both sites heard) in the urban one."""

    snapshot: SnapshotConfig = field(default_factory=SnapshotConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    track: bool = True
    min_std_m: float = 8.0
    multipath_std_m: float = 40.0

    def __post_init__(self) -> None:
        if not (_metres(self.min_std_m) and self.min_std_m > 0):
            raise ValueError(f"min_std_m: {self.min_std_m!r} must be a positive number of metres (<= 1e4)")
        if not _metres(self.multipath_std_m):
            raise ValueError(f"multipath_std_m: {self.multipath_std_m!r} must be a non-negative number of metres "
                             "(<= 1e4)")
        # one source for the dimensions and the receiver height: the tracker follows the stage's
        object.__setattr__(self, "tracker", dataclasses.replace(self.tracker, snapshot=self.snapshot))


def _metres(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and 0 <= value <= 1e4


@dataclass(frozen=True)
class FusionResult:
    """What fusion made of one stack: the snapshot's answer, the tracker's (None when not
    tracking), the site ranges both used, and the cells that could not be used.

    The snapshot is solved when first asked for (``solve_snapshot``: it is what a node
    publishes while the tracker has no fix, and what an evaluation compares): while the
    tracker has a fix, a node never needs it, and at 1-2 ms a stack it cost the replay more
    than the tracker did. The answer is the same whenever it is asked for."""

    tracked: Fix | NoFix | None
    sites: tuple[SiteArrival, ...]
    events: tuple[Health, ...]
    solve: Callable[[], Fix | NoFix] = field(repr=False, compare=False)

    @cached_property
    def snapshot(self) -> Fix | NoFix:
        return self.solve()

    @property
    def published(self) -> Fix | NoFix:
        """What a node publishes for this stack: the tracker's fix when it has one, else the
        snapshot's answer (whose :class:`NoFix` says why the stack alone gave none)."""
        return self.tracked if isinstance(self.tracked, Fix) else self.snapshot


class FusionStage:
    """Site ranges, snapshot solver and tracker for one tower database."""

    def __init__(self, towers: TowerDatabase, config: FusionConfig | None = None,
                 frame: LocalFrame | None = None) -> None:
        self.config = config or FusionConfig()
        self.anchors = Anchors(towers, frame)
        self.tracker = Tracker(self.config.tracker) if self.config.track else None
        self.reference_ns: int | None = None
        self._last_stamp_ns: int | None = None

    @property
    def frame(self) -> LocalFrame:
        return self.anchors.frame

    def start_from(self, prior: PositionPrior) -> None:
        """The tracker starts again from ``prior`` at the next stack (an operator's initial
        pose): with it, one heard site is enough to start. ValueError when not tracking."""
        if self.tracker is None:
            raise ValueError("an initial position needs the tracker, and tracking is off (FusionConfig.track)")
        self.tracker.start_from(prior)

    def process(self, arrivals: StackArrivals) -> FusionResult:
        """Fix (or no fix, with the reason) for one stack's arrivals."""
        if self._last_stamp_ns is not None and arrivals.stamp_ns < self._last_stamp_ns:
            # the stream started over (the sync stage reports it as a RESTART event): so does fusion
            self.reference_ns = None
            if self.tracker is not None:
                self.tracker.reset()
        if self.reference_ns is None:
            self.reference_ns = frame_reference_ns(arrivals.stamp_ns)
        self._last_stamp_ns = arrivals.stamp_ns
        sites, problems = self.anchors.site_arrivals(arrivals, self.reference_ns, self.config.min_std_m,
                                                     self.config.multipath_std_m)
        events = [Health(HealthKind.UNANCHORED, problem) for problem in problems]
        clock_rate = None if arrivals.clock_drift_ppm is None else arrivals.clock_drift_ppm * 1e-6
        tracked = None
        prior = None
        if self.tracker is not None:
            time_s = max([site.time_s for site in sites], default=(arrivals.stamp_ns - self.reference_ns) * 1e-9)
            tracked = self.tracker.update(sites, arrivals.stamp_ns, time_s, clock_rate)
            prior = tracked.position_enu if isinstance(tracked, Fix) else None
        if problems and not sites:
            unknown = NoFix(arrivals.stamp_ns, NoFixReason.UNKNOWN_SITES, "; ".join(problems))
            return FusionResult(tracked, (), tuple(events), lambda: unknown)
        sites = tuple(sites)
        return FusionResult(tracked, sites, tuple(events), functools.partial(
            solve_snapshot, sites, self.config.snapshot, stamp_ns=arrivals.stamp_ns, clock_rate=clock_rate or 0.0,
            prior_enu=prior))
