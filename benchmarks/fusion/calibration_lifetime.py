"""Calibration lifetime: how long site clock corrections from a 60 s recording keep the range
error within a quarter sample (39 m at 1.92 MHz), for site oscillators 1, 5 and 20 ppb off.

Synthetic recordings: six sites 1.4-2.5 km around a 300 m circular route, one 100 ms stack
every 100 ms hearing 1 or 2 of them, Gaussian timing noise of 0.1 sample (15.6 m), a receiver
clock 15 ppm fast and drifting 0.05 ppm/s. Each site's true frame timing is off the database's
by up to +-5 us and drifts by +-p ns/s (a p ppb oscillator, random sign). The calibration epoch
(the arrivals' time origin) is the recording's middle; times below count from it. Errors are of
each site's timing relative to the reference site's (what TDOA sees), as range (m).

* Analysis (``calibration_lifetime_s`` with the median sigmas of the runs): *offset only*, the
  pair's drift left uncorrected (two independent +-p ppb sites differ by p * sqrt(2) RMS), and
  *offset + drift*, limited by the drift's sigma alone.
* Monte Carlo: the RMS error of the predicted timing at +1, +5, +20 and +60 min beside the RMS
  the reported sigmas predict, and the time the measured RMS error reaches the tolerance.

The model is a constant drift: a real oscillator's frequency also wanders (temperature,
ageing), which bounds the offset + drift lifetime further and is not simulated here.

Run:  .venv/bin/python benchmarks/fusion/calibration_lifetime.py [--runs 40]
Writes docs/results/calibration_lifetime.json.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from deepsync.fusion.anchors import FRAME_RANGE_M, SiteArrival
from deepsync.fusion.calibration import CalibrationObservation, calibrate_sites, calibration_lifetime_s
from deepsync.types import SPEED_OF_LIGHT_M_S

C = SPEED_OF_LIGHT_M_S
OUT = Path(__file__).resolve().parents[2] / "docs" / "results" / "calibration_lifetime.json"
SAMPLE_M = C / 1.92e6
TOLERANCE_M = SAMPLE_M / 4
NOISE_M = 0.1 * SAMPLE_M
PPB = (1.0, 5.0, 20.0)
HORIZONS_MIN = (1, 5, 20, 60)
SITES = np.array([(-900, 1200, 30), (1500, 300, 25), (400, -1300, 28), (-1600, -500, 35), (800, 1700, 22),
                  (2100, -1400, 40)], dtype=np.float64)


def route(t: np.ndarray) -> np.ndarray:
    """The receiver: a 300 m circle at 8 m/s, antenna 1.5 m up."""
    angle = 8.0 * t / 300.0
    return np.stack([300.0 * np.cos(angle), 300.0 * np.sin(angle), np.full_like(angle, 1.5)], axis=-1)


def recording(rng: np.random.Generator, seconds: float, ppb: float):
    """Observations, and each site's true offset (s) and drift (s/s) against the database."""
    offsets = rng.uniform(-5e-6, 5e-6, len(SITES))
    drifts = ppb * 1e-9 * rng.choice([-1.0, 1.0], len(SITES))
    bias0 = rng.uniform(0, FRAME_RANGE_M)
    observations = []
    for t_stack in np.arange(-seconds / 2, seconds / 2, 0.1):
        for s in rng.choice(len(SITES), rng.choice([1, 2]), replace=False):
            t = t_stack + rng.uniform(0, 0.01)
            truth = route(np.array(t))
            clock_m = bias0 + C * 1e-6 * (15.0 * t + 0.5 * 0.05 * t * t)
            site_m = C * (offsets[s] + drifts[s] * t)
            measured = np.linalg.norm(truth - SITES[s]) + clock_m + site_m + rng.normal(0, NOISE_M)
            arrival = SiteArrival(f"S{s}", SITES[s], float(t), float(measured % FRAME_RANGE_M), NOISE_M, (s,))
            observations.append(CalibrationObservation(arrival, truth))
    return observations, offsets, drifts


