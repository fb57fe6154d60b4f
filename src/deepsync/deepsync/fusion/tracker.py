"""The tightly coupled tracker: position, velocity and receiver clock, updated by each site as it
is heard, like a GNSS receiver with too few satellites.

Each arrival says ``rho = |x(t) - p_s| + b(t) + m_s(t) (+ o_s(t))`` modulo one frame (2998 km):
the receiver at ``x`` (ENU; 2-D: up held at the receiver height), its clock bias ``b`` (m), the
site's range bias ``m_s`` (m) and, when asked for, the site's frame-clock error ``o_s`` (m). A single arrival fixes one
combination of those, so one site per stack is enough for an update: the motion model carries
the rest from arrival to arrival, and over a few seconds every heard site has its say.

**Filter.** A plain extended Kalman filter of our own (not filterpy, not a UKF). The states are
additive (no attitude, no manifold), so an error-state form buys nothing; the range is nearly
linear over the state's uncertainty (its curvature error, sigma^2 / distance, is centimetres
at metres of uncertainty and hundreds of metres of range), so sigma points buy nothing either.
One pseudorange is a scalar update: the gain is one matrix-vector product over a scalar
innovation variance, no inverse; and the state grows when site clocks join, which a library
filter sized at construction does not do. Sixty lines of numpy, no dependency.

**State** ``[position (D), horizontal velocity (2), b, d, (m_s (, o_s, r_s) per site)]``, ``D`` = 2 or 3:

* horizontal position and velocity: white-noise acceleration, power spectral density
  ``acceleration_std^2 x 1 s`` per axis, i.e. over one second the velocity wanders by
  ``acceleration_std`` (1-sigma). 0.5 m/s^2 covers a walker's stops, starts and turns (1.4 m/s
  gained or lost in about 2 s) without letting the noise of a 15 m range pull the track about.
* up (3-D only): a first-order Gauss-Markov process around the receiver height, stationary
  sigma the height prior's, correlation time ``height_correlation_s``: sites a few degrees above
  the horizon hardly measure height, so what holds it is that receivers stay near the ground.
* receiver clock: bias ``b`` (m) with white frequency noise, drift ``d = db/dt`` (m/s, c times
  the fractional frequency error: 15 ppm is 4.5 km/s) as a random walk. The defaults are a
  TCXO's Allan figures (h0 = 2e-19 -> 0.1 m/sqrt(s), h-2 = 2e-20 -> 0.2 m/s/sqrt(s)), the
  latter raised to 0.5 m/s/sqrt(s) for the temperature changes of a receiver carried about.
  ``b`` is kept modulo one frame: only that is measured.
* site range bias ``m_s`` (m), one per heard site, appended when the site is first heard (and
  after a start, for the sites it used), dropped when it has not been heard for
  ``FORGET_CORRELATIONS`` x ``bias_correlation_s``, added afresh when heard again. Multipath
  and NLOS lengthen a site's range by the same tens of metres stack after stack (the envelope's
  peak lags a blocked first path): taken as white, that error averages down over hundreds of
  stacks that share it, and the filter believes a position it cannot have (simulated walk,
  site biases of -9..+90 m: 2-D NEES 278). As a state it does not average down. A first-order
  Gauss-Markov process towards 0, correlation time ``bias_correlation_s`` (30 s: a walker
  moves ~40 m, over which the scatterers around the receiver change), stationary variance
  ``bias_std_m^2`` of the latest arrival, plus ``clock_std_m^2`` without site clock states:
  the site clock's offset error is then one more per-site constant in the same state. It
  should not decay (it is the database's, not the channel's); the approximation costs little
  while the site is heard every few seconds, since the arrivals hold it, and where the clocks
  matter ``site_clocks`` gives them their own states. A variance larger than before (a site
  clock's error grows with the database's age) is added to the state as a fresh error. The
  arrival's noise is then ``timing_std_m`` alone: what stays from stack to stack is in states.
  Sliding stacks (a stack every ``hop`` of its ``n`` frames) share frames, so that noise repeats
  in the next ``n / hop`` arrivals: its variance counts ``stack_overlap`` = n / hop times.
  A bias common to every site is the receiver clock's ``b``: the priors hold that gauge.
  Weakly observable: a position error traded against biases ``m_s = -u_s . dx`` shows only as
  the geometry turns, and with one site per stack the EKF runs somewhat overconfident along it
  (simulated, constant N(0, 40 m) biases: 2-D NEES 2.1 with 2-3 sites per stack, 3.4 with 1-3).
* site clocks (``site_clocks=True``): per site, next to ``m_s``, offset ``o_s`` (m) and drift
  ``r_s`` (m/s), the error of the tower database's frame timing, appended with the site's
  bias state with the arrival's ``clock_std_m`` and ``clock_drift_std_mps`` as priors (the
  tower database's sigmas; a site without a drift in it gets ``anchors.UNKNOWN_DRIFT_STD``),
  and dropped with it (heard again, the database's priors once more). The offsets are not observable against ``b`` as a whole (adding a
  constant to ``b`` and taking it from every ``o_s`` changes no range), nor the drifts against
  ``d``: their priors hold that gauge, and what the data estimate is how sites disagree. Weakly
  observable too: a constant velocity error ``dv`` traded against drifts ``r_s = -u_s . dv``
  (``u_s`` the unit vector from site to receiver) shows only as the geometry turns, and an EKF
  linearised at its own estimate grows overconfident along it (simulated: 2-D NEES 2-20 over
  two minutes of sites 10-20 ns/s off, now and then diverging). Worth it where site clocks do
  drift (horizontal RMS 0.16-0.94 of that with their errors taken as white, over eight simulated
  sets of three routes), not as a default.

**Gating and the robust fallback.** An innovation whose normalised square exceeds the
chi-square quantile (1 dof, ``gate_probability``) is not used: the site is named in
``rejected`` and counted. A reflection (100-300 m long) or a false lock (km) then never moves
the state; inflating the noise of such an arrival instead would still let a site that stays
long pull the track by metres per epoch. The fallback for the opposite case, where the state
is wrong and not the sites, is to start again: ``max_rejections`` arrivals in a row failing the
gate, from at least two sites, restart the tracker at once from the arrivals it could not
explain, and ``max_coast_s`` without an accepted arrival restarts it from what is heard next
(``last_restart`` keeps why; a NoFix says it).

**Start.** From the last ``init_window_s`` of arrivals, or the current stack alone when it
holds enough sites: ranges unwrapped against the earliest with the drift prior, a drift
guessed from how each repeated site's range moves, one range per site at the window's mid-time
solved by :func:`solve_snapshot`, then all arrivals at once (position, ``b`` and ``d``; the
receiver assumed static) with ``scipy.optimize.least_squares``: a Huber loss first, then the
arrivals beyond the gate left out (named) and the rest solved plainly. The drift's prior is the
sync stage's clock rate (sigma ``clock_rate_std_ppm``) when known, else 0 +- ``max_clock_ppm``.
A start needs ``D + 1`` distinct sites (position and bias; a site more lets the residual test
check them, and where two positions fit equally the snapshot step refuses), and one arrival
more when the clock rate is unknown (the drift is then solved from the data); it must pass the
same residual test as a snapshot. Its covariance comes from the Jacobian; the motion the static assumption ignores
enters twice: each arrival's sigma grows by ``initial_speed_std_mps`` times its distance in time
from the mid-time, and the velocity starts at 0 with that speed as its sigma, so predicting to
the window's end widens the position by the distance walked. The batch takes each arrival's
``std_m`` as white (its bias included); the filter it starts then gets bias states for the sites
used, at their priors, independent of the position the batch solved with their biases in it.

**An initial position** (:meth:`Tracker.start_from`: an operator's pose). Two sites measure one
range difference, a hyperbola, and nothing above starts from them. A :class:`PositionPrior`
adds ``D`` whitened rows to the batch, which then needs one site (the clock), keeps the prior's
uncertainty along what the sites do not measure, and the filter grows it as the receiver walks.
The track is held by the prior for ``prior_hold_s`` from when it was given (the first update
after :meth:`Tracker.start_from`) while fewer than ``D + 1`` sites have states, then given up (a
NoFix says so): along a hyperbola the estimate drifts by the distance walked, and once that is a
fair part of the ranges the linearisation turns overconfident (simulated two-site walks
300-1100 m from the sites: NEES 1.9 over the first 30 s from 30 m priors, 3.8-4.1 by 60 s). A
prior the recent arrivals contradict fails the start's residual test. A prior still waiting for
a site says where the receiver was: the start widens it by the motion model over its age (the
start's speed prior and the acceleration walk), and one that waited ``prior_hold_s`` is dropped
unused. Taken at its word, a 30 m prior that waited 20 s for two sites held the walk at NEES
5.3, one that waited 40 s at 12; widened and held for what is left of its 30 s, NEES 1.6-2.3
after waits of 0-29 s.

**Out-of-order input.** Arrivals older than the filter's time (a late stack) are skipped and
counted (``stale_arrivals``); the returned state is then the filter's moved back to ``time_s``.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from deepsync.fusion.anchors import FRAME_RANGE_M, SiteArrival, unwrap_range
from deepsync.fusion.snapshot import SnapshotConfig, chi_square_limit, solve_snapshot
from deepsync.types import (
    SPEED_OF_LIGHT_M_S,
    UNMEASURED_VARIANCE,
    Fix,
    FixKind,
    NoFix,
    NoFixReason,
    PositionPrior,
)

MAX_CLOCK_RATE = 1e-3  # a clock 1000 ppm off is not a receiver clock but a wrong number
# a site unheard this many bias correlation times is forgotten: its bias state then keeps
# e^-5 (under 1 %) of what the arrivals taught it, and a drive past many sites stays small
FORGET_CORRELATIONS = 5.0


@dataclass(frozen=True)
class TrackerConfig:
    """How the receiver moves, how its clock wanders, and when to trust, coast or start again
    (the module docstring gives the physics of each default)."""

    snapshot: SnapshotConfig = SnapshotConfig()  # dims, receiver height (2-D: up fixed), residual test
    acceleration_std_mps2: float = 0.5  # velocity random walk: m/s gained or lost per second (walking)
    clock_drift_std_mps_per_sqrt_s: float = 0.5  # receiver frequency random walk (TCXO carried about)
    clock_bias_std_m_per_sqrt_s: float = 0.1  # receiver white frequency noise (TCXO)
    gate_probability: float = 1e-3  # chance of gating out a Gaussian innovation (chi-square, 1 dof)
    max_coast_s: float = 10.0  # start again after this long without an accepted arrival
    init_window_s: float = 3.0  # arrivals kept for a start when no stack has enough sites
    initial_speed_std_mps: float = 2.0  # speed prior at a start (walking; ~20 for driving)
    clock_rate_std_ppm: float = 0.5  # uncertainty of the sync stage's clock rate, as a drift prior
    max_clock_ppm: float = 50.0  # drift prior (1-sigma) at a start when the clock rate is unknown
    max_rejections: int = 10  # gated arrivals in a row (from >= 2 sites) that say the state is wrong
    height_correlation_s: float = 60.0  # 3-D: how long the receiver's height stays off the nominal
    bias_correlation_s: float = 30.0  # how long a site's multipath range bias stays (~40 m walked)
    site_clocks: bool = False  # estimate per-site clock offset and drift errors as states
    site_clock_wander_mps_per_sqrt_s: float = 0.01  # site frequency random walk (disciplined eNB)
    stack_overlap: float = 1.0  # stacks each frame is in: n_frames / hop_frames (PipelineConfig sets it)
    prior_hold_s: float = 30.0  # how long an initial position is used, from when it is given, while D + 1 sites are not heard

    def __post_init__(self) -> None:
        if not isinstance(self.snapshot, SnapshotConfig):
            raise ValueError(f"snapshot: {self.snapshot!r} is not a SnapshotConfig")
        if not isinstance(self.site_clocks, bool):
            raise ValueError(f"site_clocks: {self.site_clocks!r} is not a bool")
        if not (isinstance(self.max_rejections, int) and not isinstance(self.max_rejections, bool)
                and 2 <= self.max_rejections <= 10_000):
            raise ValueError(f"max_rejections: {self.max_rejections!r} is out of range (2..10000)")
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
            "bias_correlation_s": 0 < self.bias_correlation_s <= 1e5,
            "site_clock_wander_mps_per_sqrt_s": 0 <= self.site_clock_wander_mps_per_sqrt_s <= 1e3,
            "stack_overlap": 1 <= self.stack_overlap <= 1000,
            "prior_hold_s": 0 < self.prior_hold_s <= 3600,
        }
        for name, ok in checks.items():
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and ok):
                raise ValueError(f"{name}: {value!r} is out of range")

    @property
    def dims(self) -> int:
        return self.snapshot.dims


@dataclass(frozen=True)
class _Start:
    """A batch solution: ``mean`` = [position (D), b, d] at ``time_s``, its covariance, the time
    of the latest arrival it used, and the sites it used and left out."""

    time_s: float
    mean: np.ndarray
    covariance: np.ndarray
    latest_s: float
    sites: tuple[str, ...]
    rejected: tuple[str, ...]


@dataclass
class _Site:
    """A heard site's states: its range bias at ``index`` (with site clocks, its clock offset and
    drift next), the bias's stationary variance (m^2) and when the site was last heard."""

    index: int
    variance_m2: float
    heard_s: float


