"""Side by side on the timing test set: the network, ML, FFT-upsampled, parabolic, and the
Cramer-Rao bound, against the true first-path arrival; and ``ml_frame``, the timing stage's
default, where the split holds the examples' mean frames (``DatasetConfig.frame_means``).

Every estimator sees the same windows (the first F frames of each test example, F in
``frames``); ``ml_frame`` the mean of the same F frames, through the timing stage itself.
Errors are estimate minus the true first-path offset, in samples. The bound is
``crlb.delay_crlb`` at the amplitude fitted at the true offset and the noise spectrum measured
from the rows: what an unbiased estimator of the *peak* could reach; multipath bias is on top.
``ml_frame``'s is its own (``CellTiming.crlb_std``: the whole known frame's, at its fitted
amplitude and residual spectrum), about 10 dB lower at 10 MHz.
Breakdowns: per-frame SNR bins, frames, bandwidth, LOS (TDL-D/E) vs NLOS (TDL-A/B/C), the size
of the coarse error (how far the sync stage's code lock was from the true start), and the
sigma calibration (share of errors within +-1 reported sigma, 68 % if honest) of each
estimator per SNR bin. Headline numbers (``headline``, 10 frames): the threshold SNR on LOS
channels (where RMSE exceeds 2x the median bound; where outliers, errors beyond a sample,
exceed 10 %), the RMSE on every channel at -10..0 dB, the RMSE on LOS channels from 0 dB up,
and the range of the calibration over SNR bins.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.stats import binomtest
from tqdm import tqdm

from deepsync.eval.cell_search import timing_error
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.templates import SyncTemplates
from deepsync.pipeline import Pipeline, PipelineConfig
from deepsync.sources.bagfile import BagSource
from deepsync.timing.crlb import delay_crlb, fit_amplitude
from deepsync.timing.estimators import SIGMA_CALIBRATION_BAND, noise_psd
from deepsync.timing.registry import ESTIMATORS, Estimator, Input
from deepsync.timing.stage import TimingConfig, TimingStage
from deepsync.towers import TowerDatabase
from deepsync.training.dataset import LOS_PROFILES, PROFILES, frame_delay_key, frame_key, load_split
from deepsync.types import StackWindows, SyncWindow

if TYPE_CHECKING:
    from deepsync.timing.network import NetworkEstimator

SNR_EDGES_DB = np.arange(-30.0, 12.5, 5.0)

def of_input(kind: Input) -> tuple[Estimator, ...]:
    """The registered estimators that time a cell from ``kind``."""
    return tuple(e for e in ESTIMATORS.values() if e.input is kind)


def side_by_side(with_frame: bool = True) -> tuple[str, ...]:
    """Every registered estimator's name in the side by side's order: those of the frame (where
    the stack's mean frame comes along: a recording, a split that keeps it; ``with_frame``), the
    network's, the windows'."""
    kinds = (Input.FRAME, Input.NETWORK, Input.WINDOWS) if with_frame else (Input.NETWORK, Input.WINDOWS)
    return tuple(e.name for kind in kinds for e in of_input(kind))

FRAME_BOUND = "crlb_frame"  # ml_frame's own bound, beside the code windows' "crlb"


COARSE_ERROR_EDGES = np.array([0, 3, 6, 9, 20, 40])  # bins of the coarse error's size (samples)
OUTLIER_SAMPLES = 1.0  # an error beyond this is a wrong lobe, not noise (156 m)
CONFIDENCE = 0.95  # of the interval given with each share within +-1 sigma


def error_stats(errors: np.ndarray, sigmas: np.ndarray | None = None) -> dict[str, float | list[float]]:
    """Median, p90 and RMS of timing errors (samples), the share beyond ``OUTLIER_SAMPLES``, and
    with the reported sigmas the share within +-1 sigma and its ``CONFIDENCE`` interval (Wilson):
    in a bin of a few dozen examples even an honest sigma's share wanders by +-10 %."""
    if errors.size == 0:
        return {"n": 0}
    absolute = np.abs(errors)
    out = {"n": int(errors.size), "median": float(np.median(absolute)), "p90": float(np.percentile(absolute, 90)),
           "rmse": float(np.sqrt(np.mean(errors**2))), "outliers": float(np.mean(absolute > OUTLIER_SAMPLES))}
    if sigmas is not None:
        within = int(np.sum(absolute <= sigmas))
        interval = binomtest(within, errors.size).proportion_ci(CONFIDENCE, method="wilson")
        out["within_1_sigma"] = within / errors.size
        out["within_1_sigma_ci"] = [float(interval.low), float(interval.high)]
    return out


def run_estimators(data: dict[str, np.ndarray], frames: int, network: NetworkEstimator | None,
                   progress: bool = True) -> dict[str, np.ndarray]:
    """Per example: each estimator's error and sigma, and the bound (samples). Without a
    ``network`` (windows it does not take) its rows and network_ml's stay NaN; ``ml_frame``'s
    are there where the split holds the mean frames of ``frames`` stacked frames."""
    windows = data["windows"][:, :frames]
    templates = data["template"]
    margin = (windows.shape[2] - templates.shape[1]) // 2
    rate = FrontendConfig().adc_rate_hz
    n = len(windows)
    with_frame = frame_key(frames) in data
    names = side_by_side(with_frame)
    results = {f"{name}_{kind}": np.full(n, np.nan) for name in names for kind in ("error", "sigma")}
    results["crlb"] = np.full(n, np.nan)
    for estimator in of_input(Input.FRAME) if with_frame else ():
        timed = np.array(time_by_frame(data, frames, estimator, progress)).reshape(n, 3)
        results[f"{estimator.name}_error"], results[f"{estimator.name}_sigma"] = timed[:, 0] - data["offset"], timed[:, 1]
        results[FRAME_BOUND] = timed[:, 2]
    outputs = np.full((n, 2), np.nan)  # the network's offset and sigma per example
    for start in range(0, n if network is not None else 0, 256):
        batch = network.estimate(list(windows[start : start + 256]), list(templates[start : start + 256]))
        outputs[start : start + len(batch)] = batch
    for i in tqdm(range(n), desc=f"classical estimators, {frames} frames", disable=not progress):
        w, t = windows[i].astype(np.float64), templates[i].astype(np.float64)
        psd = noise_psd(w)
        estimates = [(e, e.on_windows(w, t, margin, psd)) for e in of_input(Input.WINDOWS)]
        if network is not None:
            estimates += [(e, e.after_network(w, t, margin, psd, float(outputs[i, 0]), float(outputs[i, 1])))
                          for e in of_input(Input.NETWORK)]
        for estimator, result in estimates:
            results[f"{estimator.name}_error"][i] = result.offset - data["offset"][i]
            results[f"{estimator.name}_sigma"][i] = result.std
        amplitude = fit_amplitude(w.mean(axis=0), t, margin, float(data["offset"][i]), psd)
        if amplitude > 0:
            results["crlb"][i] = delay_crlb(t, amplitude, psd, frames, rate, w.shape[1]).std_samples
    return results


def time_by_frame(data: dict[str, np.ndarray], frames: int, estimator: Estimator,
                  progress: bool = True) -> list[tuple[float, float, float]]:
    """(offset, sigma, Cramer-Rao bound) of each example by ``estimator`` (of the frame) through the timing
    stage, as a stack of ``frames`` frames hands it the cell: its windows, its bandwidth from the
    tower database, a pair's fit, and the stack's mean frame (its sample 0 at the coarse code
    start) with its delay."""
    frontend = FrontendConfig()
    templates = SyncTemplates(frontend)
    means, delays = data[frame_key(frames)], data[frame_delay_key(frames)]
    out = []
    for i in tqdm(range(len(means)), desc=f"{estimator.name}, {frames} frames", disable=not progress):
        pair = int(data["cosited_pci"][i]) >= 0
        window = SyncWindow(
            stamp_ns=0, pci=int(data["pci"][i]), coarse_index=0, windows=data["windows"][i, :frames],
            peak_metric=math.nan, snr_db=float(data["snr_db"][i]), bandwidth_mhz=float(data["bandwidth_mhz"][i]),
            cosited_pci=int(data["cosited_pci"][i]) if pair else None,
            site_coefficients=tuple(map(float, data["site_coefficients"][i])) if pair else None)
        # a stage per example: its cache of known frames (0.5 MB per PCI and bandwidth) would
        # otherwise hold every example's; the shared templates' CRS caches still grow, by less
        stage = TimingStage(frontend, TimingConfig(estimator), templates)
        timed = stage.process(StackWindows(0, 0, frontend.adc_rate_hz, (window,), frame=means[i],
                                           frame_delay=float(delays[i])))
        cell = timed.cells[0] if timed.cells else None
        out.append((math.nan,) * 3 if cell is None else (cell.toa, cell.toa_std, cell.crlb_std))
    return out


def estimator_names(results: dict[str, np.ndarray]) -> tuple[str, ...]:
    """The estimators ``results`` holds, in the side by side's order."""
    return tuple(name for name in side_by_side() if f"{name}_error" in results)


def estimators_in(row: dict) -> tuple[str, ...]:
    """The estimators a summary row (``breakdown``'s) has statistics of, in the same order."""
    return tuple(name for name in side_by_side() if name in row)


def breakdown(data: dict[str, np.ndarray], results: dict[str, np.ndarray], mask: np.ndarray) -> dict:
    """Every estimator's statistics over the examples in ``mask``, and the bound's RMS."""
    out = {name: error_stats(results[f"{name}_error"][mask], results[f"{name}_sigma"][mask])
           for name in estimator_names(results)}
    # the median: a few codes barely above the noise have a bound of many samples
    for key in ("crlb", FRAME_BOUND):
        if key in results:
            bound = results[key][mask]
            bound = bound[np.isfinite(bound)]
            out[f"{key}_median"] = float(np.median(bound)) if bound.size else math.nan
    return out


def by_snr(data: dict[str, np.ndarray], results: dict[str, np.ndarray], mask: np.ndarray) -> list[dict]:
    rows = []
    for low, high in zip(SNR_EDGES_DB[:-1], SNR_EDGES_DB[1:]):
        inside = mask & (data["snr_db"] >= low) & (data["snr_db"] < high)
        rows.append({"snr_db": [float(low), float(high)], **breakdown(data, results, inside)})
    return rows


def by_coarse_error(data: dict[str, np.ndarray], results: dict[str, np.ndarray]) -> dict[str, dict]:
    """Breakdowns by how far (whole samples, either way) the coarse code start was from the true
    one: does an estimator hold up to the edge of the margin its windows give it?"""
    distance = np.abs(data["coarse_error"])
    edges = [*COARSE_ERROR_EDGES[COARSE_ERROR_EDGES <= distance.max()], int(distance.max()) + 1]
    return {f"{low}-{high - 1}": breakdown(data, results, (distance >= low) & (distance < high))
            for low, high in zip(edges[:-1], edges[1:])}


def threshold_snr_db(rows: list[dict], name: str) -> dict[str, float | None]:
    """Upper edge of the highest SNR bin (None: none) where the RMSE exceeds 2x the (median)
    bound (an estimator of the frame: its own), and where more than 10 % of the errors are outliers (beyond
    ``OUTLIER_SAMPLES``)."""
    bound = f"{FRAME_BOUND}_median" if ESTIMATORS[name].input is Input.FRAME else "crlb_median"
    filled = [row for row in rows if row[name].get("n", 0) >= 10]
    rmse = [row["snr_db"][1] for row in filled if row[name]["rmse"] > 2 * row[bound]]
    outliers = [row["snr_db"][1] for row in filled if row[name]["outliers"] > 0.1]
    return {"rmse_over_2_crlb": max(rmse) if rmse else None, "outliers_over_10_percent": max(outliers) if outliers else None}


def threshold_text(value: float | None) -> str:
    """A ``threshold_snr_db`` value as a table prints it ("never": no SNR bin crosses)."""
    return "never" if value is None else f"{value:+.0f} dB"


SHIPPED_RUN = "config/timing/timing_net.yaml"  # the run that made the shipped network, and its data


def check_split_made(data_dir: str | Path, split: str) -> None:
    """ValueError saying what to run first (and how long it takes) where ``split`` has no examples."""
    where = Path(data_dir) / split
    if not any(where.glob("shard_*.npz")):
        raise ValueError(
            f"no timing examples in {where}: make them first with `deepsync make-dataset --config {SHIPPED_RUN}` "
            "(every split of the shipped run: about 20 minutes on 2 cores; `deepsync train` makes them too, then "
            "trains: about 40 minutes), or score a simulated recording instead, in seconds: `deepsync "
            "evaluate-timing --bag "
            "bags/campus_route --towers config/towers/campus.yaml`")


def evaluate_timing(data_dir: str | Path, out: str | Path, checkpoint: str | Path | None = None,
                    frames: Sequence[int] = (5, 10, 12), split: str = "test", progress: bool = True) -> dict:
    """The side by side on a split of the timing data; writes timing.json and timing.png to ``out``."""
    check_split_made(data_dir, split)
    from deepsync.timing.network import NetworkEstimator  # torch: only for this command

    data = load_split(Path(data_dir), split)
    available = data["windows"].shape[1]
    if max(frames) > available or min(frames) < 2:
        raise ValueError(f"frames {', '.join(map(str, frames))}: the examples of {data_dir}/{split} have "
                         f"{available} frames, and timing needs at least 2")
    network = NetworkEstimator(checkpoint)
    los = np.isin(data["profile"], [PROFILES.index(p) for p in LOS_PROFILES])
    everything = np.ones(len(los), dtype=bool)
    summary: dict = {"split": split, "examples": int(len(los)), "frames": {}}
    for count in frames:
        results = run_estimators(data, count, network, progress)
        summary["frames"][str(count)] = {
            "all": breakdown(data, results, everything),
            "by_snr": by_snr(data, results, everything),
            "los_by_snr": by_snr(data, results, los),
            "nlos_by_snr": by_snr(data, results, ~los),
            "by_bandwidth": {f"{bw:g}": breakdown(data, results, data["bandwidth_mhz"] == bw)
                             for bw in np.unique(data["bandwidth_mhz"])},
            "by_profile": {name: breakdown(data, results, data["profile"] == k) for k, name in enumerate(PROFILES)
                           if np.any(data["profile"] == k)},
            "by_coarse_error": by_coarse_error(data, results),
            # a co-sited pair is timed with its fitted model, as the sync stage reports it
            "by_cosited": {kind: breakdown(data, results, mask) for kind, mask in
                           (("single", data["cosited_pci"] < 0), ("pair", data["cosited_pci"] >= 0)) if np.any(mask)},
        }
    summary["headline"] = headline(data, summary)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "timing.json").write_text(json.dumps(summary, indent=1))
    plot(summary, out / "timing.png")
    return summary


