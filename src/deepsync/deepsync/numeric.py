"""Numerical helpers every stage uses: the parabolic peak and the robust noise spread, a
least-squares covariance that refuses to exist where rounding broke it, and one BLAS thread
for a process that runs the stages.

The first two are used where a correlation is examined: a peak on a grid of lags is refined by
the parabola through it and its two neighbours, and the noise of a correlation that holds a few
peaks among thousands of lags is measured by the median absolute deviation, which the peaks
do not move.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike
from threadpoolctl import threadpool_limits

MAD_TO_SIGMA = 1.4826  # the median absolute deviation of a Gaussian is 0.6745 sigma


def parabolic_offset(left: ArrayLike, centre: ArrayLike, right: ArrayLike) -> np.ndarray:
    """Vertex of the parabola through three equally spaced values, in steps from the middle
    one (elementwise); 0 where they do not curve downwards, i.e. where there is no maximum."""
    left, centre, right = np.asarray(left), np.asarray(centre), np.asarray(right)
    curvature = left - 2 * centre + right
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(curvature < 0, 0.5 * (left - right) / curvature, 0.0)


def parabolic_peak(values: np.ndarray, i: int) -> float:
    """Sub-sample position of a peak at index ``i`` of ``values``, relative to ``i``; the
    neighbours are taken circularly (correlations over a period wrap around)."""
    return float(parabolic_offset(values[i - 1], values[i], values[(i + 1) % len(values)]))


def mad_spread(values: ArrayLike, axis: int | None = None, keepdims: bool = False,
               centre: float | None = None) -> np.ndarray:
    """Robust standard deviation: 1.4826 x the median absolute deviation from the median, or
    from ``centre`` where the centre is known (a circular correlation with a zero-mean template
    sums to zero over its lags): one median instead of two, the costly part."""
    values = np.asarray(values)
    if centre is None:
        deviations = np.abs(values - np.median(values, axis=axis, keepdims=True))
    else:
        deviations = np.abs(values - centre) if centre else np.abs(values)
    # the deviations are this function's own: the median may reorder them in place (no copy)
    return MAD_TO_SIGMA * np.median(deviations, axis=axis, keepdims=keepdims, overwrite_input=True)


def covariance_from_information(information: np.ndarray) -> np.ndarray:
    """The inverse of a least-squares information matrix, or infinite variances where it has
    none: singular, or so near it that rounding left the inverse indefinite (a track start whose
    solve ran off to 1e9 m, every site seen along one line, got variances of -1e17 m^2, which
    read as a 0 m sigma and started a track there)."""
    try:
        covariance = np.linalg.inv(information)
        np.linalg.cholesky(covariance)
        return covariance
    except np.linalg.LinAlgError:
        return np.full(information.shape, math.inf)


def one_blas_thread() -> threadpool_limits:
    """BLAS on one thread while the returned context is held (``with``): for a whole process
    or a long piece of work, not per call (entering it costs about 0.7 ms). The stages' matrix
    products are small, so BLAS threads add synchronisation, not speed, and the nodes of one
    computer would each start as many threads as it has cores. The walk bag's replay took
    0.7-0.9 s with one thread against 1.0-1.8 s with BLAS's default while another job kept this
    2-core machine busy, and 0.8 s either way when it was idle."""
    return threadpool_limits(limits=1, user_api="blas")
