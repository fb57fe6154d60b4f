"""How representative the dense walk is: its scenario with other seeds, and with a channel that
changes along the route.

The scenario's seed draws each site's LOS state, shadowing and delay spread once; with
``channel: spatial_consistency: true`` the shadowing and the delay spread then follow the
receiver's distance along the walk (38.901's 30-50 m correlation distances, ``docs/design/simulator.md``).
For each seed, with and without it, this makes the bag (kept in bags/generated/ for the next
run; seed 1 without it is ``route_dense`` itself, made by scripts/route_bags.sh), replays it
through the pipeline (the walker's stacks, the dense walk's tower database) and prints the sites
heard per stack (whole walk and halves) and, on the second half, the tracked and snapshot fixes
with the true site clocks and with the clocks calibrated on the whole walk (where at least two
sites are heard). The sites, their clocks and the walk are the same in every run.

    python benchmarks/fusion/route_draws.py [--seeds 1 2 3] [--workers 2]

Each new bag takes about 3 minutes on this 2-core machine, each replay and its fusion about 1.
Writes docs/results/route_draws.json.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import yaml
from threadpoolctl import threadpool_limits

from deepsync.configio import load_yaml
from deepsync.eval.calibrate import calibratable, oracle_database
from deepsync.eval.route import RouteRun, fuse_route, replay, summarize_route
from deepsync.fusion.calibration import calibrate_sites, calibrated_database
from deepsync.recording import record_scenario
from deepsync.sources import BagSource
from deepsync.towers import load_tower_database
from route_table import second_half

REPO = Path(__file__).resolve().parents[2]
SCENARIO = REPO / "config" / "scenarios" / "route_dense.yaml"
TOWERS = REPO / "config" / "towers" / "route_dense.yaml"
BAGS = REPO / "bags" / "generated"
SECONDS = 96.4  # one pass of the walk, as scripts/route_bags.sh records it


def bag_for(seed: int, consistent: bool, workers: int) -> Path:
    """The walk's bag for ``seed`` (and spatial consistency), made if it is not there yet."""
    scenario = load_yaml(SCENARIO)
    if seed == scenario["seed"] and not consistent:
        bag = BAGS / "route_dense"
        if not bag.exists():
            raise SystemExit(f"{bag} is missing: make it with scripts/route_bags.sh")
        return bag
    name = f"route_dense_seed{seed}" + ("_consistent" if consistent else "")
    bag = BAGS / name
    if not bag.exists():
        scenario["seed"] = seed
        scenario["channel"]["spatial_consistency"] = consistent
        BAGS.mkdir(parents=True, exist_ok=True)
        path = BAGS / f"{name}.yaml"  # the bag's provenance names it
        path.write_text(yaml.safe_dump(scenario, sort_keys=False))
        record_scenario(path, SECONDS, bag, workers=workers)
    return bag


def sites_per_stack(run: RouteRun) -> dict:
    heard = np.array([len(epoch.sites) for epoch in run.epochs])
    half = len(heard) // 2
    return {"whole": float(heard.mean()), "first_half": float(heard[:half].mean()),
            "second_half": float(heard[half:].mean()), "stacks_with_3": float(np.mean(heard >= 3)),
            "sites": sorted({site.site for epoch in run.epochs for site in epoch.sites})}


def fixes(run: RouteRun) -> dict:
    methods = summarize_route(second_half(run))["methods"]
    return {method: {key: methods[method][key] for key in ("fix_rate", "median_m", "p90_m", "nees_mean")}
            for method in ("tracked", "snapshot")}


def measure(bag: Path) -> dict:
    source = BagSource(bag)
    towers = load_tower_database(TOWERS)
    with threadpool_limits(limits=1):
        recorded = replay(source, towers)
    database = fuse_route(recorded, towers)
    row = {"bag": str(bag.relative_to(REPO)), "sites_per_stack": sites_per_stack(database),
           "true_clocks": fixes(fuse_route(recorded, oracle_database(towers, source)))}
    observations, _ = calibratable(database.observations())
    try:
        calibration = calibrate_sites(observations)
    except ValueError as error:  # one site heard: no clock to calibrate against
        row["calibrated_on_all"] = str(error)
    else:
        row["calibrated_on_all"] = fixes(fuse_route(
            recorded, calibrated_database(towers, calibration.sites, database.reference_ns)))
    return row


def fix_text(row: dict | str) -> str:
    if isinstance(row, str):
        return "no calibration"
    tracked = row["tracked"]
    if tracked["median_m"] is None:
        return "no fix"
    return f"{tracked['median_m']:.0f} / {tracked['p90_m']:.0f} m, NEES {tracked['nees_mean']:.1f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--workers", type=int, default=2, help="simulator processes for a new bag")
    args = parser.parse_args()
    rows = []
    print(f"{'seed':>4s} {'consistent':>10s} {'sites/stack (halves)':>22s} {'>=3':>5s} "
          f"{'true clocks, tracked':>26s} {'calibrated on all, tracked':>28s}  sites")
    for seed in args.seeds:
        for consistent in (False, True):
            row = {"seed": seed, "spatial_consistency": consistent,
                   **measure(bag_for(seed, consistent, args.workers))}
            rows.append(row)
            heard = row["sites_per_stack"]
            halves = f"{heard['whole']:.2f} ({heard['first_half']:.2f}, {heard['second_half']:.2f})"
            print(f"{seed:4d} {str(consistent):>10s} {halves:>22s} {heard['stacks_with_3']:5.0%} "
                  f"{fix_text(row['true_clocks']):>26s} {fix_text(row['calibrated_on_all']):>28s}  "
                  f"{', '.join(heard['sites'])}")
    out = REPO / "docs" / "results" / "route_draws.json"
    out.write_text(json.dumps({"scenario": str(SCENARIO.relative_to(REPO)), "seconds": SECONDS,
                               "scored": "second half", "rows": rows}, indent=1))
    print(f"written: {out}")


if __name__ == "__main__":
    main()
