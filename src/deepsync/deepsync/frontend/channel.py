"""What the front end needs from the world: emitters and the propagation paths to them.

The digital twin (``deepsync.twin``) implements :class:`ChannelProvider`; a ray tracer
plugs in the same way. The front end never asks *why* a path exists, only its delay, gain
and Doppler, so a statistical 3GPP channel and a ray-traced one are interchangeable.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from deepsync.lte.cell import CellConfig
from deepsync.types import FRAME_SECONDS

MAX_FRAME_RATE_ERROR = 1e-3  # 1e6 ppb: far beyond any oscillator that still carries LTE


@dataclass(frozen=True)
class Emitter:
    """One cell as the receiver sees it, before propagation.

    ``re_power_w`` is the EIRP of one resource element towards antenna boresight (W); the
    channel's path gains carry everything after that (antenna pattern, path loss, fading).
    ``frequency_offset_hz`` is the carrier error of the site oscillator. Cells of one ``site``
    share position, timing and oscillator.

    Frame timing: the site's frame clock runs on its oscillator, ``frame_rate_error`` (eps)
    fast (+20e-9: 20 ppb fast), and reads ``(1 + eps) t - timing_offset_s`` at true (network)
    time t; frame k starts when it reads k frames (:meth:`frame_start_s`). So
    ``timing_offset_s`` is the frame timing offset (a frame start minus a whole number of
    frames) at true time 0, and that offset changes by exactly ``-eps`` seconds per second
    (:attr:`timing_drift_s_per_s`): a site 20 ppb fast is 1.2 us early after a minute. With
    eps = 0 frame k starts at ``timing_offset_s + k * FRAME_SECONDS``, bit for bit. Only frame
    starts drift: within a frame the waveform keeps its nominal sample spacing (at most
    10 ms x eps late by the frame's end, 10 ns at the 1000 ppb a scenario allows).
    """

    cell: CellConfig
    carrier_hz: float
    re_power_w: float
    timing_offset_s: float = 0.0
    frequency_offset_hz: float = 0.0
    site: str = ""
    frame_rate_error: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.frame_rate_error) and abs(self.frame_rate_error) <= MAX_FRAME_RATE_ERROR):
            raise ValueError(f"Emitter.frame_rate_error must be finite and within +-{MAX_FRAME_RATE_ERROR:g}, "
                             f"got {self.frame_rate_error!r}")

    @property
    def timing_drift_s_per_s(self) -> float:
        """How fast the frame timing offset changes (s per s of true time): ``-frame_rate_error``."""
        return -self.frame_rate_error

    def frame_slip_s(self, k: int) -> float:
        """How much earlier than ``timing_offset_s + k * FRAME_SECONDS`` frame k starts (s):
        ``(timing_offset_s + k F) eps / (1 + eps)``; exactly 0.0 without drift."""
        eps = self.frame_rate_error
        if eps == 0.0:
            return 0.0
        return (self.timing_offset_s + k * FRAME_SECONDS) * (eps / (1.0 + eps))

    def frame_start_s(self, k: int) -> float:
        """True time at which frame ``k`` leaves the antenna (s)."""
        return self.timing_offset_s + k * FRAME_SECONDS - self.frame_slip_s(k)

    def timing_offset_at(self, t: float) -> float:
        """The frame timing offset at true time ``t`` (s): ``timing_offset_s - eps t``."""
        return self.timing_offset_s + self.timing_drift_s_per_s * t

    def frame_index_at(self, t: float) -> int:
        """Index of the frame the site is sending at true time ``t`` (the last one started)."""
        k = math.floor(((1.0 + self.frame_rate_error) * t - self.timing_offset_s) / FRAME_SECONDS)
        # float rounding at a frame boundary: settle on the exact start times
        while self.frame_start_s(k) > t:
            k -= 1
        while self.frame_start_s(k + 1) <= t:
            k += 1
        return k


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
