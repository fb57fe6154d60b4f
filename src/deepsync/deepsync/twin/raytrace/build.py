"""The ray-traced channel of a scenario: its scene, placement checks, traces (cached), channel."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from tqdm import tqdm

from deepsync.geo import LocalFrame
from deepsync.twin.raytrace.channel import RayTracedChannel, route_samples
from deepsync.twin.raytrace.scenes import open_scene
from deepsync.twin.raytrace.sites import check_antennas, check_route
from deepsync.twin.raytrace.tracing import trace_paths
from deepsync.twin.route import Trajectory
from deepsync.twin.scenario import RayTracingSettings, Scenario
from deepsync.twin.statistical_channel import Transmitter


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/deepsync/raytrace`` (``~/.cache/deepsync/raytrace`` without it)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "deepsync" / "raytrace"


def raytraced_channel(settings: RayTracingSettings, scenario: Scenario, frame: LocalFrame,
                      transmitters: Sequence[Transmitter], receiver: Trajectory) -> RayTracedChannel:
    """Open the scene, check that no antenna and no part of the route is inside a building
    (ConfigError naming it), trace every site once per carrier to the route's sample points
    (or load the traces from the cache) and make the channel."""
    cache_dir = Path(settings.cache_dir).expanduser() if settings.cache_dir else default_cache_dir()
    origin = settings.scene_origin
    scene = open_scene(settings.scene, frame, cache_dir, where="scenario.channel.scene",
                       scene_origin=None if origin is None else (origin.latitude_deg, origin.longitude_deg),
                       default_building_height_m=settings.default_building_height_m)
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
    links = sorted({(tx.site, tx.carrier_hz) for tx in transmitters}, key=str)
    traces = {}
    with tqdm(total=len(links) * len(points), desc="ray tracing", unit="point", disable=None) as bar:
        for site, carrier_hz in links:
            traces[site, carrier_hz] = trace_paths(scene, first[site].position_enu, carrier_hz, points,
                                                   settings.trace_settings, cache_dir, bar)
    return RayTracedChannel(transmitters, receiver, along, [traces[tx.site, tx.carrier_hz] for tx in transmitters],
                            scenario.seed)
