"""Scenario files: the digital twin's world (sites, cells, receiver, channel model) in YAML.

``load_scenario(path)`` reads and validates a file into frozen dataclasses; every error is a
:class:`~deepsync.configio.ConfigError` naming the field path (``scenario.sites[1].cells[0].pci``).
The schema, with defaults for the optional keys::

    name: campus
    seed: 7                        # every "auto" value and random draw derives from it
    origin: {latitude_deg, longitude_deg, height_m}   # map-frame origin, ellipsoidal height
    environment: {model: UMa, los: auto}              # UMa | UMi; auto | los | nlos
    channel: {model: statistical, profile_los: TDL-D, profile_nlos: TDL-A, delay_spread_ns: auto,
              shadow_fading: true, environment_doppler_hz: 1.0, spatial_consistency: false}
    # or ray-traced (the optional extra deepsync[raytrace]; docs/raytracing.md):
    # channel: {model: raytraced, scene: munich | florence | etoile | footprints.geojson | scene.xml,
    #           scene_origin: {latitude_deg, longitude_deg},   # a scene.xml's x = y = 0 only
    #           default_building_height_m: null,   # for footprints without height or levels
    #           remove_buildings: [],      # buildings of the scene left out, by name
    #           max_depth: 3, diffraction: true, diffuse: false, refraction: true,
    #           samples_per_source: 1000000, route_step_m: 1.0, cache_dir: null}
    sites:
      - name: A
        latitude_deg: ..
        longitude_deg: ..
        height_m: 25               # antenna height above ground
        timing_offset_us: auto     # [0, 10000): frame timing vs common time
        frequency_error_ppb: auto  # oscillator error (auto: uniform +-20 ppb)
        cells:
          - {pci, earfcn, bandwidth_mhz, eirp_dbm, azimuth_deg, downtilt_deg,
             load: 1.0, cfi: 2, modulation_weights: [1/3, 1/3, 1/3],
             antenna: {horizontal_beamwidth_deg: 65, vertical_beamwidth_deg: 10,
                       front_back_db: 30, side_lobe_db: 20}}
    receiver:
      height_m: 1.5
      position: {latitude_deg, longitude_deg}          # exactly one of position ...
      route: {speed_mps, loop: false, waypoints: [{latitude_deg, longitude_deg}, ...]}
    frontend: {}                   # FrontendConfig overrides

``auto`` (or ``null``) values stay ``None`` here; the twin draws them from the seed. The
ground is flat at the origin's ellipsoidal height: every antenna height is above it.

Every number has a physical range (the ``*_RANGE*`` constants below, each with its reason),
and the geometry must fit one LTE neighbourhood: no site and no receiver point farther than
``MAX_DISTANCE_M`` from the origin, and no receiver point farther than that from every site.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from deepsync.configio import ConfigError, build_dataclass, load_yaml, require_list, require_mapping
from deepsync.frontend.config import FrontendConfig
from deepsync.geo import geodetic_to_ecef
from deepsync.lte.cell import CellConfig, check_pci
from deepsync.lte.earfcn import band_of, check_channel, downlink_frequency_hz
from deepsync.lte.numerology import check_bandwidth
from deepsync.twin.antenna import SectorPattern
from deepsync.twin.propagation import MODELS
from deepsync.twin.raytrace.scenes import check_scene_spec
from deepsync.twin.raytrace.tracing import TraceSettings
from deepsync.towers import MapOrigin
from deepsync.twin.tdl import TDL_PROFILES
from deepsync.types import MAX_CELL_RANGE_M

T = TypeVar("T")

LOS_MODES = ("auto", "los", "nlos")
TIMING_OFFSET_RANGE_US = (0.0, 10_000.0)  # one 10 ms frame
AUTO_FREQUENCY_ERROR_PPB = 20.0

# Physical ranges (inclusive) of the scenario's numbers. A value outside is a typo or a unit
# slip (kW for dBm, radians for degrees), never a world the twin should simulate.
# The seed travels in bag provenance and ROS 2 parameters, both int64.
SEED_RANGE = (0, 2**63 - 1)
# Ellipsoidal height of the ground: the Dead Sea shore (-430 m) to Everest (8849 m), plus the
# geoid's undulation (-106..+85 m).
GROUND_HEIGHT_RANGE_M = (-1000.0, 9000.0)
# Antenna above ground: a transmitter on a tripod to the tallest masts (~630 m); a hill under
# a site is not modelled (the ground is flat), so up to 1000 m also stands for a ridge site.
SITE_HEIGHT_RANGE_M = (1.0, 1000.0)
# A receiver on the ground to a drone (TR 36.777's aerial UEs fly up to 300 m; TR 38.901's
# path loss itself is fitted for 1.5..22.5 m).
RECEIVER_HEIGHT_RANGE_M = (0.1, 300.0)
# TS 36.104 (6.5.1) holds a wide-area eNB's carrier within +-50 ppb (local area +-100, home
# +-250). The twin allows +-1000 ppb to simulate a faulty or free-running oscillator, which a
# tracker must survive; beyond that (2 kHz at 2 GHz, 1/8 of a subcarrier) no UE camps.
FREQUENCY_ERROR_RANGE_PPB = (-1000.0, 1000.0)
# Carrier EIRP at boresight: a bench test source or a femtocell behind a wall (-30 dBm) to
# the largest macro sector (2 x 60 W into an 18 dBi panel is ~70 dBm), with margin.
EIRP_RANGE_DBM = (-30.0, 80.0)
# A compass bearing of either sign (-30 is 330); more than a turn is a typo.
AZIMUTH_RANGE_DEG = (-360.0, 360.0)
# Macro panels tilt 0..15 deg (electrical plus mechanical), a rooftop small cell looks down at
# up to ~45 deg; an uptilt towards high floors is a few degrees.
DOWNTILT_RANGE_DEG = (-20.0, 45.0)
# Sector pattern (twin.antenna): panels are 33..120 deg wide and 4..30 deg tall; narrower is a
# dish, wider than a half-plane is no sector. Front-to-back and side-lobe levels of real
# panels are 15..40 dB; beyond 60 dB the scattered environment sets the floor anyway.
ANTENNA_RANGES: dict[str, tuple[float, float, str]] = {
    "horizontal_beamwidth_deg": (10.0, 180.0, "deg"),
    "vertical_beamwidth_deg": (2.0, 90.0, "deg"),
    "front_back_db": (5.0, 60.0, "dB"),
    "side_lobe_db": (5.0, 60.0, "dB"),
}
# RMS delay spread: one path (1 ns) to hilly terrain (COST 207 HT, ~5 us); TR 38.901's
# longest reference value is 1000 ns.
DELAY_SPREAD_RANGE_NS = (1.0, 5000.0)
# Doppler of the moving surroundings of a static receiver: still air (0) to traffic passing at
# highway speed (30 m/s at 2.7 GHz is 270 Hz).
ENVIRONMENT_DOPPLER_RANGE_HZ = (0.0, 300.0)
# Route speed: a slow walk (slower is standing: give a position) to a high-speed train at
# 500 km/h, the highest speed LTE is designed for.
SPEED_RANGE_MPS = (0.1, 140.0)
# Time for one pass of a route: at least one 10 ms frame (shorter moves the receiver between
# two fixes: give a position) and at most a day (longer is not one drive: split it).
ROUTE_DURATION_RANGE_S = (0.01, 86_400.0)
# Ray tracing: interactions per path (0: line of sight only; each more multiplies the time,
# and beyond ~6 a path is far below the first ones), rays per antenna (below 1e4 even street
# reflections are missed; above 1e8 a trace outgrows memory), the spacing of traced route points
# (a decimetre to half a block: the first-order move between them holds over metres) and a
# building's height (a shed to the tallest towers).
MAX_DEPTH_RANGE = (0, 8)
SAMPLES_PER_SOURCE_RANGE = (10_000, 100_000_000)
ROUTE_STEP_RANGE_M = (0.1, 20.0)
BUILDING_HEIGHT_RANGE_M = (1.0, 1000.0)
# At LTE's largest cell range the flat map-frame ground is already ~0.8 km below the real one. No
# scenario point may be farther from the origin, and a receiver farther than that from every
# site hears none of them.
MAX_DISTANCE_M = MAX_CELL_RANGE_M


@dataclass(frozen=True)
class LatLon:
    """A point on the ground: WGS84 latitude and longitude (deg)."""

    latitude_deg: float
    longitude_deg: float


@dataclass(frozen=True)
class Environment:
    """TR 38.901 scenario (``UMa`` or ``UMi`` street canyon) and LOS condition.

    ``los: auto`` draws each site's LOS state with the 38.901 LOS probability.
    """

    model: str = "UMa"
    los: str = "auto"


@dataclass(frozen=True)
class ChannelSettings:
    """Multipath model: TDL profile per LOS state, delay spread (``None`` = drawn from the
    38.901 log-normal), log-normal shadowing on/off, a Doppler floor (Hz) for a changing
    environment around a static receiver, and whether a moving receiver's shadowing and drawn
    delay spread change along its route (38.901 spatial consistency) or keep their first draw."""

    profile_los: str = "TDL-D"
    profile_nlos: str = "TDL-A"
    delay_spread_ns: float | None = None
    shadow_fading: bool = True
    environment_doppler_hz: float = 1.0
    spatial_consistency: bool = False


@dataclass(frozen=True)
class RayTracingSettings:
    """A ray-traced channel (``model: raytraced``): the ``scene`` (a bundled city's name, a
    GeoJSON of footprints or a Mitsuba XML, paths relative to the working directory), Sionna's
    solver settings, the spacing of the traced points along the route (m) and where traces are
    cached (``None``: ``$XDG_CACHE_HOME/deepsync/raytrace``, else ``~/.cache/...``).
    ``remove_buildings``: the scene's buildings to leave out, by name (checked when the scene is
    opened: ``deepsync.twin.raytrace.scenes.open_scene``)."""

    scene: str
    scene_origin: LatLon | None = None
    default_building_height_m: float | None = None
    remove_buildings: tuple[str, ...] = ()
    max_depth: int = TraceSettings.max_depth
    diffraction: bool = TraceSettings.diffraction
    diffuse: bool = TraceSettings.diffuse
    refraction: bool = TraceSettings.refraction
    samples_per_source: int = TraceSettings.samples_per_source
    route_step_m: float = 1.0
    cache_dir: str | None = None

    @property
    def trace_settings(self) -> TraceSettings:
        return TraceSettings(self.max_depth, self.diffraction, self.diffuse, self.refraction,
                             self.samples_per_source)


# the channel models a scenario may name, by their settings (the twin builds the channel of the
# settings' type): the one list
CHANNEL_MODELS: dict[str, type] = {"statistical": ChannelSettings, "raytraced": RayTracingSettings}


@dataclass(frozen=True)
class CellSpec:
    """One sector/carrier of a site: what it sends (``config``), where and how strongly.

    ``eirp_dbm`` is the total EIRP of the carrier at antenna boresight; ``azimuth_deg`` is the
    compass bearing of boresight (clockwise from north); ``downtilt_deg`` the electrical tilt.
    """

    config: CellConfig
    earfcn: int
    eirp_dbm: float
    azimuth_deg: float
    downtilt_deg: float
    antenna: SectorPattern = field(default_factory=SectorPattern)

    @property
    def pci(self) -> int:
        return self.config.pci

    @property
    def bandwidth_mhz(self) -> float:
        return self.config.bandwidth_mhz

    @property
    def band(self) -> int:
        return band_of(self.earfcn)

    @property
    def carrier_hz(self) -> float:
        return downlink_frequency_hz(self.earfcn)


@dataclass(frozen=True)
class SiteSpec:
    """A cell site: one mast, one timing reference and one oscillator shared by its sectors.

    ``height_m`` is the antenna height above ground; ``None`` timing offset (us) or frequency
    error (ppb) means drawn from the scenario seed.
    """

    name: str
    latitude_deg: float
    longitude_deg: float
    height_m: float
    cells: tuple[CellSpec, ...]
    timing_offset_us: float | None = None
    frequency_error_ppb: float | None = None


@dataclass(frozen=True)
class RouteSpec:
    """A walk along ``waypoints`` at constant ``speed_mps``, optionally looping."""

    speed_mps: float
    waypoints: tuple[LatLon, ...]
    loop: bool = False


@dataclass(frozen=True)
class ReceiverSpec:
    """The receiver: antenna height above ground and either a fixed position or a route."""

    height_m: float
    position: LatLon | None = None
    route: RouteSpec | None = None


@dataclass(frozen=True)
class Scenario:
    """A validated scenario file."""

    name: str
    seed: int
    origin: MapOrigin
    environment: Environment
    channel: ChannelSettings | RayTracingSettings
    sites: tuple[SiteSpec, ...]
    receiver: ReceiverSpec
    frontend: FrontendConfig

    @property
    def cells(self) -> tuple[CellSpec, ...]:
        """All cells in scenario order (site by site)."""
        return tuple(cell for site in self.sites for cell in site.cells)


# The YAML mappings with nested parts, as build_dataclass sees them: nested values stay raw
# (``Any``) and are parsed afterwards with their own field paths.


@dataclass(frozen=True)
class _ScenarioKeys:
    name: str
    seed: int
    origin: Any
    sites: Any
    receiver: Any
    environment: Any = None
    channel: Any = None
    frontend: Any = None


@dataclass(frozen=True)
class _SiteKeys:
    name: str
    latitude_deg: float
    longitude_deg: float
    height_m: float
    cells: Any
    timing_offset_us: float | None = None
    frequency_error_ppb: float | None = None


@dataclass(frozen=True)
class _CellKeys:
    pci: int
    earfcn: int
    bandwidth_mhz: float
    eirp_dbm: float
    azimuth_deg: float
    downtilt_deg: float
    load: float = CellConfig.load
    cfi: int = CellConfig.cfi
    modulation_weights: tuple[float, float, float] = CellConfig.modulation_weights
    antenna: Any = None


@dataclass(frozen=True)
class _ReceiverKeys:
    height_m: float
    position: Any = None
    route: Any = None


@dataclass(frozen=True)
class _RouteKeys:
    speed_mps: float
    waypoints: Any
    loop: bool = False


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario YAML file."""
    return parse_scenario(load_yaml(path))


