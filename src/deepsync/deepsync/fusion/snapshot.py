"""The snapshot solver: one stack's site ranges to a position, or a reason why not.

Unknowns: the receiver's position (east, north; up too in 3-D, held by a height prior) and its
clock bias ``b`` (m). Each site gives ``rho_i = |x - p_i| + b`` (ranges unwrapped next to the
best-measured site's, the clock's drift over the stack removed with the rate the sync stage
measured). With ``N`` sites and ``n`` unknowns:

* **Start, closed form** (spherical intersection, as Smith & Abel / Chan): squaring
  ``|x - p_i| = rho_i - b`` makes every equation linear in ``x``, ``b`` and ``R = |x|^2 - b^2``;
  ``x`` and ``b`` follow from the ``N`` equations as a line in ``R``, and ``R``'s own definition
  is a quadratic on that line: up to two candidates, both refined. ``N >= n`` suffices.
* **Refinement**: weighted nonlinear least squares (``scipy.optimize.least_squares``) with a
  Huber loss at 3 sigma: plain least squares for Gaussian errors, a bounded pull for an outlier.
* **Outliers**: the weighted residuals' sum of squares against chi-square(N - n). If it fails
  and a site can be left out with a degree of freedom to spare, the site with the largest
  studentised residual at the robust solution is rejected and named if the rest then pass
  (else the removal that passes best), and the test repeats; if no removal passes, no fix
  (``INCONSISTENT``).
* **Covariance**: ``(H^T W H)^-1`` from the analytic Jacobian at the solution. It is *not*
  rescaled by the residuals: with 1-3 degrees of freedom their variance estimate swings by
  10x between stacks. The stated sigmas carry the honesty (the timing stage's 1-sigma, the
  site clock's uncertainty, a floor for what neither knows), and the residual test refuses what
  contradicts them.
* **No fix** with its reason: fewer sites than unknowns, sites on one line (2-D: a mirror
  image fits as well) or a GDOP beyond bounds, a solver that does not converge or lands
  beyond any LTE cell, a residual test that fails, two different positions that fit equally.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.stats import chi2

from deepsync.fusion.anchors import SiteArrival, site_names, unwrap_range
from deepsync.numeric import covariance_from_information
from deepsync.schema import check_settings, setting
from deepsync.types import MAX_CELL_RANGE_M, SPEED_OF_LIGHT_M_S, UNMEASURED_VARIANCE, Fix, FixKind, NoFix, NoFixReason

HUBER_KNEE = 3.0  # sigmas: residuals beyond pull linearly, not quadratically


@dataclass(frozen=True)
class SnapshotConfig:
    """``dims``: 2 (east, north; the receiver at ``receiver_height_m`` above the ground) or 3
    (up solved too, with a prior of ``height_prior_std_m`` around ``receiver_height_m``)."""

    dims: int = 2
    receiver_height_m: float = setting(1.5, help="Antenna height above the map origin's ground in a 2-D fix.",
                                       unit="m", bounds=(-500.0, 1e4))
    height_prior_std_m: float = 10.0
    outlier_probability: float = 0.01  # residual test: chance of calling Gaussian errors inconsistent
    max_gdop: float = 30.0

    def __post_init__(self) -> None:
        if self.dims not in (2, 3):
            raise ValueError(f"dims must be 2 or 3, got {self.dims!r}")
        check_settings(self)
        checks = {
            "height_prior_std_m": 0 < self.height_prior_std_m <= 1e4,
            "outlier_probability": 0 < self.outlier_probability < 0.5,
            "max_gdop": 1 <= self.max_gdop <= 1e4,
        }
        for name, ok in checks.items():
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and ok):
                raise ValueError(f"{name}: {value!r} is out of range")

    @property
    def n_unknowns(self) -> int:
        return self.dims + 1  # position and clock bias (3-D: the height prior adds a measurement)


@dataclass(frozen=True)
class _Solution:
    state: np.ndarray  # (dims + 1,) position (relative to the centre) and clock bias
    chi_square: float
    converged: bool


class SnapshotProblem:
    """The ranges of one stack, unwrapped and centred for a well-conditioned solve."""

    def __init__(self, arrivals: Sequence[SiteArrival], config: SnapshotConfig, clock_rate: float = 0.0) -> None:
        self.config = config
        self.arrivals = list(arrivals)
        best = min(range(len(self.arrivals)), key=lambda i: self.arrivals[i].std_m)
        t0 = self.arrivals[best].time_s
        # the receiver clock runs on while the codes of one stack arrive (20 ppm: 60 m in 10 ms)
        ranges = [a.range_mod_m - clock_rate * SPEED_OF_LIGHT_M_S * (a.time_s - t0) for a in self.arrivals]
        reference = ranges[best]
        self.rho = np.array([unwrap_range(r, reference) - reference for r in ranges])
        self.reference_m = reference
        self.sigma = np.array([a.std_m for a in self.arrivals])
        positions = np.array([a.position_enu for a in self.arrivals], dtype=np.float64)
        self.centre = positions.mean(axis=0)
        self.centre[2] = 0.0
        self.sites = positions - self.centre  # (N, 3)
        self.time_s = t0

    @property
    def height(self) -> float:
        return self.config.receiver_height_m

    def position(self, state: np.ndarray) -> np.ndarray:
        """(3,) position relative to the centre for a state vector."""
        if self.config.dims == 2:
            return np.array([state[0], state[1], self.height])
        return state[:3]

    def residuals(self, state: np.ndarray, keep: np.ndarray) -> np.ndarray:
        x, b = self.position(state), state[-1]
        distance = np.linalg.norm(self.sites[keep] - x, axis=1)
        r = (self.rho[keep] - distance - b) / self.sigma[keep]
        if self.config.dims == 3:
            r = np.append(r, (state[2] - self.height) / self.config.height_prior_std_m)
        return r

    def jacobian(self, state: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """d residuals / d state (the residuals' sign: measured minus modelled, over sigma)."""
        x = self.position(state)
        diff = x - self.sites[keep]
        unit = diff / np.maximum(np.linalg.norm(diff, axis=1, keepdims=True), 1e-9)
        dims = self.config.dims
        jac = -np.hstack([unit[:, :dims], np.ones((keep.sum(), 1))]) / self.sigma[keep, None]
        if dims == 3:
            prior = np.zeros((1, dims + 1))
            prior[0, 2] = 1 / self.config.height_prior_std_m
            jac = np.vstack([jac, prior])
        return jac

    def starts(self, keep: np.ndarray) -> list[np.ndarray]:
        """Closed-form candidates (spherical intersection); the sites' centre if none is real."""
        dims = self.config.dims
        p, rho = self.sites[keep], self.rho[keep]
        # |x - p_i|^2 = (rho_i - b)^2  ->  -2 p_i.x + 2 rho_i b + R = rho_i^2 - |p_i|^2,  R = |x|^2 - b^2
        if dims == 2:
            z = self.height
            a = np.hstack([-2 * p[:, :2], 2 * rho[:, None]])
            y = rho**2 - np.sum(p**2, axis=1) + 2 * p[:, 2] * z
        else:
            z = 0.0
            a = np.hstack([-2 * p, 2 * rho[:, None]])
            y = rho**2 - np.sum(p**2, axis=1)
        pinv = np.linalg.pinv(a)
        u, v = pinv @ y, -pinv @ np.ones(len(rho))  # [x; b] = u + R v
        # R = |x|^2 + z^2 - b^2 on that line: a quadratic in R
        sign = np.ones(dims + 1)
        sign[-1] = -1
        qa = np.sum(sign * v * v)
        qb = 2 * np.sum(sign * u * v) - 1
        qc = np.sum(sign * u * u) + z * z
        roots: list[float]
        if abs(qa) < 1e-12:
            roots = [-qc / qb] if qb else []
        else:
            disc = qb * qb - 4 * qa * qc
            roots = [(-qb + s * math.sqrt(max(disc, 0.0))) / (2 * qa) for s in (1, -1)]
        starts = [u + r * v for r in roots if math.isfinite(r)]
        fallback = np.zeros(dims + 1)
        if dims == 3:
            fallback[2] = self.height
        fallback[-1] = float(np.mean(rho - np.linalg.norm(p - self.position(fallback), axis=1)))
        return starts + [fallback]

    def solve(self, keep: np.ndarray) -> _Solution:
        """Best refined candidate for the sites in ``keep``: the closed-form start that fits best,
        refined; the others too if that one does not fit."""
        starts = sorted(self.starts(keep), key=lambda start: float(np.sum(self.residuals(start, keep) ** 2)))
        best = None
        for start in starts:
            solution = self.refine(start, keep)
            if best is None or solution.chi_square < best.chi_square:
                best = solution
            if _passes(best, int(keep.sum()) - self.config.n_unknowns, self.config):
                break
        return best

    def refine(self, start: np.ndarray, keep: np.ndarray) -> _Solution:
        """Levenberg-Marquardt from ``start``; where a residual lies beyond the Huber knee (3
        sigma), again with the Huber loss, which bounds an outlier's pull. For Gaussian errors
        both are the same weighted least squares; the first is 8x faster."""
        result = least_squares(self.residuals, start, jac=self.jacobian, args=(keep,), method="lm", max_nfev=100)
        if np.max(np.abs(result.fun)) > HUBER_KNEE:
            result = least_squares(self.residuals, result.x, jac=self.jacobian, args=(keep,), loss="huber",
                                   f_scale=HUBER_KNEE, x_scale="jac", max_nfev=100)
        chi_square = float(np.sum(self.residuals(result.x, keep) ** 2))
        return _Solution(result.x, chi_square, result.status > 0)

    def fix(self, state: np.ndarray, keep: np.ndarray, stamp_ns: int, rejected: tuple[str, ...]) -> Fix:
        jac = self.jacobian(state, keep)
        covariance_state = np.linalg.inv(jac.T @ jac)
        dims = self.config.dims
        covariance = np.zeros((3, 3))
        covariance[:dims, :dims] = covariance_state[:dims, :dims]
        if dims == 2:
            covariance[2, 2] = UNMEASURED_VARIANCE
        position = self.position(state) + self.centre
        return Fix(stamp_ns, tuple(float(v) for v in position), covariance,
                   tuple(a.site for a, k in zip(self.arrivals, keep) if k), FixKind.SNAPSHOT, rejected,
                   self.gdop(state, keep), float(state[-1] + self.reference_m))

    def gdop(self, state: np.ndarray, keep: np.ndarray) -> float:
        """Geometric dilution of precision for unit range sigmas; in 3-D the height prior counts
        in proportion to its sigma against the median range sigma (it is what holds the height)."""
        diff = self.position(state) - self.sites[keep]
        unit = diff / np.linalg.norm(diff, axis=1, keepdims=True)
        dims = self.config.dims
        h = np.hstack([unit[:, :dims], np.ones((keep.sum(), 1))])
        if dims == 3:
            prior = np.zeros((1, dims + 1))
            prior[0, 2] = float(np.median(self.sigma[keep])) / self.config.height_prior_std_m
            h = np.vstack([h, prior])
        return math.sqrt(float(np.trace(covariance_from_information(h.T @ h))))  # inf: singular, in rounding too


def solve_snapshot(arrivals: Sequence[SiteArrival], config: SnapshotConfig | None = None, *, stamp_ns: int = 0,
                   clock_rate: float = 0.0, prior_enu: np.ndarray | None = None) -> Fix | NoFix:
    """A position from one stack's site ranges, or the reason there is none.

    ``clock_rate`` is the receiver clock's fractional frequency error (ppm * 1e-6) over the
    stack; ``prior_enu`` (optional) picks between two positions that fit equally well.
    """
    config = config or SnapshotConfig()
    names = site_names(arrivals)
    if len(set(names)) != len(names):
        raise ValueError(f"sites heard twice in one snapshot: {', '.join(sorted(n for n in set(names) if names.count(n) > 1))}")
    n = config.n_unknowns
    if len(arrivals) < n:
        return NoFix(stamp_ns, NoFixReason.TOO_FEW_SITES,
                     f"{len(arrivals)} site(s) heard ({', '.join(names) or 'none'}), {n} needed in {config.dims}-D")
    problem = SnapshotProblem(arrivals, config, clock_rate)
    collinear = _collinear(problem.sites[:, :2])
    if collinear:
        return NoFix(stamp_ns, NoFixReason.DEGENERATE_GEOMETRY,
                     f"sites {', '.join(names)} lie on one line: a mirror image of the position fits as well")
    keep = np.ones(len(arrivals), dtype=bool)
    rejected: list[str] = []
    while True:
        solution = problem.solve(keep)
        dof = int(keep.sum()) - n
        if not _passes(solution, dof, config):
            candidate = _leave_one_out(problem, keep, config, solution) if dof >= 2 else None
            if candidate is None:
                worst = _worst_site(problem, solution.state, keep)
                return NoFix(stamp_ns, NoFixReason.INCONSISTENT,
                             f"the ranges of {', '.join(names)} contradict their sigmas (chi-square "
                             f"{solution.chi_square:.1f} with {dof} degrees of freedom; worst: {worst})",
                             tuple(rejected))
            keep[candidate] = False
            rejected.append(names[candidate])
            continue
        break
    return _checked_fix(problem, solution, keep, stamp_ns, tuple(rejected), prior_enu)


def _checked_fix(problem: SnapshotProblem, solution: _Solution, keep: np.ndarray, stamp_ns: int,
                 rejected: tuple[str, ...], prior_enu: np.ndarray | None) -> Fix | NoFix:
    config = problem.config
    if not solution.converged or not np.all(np.isfinite(solution.state)):
        return NoFix(stamp_ns, NoFixReason.NOT_CONVERGED, "the least-squares solver did not converge", rejected)
    position = problem.position(solution.state)
    nearest = float(np.min(np.linalg.norm(problem.sites[keep] - position, axis=1)))
    if nearest > MAX_CELL_RANGE_M:
        return NoFix(stamp_ns, NoFixReason.NOT_CONVERGED,
                     f"the solution lies {nearest / 1e3:.0f} km from the nearest site, beyond any LTE cell", rejected)
    other = _other_fit(problem, solution, keep, config)
    if other is not None:
        if prior_enu is None:
            return NoFix(stamp_ns, NoFixReason.DEGENERATE_GEOMETRY,
                         "two positions fit the ranges equally well (too few sites to tell them apart)", rejected)
        prior = np.asarray(prior_enu, dtype=np.float64)[:2] - problem.centre[:2]
        here = np.linalg.norm(position[:2] - prior)
        there = np.linalg.norm(problem.position(other)[:2] - prior)
        if there < here:
            solution = _Solution(other, solution.chi_square, True)
    gdop = problem.gdop(solution.state, keep)
    if not gdop <= config.max_gdop:
        return NoFix(stamp_ns, NoFixReason.DEGENERATE_GEOMETRY,
                     f"GDOP {gdop:.0f} beyond {config.max_gdop:g}: the geometry does not fix the position", rejected)
    return problem.fix(solution.state, keep, stamp_ns, rejected)


def _passes(solution: _Solution, dof: int, config: SnapshotConfig) -> bool:
    return dof <= 0 or solution.chi_square <= chi_square_limit(config.outlier_probability, dof)


@functools.lru_cache(maxsize=256)
def chi_square_limit(probability: float, dof: int) -> float:
    """The chi-square value Gaussian errors exceed with ``probability`` (scipy's isf: 0.1 ms)."""
    return float(chi2.isf(probability, dof))


def _leave_one_out(problem: SnapshotProblem, keep: np.ndarray, config: SnapshotConfig,
                   solution: _Solution) -> int | None:
    """The site to reject, or None: the one with the largest studentised residual at the robust
    solution (its residual over its own spread, leverage removed: a site the geometry cannot
    check has a small residual whatever it says) if the rest then pass the residual test; else
    the removal that passes with the smallest chi-square."""
    jac = problem.jacobian(solution.state, keep)
    leverage = np.einsum("ij,jk,ik->i", jac, np.linalg.pinv(jac.T @ jac), jac)[: int(keep.sum())]
    residuals = problem.residuals(solution.state, keep)[: int(keep.sum())]
    studentised = np.abs(residuals) / np.sqrt(np.maximum(1 - leverage, 1e-9))
    sites = np.flatnonzero(keep)
    first = int(sites[int(np.argmax(studentised))])
    best, best_chi = None, math.inf
    for i in [first, *(int(j) for j in sites if j != first)]:
        trial = keep.copy()
        trial[i] = False
        trial_solution = problem.solve(trial)
        if _passes(trial_solution, int(trial.sum()) - config.n_unknowns, config):
            if i == first:
                return i
            if trial_solution.chi_square < best_chi:
                best, best_chi = i, trial_solution.chi_square
    return best


def _other_fit(problem: SnapshotProblem, solution: _Solution, keep: np.ndarray,
               config: SnapshotConfig) -> np.ndarray | None:
    """Another closed-form candidate that, refined, passes the residual test as well as the
    solution (exactly determined: fits as exactly), lies elsewhere, and has every modelled
    distance positive (ranges minus the clock bias): a mirror the ranges cannot rule out.
    Checked up to one spare site (with two, a second minimum that passes too is rare and the
    search would cost a third of the solve); candidates whose start already fails the test
    badly are not refined."""
    dof = int(keep.sum()) - config.n_unknowns
    if dof > 1:
        return None
    limit = chi_square_limit(config.outlier_probability, dof) if dof > 0 else 0.0
    sigma = float(np.min(problem.sigma[keep]))
    here = problem.position(solution.state)[:2]
    for start in problem.starts(keep)[:-1]:
        if dof > 0 and float(np.sum(problem.residuals(start, keep) ** 2)) > 10 * limit:
            continue
        other = problem.refine(start, keep)
        position = problem.position(other.state)
        moved = np.linalg.norm(position[:2] - here)
        distances = np.linalg.norm(problem.sites[keep] - position, axis=1)
        plausible = np.all(problem.rho[keep] - other.state[-1] > 0) and distances.min() < MAX_CELL_RANGE_M
        fits = other.chi_square < 1e-3 + solution.chi_square if dof <= 0 else other.chi_square <= limit
        if fits and moved > 10 * sigma and plausible:
            return other.state
    return None


def _collinear(horizontal: np.ndarray) -> bool:
    """Sites within about half a degree of one line (their spread across it < 1 % along it)."""
    centred = horizontal - horizontal.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    return singular[0] == 0 or singular[-1] < 1e-2 * singular[0]


def _worst_site(problem: SnapshotProblem, state: np.ndarray, keep: np.ndarray) -> str:
    residuals = problem.residuals(state, keep)[: int(keep.sum())]
    index = int(np.flatnonzero(keep)[int(np.argmax(np.abs(residuals)))])
    return f"{problem.arrivals[index].site} at {np.abs(residuals).max():.1f} sigma"


def position_bound(site_positions: np.ndarray, range_std_m: np.ndarray, receiver_enu: np.ndarray,
                   dims: int = 2) -> np.ndarray:
    """Cramer-Rao bound of the snapshot position (``dims`` x ``dims``, m^2) at ``receiver_enu``
    for sites ranged with the given 1-sigmas (the timing bounds, in metres), clock bias unknown:
    the inverse Fisher information of the pseudorange model, position block."""
    diff = np.asarray(receiver_enu, dtype=np.float64) - np.asarray(site_positions, dtype=np.float64)
    unit = diff / np.linalg.norm(diff, axis=1, keepdims=True)
    h = np.hstack([unit[:, :dims], np.ones((len(unit), 1))]) / np.asarray(range_std_m, dtype=np.float64)[:, None]
    return np.linalg.inv(h.T @ h)[:dims, :dims]
