"""Fine timing: offset error vs per-frame SNR for each estimator, against the Cramér-Rao bound.

Interference: real, from the simulator. ``EnvelopeSimulator`` runs one fully loaded 10 MHz
cell (PCI 301, line of sight, -90 dBm per RE, default front end and ADC); every sync code
(subframes 0 and 5) is cut out at its true arrival with the window layout the cell search
uses (``margin`` samples either side), and the expected code response (template at the exact
sub-sample arrival, scaled by RE power and video gain as in ``sync_snr.py``) is subtracted.
What is left is a pool of interference windows: the data's square-law self-mixing, noise and
quantisation, as the receiver sees them next to a sync code.

Trials: a random PCI (0..503) and subframe, a random offset in [-3, 3] samples, the code from
``SyncTemplates`` at that exact delay (tails included) plus ``frames`` distinct interference
windows from the pool, scaled so the per-frame SNR (``sync_snr.json`` definition: mean-removed
code energy over the 276-sample code window / interference energy there) is the target. Each
estimator gets the same windows. A second run ("gaussian") replaces the pool by coloured
Gaussian noise with the pool's measured spectrum, to separate the interference's non-Gaussian
statistics from its spectrum.

CRLB: ``crlb.delay_crlb`` for each trial's template with the pool's measured per-frame PSD
(scaled), ``frames`` frames stacked; the curve is its RMS over the trials of a point.

Run:  .venv/bin/python benchmarks/timing/fine_timing.py  [--trials 200] [--frames 10] [--seconds 6]
Writes docs/results/fine_timing.json and docs/results/fine_timing.png.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from deepsync.frontend.channel import Emitter, FixedChannel, Paths  # noqa: E402
from deepsync.frontend.config import FrontendConfig  # noqa: E402
from deepsync.frontend.simulator import EnvelopeSimulator, SimulationStats  # noqa: E402
from deepsync.frontend.templates import SyncTemplates, sync_code_offset_seconds  # noqa: E402
from deepsync.lte.cell import CellConfig  # noqa: E402
from deepsync.timing.crlb import delay_crlb  # noqa: E402
from deepsync.timing.estimators import (  # noqa: E402
    estimate_fft_upsampled,
    estimate_ml,
    estimate_parabolic,
    noise_psd,
)
from deepsync.types import FRAME_SECONDS, HALF_FRAME_SECONDS, SPEED_OF_LIGHT_M_S  # noqa: E402

OUT = Path(__file__).resolve().parents[2] / "docs" / "results"
PCI = 301
DELAY_S = 1.5e-6
RE_POWER_DBM = -90.0
EIRP_PER_RE_W = 10 ** ((61 - 30) / 10) / 600  # a 61 dBm, 10 MHz macro sector, per RE
SNRS_DB = np.arange(-30.0, 10.01, 2.5)

ESTIMATORS = {
    "parabolic": lambda w, t, m: estimate_parabolic(w, t, m),
    "fft_upsampled": lambda w, t, m: estimate_fft_upsampled(w, t, m),
    "ml_white": lambda w, t, m: estimate_ml(w, t, m),
    "ml_whittle": lambda w, t, m: estimate_ml(w, t, m, noise_psd(w, t)),
}


def wide_templates(config: FrontendConfig, length: int) -> SyncTemplates:
    """Templates over the whole window: the code at any delay with its filter/coupling tails."""
    return SyncTemplates(config, length=length)


def interference_pool(seconds: float, margin: int, config: FrontendConfig) -> tuple[np.ndarray, dict]:
    """(windows, stats): simulated windows at every true code arrival, the code subtracted."""
    gain = math.sqrt(10 ** ((RE_POWER_DBM - 30) / 10) / EIRP_PER_RE_W)
    emitter = Emitter(CellConfig(pci=PCI, bandwidth_mhz=10, load=1.0), 2115e6, EIRP_PER_RE_W, 0.0, 0.0, "A")
    sim = EnvelopeSimulator([emitter], FixedChannel(Paths([DELAY_S], [gain], [0.0])), config, seed=23)
    stats = SimulationStats()
    codes = np.concatenate([c.samples for c in sim.stream(seconds + 0.02, stats=stats, workers=2)])
    volts = codes.astype(np.float64) * config.volts_per_code
    templates = SyncTemplates(config)
    length = templates.length + 2 * margin
    longer = wide_templates(config, length)
    scale = 10 ** ((RE_POWER_DBM - 30) / 10) * 10 ** (stats.gain_db / 20)
    pool, signal_energy, noise_energy = [], 0.0, 0.0
    for frame in range(1, round(seconds / FRAME_SECONDS)):
        for subframe, half in ((0, 0.0), (5, HALF_FRAME_SECONDS)):
            arrival = float(sim.sample_index(frame * FRAME_SECONDS + half + sync_code_offset_seconds() + DELAY_S))
            start = int(np.floor(arrival)) - margin
            expected = longer.template(PCI, subframe, arrival - start) * scale
            residual = volts[start : start + length] - expected
            pool.append(residual)
            code = expected[margin : margin + templates.length]
            inner = residual[margin : margin + templates.length]
            signal_energy += float(np.sum((code - code.mean()) ** 2))
            noise_energy += float(np.sum((inner - inner.mean()) ** 2))
    pool = np.array(pool)
    centred = pool[:, margin:-margin] - pool[:, margin:-margin].mean(axis=1, keepdims=True)
    excess_kurtosis = float(np.mean(centred**4) / np.mean(centred**2) ** 2 - 3)
    return pool, {
        "windows": len(pool),
        "per_frame_snr_db_of_the_simulated_cell": 10 * math.log10(signal_energy / noise_energy),
        "excess_kurtosis": excess_kurtosis,
        "diode_power_dbm": stats.diode_power_dbm,
    }


def pool_psd(pool: np.ndarray) -> np.ndarray:
    """Per-frame PSD of the interference at the window's rfft bins (mean-removed periodograms)."""
    centred = pool - pool.mean(axis=1, keepdims=True)
    return np.mean(np.abs(np.fft.rfft(centred, axis=1)) ** 2, axis=0) / pool.shape[1]


