"""Ray-traced paths along a route as the front end's channel (:class:`ChannelProvider`).

The route is traced at sample points every ``step_m`` along it (``route_samples``). At time t
the receiver takes the path set of the *nearest* sample point and moves each path from there by
its own geometry, to first order: a path arriving from unit direction r (receiver towards the
path's last bounce) is shortened by r . dx when the receiver moves by dx, so

    delay(t)   = delay_k - r . (x(t) - x_k) / c
    gain(t)    = gain_k exp(-j 2 pi f (delay(t) - delay_k)) G_sector(departure) exp(j phi_chain)
    Doppler(t) = f r . v(t) / c                   (the rate of that delay, -f d(delay)/dt)

Nearest rather than path-wise linear interpolation between two samples: paths are born and die
between samples (a corner's shadow edge) and Sionna numbers them per receiver with no identity
across receivers, so pairing them would guess; the first-order move is exact in delay and phase
for a plane wave and off by ~(step/2)^2 / (2 d) for a path whose last leg is d long (6 mm at a
1 m step and 20 m), and the Doppler it reports is that delay's rate, so the front end's
within-frame rotation joins the next frame's phase. Amplitudes are held from the sample point
(path loss changes by < 0.1 dB over half a metre at 50 m).

The sector's pattern multiplies each path's gain by its value along the path's departure
direction (see ``tracing``); every path of a cell also carries that sector's transmit-chain
phase, as in the statistical channel. A receiver position with no traced path at all gets one
path of zero gain at the straight-line delay: the cell is not heard there.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from deepsync.frontend.channel import Paths
from deepsync.frontend.portable import phasor
from deepsync.twin.antenna import SectorAntenna
from deepsync.twin.raytrace.tracing import TracedPaths
from deepsync.twin.route import Trajectory
from deepsync.twin.seeding import transmit_chain_phase
from deepsync.twin.statistical_channel import Transmitter
from deepsync.types import SPEED_OF_LIGHT_M_S


def route_samples(receiver: Trajectory, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Where to trace a route: distances along it (m, every ``step_m`` from 0 to its length,
    the end included) and the receiver positions there (N, 3); one point for a fixed receiver."""
    if not (math.isfinite(step_m) and step_m > 0):
        raise ValueError(f"step_m must be positive, got {step_m!r}")
    if receiver.speed_mps == 0:
        return np.zeros(1), receiver.position_enu(0.0)[None]
    count = int(math.ceil(receiver.length_m / step_m - 1e-3)) + 1  # no extra point a millimetre from the end
    along = np.minimum(np.arange(count) * step_m, receiver.length_m)
    return along, receiver.position_enu(along / receiver.speed_mps)


def sector_gains(traced: TracedPaths, antenna: SectorAntenna, chain_phase_rad: float = 0.0) -> np.ndarray:
    """(N, P) gains of ``traced``'s paths as one sector sends them: each weighted by the sector
    pattern along its departure direction and turned by the sector's transmit-chain phase
    (zero where there is no path)."""
    pattern_db = np.where(traced.valid, antenna.gain_db(traced.departure_enu), -np.inf)
    return traced.gains * 10.0 ** (pattern_db / 20.0) * complex(math.cos(chain_phase_rad), math.sin(chain_phase_rad))


def static_paths(traced: TracedPaths, index: int, antenna: SectorAntenna, chain_phase_rad: float = 0.0) -> Paths:
    """The front end's :class:`Paths` of one sector at traced position ``index`` for a receiver
    standing there (no Doppler): e.g. ``FixedChannel`` input for a map over many positions. A
    position no path reaches gets one path of zero gain at the straight-line delay."""
    keep = traced.path_order(index)
    if keep.size == 0:
        distance = math.hypot(*(traced.receivers_enu[index] - traced.transmitter_enu))
        return Paths([distance / SPEED_OF_LIGHT_M_S], [0j], [0.0])
    gains = sector_gains(traced, antenna, chain_phase_rad)[index, keep]
    return Paths(traced.delays_s[index, keep], gains, np.zeros(keep.size))


@dataclass(frozen=True)
class _Link:
    transmitter: Transmitter
    traced: TracedPaths
    gains: np.ndarray        # (N, P) traced gains x sector pattern x chain phase
    keep: tuple[np.ndarray, ...]  # per sample point: its valid paths, earliest first


