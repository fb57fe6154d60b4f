"""The tightly coupled tracker: position, velocity and receiver clock, updated by each site as it
is heard, like a GNSS receiver with too few satellites; and by GNSS fixes and odometry where the
receiver has them.

Each arrival says ``rho = |x(t) - p_s| + b(t) + m_s(t) (+ o_s(t))`` modulo one frame (2998 km):
the receiver at ``x`` (ENU; 2-D: up held at the receiver height), its clock bias ``b`` (m), the
site's range bias ``m_s`` (m) and, when asked for, the site's frame-clock error ``o_s`` (m). A
single arrival fixes one combination of those, so one site per stack is enough for an update:
the motion model carries the rest from arrival to arrival, and over a few seconds every heard
site has its say.

**Filter.** A plain extended Kalman filter of our own (not filterpy, not a UKF). The states are
additive (no attitude, no manifold), so an error-state form buys nothing; the range is nearly
linear over the state's uncertainty (its curvature error, sigma^2 / distance, is centimetres
at metres of uncertainty and hundreds of metres of range), so sigma points buy nothing either.
One pseudorange is a scalar update: the gain is one matrix-vector product over a scalar
innovation variance, no inverse; and the state grows when sites join, which a library filter
sized at construction does not do.

**State** ``[position (D), horizontal velocity (2), b, d, (m_s (, o_s, r_s) per site), (psi,
s)]``, ``D`` = 2 or 3:

* horizontal position and velocity: white-noise acceleration, power spectral density
  ``acceleration_std^2 x 1 s`` per axis, i.e. over one second the velocity wanders by
  ``acceleration_std`` (1-sigma): the motion model's (``deepsync.motion``: 0.5 m/s^2 for a
  pedestrian, 3 for a vehicle, 0.01 for a static asset).
* up (3-D only): a first-order Gauss-Markov process around the receiver height, stationary
  sigma the height prior's, correlation time ``height_correlation_s``: sites a few degrees above
  the horizon hardly measure height, so what holds it is that receivers stay near the ground.
* receiver clock: bias ``b`` (m) with white frequency noise, drift ``d = db/dt`` (m/s, c times
  the fractional frequency error: 15 ppm is 4.5 km/s) as a random walk. The defaults are a
  TCXO's Allan figures (h0 = 2e-19 -> 0.1 m/sqrt(s), h-2 = 2e-20 -> 0.2 m/s/sqrt(s)), the
  latter raised to 0.5 m/s/sqrt(s) for the temperature changes of a receiver carried about.
  ``b`` is kept modulo one frame: only that is measured.
* site range bias ``m_s`` (m), one per heard site, appended when the site is first heard (and
  after a start, for the sites it used), dropped once it has faded (below), added afresh when
  heard again. Multipath and NLOS lengthen a site's range by tens of metres stack after stack
  (the envelope's peak lags a blocked first path): taken as white, that error averages down
  over hundreds of stacks that share it, and the filter believes a position it cannot have
  (simulated walk, site biases of -9..+90 m: 2-D NEES 278). As a state it does not average
  down. Two states per site: a **persistent** part, the site's own level (a weak site's peak
  lags more than a strong one's, wherever the receiver is), ``persistent_bias_fraction`` (25 %)
  of the variance, which never fades; and a **fading** part, a first-order Gauss-Markov
  process towards 0 **over the distance travelled**: over
  ``bias_decorrelation_m`` (40 m) of the receiver's own path it keeps ``1/e`` of itself, over
  ``bias_correlation_s`` of time (600 s) too, whichever comes first. The bias is the channel's,
  and the channel changes with where the receiver is, not with time: 38.901's correlation
  distances of the delay spread and shadowing are 30-50 m in UMa (40 m NLOS; 7-13 m UMi), so a
  walker's bias changes over 30 s and a car's over 3 s, and a receiver that stands keeps its
  bias for as long as its surroundings stand. The distance is the filter's own speed times the
  step, its speed counted as ``sqrt(|v|^2 + trace(P_v))``: an uncertain velocity fades the biases
  as if the receiver moved that fast, which errs towards trusting them less. The two share
  ``bias_std_m^2`` of the latest arrival; without site clock states ``clock_std_m^2`` joins the
  persistent part: the site clock's offset error is one more per-site constant (it is the
  database's, not the channel's), and where the clocks drift ``site_clocks`` gives them their
  own states. Without the persistent part, odometry that carried the track past many bias
  draws made the tracker believe the biases had averaged out (a drive: NEES 4.2; with it 3.2,
  and with GNSS fixes 3.2 -> 2.1, the p90 75 -> 55 m). A persistent variance larger than before
  (a site clock's error grows with the database's age) is added as a fresh error. The
  arrival's noise is then ``timing_std_m`` alone: what stays from stack to stack is in states.
  Sliding stacks (a stack every ``hop`` of its ``n`` frames) share frames, so that noise repeats
  in the next ``n / hop`` arrivals: its variance counts ``stack_overlap`` = n / hop times.
  A bias common to every site is the receiver clock's ``b``: the priors hold that gauge.
  Without an anchor the biases are weakly observable: a position error traded against biases
  ``m_s = -u_s . dx`` shows only as the geometry turns. With one (below) they are not: the
  position is pinned, and what is left of each site's range is its bias.
* site clocks (``site_clocks=True``): per site, after ``m_s``'s two parts, offset ``o_s`` (m) and drift
  ``r_s`` (m/s), the error of the tower database's frame timing, appended with the site's
  bias state with the arrival's ``clock_std_m`` and ``clock_drift_std_mps`` as priors (the
  tower database's sigmas; a site without a drift in it gets ``anchors.UNKNOWN_DRIFT_STD``),
  and dropped with it. The offsets are not observable against ``b`` as a whole (adding a
  constant to ``b`` and taking it from every ``o_s`` changes no range), nor the drifts against
  ``d``: their priors hold that gauge, and what the data estimate is how sites disagree. Without
  an anchor, a constant velocity error ``dv`` trades against drifts ``r_s = -u_s . dv`` and an EKF
  linearised at its own estimate grows overconfident along it (simulated: 2-D NEES 2-20 over
  two minutes of sites 10-20 ns/s off): off by default.
* odometry (``psi``, ``s``): the odometry frame's yaw from ``map`` and the odometry's scale
  error, random walks of ``heading_drift_rad_per_sqrt_s`` and
  ``odometry_scale_wander_per_sqrt_s``, the scale's prior ``odometry_scale_std``. Appended once
  the track says where the odometry frame points: from the first odometry velocity on, the
  track's position is cloned into the state (stochastic cloning: two states that stay put while
  the filter keeps their covariance with everything) and the odometry's displacement integrated;
  when it has read ``ALIGN_MIN_M`` and the track's displacement since the clone points within
  ``ALIGN_DIRECTION_STD_RAD``, the angle between the two is ``psi`` (``fusion.aiding``), with its
  covariance to every state, and the clone goes. The track's velocity alone would rarely do: NLOS
  biases that change over tens of metres make a site's range rate a poor measure of speed. The
  yaw and scale outlive a restart of the track (they describe the odometry, not the track).
  Odometry in ``map`` joins them from its first velocity, the yaw at 0 exactly: its scale error
  is still unknown, and taken as white noise it piles up between anchors as position error. An
  initial position with a heading (``PositionPrior.heading_rad``) and the odometry's own heading
  at that moment give the yaw at once, its variance the two headings' (no stretch needed).
  Two positions taken in a row (GNSS fixes) and the odometry read between them say the yaw
  and the scale as well, whatever the track did meanwhile: the angle between the fixes'
  displacement and the odometry's, and their lengths' ratio (``aiding.frame_offset``), with
  the covariance of the fixes' errors, the later fix's shared with the position update they
  join. A frame already aligned is updated by them, the pair being the better witness: the
  sites' pulls bend the track's own stretch. A pair that disagrees with the frame known (its
  yaw and scale beyond the 2-dof gate; unaligned, the scale against its prior) is not used,
  and said: a fix tens of metres off reads a frame no odometry has. On the route set's drives,
  fixes a minute apart (900 m) give the yaw to 0.03 rad where the stretch came 87-144 s into
  the drive, or 0.34 rad off.

**Aiding** (:meth:`Tracker.add_position`, :meth:`Tracker.add_velocity`): measurements of where
the receiver is (a GNSS fix, with its covariance) and how it moves (odometry), queued and used
in time order among the arrivals of the next update that reaches their time. Before a start, a
position stands in for an initial position (below). A position the track contradicts (its
normalised innovation beyond the chi-square gate, D dof) is refused and said; the track is wrong
instead when ``max_position_rejections`` positions in a row are refused and agree with each
other: the tracker then starts again from the latest. A velocity beyond the gate is refused and
said. Those older than the filter's time are stale: refused and said. Odometry in its own
frame before the frame's yaw is known still says when the receiver stands (a velocity within its
noise of zero is ``v = 0`` in any frame), and its displacement aligns the frame (above).

**Gating and the robust fallback.** An innovation whose normalised square exceeds the
chi-square quantile (1 dof, ``gate_probability``) is not used: the site is named in
``rejected`` and counted. A reflection (100-300 m long) or a false lock (km) then never moves
the state; inflating the noise of such an arrival instead would still let a site that stays
long pull the track by metres per epoch. The fallback for the opposite case, where the state
is wrong and not the sites, is to start again: ``max_rejections`` arrivals in a row failing the
gate, from at least two sites, restart the tracker at once from the arrivals it could not
explain, and ``max_coast_s`` without an accepted measurement restarts it from what is heard next
(``last_restart`` keeps why; a NoFix says it). A track whose horizontal 1-sigma (DRMS) has grown
beyond ``max_std_m`` is lost: reported as a NoFix (``TRACK_LOST``), as a pose that vague
guides nothing, until an anchor pins it or the sites alone start a track where it says it is
(one elsewhere replaces it). It runs on meanwhile, its bias states and odometry frame kept,
but single sites narrowing it prove nothing: on a drive, one that had locked 1-5 samples late
pulled a lost track 1 km off claiming 100 m, and the poses it published then gave the route a
NEES of 30.

**Start** (``fusion.track_start``): from the last ``init_window_s`` of arrivals (8 s: long
enough to gather the sites a city stack rarely holds at once, short enough that the speed
prior covers the distance walked), or the current stack alone when it holds enough sites;
``D + 2`` sites where the tower database has that many (``sites_known``: a false lock among
``D + 1`` fits exactly and cannot be caught), else ``D + 1`` (and for a motion model without
``spare_site_at_start``: a static asset, which rarely hears a fourth site where it stands); one
with an initial position. The velocity starts at 0 with ``initial_speed_std_mps`` as its sigma,
so predicting to the window's end widens the position by the distance travelled meanwhile. The batch solves one
bias per site (its arrivals share it; only their timing noise is white), and the filter it
starts takes those biases into the sites' bias states, with their covariance to the position
and clock (:meth:`Tracker._begin`).

**An initial position** (:meth:`Tracker.start_from`: an operator's pose; or a GNSS fix while no
track runs). Two sites measure one range difference, a hyperbola, and the batch alone does not
start from them; with a prior it starts from one site (the clock), keeps the prior's uncertainty
along what the sites do not measure, and the filter grows it as the receiver moves. The track
is held by the prior for ``prior_hold_s`` from when it was given while fewer than ``D + 1`` sites
have states (an accepted GNSS fix renews the hold), then given up (a NoFix says so): along a
hyperbola the estimate drifts by the distance walked, and once that is a fair part of the
ranges the linearisation turns overconfident (simulated two-site walks 300-1100 m from the
sites: NEES 1.9 over the first 30 s from 30 m priors, 3.8-4.1 by 60 s). A prior the recent
arrivals contradict fails the start's residual test. A prior still waiting for a site says
where the receiver was: the start widens it by the motion model over its age (the start's speed
prior and the acceleration walk), and one that waited ``prior_hold_s`` is dropped unused.
Taken at its word, a 30 m prior that waited 20 s for two sites held the walk at NEES 5.3, one
that waited 40 s at 12; widened and held for what is left of its 30 s, NEES 1.6-2.3 after waits
of 0-29 s.

**Out-of-order input.** Arrivals older than the filter's time (a late stack) are skipped and
counted (``stale_arrivals``); the returned state is then the filter's moved back to ``time_s``.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from deepsync.fusion.aiding import (PositionAid, VelocityAid, frame_offset, heading_offset, odometry_velocity,
                                    rotation)
from deepsync.fusion.anchors import FRAME_RANGE_M, SiteArrival, unwrap_range
from deepsync.fusion.snapshot import SnapshotConfig, chi_square_limit
from deepsync.fusion.track_start import Start, batch_start
from deepsync.motion import DEFAULT_MOTION, MOTION_MODELS
from deepsync.schema import check_settings, setting
from deepsync.types import UNMEASURED_VARIANCE, Fix, FixKind, NoFix, NoFixReason, PositionPrior, wrap_angle

MAX_CLOCK_RATE = 1e-3  # a clock 1000 ppm off is not a receiver clock but a wrong number
# a site whose bias has faded this many correlations since it was last heard is forgotten: its
# state then keeps e^-5 (under 1 %) of what the arrivals taught it, and a drive past many
# sites stays small
FORGET_CORRELATIONS = 5.0
# odometry is aligned with the track once the track's displacement over a stretch the odometry
# measured too (at least ALIGN_MIN_M long) points this well (rad, 1-sigma); a stretch with a gap
# in the odometry longer than ODOMETRY_GAP_S starts over. The yaw found is kept (considered, not
# updated, by the sites): at 0.3 rad one drive aligned 0.77 rad off (2.8 sigma) and ran 100-200 m
# off claiming 40; at 0.15 two drives of three never aligned
ALIGN_DIRECTION_STD_RAD = 0.2
ALIGN_MIN_M = 20.0
ODOMETRY_GAP_S = 2.0
STANDSTILL_SIGMAS = 3.0  # an odometry speed within this many of its sigmas of 0 is a standstill
# how fast a body may turn (rad/s) between an initial pose's heading and the odometry heading
# paired with it (a car's brisk corner, a walker's turn): the pair's time apart widens the yaw
HEADING_TURN_RATE_RAD_S = 0.5
# odometry velocities refused in a row that say the track's velocity, not the odometry, is wrong
MAX_VELOCITY_REFUSALS = 3
# the yaw prior of an odometry frame that two fixes align (rad^2): wide enough that the fixes
# alone say it, whatever the value it starts from
UNKNOWN_YAW_VARIANCE = 100.0
_WALKER = MOTION_MODELS[DEFAULT_MOTION]


@dataclass(frozen=True)
class TrackerConfig:
    """How the receiver moves, how its clock wanders, and when to trust, coast or start again
    (the module docstring gives the physics of each default; ``deepsync.motion`` the motion
    models that set the first ones)."""

    snapshot: SnapshotConfig = SnapshotConfig()  # dims, receiver height (2-D: up fixed), residual test
    acceleration_std_mps2: float = _WALKER.acceleration_std_mps2  # velocity random walk, m/s per second
    clock_drift_std_mps_per_sqrt_s: float = 0.5  # receiver frequency random walk (TCXO carried about)
    clock_bias_std_m_per_sqrt_s: float = 0.1  # receiver white frequency noise (TCXO)
    gate_probability: float = 1e-3  # chance of gating out a Gaussian innovation (chi-square)
    max_coast_s: float = 10.0  # start again after this long without an accepted measurement
    init_window_s: float = 8.0  # arrivals kept for a start when no stack has enough sites
    initial_speed_std_mps: float = _WALKER.initial_speed_std_mps  # speed prior at a start
    clock_rate_std_ppm: float = 0.5  # uncertainty of the sync stage's clock rate, as a drift prior
    max_clock_ppm: float = 50.0  # drift prior (1-sigma) at a start when the clock rate is unknown
    max_rejections: int = 10  # gated arrivals in a row (from >= 2 sites) that say the state is wrong
    height_correlation_s: float = 60.0  # 3-D: how long the receiver's height stays off the nominal
    bias_decorrelation_m: float = setting(40.0, help="Path over which a site's NLOS range bias changes (fades to "
                                          "1/e): 38.901 UMa's delay-spread correlation distance is 40 m NLOS, UMi's "
                                          "10 m.", unit="m", bounds=(0.0, 1e6), open_low=True)
    bias_correlation_s: float = 600.0  # time over which it fades for a receiver that stands
    persistent_bias_fraction: float = 0.25  # share of a site's bias variance that does not fade (its own level)
    site_clocks: bool = False  # estimate per-site clock offset and drift errors as states
    site_clock_wander_mps_per_sqrt_s: float = 0.01  # site frequency random walk (disciplined eNB)
    stack_overlap: float = 1.0  # stacks each frame is in: n_frames / hop_frames (PipelineConfig sets it)
    # how long an initial position is used, from when it is given, while D + 1 sites are not heard
    prior_hold_s: float = _WALKER.prior_hold_s
    spare_site_at_start: bool = _WALKER.spare_site_at_start  # D + 2 sites for a start where the database has them
    max_std_m: float = setting(150.0, help="Horizontal 1-sigma (DRMS) beyond which the track is reported lost and "
                               "no pose is published for it.", unit="m", bounds=(0.0, 1e6), open_low=True)
    max_position_rejections: int = 2  # refused positions in a row, agreeing, that say the track is wrong
    heading_drift_rad_per_sqrt_s: float = 0.003  # odometry frame's yaw random walk (a gyro's drift)
    odometry_scale_std: float = 0.05  # odometry scale error, prior 1-sigma (fraction)
    odometry_scale_wander_per_sqrt_s: float = 1e-4  # odometry scale random walk (tyre warming, load)

    def __post_init__(self) -> None:
        if not isinstance(self.snapshot, SnapshotConfig):
            raise ValueError(f"snapshot: {self.snapshot!r} is not a SnapshotConfig")
        for name in ("site_clocks", "spare_site_at_start"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: {getattr(self, name)!r} is not a bool")
        check_settings(self)
        for name, low, high in (("max_rejections", 2, 10_000), ("max_position_rejections", 1, 1000)):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and low <= value <= high):
                raise ValueError(f"{name}: {value!r} is out of range ({low}..{high})")
        checks = {
            "acceleration_std_mps2": 0 < self.acceleration_std_mps2 <= 100,
            "clock_drift_std_mps_per_sqrt_s": 0 < self.clock_drift_std_mps_per_sqrt_s <= 1e4,
            "clock_bias_std_m_per_sqrt_s": 0 <= self.clock_bias_std_m_per_sqrt_s <= 1e4,
            "gate_probability": 0 < self.gate_probability < 0.5,
            "max_coast_s": 0 < self.max_coast_s <= 3600,
            "init_window_s": 0 < self.init_window_s <= 60,
            "initial_speed_std_mps": 0 < self.initial_speed_std_mps <= 340,
            "clock_rate_std_ppm": 0 < self.clock_rate_std_ppm <= 1000,
            "max_clock_ppm": 0 < self.max_clock_ppm <= 1000,
            "height_correlation_s": 0 < self.height_correlation_s <= 1e5,
            "bias_correlation_s": 0 < self.bias_correlation_s <= 1e7,
            "persistent_bias_fraction": 0 <= self.persistent_bias_fraction < 1,
            "site_clock_wander_mps_per_sqrt_s": 0 <= self.site_clock_wander_mps_per_sqrt_s <= 1e3,
            "stack_overlap": 1 <= self.stack_overlap <= 1000,
            "prior_hold_s": 0 < self.prior_hold_s <= 3600,
            "heading_drift_rad_per_sqrt_s": 0 <= self.heading_drift_rad_per_sqrt_s <= 1,
            "odometry_scale_std": 0 < self.odometry_scale_std <= 1,
            "odometry_scale_wander_per_sqrt_s": 0 <= self.odometry_scale_wander_per_sqrt_s <= 1,
        }
        for name, ok in checks.items():
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and ok):
                raise ValueError(f"{name}: {value!r} is out of range")

    @property
    def dims(self) -> int:
        return self.snapshot.dims


@dataclass
class _Site:
    """A heard site's states: the persistent part of its range bias at ``index``, the fading
    part next (with site clocks, its clock offset and drift after them); the persistent part's
    prior and the fading part's stationary variance (m^2), and how faded the tracker's biases
    were (:attr:`Tracker._faded`) when the site was last heard."""

    index: int
    persistent_m2: float
    fading_m2: float
    heard_fade: float


@dataclass(frozen=True)
class SiteBias:
    """What the tracker has learned of a heard site: its range bias (m, against the receiver
    clock; with site clock states, the clock offset added) and 1-sigma, and its clock drift
    (m/s, NaN without site clock states)."""

    bias_m: float
    std_m: float
    drift_mps: float = math.nan
    drift_std_mps: float = math.nan


@dataclass(frozen=True)
class OdometryFrame:
    """What the tracker has learned of an odometry's own frame: its yaw from ``map`` (rad) and
    its scale error (a fraction: the odometry reads ``1 + scale`` of the distance), each with
    its 1-sigma."""

    yaw_rad: float
    yaw_std_rad: float
    scale: float
    scale_std: float


@dataclass
class _Stretch:
    """An odometry stretch: from ``first_s`` to ``last_s``, the displacement it read in its own
    frame (m) and that displacement's covariance, and the latest velocity and its covariance."""

    first_s: float = math.nan
    last_s: float = math.nan
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    velocity_covariance: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    displacement: np.ndarray = field(default_factory=lambda: np.zeros(2))
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))

    def extend(self, aid: VelocityAid) -> None:
        """Integrate on to ``aid`` (trapezoid), its velocity the latest."""
        dt = aid.time_s - self.last_s
        self.displacement = self.displacement + 0.5 * (self.velocity + aid.velocity) * dt
        self.covariance = self.covariance + 0.25 * (self.velocity_covariance + aid.covariance) * dt**2
        self.last_s, self.velocity, self.velocity_covariance = aid.time_s, aid.velocity, aid.covariance

    def held_to(self, time_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The displacement and its covariance at ``time_s``, the latest velocity held since."""
        dt = time_s - self.last_s
        return self.displacement + self.velocity * dt, self.covariance + self.velocity_covariance * dt**2


class Tracker:
    """Follows the receiver through stacks of 0..N site arrivals, and positions and velocities
    from outside (see the module docstring)."""

    def __init__(self, config: TrackerConfig | None = None, sites_known: int | None = None) -> None:
        """``sites_known``: how many placed sites the tower database holds; where they are at
        least ``D + 2``, a start without an initial position needs that many heard."""
        self.config = config or TrackerConfig()
        c = self.config
        self._redundant_start = c.spare_site_at_start and sites_known is not None and sites_known >= c.dims + 2
        self._gate = chi_square_limit(c.gate_probability, 1)
        self._gate2 = chi_square_limit(c.gate_probability, 2)
        self._gate_position = chi_square_limit(c.gate_probability, c.dims)
        self.stale_arrivals = 0  # arrivals older than the filter's time, skipped
        self.rejected_arrivals = 0  # arrivals that failed the gate
        self.last_restart: str | None = None  # why the tracker last gave up its state and started again
        self._aids: list[tuple[float, int, PositionAid | VelocityAid]] = []  # a heap by time
        self._order = itertools.count()
        self._notes: list[str] = []
        self.reset()

    def reset(self) -> None:
        """Forget everything heard (a new stream, or one that started over): the next start
        needs fresh arrivals; positions and velocities queued are dropped."""
        self._window: deque[SiteArrival] = deque()
        self._newest = -math.inf
        self._prior: PositionPrior | None = None
        self._prior_since: float | None = None  # when the prior was given (None: at the next update)
        self._heading: tuple[float, float] | None = None  # an initial pose's heading and sigma, not yet paired
        self._heading_at: float | None = None  # when it was given (None: at the next update)
        self._heading_seen: tuple[float, float] | None = None  # the odometry heading nearest it: (dt, rad)
        self._aids.clear()
        self._forget()
        self._odometry_known: tuple[np.ndarray, np.ndarray] | None = None  # (psi, s), covariance kept over restarts
        # the latest position taken (the first of the next pair), and what the odometry in its
        # own frame has read since (None until its first velocity): the next fix reads the frame
        self._since_fix: tuple[PositionAid, _Stretch | None] | None = None

    def start_from(self, prior: PositionPrior) -> None:
        """Give up the state and start again from ``prior`` at the next update (an operator's
        initial pose): the recent arrivals are kept, and the start needs one site instead of
        ``D + 1``, the prior standing in for the position. One start uses it."""
        if not isinstance(prior, PositionPrior):
            raise ValueError(f"prior: {prior!r} is not a PositionPrior")
        if self.initialised:
            self.last_restart = "an initial position was given"
        self._forget()
        self._prior, self._prior_since = prior, None
        self._heading = None if prior.heading_rad is None else (prior.heading_rad, prior.heading_std_rad)
        self._heading_at = self._heading_seen = None

    def add_position(self, aid: PositionAid) -> None:
        """Queue an absolute position (a GNSS fix) for the update that reaches its time."""
        if not isinstance(aid, PositionAid):
            raise ValueError(f"aid: {aid!r} is not a PositionAid")
        heapq.heappush(self._aids, (aid.time_s, next(self._order), aid))

    def add_velocity(self, aid: VelocityAid) -> None:
        """Queue an odometry velocity for the update that reaches its time."""
        if not isinstance(aid, VelocityAid):
            raise ValueError(f"aid: {aid!r} is not a VelocityAid")
        heapq.heappush(self._aids, (aid.time_s, next(self._order), aid))

    def take_notes(self) -> list[str]:
        """What the tracker refused of the positions and velocities given since the last call,
        in words (one sentence each)."""
        notes, self._notes = self._notes, []
        return notes

    def site_biases(self) -> dict[str, SiteBias]:
        """Every site with states: what the tracker has learned of its bias (and clock)."""
        out = {}
        for name, site in self._sites.items():
            parts = slice(site.index, site.index + self._range_parts)
            bias = float(np.sum(self._x[parts]))
            std = math.sqrt(max(float(np.sum(self._P[parts, parts])), 0.0))
            if self.config.site_clocks:
                drift = site.index + 3
                out[name] = SiteBias(bias, std, float(self._x[drift]), math.sqrt(max(self._P[drift, drift], 0.0)))
            else:
                out[name] = SiteBias(bias, std)
        return out

    def odometry_frame(self) -> OdometryFrame | None:
        """The odometry frame as aligned (by the track's stretch, two fixes or an initial pose's
        heading; a track that restarted keeps it), None before it is; for odometry in ``map``,
        its yaw 0 and its scale."""
        held = self._frame_held()
        if held is None:
            return None
        values, covariance = held
        spread = np.sqrt(np.maximum(np.diag(covariance), 0.0))
        return OdometryFrame(wrap_angle(float(values[0])), float(spread[0]), float(values[1]), float(spread[1]))

    def _forget(self) -> None:
        """Forget the state but keep the window of recent arrivals, for a start at once."""
        c, dims = self.config, self.config.dims
        if getattr(self, "_odometry", None) is not None:  # the odometry's yaw and scale outlive the track
            block = slice(self._odometry, self._odometry + 2)
            self._odometry_known = (self._x[block].copy(), self._P[block, block].copy())
        self._x = np.zeros(0)
        self._P = np.zeros((0, 0))
        self._t = math.nan
        self._last_accepted = math.nan
        self._lost = False  # the track's 1-sigma grew beyond max_std_m, and nothing has found it since
        self._held_since: float | None = None  # when the initial position the track rests on was given
        self._rejection_run: list[str] = []
        self._refused_positions: list[PositionAid] = []
        self._velocity_refusals = 0  # odometry velocities refused in a row
        self._odometry_heard_s = -math.inf  # the latest odometry velocity used
        self._sites: dict[str, _Site] = {}  # in the order of their states
        self._odometry: int | None = None  # index of the odometry frame's yaw (its scale next)
        self._clone: int | None = None  # index of the position cloned where an odometry stretch began
        self._stretch = _Stretch()
        self._faded = 0.0  # the site biases' Gauss-Markov exponent summed since the start
        self._width = 4 if c.site_clocks else 2  # states per site: bias, persistent and fading (, clock offset, drift)
        self._range_parts = 3 if c.site_clocks else 2  # of them, those a range adds up: the bias (, clock offset)
        self._bias = dims + 2  # after the position and the horizontal velocity
        self._model()

    def _model(self) -> None:
        """The motion model of the receiver's states and the others': F = I + dt S, Q = |dt|^3/3
        Q3 + dt|dt|/2 Q2 + |dt| Q1 (an integrated random walk per pair, exact for any step, back
        in time too), the site biases' Gauss-Markov decay set in by :meth:`_propagated`."""
        c, dims = self.config, self.config.dims
        n = (self._bias + 2 + self._width * len(self._sites) + (0 if self._odometry is None else 2)
             + (0 if self._clone is None else 2))
        # each pair: a "to" state integrating its "from" state, which random-walks with that PSD
        pairs = [(i, dims + i, c.acceleration_std_mps2**2) for i in range(2)]
        pairs.append((self._bias, self._bias + 1, c.clock_drift_std_mps_per_sqrt_s**2))
        if c.site_clocks:
            pairs += [(site.index + 2, site.index + 3, c.site_clock_wander_mps_per_sqrt_s**2)
                      for site in self._sites.values()]
        self._eye = np.eye(n)
        self._shift, self._q3, self._q2, self._q1 = (np.zeros((n, n)) for _ in range(4))
        for to, frm, q in pairs:
            self._shift[to, frm] = 1.0
            self._q3[to, to] = self._q2[to, frm] = self._q2[frm, to] = self._q1[frm, frm] = q
        self._q1[self._bias, self._bias] = c.clock_bias_std_m_per_sqrt_s**2
        if self._odometry is not None:
            self._q1[self._odometry, self._odometry] = c.heading_drift_rad_per_sqrt_s**2
            self._q1[self._odometry + 1, self._odometry + 1] = c.odometry_scale_wander_per_sqrt_s**2
        self._site_biases = np.array([site.index + 1 for site in self._sites.values()], dtype=np.intp)  # fading
        self._site_variances = np.array([site.fading_m2 for site in self._sites.values()])

    @property
    def initialised(self) -> bool:
        return len(self._x) > 0

    @property
    def time_s(self) -> float:
        """The filter's time, on the update's time base (NaN before a start)."""
        return self._t

    def update(self, arrivals: Sequence[SiteArrival], stamp_ns: int, time_s: float,
               clock_rate: float | None = None) -> Fix | NoFix:
        """Predict to each measurement's time in order and update with it: the arrivals, and
        the positions and velocities queued up to ``time_s``; return the state at ``time_s``
        (a :class:`Fix`, ``kind`` TRACKED) or why there is none (NOT_INITIALISED, TRACK_LOST).

        ``clock_rate`` (ppm * 1e-6), the receiver clock error the sync stage measured, is the
        drift prior of a start. Once tracking it is not used: the ranges measure the drift to
        m/s within seconds, and the sync stage smooths its rate over stacks, so its errors would
        enter stack after stack as the same error, not as fresh information.
        Raises ValueError for a non-finite time, range, position or sigma (nothing changes then).
        """
        arrivals = _checked(arrivals, time_s, clock_rate)
        self._remember(arrivals, time_s)
        if self._heading is not None and self._heading_at is None:
            self._heading_at = time_s  # as the prior's (_pending_prior)
        aids = self._due_aids(time_s)
        if not self.initialised:
            return self._start_aided(stamp_ns, time_s, clock_rate, arrivals, aids)
        first = min([a.time_s for a in arrivals] + [a.time_s for a in aids], default=time_s)
        now = min(time_s, first)
        if now - self._last_accepted > self.config.max_coast_s:
            return self._restart(f"no measurement accepted for {now - self._last_accepted:.1f} s "
                                 f"(max_coast_s {self.config.max_coast_s:g} s)", stamp_ns, time_s, clock_rate, ())
        if self._held_since is not None and len(self._sites) > self.config.dims:
            self._held_since = None  # the sites fix the position now: the prior is forgotten
        if self._held_since is not None and now - self._held_since > self.config.prior_hold_s:
            return self._restart(f"the initial position, given {now - self._held_since:.1f} s ago, still held the "
                                 f"track (prior_hold_s {self.config.prior_hold_s:g} s) with only "
                                 f"{', '.join(self._sites)} heard", stamp_ns, time_s, clock_rate, ())
        self._drop_unheard()
        used: list[str] = []
        rejected: list[str] = []
        measurements = sorted([*arrivals, *aids], key=lambda m: m.time_s)  # stable: arrivals first at a tie
        for measurement in measurements:
            if measurement.time_s < self._t:
                self._stale(measurement)
                continue
            self._predict(measurement.time_s - self._t)
            self._t = measurement.time_s
            if isinstance(measurement, VelocityAid):
                self._use_velocity(measurement)
                continue
            if isinstance(measurement, PositionAid):
                restart = self._use_position(measurement)
                if restart is not None:
                    return self._restart(restart, stamp_ns, time_s, clock_rate, tuple(rejected), measurement)
                continue
            if self._correct(measurement):
                _add(used, measurement.site)
                self._last_accepted = measurement.time_s
                self._rejection_run.clear()
                continue
            _add(rejected, measurement.site)
            self.rejected_arrivals += 1
            self._rejection_run.append(measurement.site)
            if len(self._rejection_run) >= self.config.max_rejections and len(set(self._rejection_run)) >= 2:
                sites = ", ".join(sorted(set(self._rejection_run)))
                return self._restart(f"the last {len(self._rejection_run)} arrivals (sites {sites}) all failed the "
                                     "gate: the state, not the sites, was wrong", stamp_ns, time_s, clock_rate,
                                     tuple(rejected))
        self._P = 0.5 * (self._P + self._P.T)  # the updates' rounding, kept from accumulating
        fix = self._reported(self._fix_at(time_s, stamp_ns, tuple(used), tuple(rejected)))
        return self._found_again(fix, tuple(used), stamp_ns, time_s, clock_rate) if self._lost else fix

    def _reported(self, fix: Fix) -> Fix | NoFix:
        """The fix, or TRACK_LOST where the track is lost: its horizontal 1-sigma grew beyond
        ``max_std_m``, and it has not been found again since."""
        if fix.horizontal_std_m > self.config.max_std_m:
            self._lost = True
        if not self._lost:
            return fix
        return NoFix(fix.stamp_ns, NoFixReason.TRACK_LOST,
                     f"the track's horizontal 1-sigma is {fix.horizontal_std_m:.0f} m and grew beyond max_std_m "
                     f"{self.config.max_std_m:g} m: lost until an anchor pins it or the sites alone place the "
                     "receiver where it says", fix.rejected)

    def _found_again(self, lost: NoFix, used: tuple[str, ...], stamp_ns: int, time_s: float,
                     clock_rate: float | None) -> Fix | NoFix:
        """A lost track runs on (its bias states, its odometry frame) but single sites narrowing
        it prove nothing: one locked a few samples late pulls it anywhere it likes. It is found
        again when the sites alone start a track, as a new one would need, where it says it is;
        if they start one elsewhere, that replaces it."""
        start = batch_start(sorted(self._window, key=lambda a: a.time_s), self.config, clock_rate, None,
                            self._redundant_start)
        if not isinstance(start, Start):
            return lost
        horizontal = self._P[:2, :2]
        moved = (self.config.initial_speed_std_mps * (time_s - start.time_s)) ** 2  # since the start's mid-time
        apart = self._x[:2] - start.mean[:2]
        spread = horizontal + start.covariance[:2, :2] + moved * np.eye(2)
        if math.sqrt(max(np.trace(horizontal), 0.0)) <= self.config.max_std_m \
                and float(apart @ np.linalg.solve(spread, apart)) <= self._gate2:
            self._lost = False
            return self._fix_at(time_s, stamp_ns, used, lost.rejected)
        self._forget()
        self.last_restart = (f"the track was lost, and the sites alone ({', '.join(start.sites)}) placed the receiver "
                             f"{float(np.hypot(*apart)):.0f} m from it")
        return self._start(stamp_ns, time_s, clock_rate, [])

    # ------------------------------------------------------------------ the filter

    def _predict(self, dt: float) -> None:
        """Move the filter ``dt`` seconds on; ``b`` stays within half a frame of 0."""
        self._faded += self._fade(self._x, self._P, abs(dt))
        self._x, self._P = self._propagated(self._x, self._P, dt)
        self._x[self._bias] = (self._x[self._bias] + FRAME_RANGE_M / 2) % FRAME_RANGE_M - FRAME_RANGE_M / 2

    def _fade(self, x: np.ndarray, P: np.ndarray, seconds: float) -> float:
        """The site biases' Gauss-Markov exponent over ``seconds``: time over their correlation
        time plus the distance the receiver covers (its speed, an uncertain one counted as
        faster) over their decorrelation distance."""
        if not len(self._site_biases) or seconds == 0:
            return 0.0
        dims, c = self.config.dims, self.config
        v, Pv = x[dims: dims + 2], P[dims: dims + 2, dims: dims + 2]
        speed = math.sqrt(float(v @ v) + float(np.trace(Pv)))
        return seconds / c.bias_correlation_s + speed * seconds / c.bias_decorrelation_m

    def _propagated(self, x: np.ndarray, P: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        F = self._eye + dt * self._shift
        a = abs(dt)
        Q = (a**3 / 3) * self._q3 + (0.5 * dt * a) * self._q2 + a * self._q1
        if len(self._site_biases):
            # site biases: first-order Gauss-Markov towards 0 over time and path, holding their
            # stationary variance (back in time, the decay undone)
            fade = self._fade(x, P, a)
            F[self._site_biases, self._site_biases] = math.exp(-math.copysign(fade, dt))
            Q[self._site_biases, self._site_biases] = self._site_variances * -math.expm1(-2 * fade)
        if self.config.dims == 2:
            return F @ x, F @ P @ F.T + Q
        # 3-D: up relaxes towards the receiver height (first-order Gauss-Markov, stationary sigma
        # the height prior's): the sites, a few degrees above the horizon, hardly measure it
        snapshot = self.config.snapshot
        F[2, 2] = math.exp(-dt / self.config.height_correlation_s)
        Q[2, 2] = snapshot.height_prior_std_m**2 * -math.expm1(-2 * a / self.config.height_correlation_s)
        moved = F @ x
        moved[2] += (1 - F[2, 2]) * snapshot.receiver_height_m
        return moved, F @ P @ F.T + Q

    def _correct(self, arrival: SiteArrival) -> bool:
        """One pseudorange update; False (state untouched) when the innovation fails the gate."""
        site = self._heard(arrival)  # may grow the state: read it after
        dims, bias, x, P = self.config.dims, self._bias, self._x, self._P
        diff = self._position(x) - arrival.position_enu
        distance = math.sqrt(float(diff @ diff))
        h = np.zeros(len(x))
        h[:dims] = diff[:dims] / distance
        h[bias] = 1.0
        h[site.index: site.index + self._range_parts] = 1.0
        predicted = distance + float(h[bias:] @ x[bias:])
        innovation = unwrap_range(arrival.range_mod_m, predicted) - predicted
        # what stays from stack to stack is in the site's states; a sliding stack's noise also
        # stays in the next stacks that share its frames: counted once per stack it is in
        noise2 = arrival.timing_std_m**2 * self.config.stack_overlap
        ph = P @ h
        variance = float(h @ ph) + noise2
        if innovation * innovation > self._gate * variance:
            return False
        gain = ph / variance
        if self._odometry is None:
            x += gain * innovation
            P -= np.outer(gain, ph)
            return True
        # the odometry's yaw and scale are considered, not updated, by the sites (a Schmidt
        # update), and so is the velocity while the odometry measures it: a bias drifting along
        # the route would pass for a velocity or scale error it then carries on (simulated walk:
        # scale -0.27 for a true -0.02, the track drifting 0.5 m/s)
        gain[self._odometry: self._odometry + 2] = 0.0
        if arrival.time_s - self._odometry_heard_s <= ODOMETRY_GAP_S:
            dims = self.config.dims
            gain[dims: dims + 2] = 0.0
        x += gain * innovation
        self._P = P - np.outer(gain, ph) - np.outer(ph, gain) + variance * np.outer(gain, gain)
        return True

    def _correct_block(self, innovation: np.ndarray, H: np.ndarray, R: np.ndarray, gate: float,
                       considered: Sequence[int] = ()) -> float | None:
        """A vector update (Joseph form: right for any gain); the normalised innovation squared
        where it fails ``gate`` (state untouched), else None. ``considered`` states keep their
        values (a Schmidt update: their uncertainty counts, they learn nothing from it)."""
        P = self._P
        PH = P @ H.T
        S = H @ PH + R
        score = float(innovation @ np.linalg.solve(S, innovation))
        if not score <= gate:
            return score
        K = np.linalg.solve(S, PH.T).T
        K[list(considered)] = 0.0
        self._x += K @ innovation
        A = self._eye - K @ H
        self._P = A @ P @ A.T + K @ R @ K.T
        return None

    def _use_position(self, aid: PositionAid) -> str | None:
        """An absolute position: used, or refused and said; a reason to start again from it
        when it is the latest of ``max_position_rejections`` refused positions that agree. Used,
        it and the fix before it read the odometry frame (:meth:`_frame_between_fixes`), which
        they align, or update, where they agree with what is known of it (:meth:`_pair_agrees`)."""
        dims = self.config.dims
        innovation = aid.position_enu[:dims] - self._x[:dims]
        R = aid.covariance[:dims, :dims]
        score = float(innovation @ np.linalg.solve(self._P[:dims, :dims] + R, innovation))
        if score <= self._gate_position:
            frame = self._frame_between_fixes(aid)
            if frame is not None and self._pair_agrees(aid, *frame):
                values, R = frame
                if self._odometry is None:
                    self._add_odometry_frame(*self._frame_known(values[0]))
                if self._clone is not None:
                    self._remove(range(self._clone, self._clone + 2))
                innovation = np.r_[innovation, self._frame_apart(values)[0]]
            H = np.zeros((len(innovation), len(self._x)))
            H[:dims, :dims] = np.eye(dims)
            if len(innovation) > dims:
                H[dims:, self._odometry: self._odometry + 2] = np.eye(2)
            self._correct_block(innovation, H, R, math.inf)
            self._last_accepted = aid.time_s
            self._lost = False  # pinned
            self._refused_positions.clear()
            if self._held_since is not None:
                self._held_since = aid.time_s  # the track rests on this position now
            return None
        distance = float(np.hypot(*innovation[:2]))
        self._notes.append(f"{aid.source} at {aid.time_s:.1f} s refused: {distance:.0f} m from the track "
                           f"(normalised innovation {score:.1f} beyond the gate {self._gate_position:.1f})")
        self._refused_positions.append(aid)
        run = self._refused_positions[-self.config.max_position_rejections:]
        if len(run) == self.config.max_position_rejections and _agree(run, self.config.initial_speed_std_mps):
            return (f"{len(run)} {aid.source}s in a row, agreeing with each other, were {distance:.0f} m from the "
                    "track: the track, not the fixes, was wrong")
        return None

    def _use_velocity(self, aid: VelocityAid) -> None:
        """An odometry velocity: in an odometry frame, with the frame's yaw and scale once
        aligned, only a standstill before (and a step of the stretch that aligns it); in ``map``,
        with its scale from the first on (its yaw is 0); refused and said beyond the gate."""
        dims = self.config.dims
        velocity = np.arange(dims, dims + 2)
        v = self._x[velocity]
        self._pair_heading(aid)
        z, R = aid.velocity, aid.covariance
        speed = float(np.hypot(*z))
        standstill = speed <= STANDSTILL_SIGMAS * math.sqrt(float(np.linalg.eigvalsh(R)[-1]))
        if not aid.in_map_frame:
            self._read_since_fix(aid)
        if self._odometry is None:  # may grow the state: size H after
            if not aid.in_map_frame:
                self._stretch_to(aid)
            elif not standstill:
                self._add_odometry_frame(np.zeros(2), np.diag([0.0, self.config.odometry_scale_std**2]))
        H = np.zeros((2, len(self._x)))
        if standstill:
            # a standstill reads 0 in any frame: what it read is folded into the noise
            H[:, velocity] = np.eye(2)
            if not aid.in_map_frame:
                z, R = np.zeros(2), np.eye(2) * (speed**2 + float(np.linalg.eigvalsh(R)[-1]))
            self._velocity_outcome(aid, self._correct_block(z - v, H, R, self._gate2), speed)
            return
        if self._odometry is None:
            if self._clone is not None:  # none while the track is lost
                self._align_odometry(aid)
            return
        psi, scale = self._x[self._odometry], self._x[self._odometry + 1]
        seen, by_v, by_psi, by_scale = odometry_velocity(v, psi, scale)
        H[:, velocity] = by_v
        H[:, self._odometry] = by_psi
        H[:, self._odometry + 1] = by_scale
        # only the velocity learns from it; the rest is considered, not updated. The yaw and
        # scale: the odometry alone cannot tell a turned or scaled velocity from a scaled
        # odometry (z = (1 + s) R(-psi) v), and an EKF linearised on its own estimate walks along
        # that direction, ever more sure of it (simulated: the scale from -0.02 to -0.27 in two
        # minutes); positions teach them. The position: through the motion model's
        # position-velocity covariance each velocity would also move it, as if the odometry's
        # slow errors were fresh accelerations; a walk without sites ran 25 m from its odometry's
        # own path in a minute (within 2 m without)
        others = [i for i in range(len(self._x)) if i not in velocity]
        score = self._correct_block(z - seen, H, R, self._gate2, others)
        if score is not None and self._velocity_refusals + 1 >= MAX_VELOCITY_REFUSALS:
            # the odometry said it again: the track's velocity is what is wrong (a turn the motion
            # model did not expect); it is given the odometry's word, its own uncertainty widened
            missed = float(np.sum((rotation(psi) @ z / (1 + scale) - v) ** 2))
            self._P[velocity, velocity] += missed
            self._notes.append(f"odometry at {aid.time_s:.1f} s disagreed with the track's velocity "
                               f"{self._velocity_refusals + 1} times in a row: the track's velocity was wrong "
                               f"({math.sqrt(missed):.1f} m/s off), taken from the odometry")
            score = self._correct_block(z - seen, H, R, math.inf, others)
        self._velocity_outcome(aid, score, speed)

    def _read_since_fix(self, aid: VelocityAid) -> None:
        """Integrate the odometry's displacement since the latest fix; a gap drops it."""
        if self._since_fix is None:
            return
        fix, stretch = self._since_fix
        if aid.time_s - (fix.time_s if stretch is None else stretch.last_s) > ODOMETRY_GAP_S:
            self._since_fix = None
        elif stretch is None:
            self._since_fix = (fix, _Stretch(fix.time_s, fix.time_s, aid.velocity, aid.covariance))
            self._since_fix[1].extend(aid)
        else:
            stretch.extend(aid)

    def _frame_between_fixes(self, aid: PositionAid) -> tuple[np.ndarray, np.ndarray] | None:
        """The odometry frame's yaw and scale from two fixes and the odometry read between
        them (``aiding.frame_offset`` of the fixes' displacement and the odometry's), and the
        covariance of this fix and those two read together (the fix's error is in all three):
        or None where the odometry did not run all the way from the fix before (a gap longer
        than ``ODOMETRY_GAP_S``), read less than ``ALIGN_MIN_M``, or the fixes do not say the
        direction to ``ALIGN_DIRECTION_STD_RAD``. Neither the track nor the sites enter: a track
        lost between the fixes aligns the frame as well. ``aid`` is then the first fix of the
        next pair, but where the odometry runs on from a fix too near to say the direction
        (fixes every second): that one stays first, until a fix far enough from it."""
        pair, self._since_fix = self._since_fix, (aid, None)
        if pair is None or pair[1] is None:
            return None
        (before, stretch), dims = pair, self.config.dims
        if aid.time_s - stretch.last_s > ODOMETRY_GAP_S:
            return None
        in_odometry, odometry_covariance = stretch.held_to(aid.time_s)
        in_map = aid.position_enu[:2] - before.position_enu[:2]
        apart = before.covariance[:2, :2] + aid.covariance[:2, :2]
        length = float(np.hypot(*in_map))
        if float(np.hypot(*in_odometry)) < ALIGN_MIN_M or \
                float(np.linalg.eigvalsh(apart)[-1]) > (ALIGN_DIRECTION_STD_RAD * length) ** 2:
            self._since_fix = pair
            return None
        values, by_map, odometry_noise = frame_offset(in_map, in_odometry, odometry_covariance)
        c, seconds = self.config, aid.time_s - before.time_s
        wander = np.diag([c.heading_drift_rad_per_sqrt_s**2, c.odometry_scale_wander_per_sqrt_s**2]) * seconds
        R = np.zeros((dims + 2, dims + 2))
        R[:dims, :dims] = aid.covariance[:dims, :dims]
        R[dims:, :dims] = by_map @ aid.covariance[:2, :dims]
        R[:dims, dims:] = R[dims:, :dims].T
        R[dims:, dims:] = by_map @ apart @ by_map.T + odometry_noise + wander
        return values, R

    def _frame_held(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The odometry frame's yaw and scale and their covariance: the state's, else the last
        track's; None before any alignment."""
        if self._odometry is not None:
            block = slice(self._odometry, self._odometry + 2)
            return self._x[block], self._P[block, block]
        return self._odometry_known

    def _frame_known(self, yaw_rad: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_frame_held`, or before any alignment ``yaw_rad`` with a prior too wide to
        count and the scale's own prior."""
        held = self._frame_held()
        if held is not None:
            return held
        return np.array([yaw_rad, 0.0]), np.diag([UNKNOWN_YAW_VARIANCE, self.config.odometry_scale_std**2])

    def _frame_apart(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """How far a frame read by two fixes (yaw, scale) is from the one known (the yaw
        wrapped), and the known frame and its covariance (:meth:`_frame_known`)."""
        known, spread = self._frame_known(values[0])
        return np.array([wrap_angle(values[0] - known[0]), values[1] - known[1]]), known, spread

    def _pair_agrees(self, aid: PositionAid, values: np.ndarray, R: np.ndarray) -> bool:
        """Whether the frame two fixes read agrees with what is known of it (chi-square, 2
        dof): a fix off by tens of metres reads a yaw and a scale no odometry has. Said where
        it does not; the fix itself is used all the same."""
        apart, known, spread = self._frame_apart(values)
        score = float(apart @ np.linalg.solve(spread + R[-2:, -2:], apart))
        if score <= self._gate2:
            return True
        self._notes.append(f"{aid.source} at {aid.time_s:.1f} s and the fix before it read the odometry frame "
                           f"{values[0]:+.2f} rad, scale {100 * values[1]:+.0f} %, against {known[0]:+.2f} rad, "
                           f"{100 * known[1]:+.0f} % (normalised innovation {score:.1f} beyond the gate "
                           f"{self._gate2:.1f}): the pair is not used")
        return False

    def _know_frame(self, values: np.ndarray, covariance: np.ndarray) -> None:
        """The odometry frame's yaw and scale read by two fixes while no track runs: kept for
        the next track, combined with what is known of it (:meth:`_frame_known`; independent)."""
        apart, known, spread = self._frame_apart(values)
        gain = spread @ np.linalg.inv(spread + covariance)
        self._odometry_known = (known + gain @ apart, (np.eye(2) - gain) @ spread)

    def _pair_heading(self, aid: VelocityAid) -> None:
        """An initial pose's heading (in map) and the odometry's own heading nearest its time
        give the odometry frame's yaw, ``psi = heading_map - heading_odometry``, at once: the
        frame joins the state (or its yaw is replaced, the operator's word being fresher) and
        no stretch is needed. Paired once the odometry has passed the heading's time and a track
        runs; an odometry heading more than ``ODOMETRY_GAP_S`` from it drops it, said."""
        if self._heading is None or aid.heading_rad is None or aid.in_map_frame or self._heading_at is None:
            return
        apart = aid.time_s - self._heading_at
        if self._heading_seen is None or abs(apart) < abs(self._heading_seen[0]):
            self._heading_seen = (apart, aid.heading_rad)
        if apart < 0 or not self.initialised:
            return
        (apart, odometry_heading), (heading, std) = self._heading_seen, self._heading
        self._heading = self._heading_seen = None
        if abs(apart) > ODOMETRY_GAP_S:
            self._notes.append(f"the initial pose's heading was not used: the odometry's nearest heading came "
                               f"{abs(apart):.1f} s from it (more than {ODOMETRY_GAP_S:g} s)")
            return
        psi = wrap_angle(heading - odometry_heading)
        variance = std**2 + (HEADING_TURN_RATE_RAD_S * apart) ** 2
        if self._clone is not None:
            self._remove(range(self._clone, self._clone + 2))
        if self._odometry is None:
            self._add_odometry_frame(np.array([psi, 0.0]), np.diag([variance, self.config.odometry_scale_std**2]))
            return
        i = self._odometry
        self._x[i] = psi
        self._P[i, :] = self._P[:, i] = 0.0
        self._P[i, i] = variance

    def _velocity_outcome(self, aid: VelocityAid, score: float | None, speed: float) -> None:
        if score is None:
            self._last_accepted = self._odometry_heard_s = aid.time_s
            self._velocity_refusals = 0
            return
        self._velocity_refusals += 1
        self._notes.append(f"odometry velocity at {aid.time_s:.1f} s refused: {speed:.1f} m/s read, the track "
                           f"disagrees (normalised innovation {score:.1f})")

    def _stretch_to(self, aid: VelocityAid) -> None:
        """Integrate the odometry frame's displacement since the stretch began, where the track's
        position was cloned into the state (its covariance with everything kept as the filter
        runs on); a gap in the odometry starts a new stretch, and a lost track has none (its
        displacement may be a false lock's doing, and the yaw would be read from it)."""
        stretch = self._stretch
        if self._clone is not None and (aid.time_s - stretch.last_s > ODOMETRY_GAP_S or self._lost):
            self._remove(range(self._clone, self._clone + 2))
        if self._lost:
            return
        if self._clone is None:
            n = len(self._x)
            P = np.zeros((n + 2, n + 2))
            P[:n, :n] = self._P
            P[n:, :n] = self._P[:2, :]
            P[:n, n:] = self._P[:, :2]
            P[n:, n:] = self._P[:2, :2]
            self._x, self._P, self._clone = np.append(self._x, self._x[:2]), P, n
            self._stretch = _Stretch(aid.time_s, aid.time_s, aid.velocity, aid.covariance)
            self._model()
            return
        stretch.extend(aid)

    def _align_odometry(self, aid: VelocityAid) -> None:
        """Once the odometry's stretch is long enough and the track's displacement over it points
        well enough, the odometry frame's yaw (the angle between the two, with its covariance to
        every state kept) and scale (its prior) join the state and the clone goes; the yaw a
        track before this one learned is taken again at once."""
        stretch, c = self._stretch, self._clone
        displacement = self._x[:2] - self._x[c: c + 2]
        if float(np.hypot(*stretch.displacement)) < ALIGN_MIN_M or not float(np.hypot(*displacement)) > 0:
            return
        spread = (self._P[:2, :2] + self._P[c: c + 2, c: c + 2] - self._P[:2, c: c + 2] - self._P[c: c + 2, :2])
        if float(np.linalg.eigvalsh(spread)[-1]) > (ALIGN_DIRECTION_STD_RAD * float(np.hypot(*displacement))) ** 2:
            return
        psi, by_track, odometry_variance = heading_offset(displacement, stretch.displacement, stretch.covariance)
        n = len(self._x)
        cross = by_track @ (self._P[:2, :] - self._P[c: c + 2, :])  # (n,): psi's covariance with every state
        wander = self.config.heading_drift_rad_per_sqrt_s**2 * (stretch.last_s - stretch.first_s)
        P = np.zeros((n + 2, n + 2))
        P[:n, :n] = self._P
        P[n, :n] = P[:n, n] = cross
        P[n, n] = float(by_track @ spread @ by_track) + odometry_variance + wander
        P[n + 1, n + 1] = self.config.odometry_scale_std**2
        self._x, self._P, self._odometry = np.append(self._x, [psi, 0.0]), P, n
        self._remove(range(c, c + 2))
        self._last_accepted = aid.time_s

    def _remove(self, states: Sequence[int]) -> None:
        """Marginalise ``states`` out (their rows and columns go), every index moved along."""
        keep = np.ones(len(self._x), dtype=bool)
        keep[list(states)] = False
        moved = np.cumsum(keep) - 1  # each kept state's new index
        for site in self._sites.values():
            site.index = int(moved[site.index])
        self._odometry = None if self._odometry is None or not keep[self._odometry] else int(moved[self._odometry])
        self._clone = None if self._clone is None or not keep[self._clone] else int(moved[self._clone])
        self._x, self._P = self._x[keep], self._P[np.ix_(keep, keep)]
        self._model()

    def _stale(self, measurement: SiteArrival | PositionAid | VelocityAid) -> None:
        if isinstance(measurement, SiteArrival):
            self.stale_arrivals += 1
            return
        kind = "odometry velocity" if isinstance(measurement, VelocityAid) else measurement.source
        self._notes.append(f"{kind} at {measurement.time_s:.2f} s refused: older than the track "
                           f"({self._t:.2f} s); give it before the stacks that come after it")

    def _due_aids(self, time_s: float) -> list[PositionAid | VelocityAid]:
        """The queued positions and velocities up to ``time_s``, in time order."""
        due = []
        while self._aids and self._aids[0][0] <= time_s:
            due.append(heapq.heappop(self._aids)[2])
        return due

    def _bias_variances(self, arrival: SiteArrival) -> tuple[float, float]:
        """The prior of the site's persistent bias and the stationary variance of its fading
        bias (m^2): ``persistent_bias_fraction`` of the multipath's variance persists, the rest
        fades; without site clock states, the site clock's error is persistent too (see the
        module docstring)."""
        clock = 0.0 if self.config.site_clocks else arrival.clock_std_m
        share = self.config.persistent_bias_fraction
        return share * arrival.bias_std_m**2 + clock**2, (1 - share) * arrival.bias_std_m**2

    def _heard(self, arrival: SiteArrival) -> _Site:
        """The arrival's site, its states added when new; a larger persistent variance than
        before (a site clock's error grows with the database's age) adds the difference, as a
        fresh error."""
        site = self._sites.get(arrival.site)
        if site is None:
            return self._add_site(arrival)
        site.heard_fade = self._faded
        persistent, fading = self._bias_variances(arrival)
        if persistent > site.persistent_m2:
            self._P[site.index, site.index] += persistent - site.persistent_m2
        site.persistent_m2 = persistent
        if fading != site.fading_m2:
            site.fading_m2 = fading
            self._site_variances[list(self._sites).index(arrival.site)] = fading
        return site

    def _add_site(self, arrival: SiteArrival) -> _Site:
        """A newly heard site: its bias states (with site clocks, offset and drift states too) at
        0, with the arrival's sigmas as priors, independent of the rest."""
        c, n = self.config, len(self._x)
        persistent, fading = self._bias_variances(arrival)
        self._sites[arrival.site] = site = _Site(n, persistent, fading, self._faded)
        prior = [persistent, fading]
        if c.site_clocks:
            prior += [arrival.clock_std_m**2, arrival.clock_drift_std_mps**2]
        self._x = np.append(self._x, np.zeros(self._width))
        P = np.zeros((n + self._width, n + self._width))
        P[:n, :n] = self._P
        P[n:, n:] = np.diag(prior)
        self._P = P
        self._model()
        return site

    def _drop_unheard(self) -> None:
        """Forget the states of sites whose bias has faded ``FORGET_CORRELATIONS`` correlations
        since they were last heard (marginalised: their rows and columns go); heard again, they
        start afresh."""
        gone = [name for name, site in self._sites.items() if self._faded - site.heard_fade > FORGET_CORRELATIONS]
        if gone:
            indices = [self._sites.pop(name).index for name in gone]
            self._remove([i + k for i in indices for k in range(self._width)])

    def _position(self, x: np.ndarray) -> np.ndarray:
        if self.config.dims == 2:
            return np.array([x[0], x[1], self.config.snapshot.receiver_height_m])
        return x[:3].copy()

    def _fix_at(self, time_s: float, stamp_ns: int, used: tuple[str, ...], rejected: tuple[str, ...]) -> Fix:
        """The state at ``time_s``: the filter moves on to it; a time before the filter's (a stack
        stamped before its last arrival) gets a copy moved back, the filter staying where it is."""
        dt = time_s - self._t
        if dt >= 0:
            if dt > 0:
                self._predict(dt)
            self._t = time_s
            x, P = self._x, self._P
        else:
            x, P = self._propagated(self._x, self._P, dt)
        dims = self.config.dims
        covariance = np.zeros((3, 3))
        covariance[:dims, :dims] = P[:dims, :dims]
        if dims == 2:
            covariance[2, 2] = UNMEASURED_VARIANCE
        position = self._position(x)
        return Fix(stamp_ns, (float(position[0]), float(position[1]), float(position[2])), covariance, used,
                   FixKind.TRACKED, rejected, math.nan, float(x[self._bias] % FRAME_RANGE_M))

    # ------------------------------------------------------------------ starting

    def _remember(self, arrivals: list[SiteArrival], time_s: float) -> None:
        """Keep the arrivals of the last ``init_window_s``: what a start solves from."""
        self._window.extend(arrivals)
        self._newest = max(self._newest, time_s, arrivals[-1].time_s if arrivals else time_s)
        while self._window and self._window[0].time_s < self._newest - self.config.init_window_s:
            self._window.popleft()

    def _restart(self, why: str, stamp_ns: int, time_s: float, clock_rate: float | None,
                 rejected: tuple[str, ...], anchor: PositionAid | None = None) -> Fix | NoFix:
        """Forget the state and start again at once from the arrivals it could not explain (those
        before them agreed with the state given up), from ``anchor`` where one says where the
        receiver is; ``last_restart`` keeps why, a NoFix says it."""
        self._window = deque(a for a in self._window if a.time_s > self._last_accepted)
        self.last_restart = why
        self._forget()
        if anchor is not None:
            self._prior, self._prior_since = _prior_of(anchor), anchor.time_s
            self._since_fix = (anchor, None)
        outcome = self._start(stamp_ns, time_s, clock_rate, [])
        if isinstance(outcome, NoFix):
            return NoFix(stamp_ns, outcome.reason, f"restarted: {why}; {outcome.message}", rejected)
        return outcome

    def _start_aided(self, stamp_ns: int, time_s: float, clock_rate: float | None, arrivals: list[SiteArrival],
                     aids: list[PositionAid | VelocityAid]) -> Fix | NoFix:
        """A start, the latest position among ``aids`` standing in for an initial position. The
        velocities find no track to move: they pair an operator's heading, and count towards
        the odometry frame two fixes read (:meth:`_know_frame`, for the track that starts next)."""
        for aid in aids:
            if isinstance(aid, VelocityAid):
                self._pair_heading(aid)
                if not aid.in_map_frame:
                    self._read_since_fix(aid)
                continue
            if (frame := self._frame_between_fixes(aid)) is not None and self._pair_agrees(aid, *frame):
                self._know_frame(frame[0], frame[1][-2:, -2:])
        positions = [aid for aid in aids if isinstance(aid, PositionAid)]
        if positions:
            self._prior, self._prior_since = _prior_of(positions[-1]), positions[-1].time_s
        return self._start(stamp_ns, time_s, clock_rate, arrivals)

    def _start(self, stamp_ns: int, time_s: float, clock_rate: float | None,
               arrivals: list[SiteArrival]) -> Fix | NoFix:
        """Start from the stack alone if it can, else from the window; NoFix saying what is missing."""
        dims = self.config.dims
        prior, dropped = self._pending_prior(time_s)
        # a prior is about the receiver now: every recent arrival tells the clock something
        candidates = [arrivals] if prior is None and len({a.site for a in arrivals}) >= dims + 1 else []
        candidates.append(sorted(self._window, key=lambda a: a.time_s))
        outcome: Start | str = ""
        for candidate in candidates:
            outcome = batch_start(candidate, self.config, clock_rate, prior, self._redundant_start)
            if isinstance(outcome, Start):
                break
        if isinstance(outcome, str):
            hint = ("" if prior is not None else "; an initial position (start_from; /initialpose or a GNSS fix in "
                    "ROS) would start from one site")
            return NoFix(stamp_ns, NoFixReason.NOT_INITIALISED, f"waiting for a start: {outcome}{hint}{dropped}")
        self._begin(outcome, candidate)
        if prior is not None:  # the prior's hold counts from when it was given, its wait included
            self._prior, self._held_since = None, self._prior_since
        return self._reported(self._fix_at(time_s, stamp_ns, outcome.sites, outcome.rejected))

    def _pending_prior(self, time_s: float) -> tuple[PositionPrior | None, str]:
        """The initial position waiting for a start, widened by what the receiver may have
        walked since it was given; None and why once it waited ``prior_hold_s`` unused."""
        if self._prior is None:
            return None, ""
        if self._prior_since is None:
            self._prior_since = time_s
        age = time_s - self._prior_since
        c = self.config
        if age > c.prior_hold_s:
            self._prior = None
            return None, (f"; the initial position waited {age:.1f} s for a site (prior_hold_s "
                          f"{c.prior_hold_s:g} s) and was dropped: the receiver may have moved away from it")
        if age <= 0:
            return self._prior, ""
        # per horizontal axis: an unknown velocity (the start's speed prior) and the acceleration walk
        walked = (c.initial_speed_std_mps * age) ** 2 + c.acceleration_std_mps2**2 * age**3 / 3
        return PositionPrior(self._prior.position_enu, self._prior.covariance + np.diag([walked, walked, 0.0])), ""

    def _begin(self, start: Start, arrivals: Sequence[SiteArrival]) -> None:
        """The filter from a batch solution: velocity 0 with the speed prior; the bias states of
        the sites it used, with the priors of their latest arrivals, holding what the batch
        learned of each site's bias (its covariance with the position and clock kept); then
        predicted to the latest arrival used (which widens the position by the distance
        travelled meanwhile).

        A site's bias in the batch is the sum of its states' parts (persistent, fading, and
        with site clock states its clock offset), independent a priori: given the sum ``m``,
        the parts are ``v / V m`` (``v`` their prior variances, ``V`` the sum's) with ``diag(v)
        - v v^T / V`` of their own, whatever ``m`` turned out to be."""
        dims = self.config.dims
        n = dims + 4
        self._x = np.zeros(n)
        self._P = np.zeros((n, n))
        latest = {a.site: a for a in arrivals if a.site in start.sites}  # in time order: the last stays
        for name in start.sites:
            self._add_site(latest[name])
        # theta = [position, b, d, m_s of start.biased] -> the state, T theta, and each site's split
        T = np.zeros((len(self._x), len(start.mean)))
        T[[*range(dims), self._bias, self._bias + 1], np.arange(dims + 2)] = 1.0
        split = np.zeros_like(self._P)
        for j, name in enumerate(start.biased):
            states = np.arange(self._range_parts) + self._sites[name].index
            v = np.diag(self._P)[states]
            T[states, dims + 2 + j] = v / v.sum()
            split[np.ix_(states, states)] = np.diag(v) - np.outer(v, v) / v.sum()
        touched = np.flatnonzero(T.any(axis=1))
        self._x[touched] = (T @ start.mean)[touched]
        self._P[np.ix_(touched, touched)] = (T @ start.covariance @ T.T + split)[np.ix_(touched, touched)]
        velocity = np.arange(dims, dims + 2)
        self._P[velocity, velocity] = self.config.initial_speed_std_mps**2
        self._t = start.time_s
        self._predict(start.latest_s - start.time_s)
        self._t = self._last_accepted = start.latest_s
        if self._odometry_known is not None:  # the odometry's yaw and scale, as the last track left them
            self._add_odometry_frame(*self._odometry_known)

    def _add_odometry_frame(self, values: np.ndarray, covariance: np.ndarray) -> None:
        """The odometry frame's yaw and scale join the state, independent of the rest."""
        n = len(self._x)
        P = np.zeros((n + 2, n + 2))
        P[:n, :n], P[n:, n:] = self._P, covariance
        self._x, self._P, self._odometry = np.append(self._x, values), P, n
        self._model()


def _prior_of(aid: PositionAid) -> PositionPrior:
    """An absolute position as an initial position (its up axis unmeasured in 2-D)."""
    covariance = np.array(aid.covariance, dtype=np.float64)
    covariance[2, :2] = covariance[:2, 2] = 0.0
    covariance[2, 2] = max(covariance[2, 2], UNMEASURED_VARIANCE)
    return PositionPrior(tuple(aid.position_enu), covariance)


def _agree(positions: Sequence[PositionAid], speed_std_mps: float) -> bool:
    """Whether consecutive positions are within 3 sigma of each other, counting what the
    receiver may have moved between them (the start's speed prior)."""
    for earlier, later in zip(positions, positions[1:]):
        moved = speed_std_mps * (later.time_s - earlier.time_s)
        spread = np.trace(earlier.covariance[:2, :2] + later.covariance[:2, :2]) + 2 * moved**2
        if np.sum((later.position_enu[:2] - earlier.position_enu[:2]) ** 2) > 9 * spread:
            return False
    return True


def _checked(arrivals: Sequence[SiteArrival], time_s: float, clock_rate: float | None) -> list[SiteArrival]:
    """The arrivals in time order, or ValueError naming what is not a number it can use."""
    if not _finite(time_s):
        raise ValueError(f"time_s {time_s!r} must be a finite number of seconds")
    if clock_rate is not None and not (_finite(clock_rate) and abs(clock_rate) < MAX_CLOCK_RATE):
        raise ValueError(f"clock_rate {clock_rate!r} must be a finite fraction (ppm * 1e-6) within +-1000 ppm")
    for a in arrivals:
        where = f"arrival of site {a.site!r}"
        for name in ("time_s", "range_mod_m", "timing_std_m", "clock_std_m"):
            if not _finite(getattr(a, name)):
                raise ValueError(f"{where}: {name} {getattr(a, name)!r} is not a finite number")
        if not a.timing_std_m > 0 or a.clock_std_m < 0:
            raise ValueError(f"{where}: timing_std_m {a.timing_std_m!r} must be > 0 and clock_std_m "
                             f"{a.clock_std_m!r} >= 0 (floor ground-truth sigmas before fusion)")
        if np.shape(a.position_enu) != (3,) or not all(_finite(v) for v in a.position_enu):
            raise ValueError(f"{where}: position_enu must be 3 finite ENU metres, got {a.position_enu!r}")
    return sorted(arrivals, key=lambda a: a.time_s)


def _finite(value: object) -> bool:
    """A finite real number (numpy's scalars included), not a string, None or NaN."""
    try:
        return math.isfinite(value)
    except TypeError:
        return False


def _add(names: list[str], name: str) -> None:
    if name not in names:
        names.append(name)