def gaussian_rows(
    rng: np.random.Generator, psd: np.ndarray, n_rows: int, length: int, buffer: int = 4096
) -> np.ndarray:
    """Gaussian rows with spectrum ``psd`` (rfft bins of ``length``), cut from a longer process."""
    f = np.fft.rfftfreq(buffer)
    shape = np.interp(f, np.fft.rfftfreq(length), np.maximum(psd, psd[1:].min()))
    shape[0] = 0.0
    white = rng.normal(size=(n_rows, f.size)) + 1j * rng.normal(size=(n_rows, f.size))
    spectrum = np.sqrt(shape * buffer / 2) * white
    return np.fft.irfft(spectrum, buffer, axis=1)[:, :length]


def run(
    kind: str, pool: np.ndarray, psd: np.ndarray, args, templates: SyncTemplates, longer: SyncTemplates,
    estimators: dict = ESTIMATORS, snr_grid: np.ndarray = SNRS_DB,
) -> list[dict]:
    """Per SNR point (``snr_grid``, dB per frame): each estimator's errors against the CRLB, over
    ``args.trials`` trials of ``args.frames`` frames in ``kind`` interference."""
    rng = np.random.default_rng(args.seed + (0 if kind == "simulator" else 1))
    bank = templates.all()
    margin, frames, length = args.margin, args.frames, pool.shape[1]
    inner = slice(margin, margin + templates.length)
    pool_inner = pool[:, inner] - pool[:, inner].mean(axis=1, keepdims=True)
    noise_energy = float(np.mean(np.sum(pool_inner**2, axis=1)))  # per frame, over the code window
    points = []
    for snr_db in tqdm(snr_grid, desc=f"fine timing ({kind})"):
        errors = {name: [] for name in estimators}
        stds = {name: [] for name in estimators}
        snrs = {name: [] for name in estimators}
        crlb_var = []
        for _ in range(args.trials):
            pci, sf_index = int(rng.integers(504)), int(rng.integers(2))
            offset = float(rng.uniform(-3, 3))
            template = bank[pci, sf_index]
            code = longer.template(pci, 5 * sf_index, margin + offset)
            t0 = template - template.mean()
            k = math.sqrt(np.sum(t0**2) / (10 ** (snr_db / 10) * noise_energy))
            if kind == "simulator":
                interference = pool[rng.choice(len(pool), frames, replace=False)]
            else:
                interference = gaussian_rows(rng, psd, frames, length)
            windows = code[None, :] + k * interference
            crlb_var.append(delay_crlb(template, 1.0, k**2 * psd, frames).std_samples ** 2)
            for name, estimator in estimators.items():
                estimate = estimator(windows, template, margin)
                errors[name].append(estimate.offset - offset)
                stds[name].append(estimate.std)
                snrs[name].append(estimate.snr_db)
        point = {"snr_per_frame_db": float(snr_db), "crlb_samples": float(np.sqrt(np.mean(crlb_var)))}
        for name in estimators:
            err = np.abs(np.array(errors[name]))
            std = np.array(stds[name])
            rmse = float(np.sqrt(np.mean(err**2)))
            point[name] = {
                "median_abs_err_samples": float(np.median(err)),
                "p90_abs_err_samples": float(np.percentile(err, 90)),
                "rmse_samples": rmse,
                "rms_reported_std_samples": float(np.sqrt(np.mean(std**2))),
                "rmse_over_rms_std": rmse / float(np.sqrt(np.mean(std**2))),
                "fraction_within_2_std": float(np.mean(err < 2 * std)),
                "median_snr_db_estimate": float(np.median(snrs[name])),
            }
        points.append(point)
    return points


