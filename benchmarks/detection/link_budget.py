"""Link budget, measured: the received power per RE at which a known cell is heard, and how far that is.

Three measurements, joined by the per-frame sync SNR (``sync_snr.py``'s definition: the code's
mean-removed energy over its 276-sample window / everything else's energy there), the one number
both the search and the timing see:

1. Detection (``cell_search.py``'s trials, known-PCI mode: a 20-PCI tower database, full-code
   timing): Pd vs per-frame SNR for N = 10, 20, 50, 100 stacked frames in real interference (a
   loaded 10 MHz cell). A detection counts when it names the true PCI within 1 sample of its code.
2. Timing (``fine_timing.py``'s trials, the timing stage's ML): RMSE and CRLB vs per-frame SNR.
3. The front end (``sync_snr.py``'s measurement): per-frame SNR vs received power per RE, for each
   bandwidth, PDSCH load and front end, through the full simulator (thermal and detector noise,
   the cell's own data and CRS, AGC and ADC).

A cell is heard from the lowest power whose SNR reaches both the SNR where Pd >= 90 % and the SNR
from which the ML RMSE stays within 2x the CRLB. The heard range is where the 38.901 median path
loss (UMa / UMi, LOS / NLOS; no shadowing) brings the EIRP per RE down to that power.

Check of the join: the whole chain (simulator -> SyncStage with a tower database) run directly at
the predicted heard power and 3 dB either side must put Pd around 90 % there.

Run:  .venv/bin/python benchmarks/detection/link_budget.py [--trials 100] [--quick]
Writes docs/results/link_budget.{json,csv,png}.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from argparse import Namespace
from pathlib import Path

import matplotlib

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "timing"))  # fine_timing.py's trials, beside ours

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

import cell_search  # noqa: E402
import fine_timing  # noqa: E402
from deepsync.frontend.channel import Emitter, FixedChannel, Paths  # noqa: E402
from deepsync.frontend.config import FrontendConfig  # noqa: E402
from deepsync.frontend.simulator import EnvelopeSimulator  # noqa: E402
from deepsync.frontend.templates import SyncTemplates, sync_code_offset_seconds  # noqa: E402
from deepsync.lte.cell import CellConfig  # noqa: E402
from deepsync.sync.stacking import StackConfig  # noqa: E402
from deepsync.sync.stage import SyncConfig, SyncStage  # noqa: E402
from deepsync.towers import parse_tower_database  # noqa: E402
from deepsync.twin.propagation import path_loss_db  # noqa: E402
from deepsync.types import FRAME_SECONDS  # noqa: E402
from sync_snr import EIRP_PER_RE_W, measure  # noqa: E402

OUT = Path(__file__).resolve().parents[2] / "docs" / "results"
FRAMES = (10, 20, 50, 100)
BANDWIDTHS = (1.4, 5.0, 10.0, 20.0)
LOADS = (0.3, 0.6, 1.0)
FRONTENDS = {
    "default": ("LNA 30 dB, NF 6 dB, 200 MHz RF bandwidth (the default)", FrontendConfig()),
    "low_noise": ("LNA 40 dB, NF 2 dB, 60 MHz band filter",
                  FrontendConfig(rf_gain_db=40.0, noise_figure_db=2.0, rf_bandwidth_hz=60e6)),
    "bare_diode": ("no LNA: the diode at the antenna", FrontendConfig(rf_gain_db=0.0, noise_figure_db=0.0)),
}
POWERS_DBM = np.arange(-140.0, -39.0, 5.0)  # per RE at the antenna
PD_TARGET = 0.9
RMSE_OVER_CRLB = 2.0
CARRIER_HZ = 2115e6
UE_HEIGHT_M = 1.5
SCENARIOS = {  # model, BS height (m), EIRP per RE (dBm)
    "UMa": (25.0, 10 * math.log10(EIRP_PER_RE_W) + 30),  # a 61 dBm EIRP macro sector over 600 RE (10 MHz)
    "UMi": (10.0, 10 * math.log10(EIRP_PER_RE_W) + 30 - 10),  # a small cell 10 dB below it
}
MAX_RANGE_M = 10_000.0


def crossing(x: np.ndarray, y: np.ndarray, target: float) -> float:
    """First x where the increasing-ish curve y reaches ``target`` (linear between points) and
    stays there; nan if it never does."""
    above = y >= target
    if not above[-1]:
        return math.nan
    if above.all():
        return float(x[0])
    first = len(y) - int(np.argmin(above[::-1]))  # start of the last run above
    x0, x1, y0, y1 = x[first - 1], x[first], y[first - 1], y[first]
    return float(x0 + (target - y0) * (x1 - x0) / (y1 - y0))


def detection_curves(trials: int, seconds: float, rng: np.random.Generator) -> dict:
    """Pd vs per-frame SNR with a tower database, and the SNR where it reaches 90 %, per N."""
    config = FrontendConfig()
    templates = SyncTemplates(config)
    frames, resident = cell_search.interference(seconds, config)
    sigma = cell_search.interference_sigma(frames, resident)
    database = cell_search.TowerDatabases(templates, rng)
    pcis = rng.choice(np.setdiff1d(np.arange(504), [cell_search.RESIDENT_PCI]), 40, replace=False)
    curves = {}
    for n in FRAMES:
        centre = -17.0 - 10 * math.log10(n / 10)  # stacking gains 10 log N in per-frame SNR terms
        grid = np.arange(centre - 6, centre + 4.1, 1.0)
        pd, false = [], 0
        for snr in tqdm(grid, desc=f"detection, {n} frames"):
            hits = 0
            for _ in range(trials):
                pci = int(rng.choice(pcis))
                out = cell_search.trial(rng, frames, resident, templates, None, database, pci, n, snr, sigma,
                                        ("known",))
                hits += out["known"][0] and out["known"][1]
            pd.append(hits / trials)
        for _ in range(trials):
            false += cell_search.trial(rng, frames, resident, templates, None, database, None, n, 0.0, sigma,
                                       ("known",))["known"][5]
        curves[n] = {"snr_db": grid.tolist(), "pd": pd, "pfa_per_stack": false / trials,
                     "snr_for_pd90_db": crossing(grid, np.array(pd), PD_TARGET)}
    return curves


def timing_curves(trials: int, seconds: float) -> dict:
    """ML RMSE and CRLB vs per-frame SNR, and the SNR from which RMSE <= 2 CRLB, per N."""
    config = FrontendConfig()
    margin = 10
    templates = SyncTemplates(config)
    longer = fine_timing.wide_templates(config, templates.length + 2 * margin)
    pool, _ = fine_timing.interference_pool(seconds, margin, config)
    psd = fine_timing.pool_psd(pool)
    curves = {}
    for n in FRAMES:
        centre = -17.0 - 10 * math.log10(n / 10)
        grid = np.arange(centre - 8, centre + 8.1, 2.0)
        args = Namespace(trials=trials, frames=n, margin=margin, seed=n)
        points = fine_timing.run("simulator", pool, psd, args, templates, longer,
                                 {"ml": fine_timing.ESTIMATORS["ml_whittle"]}, grid)
        ratio = np.array([p["ml"]["rmse_samples"] / p["crlb_samples"] for p in points])
        curves[n] = {"snr_db": grid.tolist(), "rmse_samples": [p["ml"]["rmse_samples"] for p in points],
                     "crlb_samples": [p["crlb_samples"] for p in points],
                     "snr_for_2crlb_db": crossing(grid, -ratio, -RMSE_OVER_CRLB)}
    return curves


def snr_curves(frames: int) -> list[dict]:
    """Per-frame SNR vs received power per RE, per front end, bandwidth and load."""
    rows = []
    total = len(FRONTENDS) * len(BANDWIDTHS) * len(LOADS) * len(POWERS_DBM)
    with tqdm(total=total, desc="SNR vs received power") as bar:
        for name, (_, config) in FRONTENDS.items():
            for bandwidth in BANDWIDTHS:
                for load in LOADS:
                    snr = []
                    for power in POWERS_DBM:
                        snr.append(measure(bandwidth, load, float(power), frames, config)["snr_db"])
                        bar.update()
                    rows.append({"frontend": name, "bandwidth_mhz": bandwidth, "load": load, "snr_db": snr})
    return rows


def heard_range_m(model: str, los: bool, power_dbm: float) -> float:
    """Distance (m) at which the median path loss brings the scenario's EIRP per RE to ``power_dbm``."""
    height, eirp = SCENARIOS[model]

    def loss(d2d: float) -> float:
        d3d = math.hypot(d2d, height - UE_HEIGHT_M)
        return float(path_loss_db(model, los, d2d, d3d, height, UE_HEIGHT_M, CARRIER_HZ))

    budget = eirp - power_dbm
    if math.isnan(power_dbm) or loss(10.0) > budget:
        return 0.0
    if loss(MAX_RANGE_M) <= budget:
        return MAX_RANGE_M
    low, high = 10.0, MAX_RANGE_M
    for _ in range(60):  # path loss grows with distance
        mid = math.sqrt(low * high)
        low, high = (mid, high) if loss(mid) <= budget else (low, mid)
    return low


