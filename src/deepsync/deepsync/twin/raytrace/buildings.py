"""Buildings as footprints with roof heights, in a scene's x/y/z (east, north, up) frame.

Two sources: a GeoJSON file of building footprints (an OpenStreetMap export: WGS84 polygons
with ``height`` in metres or ``building:levels``), and the meshes of a Mitsuba scene (Sionna's
bundled cities), whose footprint is the union of the projections of their non-vertical faces.
Rooftops for towers and the check that a route stays in the streets use them.
"""

from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ElementTree
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deepsync.configio import ConfigError, read_config_bytes
from deepsync.geo import LocalFrame

LEVEL_HEIGHT_M = 3.0  # a storey, for footprints that give building:levels and no height
GROUND_MESH_NAMES = ("ground", "terrain", "floor", "plane")  # a scene's mesh that is no building
_LEADING_NUMBER = re.compile(r"\s*([-+]?\d+(?:\.\d*)?)")


@dataclass(frozen=True)
class Building:
    """One building (or one part of one): ``footprint`` a shapely Polygon in scene x/y (m),
    ``height_m`` its roof above the ground, ``name`` where it came from (a GeoJSON feature's
    ``name`` or index, a mesh file's stem)."""

    footprint: object  # shapely.Polygon (shapely is optional: not in the annotation)
    height_m: float
    name: str


def read_footprints(path: str | Path, frame: LocalFrame, default_height_m: float | None = None
                    ) -> tuple[Building, ...]:
    """Buildings of a GeoJSON FeatureCollection (RFC 7946: lon/lat in WGS84) in ``frame``'s
    east/north metres. A feature's height is its ``height`` property (m; "12 m" reads as 12),
    else ``building:levels`` x LEVEL_HEIGHT_M, else ``default_height_m``; ConfigError naming
    the feature when it has none, and for anything that is not a polygon of a building."""
    import shapely  # noqa: PLC0415 (optional extra)

    where = str(path)
    try:
        data = json.loads(read_config_bytes(path, where))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ConfigError(f"{where}: not a GeoJSON file ({error})") from None
    if not (isinstance(data, dict) and data.get("type") == "FeatureCollection"
            and isinstance(data.get("features"), list)):
        raise ConfigError(f"{where}: expected a GeoJSON FeatureCollection with a 'features' list")
    buildings = []
    for index, feature in enumerate(data["features"]):
        at = f"{where}: features[{index}]"
        geometry = feature.get("geometry") if isinstance(feature, dict) else None
        properties = (feature.get("properties") or {}) if isinstance(feature, dict) else {}
        if not isinstance(geometry, dict) or geometry.get("type") not in ("Polygon", "MultiPolygon"):
            kind = geometry.get("type") if isinstance(geometry, dict) else type(geometry).__name__
            raise ConfigError(f"{at}: a building footprint must be a Polygon or MultiPolygon, got {kind}")
        height = _feature_height(properties, default_height_m, at)
        name = str(properties.get("name") or f"feature {index}")
        rings = [geometry["coordinates"]] if geometry["type"] == "Polygon" else geometry["coordinates"]
        for part, polygon in enumerate(rings):
            try:
                shells = [np.asarray(ring, dtype=np.float64)[:, :2] for ring in polygon]
                local = [frame.geodetic_to_enu(ring[:, 1], ring[:, 0], frame.height_m)[:, :2] for ring in shells]
                footprint = shapely.make_valid(shapely.Polygon(local[0], local[1:]))
            except (ValueError, IndexError, TypeError) as error:
                raise ConfigError(f"{at}: malformed polygon coordinates ({error})") from None
            if footprint.area <= 0:
                raise ConfigError(f"{at}: the footprint has no area")
            for piece in getattr(footprint, "geoms", [footprint]):
                if piece.geom_type == "Polygon" and piece.area > 0:
                    buildings.append(Building(piece, height, name if len(rings) == 1 else f"{name} part {part}"))
    if not buildings:
        raise ConfigError(f"{where}: no building footprints")
    return tuple(buildings)


