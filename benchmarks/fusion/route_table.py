"""The route table: snapshot, tracked and RSSI fixes along both route variants, with the site
clocks as a database knows them, as calibrated, as tracked, and as they truly were.

Each bag is replayed once (cell search and timing, the expensive part; its wall time is the
"evaluation of a route" speed figure), then fusion runs per variant on the same arrivals:

* ``database``: the tower database as written: every site's offset right at its epoch (the
  recording's start), no drift: a one-time calibration of offsets, as old as the recording;
* ``calibrated``: offsets and drifts calibrated on the first half of the route (truth known
  there), evaluated on the second half only (as are all variants, for one yardstick);
* ``calibrated on all of it``: calibrated on the whole route, the same data it is scored on
  (optimistic: the calibration absorbs each site's multipath bias too);
* ``reference station``: offsets and drifts calibrated on a fixed rooftop receiver that hears
  the same sites in line of sight (``<route>_reference``, where a scenario for it exists), the
  way a reference station serves LTE signals of opportunity: no NLOS bias, only the sites it
  hears, and the multipath bias of its own fixed position; ``... + site clock states``: the
  same database, the tracker going on estimating each site's clock from its sigmas;
* ``site clock states``: the database as written, the tracker estimating each site's clock;
* ``true clocks``: the simulation's true offsets and drifts (no calibration can beat it);
* ``initial_pose`` (beside the variants): the tracker started at the scored half's start from an
  operator's initial position, the truth off by N(0, 30 m) per axis and claiming 30 m, over ten
  draws, with the database's clocks and the true ones; and the error of that position alone,
  held still, for what the sites add to it.

The bags are too long for git: ``scripts/route_bags.sh`` makes them (bags/generated/).
Writes docs/results/route_table.json and, for the ``calibrated`` variant, the route figures
(docs/results/<route>_{cdf,map,timeline}.png). ``--frames 50`` stacks 50 frames instead of 10
(a walker moves 0.7 m in half a second: the codes stay aligned) and writes
docs/results/route_table_50.json, without figures.

    python benchmarks/fusion/route_table.py [--routes route_urban route_dense] [--frames 10]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import time
from pathlib import Path

import numpy as np

from deepsync.eval.calibrate import calibratable, calibrate_route, oracle_database
from deepsync.eval.route import InitialPose, Replay, RouteRun, add_rssi_fixes, fuse_route, replay, summarize_route
from deepsync.eval import route_figures
from deepsync.fusion.anchors import Anchors
from deepsync.fusion.calibration import calibrate_sites, calibrated_database
from deepsync.fusion.rssi import RssiConfig
from deepsync.fusion.stage import FusionConfig
from deepsync.fusion.tracker import TrackerConfig
from deepsync.pipeline import PipelineConfig
from deepsync.sources import BagSource
from deepsync.sync.stacking import StackConfig
from deepsync.sync.stage import SyncConfig
from deepsync.towers import TowerDatabase, load_tower_database
from deepsync.types import Fix

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "docs" / "results"
INITIAL_POSE_STD_M = 30.0
INITIAL_POSE_DRAWS = 10


def second_half(run: RouteRun) -> RouteRun:
    """The epochs after the route's middle: where every variant is scored."""
    middle = (run.epochs[0].stamp_ns + run.epochs[-1].stamp_ns) // 2
    return dataclasses.replace(run, epochs=[e for e in run.epochs if e.stamp_ns > middle])


