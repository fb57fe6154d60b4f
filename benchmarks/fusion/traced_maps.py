"""Site bias maps traced from the scene (``deepsync trace-map``) on the ray-traced Munich walk
and drive.

No survey: each map comes from the scenario alone (the scene's buildings, the sites, the
receiver's route), each site simulated at every street node 10 m apart within 30 m of the route
(``deepsync.eval.traced_map``). It is then used on the route set's bags of that route (seeds
1-3: other site clocks, chain phases and noise than the map's seed 5), against no map and two
deliberately wrong maps: one made with site M1 50 m north of where it stands ("site 50 m off"),
one made from the scene without the building that cuts the most straight lines from the sites
to the route, the buildings they stand on aside ("building removed": ``blocking_building``; its
meshes left out with the scenario's ``remove_buildings``). Per bag, with no anchor and with a
GNSS fix a minute: the published pose's median, p90 and NEES. Also how well the map predicts
what each site reads (``prediction_error``: per stack, at the true positions, against the
stack's other sites); errors split by line of sight (``los_split``: each arrival's lag, and the
published pose without a map, by whether the heard sites' earliest path is the straight line
there); and per route the time to trace its route points to every site, cold (an
empty cache) and from the cache.

Maps are kept in bags/generated/maps, named by a digest of the scenario and the map settings
(made when missing: minutes to tens of minutes each on two cores; delete them after changing
the tracing code). Writes docs/results/traced_maps.json (routes not run this time kept as they
were) and each route's first bag's route map with GNSS and the traced map over the scene's
buildings (traced_maps_route.png: the walk; traced_maps_drive.png).

    python benchmarks/fusion/traced_maps.py [--routes munich_walk munich_drive] [--seeds 1 2 3] [--workers 2]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import tempfile
import time
from collections import Counter
from dataclasses import asdict
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the route set's bags, configurations and summaries
import route_set as rs  # noqa: E402

from deepsync.eval.channel_stats import direct_first  # noqa: E402
from deepsync.eval.route import RouteRun, fuse_route, recorded_buildings  # noqa: E402
from deepsync.eval.route_figures import plot_map  # noqa: E402
from deepsync.eval.traced_map import TracedMapConfig, traced_bias_map  # noqa: E402
from deepsync.fusion.anchors import Anchors, unwrap_range  # noqa: E402
from deepsync.fusion.bias_map import BiasMap, load_bias_map  # noqa: E402
from deepsync.jobs import JobRunner  # noqa: E402
from deepsync.recording import EPOCH_NS  # noqa: E402
from deepsync.twin import Twin, build_twin, load_scenario  # noqa: E402
from deepsync.twin.raytrace.build import scenario_scene  # noqa: E402
from deepsync.twin.raytrace.buildings import scene_shapes  # noqa: E402
from deepsync.twin.raytrace.channel import route_samples  # noqa: E402
from deepsync.twin.scenario import parse_scenario  # noqa: E402
from deepsync.twin.world import receiver_trajectory, twin_cells  # noqa: E402
from deepsync.types import SPEED_OF_LIGHT_M_S, Fix  # noqa: E402

ROUTES = ("munich_walk", "munich_drive")  # the route set's ray-traced routes
MAPS = rs.BAGS.parent / "maps"  # bags/generated/maps
WRONG_SITE, WRONG_BY_M = "M1", 50.0
METRES_PER_DEGREE_LATITUDE = 111_320.0
MATERIAL_SEPARATOR = "-itu_"  # Sionna's Munich names a building's meshes <building>-itu_<material>
CONFIGURATIONS = ("no anchor", "GNSS 60 s")
MAP_LABELS = ("traced map", f"site {WRONG_BY_M:g} m off", "building removed")
MIN_STACKS = 30  # fewer stacks with a site say little (the drive's M5 in its 5-8 is a false lock)
OUT = rs.RESULTS / "traced_maps.json"
FIGURES = {"munich_walk": rs.RESULTS / "traced_maps_route.png", "munich_drive": rs.RESULTS / "traced_maps_drive.png"}


def scenario_file(route: str) -> Path:
    return rs.REPO / "config" / "scenarios" / f"{rs.ROUTES[route][0]}.yaml"


def variant(route: str, suffix: str, change) -> Path:
    """The route's scenario changed by ``change`` (a function of its YAML mapping), written beside the maps."""
    data = yaml.safe_load(scenario_file(route).read_text())
    change(data)
    path = MAPS / f"{rs.ROUTES[route][0]}_{suffix}.yaml"
    MAPS.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def site_off(route: str) -> Path:
    """The route's scenario with site M1 50 m north."""
    def move(data: dict) -> None:
        for site in data["sites"]:
            if site["name"] == WRONG_SITE:
                site["latitude_deg"] += WRONG_BY_M / METRES_PER_DEGREE_LATITUDE
    return variant(route, f"{WRONG_SITE}_{WRONG_BY_M:g}m_north", move)