def parse_scenario(data: object, where: str = "scenario") -> Scenario:
    """Validate an already-loaded scenario mapping (see the module docstring for the schema)."""
    keys = build_dataclass(_ScenarioKeys, data, where)
    _require_range(keys.seed, SEED_RANGE, f"{where}.seed")
    origin = build_dataclass(MapOrigin, keys.origin, f"{where}.origin")
    _check_lat_lon(origin, f"{where}.origin")
    _require_range(origin.height_m, GROUND_HEIGHT_RANGE_M, f"{where}.origin.height_m", "m")
    environment = build_dataclass(Environment, _mapping(keys.environment),
                                  f"{where}.environment")
    _require_choice(environment.model, MODELS, f"{where}.environment.model")
    _require_choice(environment.los, LOS_MODES, f"{where}.environment.los")
    channel = _parse_channel(keys.channel, f"{where}.channel")
    sites = _parse_sites(keys.sites, f"{where}.sites")
    receiver = _parse_receiver(keys.receiver, f"{where}.receiver")
    _check_distances(origin, sites, receiver, where)
    return Scenario(
        name=keys.name,
        seed=keys.seed,
        origin=origin,
        environment=environment,
        channel=channel,
        sites=sites,
        receiver=receiver,
        frontend=build_dataclass(FrontendConfig, _mapping(keys.frontend), f"{where}.frontend"),
    )


