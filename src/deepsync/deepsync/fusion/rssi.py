"""The RSSI baseline: per-site received power -> distance by a fitted path-loss model -> position.

The prior compressed-spectrum approach (LiteFoot-style, about 20 m median in its paper) locates
from power alone. Run on the same recordings as the timing fusion, it says what timing adds.

Our per-site power is the sync code's fitted envelope amplitude (volts): behind a square-law
detector the envelope is proportional to received power, so ``P = 10 log10(amplitude)`` dB is
the received power up to a constant. The log-distance model::

    P  =  A_s - 10 n log10(d / 1 m)  +  X,      X ~ N(0, sigma^2)   (shadowing)

has an intercept per site (EIRP, antenna gain and pattern differ from site to site, and the
detector's constant is folded in) and one exponent ``n`` (2 in free space, 3-4 in towns).
``sigma``, the residual spread, is the shadowing: 4-8 dB in 3GPP TR 38.901's urban scenarios.

* :func:`fit_path_loss`: linear least squares on arrivals at known positions.
* :func:`solve_rssi`: the position (2-D, the receiver at a fixed height) by weighted nonlinear
  least squares on the dB residuals, started from the sites' centroid weighted by the power
  each predicts (``10^((P - A_s) / 10)``, which falls as ``d^-n``); covariance from the Jacobian
  with the model's shadowing sigma. A range from a power is log-normal (6 dB at n = 3.2 is
  +-43 %), so this linearised covariance is somewhat optimistic: by 10-20 % in sigma at 6 dB.
* :class:`RssiAverager`: a 100 ms stack hears 1-2 sites on a hard route, too few to locate, so
  each site's power is averaged (in dB) over a sliding window of stacks (1 s) and the position
  uses every site heard within it. This assumes the receiver moves little within the window (a
  walker 1.5 m, a car 15 m: small against RSSI's errors). Averaging removes fast fading but not
  shadowing, which changes over tens of metres, so the model's sigma stays the honest one (and,
  as it includes the fading the window removes, a slightly conservative one).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from deepsync.fusion.anchors import SiteArrival, site_names
from deepsync.fusion.calibration import CalibrationObservation
from deepsync.types import MAX_CELL_RANGE_M, UNMEASURED_VARIANCE, Fix, FixKind, NoFix, NoFixReason

MIN_SITES = 3  # two unknowns (east, north), and one more to tell the fit from an interpolation
MIN_DISTANCE_M = 1.0  # the model's reference distance; nearer, its far-field law says nothing
TEN_LOG10_E = 10.0 / math.log(10.0)  # d(10 log10 d) / d(ln d): dB per neper of distance


@dataclass(frozen=True)
class RssiConfig:
    """``receiver_height_m`` above the ground (the map frame's up = 0), ``window_s`` of stacks a
    :class:`RssiAverager` averages each site's power over."""

    receiver_height_m: float = 1.5
    window_s: float = 1.0

    def __post_init__(self) -> None:
        checks = {"receiver_height_m": (-500.0, 10_000.0), "window_s": (0.0, 3600.0)}
        for name, (low, high) in checks.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not low < value <= high:
                raise ValueError(f"{name}: {value!r} must be a number in ({low:g}, {high:g}]")


@dataclass(frozen=True)
class PathLossModel:
    """``intercept_db``: each site's ``A_s`` (dB of the code amplitude in volts, at 1 m);
    ``exponent``: ``n`` (and its 1-sigma); ``shadowing_db``: the residual sigma, which weights the
    solver's residuals; ``n_observations`` it was fitted from."""

    intercept_db: Mapping[str, float]
    exponent: float
    exponent_std: float
    shadowing_db: float
    n_observations: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.exponent) and self.exponent > 0):
            raise ValueError(f"exponent: {self.exponent!r} must be a positive number")
        if not (math.isfinite(self.shadowing_db) and self.shadowing_db > 0):
            raise ValueError(f"shadowing_db: {self.shadowing_db!r} must be a positive number of dB")


def power_db(amplitude: float) -> float:
    """Received power in dB (up to the detector's constant) from a code amplitude; NaN where
    there is none (not finite or not positive: a fit that found no code)."""
    return 10.0 * math.log10(amplitude) if math.isfinite(amplitude) and amplitude > 0 else math.nan