def blocking_building(route: str) -> dict:
    """The building that cuts the most straight lines from the sites' antennas to the route's
    traced points (a line below its roof inside its footprint, sampled every metre), the
    buildings the sites stand on aside: its name, its meshes and, per site, the share of the
    points whose line it cuts."""
    import shapely  # noqa: PLC0415 (the ray-tracing extra)

    scenario = load_scenario(scenario_file(route))
    cells = twin_cells(scenario)
    scene = scenario_scene(scenario.channel, cells.frame)
    _, points = route_samples(receiver_trajectory(scenario.receiver, cells.frame), scenario.channel.route_step_m)
    buildings = scene.buildings.buildings
    building_of = [b.name.split(MATERIAL_SEPARATOR)[0] for b in buildings]
    tree, roofs = shapely.STRtree([b.footprint for b in buildings]), np.array([b.height_m for b in buildings])
    receivers = scene.to_scene(points)
    hosts, cut = set(), {}
    for site in cells.sites:
        antenna = scene.to_scene(site.position_enu)
        host = scene.buildings.at(antenna[0], antenna[1])
        hosts.add(host.name.split(MATERIAL_SEPARATOR)[0] if host else None)
        blocked = Counter()
        for receiver in receivers:
            steps = np.linspace(0.0, 1.0, max(int(np.linalg.norm(receiver - antenna)), 2))[1:-1, None]
            line = antenna + steps * (receiver - antenna)
            point, building = tree.query(shapely.points(line[:, :2]), predicate="intersects")
            blocked.update({building_of[b] for b in building[line[point, 2] < roofs[building]]})
        for name, count in blocked.items():
            cut.setdefault(name, {})[site.name] = count / len(receivers)
    name = max((n for n in cut if n not in hosts), key=lambda n: sum(cut[n].values()))
    meshes = sorted(n for n in scene_shapes(scene.xml_path) if n.split(MATERIAL_SEPARATOR)[0] == name)
    return {"building": name, "meshes": meshes, "share_blocked": dict(sorted(cut[name].items()))}


def building_removed(route: str, meshes: list[str]) -> Path:
    """The route's scenario traced without ``meshes``."""
    return variant(route, "building_removed", lambda data: data["channel"].update(remove_buildings=meshes))


def traced(scenario: Path, runner: JobRunner) -> tuple[BiasMap, dict]:
    """The scenario's traced map (made when missing) and how it was made (nodes, sites heard, seconds)."""
    config = TracedMapConfig()
    digest = hashlib.sha256(scenario.read_bytes() + repr(sorted(asdict(config).items())).encode()).hexdigest()[:12]
    path = MAPS / f"{scenario.stem}-{digest}.npz"
    made = path.with_suffix(".json")
    if not (path.is_file() and made.is_file()):  # the record written last: a map without one is made again
        started = time.monotonic()
        result = traced_bias_map(scenario, path, config, runner)
        made.write_text(json.dumps({"nodes": result.nodes, "heard": result.heard,
                                    "seconds": time.monotonic() - started}, indent=1))
    return load_bias_map(path), json.loads(made.read_text())


def trace_seconds(route: str) -> dict[str, float]:
    """Seconds to build the route's twin with its traces: cold (an empty cache) and from the cache."""
    data = yaml.safe_load(scenario_file(route).read_text())
    times = {}
    with tempfile.TemporaryDirectory() as cache:
        data["channel"]["cache_dir"] = cache
        path = Path(cache) / "scenario.yaml"
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        for run in ("first", "cached"):
            started = time.monotonic()
            build_twin(load_scenario(path))
            times[run] = time.monotonic() - started
    return times


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


