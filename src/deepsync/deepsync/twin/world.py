"""The digital twin built from a scenario: emitters, channel, receiver trajectory, truth.

Coordinates: the map frame is the ENU tangent plane at the scenario origin; the ground is
flat at the origin's ellipsoidal height, so an antenna ``height_m`` above ground sits at
ellipsoidal height ``origin.height_m + height_m``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from deepsync.frontend.channel import Emitter
from deepsync.frontend.config import FrontendConfig
from deepsync.geo import LocalFrame
from deepsync.lte.numerology import SUBCARRIERS_PER_RB, Numerology
from deepsync.twin.antenna import SectorAntenna
from deepsync.twin.raytrace.channel import RayTracedChannel
from deepsync.twin.statistical_channel import StatisticalChannel, Transmitter
from deepsync.twin.route import Trajectory
from deepsync.twin.scenario import (
    AUTO_FREQUENCY_ERROR_PPB,
    TIMING_OFFSET_RANGE_US,
    RayTracingSettings,
    ReceiverSpec,
    Scenario,
    SiteSpec,
)
from deepsync.twin.seeding import site_rng


@dataclass(frozen=True)
class TwinSite:
    """A site with its ``auto`` values resolved: position in the map frame, timing, oscillator.

    ``timing_offset_s`` holds at true time 0 (the recording's first sample); the frame timing
    then drifts with the oscillator (see :attr:`frame_rate_error`)."""

    name: str
    latitude_deg: float
    longitude_deg: float
    height_m: float
    position_enu: np.ndarray = field(compare=False)  # follows from the fields above
    timing_offset_s: float
    frequency_error_ppb: float

    @property
    def frame_rate_error(self) -> float:
        """The site's frame clock runs on its oscillator: fast by the same fraction as its
        carrier (``Emitter.frame_rate_error``), so its frame timing drifts by -ppb ns per s."""
        return self.frequency_error_ppb * 1e-9


@dataclass(frozen=True)
class CellInfo:
    """What a tower database knows about a cell (its site's position is in ``Twin.sites``)."""

    pci: int
    earfcn: int
    band: int
    carrier_hz: float
    bandwidth_mhz: float
    site: str
    azimuth_deg: float
    eirp_dbm: float


@dataclass(frozen=True)
class Twin:
    """The simulated world; ``emitters``, ``cells`` and the channel's emitter indices all
    follow the scenario's cell order."""

    scenario: Scenario
    frame: LocalFrame
    sites: tuple[TwinSite, ...]
    cells: tuple[CellInfo, ...]
    emitters: list[Emitter]
    channel: StatisticalChannel | RayTracedChannel
    receiver: Trajectory
    frontend: FrontendConfig

    def site(self, name: str) -> TwinSite:
        """The site called ``name``."""
        for site in self.sites:
            if site.name == name:
                return site
        raise KeyError(f"no site named {name!r}")

    def geometric_delay_s(self, emitter_index: int, t: float) -> float:
        """True straight-line delay from the emitter's antenna to the receiver at ``t`` (s)."""
        return self.channel.geometric_delay_s(emitter_index, t)

    def receiver_enu(self, t: ArrayLike) -> np.ndarray:
        """True receiver position in the map frame at time(s) ``t``."""
        return self.receiver.position_enu(t)


def build_twin(scenario: Scenario) -> Twin:
    """Resolve a scenario into a twin: positions in the map frame, ``auto`` timing offsets and
    oscillator errors drawn from the seed (per site name), one emitter per cell."""
    cells = twin_cells(scenario)
    receiver = receiver_trajectory(scenario.receiver, cells.frame)
    channel = _channel(scenario, cells.frame, list(cells.transmitters), receiver)
    return Twin(scenario, cells.frame, cells.sites, cells.cells, list(cells.emitters), channel, receiver,
                scenario.frontend)


@dataclass(frozen=True)
class TwinCells:
    """A scenario's sites and cells resolved without a receiver: what sends, from where, on
    whose clock (``emitters``) and through which antenna (``transmitters``), in cell order."""

    frame: LocalFrame
    sites: tuple[TwinSite, ...]
    cells: tuple[CellInfo, ...]
    emitters: tuple[Emitter, ...]
    transmitters: tuple[Transmitter, ...]


def twin_cells(scenario: Scenario) -> TwinCells:
    """The scenario's sites and cells (:class:`TwinCells`), as :func:`build_twin` resolves them."""
    origin = scenario.origin
    frame = LocalFrame(origin.latitude_deg, origin.longitude_deg, origin.height_m)
    sites = tuple(_resolve_site(site, frame, scenario.seed) for site in scenario.sites)
    emitters: list[Emitter] = []
    cells: list[CellInfo] = []
    transmitters: list[Transmitter] = []
    for spec, site in zip(scenario.sites, sites):
        for cell in spec.cells:
            n_rb = Numerology.for_bandwidth(cell.bandwidth_mhz).n_rb
            eirp_w = 10.0 ** ((cell.eirp_dbm - 30.0) / 10.0)
            emitters.append(Emitter(
                cell=cell.config,
                carrier_hz=cell.carrier_hz,
                re_power_w=eirp_w / (SUBCARRIERS_PER_RB * n_rb),
                timing_offset_s=site.timing_offset_s,
                frequency_offset_hz=site.frequency_error_ppb * 1e-9 * cell.carrier_hz,
                site=site.name,
                frame_rate_error=site.frame_rate_error,
            ))
            cells.append(CellInfo(cell.pci, cell.earfcn, cell.band, cell.carrier_hz,
                                  cell.bandwidth_mhz, site.name, cell.azimuth_deg,
                                  cell.eirp_dbm))
            transmitters.append(Transmitter(
                site.name, site.position_enu, site.height_m, cell.carrier_hz,
                SectorAntenna(cell.azimuth_deg, cell.downtilt_deg, cell.antenna), cell.pci,
            ))
    return TwinCells(frame, sites, tuple(cells), tuple(emitters), tuple(transmitters))


def _channel(scenario: Scenario, frame: LocalFrame, transmitters: list[Transmitter],
             receiver: Trajectory) -> StatisticalChannel | RayTracedChannel:
    """The one place a scenario's channel model is turned into its channel."""
    settings = scenario.channel
    if isinstance(settings, RayTracingSettings):
        from deepsync.twin.raytrace.build import raytraced_channel  # noqa: PLC0415 (tqdm, scene files)

        return raytraced_channel(settings, scenario, frame, transmitters, receiver)
    return StatisticalChannel(transmitters, receiver, scenario.environment, settings, scenario.seed,
                              scenario.receiver.height_m)


def _resolve_site(site: SiteSpec, frame: LocalFrame, seed: int) -> TwinSite:
    timing_us = site.timing_offset_us
    if timing_us is None:
        timing_us = site_rng(seed, site.name, "timing").uniform(*TIMING_OFFSET_RANGE_US)
    ppb = site.frequency_error_ppb
    if ppb is None:
        ppb = site_rng(seed, site.name, "oscillator").uniform(-AUTO_FREQUENCY_ERROR_PPB,
                                                              AUTO_FREQUENCY_ERROR_PPB)
    position = frame.geodetic_to_enu(site.latitude_deg, site.longitude_deg,
                                     frame.height_m + site.height_m)
    return TwinSite(site.name, site.latitude_deg, site.longitude_deg, site.height_m, position,
                    float(timing_us) * 1e-6, float(ppb))


def receiver_trajectory(receiver: ReceiverSpec, frame: LocalFrame) -> Trajectory:
    """The receiver's fixed position or route in the map frame."""
    height = frame.height_m + receiver.height_m
    if receiver.route is None:
        position = receiver.position
        return Trajectory.fixed(frame, frame.geodetic_to_enu(position.latitude_deg,
                                                             position.longitude_deg, height))
    route = receiver.route
    points = frame.geodetic_to_enu([p.latitude_deg for p in route.waypoints],
                                   [p.longitude_deg for p in route.waypoints], height)
    return Trajectory(frame, points, route.speed_mps, route.loop)