def runtimes(pool: np.ndarray, psd: np.ndarray, args, templates: SyncTemplates, longer: SyncTemplates) -> dict:
    """Microseconds per call (best of 5 rounds of 100 calls), n_frames windows at -15 dB per frame."""
    rng = np.random.default_rng(5)
    template = templates.template(121, 0)
    t0 = template - template.mean()
    inner = pool[:, args.margin : args.margin + templates.length]
    energy = np.mean(np.sum((inner - inner.mean(axis=1, keepdims=True)) ** 2, axis=1))
    k = math.sqrt(np.sum(t0**2) / (10 ** (-1.5) * energy))
    windows = [longer.template(121, 0, args.margin + 0.3) + k * pool[rng.choice(len(pool), args.frames, replace=False)]
               for _ in range(100)]
    out = {}
    for name, estimator in ESTIMATORS.items():
        estimator(windows[0], template, args.margin)
        best = math.inf
        for _ in range(5):
            start = time.perf_counter()
            for w in windows:
                estimator(w, template, args.margin)
            best = min(best, (time.perf_counter() - start) / len(windows))
        out[name] = best * 1e6
    start = time.perf_counter()
    for w in windows:
        noise_psd(w, template)
    out["noise_psd_alone"] = (time.perf_counter() - start) / len(windows) * 1e6
    return out


