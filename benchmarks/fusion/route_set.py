"""The city route set: positions along walks, a drive and a static asset, with the channel changing
along each route, at daytime and evening loads, over three seeds; each with no anchor, a start
pose only, GNSS fixes every 30 / 60 / 120 s, odometry, and GNSS with odometry; odometry in its own
frame (yaw unknown) and turned into map (heading known); an initial pose with a heading and
odometry in its own frame.

Routes (scenario files, ``channel: spatial_consistency: true`` forced on; each route runs with
its motion model's defaults, the tower database holding the sites' true clocks, as a
synchronised network or a calibrated database gives them, so what is measured is the NLOS bias):

    city_walk    config/scenarios/route_city.yaml          180 s  pedestrian
    dense_walk   config/scenarios/route_dense.yaml          96 s  pedestrian
    urban_walk   config/scenarios/route_urban.yaml          96 s  pedestrian
    city_drive   config/scenarios/route_city_drive.yaml    150 s  vehicle
    city_static  config/scenarios/route_city_static.yaml   120 s  static
    munich_walk  config/scenarios/munich_walk.yaml         180 s  pedestrian  (ray-traced)
    munich_statistical  the same sites and route, the statistical channel (38.901 UMa, LOS by distance)
    munich_drive config/scenarios/munich_drive.yaml         64 s  vehicle     (ray-traced; the walk's sites)

Loads: ``day`` sets every cell's load within 0.35-0.6, ``evening`` within 0.1-0.2 (each cell
its own, fixed by its place in the file). The bags are made when missing, into
bags/generated/route_set/ (not in git: 0.3-0.6 GB each; about 10-15 minutes each on this 2-core
machine with --workers 2), replayed once each (cell search and timing), and fused per
configuration; a bag's rows are kept in docs/results/route_set/<bag>.json, so an interrupted
run resumes where it stopped. Per route and configuration: fix rate (and after the first fix),
median, p90, NEES of the published pose, the RSSI baseline (oracle path loss) and the position
bound; the GNSS interval swept (10, 30, 60, 120, 300 s) on the walks and drives, with 5 m fixes
and with exact ones (what the interval allows when a fix adds no error of its own), and the
error against the time since the last fix. Writes docs/results/route_set.json and route_set.png.

    python benchmarks/fusion/route_set.py [--routes city_walk city_drive] [--loads day evening]
                                   [--seeds 1 2 3] [--workers 2] [--bags-only | --kept-only]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml
from threadpoolctl import threadpool_limits

from deepsync.configio import load_yaml
from deepsync.eval.aiding import AidingPlan
from deepsync.eval.calibrate import oracle_database
from deepsync.eval.route import (
    SINCE_ANCHOR_BINS_S,
    InitialPose,
    Replay,
    RouteRun,
    add_rssi_fixes,
    fuse_route,
    horizontal_error,
    method_summary,
    replay,
    summarize_route,
)
from deepsync.fusion.rssi import RssiConfig
from deepsync.fusion.stage import published_answer
from deepsync.pipeline import PipelineConfig
from deepsync.recording import record_scenario
from deepsync.sources import BagSource
from deepsync.towers import TowerDatabase, load_tower_database
from deepsync.types import Fix, NoFix

REPO = Path(__file__).resolve().parents[2]
BAGS = REPO / "bags" / "generated" / "route_set"
RESULTS = REPO / "docs" / "results"
ROUTES = {  # name: (scenario, towers, seconds, motion)
    "city_walk": ("route_city", "route_city", 180.0, "pedestrian"),
    "dense_walk": ("route_dense", "route_dense", 96.4, "pedestrian"),
    "urban_walk": ("route_urban", "route_urban", 96.4, "pedestrian"),
    "city_drive": ("route_city_drive", "route_city", 150.0, "vehicle"),
    "city_static": ("route_city_static", "route_city", 120.0, "static"),
    "munich_walk": ("munich_walk", "munich_walk", 180.0, "pedestrian"),
    "munich_drive": ("munich_drive", "munich_walk", 64.0, "vehicle"),
    "munich_statistical": ("munich_walk", "munich_walk", 180.0, "pedestrian"),
}
# the ray-traced walk's sites and route with the statistical channel instead: 38.901 UMa, its
# LOS probability by distance, NLOS TDL-A and LOS TDL-D as on the other routes
STATISTICAL_TWINS = {"munich_statistical": (
    {"model": "UMa", "los": "auto"},
    {"profile_los": "TDL-D", "profile_nlos": "TDL-A", "delay_spread_ns": "auto", "shadow_fading": True,
     "environment_doppler_hz": 1.0})}
LOADS = {"day": (0.35, 0.6), "evening": (0.1, 0.2)}
GNSS_STD_M = 5.0
ODOMETRY_STD = 0.05
# an operator's initial pose 5 m off, facing the way the receiver moves to 0.1 rad (a drag
# along the street), which aligns the odometry's frame at once
HEADED_START = "start pose, heading + odometry"
HEADING_STD_RAD = 0.1
CONFIGURATIONS = {
    "no anchor": AidingPlan(),
    "start pose": AidingPlan(0.0, GNSS_STD_M),
    "GNSS 30 s": AidingPlan(30.0, GNSS_STD_M),
    "GNSS 60 s": AidingPlan(60.0, GNSS_STD_M),
    "GNSS 120 s": AidingPlan(120.0, GNSS_STD_M),
    "odometry": AidingPlan(odometry_std=ODOMETRY_STD),
    "GNSS 60 s + odometry": AidingPlan(60.0, GNSS_STD_M, ODOMETRY_STD),
    "odometry in map": AidingPlan(odometry_std=ODOMETRY_STD, odometry_in_map=True),
    "GNSS 60 s + odometry in map": AidingPlan(60.0, GNSS_STD_M, ODOMETRY_STD, odometry_in_map=True),
    HEADED_START: AidingPlan(odometry_std=ODOMETRY_STD),
}
# configurations that start from an operator's initial pose
STARTS = {HEADED_START: InitialPose(GNSS_STD_M, heading_std_rad=HEADING_STD_RAD)}
INTERVALS_S = (10.0, 30.0, 60.0, 120.0, 300.0)
# an oracle's fix, nearly exact, and taken at its word (the stage's floor lowered to it): how
# far the interval alone lets the track stray, whatever the receiver's GNSS
EXACT_GNSS_STD_M = 0.3
INTERVAL_FIXES = {"interval_median_m": GNSS_STD_M, "interval_median_exact_m": EXACT_GNSS_STD_M}


def scenario_for(route: str, load: str, seed: int) -> dict:
    """The route's scenario with ``load``'s loads, ``seed`` and, on a statistical channel,
    spatial consistency (a ray-traced channel follows the geometry as it is)."""
    scenario_name = ROUTES[route][0]
    scenario = load_yaml(REPO / "config" / "scenarios" / f"{scenario_name}.yaml")
    low, high = LOADS[load]
    cells = [cell for site in scenario["sites"] for cell in site["cells"]]
    for k, cell in enumerate(cells):  # spread over the range, each cell its own
        cell["load"] = round(low + (high - low) * ((k * 0.618034) % 1.0), 3)
    scenario["seed"] = seed
    if route in STATISTICAL_TWINS:
        scenario["environment"], scenario["channel"] = (dict(part) for part in STATISTICAL_TWINS[route])
    if scenario.setdefault("channel", {}).get("model", "statistical") == "statistical":
        scenario["channel"]["spatial_consistency"] = True
    return scenario


def bag_for(route: str, load: str, seed: int, workers: int) -> Path:
    """The route's bag, made if it is not there yet (its scenario file beside it: the provenance names it)."""
    bag = BAGS / f"{route}_{load}_s{seed}"
    if not bag.exists():
        BAGS.mkdir(parents=True, exist_ok=True)
        path = BAGS / f"{bag.name}.yaml"
        path.write_text(yaml.safe_dump(scenario_for(route, load, seed), sort_keys=False))
        started = time.monotonic()
        record_scenario(path, ROUTES[route][2], bag, workers=workers)
        print(f"  made {bag.relative_to(REPO)} in {time.monotonic() - started:.0f} s", flush=True)
    return bag


