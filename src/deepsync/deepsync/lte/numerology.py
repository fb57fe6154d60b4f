"""LTE downlink numerology (TS 36.211 §6.2, §6.12; TS 36.101 §5.6).

Times are kept as integer counts of a *base sample*: 1/1.92 MHz, the sample period of the
1.4 MHz carrier's 128-point FFT. Every LTE rate is an integer multiple of 1.92 MHz, so with
``oversampling = N_fft / 128`` all CP lengths and symbol boundaries stay integers at any rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from deepsync.types import FRAME_SECONDS

SUBCARRIER_SPACING_HZ = 15_000.0
BASE_RATE_HZ = 1.92e6  # 128 subcarrier-spacings; the 1.4 MHz carrier's sample rate
SUBFRAMES_PER_FRAME = 10
SLOTS_PER_FRAME = 20
SYMBOLS_PER_SLOT = 7  # normal cyclic prefix
SYMBOLS_PER_FRAME = SLOTS_PER_FRAME * SYMBOLS_PER_SLOT
SUBCARRIERS_PER_RB = 12
N_RB_MAX = 110  # N_RB^{max,DL}, sets the CRS sequence length
BASE_FFT = 128
BASE_SAMPLES_PER_FRAME = int(round(BASE_RATE_HZ * FRAME_SECONDS))  # 19200

# Normal CP in units of Ts = 1/30.72 MHz: 160 for symbol 0 of a slot, 144 otherwise.
# At the 128-point base rate (Ts * 16) that is 10 and 9 samples.
_BASE_CP_FIRST = 10
_BASE_CP_OTHER = 9

# Channel bandwidth (MHz) -> number of downlink resource blocks (TS 36.101 Table 5.6-1)
# and the standard FFT size used for it.
_RESOURCE_BLOCKS = {1.4: 6, 3.0: 15, 5.0: 25, 10.0: 50, 15.0: 75, 20.0: 100}
_STANDARD_FFT = {1.4: 128, 3.0: 256, 5.0: 512, 10.0: 1024, 15.0: 1536, 20.0: 2048}

SUPPORTED_BANDWIDTHS_MHZ = tuple(_RESOURCE_BLOCKS)


def check_bandwidth(bandwidth_mhz: float) -> float:
    """Return the canonical bandwidth key, or raise naming the valid choices."""
    try:
        value = float(bandwidth_mhz)
    except (TypeError, ValueError):
        raise ValueError(f"bandwidth {bandwidth_mhz!r} is not a number") from None
    for key in _RESOURCE_BLOCKS:
        if abs(value - key) < 1e-6:
            return key
    raise ValueError(
        f"bandwidth {bandwidth_mhz!r} MHz is not an LTE channel bandwidth; "
        f"choose one of {', '.join(f'{b:g}' for b in SUPPORTED_BANDWIDTHS_MHZ)}"
    )


class FftGrid:
    """A grid of ``fft_size`` bins of 15 kHz: a carrier's (``Numerology``) or a cluster's of carriers."""

    fft_size: int

    @property
    def oversampling(self) -> int:
        """Samples per base (1.92 MHz) sample."""
        return self.fft_size // BASE_FFT

    @property
    def sample_rate_hz(self) -> float:
        return self.fft_size * SUBCARRIER_SPACING_HZ


@dataclass(frozen=True)
class Numerology(FftGrid):
    """Resource-grid and sampling parameters of one LTE carrier at one sample rate."""

    bandwidth_mhz: float
    n_rb: int
    fft_size: int

    @classmethod
    def for_bandwidth(cls, bandwidth_mhz: float, fft_size: int | None = None) -> Numerology:
        """Numerology of ``bandwidth_mhz``; ``fft_size`` defaults to the standard one.

        Any multiple of 128 that holds the occupied subcarriers is allowed: simulations use
        the smallest rate that is alias-free for what they need, not always the standard one.
        """
        key = check_bandwidth(bandwidth_mhz)
        n_rb = _RESOURCE_BLOCKS[key]
        size = _STANDARD_FFT[key] if fft_size is None else int(fft_size)
        if size % BASE_FFT or size < n_rb * SUBCARRIERS_PER_RB + 1:
            raise ValueError(
                f"fft_size {fft_size} must be a multiple of {BASE_FFT} larger than the "
                f"{n_rb * SUBCARRIERS_PER_RB} occupied subcarriers of a {key:g} MHz carrier"
            )
        return cls(key, n_rb, size)

    @property
    def n_subcarriers(self) -> int:
        return self.n_rb * SUBCARRIERS_PER_RB

    @property
    def occupied_bandwidth_hz(self) -> float:
        """Span of the occupied subcarriers plus the unused DC subcarrier."""
        return (self.n_subcarriers + 1) * SUBCARRIER_SPACING_HZ

    @property
    def cp_lengths(self) -> np.ndarray:
        """Cyclic-prefix length (samples) of each of the 140 symbols of a frame."""
        per_slot = np.full(SYMBOLS_PER_SLOT, _BASE_CP_OTHER * self.oversampling)
        per_slot[0] = _BASE_CP_FIRST * self.oversampling
        return np.tile(per_slot, SLOTS_PER_FRAME)

    @property
    def symbol_starts(self) -> np.ndarray:
        """Start (CP included) of each symbol of a frame, in samples from the frame start."""
        lengths = self.cp_lengths + self.fft_size
        return np.concatenate(([0], np.cumsum(lengths)[:-1]))

    @property
    def samples_per_frame(self) -> int:
        return BASE_SAMPLES_PER_FRAME * self.oversampling

    def subcarrier_offsets(self) -> np.ndarray:
        """Frequency of each occupied subcarrier k = 0..K-1 in units of 15 kHz from DC.

        TS 36.211 §6.12: the DC subcarrier carries nothing and is not counted in k, so the
        lower half sits at -K/2..-1 and the upper half at +1..+K/2.
        """
        k = np.arange(self.n_subcarriers)
        half = self.n_subcarriers // 2
        return np.where(k < half, k - half, k - half + 1)


def sync_code_start_base() -> int:
    """Start of the SSS symbol (CP included) in slot 0, in base samples from the frame start.

    The SSS+PSS pair occupies the last two symbols of slots 0 and 10 (FDD): the *sync code*
    whose arrival time DeepSync estimates starts here and lasts ``SYNC_CODE_BASE_SAMPLES``.
    """
    return int(Numerology.for_bandwidth(1.4).symbol_starts[SYMBOLS_PER_SLOT - 2])


SYNC_CODE_BASE_SAMPLES = 2 * (BASE_FFT + _BASE_CP_OTHER)  # 274 samples at 1.92 MHz
HALF_FRAME_BASE_SAMPLES = BASE_SAMPLES_PER_FRAME // 2
