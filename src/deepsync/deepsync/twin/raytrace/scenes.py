"""Scenes to trace in, tied to the map frame: Sionna RT's bundled cities by name, a user's
Mitsuba scene with its WGS84 origin, or a user's GeoJSON footprints extruded into a scene.

A scene's x, y, z are east, north and up (m) of the ENU tangent plane at its WGS84 origin (the
Blender-OSM convention Sionna's cities were made with), its ground flat at z = 0, which is the
map frame's ground (the scenario origin's ellipsoidal height). Points and directions go between
the two frames through ECEF (``deepsync.geo``), exactly.

The bundled cities carry no coordinates of their own: their origins below were located from one
landmark each (its mesh in the scene against its published position), good to a few tens of
metres. San Francisco is not offered: its ground is terrain (hills), and the twin's is flat.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from deepsync.configio import ConfigError
from deepsync.geo import LocalFrame
from deepsync.twin.raytrace.backend import sionna_rt
from deepsync.twin.raytrace.buildings import (
    Building,
    BuildingIndex,
    buildings_from_scene,
    read_footprints,
    scene_mesh_files,
    scene_shapes,
)
from deepsync.twin.raytrace.city import write_city_scene


@dataclass(frozen=True)
class Landmark:
    """Where a bundled scene sits on the earth: a landmark's scene x/y (m) and its WGS84 position."""

    name: str
    scene_x_m: float
    scene_y_m: float
    latitude_deg: float
    longitude_deg: float


# the landmark's x/y: the centre of its meshes' bounding box in the scene
BUNDLED_SCENES: dict[str, Landmark] = {
    "munich": Landmark("Frauenkirche", -163.2, 65.7, 48.138611, 11.573333),
    "florence": Landmark("Cattedrale di Santa Maria del Fiore", 95.5, -26.7, 43.773056, 11.256111),
    "etoile": Landmark("Arc de Triomphe", -127.3, 38.1, 48.873889, 2.295000),
}
GEOJSON_SUFFIXES = (".geojson", ".json")


@dataclass(frozen=True)
class RayScene:
    """A scene file and where it lies: ``frame`` is the ENU frame of its x/y/z, ``map_frame``
    the twin's. ``removed``: objects of the XML taken out before tracing (Sionna's
    ``Scene.edit``). ``digest`` hashes the XML, every mesh it loads and what is removed (the
    trace cache's key). ``footprints``: the buildings it was made from, where known (else
    derived from its meshes)."""

    xml_path: Path
    frame: LocalFrame
    map_frame: LocalFrame
    name: str
    footprints: tuple[Building, ...] | None = field(default=None, repr=False, compare=False)
    removed: tuple[str, ...] = ()
    digest: str = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "digest", scene_digest(self.xml_path, self.removed))

    @cached_property
    def buildings(self) -> BuildingIndex:
        """The scene's buildings (footprints, roof heights), in *scene* x/y; none that is removed."""
        buildings = self.footprints if self.footprints is not None else buildings_from_scene(self.xml_path)
        return BuildingIndex([b for b in buildings if b.name not in self.removed])

    def to_scene(self, points_enu: ArrayLike) -> np.ndarray:
        """Map-frame ENU points (trailing axis of 3) in scene x/y/z."""
        return self.frame.ecef_to_enu(self.map_frame.enu_to_ecef(points_enu))

    def to_map(self, points_xyz: ArrayLike) -> np.ndarray:
        """Scene x/y/z points in the map frame's ENU."""
        return self.map_frame.ecef_to_enu(self.frame.enu_to_ecef(points_xyz))

    def directions_to_map(self, directions_xyz: ArrayLike) -> np.ndarray:
        """Scene-frame direction vectors turned into the map frame's axes."""
        return self.to_map(directions_xyz) - self.to_map(np.zeros(3))


def bundled_origin(name: str, ground_height_m: float) -> LocalFrame:
    """The ENU frame of bundled scene ``name`` (its x/y/z), ground at ``ground_height_m``."""
    mark = BUNDLED_SCENES[name]
    at_landmark = LocalFrame(mark.latitude_deg, mark.longitude_deg, ground_height_m)
    lat, lon, _ = at_landmark.enu_to_geodetic(np.array([-mark.scene_x_m, -mark.scene_y_m, 0.0]))
    return LocalFrame(float(lat), float(lon), ground_height_m)