class Tracker:
    """Follows the receiver through stacks of 0..N site arrivals (see the module docstring)."""

    def __init__(self, config: TrackerConfig | None = None) -> None:
        self.config = config or TrackerConfig()
        c = self.config
        self._gate = chi_square_limit(c.gate_probability, 1)
        self.stale_arrivals = 0  # arrivals older than the filter's time, skipped
        self.rejected_arrivals = 0  # arrivals that failed the gate
        self.last_restart: str | None = None  # why the tracker last gave up its state and started again
        self.reset()

    def reset(self) -> None:
        """Forget everything heard (a new stream, or one that started over): the next start
        needs fresh arrivals."""
        self._window: deque[SiteArrival] = deque()
        self._newest = -math.inf
        self._prior: PositionPrior | None = None
        self._prior_since: float | None = None  # the time of the first update after the prior was given
        self._forget()

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

    def _forget(self) -> None:
        """Forget the state but keep the window of recent arrivals, for a start at once."""
        c, dims = self.config, self.config.dims
        self._x = np.zeros(0)
        self._P = np.zeros((0, 0))
        self._t = math.nan
        self._last_accepted = math.nan
        self._held_since: float | None = None  # when the initial position the track rests on was given
        self._rejection_run: list[str] = []
        self._sites: dict[str, _Site] = {}  # in the order of their states
        self._width = 3 if c.site_clocks else 1  # states per site: bias (, clock offset, clock drift)
        self._bias = dims + 2  # after the position and the horizontal velocity
        self._model()

    def _model(self) -> None:
        """The motion model of the receiver's states and the sites': F = I + dt S, Q = |dt|^3/3 Q3
        + dt|dt|/2 Q2 + |dt| Q1 (an integrated random walk per pair, exact for any step, back in
        time too), the site biases' Gauss-Markov decay set in by :meth:`_propagated`."""
        c, dims = self.config, self.config.dims
        n = self._bias + 2 + self._width * len(self._sites)
        # each pair: a "to" state integrating its "from" state, which random-walks with that PSD
        pairs = [(i, dims + i, c.acceleration_std_mps2**2) for i in range(2)]
        pairs.append((self._bias, self._bias + 1, c.clock_drift_std_mps_per_sqrt_s**2))
        if c.site_clocks:
            pairs += [(site.index + 1, site.index + 2, c.site_clock_wander_mps_per_sqrt_s**2)
                      for site in self._sites.values()]
        self._eye = np.eye(n)
        self._shift, self._q3, self._q2, self._q1 = (np.zeros((n, n)) for _ in range(4))
        for to, frm, q in pairs:
            self._shift[to, frm] = 1.0
            self._q3[to, to] = self._q2[to, frm] = self._q2[frm, to] = self._q1[frm, frm] = q
        self._q1[self._bias, self._bias] = c.clock_bias_std_m_per_sqrt_s**2
        self._site_biases = np.array([site.index for site in self._sites.values()], dtype=np.intp)
        self._site_variances = np.array([site.variance_m2 for site in self._sites.values()])

    @property
    def initialised(self) -> bool:
        return len(self._x) > 0

    def update(self, arrivals: Sequence[SiteArrival], stamp_ns: int, time_s: float,
               clock_rate: float | None = None) -> Fix | NoFix:
        """Predict to each arrival's time in order and update with it; return the state at
        ``time_s`` (a :class:`Fix`, ``kind`` TRACKED) or why there is none (NOT_INITIALISED).

        ``clock_rate`` (ppm * 1e-6), the receiver clock error the sync stage measured, is the
        drift prior of a start. Once tracking it is not used: the ranges measure the drift to
        m/s within seconds, and the sync stage smooths its rate over stacks, so its errors would
        enter stack after stack as the same error, not as fresh information.
        Raises ValueError for a non-finite time, range, position or sigma (nothing changes then).
        """
        arrivals = _checked(arrivals, time_s, clock_rate)
        self._remember(arrivals, time_s)
        now = min(time_s, arrivals[0].time_s) if arrivals else time_s
        if self.initialised and now - self._last_accepted > self.config.max_coast_s:
            return self._restart(f"no site accepted for {now - self._last_accepted:.1f} s "
                                 f"(max_coast_s {self.config.max_coast_s:g} s)", stamp_ns, time_s, clock_rate, ())
        if not self.initialised:
            return self._start(stamp_ns, time_s, clock_rate, arrivals)
        if self._held_since is not None and len(self._sites) > self.config.dims:
            self._held_since = None  # the sites fix the position now: the prior is forgotten
        if self._held_since is not None and now - self._held_since > self.config.prior_hold_s:
            return self._restart(f"the initial position, given {now - self._held_since:.1f} s ago, still held the "
                                 f"track (prior_hold_s {self.config.prior_hold_s:g} s) with only "
                                 f"{', '.join(self._sites)} heard", stamp_ns, time_s, clock_rate, ())
        self._drop_unheard()
        used: list[str] = []
        rejected: list[str] = []
        for arrival in arrivals:
            if arrival.time_s < self._t:
                self.stale_arrivals += 1
                continue
            self._predict(arrival.time_s - self._t)
            self._t = arrival.time_s
            if self._correct(arrival):
                _add(used, arrival.site)
                self._last_accepted = arrival.time_s
                self._rejection_run.clear()
                continue
            _add(rejected, arrival.site)
            self.rejected_arrivals += 1
            self._rejection_run.append(arrival.site)
            if len(self._rejection_run) >= self.config.max_rejections and len(set(self._rejection_run)) >= 2:
                sites = ", ".join(sorted(set(self._rejection_run)))
                return self._restart(f"the last {len(self._rejection_run)} arrivals (sites {sites}) all failed the "
                                     "gate: the state, not the sites, was wrong", stamp_ns, time_s, clock_rate,
                                     tuple(rejected))
        self._P = 0.5 * (self._P + self._P.T)  # the scalar updates' rounding, kept from accumulating
        return self._fix_at(time_s, stamp_ns, tuple(used), tuple(rejected))

    # ------------------------------------------------------------------ the filter

    def _predict(self, dt: float) -> None:
        """Move the filter ``dt`` seconds on; ``b`` stays within half a frame of 0."""
        self._x, self._P = self._propagated(self._x, self._P, dt)
        self._x[self._bias] = (self._x[self._bias] + FRAME_RANGE_M / 2) % FRAME_RANGE_M - FRAME_RANGE_M / 2

    def _propagated(self, x: np.ndarray, P: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        F = self._eye + dt * self._shift
        a = abs(dt)
        Q = (a**3 / 3) * self._q3 + (0.5 * dt * a) * self._q2 + a * self._q1
        if len(self._site_biases):
            # site biases: first-order Gauss-Markov towards 0, holding their stationary variance
            decay = -math.expm1(-2 * a / self.config.bias_correlation_s)
            F[self._site_biases, self._site_biases] = math.exp(-dt / self.config.bias_correlation_s)
            Q[self._site_biases, self._site_biases] = self._site_variances * decay
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
        h[site.index] = 1.0  # the site's range bias (and clock offset, next to it)
        if self.config.site_clocks:
            h[site.index + 1] = 1.0
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
        x += gain * innovation
        P -= np.outer(gain, ph)
        return True

    def _bias_variance(self, arrival: SiteArrival) -> float:
        """The stationary variance of the site's bias state: multipath, and without site clock
        states the site clock's error too (one constant per site, see the module docstring)."""
        clock = 0.0 if self.config.site_clocks else arrival.clock_std_m
        return arrival.bias_std_m**2 + clock**2

    def _heard(self, arrival: SiteArrival) -> _Site:
        """The arrival's site, its states added when new; a larger bias variance than before (a
        site clock's error grows with the database's age) adds the difference, as a fresh error."""
        site = self._sites.get(arrival.site)
        if site is None:
            return self._add_site(arrival)
        site.heard_s = arrival.time_s
        variance = self._bias_variance(arrival)
        if variance != site.variance_m2:
            self._P[site.index, site.index] += max(variance - site.variance_m2, 0.0)
            site.variance_m2 = variance
            self._site_variances[list(self._sites).index(arrival.site)] = variance
        return site

    def _add_site(self, arrival: SiteArrival) -> _Site:
        """A newly heard site: its bias state (with site clocks, offset and drift states too) at 0,
        with the arrival's sigmas as priors, independent of the rest."""
        c, n = self.config, len(self._x)
        site = self._sites[arrival.site] = _Site(n, self._bias_variance(arrival), arrival.time_s)
        prior = [site.variance_m2]
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
        """Forget the states of sites unheard for ``FORGET_CORRELATIONS`` bias correlation times
        (marginalised: their rows and columns go); heard again, they start afresh."""
        oldest = self._t - FORGET_CORRELATIONS * self.config.bias_correlation_s
        gone = [name for name, site in self._sites.items() if site.heard_s < oldest]
        if not gone:
            return
        keep = np.ones(len(self._x), dtype=bool)
        for name in gone:
            index = self._sites.pop(name).index
            keep[index: index + self._width] = False
        moved = np.cumsum(keep) - 1  # each kept state's new index
        for site in self._sites.values():
            site.index = int(moved[site.index])
        self._x, self._P = self._x[keep], self._P[np.ix_(keep, keep)]
        self._model()

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
                 rejected: tuple[str, ...]) -> Fix | NoFix:
        """Forget the state and start again at once from the arrivals it could not explain (those
        before them agreed with the state given up); ``last_restart`` keeps why, a NoFix says it."""
        self._window = deque(a for a in self._window if a.time_s > self._last_accepted)
        self.last_restart = why
        self._forget()
        outcome = self._start(stamp_ns, time_s, clock_rate, [])
        if isinstance(outcome, NoFix):
            return NoFix(stamp_ns, outcome.reason, f"restarted: {why}; {outcome.message}", rejected)
        return outcome

    def _start(self, stamp_ns: int, time_s: float, clock_rate: float | None,
               arrivals: list[SiteArrival]) -> Fix | NoFix:
        """Start from the stack alone if it can, else from the window; NoFix saying what is missing."""
        dims = self.config.dims
        prior, dropped = self._pending_prior(time_s)
        # a prior is about the receiver now: every recent arrival tells the clock something
        candidates = [arrivals] if prior is None and len({a.site for a in arrivals}) >= dims + 1 else []
        candidates.append(sorted(self._window, key=lambda a: a.time_s))
        outcome: _Start | str = ""
        for candidate in candidates:
            outcome = _batch_start(candidate, self.config, clock_rate, prior)
            if isinstance(outcome, _Start):
                break
        if isinstance(outcome, str):
            hint = "" if prior is not None else "; an initial position (start_from; /initialpose in ROS) would start from one site"
            return NoFix(stamp_ns, NoFixReason.NOT_INITIALISED, f"waiting for a start: {outcome}{hint}{dropped}")
        self._begin(outcome, candidate)
        if prior is not None:  # the prior's hold counts from when it was given, its wait included
            self._prior, self._held_since = None, self._prior_since
        return self._fix_at(time_s, stamp_ns, outcome.sites, outcome.rejected)

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
                          f"{c.prior_hold_s:g} s) and was dropped: the receiver may have walked away from it")
        if age <= 0:
            return self._prior, ""
        # per horizontal axis: an unknown velocity (the start's speed prior) and the acceleration walk
        walked = (c.initial_speed_std_mps * age) ** 2 + c.acceleration_std_mps2**2 * age**3 / 3
        return PositionPrior(self._prior.position_enu, self._prior.covariance + np.diag([walked, walked, 0.0])), ""

    def _begin(self, start: _Start, arrivals: Sequence[SiteArrival]) -> None:
        """The filter from a batch solution: velocity 0 with the speed prior, predicted to the
        latest arrival used (which widens the position by the distance walked meanwhile); then
        the bias states of the sites it used, with the priors of their latest arrivals (the batch
        took those biases as noise: their correlation with its position is not kept)."""
        dims = self.config.dims
        n = dims + 4
        solved = np.array([*range(dims), self._bias, self._bias + 1])
        self._x = np.zeros(n)
        self._x[solved] = start.mean
        self._P = np.zeros((n, n))
        self._P[np.ix_(solved, solved)] = start.covariance
        velocity = np.arange(dims, dims + 2)
        self._P[velocity, velocity] = self.config.initial_speed_std_mps**2
        self._t = start.time_s
        self._predict(start.latest_s - start.time_s)
        self._t = self._last_accepted = start.latest_s
        latest = {a.site: a for a in arrivals if a.site in start.sites}  # in time order: the last stays
        for name in start.sites:
            self._add_site(latest[name])


