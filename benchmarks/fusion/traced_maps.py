"""Site bias maps traced from the scene (``deepsync trace-map``) on the ray-traced Munich walk.

No survey: the map comes from the scenario alone (the scene's buildings, the sites, the
receiver's route widened by 30 m), each site simulated at every street node 10 m apart
(``deepsync.eval.traced_map``). It is then used on the route set's Munich walks (seeds 1-3:
other site clocks, chain phases and noise than the map's seed 5), against no map and against a
wrong map: one made with site M1 50 m north of where it stands. Per walk, with no anchor and with
a GNSS fix a minute: the published pose's median, p90 and NEES. Also how well the map predicts
what each site reads (``prediction_error``: per stack, at the true positions, against the
stack's other sites). Maps are kept in bags/generated/maps (made when missing: about
10 minutes each on two cores); writes docs/results/traced_maps.json and the first walk's route
map with GNSS and the traced map over the scene's buildings (traced_maps_route.png).

    python benchmarks/fusion/traced_maps.py [--seeds 1 2 3] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the route set's bags, configurations and summaries
import route_set as rs  # noqa: E402

from deepsync.eval.route import RouteRun, fuse_route, recorded_buildings  # noqa: E402
from deepsync.eval.route_figures import plot_map  # noqa: E402
from deepsync.eval.traced_map import TracedMapConfig, traced_bias_map  # noqa: E402
from deepsync.fusion.anchors import Anchors, unwrap_range  # noqa: E402
from deepsync.fusion.bias_map import BiasMap, load_bias_map  # noqa: E402
from deepsync.jobs import JobRunner  # noqa: E402

ROUTE = "munich_walk"
SCENARIO = rs.REPO / "config" / "scenarios" / "munich_walk.yaml"
MAPS = rs.BAGS.parent / "maps"  # bags/generated/maps
WRONG_SITE, WRONG_BY_M = "M1", 50.0
METRES_PER_DEGREE_LATITUDE = 111_320.0
CONFIGURATIONS = ("no anchor", "GNSS 60 s")
OUT = rs.RESULTS / "traced_maps.json"
FIGURE = rs.RESULTS / "traced_maps_route.png"  # the first walk's, GNSS 60 s with the traced map


def wrong_scenario() -> Path:
    """The Munich walk with site M1 50 m north (written beside the maps)."""
    data = yaml.safe_load(SCENARIO.read_text())
    for site in data["sites"]:
        if site["name"] == WRONG_SITE:
            site["latitude_deg"] += WRONG_BY_M / METRES_PER_DEGREE_LATITUDE
    path = MAPS / f"munich_walk_{WRONG_SITE}_{WRONG_BY_M:g}m_north.yaml"
    MAPS.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def traced(scenario: Path, runner: JobRunner) -> BiasMap:
    path = MAPS / f"{scenario.stem}.npz"
    if not path.is_file():
        traced_bias_map(scenario, path, TracedMapConfig(), runner)
    return load_bias_map(path)


def prediction_error(run: RouteRun, predicted: BiasMap) -> dict[str, dict[str, float]]:
    """How well the map says what each site reads, as fusion sees it: per stack hearing two
    mapped sites or more, what each reads beyond its true distance and what the map says at the
    true position, each against the stack's mean (a receiver clock cancels); per site, the
    median |read| (what no map leaves) and the median |read - map| (what the map leaves), m."""
    left: dict[str, list[float]] = {}
    raw: dict[str, list[float]] = {}
    for epoch in run.epochs:
        rows = []
        for arrival in epoch.sites:
            truth = epoch.site_truth[arrival.site]
            value = predicted.sites[arrival.site].at(truth[0], truth[1]) if arrival.site in predicted.sites else None
            if value is not None:
                rows.append((arrival.site, arrival.range_mod_m - float(np.linalg.norm(truth - arrival.position_enu)),
                             value[0]))
        if len(rows) >= 2:
            read = np.array([unwrap_range(r[1] - rows[0][1], 0.0) for r in rows])
            said = np.array([r[2] for r in rows])
            for (site, _, _), a, b in zip(rows, read - read.mean(), said - said.mean()):
                raw.setdefault(site, []).append(abs(a))
                left.setdefault(site, []).append(abs(a - b))
    return {site: {"stacks": len(left[site]), "no_map_m": float(np.median(raw[site])),
                   "map_m": float(np.median(left[site]))} for site in sorted(left)}


def measure(seed: int, maps: dict[str, BiasMap], figure: Path | None = None) -> dict:
    """One walk's numbers; ``figure``: its route map with a GNSS fix a minute and the traced
    map, over the scene's buildings."""
    bag = f"{ROUTE}_day_s{seed}"
    replay, towers, pipeline = rs.replayed(ROUTE, rs.BAGS / bag)
    config = pipeline.fusion
    row = {"bag": bag, "configurations": {},
           "prediction_error_m": prediction_error(fuse_route(replay, towers, config), maps["traced map"])}
    for name in CONFIGURATIONS:
        runs = {label: fuse_route(replay, towers, config, aiding=rs.CONFIGURATIONS[name], bias_map=bias_map)
                for label, bias_map in {"no map": None, **maps}.items()}
        row["configurations"][name] = {label: rs.published_summary(run, config.tracker.max_std_m)
                                       for label, run in runs.items()}
        if figure is not None and name == "GNSS 60 s":
            plot_map(runs["traced map"], Anchors(towers), figure, recorded_buildings(replay.source))
    return row