def chain_pd(config: FrontendConfig, bandwidth: float, load: float, power_dbm: float, n: int, stacks: int,
             seed: int) -> float:
    """Pd of the whole chain: one cell through the simulator, SyncStage with a 20-PCI database;
    a stack counts when it holds the PCI (confirmed or tentative) within 1 sample of its code."""
    pci, delay_s = 301, 1.5e-6
    gain = math.sqrt(10 ** ((power_dbm - 30) / 10) / EIRP_PER_RE_W)
    emitter = Emitter(CellConfig(pci=pci, bandwidth_mhz=bandwidth, load=load), CARRIER_HZ, EIRP_PER_RE_W, 0.0, 0.0, "A")
    sim = EnvelopeSimulator([emitter], FixedChannel(Paths([delay_s], [gain], [0.0])), config, seed=seed)
    others = np.random.default_rng(seed).choice(np.setdiff1d(np.arange(504), [pci]), 19, replace=False)
    towers = parse_tower_database({"name": "link budget", "sites": [
        {"name": f"S{k}", "latitude_deg": 0.0, "longitude_deg": 0.001 * k, "height_m": 25.0,
         "cells": [{"pci": int(p), "earfcn": 2000}]} for k, p in enumerate([pci, *others.tolist()])]})
    stage = SyncStage(config, SyncConfig(stack=StackConfig(n_frames=n)), towers)
    frame = round(config.adc_rate_hz * FRAME_SECONDS)
    truth = float(sim.sample_index(sync_code_offset_seconds() + delay_s)) % frame
    hits = seen = 0
    for chunk in sim.stream((stacks * n + 1) * FRAME_SECONDS):
        for result in stage.process(chunk):
            seen += 1
            hits += any(c.pci == pci and cell_search.near(c.code_position % frame, truth, frame)
                        for c in result.cells + result.tentative)
    return hits / max(seen, 1)


