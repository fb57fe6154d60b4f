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

Aiding: GNSS fixes (:meth:`FusionStage.add_gnss`) and odometry velocities
(:meth:`FusionStage.add_odometry`), stamped on the same receiver clock as the ADC, go to the
tracker (``fusion.aiding``), which uses them in time order among the arrivals of the next stacks.
What cannot be used is said as an ``AIDING_REFUSED`` event: at once (not a number, back in time,
a clock far from the stacks', tracking off) by the method's return, later (stale, or refused by
the tracker's innovation test) in the next stack's events. What the tracker learns of each
site (its range bias, with site clock states its clock) comes back as a tower database
(:meth:`FusionStage.learned_database`) the next run can start from.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from deepsync.fusion.aiding import PositionAid, VelocityAid
from deepsync.fusion.anchors import Anchors, SiteArrival, frame_reference_ns
from deepsync.fusion.bias_map import BiasMap
from deepsync.fusion.calibration import SiteCalibration, calibrated_database
from deepsync.fusion.snapshot import SnapshotConfig, solve_snapshot
from deepsync.fusion.tracker import Tracker, TrackerConfig
from deepsync.geo import LocalFrame
from deepsync.motion import DEFAULT_MOTION, MOTION_MODELS
from deepsync.schema import check_settings, setting
from deepsync.towers import TowerDatabase
from deepsync.types import (
    SPEED_OF_LIGHT_M_S,
    Fix,
    GnssFix,
    Health,
    HealthKind,
    NoFix,
    NoFixReason,
    OdometryVelocity,
    PositionPrior,
    StackArrivals,
)


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
    simulated routes (docs/design/fusion.md): LOS sites 0-15 m, NLOS 40-90 m in the dense scenario,
    about 200 m (common to both sites heard) in the urban one, 25-230 m and changing along the
    route on the city walks with a channel that follows the walker, 20-215 m for whole streets on
    the ray-traced old town. The motion model sets it (``deepsync.motion``: 100 m for a walker,
    60 m for a car or a static asset; docs/design/fusion.md says what the route set measured)."""

    snapshot: SnapshotConfig = field(default_factory=SnapshotConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    track: bool = setting(True, help="Run the tracker besides the snapshot solver; the published fix is the "
                          "tracker's when it has one.")
    min_std_m: float = setting(8.0, help="Floor of each arrival's 1-sigma: the scatter multipath adds from stack to "
                               "stack on the move.", unit="m", bounds=(0.0, 1e4), open_low=True)
    multipath_std_m: float = setting(MOTION_MODELS[DEFAULT_MOTION].multipath_std_m,
                                     help="Range bias multipath and NLOS add to a site, beyond the timing sigma: "
                                     "the stationary sigma of its bias state.", unit="m", bounds=(0.0, 1e4),
                                     open_low=True)
    gnss_std_m: float = setting(10.0, help="Horizontal 1-sigma of a GNSS fix that states no covariance (a phone in "
                                "a street).", unit="m", bounds=(0.0, 1e4), open_low=True)
    gnss_min_std_m: float = setting(3.0, help="No GNSS fix is taken as better than this per axis (urban multipath a "
                                    "receiver's own covariance does not see).", unit="m", bounds=(0.0, 1e4),
                                    open_low=True)
    aiding_clock_window_s: float = setting(60.0, help="A fix or velocity further than this from the stacks' time is "
                                           "on another clock.", unit="s", bounds=(0.0, 1e4), open_low=True)

    def __post_init__(self) -> None:
        check_settings(self)
        # one source for the dimensions and the receiver height: the tracker follows the stage's
        object.__setattr__(self, "tracker", dataclasses.replace(self.tracker, snapshot=self.snapshot))


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
    max_std_m: float = math.inf  # the tracker's: no vaguer pose is published

    @cached_property
    def snapshot(self) -> Fix | NoFix:
        return self.solve()

    @property
    def published(self) -> Fix | NoFix:
        """What a node publishes for this stack (:func:`published_answer`)."""
        return published_answer(self.tracked, lambda: self.snapshot, self.max_std_m)


def published_answer(tracked: Fix | NoFix | None, snapshot: Callable[[], Fix | NoFix], max_std_m: float) -> Fix | NoFix:
    """The tracker's fix when it has one, else the stack's own, unless that is vaguer than the
    tracker may be (``max_std_m``: a pose that vague guides nothing; on a static asset hearing
    three sites at a bad angle, fixes 600 m off claiming more); the NoFix says why."""
    if isinstance(tracked, Fix):
        return tracked
    answer = snapshot()
    if isinstance(answer, Fix) and answer.horizontal_std_m > max_std_m:
        return NoFix(answer.stamp_ns, NoFixReason.DEGENERATE_GEOMETRY,
                     f"the stack's own fix is {answer.horizontal_std_m:.0f} m 1-sigma, beyond max_std_m "
                     f"{max_std_m:g} m: too vague to publish", answer.rejected)
    return answer


def answer_counts(answers: Sequence[Fix | NoFix | None]) -> dict:
    """How many of a run's answers (None: none was asked for at that stack) were fixes, and why
    the others were not, the most frequent reason first."""
    given = [answer for answer in answers if answer is not None]
    fixes = sum(isinstance(answer, Fix) for answer in given)
    reasons = Counter(answer.reason.value for answer in given if isinstance(answer, NoFix))
    return {"epochs": len(given), "fixes": fixes, "fix_rate": fixes / len(given) if given else 0.0,
            "no_fix_reasons": dict(reasons.most_common())}


def sites_per_stack(site_counts: Iterable[int]) -> dict[str, int]:
    """How many stacks heard how many sites (the number of sites as text, ascending)."""
    heard = Counter(site_counts)
    return {str(k): heard[k] for k in sorted(heard)}


class FusionStage:
    """Site ranges, snapshot solver and tracker for one tower database."""

    def __init__(self, towers: TowerDatabase, config: FusionConfig | None = None,
                 frame: LocalFrame | None = None, bias_map: BiasMap | None = None) -> None:
        self.config = config or FusionConfig()
        self.anchors = Anchors(towers, frame)
        if bias_map is not None:
            f = self.anchors.frame
            bias_map.check_frame((f.latitude_deg, f.longitude_deg, f.height_m), f"tower database {towers.name!r}")
        self.bias_map = bias_map
        self._reading: tuple[np.ndarray, float] | None = None  # the latest tracked fix and its sigma
        self._matched: tuple[np.ndarray, float, float] | None = None  # the latest map match, its sigma, its time
        self.tracker = Tracker(self.config.tracker, len(self.anchors.anchors)) if self.config.track else None
        self.reference_ns: int | None = None
        self._last_stamp_ns: int | None = None
        self._waiting: list[GnssFix | OdometryVelocity] = []  # aiding given before the first stack
        self._latest_aid_ns: dict[type, int] = {}  # stamp of the latest fix and velocity taken

    @property
    def frame(self) -> LocalFrame:
        return self.anchors.frame

    def start_from(self, prior: PositionPrior) -> None:
        """The tracker starts again from ``prior`` at the next stack (an operator's initial
        pose): with it, one heard site is enough to start. ValueError when not tracking."""
        if self.tracker is None:
            raise ValueError("an initial position needs the tracker, and tracking is off (FusionConfig.track)")
        self.tracker.start_from(prior)

    def add_gnss(self, fix: GnssFix) -> Health | None:
        """Queue a GNSS fix for the tracker (its time must be on the ADC's receiver clock); an
        ``AIDING_REFUSED`` event saying why where it cannot be used at all."""
        return self._aid(fix, "GNSS fix")

    def add_odometry(self, velocity: OdometryVelocity) -> Health | None:
        """Queue an odometry velocity for the tracker (its time must be on the ADC's receiver
        clock); an ``AIDING_REFUSED`` event saying why where it cannot be used at all."""
        return self._aid(velocity, "odometry velocity")

    def _aid(self, aid: GnssFix | OdometryVelocity, what: str) -> Health | None:
        if not isinstance(aid, (GnssFix, OdometryVelocity)):
            raise ValueError(f"aid: {aid!r} is neither a GnssFix nor an OdometryVelocity")
        if self.tracker is None:
            return Health(HealthKind.AIDING_REFUSED, f"{what} not used: tracking is off (FusionConfig.track)")
        latest = self._latest_aid_ns.get(type(aid))
        if latest is not None and aid.stamp_ns <= latest:
            return Health(HealthKind.AIDING_REFUSED, f"{what} stamped {aid.stamp_ns} ns refused: not after the one "
                          f"before ({latest} ns): stamps must only go forward")
        if self._last_stamp_ns is not None:
            apart = (aid.stamp_ns - self._last_stamp_ns) * 1e-9
            if abs(apart) > self.config.aiding_clock_window_s:
                return Health(HealthKind.AIDING_REFUSED, f"{what} refused: stamped {apart:+.1f} s from the latest "
                              f"stack (aiding_clock_window_s {self.config.aiding_clock_window_s:g} s): it must be "
                              "on the ADC's clock (use_sim_time with the bag's /clock, or a receiver on host time)")
        self._latest_aid_ns[type(aid)] = aid.stamp_ns
        self._waiting.append(aid)
        if self.reference_ns is not None:
            self._hand_over()
        return None

    def _hand_over(self) -> None:
        """The aiding waiting for a time origin, on the tracker's time base."""
        for aid in self._waiting:
            time_s = (aid.stamp_ns - self.reference_ns) * 1e-9
            if isinstance(aid, OdometryVelocity):
                self.tracker.add_velocity(VelocityAid(time_s, np.array(aid.velocity), aid.covariance,
                                                      aid.in_map_frame, aid.heading_rad))
            else:
                self.tracker.add_position(self._position_aid(aid, time_s))
        self._waiting.clear()

    def _position_aid(self, fix: GnssFix, time_s: float) -> PositionAid:
        """A GNSS fix in the ``map`` frame; its horizontal covariance the configured sigma where
        it states none, and never tighter than ``gnss_min_std_m``."""
        position = np.asarray(self.frame.geodetic_to_enu(fix.latitude_deg, fix.longitude_deg, fix.height_m))
        c = self.config
        covariance = np.diag([c.gnss_std_m**2] * 2 + [(3 * c.gnss_std_m) ** 2]) if fix.covariance_enu is None \
            else np.array(fix.covariance_enu)
        variances, axes = np.linalg.eigh(covariance[:2, :2])
        covariance[:2, :2] = (axes * np.maximum(variances, c.gnss_min_std_m**2)) @ axes.T
        return PositionAid(time_s, position, covariance, "GNSS fix" + (f" ({fix.frame_id})" if fix.frame_id else ""))

    def _mapped(self, sites: Sequence[SiteArrival], time_s: float) -> tuple[SiteArrival, ...]:
        """The sites with the bias map's pull taken off, read where the map says the receiver
        is (``BiasMap.locate``: three mapped sites or more), else at the latest such place,
        widened by the speed prior since, else at the latest tracked fix; as they were where
        none is known (the map never stops a site being used)."""
        reading = self.bias_map.locate(sites)
        if reading is not None:
            self._matched = (reading[0], reading[1], time_s)
        elif self._matched is not None:
            where, spread, since = self._matched
            reading = (where, math.hypot(spread, self.config.tracker.initial_speed_std_mps * (time_s - since)))
        else:
            reading = self._reading
        return tuple(sites) if reading is None else self.bias_map.correct(sites, *reading)

    def learned_database(self) -> TowerDatabase | None:
        """The tower database with what the tracker has learned of each site with states: its
        range bias (with site clock states, its clock offset and drift) folded into the site's
        timing, with the sigmas, at the tracker's time (a whole frame). TDOA cannot tell a
        site's NLOS pull from its clock, so the next run near here starts with both; elsewhere the
        pull changes within tens of metres, and the bias states' prior covers it. None before a
        track has started."""
        if self.tracker is None or not self.tracker.initialised or self.reference_ns is None:
            return None
        corrections = [SiteCalibration(name, bias.bias_m / SPEED_OF_LIGHT_M_S, bias.std_m / SPEED_OF_LIGHT_M_S,
                                       bias.drift_mps / SPEED_OF_LIGHT_M_S, bias.drift_std_mps / SPEED_OF_LIGHT_M_S,
                                       0, math.nan)
                       for name, bias in self.tracker.site_biases().items()]
        epoch_ns = frame_reference_ns(self.reference_ns + round(self.tracker.time_s * 1e9))
        return calibrated_database(self.anchors.towers, corrections, epoch_ns)

    def follow_stacks(self, stack_overlap: float) -> None:
        """Count each arrival's timing variance ``stack_overlap`` times from the next stack on:
        the stacks the arrivals come from changed (their n_frames / hop_frames)."""
        self.config = dataclasses.replace(self.config, tracker=dataclasses.replace(self.config.tracker,
                                                                                  stack_overlap=stack_overlap))
        if self.tracker is not None:
            self.tracker.config = self.config.tracker

    def process(self, arrivals: StackArrivals) -> FusionResult:
        """Fix (or no fix, with the reason) for one stack's arrivals."""
        if self._last_stamp_ns is not None and arrivals.stamp_ns < self._last_stamp_ns:
            # the stream started over (the sync stage reports it as a RESTART event): so does fusion
            self.reference_ns = None
            self._latest_aid_ns.clear()
            if self.tracker is not None:
                self.tracker.reset()
            self._reading = self._matched = None
        if self.reference_ns is None:
            self.reference_ns = frame_reference_ns(arrivals.stamp_ns)
        self._last_stamp_ns = arrivals.stamp_ns
        sites, problems = self.anchors.site_arrivals(arrivals, self.reference_ns, self.config.min_std_m,
                                                     self.config.multipath_std_m)
        events = [Health(HealthKind.UNANCHORED, problem) for problem in problems]
        if self.bias_map is not None:
            sites = list(self._mapped(sites, (arrivals.stamp_ns - self.reference_ns) * 1e-9))
        clock_rate = None if arrivals.clock_drift_ppm is None else arrivals.clock_drift_ppm * 1e-6
        tracked = None
        prior = None
        if self.tracker is not None:
            self._hand_over()
            time_s = max([site.time_s for site in sites], default=(arrivals.stamp_ns - self.reference_ns) * 1e-9)
            tracked = self.tracker.update(sites, arrivals.stamp_ns, time_s, clock_rate)
            events += [Health(HealthKind.AIDING_REFUSED, note) for note in self.tracker.take_notes()]
            prior = tracked.position_enu if isinstance(tracked, Fix) else None
            self._reading = None if prior is None else (np.asarray(prior), tracked.horizontal_std_m)
        if problems and not sites:
            unknown = NoFix(arrivals.stamp_ns, NoFixReason.UNKNOWN_SITES, "; ".join(problems))
            return FusionResult(tracked, (), tuple(events), lambda: unknown, self.config.tracker.max_std_m)
        sites = tuple(sites)
        return FusionResult(tracked, sites, tuple(events), functools.partial(
            solve_snapshot, sites, self.config.snapshot, stamp_ns=arrivals.stamp_ns, clock_rate=clock_rate or 0.0,
            prior_enu=prior), self.config.tracker.max_std_m)
