"""The timing stage's default, ``ml_frame``, on the network's test split: the side by side of
``evaluate-timing`` with the whole-frame ML beside the estimators of the code windows.

The network and ML see a cell's code windows (4 of a frame's 140 OFDM symbols); ``ml_frame``
fits the cell's whole known frame (codes and CRS) in the stack's mean frame, about 10 dB more
template at 10 MHz. This makes the test split of the shipped dataset config again with each
example's mean frames kept (``frame_means``: the same seeds, so the same 2048 examples as
``data/timing``'s test split; 470 MB, about 2 minutes on this machine's 2 cores, resumable) and
runs the side by side at 5, 10 and 12 frames, ``ml_frame`` through the timing stage itself.

``--channel clean``: the same scenes with the direct path alone (``benchmarks/clean_channel.py``),
where the Cramer-Rao bound is the reach and the threshold means what it says.

Run:  .venv/bin/python benchmarks/timing_ml_frame.py [--channel tdl|clean] [--workers 2]
Writes docs/results/timing_network/ml_frame/timing.json and timing.png (clean: ml_frame/clean/);
the split goes to data/timing_ml_frame (clean: data/timing_ml_frame_clean).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from deepsync.eval.timing import evaluate_timing, threshold_text
from deepsync.training.dataset import Channel, generate
from deepsync.training.train import load_run_config

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config" / "timing" / "timing_net.yaml"
DATA = REPO / "data" / "timing_ml_frame"
OUT = REPO / "docs" / "results" / "timing_network" / "ml_frame"
FRAMES = (5, 10, 12)
SHOWN = ("ml_frame", "network", "network_ml", "ml")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channel", type=Channel, choices=list(Channel), default=Channel.TDL)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    run = load_run_config(CONFIG)
    clean = args.channel is Channel.CLEAN
    data, out = (DATA.with_name(DATA.name + "_clean"), OUT / "clean") if clean else (DATA, OUT)
    generate(data, {"test": run.training.test_shards},
             dataclasses.replace(run.dataset, frame_means=FRAMES, channel=args.channel), args.workers)
    summary = evaluate_timing(data, out, frames=FRAMES)
    print(f"{'frames':>6s} {'estimator':>10s} {'median':>7s} {'p90':>7s} {'RMSE':>7s} {'in 1 sigma':>10s}")
    for frames, result in summary["frames"].items():
        for name in SHOWN:
            row = result["all"][name]
            print(f"{frames:>6s} {name:>10s} {row['median']:7.2f} {row['p90']:7.2f} {row['rmse']:7.2f} "
                  f"{100 * row['within_1_sigma']:9.0f}%")
    ten = summary["frames"]["10"]
    print("10 frames, by per-frame SNR (dB): RMSE / outliers beyond a sample / within +-1 sigma")
    for row in ten["by_snr"]:
        cells = "  ".join(f"{name} {row[name]['rmse']:5.2f} / {100 * row[name]['outliers']:3.0f}% / "
                          f"{100 * row[name]['within_1_sigma']:3.0f}%" for name in SHOWN if row[name].get("n"))
        print(f"{row['snr_db'][0]:5.0f}..{row['snr_db'][1]:<3.0f} n {row['ml']['n']:4d}  {cells}")
    headline = summary["headline"]
    print(f"10 frames: {'outliers > 10 % on LOS up to':>28} {'RMSE > 2 CRLB up to':>20} {'RMSE -10..0 dB':>15} "
          f"{'LOS RMSE from 0 dB':>19} {'bins within 1 sigma in band':>28}")
    for name in SHOWN:
        threshold = headline["threshold_snr_db_los"][name]
        verdicts = headline["within_1_sigma_snr_bins"][name]
        print(f"{name:>10s} {threshold_text(threshold['outliers_over_10_percent']):>28} "
              f"{threshold_text(threshold['rmse_over_2_crlb']):>20} "
              f"{headline['multipath_rmse_-10_to_0_db'][name]:15.2f} "
              f"{headline['high_snr_los_rmse_from_0_db'][name]:19.3f} "
              f"{verdicts['in_band']:>24d} of {verdicts['bins']}")
    print(f"wrote {out / 'timing.json'}")


if __name__ == "__main__":
    main()
