"""The ray-traced channel of a scenario: its scene, placement checks, traces (cached), channel."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from deepsync.geo import LocalFrame
from deepsync.twin.raytrace.channel import RayTracedChannel, route_samples
from deepsync.twin.raytrace.scenes import RayScene, open_scene
from deepsync.twin.raytrace.sites import check_antennas, check_route
from deepsync.twin.raytrace.tracing import TracedPaths, trace_paths
from deepsync.twin.route import Trajectory
from deepsync.twin.scenario import RayTracingSettings, Scenario
from deepsync.twin.statistical_channel import Transmitter


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/deepsync/raytrace`` (``~/.cache/deepsync/raytrace`` without it)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "deepsync" / "raytrace"


def scenario_scene(settings: RayTracingSettings, frame: LocalFrame) -> RayScene:
    """The scene a ray-traced scenario names, tied to its map frame."""
    origin = settings.scene_origin
    return open_scene(settings.scene, frame, cache_dir(settings), where="scenario.channel.scene",
                      scene_origin=None if origin is None else (origin.latitude_deg, origin.longitude_deg),
                      default_building_height_m=settings.default_building_height_m,
                      remove=settings.remove_buildings, where_remove="scenario.channel.remove_buildings")


def cache_dir(settings: RayTracingSettings) -> Path:
    """Where a scenario's scenes and traces are cached (its ``cache_dir``, else the default)."""
    return Path(settings.cache_dir).expanduser() if settings.cache_dir else default_cache_dir()


def trace_sites(settings: RayTracingSettings, scene: RayScene, transmitters: Sequence[Transmitter],
                points_enu: np.ndarray) -> dict[tuple[str, float], TracedPaths]:
    """Every site traced once per carrier to ``points_enu`` (N, 3), or loaded from the cache:
    keyed by (site, carrier in Hz); a site's sectors share its antenna position."""
    first: dict[str, Transmitter] = {}
    for tx in transmitters:
        first.setdefault(tx.site, tx)
    links = sorted({(tx.site, tx.carrier_hz) for tx in transmitters}, key=str)
    traces = {}
    with tqdm(total=len(links) * len(points_enu), desc="ray tracing", unit="point", disable=None) as bar:
        for site, carrier_hz in links:
            traces[site, carrier_hz] = trace_paths(scene, first[site].position_enu, carrier_hz, points_enu,
                                                   settings.trace_settings, cache_dir(settings), bar)
    return traces


def raytraced_channel(settings: RayTracingSettings, scenario: Scenario, frame: LocalFrame,
                      transmitters: Sequence[Transmitter], receiver: Trajectory) -> RayTracedChannel:
    """Open the scene, check that no antenna and no part of the route is inside a building
    (ConfigError naming it), trace every site once per carrier to the route's sample points
    (or load the traces from the cache) and make the channel."""
    scene = scenario_scene(settings, frame)
    site_index = {site.name: i for i, site in enumerate(scenario.sites)}
    first = {}
    for tx in transmitters:
        first.setdefault(tx.site, tx)
    check_antennas(scene, [(f"scenario.sites[{site_index[name]}].height_m", tx.position_enu)
                           for name, tx in first.items()])
    if scenario.receiver.route is None:
        check_route(scene, receiver.waypoints_enu, "scenario.receiver.position")
    else:
        check_route(scene, receiver.waypoints_enu[: len(scenario.receiver.route.waypoints)],
                    "scenario.receiver.route.waypoints", closed=receiver.loop)
    along, points = route_samples(receiver, settings.route_step_m)
    traces = trace_sites(settings, scene, transmitters, points)
    return RayTracedChannel(transmitters, receiver, along, [traces[tx.site, tx.carrier_hz] for tx in transmitters],
                            scenario.seed)


def scenario_footprints(settings: RayTracingSettings, frame: LocalFrame) -> list[np.ndarray]:
    """The outlines of the scene's buildings in the map frame: an (N, 2) east/north ring each."""
    scene = scenario_scene(settings, frame)
    rings = []
    for building in scene.buildings.buildings:
        x, y = building.footprint.exterior.xy
        rings.append(scene.to_map(np.column_stack([x, y, np.zeros(len(x))]))[:, :2])
    return rings
