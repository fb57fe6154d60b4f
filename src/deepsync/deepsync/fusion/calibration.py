"""Site clock calibration: each heard site's frame-timing offset and drift, from a recording made
at known positions.

FDD eNodeBs are not time-synchronised, and each frame clock runs on its own oscillator, a few
to tens of ppb off: 20 ppb is 1.2 us (360 m of range) a minute. A receiver that knows where it
was turns every arrival into a reading of its site's clock. With ``d`` the true distance, an
arrival of site ``s`` read at receiver time ``t`` (seconds after the reference instant) says::

    y  =  range_mod_m - d  =  b(t) + c * (delta_s + rate_s * t)      (modulo a frame, 2998 km)

``b(t)`` is the receiver clock's bias (m), the same for every site heard at ``t``, and
``delta_s + rate_s * t`` is the site's true frame timing minus the database's: the corrections
sought. Once each ``y`` is unwrapped the model is linear in every unknown.

* **Receiver clock**: a polynomial of ``clock_order`` (2: bias, frequency error, and its drift)
  in each ``clock_segment_s`` piece of the recording. Not a free bias per stack: on a hard
  route most stacks hear one site, and a bias of its own would absorb that arrival whole. Not
  one polynomial for a whole long recording either: a free-running oscillator's frequency
  wanders with temperature, and a quadratic follows it only for so long.
* **Gauge**: site clocks are seen only against the receiver clock, so a correction common to
  every site (offset and drift alike) is indistinguishable from the receiver's own. The
  *reference site*, the one heard most often (ties: by name), keeps its database timing by
  definition; every other site's correction and sigma is relative to it. TDOA fusion needs
  nothing more: a common error of all sites is the receiver clock's.
* **Unwrapping**: each site's ``y`` is first unwrapped along its own arrivals, predicted with
  the clock rate measured over short gaps (a 100 ppm receiver moves 30 km/s, a frame is 2998
  km); after each fit every ``y`` is unwrapped again next to the model, and the fit repeated
  while any of them moved by a frame. A site's own whole-frame ambiguity goes into its offset,
  which is reported modulo a frame.
* **Fit**: linear least squares weighted by each arrival's own timing sigma
  (``scipy.optimize.least_squares``) with a Huber loss at 3 sigma against NLOS outliers (a
  late reflection pulls a bounded amount). Stated sigmas are only relative weights: their scale
  is re-estimated from the residuals (MAD, which outliers do not move).
* **Sigmas**: ``(A^T W A)^-1`` times the residual variance (in the Huber M-estimator's form:
  ``sum psi^2 / (n - p) / mean(psi')^2``, the plain variance when no residual passes the knee).
  Unlike a snapshot's 1-3 degrees of freedom, a recording gives hundreds against tens of
  unknowns: the variance estimate is good to ``sqrt(2 / (n - p))``, a few percent. Residuals
  that persist in time (multipath and NLOS bias stay with a site for seconds while the receiver
  walks) count as fewer independent arrivals: each site's sigmas grow by the AR(1) factor of
  its residuals (``_persistence``). On an NLOS route a bias that changes along the way still
  looks like a clock drift, and no recording tells the two apart: calibrate in line of sight.

Corrections hold at the observations' time origin (the ``reference_ns`` of the arrivals).
Choose it near the middle of the recording: there a site's offset and drift estimates are
almost uncorrelated, which matters because the database keeps no correlation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import least_squares

from deepsync.fusion.anchors import FRAME_NS, FRAME_RANGE_M, SiteArrival, unwrap_range
from deepsync.fusion.snapshot import HUBER_KNEE
from deepsync.numeric import mad_spread
from deepsync.towers import MAX_DRIFT_NS_PER_S, TowerDatabase, parse_tower_database, tower_database_to_dict
from deepsync.types import FRAME_SECONDS, SPEED_OF_LIGHT_M_S

C = SPEED_OF_LIGHT_M_S
SHORT_GAP_S = 1.0  # same-site arrivals this close measure the clock rate without ambiguity
MAX_UNWRAP_ROUNDS = 5  # refits while an unwrap moves: one or two in practice


@dataclass(frozen=True)
class CalibrationConfig:
    """``clock_order``: the receiver clock polynomial's order in each ``clock_segment_s`` of the
    recording (a segment with fewer distinct arrival times gets a lower order);
    ``min_timing_std_m`` floors an arrival's stated sigma (ground-truth arrivals state 0)."""

    clock_order: int = 2
    clock_segment_s: float = 10.0
    min_timing_std_m: float = 1.0

    def __post_init__(self) -> None:
        order = self.clock_order
        if isinstance(order, bool) or not isinstance(order, int) or not 0 <= order <= 5:
            raise ValueError(f"clock_order: {self.clock_order!r} must be an integer in 0..5")
        for name, high in (("clock_segment_s", 1e6), ("min_timing_std_m", 1e4)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= high:
                raise ValueError(f"{name}: {value!r} must be a positive number (<= {high:g})")


@dataclass(frozen=True)
class CalibrationObservation:
    """One site heard at one instant, and where the receiver's antenna truly was then."""

    arrival: SiteArrival
    truth_enu: np.ndarray = field(compare=False)  # (3,) m, map frame, at arrival.time_s


@dataclass(frozen=True)
class SiteCalibration:
    """A site's timing correction: true frame timing minus the database's, relative to the
    reference site, at the observations' time origin (``offset_correction_s``, modulo a frame
    into [-5, 5) ms) and its rate (``drift_correction``, s/s), with 1-sigmas; the reference site's
    are 0 by definition. ``residual_rms_m``: its arrivals' post-fit residuals (outliers too)."""

    site: str
    offset_correction_s: float
    offset_std_s: float
    drift_correction: float
    drift_std: float
    n_arrivals: int
    residual_rms_m: float


@dataclass(frozen=True)
class ReceiverClock:
    """The receiver clock bias fitted (m, modulo a frame, in the reference site's gauge): in
    segment ``k`` (``edges_s[k]`` to ``edges_s[k + 1]``) a polynomial in seconds from its middle,
    ``coefficients[k][j]`` multiplying the ``j``-th power."""

    edges_s: np.ndarray
    coefficients: tuple[np.ndarray, ...]

    def segment_of(self, time_s: np.ndarray) -> np.ndarray:
        """Index of each time's segment (before the first or after the last: that one)."""
        return np.clip(np.searchsorted(self.edges_s, time_s, side="right") - 1, 0, len(self.coefficients) - 1)

    def centre_s(self, segment: np.ndarray) -> np.ndarray:
        return 0.5 * (self.edges_s[segment] + self.edges_s[segment + 1])

    def bias_m(self, time_s: np.ndarray) -> np.ndarray:
        time_s = np.asarray(time_s, dtype=np.float64)
        segment = self.segment_of(time_s)
        local = time_s - self.centre_s(segment)
        bias = np.zeros(time_s.shape)
        for k, coefficients in enumerate(self.coefficients):
            inside = segment == k
            bias[inside] = np.polynomial.polynomial.polyval(local[inside], coefficients)
        return bias

    def rate(self, time_s: float) -> float:
        """The receiver clock's fractional frequency error at ``time_s`` (s/s, ppm * 1e-6)."""
        segment = int(self.segment_of(np.array(time_s)))
        derivative = np.polynomial.polynomial.polyder(self.coefficients[segment])
        return float(np.polynomial.polynomial.polyval(time_s - self.centre_s(segment), derivative)) / C


@dataclass(frozen=True)
class CalibrationResult:
    """Every heard site's correction (sorted by name), the gauge (``reference_site``), the
    receiver clock fitted, the residual RMS (m) against the clock alone with the database's
    timing (``before``, relative to the reference site) and after the corrections, and the
    factor the stated timing sigmas were scaled by (``sigma_scale``: 1 if they were right)."""

    sites: tuple[SiteCalibration, ...]
    reference_site: str
    clock: ReceiverClock
    residual_rms_before_m: float
    residual_rms_after_m: float
    sigma_scale: float

    def site(self, name: str) -> SiteCalibration:
        for site in self.sites:
            if site.site == name:
                return site
        raise KeyError(f"site {name!r} was not calibrated")


class _Problem:
    """The arrivals as arrays, sorted by time, and the linear model's design matrix (metres):
    clock polynomials per segment, then each non-reference site's offset, then its drift."""

    def __init__(self, observations: Sequence[CalibrationObservation], config: CalibrationConfig) -> None:
        _check_finite(observations)
        order = np.argsort([o.arrival.time_s for o in observations], kind="stable")
        arrivals = [observations[i].arrival for i in order]
        self.time = np.array([a.time_s for a in arrivals])
        self.names = sorted({a.site for a in arrivals})
        self.site = np.array([self.names.index(a.site) for a in arrivals], dtype=int)
        _check_coverage(self.names, self.site, self.time)
        truth = np.array([observations[i].truth_enu for i in order], dtype=np.float64)
        distance = np.linalg.norm(truth - np.array([a.position_enu for a in arrivals]), axis=1)
        self.y_mod = np.array([a.range_mod_m for a in arrivals]) - distance
        self.sigma = np.maximum([a.timing_std_m for a in arrivals], config.min_timing_std_m)
        self.counts = np.bincount(self.site, minlength=len(self.names))
        self.reference = int(np.argmax(self.counts))  # the first of the most heard, names being sorted
        self.clock_columns, self.edges, self.segment_orders = self._clock_columns(config)
        self.design = np.hstack([self.clock_columns, self._site_columns()])
        self._check_determined(config)

    def _clock_columns(self, config: CalibrationConfig) -> tuple[np.ndarray, np.ndarray, list[int]]:
        """The receiver clock's columns, the segments' edges and each segment's order."""
        start, end = self.time[0], self.time[-1]
        n_segments = max(1, round((end - start) / config.clock_segment_s))
        edges = np.linspace(start, end, n_segments + 1)
        occupied = np.unique(ReceiverClock(edges, (np.zeros(1),) * n_segments).segment_of(self.time))
        edges = np.append(edges[occupied], end)  # a segment without arrivals (a gap) joins the one before
        n_segments = len(occupied)
        clock = ReceiverClock(edges, (np.zeros(1),) * n_segments)
        segment = clock.segment_of(self.time)
        local = self.time - clock.centre_s(segment)
        columns, orders = [], []
        for k in range(n_segments):
            inside = segment == k
            orders.append(min(config.clock_order, len(np.unique(self.time[inside])) - 1))
            columns += [np.where(inside, local**j, 0.0) for j in range(orders[-1] + 1)]
        return np.column_stack(columns), edges, orders

    def _site_columns(self) -> np.ndarray:
        others = [s for s in range(len(self.names)) if s != self.reference]
        offsets = [(self.site == s).astype(np.float64) for s in others]
        drifts = [np.where(self.site == s, self.time, 0.0) for s in others]
        return np.column_stack(offsets + drifts)

    def _check_determined(self, config: CalibrationConfig) -> None:
        """Every unknown must be pinned by the data: a site heard only in segments where no other
        site is has its clock absorbed by the receiver's; and the residuals need a degree of freedom."""
        n, p = self.design.shape
        if n <= p:
            raise ValueError(f"{n} arrivals for {p} unknowns (receiver clock in {len(self.segment_orders)} segments, "
                             f"{len(self.names)} sites): too few to calibrate")
        weighted = self.design / np.linalg.norm(self.design, axis=0)
        _, singular, vt = np.linalg.svd(weighted, full_matrices=False)
        null = vt[singular < 1e-9 * singular[0]]
        if len(null):
            n_clock = self.clock_columns.shape[1]
            others = [n for s, n in enumerate(self.names) if s != self.reference]
            involved = np.flatnonzero(np.any(np.abs(null[:, n_clock:]) > 1e-6, axis=0)) % len(others)
            names = sorted({others[i] for i in involved}) or ["the receiver clock"]
            raise ValueError(f"the arrivals do not determine the clock of {', '.join(names)}: each site must be "
                             f"heard at two or more instants within {config.clock_segment_s:g} s receiver-clock "
                             "segments that hear another site too")

    def initial_unwrap(self) -> np.ndarray:
        """Each site's ``y`` unwrapped along its own arrivals, predicted with the receiver clock
        rate (m/s) that arrivals of one site close in time agree on."""
        rates = []
        tracks = []
        for s in range(len(self.names)):
            index = np.flatnonzero(self.site == s)
            dt, dy = np.diff(self.time[index]), np.diff(self.y_mod[index])
            short = (dt > 0) & (dt <= SHORT_GAP_S)
            rates.extend(unwrap_range(dy[short], 0.0) / dt[short])
            tracks.append((index, dt, dy))
        rate = float(np.median(rates)) if rates else 0.0
        y = self.y_mod.copy()
        for index, dt, dy in tracks:
            steps = rate * dt + unwrap_range(dy - rate * dt, 0.0)
            y[index] = self.y_mod[index[0]] + np.concatenate([[0.0], np.cumsum(steps)])
        return y

    def fit(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Parameters (m, m/s), their covariance and the sigma scale, for unwrapped ``y``."""
        a, b = self.design / self.sigma[:, None], y / self.sigma
        n, p = a.shape

        def residuals(x: np.ndarray) -> np.ndarray:
            return a @ x - b

        def jacobian(x: np.ndarray) -> np.ndarray:
            return a

        x = least_squares(residuals, np.zeros(p), jac=jacobian, method="lm", x_scale="jac").x
        # two rounds: the MAD of plain least squares' residuals sets the knee, the robust fit's refines it
        for _ in range(2):
            scale = max(float(mad_spread(residuals(x))), 1e-9)
            x = least_squares(residuals, x, jac=jacobian, loss="huber", f_scale=HUBER_KNEE * scale,
                              x_scale="jac", ftol=1e-12, xtol=1e-12, gtol=1e-12).x
        u = residuals(x) / scale
        psi = np.clip(u, -HUBER_KNEE, HUBER_KNEE)
        inside = np.mean(np.abs(u) < HUBER_KNEE)
        variance = scale**2 * float(np.sum(psi**2)) / (n - p) / inside**2
        return x, variance * np.linalg.inv(a.T @ a), math.sqrt(variance)

    def clock(self, x: np.ndarray) -> ReceiverClock:
        coefficients = []
        start = 0
        for order in self.segment_orders:
            coefficients.append(x[start:start + order + 1].copy())
            start += order + 1
        return ReceiverClock(self.edges, tuple(coefficients))


def calibrate_sites(observations: Sequence[CalibrationObservation],
                    config: CalibrationConfig | None = None) -> CalibrationResult:
    """Every heard site's timing correction relative to the most heard site, with honest sigmas
    (see the module docstring for the model, the gauge and the fit).

    Raises ValueError, naming the cause, for arrivals from fewer than 2 sites, a site heard at
    fewer than 2 instants, a value that is not finite, or a site the arrivals do not pin down.
    """
    config = config or CalibrationConfig()
    problem = _Problem(observations, config)
    y = problem.initial_unwrap()
    for _ in range(MAX_UNWRAP_ROUNDS):
        x, covariance, sigma_scale = problem.fit(y)
        unwrapped = unwrap_range(y, problem.design @ x)
        if not np.any(np.abs(unwrapped - y) > FRAME_RANGE_M / 2):
            break
        y = unwrapped
    else:
        raise ValueError(f"the ranges still moved by a frame after {MAX_UNWRAP_ROUNDS} fits: the receiver clock "
                         "does not follow a polynomial in its segments (shorten clock_segment_s)")
    residual = y - problem.design @ x
    n_clock = problem.clock_columns.shape[1]
    clock = problem.clock(x[:n_clock])
    bias = clock.bias_m(problem.time)
    before = unwrap_range(problem.y_mod, bias) - bias
    others = [s for s in range(len(problem.names)) if s != problem.reference]
    std = np.sqrt(np.diag(covariance))
    inflation = [_persistence(residual[problem.site == s], problem.time[problem.site == s])
                 for s in range(len(problem.names))]
    sites = []
    for s, name in enumerate(problem.names):
        rms = float(np.sqrt(np.mean(residual[problem.site == s] ** 2)))
        if s == problem.reference:
            sites.append(SiteCalibration(name, 0.0, 0.0, 0.0, 0.0, int(problem.counts[s]), rms))
            continue
        i, j = n_clock + others.index(s), n_clock + len(others) + others.index(s)
        k = math.sqrt(max(inflation[s], inflation[problem.reference]))  # a difference of the two sites
        sites.append(SiteCalibration(name, float(unwrap_range(x[i], 0.0)) / C, k * float(std[i]) / C,
                                     float(x[j]) / C, k * float(std[j]) / C, int(problem.counts[s]), rms))
    return CalibrationResult(tuple(sites), problem.names[problem.reference], clock,
                             float(np.sqrt(np.mean(before**2))), float(np.sqrt(np.mean(residual**2))), sigma_scale)


def _persistence(residual: np.ndarray, time_s: np.ndarray) -> float:
    """How many arrivals of a site count as one independent one: ``(1 + rho) / (1 - rho)`` for
    the lag-1 correlation ``rho`` of its residuals in time order (an AR(1) process's variance
    factor), 1 when ``rho`` is not significant, at most the number of arrivals. Multipath that
    stays with a site for seconds makes its residuals persist; the white-noise sigma of an
    estimate from them would be too small by the root of this factor."""
    n = residual.size
    if n < 3:
        return 1.0
    ordered = residual[np.argsort(time_s)] - residual.mean()
    power = float(ordered @ ordered)
    rho = float(ordered[1:] @ ordered[:-1]) / power if power > 0 else 0.0
    if rho <= 2 / math.sqrt(n):  # within the noise of a white sequence's estimate
        return 1.0
    return min((1 + rho) / (1 - rho) if rho < 1 else math.inf, float(n))


def _check_finite(observations: Sequence[CalibrationObservation]) -> None:
    for i, observation in enumerate(observations):
        arrival = observation.arrival
        for name in ("time_s", "range_mod_m", "timing_std_m"):
            value = getattr(arrival, name)
            if not math.isfinite(value):
                raise ValueError(f"observations[{i}].arrival.{name} is {value!r}: it must be finite")
        if arrival.timing_std_m < 0:
            raise ValueError(f"observations[{i}].arrival.timing_std_m is {arrival.timing_std_m!r}: it must be >= 0")
        for name, value in (("truth_enu", observation.truth_enu), ("arrival.position_enu", arrival.position_enu)):
            value = np.asarray(value, dtype=np.float64)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise ValueError(f"observations[{i}].{name} is {value!r}: it must be 3 finite coordinates (m)")


def _check_coverage(names: list[str], site: np.ndarray, time: np.ndarray) -> None:
    if len(names) < 2:
        raise ValueError(f"arrivals from {len(names)} site(s) ({', '.join(names) or 'none'}): calibration needs at "
                         "least 2, as site clocks are known only relative to each other")
    for s, name in enumerate(names):
        instants = len(np.unique(time[site == s]))
        if instants < 2:
            raise ValueError(f"site {name!r} is heard at only {instants} instant: its offset and drift need at least 2")


def calibrated_database(towers: TowerDatabase, corrections: Sequence[SiteCalibration], reference_ns: int) -> TowerDatabase:
    """``towers`` with the corrected sites' timing corrected and their sigmas replaced, all
    timing moved to the new epoch ``reference_ns`` (the arrivals' time origin, a whole frame).
    A correction without a drift (its ``drift_std`` NaN: a tracker without site clock states)
    keeps the site's drift and its sigma, and so does one whose drift or drift sigma lies beyond
    any oscillator's (``towers.MAX_DRIFT_NS_PER_S``): a site heard for a moment, whose drift the
    fit could not tell.

    A site not calibrated keeps its timing, moved to the new epoch by its drift (its offset sigma
    grows by its drift sigma times the time moved); note that the calibrated sites now follow
    the reference site's clock, which the others were never compared with. Offsets are written
    modulo a frame into [0, 10000) us; the result is checked to load as a database would.
    """
    if reference_ns % FRAME_NS:
        raise ValueError(f"reference_ns {reference_ns} is not a whole number of 10 ms frames")
    calibrated = {site.site: site for site in corrections}
    unknown = sorted(set(calibrated) - {site.name for site in towers.sites})
    if unknown:
        raise ValueError(f"calibrated site(s) {', '.join(unknown)} are not in tower database {towers.name!r}")
    moved_s = 0.0 if towers.timing_epoch_ns is None else (reference_ns - towers.timing_epoch_ns) * 1e-9
    sites = []
    for site in towers.sites:
        if site.timing_offset_us is None:
            if site.name in calibrated:
                raise ValueError(f"site {site.name!r} has no timing offset in {towers.name!r} to correct")
            sites.append(site)
            continue
        drift_ns_per_s = site.timing_drift_ns_per_s or 0.0
        offset_us = site.timing_offset_us + drift_ns_per_s * moved_s * 1e-3
        if site.name in calibrated:
            fitted = calibrated[site.name]
            site = replace(site, timing_offset_std_us=fitted.offset_std_s * 1e6)
            drift, drift_std = drift_ns_per_s + fitted.drift_correction * 1e9, fitted.drift_std * 1e9
            if abs(drift) <= MAX_DRIFT_NS_PER_S and drift_std <= MAX_DRIFT_NS_PER_S:  # NaN: no drift fitted
                site = replace(site, timing_drift_ns_per_s=drift, timing_drift_std_ns_per_s=drift_std)
            offset_us += fitted.offset_correction_s * 1e6
        elif site.timing_drift_std_ns_per_s is not None:
            grown = site.timing_drift_std_ns_per_s * abs(moved_s) * 1e-3
            site = replace(site, timing_offset_std_us=math.hypot(site.timing_offset_std_us or 0.0, grown))
        sites.append(replace(site, timing_offset_us=_within_frame_us(offset_us)))
    database = replace(towers, sites=tuple(sites), timing_epoch_ns=reference_ns)
    return parse_tower_database(tower_database_to_dict(database), f"calibrated {towers.name!r}")


def _within_frame_us(offset_us: float) -> float:
    frame_us = FRAME_SECONDS * 1e6
    wrapped = offset_us % frame_us
    return 0.0 if wrapped == frame_us else wrapped  # a tiny negative offset rounds up to the frame


def calibration_lifetime_s(tolerance_m: float, offset_std_s: float, drift_std: float,
                           drift_error: float = 0.0) -> float:
    """How long after the calibration epoch a site's predicted timing stays within
    ``tolerance_m`` of range error, in the RMS sense::

        c * sqrt(offset_std_s^2 + (drift_std^2 + drift_error^2) * T^2)  =  tolerance_m

    ``drift_error`` is a drift the calibration left uncorrected (s/s): the site's whole drift
    when only its offset was calibrated, 0 when its drift was too (then ``drift_std`` limits).
    0 if the offset alone is beyond the tolerance, infinite if nothing drifts.
    """
    for name, value in (("tolerance_m", tolerance_m), ("offset_std_s", offset_std_s), ("drift_std", drift_std),
                        ("drift_error", drift_error)):
        if not math.isfinite(value):
            raise ValueError(f"{name}: {value!r} must be finite")
    budget_s2 = (tolerance_m / C) ** 2 - offset_std_s**2
    if budget_s2 <= 0:
        return 0.0
    drift = math.hypot(drift_std, drift_error)
    return math.inf if drift == 0 else math.sqrt(budget_s2) / drift