def los_split(run: RouteRun, twin: Twin, max_std_m: float) -> dict:
    """Errors by line of sight, no map: each arrival's lag beyond the straight line (m; the
    timing stage against the recording's truth) by whether its site's earliest path is the
    straight line there (the strongest sector's, ``direct_first``), and the published pose's
    error by whether every heard site, some or none has one."""
    metres_per_sample = SPEED_OF_LIGHT_M_S / twin.frontend.adc_rate_hz
    lags: dict[str, list[float]] = {"los": [], "nlos": []}
    poses: dict[str, list[float]] = {"all_los": [], "some_los": [], "no_los": []}
    for epoch, answer in zip(run.epochs, rs.published(run, max_std_m)):
        seen = []
        for arrival in epoch.sites:
            t = (run.reference_ns + arrival.time_s * 1e9 - EPOCH_NS) * 1e-9
            seen.append(direct_first(twin.channel, twin.emitters, arrival.site, t))
            lag = epoch.timing_errors.get(arrival.site, (math.nan,))[0]
            if math.isfinite(lag):
                lags["los" if seen[-1] else "nlos"].append(lag * metres_per_sample)
        if seen and isinstance(answer, Fix):
            kind = "all_los" if all(seen) else "some_los" if any(seen) else "no_los"
            poses[kind].append(float(np.hypot(*(answer.position_enu[:2] - epoch.truth_enu[:2]))))
    return {"arrivals": {kind: {"count": len(v), "median_m": _median(v), "median_abs_m": _median(np.abs(v))}
                         for kind, v in lags.items()},
            "published": {kind: {"count": len(v), "median_m": _median(v)} for kind, v in poses.items()}}


def _median(values) -> float | None:
    return float(np.median(values)) if len(values) else None


def measure(route: str, seed: int, maps: dict[str, BiasMap], figure: Path | None = None) -> dict:
    """One bag's numbers; ``figure``: its route map with a GNSS fix a minute and the traced map,
    over the scene's buildings."""
    bag = f"{route}_day_s{seed}"
    replay, towers, pipeline = rs.replayed(route, rs.BAGS / bag)
    config = pipeline.fusion
    plain = fuse_route(replay, towers, config)
    twin = build_twin(parse_scenario(rs.scenario_for(route, "day", seed)))
    row = {"bag": bag, "configurations": {}, "prediction_error_m": prediction_error(plain, maps["traced map"]),
           "los_split": los_split(plain, twin, config.tracker.max_std_m)}
    for name in CONFIGURATIONS:
        runs = {label: fuse_route(replay, towers, config, aiding=rs.CONFIGURATIONS[name], bias_map=bias_map)
                for label, bias_map in {"no map": None, **maps}.items()}
        row["configurations"][name] = {label: rs.published_summary(run, config.tracker.max_std_m)
                                       for label, run in runs.items()}
        if figure is not None and name == "GNSS 60 s":
            plot_map(runs["traced map"], Anchors(towers), figure, recorded_buildings(replay.source))
    return row


def table(results: dict[str, dict]) -> str:
    lines = []
    for route, result in results.items():
        removed = result["building_removed"]
        lines.append(f"{route}: maps of {result['maps']['traced map']['nodes']} street nodes; trace "
                     f"{result['trace_s']['first']:.0f} s cold, {result['trace_s']['cached']:.1f} s cached; building "
                     f"removed: {removed['building']} (cuts the direct line at "
                     + ", ".join(f"{site} {share:.0%}" for site, share in removed["share_blocked"].items())
                     + " of the route's points)")
        labels = ["no map", *MAP_LABELS]
        lines.append(f"{'bag':22s} {'configuration':12s} " + " ".join(f"{label:>18s}" for label in labels)
                     + "   (median / p90 m, NEES)")
        for row in result["bags"].values():
            for name, variants in row["configurations"].items():
                cells = [f"{_m(v['median_m'])}/{_m(v['p90_m'])} {_m(v['nees_mean'], '{:.1f}')}"
                         for v in variants.values()]
                lines.append(f"{row['bag']:22s} {name:12s} " + " ".join(f"{c:>18s}" for c in cells))
            errors = ", ".join(f"{site} {v['no_map_m']:.0f} -> {v['map_m']:.0f}"
                               for site, v in row["prediction_error_m"].items())
            lines.append(f"{'':22s} per stack, median |bias| left without -> with the map (m): {errors}")
            split = row["los_split"]
            lines.append(f"{'':22s} no map, by line of sight: arrivals' lag (median m) "
                         + ", ".join(f"{kind} {_m(v['median_m'])} ({v['count']})" for kind, v in split["arrivals"].items())
                         + "; published error, no anchor (median m) "
                         + ", ".join(f"{kind} {_m(v['median_m'])} ({v['count']})" for kind, v in split["published"].items()))
    return "\n".join(lines)