def plot(document: dict, path: Path) -> None:
    fig, axes = plt.subplots(1, 4, figsize=(20, 4.4))
    for n, curve in document["detection"].items():
        axes[0].plot(curve["snr_db"], curve["pd"], "o-", ms=3, label=f"{n} frames")
        timing = document["timing"][n]
        axes[1].semilogy(timing["snr_db"], np.array(timing["rmse_samples"]) / np.array(timing["crlb_samples"]),
                         "o-", ms=3, label=f"{n} frames")
    axes[0].axhline(PD_TARGET, color="grey", lw=0.6)
    axes[0].set(xlabel="per-frame sync SNR (dB)", ylabel="Pd (right PCI, within 1 sample)",
                title="detection, 20-PCI tower database")
    axes[1].axhline(RMSE_OVER_CRLB, color="grey", lw=0.6)
    axes[1].set(xlabel="per-frame sync SNR (dB)", ylabel="ML RMSE / CRLB", title="timing")
    for row in document["snr_vs_power"]:
        if row["frontend"] == "default" and row["load"] == 0.6:
            axes[2].plot(document["powers_dbm"], row["snr_db"], label=f"{row['bandwidth_mhz']:g} MHz")
    for n, curve in document["detection"].items():
        need = max(curve["snr_for_pd90_db"], document["timing"][n]["snr_for_2crlb_db"])
        axes[2].axhline(need, color="grey", lw=0.5, ls=":")
        axes[2].text(document["powers_dbm"][0], need, f"N={n}", fontsize=7, va="bottom")
    axes[2].set(xlabel="received power per RE (dBm)", ylabel="per-frame sync SNR (dB)",
                title="default front end, load 0.6 (dotted: needed)", ylim=(-50, 20))
    table = [r for r in document["table"] if r["frontend"] == "default" and r["load"] == 0.6]
    for bandwidth in BANDWIDTHS:
        rows = [r for r in table if r["bandwidth_mhz"] == bandwidth]
        axes[3].plot([r["frames"] for r in rows], [r["range_m"]["UMa NLOS"] for r in rows], "o-",
                     label=f"{bandwidth:g} MHz, UMa NLOS")
    axes[3].set(xscale="log", xlabel="stacked frames N", ylabel="heard range (m)",
                title="default front end, load 0.6")
    for ax in axes:
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=100, help="trials per SNR point (detection and timing)")
    parser.add_argument("--snr-frames", type=int, default=20, help="frames per SNR-vs-power measurement")
    parser.add_argument("--check-stacks", type=int, default=30, help="stacks per point of the whole-chain check")
    parser.add_argument("--seconds", type=float, default=4.0, help="simulated interference for the trials")
    args = parser.parse_args()
    started = time.time()
    rng = np.random.default_rng(2027)
    detection = detection_curves(args.trials, args.seconds, rng)
    timing = timing_curves(args.trials, max(args.seconds, 6.0))
    snr_rows = snr_curves(args.snr_frames)

    needed = {n: max(detection[n]["snr_for_pd90_db"], timing[n]["snr_for_2crlb_db"]) for n in FRAMES}
    table = []
    for row in snr_rows:
        for n in FRAMES:
            power = crossing(POWERS_DBM, np.array(row["snr_db"]), needed[n])
            ranges = {f"{model} {'LOS' if los else 'NLOS'}": heard_range_m(model, los, power)
                      for model in SCENARIOS for los in (True, False)}
            table.append({"frontend": row["frontend"], "bandwidth_mhz": row["bandwidth_mhz"], "load": row["load"],
                          "frames": n, "needed_snr_db": needed[n], "heard_power_dbm": power, "range_m": ranges})

    checks = []
    default = FRONTENDS["default"][1]
    for n in (10, 50):
        predicted = next(r["heard_power_dbm"] for r in table if r["frontend"] == "default"
                         and r["bandwidth_mhz"] == 10.0 and r["load"] == 0.6 and r["frames"] == n)
        for delta in (-3.0, 0.0, 3.0):
            pd = chain_pd(default, 10.0, 0.6, predicted + delta, n, args.check_stacks, seed=7 + n)
            checks.append({"frames": n, "power_dbm": predicted + delta, "offset_db": delta, "pd": pd})
            print(f"whole chain, 10 MHz, load 0.6, {n} frames, {predicted + delta:6.1f} dBm/RE "
                  f"({delta:+.0f} dB from the predicted heard power): Pd {pd:.2f}")

    print(f"\nper-frame SNR needed (Pd >= {PD_TARGET:.0%} with a tower database; ML RMSE <= {RMSE_OVER_CRLB:g} CRLB):")
    for n in FRAMES:
        print(f"  N = {n:3d}: detection {detection[n]['snr_for_pd90_db']:6.1f} dB, timing "
              f"{timing[n]['snr_for_2crlb_db']:6.1f} dB (false alarms {detection[n]['pfa_per_stack']:.3f} per stack)")
    print("\nheard power per RE (dBm) and UMa NLOS / UMi NLOS range (m), load 0.6:")
    print(f"{'front end':12s} {'MHz':>5s} " + " ".join(f"{'N=' + str(n):>22s}" for n in FRAMES))
    for name in FRONTENDS:
        for bandwidth in BANDWIDTHS:
            cells = []
            for n in FRAMES:
                r = next(r for r in table if r["frontend"] == name and r["bandwidth_mhz"] == bandwidth
                         and r["load"] == 0.6 and r["frames"] == n)
                ranges = r["range_m"]
                cells.append(f"{r['heard_power_dbm']:7.1f} {ranges['UMa NLOS']:6.0f}/{ranges['UMi NLOS']:5.0f}")
            print(f"{name:12s} {bandwidth:5.1f} " + " ".join(f"{c:>22s}" for c in cells))

    OUT.mkdir(parents=True, exist_ok=True)
    document = {
        "description": __doc__.split("\n\n", 1)[1].rsplit("\n\nRun:", 1)[0],
        "frontends": {name: label for name, (label, _) in FRONTENDS.items()},
        "scenarios": {model: {"bs_height_m": h, "eirp_per_re_dbm": e, "ue_height_m": UE_HEIGHT_M,
                              "carrier_hz": CARRIER_HZ} for model, (h, e) in SCENARIOS.items()},
        "trials_per_point": args.trials,
        "powers_dbm": POWERS_DBM.tolist(),
        "detection": {str(n): c for n, c in detection.items()},
        "timing": {str(n): c for n, c in timing.items()},
        "needed_snr_db": {str(n): v for n, v in needed.items()},
        "snr_vs_power": snr_rows,
        "table": table,
        "whole_chain_check": checks,
        "wall_s": time.time() - started,
    }
    (OUT / "link_budget.json").write_text(json.dumps(document, indent=2))
    with (OUT / "link_budget.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["frontend", "bandwidth_mhz", "load", "frames", "needed_snr_db", "heard_power_dbm",
                         *[f"range_m_{k.replace(' ', '_')}" for k in table[0]["range_m"]]])
        for r in table:
            writer.writerow([r["frontend"], r["bandwidth_mhz"], r["load"], r["frames"], f"{r['needed_snr_db']:.1f}",
                             f"{r['heard_power_dbm']:.1f}", *[f"{v:.0f}" for v in r["range_m"].values()]])
    plot(document, OUT / "link_budget.png")
    print(f"\nwrote {OUT / 'link_budget.json'}, .csv and .png ({time.time() - started:.0f} s)")


if __name__ == "__main__":
    main()