class RayTracedChannel:
    """:class:`~deepsync.frontend.channel.ChannelProvider` over traced paths.

    ``traces[i]`` holds emitter i's paths from its antenna to the route sample points at
    distances ``along_m`` (``route_samples``); sectors of one site on one carrier may share a
    trace. ``seed`` draws the transmit-chain phases (the statistical channel's draws).
    """

    def __init__(self, transmitters: Sequence[Transmitter], receiver: Trajectory,
                 along_m: np.ndarray, traces: Sequence[TracedPaths], seed: int) -> None:
        if len(transmitters) != len(traces):
            raise ValueError(f"{len(transmitters)} transmitters but {len(traces)} traces")
        self.receiver = receiver
        self._along = np.asarray(along_m, dtype=np.float64)
        links = []
        for index, (tx, traced) in enumerate(zip(transmitters, traces)):
            if len(traced) != len(self._along):
                raise ValueError(f"emitter {index}: traced at {len(traced)} points, the route at {len(self._along)}")
            if not math.isclose(traced.carrier_hz, tx.carrier_hz, rel_tol=1e-12):
                raise ValueError(f"emitter {index}: traced at {traced.carrier_hz} Hz, sends at {tx.carrier_hz} Hz")
            chain = transmit_chain_phase(seed, tx.site, tx.pci if tx.pci >= 0 else index)
            gains = sector_gains(traced, tx.antenna, chain)
            keep = tuple(traced.path_order(k) for k in range(len(traced)))
            links.append(_Link(tx, traced, gains, keep))
        self._links = tuple(links)

    def traced(self, emitter_index: int) -> TracedPaths:
        """The traced paths behind emitter ``emitter_index`` (isotropic antennas, no chain phase)."""
        return self._links[emitter_index].traced

    def sample_index(self, t: float) -> int:
        """The route sample point nearest the receiver at time ``t``."""
        along = float(self.receiver.distance_along(t))
        k = int(np.searchsorted(self._along, along))
        if k == len(self._along) or (k > 0 and along - self._along[k - 1] <= self._along[k] - along):
            k -= 1
        return k

    def geometric_delay_s(self, emitter_index: int, t: float) -> float:
        """Straight-line propagation delay from the cell's antenna to the receiver (s)."""
        tx = self._links[emitter_index].transmitter
        return math.hypot(*(self.receiver.position_enu(t) - tx.position_enu)) / SPEED_OF_LIGHT_M_S

    def los_at(self, emitter_index: int, t: float) -> bool:
        """Whether a direct path reaches the receiver at ``t`` (at the nearest sample point)."""
        link = self._links[emitter_index]
        k = self.sample_index(t)
        return bool(np.any(link.traced.los[k, link.keep[k]]))

    def paths(self, emitter_index: int, t: float) -> Paths:
        """Paths from emitter ``emitter_index`` to the receiver at true time ``t`` (s)."""
        link = self._links[emitter_index]
        k = self.sample_index(t)
        keep = link.keep[k]
        if keep.size == 0:
            return Paths([self.geometric_delay_s(emitter_index, t)], [0j], [0.0])
        traced = link.traced
        east, north, up = (self.receiver.position_enu(t) - traced.receivers_enu[k]).tolist()
        v_east, v_north, v_up = self.receiver.velocity_enu(t).tolist()
        arrival = traced.arrival_enu[k, keep]
        # term by term, not a matrix product: BLAS rounds differently per CPU (frontend.portable)
        shortening = arrival[:, 0] * east + arrival[:, 1] * north + arrival[:, 2] * up
        closing = arrival[:, 0] * v_east + arrival[:, 1] * v_north + arrival[:, 2] * v_up
        shift_s = -shortening / SPEED_OF_LIGHT_M_S
        carrier = traced.carrier_hz
        return Paths(
            delays_s=np.maximum(traced.delays_s[k, keep] + shift_s, 0.0),
            gains=link.gains[k, keep] * phasor((-2.0 * np.pi * carrier) * shift_s),
            doppler_hz=closing * (carrier / SPEED_OF_LIGHT_M_S),
        )