def _require(condition: bool, where: str, message: str) -> None:
    if not condition:
        raise ConfigError(f"{where}: {message}")


def _require_range(value: float, bounds: tuple[float, float], where: str, unit: str = "") -> None:
    low, high = bounds
    _require(low <= value <= high, where,
             f"{value!r} is outside {f'[{low:g}, {high:g}] {unit}'.rstrip()}")


def _require_choice(value: str, choices: tuple[str, ...] | list[str], where: str) -> None:
    _require(value in choices, where,
             f"unknown value {value!r} (choose one of {', '.join(choices)})")


def _mapping(value: object) -> object:
    """An omitted or empty (``null``) optional section means all defaults."""
    return {} if value is None else value


def _auto(data: object, *names: str) -> object:
    """Replace ``auto`` by ``None`` in the named keys of a mapping (other input passes through
    for build_dataclass to reject)."""
    if not isinstance(data, Mapping):
        return data
    return {key: None if key in names and value == "auto" else value
            for key, value in data.items()}


def _check_lat_lon(point: MapOrigin | LatLon | _SiteKeys, where: str) -> None:
    _require(-90.0 <= point.latitude_deg <= 90.0, f"{where}.latitude_deg",
             f"{point.latitude_deg!r} is outside [-90, 90]")
    _require(-180.0 <= point.longitude_deg <= 180.0, f"{where}.longitude_deg",
             f"{point.longitude_deg!r} is outside [-180, 180]")