def headline(data: dict[str, np.ndarray], summary: dict) -> dict:
    ten = summary["frames"].get("10")
    if ten is None:
        return {}
    rows = ten["by_snr"]
    mid = [row for row in rows if -10 <= row["snr_db"][0] and row["snr_db"][1] <= 0]

    def pooled_rmse(selection: list[dict], name: str) -> float:
        n = sum(row[name]["n"] for row in selection if row[name].get("n"))
        return math.sqrt(sum(row[name]["rmse"] ** 2 * row[name]["n"] for row in selection if row[name].get("n")) / n) if n else math.nan

    high_los = [row for row in ten["los_by_snr"] if row["snr_db"][0] >= 0]

    def calibration(name: str) -> list[float] | None:
        shares = [row[name]["within_1_sigma"] for row in rows if row[name].get("n", 0) >= 20]
        return [min(shares), max(shares)] if shares else None

    def calibration_verdicts(name: str) -> dict[str, int]:
        """SNR bins whose share within +-1 sigma is in the band, and those whose interval lies
        wholly below it (sigma too small) or above it (too large): what the test split can tell."""
        low, high = SIGMA_CALIBRATION_BAND
        measured = [row[name] for row in rows if row[name].get("n", 0) >= 20]
        return {"bins": len(measured),
                "in_band": sum(low <= m["within_1_sigma"] <= high for m in measured),
                "sigma_too_small": sum(m["within_1_sigma_ci"][1] < low for m in measured),
                "sigma_too_large": sum(m["within_1_sigma_ci"][0] > high for m in measured)}

    names = estimators_in(rows[0])
    return {
        "threshold_snr_db_los": {name: threshold_snr_db(ten["los_by_snr"], name) for name in names},
        "multipath_rmse_-10_to_0_db": {name: pooled_rmse(mid, name) for name in names},
        "high_snr_los_rmse_from_0_db": {name: pooled_rmse(high_los, name) for name in names},
        "within_1_sigma_range_over_snr_bins": {name: calibration(name) for name in names},
        "within_1_sigma_snr_bins": {name: calibration_verdicts(name) for name in names},
    }


