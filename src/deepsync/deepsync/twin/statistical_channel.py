"""A 3GPP statistical channel (TR 38.901 path loss, shadowing, TDL multipath) as a
:class:`~deepsync.frontend.channel.ChannelProvider`.

Per *site* (sectors of one mast share it), drawn once from the scenario seed:

* LOS state: with ``los: auto``, LOS with the 38.901 LOS probability at the receiver's
  distance at t = 0;
* shadow fading: a standard normal draw scaled by the LOS/NLOS sigma;
* delay spread: the given one, or a standard normal draw mapped through the carrier's
  log-normal (Table 7.5-6), so same-carrier sectors share it;
* the TDL realisation: arrival angles and phases of 16 sinusoids per Rayleigh tap.

Path of tap k, sinusoid n at time t, for the cell at carrier f_c:

    delay   = d(t)/c + DS * tau_k                     (first tap exactly at d(t)/c)
    gain    = sqrt(10^(-(PL(t) + SF)/10) * P_k * G(t)) * exp(j (phi_kn + 2 pi f_kn t)) / sqrt(N)
    Doppler = f_kn = f_max cos(alpha_kn),   f_max = v / lambda + environment_doppler_hz

with d(t) the 3D distance between the antennas, PL the 38.901 path loss at d(t), P_k the tap
power (normalised so all taps sum to 1) and G the sector gain. The specular LOS tap of TDL-D/E
is deterministic: gain sqrt(10^(-(PL+SF)/10) P_LOS G) exp(-j 2 pi f_c d(t)/c), Doppler from the
radial velocity. The reported Doppler of every path is the time derivative of its gain's phase,
so the front end's within-frame rotation joins the next frame's gains without a phase jump.

Approximations (beyond those of :mod:`deepsync.twin.propagation`):

* TDL taps have no angles: the antenna gain towards the receiver (LOS direction) applies to
  every tap, and scattered taps have a Clarke Doppler spectrum whatever the geometry;
* the first tap sits at the geometric delay even in NLOS (no excess delay of the first path,
  only weak first taps as in TDL-A's -13.4 dB);
* scattered taps carry random phases instead of the carrier phase of their (unknown) path
  length; only the LOS tap's phase follows exp(-j 2 pi f_c d/c); every path of a cell also
  carries that sector's fixed transmit-chain phase, so co-sited sectors share their fading
  but not their phase;
* the LOS state and the fading realisation are drawn once per site and kept along a route;
  so are the shadowing and the delay spread unless ``spatial_consistency`` is set, in which
  case each follows the receiver's distance along its route as a Gaussian process with the
  38.901 exponential autocorrelation (Table 7.5-6 correlation distances: UMa 37-50 m for the
  shadowing, 30-40 m for the delay spread), starting from the draw above. That is 38.901
  §7.6.3.1 along one path, not over the plane: a route that comes back near where it passed
  gets new values (a loop's second pass repeats its first). Path loss, delays, antenna gain
  and LOS Doppler always follow the geometry;
* f_max uses the route's nominal speed throughout, also while the receiver stands still.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.signal

from deepsync.frontend.channel import Paths
from deepsync.frontend.portable import elementwise, phasor
from deepsync.twin.antenna import SectorAntenna
from deepsync.twin.fading import SumOfSinusoids
from deepsync.twin.propagation import (
    correlation_distances_m,
    delay_spread_lognormal,
    los_probability,
    path_loss_db,
    shadow_fading_std_db,
)
from deepsync.twin.route import Trajectory
from deepsync.twin.scenario import ChannelSettings, Environment
from deepsync.twin.seeding import site_rng, transmit_chain_phase
from deepsync.twin.tdl import TDL_PROFILES, TdlProfile
from deepsync.types import SPEED_OF_LIGHT_M_S

N_SINUSOIDS = 16
ALONG_ROUTE_STEP_M = 1.0  # grid of the spatially consistent parameters (correlation distances >= 7 m)


@dataclass(frozen=True)
class Transmitter:
    """One cell's antenna: where it is, what carrier it radiates and how it points.

    ``position_enu`` is the antenna position in the map frame; ``height_m`` its height above
    ground (the 38.901 h_BS). Transmitters with the same ``site`` must share both.
    """

    site: str
    position_enu: np.ndarray
    height_m: float
    carrier_hz: float
    antenna: SectorAntenna
    pci: int = -1  # names the cell's own transmit-chain phase draw


@dataclass(frozen=True)
class LinkParameters:
    """Large-scale state of one cell's link (ground truth for evaluation), where the route
    starts (with ``spatial_consistency``, shadowing and delay spread change along it)."""

    site: str
    los: bool
    profile: str
    shadow_fading_db: float
    delay_spread_s: float
    max_doppler_hz: float


@dataclass(frozen=True)
class _SiteDraw:
    """The random state of one site, shared by its sectors."""

    transmitter: Transmitter    # the site's first cell, for the shared geometry
    los: bool
    shadow_fading_db: float
    delay_spread_normal: float  # standard normal draw of lgDS
    profile: TdlProfile
    fading: SumOfSinusoids      # (taps, N) sinusoids
    # with spatial consistency: the standard normals of the shadowing and of lgDS every
    # ALONG_ROUTE_STEP_M along the route (the first ones are the draws above)
    shadow_fading_along: np.ndarray | None = None
    delay_spread_normal_along: np.ndarray | None = None


@dataclass(frozen=True)
class _Link:
    """Everything about one emitter's paths that does not change with time."""

    transmitter: Transmitter
    parameters: LinkParameters
    has_specular: bool          # path 0 is the specular LOS component
    excess_delay_s: np.ndarray  # (P,) delay after the geometric one
    amplitude: np.ndarray       # (P,) sqrt(tap power / N) (sqrt(P_LOS) for the specular path)
    phase: np.ndarray           # (P,) phase at t = 0 (unused for the specular path)
    doppler_hz: np.ndarray      # (P,) Doppler (overwritten per call for the specular path)
    chain_phase: float          # the sector's own transmit-chain phase (rad)
    # with spatial consistency, along the route every ALONG_ROUTE_STEP_M: shadowing (dB), and
    # the delay spread (s) that scales the taps' delays (then excess_delay_s is per 1 s of it)
    shadow_fading_along_db: np.ndarray | None = None
    delay_spread_along_s: np.ndarray | None = None