def _parse_list(data: object, where: str, parse: Callable[[object, str], T]) -> tuple[T, ...]:
    items = require_list(data, where)
    _require(len(items) > 0, where, "must not be empty")
    return tuple(parse(item, f"{where}[{index}]") for index, item in enumerate(items))


def _parse_channel(data: object, where: str) -> ChannelSettings | RayTracingSettings:
    keys = dict(require_mapping(_mapping(data), where))
    model = keys.pop("model", "statistical")
    _require_choice(model, list(CHANNEL_MODELS), f"{where}.model")
    if CHANNEL_MODELS[model] is RayTracingSettings:
        return _parse_raytracing(keys, where)
    channel = build_dataclass(ChannelSettings, _auto(keys, "delay_spread_ns"), where)
    for name in ("profile_los", "profile_nlos"):
        _require_choice(getattr(channel, name), list(TDL_PROFILES), f"{where}.{name}")
    if channel.delay_spread_ns is not None:
        _require_range(channel.delay_spread_ns, DELAY_SPREAD_RANGE_NS,
                       f"{where}.delay_spread_ns", "ns (or auto)")
    _require_range(channel.environment_doppler_hz, ENVIRONMENT_DOPPLER_RANGE_HZ,
                   f"{where}.environment_doppler_hz", "Hz")
    return channel