def stats_text(stats: dict) -> str:
    """One estimator's ``error_stats`` as a table row's cells (samples)."""
    if not stats.get("n"):
        return "no cell timed"
    within = stats.get("within_1_sigma")
    return (f"{stats['median']:7.3f} {stats['p90']:7.3f} {stats['rmse']:7.3f} {100 * stats['outliers']:8.1f} %"
            + ("" if within is None else f" {100 * within:10.0f} %"))


STATS_HEADER = " median     p90    RMSE  outliers  within 1 sigma"


def stats_table(rows: dict[str, dict], first: str = "estimator") -> list[str]:
    """``error_stats`` per estimator (or per bin) as aligned lines, samples (one is 156 m at 1.92 MHz)."""
    return [f"{first:14s}{STATS_HEADER}", *(f"{name:14s}{stats_text(stats)}" for name, stats in rows.items())]


def headline_table(headline: dict) -> list[str]:
    """``headline``'s numbers as aligned lines, one per estimator: "never" where no SNR bin
    crosses a threshold, "-" where nothing was measured."""

    def number(value: float | None, form: str) -> str:
        return "-" if value is None or not math.isfinite(value) else format(value, form)

    def share(span: list[float] | None) -> str:
        return "-" if span is None else f"{100 * span[0]:.0f}-{100 * span[1]:.0f} %"

    lines = ["10 frames      LOS threshold SNR (per frame)   RMSE (samples)       within +-1 sigma over SNR bins",
             "estimator      RMSE > 2 CRLB  outliers > 10 %  -10..0 dB  LOS >= 0 dB  range      bins in band"]
    for name, threshold in headline.get("threshold_snr_db_los", {}).items():
        bins = headline["within_1_sigma_snr_bins"][name]
        lines.append(f"{name:14s} {threshold_text(threshold['rmse_over_2_crlb']):>13s}  "
                     f"{threshold_text(threshold['outliers_over_10_percent']):>15s}  "
                     f"{number(headline['multipath_rmse_-10_to_0_db'][name], '.3f'):>9s}  "
                     f"{number(headline['high_snr_los_rmse_from_0_db'][name], '.3f'):>11s}  "
                     f"{share(headline['within_1_sigma_range_over_snr_bins'][name]):10s} "
                     f"{bins['in_band']} of {bins['bins']}")
    return lines


def plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ten = summary["frames"].get("10") or next(iter(summary["frames"].values()))
    estimators = estimators_in(ten["all"])
    figure, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    profiles = list(ten["by_profile"])
    for ax, key, title, los in ((axes[0], "los_by_snr", "LOS", True), (axes[1], "nlos_by_snr", "NLOS", False)):
        names = [name for name in profiles if (name in LOS_PROFILES) == los]
        ax.set_title(f"{title}: {', '.join(names) or 'none in this split'}\n10 frames, RMSE vs true first path")
        if not names:
            ax.axis("off")
            continue
        rows = ten[key]
        centres = [np.mean(row["snr_db"]) for row in rows]
        for name in estimators:
            ax.semilogy(centres, [row[name].get("rmse", np.nan) for row in rows], marker="o", label=name)
        ax.semilogy(centres, [row["crlb_median"] for row in rows], "k--", label="CRLB (median)")
        if f"{FRAME_BOUND}_median" in rows[0]:
            ax.semilogy(centres, [row[f"{FRAME_BOUND}_median"] for row in rows], "k:", label="ml_frame's CRLB")
        ax.set_xlabel("per-frame SNR (dB)")
        ax.set_ylabel("RMSE (samples)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    rows = ten["by_snr"]
    centres = [np.mean(row["snr_db"]) for row in rows]
    for name in estimators:
        axes[2].plot(centres, [row[name].get("within_1_sigma", np.nan) for row in rows], marker="o", label=name)
    axes[2].axhspan(*SIGMA_CALIBRATION_BAND, color="green", alpha=0.15, label="calibrated")
    axes[2].set_title("errors within +-1 reported sigma")
    axes[2].set_xlabel("per-frame SNR (dB)")
    axes[2].set_ylim(0, 1)
    axes[2].grid(True, alpha=0.3)
    axes[2].legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def evaluate_timing_bag(source: BagSource, towers: TowerDatabase | None, out: str | Path,
                        checkpoint: str | Path | None = None, frames: int = 10, progress: bool = True) -> dict:
    """The same side by side on a simulated recording nobody trained on: every cell the sync stage
    reports, timed by each estimator, against the bag's true arrivals (``timing_bag.json``)."""
    truth = source.truth_arrivals()
    if not truth:
        raise ValueError(f"{source.description} holds no ground truth (/deepsync/truth/cell_timing): "
                         "only a simulated recording can be scored")
    pipeline = Pipeline(source.frontend, PipelineConfig().with_choices(frames), towers)
    stages = {name: TimingStage(source.frontend, TimingConfig(Estimator.named(name), checkpoint=None
                                                              if checkpoint is None else str(checkpoint)))
              for name in side_by_side()}
    # the network estimators fall back for the same cells: one of them says which
    reporting = next((e.name for e in of_input(Input.NETWORK)), None)
    records: dict[str, list[tuple[float, float, float]]] = {name: [] for name in stages}
    fallbacks: list[str] = []
    for chunk in tqdm(source.chunks(), desc="timing on the recording", unit="chunk", disable=not progress):
        for result in pipeline.process(chunk):
            stack = result.sync.stack_windows
            windows = dataclasses.replace(stack, windows=tuple(w for w in stack.windows if w.pci in truth))
            for name, stage in stages.items():
                timed = stage.process(windows)
                if name == reporting:
                    fallbacks += [f"PCI {pci}: {reason}" for pci, reason in timed.fallbacks]
                for cell in timed.cells:
                    records[name].append((timing_error(cell.toa, truth[cell.pci]), cell.toa_std, cell.snr_db))
    summary = {"bag": source.description, "frames": frames, "fallbacks_to_ml": len(fallbacks),
               "fallback_examples": sorted(set(fallbacks))[:5],
               "cells_timed": max(map(len, records.values()))}
    for name, rows in records.items():
        values = np.array(rows).reshape(-1, 3)
        summary[name] = error_stats(values[:, 0], values[:, 1])
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "timing_bag.json").write_text(json.dumps(summary, indent=1))
    return summary