def fit_path_loss(observations: Sequence[CalibrationObservation]) -> PathLossModel:
    """Per-site intercepts and a common exponent by least squares on the arrivals' powers;
    arrivals without a power (NaN amplitude) are skipped. ValueError if a position is not finite,
    if too few remain, or if their distances do not vary (the exponent is then not determined)."""
    rows = []
    for i, o in enumerate(observations):
        distance = float(np.linalg.norm(np.asarray(o.truth_enu, dtype=np.float64) - o.arrival.position_enu))
        if not math.isfinite(distance):
            raise ValueError(f"observations[{i}]: the truth or the site position is not finite")
        rows.append((o.arrival.site, power_db(o.arrival.amplitude), distance))
    rows = [row for row in rows if math.isfinite(row[1])]
    names = sorted({site for site, _, _ in rows})
    n_unknowns = len(names) + 1
    if len(rows) < n_unknowns + 2:
        raise ValueError(f"{len(rows)} arrivals with a power from {len(names)} site(s): the path-loss fit needs at "
                         f"least {n_unknowns + 2} (an intercept per site, the exponent, and 2 to measure the "
                         "shadowing)")
    design = np.zeros((len(rows), n_unknowns))
    for i, (site, _, distance) in enumerate(rows):
        design[i, names.index(site)] = 1.0
        design[i, -1] = -10.0 * math.log10(max(distance, MIN_DISTANCE_M))
    power = np.array([p for _, p, _ in rows])
    solution, _, rank, _ = np.linalg.lstsq(design, power, rcond=None)
    if rank < n_unknowns:
        raise ValueError("the arrivals' distances do not vary within any site: the path-loss exponent is not "
                         "determined")
    residual = power - design @ solution
    variance = float(residual @ residual) / (len(rows) - n_unknowns)
    exponent_std = math.sqrt(variance * np.linalg.inv(design.T @ design)[-1, -1])
    return PathLossModel(dict(zip(names, (float(a) for a in solution[:-1]))), float(solution[-1]), exponent_std,
                         math.sqrt(variance), len(rows))


class _RssiProblem:
    """The usable arrivals' sites (horizontal, relative to their centre) and powers."""

    def __init__(self, arrivals: Sequence[SiteArrival], model: PathLossModel, config: RssiConfig) -> None:
        self.model = model
        positions = np.array([a.position_enu for a in arrivals], dtype=np.float64)
        self.centre = positions.mean(axis=0)
        self.centre[2] = 0.0  # the map frame's up = 0 is the ground, the receiver height's origin
        self.sites = positions - self.centre
        self.height = config.receiver_height_m
        self.power = np.array([power_db(a.amplitude) for a in arrivals])
        self.intercept = np.array([model.intercept_db[a.site] for a in arrivals])

    def offsets(self, xy: np.ndarray) -> np.ndarray:
        return np.array([xy[0], xy[1], self.height]) - self.sites

    def residuals(self, xy: np.ndarray) -> np.ndarray:
        distance = np.maximum(np.linalg.norm(self.offsets(xy), axis=1), MIN_DISTANCE_M)
        return (self.power - self.intercept + 10.0 * self.model.exponent * np.log10(distance)) / self.model.shadowing_db

    def jacobian(self, xy: np.ndarray) -> np.ndarray:
        offsets = self.offsets(xy)
        squared = np.maximum(np.sum(offsets**2, axis=1, keepdims=True), MIN_DISTANCE_M**2)
        return TEN_LOG10_E * self.model.exponent * offsets[:, :2] / squared / self.model.shadowing_db

    def start(self) -> np.ndarray:
        """The sites' centroid, each weighted by the power it predicts ``d^-n``, not by the raw
        power (a site's EIRP would otherwise pull the start towards it)."""
        weights = 10.0 ** ((self.power - self.intercept) / 10.0)
        return (weights @ self.sites[:, :2]) / weights.sum()