def run(ppb: float, runs: int, seconds: float, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    horizons_s = 60.0 * np.array(HORIZONS_MIN)
    offset_errors, drift_errors, offset_stds, drift_stds, true_drifts, normalised = [], [], [], [], [], []
    residuals = []
    for _ in range(runs):
        observations, offsets, drifts = recording(rng, seconds, ppb)
        result = calibrate_sites(observations)
        residuals.append((result.residual_rms_before_m, result.residual_rms_after_m))
        r = int(result.reference_site[1:])
        for site in result.sites:
            s = int(site.site[1:])
            if s == r:
                continue
            offset_error = site.offset_correction_s - (offsets[s] - offsets[r])
            offset_errors.append((offset_error + 5e-3) % 10e-3 - 5e-3)
            drift_errors.append(site.drift_correction - (drifts[s] - drifts[r]))
            offset_stds.append(site.offset_std_s)
            drift_stds.append(site.drift_std)
            true_drifts.append(drifts[s] - drifts[r])
            normalised.append((offset_errors[-1] / site.offset_std_s, drift_errors[-1] / site.drift_std))
    e_o, e_d, s_o, s_d, d_true = map(np.array, (offset_errors, drift_errors, offset_stds, drift_stds, true_drifts))

    def rms_m(errors: np.ndarray) -> list[float]:  # per horizon (row), over sites and runs
        return [round(float(C * np.sqrt(np.mean(row**2))), 1) for row in errors]

    with_drift = e_o[None, :] + e_d[None, :] * horizons_s[:, None]
    offset_only = e_o[None, :] - d_true[None, :] * horizons_s[:, None]
    predicted = np.sqrt(s_o[None, :] ** 2 + (s_d[None, :] * horizons_s[:, None]) ** 2)
    median_offset_std, median_drift_std = float(np.median(s_o)), float(np.median(s_d))
    return {
        "ppb": ppb,
        "residual_rms_before_m": round(float(np.median([b for b, _ in residuals])), 1),
        "residual_rms_after_m": round(float(np.median([a for _, a in residuals])), 2),
        "median_offset_std_ns": round(median_offset_std * 1e9, 2),
        "median_drift_std_ns_per_s": round(median_drift_std * 1e9, 3),
        "normalised_error_rms": {"offset": round(float(np.sqrt(np.mean(np.square(normalised)[:, 0]))), 3),
                                 "drift": round(float(np.sqrt(np.mean(np.square(normalised)[:, 1]))), 3)},
        "lifetime_analysis_s": {
            "offset_only": round(calibration_lifetime_s(TOLERANCE_M, median_offset_std, 0.0,
                                                        math.sqrt(2) * ppb * 1e-9), 1),
            "offset_and_drift": round(calibration_lifetime_s(TOLERANCE_M, median_offset_std, median_drift_std), 1),
        },
        "lifetime_measured_s": {"offset_only": round(crossing_s(e_o, -d_true), 1),
                                "offset_and_drift": round(crossing_s(e_o, e_d), 1)},
        "rms_error_m": {"horizons_min": list(HORIZONS_MIN), "offset_only": rms_m(offset_only),
                        "offset_and_drift": rms_m(with_drift), "offset_and_drift_predicted": rms_m(predicted)},
    }


def crossing_s(offset_errors: np.ndarray, drift_errors: np.ndarray) -> float:
    """When the RMS over sites of ``offset + drift * T`` (s) reaches the tolerance: the root of
    a quadratic in T, its coefficients the errors' mean squares and cross term."""
    a, b, c = np.mean(drift_errors**2), 2 * np.mean(offset_errors * drift_errors), np.mean(offset_errors**2)
    c -= (TOLERANCE_M / C) ** 2
    if c >= 0:
        return 0.0
    return float((-b + math.sqrt(b * b - 4 * a * c)) / (2 * a))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=40, help="synthetic recordings per drift")
    parser.add_argument("--seconds", type=float, default=60.0, help="length of each recording")
    args = parser.parse_args()
    rows = [run(ppb, args.runs, args.seconds, seed=2026 + k) for k, ppb in enumerate(PPB)]
    print(f"\nsite clock calibration from {args.seconds:g} s recordings ({args.runs} per drift), 6 sites, 1-2 per "
          f"stack, {NOISE_M:.1f} m timing noise; tolerance {TOLERANCE_M:.0f} m (1/4 sample); times from the epoch")
    print(" ppb | sigmas: offset, drift  | lifetime (analysis / measured) | RMS error (m) at "
          + ", ".join(f"+{m} min" for m in HORIZONS_MIN))
    for row in rows:
        analysis, measured, rms = row["lifetime_analysis_s"], row["lifetime_measured_s"], row["rms_error_m"]
        print(f"{row['ppb']:4.0f} | {row['median_offset_std_ns']:6.2f} ns {row['median_drift_std_ns_per_s']:5.3f} "
              f"ns/s | offset only {analysis['offset_only']:7.1f} / {measured['offset_only']:7.1f} s | "
              f"{', '.join(f'{v:8.1f}' for v in rms['offset_only'])}")
        print(f"{'':4} | {'':20} | + drift     {analysis['offset_and_drift']:7.1f} / "
              f"{measured['offset_and_drift']:7.1f} s | {', '.join(f'{v:8.1f}' for v in rms['offset_and_drift'])}"
              f"  (sigmas say {', '.join(f'{v:.1f}' for v in rms['offset_and_drift_predicted'])})")
        print(f"     | residual RMS {row['residual_rms_before_m']:.0f} m before, {row['residual_rms_after_m']:.1f} m "
              f"after; normalised error RMS offset {row['normalised_error_rms']['offset']:.2f}, "
              f"drift {row['normalised_error_rms']['drift']:.2f}")
    results = {"seconds": args.seconds, "runs": args.runs, "sites": len(SITES), "noise_m": round(NOISE_M, 2),
               "tolerance_m": round(TOLERANCE_M, 2), "receiver_clock": "15 ppm + 0.05 ppm/s", "rows": rows}
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