def _batch_start(arrivals: Sequence[SiteArrival], config: TrackerConfig, clock_rate: float | None,
                 prior: PositionPrior | None = None) -> _Start | str:
    """Position, clock bias and drift from arrivals spread over a few seconds (the receiver taken
    as static), or a sentence saying why not. ``arrivals`` must be in time order. With a
    ``prior`` (the position's, at the arrivals' mean time) one site is enough: it measures the
    clock, and along its range the position, by as much as the prior leaves open."""
    dims = config.dims
    names = sorted({a.site for a in arrivals})
    rate_known = clock_rate is not None
    needed = 1 if prior is not None else dims + 1
    if len(names) < needed:
        what = "clock bias; the initial position given" if prior is not None else "position and clock bias"
        return (f"{len(names)} site(s) heard in the last {config.init_window_s:g} s ({', '.join(names) or 'none'}); "
                f"{needed} needed in {dims}-D ({what})")
    if len(arrivals) < (2 if prior is not None else dims + 3) - rate_known:
        return f"{len(arrivals)} arrivals from {len(names)} sites: one more needed to solve the unknown clock drift"
    problem = _BatchProblem(arrivals, config, clock_rate, prior)
    start = problem.start()
    if isinstance(start, str):
        return start
    keep = np.ones(len(arrivals), dtype=bool)
    theta = problem.fit(start, keep, robust=True)
    # a false lock or a reflection among them: out (once), and the rest solved without it
    keep = np.abs(problem.residuals(theta, keep)[: keep.sum()]) ** 2 <= chi_square_limit(config.gate_probability, 1)
    kept = sorted({a.site for a, k in zip(arrivals, keep) if k})
    if len(kept) < needed:  # before solving again: fewer would leave the solve underdetermined
        return f"after leaving out arrivals beyond the gate, {len(kept)} site(s) remain; {needed} needed"
    if not keep.all():
        theta = problem.fit(theta, keep, robust=False)
    residuals = problem.residuals(theta, keep)
    chi_square = float(residuals @ residuals)
    dof = len(residuals) - len(theta)
    if dof > 0 and chi_square > chi_square_limit(config.snapshot.outlier_probability, dof):
        return (f"the {int(keep.sum())} arrivals of {', '.join(kept)} contradict their sigmas taken as static "
                f"(chi-square {chi_square:.1f} with {dof} degrees of freedom)")
    jacobian = problem.jacobian(theta, keep)
    try:
        covariance = np.linalg.inv(jacobian.T @ jacobian)
    except np.linalg.LinAlgError:
        covariance = np.full((len(theta), len(theta)), math.inf)
    horizontal = math.sqrt(max(covariance[0, 0] + covariance[1, 1], 0.0))
    typical = float(np.median(problem.sigma[keep]))
    if prior is None and not horizontal <= config.snapshot.max_gdop * typical:  # a prior bounds it
        return (f"the geometry of {', '.join(kept)} does not fix the position ({horizontal:.0f} m 1-sigma from "
                f"{typical:.0f} m ranges)")
    mean = theta.copy()
    mean[dims] = (mean[dims] + problem.reference_m) % FRAME_RANGE_M
    rejected = tuple(sorted({a.site for a, k in zip(arrivals, keep) if not k} - set(kept)))
    return _Start(problem.t_ref, mean, covariance, float(problem.t[keep].max()), tuple(kept), rejected)


