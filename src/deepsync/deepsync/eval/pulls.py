"""How each site's pull behaves along a route: the numbers behind the tracker's bias model.

A site's pull is what its arrival reads beyond the truth (the envelope's peak lagging the
straight line: NLOS, multipath), in metres. The tracker models it per site as a level that
stays plus a first-order Gauss-Markov process over the distance travelled, stationary sigma
``multipath_std_m`` and decorrelation ``bias_decorrelation_m`` (``deepsync.fusion.tracker``).
Whether a route's pulls look like that shows in their semivariogram along the path,

    gamma(d) = 1/2 E[(pull(s + d) - pull(s))^2]   (s: path distance, one site),

which such a process makes ``sigma^2 (1 - exp(-d / L))``, rising over ``L`` to the process's
variance (the timing noise, metres, is left out: the pulls change by 15 m over the first 2 m
walked). Fitted per route (:func:`fit_pull_model`), it says what sigma and decorrelation the
route's own pulls have, to set against the ones the tracker assumes; the spread of the sites'
mean pulls about the mean every site shares (the receiver clock takes that) is the level's part.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares

from deepsync.types import SPEED_OF_LIGHT_M_S

if TYPE_CHECKING:  # a route's stacks; deepsync.eval.route imports this module
    from deepsync.eval.route import RouteRun

MAX_PULL_M = 1000.0  # beyond any NLOS pull: a false lock, not a pull
# path lags (m) the semivariogram is read in, doubling; from 1.5 m, where a walker's 1 s stacks
# no longer share frames (closer ones share their noise)
LAG_EDGES_M = (1.5, 3.0, 6.0, 12.0, 24.0, 48.0, 96.0, 192.0)
# the decorrelations a fit may find (m): a route a few hundred metres long cannot tell a longer
# one from a pull that grows steadily
FIT_DECORRELATION_M = (1.0, 500.0)


@dataclass(frozen=True)
class SitePulls:
    """One site's pulls along a route: where the receiver had walked (m of its path) at each of
    its arrivals, and what the arrival read beyond the truth (m)."""

    site: str
    path_m: np.ndarray
    pull_m: np.ndarray


@dataclass(frozen=True)
class PullModel:
    """A route's pulls as the tracker models them (see the module docstring)."""

    sigma_m: float  # stationary 1-sigma of the changing part
    decorrelation_m: float  # path over which it keeps 1/e of itself
    level_std_m: float | None  # spread of the sites' mean pulls about their common mean (None: one site)
    sites: int
    arrivals: int


def site_pulls(run: RouteRun, sample_rate: float) -> list[SitePulls]:
    """Every site's pulls along ``run`` (arrivals without a true arrival, or a kilometre off, left
    out), sites by name."""
    metres = SPEED_OF_LIGHT_M_S / sample_rate
    positions = np.array([epoch.truth_enu[:2] for epoch in run.epochs]).reshape(-1, 2)
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(positions, axis=0).T))])
    rows: dict[str, list[tuple[float, float]]] = {}
    for walked, epoch in zip(path, run.epochs):
        for site, (error, _) in epoch.timing_errors.items():
            if math.isfinite(error) and abs(error * metres) <= MAX_PULL_M:
                rows.setdefault(site, []).append((walked, error * metres))
    return [SitePulls(site, np.array([r[0] for r in rows[site]]), np.array([r[1] for r in rows[site]]))
            for site in sorted(rows)]


def describe_pulls(pulls: Sequence[SitePulls]) -> dict:
    """What a report says of the pulls: the semivariogram per lag bin (``lag_m``, ``root_m``:
    its root, ``pairs``) and the fitted model (``fit``: :class:`PullModel`'s fields), or
    ``fit`` None and ``why_no_fit``."""
    lag, gamma, count = semivariogram(pulls)
    rows = [{"lag_m": float(a) if n else None, "root_m": math.sqrt(g) if n else None, "pairs": int(n)}
            for a, g, n in zip(lag, gamma, count)]
    try:
        return {"semivariogram": rows, "fit": dataclasses.asdict(fit_pull_model(pulls))}
    except ValueError as error:
        return {"semivariogram": rows, "fit": None, "why_no_fit": str(error)}


def semivariogram(pulls: Sequence[SitePulls], edges_m: Sequence[float] = LAG_EDGES_M
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pulls' semivariance (m^2) between arrivals of one site whose path distances differ by
    a lag within each pair of ``edges_m``: (the pairs' mean lag, semivariance, pair count) per
    bin; NaN where no pair falls."""
    edges = np.asarray(edges_m, dtype=float)
    bins = len(edges) - 1
    total, lags, count = np.zeros(bins), np.zeros(bins), np.zeros(bins)
    for site in pulls:
        order = np.argsort(site.path_m)
        path, pull = site.path_m[order], site.pull_m[order]
        for k in range(1, len(path)):  # every pair, a shift at a time: memory stays O(n)
            apart = path[k:] - path[:-k]
            if apart.size == 0 or apart.min() >= edges[-1]:
                break
            which = np.searchsorted(edges, apart, side="right") - 1
            inside = (which >= 0) & (which < bins)
            which = which[inside]
            total += np.bincount(which, weights=0.5 * (pull[k:] - pull[:-k])[inside] ** 2, minlength=bins)
            lags += np.bincount(which, weights=apart[inside], minlength=bins)
            count += np.bincount(which, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        return lags / count, total / count, count


def fit_pull_model(pulls: Sequence[SitePulls], edges_m: Sequence[float] = LAG_EDGES_M) -> PullModel:
    """The exponential semivariogram fitted to the pulls (least squares on the root of each
    bin's semivariance, bins weighted by the root of their pair count; the decorrelation within
    ``FIT_DECORRELATION_M``); ValueError with fewer than three populated bins (a receiver that
    stands: its pulls have no path to change over)."""
    lag, gamma, count = semivariogram(pulls, edges_m)
    known = np.isfinite(gamma) & (count > 0)
    if known.sum() < 3:
        raise ValueError(f"the pulls fill {int(known.sum())} lag bins of {len(gamma)}: three are needed for a fit")
    lag, root, weight = lag[known], np.sqrt(gamma[known]), np.sqrt(count[known])

    def residuals(theta: np.ndarray) -> np.ndarray:
        sigma, decorrelation = theta
        return weight * (sigma * np.sqrt(-np.expm1(-lag / decorrelation)) - root)

    start = np.array([root.max(), float(np.clip(np.median(lag), *FIT_DECORRELATION_M))])
    bounds = ([0.0, FIT_DECORRELATION_M[0]], [MAX_PULL_M, FIT_DECORRELATION_M[1]])
    sigma, decorrelation = least_squares(residuals, start, bounds=bounds).x
    means = np.array([site.pull_m.mean() for site in pulls])
    return PullModel(float(sigma), float(decorrelation), float(means.std()) if len(means) > 1 else None, len(pulls),
                     int(sum(len(site.pull_m) for site in pulls)))
