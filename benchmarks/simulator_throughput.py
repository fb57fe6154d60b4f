"""Simulator throughput: simulated seconds per wall-clock second on the 4-cell campus scenario.

The full chain (OFDM frames of 4 cells -> TDL channels -> two carrier clusters at 15.36 MS/s
-> square law -> video filter -> clock -> ADC), run in 1 s work units by 1..N processes. The
median of ``--repeats`` runs is printed; the result is bit-identical for any worker count.

Run:  .venv/bin/python benchmarks/simulator_throughput.py [--seconds 4] [--repeats 3]
Writes docs/results/simulator_throughput.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from deepsync.frontend.simulator import EnvelopeSimulator
from deepsync.twin import build_twin
from deepsync.twin.scenario import load_scenario

REPO = Path(__file__).resolve().parents[1]
SCENARIO = REPO / "config" / "scenarios" / "campus.yaml"


def run(seconds: float, workers: int) -> tuple[float, bytes]:
    twin = build_twin(load_scenario(SCENARIO))
    simulator = EnvelopeSimulator(twin.emitters, twin.channel, twin.frontend, twin.scenario.seed)
    started = time.perf_counter()
    codes = np.concatenate([chunk.samples for chunk in simulator.stream(seconds, workers=workers)])
    return time.perf_counter() - started, codes.tobytes()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    cores = os.cpu_count() or 1
    results = {}
    reference = None
    for workers in sorted({1, cores}):
        walls = []
        for _ in range(args.repeats):
            wall, codes = run(args.seconds, workers)
            reference = reference or codes
            assert codes == reference, "results must not depend on the number of workers"
            walls.append(wall)
        speed = args.seconds / statistics.median(walls)
        results[workers] = speed
        print(f"{workers} process(es): {speed:.2f} simulated s per wall s "
              f"(median of {args.repeats} x {args.seconds:g} s; 1 min of data in {60 / speed:.0f} s)")
    out = REPO / "docs" / "results" / "simulator_throughput.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "scenario": str(SCENARIO.relative_to(REPO)),
        "seconds_per_run": args.seconds,
        "simulated_seconds_per_wall_second": {str(k): v for k, v in results.items()},
        "cpu_count": cores,
        "machine": platform.processor() or platform.machine(),
    }, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
