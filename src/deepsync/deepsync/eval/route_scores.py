"""How a route's answers are scored against the truth: horizontal error, NEES and the methods
compared (for the route evaluation and its figures)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from deepsync.fusion.snapshot import chi_square_limit
from deepsync.types import Fix, NoFix

if TYPE_CHECKING:  # the route's stacks; deepsync.eval.route imports this module
    from deepsync.eval.route import RouteEpoch

CHI2_2DOF_95 = chi_square_limit(0.05, 2)  # 95 % of a 2-D Gaussian's NEES lies below this (5.99)


def horizontal_error(fix: Fix, truth_enu: np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(fix.position_enu[:2]) - truth_enu[:2]))


def nees(fix: Fix, truth_enu: np.ndarray) -> float:
    """Normalised estimation error squared of the horizontal position (chi-square, 2 dof, if honest)."""
    error = np.asarray(fix.position_enu[:2]) - truth_enu[:2]
    return float(error @ np.linalg.solve(fix.covariance[:2, :2], error))


METHODS: dict[str, Callable[[RouteEpoch], Fix | NoFix | None]] = {
    "snapshot": lambda epoch: epoch.snapshot,
    "tracked": lambda epoch: epoch.tracked,
    "rssi": lambda epoch: epoch.rssi,
}