def published(run: RouteRun, max_std_m: float) -> list[Fix | NoFix]:
    """What a node publishes at each stack (``FusionResult.published``)."""
    return [published_answer(epoch.tracked, lambda epoch=epoch: epoch.snapshot, max_std_m) for epoch in run.epochs]


def fix_rate_after_first(answers: list[Fix | NoFix]) -> float | None:
    """Share of the stacks after the first published fix that have a published fix."""
    first = next((k for k, answer in enumerate(answers) if isinstance(answer, Fix)), None)
    if first is None:
        return None
    return float(np.mean([isinstance(answer, Fix) for answer in answers[first:]]))


def published_summary(run: RouteRun, max_std_m: float) -> dict:
    """What a node publishes, against the truth."""
    answers = published(run, max_std_m)
    summary = method_summary(answers, [epoch.truth_enu for epoch in run.epochs])
    return {key: summary[key] for key in ("fix_rate", "median_m", "p90_m", "nees_mean")} | {
        "fix_rate_after_first": fix_rate_after_first(answers)}


def since_anchor_errors(run: RouteRun) -> list[tuple[float, float]]:
    pairs = [(run.since_anchor_s(epoch.stamp_ns), horizontal_error(epoch.tracked, epoch.truth_enu))
             for epoch in run.epochs if isinstance(epoch.tracked, Fix)]
    return [pair for pair in pairs if math.isfinite(pair[0])]