def scene_digest(xml_path: Path, removed: tuple[str, ...] = ()) -> str:
    """SHA-256 over the scene XML, every mesh file it names, the objects ``removed`` from it and
    the Sionna RT version."""
    digest = hashlib.sha256(importlib.metadata.version("sionna-rt").encode())
    for path in (xml_path, *scene_mesh_files(xml_path)):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    for name in sorted(removed):
        digest.update(b"removed\0" + name.encode() + b"\0")
    return digest.hexdigest()


def check_scene_spec(spec: str, has_origin: bool) -> None:
    """ValueError unless ``spec`` names a bundled scene, a GeoJSON file or a Mitsuba XML (which
    needs an origin: ``has_origin``)."""
    if spec in BUNDLED_SCENES:
        return
    path = Path(spec)
    if not path.is_file():
        raise ValueError(f"{spec!r} is neither a bundled scene ({', '.join(BUNDLED_SCENES)}) nor a file")
    suffix = path.suffix.lower()
    if suffix == ".xml" and not has_origin:
        raise ValueError(f"{spec!r}: a Mitsuba scene needs scene_origin {{latitude_deg, longitude_deg}} "
                         f"of its x = y = 0")
    if suffix not in (*GEOJSON_SUFFIXES, ".xml"):
        raise ValueError(f"{spec!r}: a scene file must be GeoJSON (.geojson, .json) or a Mitsuba scene (.xml)")


def open_scene(spec: str, map_frame: LocalFrame, cache_dir: str | Path, *,
               scene_origin: tuple[float, float] | None = None,
               default_building_height_m: float | None = None, remove: Sequence[str] = (),
               where: str = "scene", where_remove: str = "remove_buildings") -> RayScene:
    """The scene ``spec`` names (``check_scene_spec``): a bundled city (its buildings from its
    meshes), a GeoJSON of footprints (extruded once into ``cache_dir``, in the map frame; its
    buildings as given) or a Mitsuba XML whose x = y = 0 is ``scene_origin`` (latitude,
    longitude). ``remove``: buildings to leave out, by name (a mesh's object name in a Mitsuba
    scene, e.g. ``Neues_Rathaus-itu_marble``; a footprint's ``name`` or ``feature <index>``).
    ConfigError naming ``where`` for a spec that is none of these, ``where_remove[k]`` for a
    name the scene does not hold."""
    try:
        check_scene_spec(spec, scene_origin is not None)
    except ValueError as error:
        raise ConfigError(f"{where}: {error}") from None
    remove = tuple(remove)
    if spec in BUNDLED_SCENES or Path(spec).suffix.lower() == ".xml":
        if spec in BUNDLED_SCENES:
            xml, frame = Path(getattr(sionna_rt().scene, spec)), bundled_origin(spec, map_frame.height_m)
        else:
            xml, frame = Path(spec), LocalFrame(scene_origin[0], scene_origin[1], map_frame.height_m)
        _check_removable(remove, set(scene_shapes(xml)), where_remove, spec)
        return RayScene(xml, frame, map_frame, spec if spec in BUNDLED_SCENES else xml.stem, removed=remove)
    path = Path(spec)
    buildings = read_footprints(path, map_frame, default_building_height_m)
    _check_removable(remove, {b.name for b in buildings}, where_remove, spec)
    buildings = tuple(b for b in buildings if b.name not in remove)
    if not buildings:
        raise ConfigError(f"{where_remove}: removes every building of {spec!r}")
    inputs = repr((map_frame.latitude_deg, map_frame.longitude_deg, map_frame.height_m, default_building_height_m,
                   sorted(remove)))
    digest = hashlib.sha256(path.read_bytes() + inputs.encode()).hexdigest()[:16]
    directory = Path(cache_dir) / "scenes" / f"{path.stem}-{digest}"
    xml = directory / "scene.xml"
    if not xml.is_file():  # written last: a scene cut short is written again
        write_city_scene(buildings, directory)
    return RayScene(xml, map_frame, map_frame, path.stem, buildings)


def _check_removable(remove: tuple[str, ...], names: set[str], where: str, spec: str) -> None:
    for k, name in enumerate(remove):
        if name not in names:
            close = sorted(n for n in names if n.lower().startswith(name.lower()[:6]))[:4]
            raise ConfigError(f"{where}[{k}]: scene {spec!r} has no building {name!r}"
                              + (f" (similar: {', '.join(close)})" if close else ""))