class StatisticalChannel:
    """TR 38.901 statistical channel from every transmitter to one receiver trajectory.

    ``receiver_height_m`` is the receiver antenna's height above ground (the 38.901 h_UT).
    ``paths(i, t)`` is cheap: all random draws and tap constants are made here, a call only
    evaluates the geometry (distance, path loss, antenna gain) and one complex exponential
    per sinusoid.
    """

    def __init__(self, transmitters: Sequence[Transmitter], receiver: Trajectory,
                 environment: Environment, settings: ChannelSettings, seed: int,
                 receiver_height_m: float) -> None:
        self.receiver = receiver
        self.environment = environment
        self.settings = settings
        self.receiver_height_m = float(receiver_height_m)
        self._seed = seed
        sites: dict[str, _SiteDraw] = {}
        links = []
        for tx in transmitters:
            if tx.site not in sites:
                sites[tx.site] = self._draw_site(tx)
            first = sites[tx.site].transmitter
            if not (np.allclose(first.position_enu, tx.position_enu)
                    and first.height_m == tx.height_m):
                raise ValueError(f"cells of site {tx.site!r} must share position and height")
            links.append(self._make_link(tx, sites[tx.site], len(links)))
        self._links: tuple[_Link, ...] = tuple(links)
        self._fixed: dict[int, tuple] = {}  # a receiver that never moves: each link's geometry, once

    def _draw_site(self, tx: Transmitter) -> _SiteDraw:
        rng = site_rng(self._seed, tx.site, "large_scale")
        los_draw, sf_draw, ds_draw = rng.uniform(), rng.standard_normal(), rng.standard_normal()
        model, mode = self.environment.model, self.environment.los
        if mode == "auto":
            offset = self.receiver.position_enu(0.0) - tx.position_enu
            los = bool(los_draw < los_probability(model, np.hypot(offset[0], offset[1]),
                                                  self.receiver_height_m))
        else:
            los = mode == "los"
        sf_db = shadow_fading_std_db(model, los) * sf_draw if self.settings.shadow_fading else 0.0
        profile = TDL_PROFILES[self.settings.profile_los if los else self.settings.profile_nlos]
        fading = SumOfSinusoids.draw(site_rng(self._seed, tx.site, "fading"),
                                     (len(profile.delays),), N_SINUSOIDS)
        sf_along = ds_along = None
        if self.settings.spatial_consistency:
            along = site_rng(self._seed, tx.site, "along route")  # its own stream: the draws above stay
            sf_distance, ds_distance = correlation_distances_m(model, los)
            sf_along = correlated_normal_along(along, sf_draw, self.receiver.length_m, sf_distance)
            ds_along = correlated_normal_along(along, ds_draw, self.receiver.length_m, ds_distance)
        return _SiteDraw(tx, los, float(sf_db), float(ds_draw), profile, fading, sf_along, ds_along)

    def _make_link(self, tx: Transmitter, site: _SiteDraw, index: int) -> _Link:
        profile, fading = site.profile, site.fading
        delay_spread_along = shadow_fading_along = None
        if self.settings.delay_spread_ns is not None:
            delay_spread = self.settings.delay_spread_ns * 1e-9
        else:
            mu, sigma = delay_spread_lognormal(self.environment.model, site.los, tx.carrier_hz)
            delay_spread = 10.0 ** (mu + sigma * site.delay_spread_normal)
            if site.delay_spread_normal_along is not None:
                delay_spread_along = elementwise(math.pow, 10.0, mu + sigma * site.delay_spread_normal_along)
        if site.shadow_fading_along is not None and self.settings.shadow_fading:
            shadow_std_db = shadow_fading_std_db(self.environment.model, site.los)
            shadow_fading_along = shadow_std_db * site.shadow_fading_along
        wavelength = SPEED_OF_LIGHT_M_S / tx.carrier_hz
        max_doppler = self.receiver.speed_mps / wavelength + self.settings.environment_doppler_hz
        scattered, specular = profile.normalized_powers()
        n = fading.n_sinusoids
        # the taps' delays, or per second of delay spread where it changes along the route (paths scales them)
        scale = 1.0 if delay_spread_along is not None else delay_spread
        excess = np.repeat(np.asarray(profile.delays) * scale, n)
        amplitude = np.repeat(np.sqrt(scattered / n), n)
        phase = fading.phase.ravel()
        doppler = fading.doppler_hz(max_doppler).ravel()
        has_specular = profile.los_power_db is not None
        if has_specular:
            excess = np.concatenate(([0.0], excess))
            amplitude = np.concatenate(([np.sqrt(specular)], amplitude))
            phase = np.concatenate(([0.0], phase))
            doppler = np.concatenate(([0.0], doppler))
        chain = transmit_chain_phase(self._seed, tx.site, tx.pci if tx.pci >= 0 else index)
        parameters = LinkParameters(tx.site, site.los, profile.name, site.shadow_fading_db,
                                    float(delay_spread), float(max_doppler))
        return _Link(tx, parameters, has_specular, excess, amplitude, phase, doppler, float(chain),
                     shadow_fading_along, delay_spread_along)

    def link_parameters(self, emitter_index: int) -> LinkParameters:
        """Large-scale state drawn for ``emitter_index`` (LOS, shadowing, delay spread, ...)."""
        return self._links[emitter_index].parameters

    def los_at(self, emitter_index: int, t: float) -> bool:
        """Whether the receiver sees the cell's antenna at ``t`` (drawn once per site here)."""
        return self._links[emitter_index].parameters.los

    def geometric_delay_s(self, emitter_index: int, t: float) -> float:
        """Straight-line propagation delay d(t)/c from the cell's antenna to the receiver (s)."""
        tx = self._links[emitter_index].transmitter
        return math.hypot(*(self.receiver.position_enu(t) - tx.position_enu)) / SPEED_OF_LIGHT_M_S

    def paths(self, emitter_index: int, t: float) -> Paths:
        """Paths from emitter ``emitter_index`` to the receiver at true time ``t`` (s)."""
        link = self._links[emitter_index]
        delays, scale, doppler, specular_phase = self._geometry(emitter_index, t)
        phase = link.phase + (2.0 * np.pi * t) * link.doppler_hz
        if link.has_specular:
            phase[0] = specular_phase
        return Paths(
            delays_s=delays.copy(),
            gains=scale * link.amplitude * phasor(phase + link.chain_phase),
            doppler_hz=doppler.copy(),  # the Paths must not alias what is kept here
        )

    def _geometry(self, emitter_index: int, t: float) -> tuple[np.ndarray, float, np.ndarray, float]:
        """What the receiver's place decides: delays, amplitude scale, Doppler shifts and the
        specular path's phase; a receiver that never moves has them once."""
        if emitter_index in self._fixed:
            return self._fixed[emitter_index]
        link = self._links[emitter_index]
        tx, parameters = link.transmitter, link.parameters
        offset = self.receiver.position_enu(t) - tx.position_enu
        east, north, up = offset.tolist()
        d3d = math.hypot(east, north, up)
        d2d = math.hypot(east, north)
        loss_db = path_loss_db(self.environment.model, parameters.los, d2d, d3d, tx.height_m,
                               self.receiver_height_m, tx.carrier_hz)
        excess = link.excess_delay_s
        shadow_fading_db = parameters.shadow_fading_db
        if link.shadow_fading_along_db is not None or link.delay_spread_along_s is not None:
            along = float(self.receiver.distance_along(t)) / ALONG_ROUTE_STEP_M
            if link.shadow_fading_along_db is not None:
                shadow_fading_db = _interpolated(link.shadow_fading_along_db, along)
            if link.delay_spread_along_s is not None:
                excess = excess * _interpolated(link.delay_spread_along_s, along)
        loss_db = float(loss_db) + shadow_fading_db - float(tx.antenna.gain_db(offset))
        doppler, specular_phase = link.doppler_hz.copy(), 0.0
        if link.has_specular:
            # (at the antenna itself, a receiver has no direction to move along)
            velocity = self.receiver.velocity_enu(t).tolist()
            radial_speed = (velocity[0] * east + velocity[1] * north + velocity[2] * up) / d3d if d3d > 0 else 0.0
            doppler[0] = -radial_speed * tx.carrier_hz / SPEED_OF_LIGHT_M_S
            specular_phase = -2.0 * np.pi * tx.carrier_hz * d3d / SPEED_OF_LIGHT_M_S
        geometry = d3d / SPEED_OF_LIGHT_M_S + excess, 10.0 ** (-loss_db / 20.0), doppler, specular_phase
        if self.receiver.speed_mps == 0:
            self._fixed[emitter_index] = geometry
        return geometry


def correlated_normal_along(rng: np.random.Generator, start: float, length_m: float,
                            correlation_m: float) -> np.ndarray:
    """Standard normal values every ``ALONG_ROUTE_STEP_M`` over ``length_m`` of route, the first
    ``start``, with the exponential autocorrelation exp(-d / ``correlation_m``) of 38.901
    §7.6.3.1: the first-order autoregression that has it exactly on the grid."""
    n = int(np.ceil(length_m / ALONG_ROUTE_STEP_M)) + 1
    rho = math.exp(-ALONG_ROUTE_STEP_M / correlation_m)
    innovations = np.sqrt(1.0 - rho**2) * rng.standard_normal(n - 1)
    # x[k] = rho x[k-1] + innovation: a one-pole filter of the start followed by the innovations
    return scipy.signal.lfilter([1.0], [1.0, -rho], np.concatenate(([start], innovations)))


def _interpolated(values: np.ndarray, position: float) -> float:
    """``values`` on the along-route grid, linearly interpolated at ``position`` (grid steps)."""
    return float(np.interp(position, np.arange(len(values)), values))