def _parse_raytracing(keys: dict, where: str) -> RayTracingSettings:
    origin = keys.get("scene_origin")
    if origin is not None:
        keys["scene_origin"] = None  # parsed below with its own field path
    settings = build_dataclass(RayTracingSettings, keys, where)
    if origin is not None:
        point = build_dataclass(LatLon, origin, f"{where}.scene_origin")
        _check_lat_lon(point, f"{where}.scene_origin")
        settings = dataclasses.replace(settings, scene_origin=point)
    _wrap(lambda spec: check_scene_spec(spec, settings.scene_origin is not None), settings.scene, f"{where}.scene")
    _require_range(settings.max_depth, MAX_DEPTH_RANGE, f"{where}.max_depth")
    _require_range(settings.samples_per_source, SAMPLES_PER_SOURCE_RANGE, f"{where}.samples_per_source")
    _require_range(settings.route_step_m, ROUTE_STEP_RANGE_M, f"{where}.route_step_m", "m")
    if settings.default_building_height_m is not None:
        _require_range(settings.default_building_height_m, BUILDING_HEIGHT_RANGE_M,
                       f"{where}.default_building_height_m", "m")
    _require(settings.cache_dir is None or settings.cache_dir.strip() != "", f"{where}.cache_dir",
             "must not be empty (omit it for the default)")
    return settings


def _parse_sites(data: object, where: str) -> tuple[SiteSpec, ...]:
    sites = _parse_list(data, where, _parse_site)
    names: dict[str, int] = {}
    carriers: dict[tuple[int, int], str] = {}
    for i, site in enumerate(sites):
        _require(site.name not in names, f"{where}[{i}].name",
                 f"site name {site.name!r} is already used by {where}[{names.get(site.name)}]")
        names[site.name] = i
        for j, cell in enumerate(site.cells):
            path = f"{where}[{i}].cells[{j}]"
            key = (cell.earfcn, cell.pci)
            _require(key not in carriers, f"{path}.pci",
                     f"PCI {cell.pci} on EARFCN {cell.earfcn} is already used by "
                     f"{carriers.get(key)}")
            carriers[key] = path
    return sites