def doc_tables(results: dict[str, dict]) -> str:
    """docs/raytracing.md's tables: per route and site the median |bias| left without and with
    the map (the range over the bags where the site is in MIN_STACKS stacks or more), and per bag
    and configuration each map's median / p90 (NEES)."""
    sites = sorted({site for result in results.values() for row in result["bags"].values()
                    for site in row["prediction_error_m"]})
    lines = ["| site | " + " | ".join(f"{route.split('_')[1]}: no map | traced map" for route in results) + " |",
             "|---" * (1 + 2 * len(results)) + "|"]
    for site in sites:
        cells = []
        for result in results.values():
            rows = [row["prediction_error_m"][site] for row in result["bags"].values()
                    if row["prediction_error_m"].get(site, {}).get("stacks", 0) >= MIN_STACKS]
            cells += [rs._span([r["no_map_m"] for r in rows]), rs._span([r["map_m"] for r in rows])]
        if any(cell != "-" for cell in cells):
            lines.append(f"| {site} | " + " | ".join(cells) + " |")
    labels = ["no map", *MAP_LABELS]
    lines += ["", "| route | anchors | " + " | ".join(labels) + " |", "|---" * (2 + len(labels)) + "|"]
    for route, result in results.items():
        for seed, row in result["bags"].items():
            for name, variants in row["configurations"].items():
                cells = [f"{_m(v['median_m'])} / {_m(v['p90_m'])} ({_m(v['nees_mean'], '{:.1f}')})"
                         for v in variants.values()]
                anchors = "none" if name == "no anchor" else name
                lines.append(f"| {route.split('_')[1]}, seed {seed} | {anchors} | " + " | ".join(cells) + " |")
    lines += ["", "| route | arrivals with a direct path (%) | their lag (m) | the others' lag (m) | published "
              "error (m; stacks), every heard site direct | some | none |", "|---" * 7 + "|"]
    for route, result in results.items():
        splits = [row["los_split"] for row in result["bags"].values()]
        share = [s["arrivals"]["los"]["count"] / max(s["arrivals"]["los"]["count"] + s["arrivals"]["nlos"]["count"], 1)
                 for s in splits]
        cells = [rs._span([100 * v for v in share])]
        cells += [rs._span([s["arrivals"][kind]["median_m"] for s in splits]) for kind in ("los", "nlos")]
        cells += [rs._span([s["published"][kind]["median_m"] for s in splits])
                  + f" ({sum(s['published'][kind]['count'] for s in splits)})"
                  for kind in ("all_los", "some_los", "no_los")]
        lines.append(f"| {route.split('_')[1]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _m(value: float | None, style: str = "{:.0f}") -> str:
    return "-" if value is None else style.format(value)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--routes", nargs="+", choices=ROUTES, default=list(ROUTES))
    parser.add_argument("--seeds", nargs="+", type=int, choices=(1, 2, 3), default=[1, 2, 3])
    parser.add_argument("--workers", type=int, default=2, help="processes for making a map (default 2)")
    args = parser.parse_args()
    missing = [f"{route}_day_s{seed}" for route in args.routes for seed in args.seeds
               if not (rs.BAGS / f"{route}_day_s{seed}").exists()]
    if missing:
        parser.exit(2, f"traced_maps: missing route-set bags {', '.join(missing)}: make them with "
                       f"benchmarks/fusion/route_set.py --bags-only --routes {' '.join(args.routes)} --loads day\n")
    runner = JobRunner(args.workers)
    kept = json.loads(OUT.read_text()) if OUT.is_file() else {}
    results = {route: kept[route] for route in ROUTES if route in kept and route not in args.routes}
    for route in args.routes:
        removed = blocking_building(route)
        print(f"== {route}: building removed for the wrong map: {removed}", flush=True)
        scenarios = dict(zip(MAP_LABELS, (scenario_file(route), site_off(route),
                                          building_removed(route, removed["meshes"]))))
        made = {label: traced(path, runner) for label, path in scenarios.items()}
        maps = {label: bias_map for label, (bias_map, _) in made.items()}
        result = {"building_removed": removed, "maps": {label: info for label, (_, info) in made.items()},
                  "trace_s": trace_seconds(route), "bags": {}}
        for seed in args.seeds:
            print(f"== {route} seed {seed}", flush=True)
            result["bags"][str(seed)] = measure(route, seed, maps, FIGURES[route] if seed == args.seeds[0] else None)
        results[route] = result
    results = {route: results[route] for route in ROUTES if route in results}
    print(table(results))
    print("\n" + doc_tables(results))
    OUT.write_text(json.dumps(results, indent=1))
    print(f"written: {OUT}")


if __name__ == "__main__":
    main()