def initial_pose_runs(recorded: Replay, databases: dict[str, TowerDatabase], middle_ns: int) -> dict:
    """The tracker started from an operator's initial position where the scored half begins,
    over ``INITIAL_POSE_DRAWS`` draws of its error: medians over the draws of each draw's
    numbers, and the position alone held still over the stacks the tracker fixed."""
    result: dict = {"std_m": INITIAL_POSE_STD_M, "draws": INITIAL_POSE_DRAWS}
    held = []
    for label, towers in databases.items():
        rows = []
        for seed in range(INITIAL_POSE_DRAWS):
            pose = InitialPose(INITIAL_POSE_STD_M, after_ns=middle_ns, seed=seed)
            run = second_half(fuse_route(recorded, towers, initial_pose=pose))
            rows.append(summarize_route(run)["methods"]["tracked"])
            if label == "database":
                start = run.epochs[0]
                prior = np.array(pose.prior(start.truth_enu).position_enu[:2])
                held += [float(np.linalg.norm(prior - e.truth_enu[:2])) for e in run.epochs if isinstance(e.tracked, Fix)]
        result[label] = {key: float(np.median([row[key] if row[key] is not None else np.nan for row in rows]))
                         for key in ("fix_rate", "median_m", "p90_m", "nees_mean")}
        result[label]["nees_mean_per_draw"] = [row["nees_mean"] for row in rows]
    result["held_still"] = {"median_m": float(np.median(held)), "p90_m": float(np.percentile(held, 90))}
    return result


def evaluate(name: str, frames: int = 10) -> dict:
    bag = REPO / "bags" / "generated" / name
    if not bag.exists():
        raise SystemExit(f"{bag} is missing: make it with scripts/route_bags.sh")
    source = BagSource(bag)
    towers = load_tower_database(REPO / "config" / "towers" / f"{name}.yaml")
    config = PipelineConfig(sync=SyncConfig(stack=StackConfig(n_frames=frames)))
    cache = REPO / "out" / "route_cache" / (f"{name}.pickle" if frames == 10 else f"{name}_{frames}.pickle")
    started = time.perf_counter()
    if cache.exists() and cache.stat().st_mtime > max(p.stat().st_mtime for p in bag.iterdir()):
        with cache.open("rb") as file:  # our own replay of this bag, from an earlier run
            recorded, replay_s = pickle.load(file), None
    else:
        recorded = replay(source, towers, config)
        replay_s = time.perf_counter() - started
        cache.parent.mkdir(parents=True, exist_ok=True)
        with cache.open("wb") as file:
            pickle.dump(dataclasses.replace(recorded, source=None), file)
    recorded = dataclasses.replace(recorded, source=source)

    runs = {"database": fuse_route(recorded, towers)}
    middle = (recorded.arrivals[0].stamp_ns + recorded.arrivals[-1].stamp_ns) // 2
    observations, skipped = calibratable(runs["database"].observations(until_ns=middle))
    calibration = calibrate_sites(observations)
    calibrated = calibrated_database(towers, calibration.sites, runs["database"].reference_ns)
    runs["calibrated"] = fuse_route(recorded, calibrated)
    whole, _ = calibratable(runs["database"].observations())
    runs["calibrated on all of it"] = fuse_route(
        recorded, calibrated_database(towers, calibrate_sites(whole).sites, runs["database"].reference_ns))
    station = None
    reference = REPO / "bags" / "generated" / f"{name}_reference"
    if reference.exists():
        station = calibrate_route(BagSource(reference), towers, progress=False)
        runs["reference station"] = fuse_route(recorded, station.database)
        runs["reference station + site clock states"] = fuse_route(
            recorded, station.database, FusionConfig(tracker=TrackerConfig(site_clocks=True)))
    runs["site clock states"] = fuse_route(recorded, towers, FusionConfig(tracker=TrackerConfig(site_clocks=True)))
    oracle = oracle_database(towers, source)
    runs["true clocks"] = fuse_route(recorded, oracle)
    table = {}
    for variant, run in runs.items():
        model = add_rssi_fixes(run, RssiConfig())
        table[variant] = {**summarize_route(second_half(run)), "rssi_model": model}
    if frames == 10:  # the figures docs/design/fusion.md shows
        figures = RESULTS / name
        route_figures.plot_cdf(second_half(runs["calibrated"]), Path(f"{figures}_cdf.png"))
        route_figures.plot_map(runs["calibrated"], Anchors(calibrated), Path(f"{figures}_map.png"))
        route_figures.plot_timeline(runs["calibrated"], Path(f"{figures}_timeline.png"))
    seconds = (recorded.arrivals[-1].stamp_ns - recorded.arrivals[0].stamp_ns) * 1e-9
    return {"bag": str(bag.relative_to(REPO)), "route_seconds": seconds, "replay_wall_s": replay_s,
            "calibration": {"sites": [dataclasses.asdict(s) for s in calibration.sites], "skipped": skipped,
                            "residual_rms_before_m": calibration.residual_rms_before_m,
                            "residual_rms_after_m": calibration.residual_rms_after_m,
                            "sigma_scale": calibration.sigma_scale},
            "reference_station": None if station is None else {
                "bag": str(reference.relative_to(REPO)),
                "sites": [dataclasses.asdict(s) for s in station.result.sites], "skipped": station.skipped,
                "residual_rms_after_m": station.result.residual_rms_after_m},
            "variants": table,
            "initial_pose": initial_pose_runs(recorded, {"database": towers, "true clocks": oracle}, middle)}


