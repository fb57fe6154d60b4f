"""Scenario files: the digital twin's world (sites, cells, receiver, channel model) in YAML.

``load_scenario(path)`` reads and validates a file into frozen dataclasses; every error is a
:class:`~deepsync.configio.ConfigError` naming the field path (``scenario.sites[1].cells[0].pci``).
The schema, with defaults for the optional keys::

    name: campus
    seed: 7                        # every "auto" value and random draw derives from it
    origin: {latitude_deg, longitude_deg, height_m}   # map-frame origin, ellipsoidal height
    environment: {model: UMa, los: auto}              # UMa | UMi; auto | los | nlos
    channel: {profile_los: TDL-D, profile_nlos: TDL-A, delay_spread_ns: auto,
              shadow_fading: true, environment_doppler_hz: 1.0}
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
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from deepsync.configio import ConfigError, build_dataclass, load_yaml, require_list
from deepsync.frontend.config import FrontendConfig
from deepsync.lte.cell import CellConfig, check_pci
from deepsync.lte.earfcn import band_of, check_channel, downlink_frequency_hz
from deepsync.lte.numerology import check_bandwidth
from deepsync.twin.antenna import SectorPattern
from deepsync.twin.propagation import MODELS
from deepsync.twin.tdl import TDL_PROFILES

T = TypeVar("T")

LOS_MODES = ("auto", "los", "nlos")
TIMING_OFFSET_RANGE_US = (0.0, 10_000.0)  # one 10 ms frame
AUTO_FREQUENCY_ERROR_PPB = 20.0


@dataclass(frozen=True)
class Origin:
    """Map-frame origin: WGS84 latitude/longitude (deg) and ellipsoidal height (m)."""

    latitude_deg: float
    longitude_deg: float
    height_m: float


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
    38.901 log-normal), log-normal shadowing on/off, and a Doppler floor (Hz) for a changing
    environment around a static receiver."""

    profile_los: str = "TDL-D"
    profile_nlos: str = "TDL-A"
    delay_spread_ns: float | None = None
    shadow_fading: bool = True
    environment_doppler_hz: float = 1.0


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
    origin: Origin
    environment: Environment
    channel: ChannelSettings
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
    _require(keys.seed >= 0, f"{where}.seed", f"must be >= 0, got {keys.seed}")
    origin = build_dataclass(Origin, keys.origin, f"{where}.origin")
    _check_lat_lon(origin, f"{where}.origin")
    environment = build_dataclass(Environment, _mapping(keys.environment),
                                  f"{where}.environment")
    _require_choice(environment.model, MODELS, f"{where}.environment.model")
    _require_choice(environment.los, LOS_MODES, f"{where}.environment.los")
    return Scenario(
        name=keys.name,
        seed=keys.seed,
        origin=origin,
        environment=environment,
        channel=_parse_channel(keys.channel, f"{where}.channel"),
        sites=_parse_sites(keys.sites, f"{where}.sites"),
        receiver=_parse_receiver(keys.receiver, f"{where}.receiver"),
        frontend=build_dataclass(FrontendConfig, _mapping(keys.frontend), f"{where}.frontend"),
    )


def _require(condition: bool, where: str, message: str) -> None:
    if not condition:
        raise ConfigError(f"{where}: {message}")


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


def _check_lat_lon(point: Origin | LatLon | _SiteKeys, where: str) -> None:
    _require(-90.0 <= point.latitude_deg <= 90.0, f"{where}.latitude_deg",
             f"{point.latitude_deg!r} is outside [-90, 90]")
    _require(-180.0 <= point.longitude_deg <= 180.0, f"{where}.longitude_deg",
             f"{point.longitude_deg!r} is outside [-180, 180]")


def _parse_list(data: object, where: str, parse: Callable[[object, str], T]) -> tuple[T, ...]:
    items = require_list(data, where)
    _require(len(items) > 0, where, "must not be empty")
    return tuple(parse(item, f"{where}[{index}]") for index, item in enumerate(items))


