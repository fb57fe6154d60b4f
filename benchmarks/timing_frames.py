"""Timing against the number of stacked frames, up to 20: every estimator on a test split whose
examples hold 20 frames (the training data holds 12).

Makes the split if it is missing (the shipped dataset config, ``max_frames`` 20; resumable,
2 workers), then runs ``evaluate-timing``'s side by side on its first 2, 5, 10 and 20 frames.
The network was trained on 4-12 frames (the timing stage hands it nothing else: more frames
fall back to ML), so 20 frames says whether its frame average carries beyond them. One frame is
not evaluated: every estimator here measures its noise from the differences between frames.

Run:  .venv/bin/python benchmarks/timing_frames.py [--workers 2]
Writes docs/results/timing_network/frames/timing.json and timing.png; the split goes to
data/timing_frames (about 6 minutes on this machine's 2 cores).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from deepsync.eval.timing import evaluate_timing
from deepsync.training.dataset import generate
from deepsync.training.train import load_run_config

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config" / "timing" / "timing_net.yaml"
DATA = REPO / "data" / "timing_frames"
OUT = REPO / "docs" / "results" / "timing_network" / "frames"
FRAMES = (2, 5, 10, 20)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    run = load_run_config(CONFIG)
    dataset = dataclasses.replace(run.dataset, max_frames=max(FRAMES))
    generate(DATA, {"test": run.training.test_shards}, dataset, args.workers)
    summary = evaluate_timing(DATA, OUT, frames=FRAMES)
    print(f"{'frames':>6s} {'estimator':>10s} {'median':>7s} {'p90':>7s} {'RMSE':>7s} {'in 1 sigma':>10s}")
    for frames, result in summary["frames"].items():
        for name in ("network", "network_ml", "ml", "parabolic"):
            row = result["all"][name]
            print(f"{frames:>6s} {name:>10s} {row['median']:7.2f} {row['p90']:7.2f} {row['rmse']:7.2f} "
                  f"{100 * row['within_1_sigma']:9.0f}%")
    print(json.dumps(summary["headline"], indent=1))
    print(f"wrote {OUT / 'timing.json'}")


if __name__ == "__main__":
    main()