def _parse_site(data: object, where: str) -> SiteSpec:
    keys = build_dataclass(_SiteKeys, _auto(data, "timing_offset_us", "frequency_error_ppb"),
                           where)
    _require(keys.name.strip() != "", f"{where}.name", "must not be empty")
    _check_lat_lon(keys, where)
    _require_range(keys.height_m, SITE_HEIGHT_RANGE_M, f"{where}.height_m", "m")
    if keys.timing_offset_us is not None:
        low, high = TIMING_OFFSET_RANGE_US
        _require(low <= keys.timing_offset_us < high, f"{where}.timing_offset_us",
                 f"{keys.timing_offset_us!r} is outside [{low:g}, {high:g}) us (or use auto)")
    if keys.frequency_error_ppb is not None:
        _require_range(keys.frequency_error_ppb, FREQUENCY_ERROR_RANGE_PPB,
                       f"{where}.frequency_error_ppb", "ppb (or use auto)")
    fields = {f.name: getattr(keys, f.name) for f in dataclasses.fields(keys)}
    fields["cells"] = _parse_list(keys.cells, f"{where}.cells", _parse_cell)
    return SiteSpec(**fields)


def _parse_cell(data: object, where: str) -> CellSpec:
    keys = build_dataclass(_CellKeys, data, where)
    _wrap(check_pci, keys.pci, f"{where}.pci")
    _wrap(band_of, keys.earfcn, f"{where}.earfcn")
    bandwidth = _wrap(check_bandwidth, keys.bandwidth_mhz, f"{where}.bandwidth_mhz")
    _wrap(lambda earfcn: check_channel(earfcn, bandwidth), keys.earfcn, f"{where}.bandwidth_mhz")
    _require_range(keys.eirp_dbm, EIRP_RANGE_DBM, f"{where}.eirp_dbm", "dBm")
    _require_range(keys.azimuth_deg, AZIMUTH_RANGE_DEG, f"{where}.azimuth_deg", "deg")
    _require_range(keys.downtilt_deg, DOWNTILT_RANGE_DEG, f"{where}.downtilt_deg", "deg")
    # CellConfig checks load, cfi and weights; add them one at a time so an error names its key.
    config: dict[str, Any] = {"pci": keys.pci, "bandwidth_mhz": bandwidth}
    for name in ("load", "cfi", "modulation_weights"):
        config[name] = getattr(keys, name)
        cell = _wrap(lambda values: CellConfig(**values), config, f"{where}.{name}")
    antenna = build_dataclass(SectorPattern, _mapping(keys.antenna), f"{where}.antenna")
    for name, (low, high, unit) in ANTENNA_RANGES.items():
        _require_range(getattr(antenna, name), (low, high), f"{where}.antenna.{name}", unit)
    return CellSpec(cell, keys.earfcn, keys.eirp_dbm, keys.azimuth_deg, keys.downtilt_deg,
                    antenna)


def _wrap(check: Callable[[Any], T], value: Any, where: str) -> T:
    """Run a ValueError-raising check, re-raising as a ConfigError naming ``where``."""
    try:
        return check(value)
    except ValueError as error:
        raise ConfigError(f"{where}: {error}") from None


def _parse_receiver(data: object, where: str) -> ReceiverSpec:
    keys = build_dataclass(_ReceiverKeys, data, where)
    _require_range(keys.height_m, RECEIVER_HEIGHT_RANGE_M, f"{where}.height_m", "m")
    _require((keys.position is None) != (keys.route is None), where,
             "give exactly one of 'position' (a fixed receiver) or 'route' (a moving one)")
    if keys.position is not None:
        position = build_dataclass(LatLon, keys.position, f"{where}.position")
        _check_lat_lon(position, f"{where}.position")
        return ReceiverSpec(keys.height_m, position=position)
    return ReceiverSpec(keys.height_m, route=_parse_route(keys.route, f"{where}.route"))