def _parse_channel(data: object, where: str) -> ChannelSettings:
    channel = build_dataclass(ChannelSettings, _auto(_mapping(data), "delay_spread_ns"), where)
    for name in ("profile_los", "profile_nlos"):
        _require_choice(getattr(channel, name), list(TDL_PROFILES), f"{where}.{name}")
    if channel.delay_spread_ns is not None:
        _require(channel.delay_spread_ns > 0, f"{where}.delay_spread_ns",
                 f"must be > 0 (or auto), got {channel.delay_spread_ns!r}")
    _require(channel.environment_doppler_hz >= 0, f"{where}.environment_doppler_hz",
             f"must be >= 0, got {channel.environment_doppler_hz!r}")
    return channel


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
    _require(keys.height_m > 0, f"{where}.height_m", f"must be > 0 m, got {keys.height_m!r}")
    if keys.timing_offset_us is not None:
        low, high = TIMING_OFFSET_RANGE_US
        _require(low <= keys.timing_offset_us < high, f"{where}.timing_offset_us",
                 f"{keys.timing_offset_us!r} is outside [{low:g}, {high:g}) us (or use auto)")
    fields = {f.name: getattr(keys, f.name) for f in dataclasses.fields(keys)}
    fields["cells"] = _parse_list(keys.cells, f"{where}.cells", _parse_cell)
    return SiteSpec(**fields)


def _parse_cell(data: object, where: str) -> CellSpec:
    keys = build_dataclass(_CellKeys, data, where)
    _wrap(check_pci, keys.pci, f"{where}.pci")
    _wrap(band_of, keys.earfcn, f"{where}.earfcn")
    bandwidth = _wrap(check_bandwidth, keys.bandwidth_mhz, f"{where}.bandwidth_mhz")
    _wrap(lambda earfcn: check_channel(earfcn, bandwidth), keys.earfcn, f"{where}.bandwidth_mhz")
    _require(-90.0 <= keys.downtilt_deg <= 90.0, f"{where}.downtilt_deg",
             f"{keys.downtilt_deg!r} is outside [-90, 90]")
    # CellConfig checks load, cfi and weights; add them one at a time so an error names its key.
    config: dict[str, Any] = {"pci": keys.pci, "bandwidth_mhz": bandwidth}
    for name in ("load", "cfi", "modulation_weights"):
        config[name] = getattr(keys, name)
        cell = _wrap(lambda values: CellConfig(**values), config, f"{where}.{name}")
    antenna = build_dataclass(SectorPattern, _mapping(keys.antenna), f"{where}.antenna")
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
    _require(keys.height_m > 0, f"{where}.height_m", f"must be > 0 m, got {keys.height_m!r}")
    _require((keys.position is None) != (keys.route is None), where,
             "give exactly one of 'position' (a fixed receiver) or 'route' (a moving one)")
    if keys.position is not None:
        position = build_dataclass(LatLon, keys.position, f"{where}.position")
        _check_lat_lon(position, f"{where}.position")
        return ReceiverSpec(keys.height_m, position=position)
    return ReceiverSpec(keys.height_m, route=_parse_route(keys.route, f"{where}.route"))


def _parse_route(data: object, where: str) -> RouteSpec:
    keys = build_dataclass(_RouteKeys, data, where)
    _require(keys.speed_mps > 0, f"{where}.speed_mps", f"must be > 0 m/s, got {keys.speed_mps!r}")
    waypoints = _parse_list(keys.waypoints, f"{where}.waypoints", _parse_waypoint)
    _require(len(waypoints) >= 2, f"{where}.waypoints",
             f"a route needs at least 2 waypoints, got {len(waypoints)}")
    _require(len(set(waypoints)) > 1, f"{where}.waypoints",
             "all waypoints are the same point: the route has zero length")
    return RouteSpec(keys.speed_mps, waypoints, keys.loop)


def _parse_waypoint(data: object, where: str) -> LatLon:
    point = build_dataclass(LatLon, data, where)
    _check_lat_lon(point, where)
    return point
