"""Speed of fusion: one snapshot solve of 6 sites, one tracker update with 1 site and with 3.

Synthetic stacks along a straight walk (1.4 m/s) among 6 sites 300-1100 m away: ranges with
15 m of Gaussian noise and a 15 ppm receiver clock, each arrival at its own time in a 100 ms
stack, modulo one frame. ``solve_snapshot`` is timed on stacks of all 6 sites (target: 1 ms
median); ``Tracker.update`` once started and settled (10 s of 3-site stacks), on stacks of 1
site (target: 0.2 ms) and of 3 sites, and on 1-site stacks with site clock states (6 sites:
18 states). Each update predicts to every arrival, updates with it and predicts to the stack's
end. One core: BLAS and OpenMP pinned to one thread before numpy loads. Prints the median and
90th percentile of --repeats calls.

Run:  .venv/bin/python benchmarks/speed/fusion_speed.py [--repeats 2000]
Writes docs/results/fusion_speed.json.
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"  # before numpy loads: its BLAS reads these once

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from deepsync.fusion.anchors import FRAME_RANGE_M, SiteArrival  # noqa: E402
from deepsync.fusion.snapshot import solve_snapshot  # noqa: E402
from deepsync.fusion.tracker import Tracker, TrackerConfig  # noqa: E402
from deepsync.types import SPEED_OF_LIGHT_M_S, Fix  # noqa: E402

OUT = Path(__file__).resolve().parents[2] / "docs" / "results" / "fusion_speed.json"
SITES = np.array([[600.0, 150.0, 30.0], [-250.0, 500.0, 25.0], [-700.0, -400.0, 40.0],
                  [200.0, -800.0, 20.0], [900.0, 700.0, 35.0], [-300.0, -250.0, 15.0]])
SIGMA_M = 15.0
CLOCK_RATE = 15e-6
STACK_S = 0.1


class Walk:
    """Stacks of site arrivals along a straight walk, one stack after the other."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.bias = self.rng.uniform(0, FRAME_RANGE_M)
        self.k = 0

    def stack(self, n_sites: int) -> tuple[list[SiteArrival], float]:
        """The next stack: ``n_sites`` sites drawn at random, and the stack's end time."""
        start = self.k * STACK_S
        self.k += 1
        arrivals = []
        chosen = sorted(self.rng.choice(len(SITES), n_sites, replace=False))
        for i, t in zip(chosen, np.sort(self.rng.uniform(start, start + STACK_S, n_sites))):
            position = np.array([1.0, 1.0, 0.0]) * t + np.array([0.0, 0.0, 1.5])
            rho = (np.linalg.norm(position - SITES[i]) + self.bias + CLOCK_RATE * SPEED_OF_LIGHT_M_S * t
                   + SIGMA_M * self.rng.standard_normal())
            arrivals.append(SiteArrival("ABCDEF"[i], SITES[i], float(t), float(rho % FRAME_RANGE_M), SIGMA_M, (1,)))
        return arrivals, start + STACK_S


def percentiles(times_ms: list[float]) -> dict[str, float]:
    times_ms = sorted(times_ms)
    return {"median_ms": statistics.median(times_ms), "p90_ms": times_ms[int(0.9 * (len(times_ms) - 1))]}


def time_snapshot(repeats: int) -> dict[str, float]:
    walk = Walk(1)
    stacks = [walk.stack(6)[0] for _ in range(repeats)]
    solve_snapshot(stacks[0], clock_rate=CLOCK_RATE)  # scipy's first call loads what it needs
    times = []
    for arrivals in stacks:
        started = time.perf_counter()
        fix = solve_snapshot(arrivals, clock_rate=CLOCK_RATE)
        times.append((time.perf_counter() - started) * 1e3)
        assert isinstance(fix, Fix), fix
    return percentiles(times)


def time_tracker(repeats: int, n_sites: int, config: TrackerConfig) -> dict[str, float]:
    walk = Walk(2)
    tracker = Tracker(config)
    for k in range(100):  # start and settle: 10 s of 3-site stacks
        arrivals, end = walk.stack(3)
        tracker.update(arrivals, k, end, CLOCK_RATE)
    stacks = [walk.stack(n_sites) for _ in range(repeats)]
    times = []
    for k, (arrivals, end) in enumerate(stacks):
        started = time.perf_counter()
        fix = tracker.update(arrivals, k, end, CLOCK_RATE)
        times.append((time.perf_counter() - started) * 1e3)
        assert isinstance(fix, Fix), fix
    return percentiles(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2000)
    args = parser.parse_args()
    results = {
        "snapshot_6_sites": time_snapshot(args.repeats),
        "tracker_1_site": time_tracker(args.repeats, 1, TrackerConfig()),
        "tracker_3_sites": time_tracker(args.repeats, 3, TrackerConfig()),
        "tracker_1_site_site_clocks": time_tracker(args.repeats, 1, TrackerConfig(site_clocks=True)),
    }
    labels = {
        "snapshot_6_sites": "solve_snapshot, 6 sites (target 1 ms)",
        "tracker_1_site": "Tracker.update, 1 site (target 0.2 ms)",
        "tracker_3_sites": "Tracker.update, 3 sites",
        "tracker_1_site_site_clocks": "Tracker.update, 1 site, site clocks (18 states)",
    }
    for key, label in labels.items():
        median, p90 = results[key]["median_ms"], results[key]["p90_ms"]
        print(f"{label:50s}: {median:6.3f} ms median, {p90:6.3f} ms p90, one core")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps({"repeats": args.repeats, "targets_ms": {"snapshot_6_sites": 1.0, "tracker_1_site": 0.2},
                               **results}, indent=2))
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