def _parse_route(data: object, where: str) -> RouteSpec:
    keys = build_dataclass(_RouteKeys, data, where)
    _require_range(keys.speed_mps, SPEED_RANGE_MPS, f"{where}.speed_mps", "m/s")
    waypoints = _parse_list(keys.waypoints, f"{where}.waypoints", _parse_waypoint)
    _require(len(waypoints) >= 2, f"{where}.waypoints",
             f"a route needs at least 2 waypoints, got {len(waypoints)}")
    _require(len(set(waypoints)) > 1, f"{where}.waypoints",
             "all waypoints are the same point: the route has zero length")
    # Straight segments, as the trajectory walks them (chords on the ellipsoid: the ground's
    # height changes the length by < 0.2 %).
    points = _ecef(waypoints + waypoints[:1] if keys.loop else waypoints, 0.0)
    length_m = float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1)))
    duration_s = length_m / keys.speed_mps
    low, high = ROUTE_DURATION_RANGE_S
    _require(low <= duration_s <= high, where,
             f"one pass takes {duration_s:.4g} s ({length_m:.4g} m at {keys.speed_mps:g} m/s), "
             f"outside [{low:g}, {high:g}] s")
    return RouteSpec(keys.speed_mps, waypoints, keys.loop)


def _parse_waypoint(data: object, where: str) -> LatLon:
    point = build_dataclass(LatLon, data, where)
    _check_lat_lon(point, where)
    return point


def _ecef(points: Sequence[MapOrigin | LatLon | SiteSpec], height_m: float | list[float]
          ) -> np.ndarray:
    """ECEF (m) of N >= 2 points at ellipsoidal ``height_m``, shape (N, 3) (pyproj warns on
    one-element arrays)."""
    return geodetic_to_ecef([p.latitude_deg for p in points], [p.longitude_deg for p in points],
                            height_m).reshape(-1, 3)


def _check_distances(origin: MapOrigin, sites: tuple[SiteSpec, ...], receiver: ReceiverSpec,
                     where: str) -> None:
    """Refuse a site or receiver point beyond ``MAX_DISTANCE_M`` (straight line) from the
    origin, and a receiver point beyond it from every site: a world the flat map frame cannot
    hold, or a receiver that hears no cell (and would still get a channel, even LOS)."""
    limit_km = MAX_DISTANCE_M / 1e3
    if receiver.position is not None:
        points, paths = [receiver.position], [f"{where}.receiver.position"]
    else:
        points = list(receiver.route.waypoints)
        paths = [f"{where}.receiver.route.waypoints[{k}]" for k in range(len(points))]
    # one conversion for all points (the origin and a site make at least two)
    heights = [origin.height_m, *(origin.height_m + site.height_m for site in sites),
               *[origin.height_m + receiver.height_m] * len(points)]
    xyz = _ecef([origin, *sites, *points], heights)
    centre, site_points, receiver_points = xyz[0], xyz[1 : len(sites) + 1], xyz[len(sites) + 1 :]
    for i, (site, distance) in enumerate(zip(sites, np.linalg.norm(site_points - centre, axis=1))):
        _require(distance <= MAX_DISTANCE_M, f"{where}.sites[{i}]",
                 f"site {site.name!r} is {distance / 1e3:.1f} km from the origin, beyond the "
                 f"{limit_km:g} km a scenario may span (LTE's largest cell radius)")
    from_origin = np.linalg.norm(receiver_points - centre, axis=1)
    from_sites = np.linalg.norm(receiver_points[:, None] - site_points[None], axis=2)
    for path, distance, to_sites in zip(paths, from_origin, from_sites):
        _require(distance <= MAX_DISTANCE_M, path,
                 f"the receiver is {distance / 1e3:.1f} km from the origin, beyond the "
                 f"{limit_km:g} km a scenario may span (LTE's largest cell radius)")
        nearest = int(np.argmin(to_sites))
        _require(to_sites[nearest] <= MAX_DISTANCE_M, path,
                 f"the receiver is {to_sites[nearest] / 1e3:.1f} km from the nearest site "
                 f"({sites[nearest].name!r}), beyond the {limit_km:g} km an LTE cell reaches")
