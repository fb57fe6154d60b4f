"""Ray-tracing speed and what the solver settings change: a walk through Munich (Sionna RT's
bundled scene) traced to six three-sector sites on the tallest rooftops, timed cold (every
site traced) and from the cache, and the same walk under other solver settings.

The route: 250 m across Marienhof and up a street north of it, a traced point every metre (251
points); the sites: ``rooftops(scene, 6)``, antennas 3 m above the roof, one carrier (EARFCN
300, 2140 MHz), so each site is traced once for its three sectors. Per setting it reports the
share of route points that receive any path and a direct one from each site, the first path's
excess delay over the straight line (median and 90th percentile where any path arrives) of the
first path within 15 dB of the strongest, and the trace time.

Run:  .venv/bin/python benchmarks/speed/raytrace_speed.py [--settings-points 42]
Writes docs/results/raytrace_speed.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from deepsync.twin import build_twin
from deepsync.twin.raytrace.scenes import bundled_origin, open_scene
from deepsync.twin.raytrace.sites import rooftops, three_sector_site
from deepsync.twin.raytrace.tracing import TraceSettings, trace_paths
from deepsync.twin.scenario import parse_scenario
from deepsync.types import SPEED_OF_LIGHT_M_S

OUT = Path(__file__).resolve().parents[2] / "docs" / "results" / "raytrace_speed.json"
GROUND_HEIGHT_M = 520.0  # Munich's old town, ellipsoidal (about 519 m above sea level + 47 m of geoid, rounded)
ROUTE_ENU = [(150.0, 92.0), (8.0, 92.0), (8.0, 200.0)]  # scene metres, checked against its buildings
MAST_M = 3.0
STRONG_WINDOW_DB = 15.0
EARFCN = 300
VARIANTS = {
    "default": TraceSettings(),
    "no diffraction": TraceSettings(diffraction=False),
    "no refraction": TraceSettings(refraction=False),
    "max_depth 2": TraceSettings(max_depth=2),
    "max_depth 5": TraceSettings(max_depth=5),
    "diffuse": TraceSettings(diffuse=True),
}


def scenario(frame, scene) -> dict:
    sites = []
    for n, roof in enumerate(rooftops(scene, 6)):
        lat, lon, _ = frame.enu_to_geodetic(roof.position_enu)
        sites.append(three_sector_site(f"S{n}", float(lat), float(lon), roof.height_m + MAST_M, 10 + n, EARFCN))
    waypoints = []
    for east, north in ROUTE_ENU:
        lat, lon, _ = frame.enu_to_geodetic(np.array([east, north, 0.0]))
        waypoints.append({"latitude_deg": float(lat), "longitude_deg": float(lon)})
    return {"name": "munich_walk", "seed": 1,
            "origin": {"latitude_deg": frame.latitude_deg, "longitude_deg": frame.longitude_deg,
                       "height_m": GROUND_HEIGHT_M},
            "sites": sites, "receiver": {"height_m": 1.5, "route": {"speed_mps": 1.4, "waypoints": waypoints}}}


def summary(traced, positions) -> dict:
    heard = traced.valid.any(axis=1)
    los = traced.los.any(axis=1)
    straight = np.linalg.norm(positions - traced.transmitter_enu, axis=1) / SPEED_OF_LIGHT_M_S
    power = np.where(traced.valid, np.abs(traced.gains) ** 2, 0.0)
    # the earliest path within STRONG_WINDOW_DB of the strongest: what a timing estimator can
    # lock to (an earlier path 40 dB down, through three buildings, it cannot)
    strong = traced.valid & (power >= power.max(axis=1, keepdims=True) * 10 ** (-STRONG_WINDOW_DB / 10))
    first = np.where(strong, traced.delays_s, np.inf).min(axis=1)
    excess_m = (first - straight)[heard] * SPEED_OF_LIGHT_M_S
    return {"heard": float(heard.mean()), "los": float(los.mean()), "excess_m": excess_m,
            "paths_per_point": float(traced.valid.sum(axis=1).mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--settings-points", type=int, default=42,
                        help="route points traced per solver setting (every k-th of the route's)")
    args = parser.parse_args()
    frame = bundled_origin("munich", GROUND_HEIGHT_M)
    with tempfile.TemporaryDirectory() as cache:
        started = time.perf_counter()
        scene = open_scene("munich", frame, cache)
        buildings = len(scene.buildings.buildings)
        scene_s = time.perf_counter() - started
        data = scenario(frame, scene)
        data["channel"] = {"model": "raytraced", "scene": "munich", "cache_dir": cache}
        parsed = parse_scenario(data)
        started = time.perf_counter()
        twin = build_twin(parsed)
        cold_s = time.perf_counter() - started
        started = time.perf_counter()
        build_twin(parsed)
        cached_s = time.perf_counter() - started
        points = len(twin.channel.traced(0))
        print(f"scene: {buildings} buildings from the meshes in {scene_s:.1f} s; route {twin.receiver.length_m:.0f} m, "
              f"{points} points, {len(parsed.sites)} sites x 3 sectors")
        print(f"trace (cold, first compilation included): {cold_s:.1f} s; from the cache: {cached_s:.2f} s")
        positions = twin.channel.traced(0).receivers_enu
        pick = np.linspace(0, points - 1, min(args.settings_points, points)).round().astype(int)
        sites = {cell.site: i for i, cell in reversed(list(enumerate(twin.cells)))}
        variants = {}
        for name, settings in VARIANTS.items():
            started = time.perf_counter()
            per_site = [summary(trace_paths(scene, twin.sites[s].position_enu, twin.cells[i].carrier_hz,
                                            positions[pick], settings), positions[pick])
                        for s, i in enumerate(sites.values())]
            seconds = time.perf_counter() - started
            excess = np.concatenate([site["excess_m"] for site in per_site])
            variants[name] = {"settings": dataclasses.asdict(settings), "seconds": seconds,
                              "heard": float(np.mean([s["heard"] for s in per_site])),
                              "los": float(np.mean([s["los"] for s in per_site])),
                              "paths_per_point": float(np.mean([s["paths_per_point"] for s in per_site])),
                              "strong_path_excess_median_m": float(np.median(excess)),
                              "strong_path_excess_p90_m": float(np.percentile(excess, 90))}
            v = variants[name]
            print(f"{name:15s} {seconds:6.1f} s  heard {v['heard']:.0%}  LOS {v['los']:.0%}  "
                  f"paths/point {v['paths_per_point']:.1f}  excess of the first strong path: median "
                  f"{v['strong_path_excess_median_m']:.1f} m, p90 {v['strong_path_excess_p90_m']:.1f} m")
    result = {"machine": {"cpus": os.cpu_count(), "processor": platform.processor() or platform.machine()},
              "scene": "munich", "buildings": buildings, "route_m": twin.receiver.length_m, "points": points,
              "sites": len(parsed.sites), "sectors": len(twin.cells), "scene_seconds": scene_s,
              "trace_seconds": cold_s, "cached_seconds": cached_s, "settings_points": int(len(pick)), "strong_window_db": STRONG_WINDOW_DB,
              "variants": variants}
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
