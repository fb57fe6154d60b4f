"""Simulator throughput, this code beside a baseline commit's, on one core, in one run.

Simulated seconds per wall second and per CPU second (one process, workers=1) of the 4-cell
campus scenario (3 sites, 2 carriers, static) and the urban walk (7 sites, 11 cells, 2
carriers, route_urban.yaml), each run in its own process, the baseline's and this code's
interleaved, the median of ``--repeats``; the baseline is the code at ``--baseline`` (default:
the simulator before its rewrite for speed), taken from git. On a machine shared with other
work the CPU seconds are the steadier measure. ``--profile`` adds where this code's CPU time
goes, stage by stage.

Run:  .venv/bin/python benchmarks/speed/simulator_throughput.py [--seconds 3] [--repeats 3] [--profile]
Writes docs/results/simulator_throughput.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tarfile
import tempfile
from io import BytesIO
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
BASELINE = "15941dd"  # the simulator before it was rewritten for speed
SCENARIOS = {"campus": "config/scenarios/campus.yaml", "urban walk": "config/scenarios/route_urban.yaml"}

RUN = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
from deepsync.frontend.simulator import EnvelopeSimulator
from deepsync.twin import build_twin
from deepsync.twin.scenario import load_scenario
twin = build_twin(load_scenario(sys.argv[2]))
simulator = EnvelopeSimulator(twin.emitters, twin.channel, twin.frontend, twin.scenario.seed)
wall, cpu = time.perf_counter(), time.process_time()
for chunk in simulator.stream(float(sys.argv[3]), workers=1):
    pass
print(json.dumps({"wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu}))
"""

# where this code's time goes: (stage, class or module, function); the time of nested stages
# is counted once, in the innermost
STAGES = [
    ("frame content (scheduler, QAM)", "deepsync.lte.frame:FrameGenerator", "grid"),
    ("channel responses", "deepsync.frontend.render:GroupRenderer", "_response"),
    ("channel paths (twin)", "deepsync.twin.statistical_channel:StatisticalChannel", "paths"),
    ("IFFT per symbol", "scipy.fft", "ifft"),
    ("cyclic prefixes", "deepsync.frontend.render:GroupRenderer", "_with_prefixes"),
    ("weighting, rotation (render)", "deepsync.frontend.render:GroupRenderer", "render"),
    ("square law", "deepsync.frontend.square_law:ClusterDetector", "power"),
    ("video filter FFTs", "scipy.fft", "rfft"),
    ("folding, inverse FFTs", "deepsync.frontend.square_law:Detector", "output"),
    ("detector noise", "deepsync.frontend.square_law:DetectorNoise", "samples"),
    ("AC coupling", "deepsync.frontend.adc:AdcStage", "couple"),
    ("ADC noise, quantisation", "deepsync.frontend.adc:AdcStage", "quantize"),
]

PROFILE = r"""
import functools, importlib, json, sys, time
from collections import defaultdict
stages, seconds, scenario = json.loads(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
spent, stack = defaultdict(float), []
def timed(function, name):
    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        start = time.process_time(); stack.append(0.0)
        try:
            return function(*args, **kwargs)
        finally:
            took, inner = time.process_time() - start, stack.pop()
            spent[name] += took - inner
            if stack:
                stack[-1] += took
    return wrapper
for name, where, attribute in stages:
    module, _, owner = where.partition(":")
    target = importlib.import_module(module)
    target = getattr(target, owner) if owner else target
    setattr(target, attribute, timed(getattr(target, attribute), name))
from deepsync.frontend.simulator import EnvelopeSimulator
from deepsync.twin import build_twin
from deepsync.twin.scenario import load_scenario
twin = build_twin(load_scenario(scenario))
simulator = EnvelopeSimulator(twin.emitters, twin.channel, twin.frontend, twin.scenario.seed)
start = time.process_time()
for chunk in simulator.stream(seconds, workers=1):
    pass
total = time.process_time() - start
spent["other"] = total - sum(spent.values())
print(json.dumps({"total": total, "stages": spent}))
"""


def baseline_tree(revision: str, into: Path) -> Path:
    """The baseline's core package, from git, under ``into``."""
    archive = subprocess.run(["git", "-C", str(REPO), "archive", revision, "src/deepsync/deepsync"],
                             capture_output=True, check=True).stdout
    with tarfile.open(fileobj=BytesIO(archive)) as tar:
        tar.extractall(into, filter="data")
    return into / "src" / "deepsync"


def run(tree: Path, scenario: str, seconds: float) -> dict:
    out = subprocess.run([sys.executable, "-c", RUN, str(tree), str(REPO / scenario), str(seconds)],
                         capture_output=True, text=True, check=True, env={**os.environ, "OMP_NUM_THREADS": "1",
                                                                          "OPENBLAS_NUM_THREADS": "1"})
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--baseline", default=BASELINE, help="git revision to compare with")
    parser.add_argument("--profile", action="store_true", help="also where this code's CPU time goes")
    args = parser.parse_args()
    results = {}
    with tempfile.TemporaryDirectory() as scratch:
        trees = {"baseline": baseline_tree(args.baseline, Path(scratch)), "this code": REPO / "src" / "deepsync"}
        for name, scenario in SCENARIOS.items():
            runs = {version: [] for version in trees}
            for _ in range(args.repeats):
                for version, tree in trees.items():
                    runs[version].append(run(tree, scenario, args.seconds))
            speeds = {version: {"per_wall_second": args.seconds / statistics.median(r["wall"] for r in got),
                                "per_cpu_second": args.seconds / statistics.median(r["cpu"] for r in got)}
                      for version, got in runs.items()}
            results[name] = {"scenario": scenario, **speeds}
            old, new = speeds["baseline"], speeds["this code"]
            print(f"{name:11s} baseline {old['per_wall_second']:.2f} per wall s, {old['per_cpu_second']:.2f} per CPU s"
                  f" | this code {new['per_wall_second']:.2f} per wall s, {new['per_cpu_second']:.2f} per CPU s"
                  f" | x{new['per_cpu_second'] / old['per_cpu_second']:.1f} (CPU), "
                  f"x{new['per_wall_second'] / old['per_wall_second']:.1f} (wall)")
    if args.profile:
        for name, scenario in SCENARIOS.items():
            out = subprocess.run([sys.executable, "-c", PROFILE, json.dumps(STAGES), str(args.seconds),
                                  str(REPO / scenario)], capture_output=True, text=True, check=True)
            profile = json.loads(out.stdout.strip().splitlines()[-1])
            shares = {stage: took / profile["total"] for stage, took in profile["stages"].items()}
            results[name]["profile"] = shares
            print(f"{name}: " + ", ".join(f"{stage} {100 * share:.0f} %"
                                          for stage, share in sorted(shares.items(), key=lambda kv: -kv[1])))
    out = REPO / "docs" / "results" / "simulator_throughput.json"
    out.write_text(json.dumps({"seconds_per_run": args.seconds, "repeats": args.repeats, "baseline": args.baseline,
                               "simulated_seconds": results, "cpu_count": os.cpu_count(),
                               "machine": platform.processor() or platform.machine()}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