def _feature_height(properties: dict, default_height_m: float | None, at: str) -> float:
    for key, scale in (("height", 1.0), ("building:levels", LEVEL_HEIGHT_M)):
        value = properties.get(key)
        if value is None:
            continue
        match = _LEADING_NUMBER.match(str(value))
        number = float(match.group(1)) * scale if match else math.nan
        if not (math.isfinite(number) and 0 < number <= 1000):
            raise ConfigError(f"{at}: {key} {value!r} is not a height in (0, 1000] m")
        return number
    if default_height_m is None:
        raise ConfigError(f"{at}: has neither 'height' nor 'building:levels' (give the channel's "
                          f"default_building_height_m to extrude such footprints)")
    return float(default_height_m)


def buildings_from_scene(xml_path: str | Path) -> tuple[Building, ...]:
    """Buildings of a Mitsuba scene: one per PLY mesh that is not the ground, named as Sionna
    names the mesh's object (``scene_shapes``), its footprint the union of its non-vertical faces
    projected on the ground, its height its highest vertex."""
    import shapely  # noqa: PLC0415
    import trimesh  # noqa: PLC0415

    xml_path = Path(xml_path)
    buildings = []
    for name, mesh_path in scene_shapes(xml_path).items():
        if any(word in name.lower() for word in GROUND_MESH_NAMES):
            continue
        mesh = trimesh.load(mesh_path, process=False, force="mesh")
        if len(mesh.faces) == 0:
            continue
        flat = np.abs(mesh.face_normals[:, 2]) > 1e-3  # walls project to lines
        triangles = [shapely.Polygon(t) for t in mesh.triangles[flat][:, :, :2]]
        footprint = shapely.union_all([t for t in triangles if t.area > 1e-6])
        for piece in getattr(footprint, "geoms", [footprint]):
            if piece.geom_type == "Polygon" and piece.area > 1.0:
                buildings.append(Building(piece, float(mesh.vertices[:, 2].max()), name))
    return tuple(buildings)


def scene_shapes(xml_path: Path) -> dict[str, Path]:
    """The mesh shapes of a Mitsuba scene XML: the name Sionna RT gives each one's object (the
    shape's id less a leading ``mesh-``, as ``sionna.rt.SceneObject.shape_id_to_name``; its
    file's stem where it has no id) -> its mesh file."""
    shapes = {}
    for shape in ElementTree.parse(xml_path).getroot().iter("shape"):
        files = [node.get("value") for node in shape.iter("string") if node.get("name") == "filename"]
        if files:
            name = shape.get("id") or Path(files[0]).stem
            shapes[name.removeprefix("mesh-")] = xml_path.parent / files[0]
    return shapes


def scene_mesh_files(xml_path: Path) -> list[Path]:
    """The mesh files a Mitsuba scene XML loads (its ``filename`` strings), in file order."""
    root = ElementTree.parse(xml_path).getroot()
    return [xml_path.parent / node.get("value") for node in root.iter("string")
            if node.get("name") == "filename"]


class BuildingIndex:
    """Buildings with a spatial index (shapely's STRtree): which one holds a point, which one a
    segment passes through."""

    def __init__(self, buildings: Sequence[Building]) -> None:
        import shapely  # noqa: PLC0415

        self.buildings = tuple(buildings)
        self._shapely = shapely
        self._tree = shapely.STRtree([b.footprint for b in self.buildings])
        # shrunk by a millimetre: a segment along a wall or a point on it is outside
        self._insides = [b.footprint.buffer(-1e-3) for b in self.buildings]

    def at(self, x: float, y: float, z: float | None = None) -> Building | None:
        """The building whose footprint holds (x, y) below its roof (at any height when ``z``
        is None), or None."""
        point = self._shapely.Point(x, y)
        for i in sorted(self._tree.query(point)):
            building = self.buildings[i]
            if (z is None or z < building.height_m) and self._insides[i].covers(point):
                return building
        return None

    def crossed(self, start: Sequence[float], end: Sequence[float]) -> Building | None:
        """A building the straight ground segment from ``start`` to ``end`` (x, y) passes
        through (running along a wall is allowed), or None."""
        segment = self._shapely.LineString([tuple(start[:2]), tuple(end[:2])])
        for i in sorted(self._tree.query(segment)):
            if segment.intersects(self._insides[i]):
                return self.buildings[i]
        return None