def plot(results: dict, path: Path, frames: int, sample_rate: float) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8))
    colours = {"parabolic": "C0", "fft_upsampled": "C1", "ml_white": "C2", "ml_whittle": "C3"}
    for kind, style in (("simulator", "-"), ("gaussian", ":")):
        points = results[kind]
        snr = [p["snr_per_frame_db"] for p in points]
        solid = kind == "simulator"
        for name, colour in colours.items():
            marks = {"color": colour, "marker": "o" if solid else None, "ms": 3}
            rmse = [p[name]["rmse_samples"] for p in points]
            honesty = [p[name]["rmse_over_rms_std"] for p in points]
            axes[0].semilogy(snr, rmse, style, label=f"{name} RMSE" if solid else None, **marks)
            axes[1].plot(snr, honesty, style, label=name if solid else None, **marks)
        if solid:
            axes[0].semilogy(snr, [p["crlb_samples"] for p in points], "k--", lw=2, label="CRLB")
            median = [p["ml_whittle"]["median_abs_err_samples"] for p in points]
            axes[0].semilogy(snr, median, color="C3", lw=0.8, alpha=0.6, label="ml_whittle median |err|")
    axes[0].set_xlabel(f"SNR per frame (dB), {frames} frames stacked")
    axes[0].set_ylabel("offset error (samples)")
    axes[0].set_ylim(1e-3, 10)
    axes[0].grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=8)
    per_sample = SPEED_OF_LIGHT_M_S / sample_rate
    metres = axes[0].secondary_yaxis("right", functions=(lambda s: s * per_sample, lambda m: m / per_sample))
    metres.set_ylabel("metres")
    axes[0].set_title("simulator interference (solid), Gaussian with its spectrum (dotted)", fontsize=9)
    axes[1].axhspan(0.7, 1.4, color="0.9")
    axes[1].axhline(1.0, color="k", lw=0.8)
    axes[1].set_xlabel("SNR per frame (dB)")
    axes[1].set_ylabel("RMSE / RMS reported std")
    axes[1].set_yscale("log")
    axes[1].set_ylim(0.1, 10)
    axes[1].grid(alpha=0.3, which="both")
    axes[1].legend(fontsize=8)
    axes[1].set_title("honesty of the reported 1-sigma (1 = honest)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--seconds", type=float, default=6.0, help="simulated seconds for the interference pool")
    parser.add_argument("--margin", type=int, default=10)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    if args.trials < 1 or args.frames < 2:
        sys.exit("need --trials >= 1 and --frames >= 2")
    config = FrontendConfig()
    templates = SyncTemplates(config)
    longer = wide_templates(config, templates.length + 2 * args.margin)

    started = time.time()
    pool, pool_stats = interference_pool(args.seconds, args.margin, config)
    psd = pool_psd(pool)
    print(f"interference pool: {pool_stats['windows']} windows, simulated cell at "
          f"{pool_stats['per_frame_snr_db_of_the_simulated_cell']:.1f} dB per frame, excess kurtosis "
          f"{pool_stats['excess_kurtosis']:.2f} ({time.time() - started:.0f} s)")
    results = {kind: run(kind, pool, psd, args, templates, longer) for kind in ("simulator", "gaussian")}
    timing = runtimes(pool, psd, args, templates, longer)

    names = list(ESTIMATORS)
    for kind, points in results.items():
        print(f"\n{kind} interference, {args.frames} frames, {args.trials} trials per point: "
              "RMSE (samples) [RMSE / RMS reported std]")
        print(f"{'SNR/frame':>9} {'CRLB':>7} " + " ".join(f"{n:>22}" for n in names))
        for p in points:
            cells = " ".join(f"{p[n]['rmse_samples']:>13.4f} [{p[n]['rmse_over_rms_std']:5.2f}]" for n in names)
            print(f"{p['snr_per_frame_db']:>7.1f}dB {p['crlb_samples']:>7.4f} {cells}")
    print("\nmedian |err| / p90 |err| (samples), simulator interference:")
    for p in results["simulator"]:
        cells = " ".join(f"{p[n]['median_abs_err_samples']:>9.4f}/{p[n]['p90_abs_err_samples']:<9.4f}" for n in names)
        print(f"{p['snr_per_frame_db']:>7.1f}dB {cells}")
    high = {
        kind: [(p["snr_per_frame_db"], p["ml_whittle"]["rmse_samples"] / p["crlb_samples"],
                p["ml_white"]["rmse_samples"] / p["crlb_samples"]) for p in pts[-4:]]
        for kind, pts in results.items()
    }
    print("\nML RMSE / CRLB at the highest SNRs (whittle, white):")
    for kind, rows in high.items():
        print(f"  {kind}: " + ", ".join(f"{s:+.1f} dB: {a:.3f}, {b:.3f}" for s, a, b in rows))
    print("\nmicroseconds per call (n_frames = %d, L_w = %d): " % (args.frames, pool.shape[1])
          + ", ".join(f"{k} {v:.0f}" for k, v in timing.items()))

    OUT.mkdir(parents=True, exist_ok=True)
    document = {
        "description": __doc__.split("\n\n")[1] + "\n\n" + __doc__.split("\n\n")[2],
        "interference": "simulator (EnvelopeSimulator, one fully loaded 10 MHz cell, -90 dBm/RE, cut at the true "
                        "arrival, code subtracted); 'gaussian' = coloured Gaussian noise with the pool's measured PSD",
        "estimators": {"parabolic": "estimate_parabolic", "fft_upsampled": "estimate_fft_upsampled (factor 32)",
                       "ml_white": "estimate_ml (noise_psd=None)",
                       "ml_whittle": "estimate_ml (noise_psd=noise_psd(windows))"},
        "frames": args.frames,
        "trials_per_point": args.trials,
        "margin": args.margin,
        "offsets": "uniform in [-3, 3] samples; random PCI and subframe per trial",
        "samples_to_metres": SPEED_OF_LIGHT_M_S / config.adc_rate_hz,
        "pool": pool_stats,
        "pool_psd_per_frame": psd.tolist(),
        "runtime_us_per_call": timing,
        "ml_rmse_over_crlb_at_highest_snrs": {kind: [{"snr_per_frame_db": s, "ml_whittle": a, "ml_white": b}
                                                     for s, a, b in rows] for kind, rows in high.items()},
        "results": results,
    }
    (OUT / "fine_timing.json").write_text(json.dumps(document, indent=2))
    plot(results, OUT / "fine_timing.png", args.frames, config.adc_rate_hz)
    print(f"\nwrote {OUT / 'fine_timing.json'} and {OUT / 'fine_timing.png'} ({time.time() - started:.0f} s)")


if __name__ == "__main__":
    main()
