"""Large-scale propagation of 3GPP TR 38.901 (Release 16+): path loss, LOS probability,
shadow fading and delay spread for the urban macro (UMa) and urban micro street-canyon (UMi)
scenarios.

Distances are in metres (``d2d`` horizontal, ``d3d`` straight line), heights in metres above
ground, carrier frequencies in Hz (the tables' fc is in GHz; conversion happens here).
Approximations, all documented by the standard's own notes:

* the effective environment height is h_E = 1 m, so the breakpoint uses h' = h - 1 m (exact
  for UMi and for UMa with h_UT < 13 m; for taller UMa receivers 38.901 draws h_E at random);
* the formulas are applied outside their validity range (10 m <= d2D <= 5 km,
  1.5 m <= h_UT <= 22.5 m, h_BS = 25 m UMa / 10 m UMi) without clamping, except that a
  straight-line distance under ``MIN_DISTANCE_M`` counts as that: closer, in the antenna's
  near field, they mean nothing and at zero they diverge.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from deepsync.frontend.portable import elementwise
from deepsync.types import SPEED_OF_LIGHT_M_S

MODELS = ("UMa", "UMi")
MIN_DISTANCE_M = 1.0  # the shortest straight-line distance the path-loss formulas are evaluated at

# Shadow-fading standard deviation (dB), Table 7.4.1-1: (model, los) -> sigma_SF.
_SHADOW_STD_DB = {("UMa", True): 4.0, ("UMa", False): 6.0,
                  ("UMi", True): 4.0, ("UMi", False): 7.82}


def _log10(values: ArrayLike) -> np.ndarray:
    return elementwise(math.log10, values)


def _check_model(model: str) -> None:
    if model not in MODELS:
        raise ValueError(f"unknown propagation model {model!r} (known: {', '.join(MODELS)})")


def breakpoint_distance_m(h_bs: float, h_ut: float, carrier_hz: float) -> float:
    """d'_BP = 4 h'_BS h'_UT f_c / c with effective heights h' = h - 1 m (Table 7.4.1-1 note 1)."""
    return 4.0 * (h_bs - 1.0) * (h_ut - 1.0) * carrier_hz / SPEED_OF_LIGHT_M_S


def path_loss_los_db(model: str, d2d: ArrayLike, d3d: ArrayLike, h_bs: float, h_ut: float,
                     carrier_hz: float) -> np.ndarray:
    """LOS path loss (dB), Table 7.4.1-1: PL1 up to the breakpoint, PL2 beyond it."""
    _check_model(model)
    d2d, d3d = np.asarray(d2d, dtype=np.float64), np.asarray(d3d, dtype=np.float64)
    fc_ghz = carrier_hz / 1e9
    d_bp = breakpoint_distance_m(h_bs, h_ut, carrier_hz)
    lg_d, lg_fc = _log10(d3d), math.log10(fc_ghz)
    if model == "UMa":
        pl1 = 28.0 + 22.0 * lg_d + 20.0 * lg_fc
        pl2 = 28.0 + 40.0 * lg_d + 20.0 * lg_fc - 9.0 * math.log10(d_bp**2 + (h_bs - h_ut) ** 2)
    else:
        pl1 = 32.4 + 21.0 * lg_d + 20.0 * lg_fc
        pl2 = 32.4 + 40.0 * lg_d + 20.0 * lg_fc - 9.5 * math.log10(d_bp**2 + (h_bs - h_ut) ** 2)
    return np.where(d2d <= d_bp, pl1, pl2)


def path_loss_nlos_db(model: str, d2d: ArrayLike, d3d: ArrayLike, h_bs: float, h_ut: float,
                      carrier_hz: float) -> np.ndarray:
    """NLOS path loss (dB), Table 7.4.1-1: max(PL_LOS, PL'_NLOS)."""
    d3d = np.asarray(d3d, dtype=np.float64)
    fc_ghz = carrier_hz / 1e9
    if model == "UMa":
        nlos = 13.54 + 39.08 * _log10(d3d) + 20.0 * math.log10(fc_ghz) - 0.6 * (h_ut - 1.5)
    else:
        nlos = 22.4 + 35.3 * _log10(d3d) + 21.3 * math.log10(fc_ghz) - 0.3 * (h_ut - 1.5)
    return np.maximum(path_loss_los_db(model, d2d, d3d, h_bs, h_ut, carrier_hz), nlos)


def path_loss_db(model: str, los: bool, d2d: ArrayLike, d3d: ArrayLike, h_bs: float,
                 h_ut: float, carrier_hz: float) -> np.ndarray:
    """Path loss (dB) of a LOS or NLOS link, without shadow fading."""
    loss = path_loss_los_db if los else path_loss_nlos_db
    return loss(model, d2d, np.maximum(d3d, MIN_DISTANCE_M), h_bs, h_ut, carrier_hz)


def los_probability(model: str, d2d: ArrayLike, h_ut: float) -> np.ndarray:
    """Probability of line of sight, Table 7.4.2-1 (outdoor receiver).

    1 up to 18 m; beyond, 18/d + exp(-d/36)(1 - 18/d) for UMi and
    [18/d + exp(-d/63)(1 - 18/d)] (1 + C'(h_UT) 5/4 (d/100)^3 exp(-d/150)) for UMa, with
    C'(h_UT) = 0 for h_UT <= 13 m and ((h_UT - 13)/10)^1.5 above (valid up to 23 m).
    """
    _check_model(model)
    d = np.maximum(np.asarray(d2d, dtype=np.float64), 18.0)
    if model == "UMi":
        probability = 18.0 / d + elementwise(math.exp, -d / 36.0) * (1.0 - 18.0 / d)
    else:
        c_prime = 0.0 if h_ut <= 13.0 else ((h_ut - 13.0) / 10.0) ** 1.5
        cube = (d / 100.0) * (d / 100.0) * (d / 100.0)
        probability = ((18.0 / d + elementwise(math.exp, -d / 63.0) * (1.0 - 18.0 / d))
                       * (1.0 + c_prime * 1.25 * cube * elementwise(math.exp, -d / 150.0)))
    return np.minimum(probability, 1.0)


def shadow_fading_std_db(model: str, los: bool) -> float:
    """Log-normal shadow-fading standard deviation (dB), Table 7.4.1-1."""
    _check_model(model)
    return _SHADOW_STD_DB[(model, los)]


def delay_spread_lognormal(model: str, los: bool, carrier_hz: float) -> tuple[float, float]:
    """(mu, sigma) of lgDS = log10(DS / 1 s), Table 7.5-6 Part 1.

    Per the table's notes the frequency-dependent values use fc = 6 GHz below 6 GHz for UMa
    and fc = 2 GHz below 2 GHz for UMi.
    """
    _check_model(model)
    fc_ghz = carrier_hz / 1e9
    if model == "UMa":
        lg_fc = math.log10(max(fc_ghz, 6.0))
        if los:
            return -6.955 - 0.0963 * lg_fc, 0.66
        return -6.28 - 0.204 * lg_fc, 0.39
    lg_1fc = math.log10(1.0 + max(fc_ghz, 2.0))
    if los:
        return -0.24 * lg_1fc - 7.14, 0.38
    return -0.24 * lg_1fc - 6.83, 0.16 * lg_1fc + 0.28


# Correlation distances in the horizontal plane (m), Table 7.5-6 Part 1: (model, los) ->
# (shadow fading, delay spread). How far a receiver moves before its large-scale parameters
# towards a site are new draws (38.901 §7.6.3.1: exponential autocorrelation over distance).
_CORRELATION_DISTANCE_M = {("UMa", True): (37.0, 30.0), ("UMa", False): (50.0, 40.0),
                           ("UMi", True): (10.0, 7.0), ("UMi", False): (13.0, 10.0)}


def correlation_distances_m(model: str, los: bool) -> tuple[float, float]:
    """(shadow fading, delay spread) correlation distances (m), Table 7.5-6 Part 1."""
    _check_model(model)
    return _CORRELATION_DISTANCE_M[(model, bool(los))]
