"""Sites and routes on a scene: rooftops for towers, three-sector sites as scenario entries,
and the check that a route stays in the streets and no antenna sits inside a building."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from deepsync.configio import ConfigError
from deepsync.twin.raytrace.scenes import RayScene

SECTOR_AZIMUTHS_DEG = (0.0, 120.0, 240.0)


@dataclass(frozen=True)
class Rooftop:
    """A roof a tower may stand on: a point inside the building's footprint, in the map frame at
    roof height (``position_enu``), the roof's ``height_m`` above ground and the footprint's area."""

    building: str
    position_enu: np.ndarray
    height_m: float
    area_m2: float


def rooftops(scene: RayScene, count: int, *, min_area_m2: float = 200.0, max_height_m: float = 60.0,
             min_separation_m: float = 150.0) -> list[Rooftop]:
    """Up to ``count`` candidate rooftops, tallest first: buildings of at least ``min_area_m2``
    footprint and at most ``max_height_m`` (a church spire is no mast), each at least
    ``min_separation_m`` from those already chosen, so the sites spread over the scene."""
    chosen: list[Rooftop] = []
    for building in sorted(scene.buildings.buildings, key=lambda b: -b.height_m):
        if len(chosen) == count:
            break
        if building.footprint.area < min_area_m2 or building.height_m > max_height_m:
            continue
        point = building.footprint.representative_point()  # inside, even for an L-shaped block
        position = scene.to_map(np.array([point.x, point.y, building.height_m]))
        if all(np.hypot(*(position - other.position_enu)[:2]) >= min_separation_m for other in chosen):
            chosen.append(Rooftop(building.name, position, building.height_m, float(building.footprint.area)))
    return chosen


def three_sector_site(name: str, latitude_deg: float, longitude_deg: float, height_m: float,
                      n_id_1: int, earfcn: int, *, bandwidth_mhz: float = 10.0, eirp_dbm: float = 60.0,
                      downtilt_deg: float = 6.0) -> dict:
    """A scenario's site entry (the YAML mapping) with three sectors at 0/120/240 deg on one
    carrier, PCIs 3 n_id_1 + 0, 1, 2 (one PCI group, as operators plan them)."""
    cells = [{"pci": 3 * n_id_1 + sector, "earfcn": earfcn, "bandwidth_mhz": bandwidth_mhz,
              "eirp_dbm": eirp_dbm, "azimuth_deg": azimuth, "downtilt_deg": downtilt_deg}
             for sector, azimuth in enumerate(SECTOR_AZIMUTHS_DEG)]
    return {"name": name, "latitude_deg": latitude_deg, "longitude_deg": longitude_deg,
            "height_m": height_m, "cells": cells}


def check_route(scene: RayScene, waypoints_enu: ArrayLike, where: str, *, closed: bool = False) -> None:
    """ConfigError naming the waypoint (``where[k]``) that lies inside a building, or the pair of
    waypoints whose straight segment passes through one; ``closed``: the last one leads back to
    the first (a looping route)."""
    points = scene.to_scene(np.asarray(waypoints_enu, dtype=np.float64).reshape(-1, 3))
    for k, (x, y, z) in enumerate(points.tolist()):
        building = scene.buildings.at(x, y, z)
        if building is not None:
            raise ConfigError(f"{where if len(points) == 1 else f'{where}[{k}]'}: inside building {building.name!r} "
                              f"(roof {building.height_m:.0f} m) of scene {scene.name!r}")
    legs = list(zip(range(len(points) - 1), range(1, len(points))))
    if closed and len(points) > 2:
        legs.append((len(points) - 1, 0))
    for a, b in legs:
        building = scene.buildings.crossed(points[a], points[b])
        if building is not None:
            raise ConfigError(f"{where}: the leg from waypoint {a} to waypoint {b} passes through "
                              f"building {building.name!r} of scene {scene.name!r}")


def check_antennas(scene: RayScene, antennas: Sequence[tuple[str, np.ndarray]]) -> None:
    """ConfigError naming the antenna (``where``, position in the map frame) that sits inside a
    building, below its roof: every path of it would start inside a wall."""
    for where, position in antennas:
        x, y, z = scene.to_scene(position).tolist()
        building = scene.buildings.at(x, y, z)
        if building is not None:
            raise ConfigError(f"{where}: the antenna ({z:.1f} m above ground) is inside building "
                              f"{building.name!r} (roof {building.height_m:.1f} m) of scene {scene.name!r}: "
                              f"raise it above the roof or move it")


def street_grid(scene: RayScene, route_enu: ArrayLike, margin_m: float, height_m: float,
                step_m: float) -> np.ndarray:
    """(N, 3) map-frame points every ``step_m`` within ``margin_m`` of a route (the polyline
    through ``route_enu``'s (K, 2 or 3) east/north points; one point: a disc around it),
    ``height_m`` up, outside every building: where a receiver near it can stand (a street, a
    square, a yard). The grid starts at the route's south-west corner less the margin."""
    import shapely  # noqa: PLC0415 (optional extra)

    route = np.asarray(route_enu, dtype=np.float64)
    if not (step_m > 0 and margin_m >= 0 and route.ndim == 2 and route.shape[1] in (2, 3) and len(route)
            and np.all(np.isfinite(route))):
        raise ValueError(f"a street grid needs a positive step, a margin >= 0 and a route of finite east/north "
                         f"points, got step {step_m!r}, margin {margin_m!r}, route of shape {route.shape}")
    route = route[:, :2]
    lower, upper = route.min(axis=0) - margin_m, route.max(axis=0) + margin_m
    east = lower[0] + step_m * np.arange(int(np.floor((upper[0] - lower[0]) / step_m + 1e-9)) + 1)
    north = lower[1] + step_m * np.arange(int(np.floor((upper[1] - lower[1]) / step_m + 1e-9)) + 1)
    grid = np.stack(np.meshgrid(east, north), axis=-1).reshape(-1, 2)
    path = shapely.Point(route[0]) if len(route) == 1 else shapely.LineString(route)
    # + 1 um: the grid's first column and row lie on the margin, and a waypoint's round trip
    # through latitude and longitude must not drop them
    grid = grid[shapely.distance(path, shapely.points(grid)) <= margin_m + 1e-6]
    points = np.column_stack([grid, np.full(len(grid), float(height_m))])
    inside = [scene.buildings.at(x, y, z) is not None for x, y, z in scene.to_scene(points).tolist()]
    return points[~np.asarray(inside, dtype=bool)]