def solve_rssi(arrivals: Sequence[SiteArrival], model: PathLossModel, config: RssiConfig | None = None,
               stamp_ns: int = 0) -> Fix | NoFix:
    """A position from the sites' powers and the path-loss model, or the reason there is none:
    ``UNKNOWN_SITES`` (no heard site is in the model), ``TOO_FEW_SITES`` (fewer than 3 with a
    model and a power), ``NOT_CONVERGED``, ``DEGENERATE_GEOMETRY`` (the sites leave a direction
    unmeasured: on one line with the solution)."""
    config = config or RssiConfig()
    names = site_names(arrivals)
    if len(set(names)) != len(names):
        raise ValueError(f"sites heard twice: {', '.join(sorted(n for n in set(names) if names.count(n) > 1))}")
    unknown = [a.site for a in arrivals if a.site not in model.intercept_db]
    silent = [a.site for a in arrivals if a.site in model.intercept_db and math.isnan(power_db(a.amplitude))]
    usable = [a for a in arrivals if a.site in model.intercept_db and not math.isnan(power_db(a.amplitude))]
    if arrivals and len(unknown) == len(arrivals):
        return NoFix(stamp_ns, NoFixReason.UNKNOWN_SITES, f"no path-loss model for {', '.join(unknown)}")
    if len(usable) < MIN_SITES:
        missing = "".join(f"; {label}: {', '.join(sites)}" for label, sites in
                          (("no path-loss model", unknown), ("no power", silent)) if sites)
        return NoFix(stamp_ns, NoFixReason.TOO_FEW_SITES,
                     f"{len(usable)} site(s) with a power and a model ({', '.join(site_names(usable)) or 'none'}), "
                     f"{MIN_SITES} needed{missing}")
    problem = _RssiProblem(usable, model, config)
    result = least_squares(problem.residuals, problem.start(), jac=problem.jacobian, method="lm", max_nfev=200)
    if result.status <= 0 or not np.all(np.isfinite(result.x)):
        return NoFix(stamp_ns, NoFixReason.NOT_CONVERGED, "the least-squares solver did not converge")
    nearest = float(np.min(np.linalg.norm(problem.offsets(result.x), axis=1)))
    if nearest > MAX_CELL_RANGE_M:
        return NoFix(stamp_ns, NoFixReason.NOT_CONVERGED,
                     f"the solution lies {nearest / 1e3:.0f} km from the nearest site, beyond any LTE cell")
    jac = problem.jacobian(result.x)
    information = jac.T @ jac
    if np.linalg.cond(information) > 1e12:
        return NoFix(stamp_ns, NoFixReason.DEGENERATE_GEOMETRY,
                     f"sites {', '.join(site_names(usable))} leave a direction unmeasured (on one line with the "
                     "position)")
    covariance = np.zeros((3, 3))
    covariance[:2, :2] = np.linalg.inv(information)
    covariance[2, 2] = UNMEASURED_VARIANCE
    position = (result.x[0] + problem.centre[0], result.x[1] + problem.centre[1], config.receiver_height_m)
    return Fix(stamp_ns, tuple(float(v) for v in position), covariance, site_names(usable), FixKind.SNAPSHOT)


class RssiAverager:
    """Each site's power averaged in dB over the last ``window_s`` of arrivals (receiver time).

    :meth:`add` takes a stack's site arrivals and returns one arrival per site heard within the
    window: the site's latest, its amplitude replaced by the window's average (the geometric
    mean, i.e. the mean in dB). Arrivals without a power are left out. Time only moves forwards:
    a stream that starts over needs a new averager.
    """

    def __init__(self, config: RssiConfig | None = None) -> None:
        self.window_s = (config or RssiConfig()).window_s
        self._powers: dict[str, deque[tuple[float, float]]] = {}  # site -> (time_s, dB), oldest first
        self._latest: dict[str, SiteArrival] = {}
        self._now = -math.inf

    def add(self, arrivals: Sequence[SiteArrival]) -> list[SiteArrival]:
        for arrival in arrivals:
            power = power_db(arrival.amplitude)
            if math.isnan(power):
                continue
            self._powers.setdefault(arrival.site, deque()).append((arrival.time_s, power))
            if arrival.site not in self._latest or arrival.time_s >= self._latest[arrival.site].time_s:
                self._latest[arrival.site] = arrival
            self._now = max(self._now, arrival.time_s)
        averaged = []
        for site in sorted(self._powers):
            powers = self._powers[site]
            while powers and powers[0][0] <= self._now - self.window_s:
                powers.popleft()
            if not powers:
                del self._powers[site], self._latest[site]
                continue
            mean_db = sum(p for _, p in powers) / len(powers)
            averaged.append(replace(self._latest[site], amplitude=10.0 ** (mean_db / 10.0)))
        return averaged
