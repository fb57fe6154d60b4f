"""The tracker's start: position, clock bias and drift from a few seconds of arrivals at once.

From the last ``init_window_s`` of arrivals, or the current stack alone when it holds enough
sites: ranges unwrapped against the earliest with the drift prior, a drift guessed from how each
repeated site's range moves, one range per site at the window's mid-time solved by
:func:`solve_snapshot`, then all arrivals at once (position, ``b`` and ``d``; the receiver
assumed static) with ``scipy.optimize.least_squares``: a Huber loss first, then the arrivals
beyond the gate left out (named) and the rest solved plainly. The drift's prior is the sync
stage's clock rate (sigma ``clock_rate_std_ppm``) when known, else 0 +- ``max_clock_ppm``. A
start needs ``D + 1`` distinct sites (position and bias; where two positions fit equally the
snapshot step refuses), ``D + 2`` where the tower database has them (a site more lets the
residual test check them: on a drive, a start from three sites one of which had locked 2-5
samples late began 740 m off claiming 130 m, and odometry aligned to it carried the track
700 m off), and one arrival
more when the clock rate is unknown (the drift is then solved from the data); it must pass the
same residual test as a snapshot. What stays the same over the window is one unknown per site,
not noise: a site's range bias and its clock's error (``bias_std_m``, ``clock_std_m``) are
the same in each of its arrivals, so each site has a bias in the batch with them as its prior,
and only the timing noise (``timing_std_m``) is white. Taken as white, a site heard twenty times
in the window had its bias sigma averaged down 4.5-fold, and the start claimed that: on the
ray-traced walk it began 156 m off claiming 46 m. Sites whose bias comes out beyond the gate
of its prior (false locks) are left out, named, the worst first and one at a time (the others
took up a share of its error). Its covariance comes from the Jacobian, the sites' biases with it
(the tracker's bias states start from them); the motion the static assumption ignores enters
each arrival's sigma, which grows by ``initial_speed_std_mps`` times its distance in time from
the mid-time, and so does its site clock's drift (``clock_drift_std_mps``). With a
:class:`PositionPrior` (an operator's pose, a GNSS fix) the batch gets ``D`` whitened rows more and needs one site: it measures the clock,
and along its range the position, by as much as the prior leaves open.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares

from deepsync.fusion.anchors import FRAME_RANGE_M, SiteArrival, unwrap_range
from deepsync.fusion.snapshot import chi_square_limit, solve_snapshot
from deepsync.numeric import covariance_from_information
from deepsync.types import SPEED_OF_LIGHT_M_S, NoFix, PositionPrior

if TYPE_CHECKING:  # the tracker's config; the tracker imports this module
    from deepsync.fusion.tracker import TrackerConfig


@dataclass(frozen=True)
class Start:
    """A batch solution: ``mean`` = [position (D), b, d, the range bias of each of ``biased``]
    at ``time_s``, its covariance, the time of the latest arrival it used, and the sites it used
    (``biased``: those of them with a bias prior) and left out."""

    time_s: float
    mean: np.ndarray
    covariance: np.ndarray
    latest_s: float
    sites: tuple[str, ...]
    rejected: tuple[str, ...]
    biased: tuple[str, ...] = ()


def batch_start(arrivals: Sequence[SiteArrival], config: TrackerConfig, clock_rate: float | None,
                 prior: PositionPrior | None = None, redundant: bool = False) -> Start | str:
    """Position, clock bias and drift from arrivals spread over a few seconds (the receiver taken
    as static), or a sentence saying why not. ``arrivals`` must be in time order. With a
    ``prior`` (the position's, at the arrivals' mean time) one site is enough: it measures the
    clock, and along its range the position, by as much as the prior leaves open. ``redundant``:
    without a prior, one site more than the unknowns, so that the residual test can catch a
    false lock among them (with ``D + 1`` sites any one of them fits exactly)."""
    dims = config.dims
    names = sorted({a.site for a in arrivals})
    rate_known = clock_rate is not None
    needed = 1 if prior is not None else dims + 1 + redundant
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
    gate = chi_square_limit(config.gate_probability, 1)
    keep = np.abs(problem.residuals(theta, keep)[: keep.sum()]) ** 2 <= gate
    least = needed - (redundant and prior is None)  # fewer would leave the solve underdetermined
    refit = not keep.all()
    while True:
        kept = sorted({a.site for a, k in zip(arrivals, keep) if k})
        if len(kept) < least:
            return f"after leaving out arrivals beyond the gate, {len(kept)} site(s) remain; {needed} needed"
        if refit:
            theta = problem.fit(theta, keep, robust=False)
        # a site's false lock shows as its bias beyond its prior's gate (its own arrivals agree
        # with each other): the worst out, one at a time, as the others' biases took up a share
        worst = problem.locked_off(theta, gate, kept)
        if worst is None:
            break
        keep &= problem.names != worst
        refit = True
    residuals = problem.residuals(theta, keep)
    chi_square = float(residuals @ residuals)
    dof = len(residuals) - len(theta)
    if dof > 0 and chi_square > chi_square_limit(config.snapshot.outlier_probability, dof):
        return (f"the {int(keep.sum())} arrivals of {', '.join(kept)} contradict their sigmas taken as static "
                f"(chi-square {chi_square:.1f} with {dof} degrees of freedom)")
    jacobian = problem.jacobian(theta, keep)
    covariance = covariance_from_information(jacobian.T @ jacobian)
    horizontal = math.sqrt(max(covariance[0, 0] + covariance[1, 1], 0.0))
    typical = float(np.median(np.hypot(problem.sigma, problem.site_sigma[problem.site_of])[keep]))
    if prior is None and not horizontal <= config.snapshot.max_gdop * typical:  # a prior bounds it
        return (f"the geometry of {', '.join(kept)} does not fix the position ({horizontal:.0f} m 1-sigma from "
                f"{typical:.0f} m ranges)")
    solved = [*range(dims + 2), *(dims + 2 + j for j, name in enumerate(problem.biased) if name in kept)]
    mean = theta[solved]
    mean[dims] = (mean[dims] + problem.reference_m) % FRAME_RANGE_M
    rejected = tuple(sorted({a.site for a, k in zip(arrivals, keep) if not k} - set(kept)))
    return Start(problem.t_ref, mean, covariance[np.ix_(solved, solved)], float(problem.t[keep].max()), tuple(kept),
                 rejected, tuple(name for name in problem.biased if name in kept))


class _BatchProblem:
    """Arrivals over a window as one least-squares problem in [position (D), b, d, m_s] at the
    mean arrival time, ``b`` counted from the earliest arrival's range (``reference_m``), ``m_s``
    the range bias (and clock error) of each site that has a prior for it (``biased``), which
    adds a row each; a position prior, whitened by its covariance's Cholesky factor, adds ``D``."""

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
        # white from arrival to arrival: the timing noise, and what the window's seconds away from
        # its middle add: the motion the static assumption ignores, and the site clock's drift
        # (a database without drifts: 6 m/s a site)
        away = np.abs(self.t - self.t_ref)
        drift = np.array([a.clock_drift_std_mps for a in arrivals]) * away
        self.sigma = np.sqrt(np.array([a.timing_std_m for a in arrivals]) ** 2
                             + (config.initial_speed_std_mps * away) ** 2 + drift**2)
        self.sites = np.array([a.position_enu for a in arrivals], dtype=np.float64)
        self.names = np.array([a.site for a in arrivals])
        latest = {a.site: math.hypot(a.bias_std_m, a.clock_std_m) for a in arrivals}  # in time order
        self.biased = tuple(name for name in sorted(latest) if latest[name] > 0)
        self.bias_prior = np.array([latest[name] for name in self.biased])
        # each arrival's site's bias: its index in theta's biases (-1: none), and its prior sigma
        index = {name: j for j, name in enumerate(self.biased)}
        self.site_of = np.array([index.get(a.site, -1) for a in arrivals], dtype=np.intp)
        self.site_sigma = np.append(self.bias_prior, 0.0)  # [-1]: no bias

    def position(self, theta: np.ndarray) -> np.ndarray:
        if self.config.dims == 2:
            return np.array([theta[0], theta[1], self.config.snapshot.receiver_height_m])
        return theta[:3]

    def locked_off(self, theta: np.ndarray, gate: float, among: Sequence[str]) -> str | None:
        """The site of ``among`` whose bias lies furthest beyond ``gate`` (chi-square, 1 dof) of
        its prior, None where none does."""
        scores = {name: (m / s) ** 2 for name, m, s in zip(self.biased, theta[self.config.dims + 2:], self.bias_prior)
                  if name in among}
        worst = max(scores, key=scores.get, default=None)
        return worst if worst is not None and scores[worst] > gate else None

    def start(self) -> np.ndarray | str:
        """A first guess (the sites' biases 0): the drift from how repeated sites' ranges move,
        then one range per site at ``t_ref`` (the median: a single false lock does not move it)
        solved as a snapshot, or with a prior, its position (the sites may be too few for a
        snapshot)."""
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
        biases = np.zeros(len(self.biased))
        if self.prior_mean is not None:
            bias = float(np.median(collapsed - np.linalg.norm(self.sites - self.position(self.prior_mean), axis=1)))
            return np.array([*self.prior_mean, bias, drift, *biases])
        stack = []
        for name in sorted(set(self.names)):
            mine = np.flatnonzero(self.names == name)
            std = math.hypot(float(np.median(self.sigma[mine])), float(self.site_sigma[self.site_of[mine[0]]]))
            stack.append(SiteArrival(str(name), self.sites[mine[0]], self.t_ref,
                                     float(np.median(collapsed[mine])) % FRAME_RANGE_M, std, ()))
        snapshot = solve_snapshot(stack, self.config.snapshot)
        if isinstance(snapshot, NoFix):
            return f"the sites' ranges do not solve ({snapshot.reason.value}): {snapshot.message}"
        position = np.asarray(snapshot.position_enu)
        distances = np.linalg.norm(self.sites - position, axis=1)
        bias = float(np.median(collapsed - distances))
        return np.array([*position[:dims], bias, drift, *biases])

    def _site_biases(self, theta: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """Each kept arrival's site bias (0 for a site without a prior)."""
        return np.append(theta[self.config.dims + 2:], 0.0)[self.site_of[keep]]

    def residuals(self, theta: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """Arrivals (measured minus modelled, over sigma), then the drift prior (and height
        prior, the position prior), then the sites' bias priors."""
        dims = self.config.dims
        distance = np.linalg.norm(self.sites[keep] - self.position(theta), axis=1)
        model = distance + theta[dims] + theta[dims + 1] * (self.t[keep] - self.t_ref) + self._site_biases(theta, keep)
        priors = [(theta[dims + 1] - self.drift_prior) / self.drift_std]
        if dims == 3:
            priors.append((theta[2] - self.config.snapshot.receiver_height_m) / self.config.snapshot.height_prior_std_m)
        if self.prior_root is not None:
            priors.extend(self.prior_root @ (theta[:dims] - self.prior_mean))
        priors.extend(theta[dims + 2:] / self.bias_prior)
        return np.concatenate([(self.rho[keep] - model) / self.sigma[keep], priors])

    def jacobian(self, theta: np.ndarray, keep: np.ndarray) -> np.ndarray:
        dims, biases = self.config.dims, len(self.biased)
        diff = self.position(theta) - self.sites[keep]
        unit = diff / np.maximum(np.linalg.norm(diff, axis=1, keepdims=True), 1e-9)
        by_site = np.zeros((len(unit), biases + 1))
        by_site[np.arange(len(unit)), self.site_of[keep]] = 1.0  # column -1: no bias, dropped
        rows = np.hstack([unit[:, :dims], np.ones((len(unit), 1)), (self.t[keep] - self.t_ref)[:, None],
                          by_site[:, :biases]])
        n = dims + 2 + biases
        priors = np.zeros((1 + (dims == 3), n))
        priors[0, dims + 1] = -1 / self.drift_std
        if dims == 3:
            priors[1, 2] = -1 / self.config.snapshot.height_prior_std_m
        if self.prior_root is not None:
            position = np.zeros((dims, n))
            position[:, :dims] = -self.prior_root
            priors = np.vstack([priors, position])
        bias_rows = np.zeros((biases, n))
        bias_rows[:, dims + 2:] = -np.diag(1 / self.bias_prior)
        return -np.vstack([rows / self.sigma[keep, None], priors, bias_rows])

    def fit(self, theta: np.ndarray, keep: np.ndarray, robust: bool) -> np.ndarray:
        """Levenberg-Marquardt; ``robust``: then again with a Huber loss (3 sigma) where a
        residual lies beyond it, which bounds what a wild arrival can pull."""
        result = least_squares(self.residuals, theta, jac=self.jacobian, args=(keep,), method="lm", max_nfev=100)
        if robust and np.max(np.abs(result.fun)) > 3.0:
            result = least_squares(self.residuals, result.x, jac=self.jacobian, args=(keep,), loss="huber",
                                   f_scale=3.0, x_scale="jac", max_nfev=100)
        return result.x
