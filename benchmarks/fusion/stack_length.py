"""How far longer stacks carry a walker or a car: sites heard, timing error and fixes against N.

A walker moves 1.4 m/s, 0.009 samples of range per second at 1.92 MS/s; a car at 15 m/s, 0.1
sample per second. Over a 50-frame stack (0.5 s) a car's codes move 0.05 sample, below the
timing noise, so the stacks are not delay-rate compensated; the stack measures the arrival at
its middle. Each stack layout replays the route once (cell search and timing) and fuses it with
the simulation's true site clocks, so what changes is what the receiver hears and how well it
times it, not the clocks. Scored on the whole route. A layout is N frames per stack, back to
back (one fix per stack: 10 Hz at N = 10, 2 Hz at N = 50), or N/H: N frames every H frames,
sliding (50/10: 50-frame stacks at 10 Hz). ``--search-every`` sets how often the full search
for new cells runs (``SyncConfig.search_every``: the shortest gap, which doubles up to
``max_search_interval_s`` while the searches find nothing new).

    python benchmarks/fusion/stack_length.py [--route route_dense] [--stacks 10 20 50 100] [--search-every K] [--out NAME]
    python benchmarks/fusion/stack_length.py --route route_drive --towers config/towers/route_dense.yaml --stacks 10 50 50/10

Needs the route bag (scripts/route_bags.sh). Writes docs/results/stack_length.json (or --out).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from threadpoolctl import threadpool_limits

from deepsync.eval.calibrate import oracle_database
from deepsync.eval.route import fuse_route, replay, summarize_route
from deepsync.pipeline import PipelineConfig
from deepsync.sources import BagSource
from deepsync.sync.stacking import StackConfig
from deepsync.sync.stage import SyncConfig
from deepsync.towers import load_tower_database

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "docs" / "results"


def measure(route: str, towers_path: Path, layout: str, search_every: int) -> dict:
    bag = REPO / "bags" / "generated" / route
    if not bag.exists():
        raise SystemExit(f"{bag} is missing: make it with scripts/route_bags.sh")
    frames, _, hop = layout.partition("/")
    stack = StackConfig(n_frames=int(frames), hop_frames=int(hop) if hop else None)
    source = BagSource(bag)
    towers = load_tower_database(towers_path)
    started = time.perf_counter()
    with threadpool_limits(1):
        # sliding: the tracker counts the overlap
        config = PipelineConfig(sync=SyncConfig(stack=stack, search_every=search_every))
        recorded = replay(source, towers, config, progress=False)
    replay_s = time.perf_counter() - started
    summary = summarize_route(fuse_route(recorded, oracle_database(towers, source), config.fusion))
    heard = summary["sites_heard_per_stack"]
    stacks = sum(heard.values())
    return {
        "frames": stack.n_frames,
        "hop_frames": stack.hop,
        "search_every": search_every,
        "stacks": stacks,
        "replay_wall_s": replay_s,
        "sites_per_stack": sum(int(k) * n for k, n in heard.items()) / stacks,
        "stacks_with_3_sites": sum(n for k, n in heard.items() if int(k) >= 3) / stacks,
        "sites_heard": summary["sites_heard"],
        "timing": {site: {"stacks": row["stacks"], "rms_error_samples": row["rms_error_samples"],
                          "median_error_samples": row["median_error_samples"],
                          "median_claimed_std_samples": row["median_claimed_std_samples"]}
                   for site, row in summary["sites"].items()},
        "methods": {m: summary["methods"][m] for m in ("snapshot", "tracked")},
        "position_bound": summary["position_bound"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--route", default="route_dense")
    parser.add_argument("--towers", help="tower database (default config/towers/ROUTE.yaml)")
    parser.add_argument("--stacks", nargs="+", default=["10", "20", "50", "100"],
                        help="stack layouts: N (back to back) or N/H (N frames every H frames, sliding)")
    parser.add_argument("--search-every", type=int, default=SyncConfig().search_every,
                        help="stacks per full search for new cells (between, the cells found are tracked)")
    parser.add_argument("--out", default="stack_length.json", help="file name under docs/results")
    args = parser.parse_args()
    towers = Path(args.towers).resolve() if args.towers else REPO / "config" / "towers" / f"{args.route}.yaml"
    if not towers.exists():  # route_drive shares route_dense's sites (its scenario names the database)
        raise SystemExit(f"tower database {towers} does not exist: name the route's with --towers")
    rows = []
    print(f"{args.route}, true site clocks, whole route, a full search every {args.search_every} stacks")
    print(f"  {'N/hop':>6s} {'sites/stack':>11s} {'>=3 sites':>9s} {'snapshot':>17s} {'tracked m':>14s} "
          f"{'bound m':>8s} {'replay s':>8s}   timing RMS vs truth per site (samples)")
    for layout in args.stacks:
        row = measure(args.route, towers, layout, args.search_every)
        rows.append(row)
        snap, tracked, bound = row["methods"]["snapshot"], row["methods"]["tracked"], row["position_bound"]
        timing = ", ".join(f"{site} {t['rms_error_samples']:.2f}" for site, t in row["timing"].items()
                           if t["rms_error_samples"] is not None)
        snapshot = f"{snap['fix_rate']:.0%} {snap['median_m']:.0f} m" if snap["median_m"] is not None else "no fix"
        track = f"{tracked['median_m']:.0f} / {tracked['p90_m']:.0f}" if tracked["median_m"] is not None else "-"
        bound_m = f"{bound['median_m']:.0f}" if bound["median_m"] is not None else "-"
        layout = f"{row['frames']}/{row['hop_frames']}"
        print(f"  {layout:>6s} {row['sites_per_stack']:11.2f} {row['stacks_with_3_sites']:9.0%} {snapshot:>17s} "
              f"{track:>14s} {bound_m:>8s} {row['replay_wall_s']:8.0f}   {timing}")
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / args.out
    out.write_text(json.dumps({"route": args.route, "towers": str(towers.relative_to(REPO)), "clocks": "true",
                               "rows": rows}, indent=1, default=str))
    print(f"written: {out}")


if __name__ == "__main__":
    main()