def replayed(route: str, bag: Path) -> tuple[Replay, TowerDatabase, PipelineConfig]:
    """A route's bag replayed (cell search and timing) with its motion model's settings, and its
    tower database holding the recording's true clocks."""
    source = BagSource(bag)
    towers = oracle_database(load_tower_database(REPO / "config" / "towers" / f"{ROUTES[route][1]}.yaml"), source)
    config = PipelineConfig.for_motion(ROUTES[route][3])
    with threadpool_limits(limits=1):
        return replay(source, towers, config, progress=False), towers, config


def measure(route: str, bag: Path) -> dict:
    """Every configuration's numbers on one bag (one replay, fusion per configuration)."""
    started = time.monotonic()
    recorded, towers, config = replayed(route, bag)
    row: dict = {"bag": str(bag.relative_to(REPO)), "replay_s": time.monotonic() - started}
    plain = fuse_route(recorded, towers, config.fusion)
    model = add_rssi_fixes(plain, RssiConfig(receiver_height_m=config.fusion.snapshot.receiver_height_m))
    summary = summarize_route(plain)
    heard = np.array([len(epoch.sites) for epoch in plain.epochs])
    row["heard"] = {"mean": float(heard.mean()), "with_3": float(np.mean(heard >= 3)),
                    "sites": summary["sites_heard"]}
    row["rssi"] = {key: summary["methods"]["rssi"][key] for key in ("fix_rate", "median_m", "p90_m")} | {
        "fitted": model["fitted"]}
    row["bound"] = summary["position_bound"]
    row["site_bias_samples"] = {site: values["median_error_samples"] for site, values in summary["sites"].items()}
    row["configurations"] = {}
    for name, plan in CONFIGURATIONS.items():
        if name == "no anchor":
            run = plain
        else:  # each bag its own draws: GNSS errors, odometry errors, the start's offset
            start = None if name not in STARTS else STARTS[name].for_recording(bag.name)
            run = fuse_route(recorded, towers, config.fusion, start, plan.for_recording(bag.name))
        row["configurations"][name] = published_summary(run, config.fusion.tracker.max_std_m)
        if name == "GNSS 60 s":
            row["since_anchor"] = since_anchor_errors(run)
    if ROUTES[route][3] != "static":
        for key, std_m in INTERVAL_FIXES.items():
            fusion = replace(config.fusion, gnss_min_std_m=min(std_m, config.fusion.gnss_min_std_m))
            row[key] = {}
            for interval in INTERVALS_S:
                run = fuse_route(recorded, towers, fusion, aiding=AidingPlan(interval, std_m).for_recording(bag.name))
                row[key][f"{interval:g}"] = published_summary(run, fusion.tracker.max_std_m)["median_m"]
    return row