class _BatchProblem:
    """Arrivals over a window as one least-squares problem in [position (D), b, d] at the mean
    arrival time, ``b`` counted from the earliest arrival's range (``reference_m``); a position
    prior, whitened by its covariance's Cholesky factor, adds ``D`` rows."""

    def __init__(self, arrivals: Sequence[SiteArrival], config: TrackerConfig, clock_rate: float | None,
                 prior: PositionPrior | None = None) -> None:
        self.config = config
        dims = config.dims
        self.prior_mean = None if prior is None else np.array(prior.position_enu[:dims])
        # rows W (x - mean) with W = L^-1, C = L L^T: unit-variance residuals of the prior
        self.prior_root = None if prior is None else np.linalg.inv(np.linalg.cholesky(prior.covariance[:dims, :dims]))
        self.arrivals = list(arrivals)
        self.t = np.array([a.time_s for a in arrivals])
        self.t_ref = float(self.t.mean())
        if clock_rate is None:
            self.drift_prior, self.drift_std = 0.0, config.max_clock_ppm * 1e-6 * SPEED_OF_LIGHT_M_S
        else:
            self.drift_prior = clock_rate * SPEED_OF_LIGHT_M_S
            self.drift_std = config.clock_rate_std_ppm * 1e-6 * SPEED_OF_LIGHT_M_S
        first = self.arrivals[0]
        self.reference_m = first.range_mod_m
        # a 20 ppm clock moves the ranges 18 km in 3 s: well within the half frame unwrapping allows
        predicted = [first.range_mod_m + self.drift_prior * (a.time_s - first.time_s) for a in arrivals]
        self.rho = np.array([unwrap_range(a.range_mod_m, p) for a, p in zip(arrivals, predicted)]) - self.reference_m
        motion = config.initial_speed_std_mps * np.abs(self.t - self.t_ref)  # the static assumption's error
        self.sigma = np.hypot([a.std_m for a in arrivals], motion)
        self.sites = np.array([a.position_enu for a in arrivals], dtype=np.float64)
        self.names = np.array([a.site for a in arrivals])

    def position(self, theta: np.ndarray) -> np.ndarray:
        if self.config.dims == 2:
            return np.array([theta[0], theta[1], self.config.snapshot.receiver_height_m])
        return theta[:3]

    def start(self) -> np.ndarray | str:
        """A first guess: the drift from how repeated sites' ranges move, then one range per
        site at ``t_ref`` (the median: a single false lock does not move it) solved as a snapshot,
        or with a prior, its position (the sites may be too few for a snapshot)."""
        dt = self.t - self.t_ref
        dims = self.config.dims
        numerator = denominator = 0.0
        for name in set(self.names):
            mine = self.names == name
            t = dt[mine] - dt[mine].mean()
            numerator += float(t @ (self.rho[mine] - self.rho[mine].mean()))
            denominator += float(t @ t)
        # the slope's information (denominator / sigma^2) against the prior's: repeats 10 ms
        # apart say little about a drift, seconds apart almost everything
        weight = float(np.median(self.sigma)) ** 2 / self.drift_std**2
        drift = (numerator + weight * self.drift_prior) / (denominator + weight)
        collapsed = self.rho - drift * dt
        if self.prior_mean is not None:
            bias = float(np.median(collapsed - np.linalg.norm(self.sites - self.position(self.prior_mean), axis=1)))
            return np.array([*self.prior_mean, bias, drift])
        stack = []
        for name in sorted(set(self.names)):
            mine = np.flatnonzero(self.names == name)
            stack.append(SiteArrival(str(name), self.sites[mine[0]], self.t_ref,
                                     float(np.median(collapsed[mine])) % FRAME_RANGE_M,
                                     float(np.median(self.sigma[mine])), ()))
        snapshot = solve_snapshot(stack, self.config.snapshot)
        if isinstance(snapshot, NoFix):
            return f"the sites' ranges do not solve ({snapshot.reason.value}): {snapshot.message}"
        position = np.asarray(snapshot.position_enu)
        distances = np.linalg.norm(self.sites - position, axis=1)
        bias = float(np.median(collapsed - distances))
        return np.array([*position[:dims], bias, drift])

    def residuals(self, theta: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """Arrivals (measured minus modelled, over sigma), then the drift prior (and height prior)."""
        dims = self.config.dims
        distance = np.linalg.norm(self.sites[keep] - self.position(theta), axis=1)
        model = distance + theta[dims] + theta[dims + 1] * (self.t[keep] - self.t_ref)
        priors = [(theta[dims + 1] - self.drift_prior) / self.drift_std]
        if dims == 3:
            priors.append((theta[2] - self.config.snapshot.receiver_height_m) / self.config.snapshot.height_prior_std_m)
        if self.prior_root is not None:
            priors.extend(self.prior_root @ (theta[:dims] - self.prior_mean))
        return np.concatenate([(self.rho[keep] - model) / self.sigma[keep], priors])

    def jacobian(self, theta: np.ndarray, keep: np.ndarray) -> np.ndarray:
        dims = self.config.dims
        diff = self.position(theta) - self.sites[keep]
        unit = diff / np.maximum(np.linalg.norm(diff, axis=1, keepdims=True), 1e-9)
        rows = np.hstack([unit[:, :dims], np.ones((len(unit), 1)), (self.t[keep] - self.t_ref)[:, None]])
        priors = np.zeros((1 + (dims == 3), dims + 2))
        priors[0, dims + 1] = -1 / self.drift_std
        if dims == 3:
            priors[1, 2] = -1 / self.config.snapshot.height_prior_std_m
        if self.prior_root is not None:
            position = np.zeros((dims, dims + 2))
            position[:, :dims] = -self.prior_root
            priors = np.vstack([priors, position])
        return -np.vstack([rows / self.sigma[keep, None], priors])

    def fit(self, theta: np.ndarray, keep: np.ndarray, robust: bool) -> np.ndarray:
        """Levenberg-Marquardt; ``robust``: then again with a Huber loss (3 sigma) where a
        residual lies beyond it, which bounds what a wild arrival can pull."""
        result = least_squares(self.residuals, theta, jac=self.jacobian, args=(keep,), method="lm", max_nfev=100)
        if robust and np.max(np.abs(result.fun)) > 3.0:
            result = least_squares(self.residuals, result.x, jac=self.jacobian, args=(keep,), loss="huber",
                                   f_scale=3.0, x_scale="jac", max_nfev=100)
        return result.x


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
