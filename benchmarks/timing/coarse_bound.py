"""Classical timing when the code lock may be up to 40 samples off: a test split cut with
windows wide enough for it, beside the shipped one (+-10), by the coarse error's size.

Makes the splits if they are missing (the shipped dataset config as it is: windows of +-10
samples, coarse errors up to 8; and with ``window_margin`` 42, ``max_coarse_error`` 40;
resumable, 2 workers), then times every example's first 10 frames with the classical
estimators of ``evaluate-timing`` and bins their errors against the true first path by how far
the coarse code start was (0-5, 6-10, 11-20, 21-40 samples, and all), for every example and for
those at -10 dB per frame or more (above ML's threshold with 10 frames). The shipped network is
not in it: it takes the sync stage's 296-sample windows (+-10 samples), so a bound of 40 needs
a model with a wider input, trained on such windows.

Run:  .venv/bin/python benchmarks/timing/coarse_bound.py [--workers 2]
Writes docs/results/timing_network/coarse_bound.json; the wide split goes to
data/timing_coarse40 (about 4 minutes on this machine's 2 cores), the shipped one to data/timing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from deepsync.eval.timing import error_stats, of_input, run_estimators
from deepsync.timing.registry import Input
from deepsync.training.dataset import generate, load_split
from deepsync.training.train import load_run_config

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "config" / "timing" / "timing_net.yaml"
SPLITS = {"margin 10": (REPO / "data" / "timing", {}),
          "margin 42": (REPO / "data" / "timing_coarse40", {"window_margin": 42, "max_coarse_error": 40})}
OUT = REPO / "docs" / "results" / "timing_network" / "coarse_bound.json"
FRAMES = 10
BINS = ((0, 5), (6, 10), (11, 20), (21, 40), (0, 40))  # |coarse error|, whole samples, both ends included
CLASSICAL = tuple(e.name for e in of_input(Input.WINDOWS))  # the network does not take these windows
STRONG_DB = -10.0  # per-frame SNR from which a group counts as above ML's threshold


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    run = load_run_config(CONFIG)
    summary: dict = {"frames": FRAMES, "splits": {}}
    for split, (root, changes) in SPLITS.items():
        generate(root, {"test": run.training.test_shards}, dataclasses.replace(run.dataset, **changes), args.workers)
        data = load_split(root, "test")
        results = run_estimators(data, FRAMES, None)  # the network does not take these windows
        errors = {name: results[f"{name}_error"] for name in CLASSICAL}
        distance = np.abs(data["coarse_error"])
        groups = {"all": np.ones(len(distance), dtype=bool), f"snr >= {STRONG_DB:g} dB": data["snr_db"] >= STRONG_DB}
        summary["splits"][split] = {group: {
            f"{low}-{high}": {name: error_stats(errors[name][selected & (distance >= low) & (distance <= high)])
                              for name in CLASSICAL}
            for low, high in BINS if low <= distance.max()} for group, selected in groups.items()}
    OUT.write_text(json.dumps(summary, indent=1))
    for split, groups in summary["splits"].items():
        for group, rows in groups.items():
            print(f"{split}, {group}: median / RMSE / beyond a sample, by |coarse error|")
            for span, row in rows.items():
                cells = "  ".join(f"{name} {s['median']:.2f} / {s['rmse']:.2f} / {100 * s['outliers']:.0f} %"
                                  for name, s in row.items() if s["n"])
                print(f"  {span:>5s} (n {row['ml']['n']:4d}): {cells}")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