def table(rows: dict[str, dict]) -> str:
    lines = [f"{'bag':28s} {'configuration':22s} {'fixes':>6s} {'after 1st':>9s} {'median':>7s} {'p90':>7s} "
             f"{'NEES':>5s}  RSSI median / bound median"]
    for name, row in rows.items():
        rssi, bound = row["rssi"]["median_m"], row["bound"]["median_m"]
        extra = f"{_m(rssi)} / {_m(bound)}  sites/stack {row['heard']['mean']:.1f}, >=3 {row['heard']['with_3']:.0%}"
        for k, (configuration, c) in enumerate(row["configurations"].items()):
            after = "    -" if c["fix_rate_after_first"] is None else f"{c['fix_rate_after_first']:9.0%}"
            nees = "    -" if c["nees_mean"] is None else f"{c['nees_mean']:5.1f}"
            lines.append(f"{name if k == 0 else '':28s} {configuration:22s} {c['fix_rate']:6.0%} {after} "
                         f"{_m(c['median_m'])} {_m(c['p90_m'])} {nees}  {extra if k == 0 else ''}")
    return "\n".join(lines)


def route_table(rows: dict[str, dict]) -> str:
    """The README's table: per route and load, each configuration's published median / p90 (NEES)
    as the range over the seeds measured."""
    groups: dict[str, list[dict]] = {}
    for name, row in rows.items():
        groups.setdefault(name.rsplit("_s", 1)[0], []).append(row)
    names = list(next(iter(rows.values()))["configurations"])
    lines = ["| route (seeds) | sites per stack | " + " | ".join(names) + " | RSSI | bound |",
             "|---" * (len(names) + 4) + "|"]
    for group, members in groups.items():
        cells = [f"{group.replace('_', ' ')} ({len(members)})",
                 _span([row["heard"]["mean"] for row in members], "{:.1f}")]
        for configuration in names:
            chosen = [row["configurations"][configuration] for row in members]
            cells.append(f"{_span([c['median_m'] for c in chosen])} / {_span([c['p90_m'] for c in chosen])} "
                         f"({_span([c['nees_mean'] for c in chosen], '{:.1f}')})")
        cells.append(_span([row["rssi"]["median_m"] for row in members]))
        cells.append(_span([row["bound"]["median_m"] for row in members], "{:.1f}"))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def nees_by_configuration(rows: dict[str, dict]) -> str:
    """Per configuration, over every bag it tracked: the mean of the bags' NEES, and how many
    bags' NEES lie within [1, 3] (honest), below (cautious) and above (overconfident)."""
    lines = [f"{'configuration':32s} {'bags':>4s} {'mean NEES':>9s}  within [1, 3] / below / above"]
    for configuration in next(iter(rows.values()))["configurations"]:
        values = np.array([row["configurations"][configuration]["nees_mean"] for row in rows.values()
                           if row["configurations"][configuration]["nees_mean"] is not None], dtype=float)
        if values.size:
            lines.append(f"{configuration:32s} {values.size:4d} {values.mean():9.2f}  {np.sum((values >= 1) & (values <= 3))}"
                         f" / {np.sum(values < 1)} / {np.sum(values > 3)}")
    return "\n".join(lines)


def _span(values: list[float | None], style: str = "{:.0f}") -> str:
    """``low-high`` of the values there are (``-`` where none is)."""
    present = [value for value in values if value is not None and math.isfinite(value)]
    if not present:
        return "-"
    low, high = style.format(min(present)), style.format(max(present))
    return low if low == high else f"{low}-{high}"


def _m(value: float | None) -> str:
    return "      -" if value is None else f"{value:7.1f}"


def _interval_medians(row: dict, key: str) -> list[float]:
    """A route's medians at each of ``INTERVALS_S`` under ``key`` (NaN where it has none)."""
    medians = row.get(key, {})
    return [math.nan if medians.get(f"{interval:g}") is None else medians[f"{interval:g}"] for interval in INTERVALS_S]


