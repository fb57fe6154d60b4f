"""What the front end needs from the world: emitters and the propagation paths to them.

The digital twin (``deepsync.twin``) implements :class:`ChannelProvider`; a ray tracer
plugs in the same way. The front end never asks *why* a path exists, only its delay, gain
and Doppler, so a statistical 3GPP channel and a ray-traced one are interchangeable.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from deepsync.lte.cell import CellConfig


@dataclass(frozen=True)
class Emitter:
    """One cell as the receiver sees it, before propagation.

    ``re_power_w`` is the EIRP of one resource element towards antenna boresight (W); the
    channel's path gains carry everything after that (antenna pattern, path loss, fading).
    ``timing_offset_s`` is when the cell's frame 0 starts in true (network) time, i.e. its
    frame timing relative to the common time origin; ``frequency_offset_hz`` the carrier
    error of the site oscillator. Cells of one ``site`` share position, timing and oscillator.
    """

    cell: CellConfig
    carrier_hz: float
    re_power_w: float
    timing_offset_s: float = 0.0
    frequency_offset_hz: float = 0.0
    site: str = ""


@dataclass(frozen=True)
class Paths:
    """Propagation paths from one emitter to the receiver antenna at one instant.

    delays_s:   (P,) absolute propagation delay of each path (s), all >= 0
    gains:      (P,) complex amplitude gain of each path (sqrt of linear power gain), with
                the transmit antenna pattern, path loss, shadowing, fading and carrier phase
    doppler_hz: (P,) Doppler shift of each path (Hz); the gain evolves as exp(j 2 pi f t)
    """

    delays_s: np.ndarray
    gains: np.ndarray
    doppler_hz: np.ndarray

    def __post_init__(self) -> None:
        delays = np.atleast_1d(np.asarray(self.delays_s, dtype=np.float64))
        gains = np.atleast_1d(np.asarray(self.gains, dtype=np.complex128))
        doppler = np.atleast_1d(np.asarray(self.doppler_hz, dtype=np.float64))
        if not (delays.shape == gains.shape == doppler.shape) or delays.ndim != 1:
            raise ValueError(
                f"Paths arrays must be 1-D of equal length, got delays {delays.shape}, "
                f"gains {gains.shape}, doppler {doppler.shape}"
            )
        if delays.size == 0:
            raise ValueError("Paths needs at least one path")
        for name, values in (("delays_s", delays), ("gains", gains), ("doppler_hz", doppler)):
            if not np.all(np.isfinite(values)):
                raise ValueError(f"Paths.{name} contains NaN or inf")
        if np.any(delays < 0):
            raise ValueError("Paths.delays_s must be non-negative")
        object.__setattr__(self, "delays_s", delays)
        object.__setattr__(self, "gains", gains)
        object.__setattr__(self, "doppler_hz", doppler)

    @property
    def first_delay_s(self) -> float:
        return float(self.delays_s.min())


class ChannelProvider(Protocol):
    """Source of propagation paths; the seam between the front end and the world model."""

    def paths(self, emitter_index: int, t: float) -> Paths:
        """Paths from emitter ``emitter_index`` to the receiver at true time ``t`` (s).

        Called once per emitted 10 ms frame with ``t`` at the frame's arrival; within that
        frame the front end holds delays fixed and rotates each gain by its Doppler.
        """
        ...


class FixedChannel:
    """A :class:`ChannelProvider` whose paths never change: a static scene, a test, a benchmark.

    ``paths`` is one :class:`Paths` for every emitter, or one per emitter (by index).
    """

    def __init__(self, paths: Paths | Sequence[Paths]) -> None:
        self._paths = paths

    def paths(self, emitter_index: int, t: float) -> Paths:
        return self._paths if isinstance(self._paths, Paths) else self._paths[emitter_index]
