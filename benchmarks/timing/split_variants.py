"""``evaluate-timing``'s side by side on variants of the network's test split: the same scenes
(the shipped dataset config: its bandwidths, loads, other cells and carriers, clocks, coarse
errors, seeds) made again with one thing changed. Each split is made if it is missing
(resumable, 2 workers), then evaluated:

* ``clean``: ``channel: clean``, every cell one path of constant power. The shipped split's
  channels are TR 38.901 TDL realisations; even its LOS profiles (TDL-D/E) carry scattered taps
  that move the envelope's peak off the first path by more than the bound, so there every
  estimator's RMSE exceeds twice the bound in every SNR bin. Here the Cramer-Rao bound is an
  estimator's reach and the threshold and high-SNR criteria mean what they say (about 2 minutes).
* ``frames``: examples of 20 frames (the training data holds 12), evaluated on their first 2,
  5, 10 and 20. The network was trained on 4-12 frames (the timing stage hands it nothing else:
  more frames fall back to ML), so 20 says whether its frame average carries beyond them. One
  frame is not evaluated: every estimator here measures its noise from the differences between
  frames (about 6 minutes).
* ``ml_frame``: each example's mean frames kept (``frame_means``: the same seeds, so the same
  2048 examples as ``data/timing``'s test split; 470 MB, about 2 minutes), so that the timing
  stage's default, ``ml_frame``, which fits the cell's whole known frame (codes and CRS, about
  10 dB more template at 10 MHz), runs beside the estimators of the code windows (4 of a frame's
  140 OFDM symbols).
* ``ml_frame_clean``: ``ml_frame`` with the direct path alone.

Printed: per frame count, each shown estimator's median / p90 / RMSE / share within 1 sigma;
at 10 frames, its thresholds (the highest SNR bin whose RMSE exceeds 2x the median bound, and
whose errors beyond a sample exceed 10 %), multipath RMSE and high-SNR RMSE, and how many SNR
bins have their sigma in band.

Run:  .venv/bin/python benchmarks/timing/split_variants.py VARIANT [--workers 2]
Writes docs/results/timing_network/<clean|frames|ml_frame|ml_frame/clean>/timing.json and
timing.png; the split goes to data/timing_<variant>.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import NamedTuple

from deepsync.eval.timing import evaluate_timing, side_by_side, threshold_text
from deepsync.training.dataset import Channel, generate
from deepsync.training.train import load_run_config

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "config" / "timing" / "timing_net.yaml"
RESULTS = REPO / "docs" / "results" / "timing_network"


class Variant(NamedTuple):
    data: Path  # where the split is made
    out: Path  # where timing.json and timing.png go
    changes: dict  # to the shipped dataset config
    frames: tuple[int, ...]  # evaluated on each example's first this many frames
    shown: tuple[str, ...]  # the estimators printed


ML_FRAME = (5, 10, 12)
VARIANTS = {
    "clean": Variant(REPO / "data" / "timing_clean", RESULTS / "clean", {"channel": Channel.CLEAN},
                     (5, 10, 12), side_by_side(with_frame=False)),
    "frames": Variant(REPO / "data" / "timing_frames", RESULTS / "frames", {"max_frames": 20},
                      (2, 5, 10, 20), ("network", "network_ml", "ml", "parabolic")),
    "ml_frame": Variant(REPO / "data" / "timing_ml_frame", RESULTS / "ml_frame",
                        {"frame_means": ML_FRAME, "channel": Channel.TDL}, ML_FRAME,
                        ("ml_frame", "network", "network_ml", "ml")),
    "ml_frame_clean": Variant(REPO / "data" / "timing_ml_frame_clean", RESULTS / "ml_frame" / "clean",
                              {"frame_means": ML_FRAME, "channel": Channel.CLEAN}, ML_FRAME,
                              ("ml_frame", "network", "network_ml", "ml")),
}


def report(summary: dict, shown: tuple[str, ...]) -> None:
    print(f"{'frames':>6s} {'estimator':>10s} {'median':>7s} {'p90':>7s} {'RMSE':>7s} {'in 1 sigma':>10s}")
    for frames, result in summary["frames"].items():
        for name in shown:
            row = result["all"][name]
            print(f"{frames:>6s} {name:>10s} {row['median']:7.2f} {row['p90']:7.2f} {row['rmse']:7.2f} "
                  f"{100 * row['within_1_sigma']:9.0f}%")
    headline = summary["headline"]
    print(f"10 frames: {'outliers > 10 % on LOS up to':>28} {'RMSE > 2 CRLB up to':>20} {'RMSE -10..0 dB':>15} "
          f"{'LOS RMSE from 0 dB':>19} {'bins within 1 sigma in band':>28}")
    for name in shown:
        threshold = headline["threshold_snr_db_los"][name]
        verdicts = headline["within_1_sigma_snr_bins"][name]
        print(f"{name:>10s} {threshold_text(threshold['outliers_over_10_percent']):>28} "
              f"{threshold_text(threshold['rmse_over_2_crlb']):>20} "
              f"{headline['multipath_rmse_-10_to_0_db'][name]:15.2f} "
              f"{headline['high_snr_los_rmse_from_0_db'][name]:19.3f} "
              f"{verdicts['in_band']:>24d} of {verdicts['bins']}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("variant", choices=list(VARIANTS), help="which test split to make and evaluate")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    variant = VARIANTS[args.variant]
    run = load_run_config(CONFIG)
    generate(variant.data, {"test": run.training.test_shards}, dataclasses.replace(run.dataset, **variant.changes),
             args.workers)
    summary = evaluate_timing(variant.data, variant.out, frames=variant.frames)
    print(f"{args.variant}: {summary['examples']} examples")
    report(summary, variant.shown)
    print(f"wrote {variant.out / 'timing.json'}")


if __name__ == "__main__":
    main()