def plot(rows: dict[str, dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    for motion, colour in (("pedestrian", "tab:blue"), ("vehicle", "tab:orange")):
        chosen = [row for name, row in rows.items() if ROUTES[name.rsplit("_", 2)[0]][3] == motion]
        for key, style in (("interval_median_m", "o-"), ("interval_median_exact_m", "s--")):
            per_route = np.array([_interval_medians(row, key) for row in chosen]).reshape(-1, len(INTERVALS_S))
            kept = np.isfinite(per_route).any(axis=0)
            if not kept.any():
                continue
            x, values = np.array(INTERVALS_S)[kept], per_route[:, kept]
            fixes = "exact fixes" if key.endswith("exact_m") else f"{GNSS_STD_M:g} m fixes"
            left.plot(x, np.nanmedian(values, axis=0), style, color=colour, ms=4,
                      label=f"{'walks' if motion == 'pedestrian' else 'drives'} ({len(chosen)}), {fixes}")
            left.fill_between(x, np.nanmin(values, axis=0), np.nanmax(values, axis=0), color=colour, alpha=0.12)
    left.set_xscale("log")
    left.set_yscale("log")
    left.set_xlabel("GNSS interval (s)")
    left.set_ylabel("median horizontal error (m)")
    left.set_title("Median error against the GNSS interval\n(the routes' median; band: their range)")
    left.grid(True, which="both", alpha=0.3)
    if left.lines:
        left.legend(fontsize=7)
    pairs = [pair for row in rows.values() for pair in row.get("since_anchor", [])]
    edges = [edge for edge in SINCE_ANCHOR_BINS_S if edge <= 60.0] + [60.0 + 1e-9]
    centres, medians, p90s = [], [], []
    for low, high in zip(edges, edges[1:]):
        errors = np.array([error for since, error in pairs if low <= since < high])
        if errors.size:
            centres.append(0.5 * (low + high))
            medians.append(float(np.median(errors)))
            p90s.append(float(np.percentile(errors, 90)))
    seconds = np.array([since for since, _ in pairs])
    errors = np.array([error for _, error in pairs])
    if errors.size:
        right.plot(seconds, errors, ".", ms=1.5, color="0.6", label="tracked fixes (every route)")
        right.plot(centres, medians, "o-", color="tab:green", label="median")
        right.plot(centres, p90s, "s--", color="tab:red", label="p90")
        right.set_yscale("log")
        right.legend(fontsize=7)
    right.set_xlabel("time since the last GNSS fix (s; fixes every 60 s)")
    right.set_ylabel("horizontal error (m)")
    right.set_title("Error against the time since the last anchor")
    right.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--routes", nargs="+", choices=tuple(ROUTES), default=list(ROUTES))
    parser.add_argument("--loads", nargs="+", choices=tuple(LOADS), default=list(LOADS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--workers", type=int, default=2, help="simulator processes for a new bag")
    parser.add_argument("--bags-only", action="store_true", help="make the missing bags, measure nothing")
    parser.add_argument("--kept-only", action="store_true",
                        help="tabulate the rows already measured (docs/results/route_set/), make and measure nothing")
    args = parser.parse_args()
    if args.bags_only:
        for route in args.routes:
            for load in args.loads:
                for seed in args.seeds:
                    bag_for(route, load, seed, args.workers)
        return
    cache = RESULTS / "route_set"
    cache.mkdir(parents=True, exist_ok=True)
    rows = {}
    for route in args.routes:
        for load in args.loads:
            for seed in args.seeds:
                name = f"{route}_{load}_s{seed}"
                kept = cache / f"{name}.json"
                if kept.exists():
                    rows[name] = json.loads(kept.read_text())
                    continue
                if args.kept_only:
                    continue
                print(f"== {name}", flush=True)
                rows[name] = measure(route, bag_for(route, load, seed, args.workers))
                temporary = kept.with_suffix(".tmp")
                temporary.write_text(json.dumps(rows[name], indent=1))
                temporary.replace(kept)  # a row is there whole or not at all
    if not rows:
        parser.exit(2, "route_set: no rows measured for this selection\n")
    print(table(rows))
    print("\n" + route_table(rows))
    print("\n" + nees_by_configuration(rows))
    (RESULTS / "route_set.json").write_text(json.dumps(rows, indent=1))
    plot(rows, RESULTS / "route_set.png")
    print(f"written: {RESULTS / 'route_set.json'}, {RESULTS / 'route_set.png'}")


if __name__ == "__main__":
    main()