def print_table(name: str, result: dict) -> None:
    replayed = "from the cache" if result["replay_wall_s"] is None else f"in {result['replay_wall_s']:.0f} s"
    print(f"\n== {name}: {result['route_seconds']:.0f} s of route, replayed {replayed}; scored on the second half")
    database = result["variants"]["database"]
    print(f"   sites heard per stack {database['sites_heard_per_stack']}; heard: {', '.join(database['sites_heard'])}")
    for site, row in database["sites"].items():
        if row["median_error_samples"] is not None:
            print(f"   site {site}: {row['stacks']} stacks, timing error median {row['median_error_samples']:+.2f} "
                  f"samples, RMS {row['rms_error_samples']:.2f}, {row['beyond_1_sample']:.0%} beyond 1 sample, "
                  f"claimed {row['median_claimed_std_samples']:.2f}")
    print(f"   {'variant':38s} {'method':9s} {'fix rate':>8s} {'median m':>9s} {'p90 m':>8s} {'NEES':>6s}")
    for variant, summary in result["variants"].items():
        for method, row in summary["methods"].items():
            median = "-" if row["median_m"] is None else f"{row['median_m']:.1f}"
            p90 = "-" if row["p90_m"] is None else f"{row['p90_m']:.1f}"
            nees = "-" if row["nees_mean"] is None else f"{row['nees_mean']:.1f}"
            print(f"   {variant:38s} {method:9s} {row['fix_rate']:8.0%} {median:>9s} {p90:>8s} {nees:>6s}")
    pose = result["initial_pose"]
    for label in ("database", "true clocks"):
        row = pose[label]
        print(f"   {'initial pose ' + str(int(pose['std_m'])) + ' m, ' + label:38s} {'tracked':9s} {row['fix_rate']:8.0%} "
              f"{row['median_m']:9.1f} {row['p90_m']:8.1f} {row['nees_mean']:6.1f}   (medians of {pose['draws']} draws)")
    print(f"   {'initial pose held still':38s} {'':9s} {'':8s} {pose['held_still']['median_m']:9.1f} "
          f"{pose['held_still']['p90_m']:8.1f}")
    bound = database["position_bound"]
    if bound["median_m"] is not None:
        print(f"   position bound (stacks with >= 3 sites: {bound['stacks']}): median {bound['median_m']:.1f} m, "
              f"p90 {bound['p90_m']:.1f} m")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--routes", nargs="+", default=["route_urban", "route_dense"])
    parser.add_argument("--frames", type=int, default=10, help="frames per stack (default %(default)s)")
    args = parser.parse_args()
    results = {}
    for name in args.routes:
        results[name] = evaluate(name, args.frames)
        print_table(name, results[name])
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / ("route_table.json" if args.frames == 10 else f"route_table_{args.frames}.json")
    out.write_text(json.dumps(results, indent=1, default=str))
    print(f"\nwritten: {out}")


if __name__ == "__main__":
    main()