def table(rows: dict[str, dict]) -> str:
    labels = list(next(iter(rows.values()))["configurations"][CONFIGURATIONS[0]])
    lines = [f"{'walk':20s} {'configuration':12s} " + " ".join(f"{label:>18s}" for label in labels)
             + "   (median / p90 m, NEES)"]
    for row in rows.values():
        for name, variants in row["configurations"].items():
            cells = [f"{_m(v['median_m'])}/{_m(v['p90_m'])} {_m(v['nees_mean'], '{:.1f}')}" for v in variants.values()]
            lines.append(f"{row['bag']:20s} {name:12s} " + " ".join(f"{c:>18s}" for c in cells))
        errors = ", ".join(f"{site} {v['no_map_m']:.0f} -> {v['map_m']:.0f}" for site, v in row["prediction_error_m"].items())
        lines.append(f"{'':20s} per stack, median |bias| left without -> with the map (m): {errors}")
    return "\n".join(lines)


def _m(value: float | None, style: str = "{:.0f}") -> str:
    return "-" if value is None else style.format(value)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", nargs="+", type=int, choices=(1, 2, 3), default=[1, 2, 3])
    parser.add_argument("--workers", type=int, default=2, help="processes for making a map (default 2)")
    args = parser.parse_args()
    missing = [f"{ROUTE}_day_s{seed}" for seed in args.seeds if not (rs.BAGS / f"{ROUTE}_day_s{seed}").exists()]
    if missing:
        parser.exit(2, f"traced_maps: missing route-set bags {', '.join(missing)}: make them with "
                       "benchmarks/fusion/route_set.py --bags-only --routes munich_walk --loads day\n")
    runner = JobRunner(args.workers)
    maps = {"traced map": traced(SCENARIO, runner),
            f"wrong map ({WRONG_SITE} {WRONG_BY_M:g} m off)": traced(wrong_scenario(), runner)}
    rows = {}
    for seed in args.seeds:
        print(f"== {ROUTE} seed {seed}", flush=True)
        rows[str(seed)] = measure(seed, maps, FIGURE if seed == args.seeds[0] else None)
    print(table(rows))
    OUT.write_text(json.dumps(rows, indent=1))
    print(f"written: {OUT}")


if __name__ == "__main__":
    main()
