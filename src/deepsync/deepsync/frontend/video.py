"""The analog video path after the diode: low-pass (anti-alias) filter and AC coupling.

The low-pass filter is an analog Butterworth applied through its exact frequency response
H(f) (see ``deepsync.frontend.square_law``), so the result does not depend on any simulation
rate: the simulated stream and the sync templates see the same filter to numerical precision.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.signal

from deepsync.frontend.config import FrontendConfig

STOPBAND_DB = 60.0  # beyond the frequency where |H| falls this far, the detector output is dropped
TAPER_FRACTION = 0.3
SETTLE_FRACTION = 1e-7  # impulse-response tail left out of the overlap, relative to its peak


class VideoFilter:
    """Analog low-pass between the square-law diode and the ADC.

    Order 0 means no video filter: the envelope of an SDR recording, squared digitally after
    the radio's own channel filter, is described that way (for templates; the simulator needs
    an anti-alias filter in front of its ADC).
    """

    def __init__(self, config: FrontendConfig) -> None:
        self.cutoff_hz = config.video_cutoff_hz
        self.order = config.video_filter_order
        self.nyquist_hz = config.adc_rate_hz / 2
        self._zpk = None if self.order == 0 else scipy.signal.butter(
            self.order, 2 * np.pi * self.cutoff_hz, analog=True, output="zpk")

    def analog_response(self, frequency_hz: np.ndarray) -> np.ndarray:
        """Complex H(f) of the ideal analog Butterworth at the given frequencies (Hz); 1 for order 0."""
        if self._zpk is None:
            return np.ones(np.shape(frequency_hz), dtype=complex)
        _, h = scipy.signal.freqs_zpk(*self._zpk, worN=2 * np.pi * np.asarray(frequency_hz))
        return h

    def response(self, frequency_hz: np.ndarray) -> np.ndarray:
        """H(f) as simulated: the analog response, tapered to zero where it is already < -57 dB.

        The detector keeps nothing above ``stopband_hz``; a raised-cosine taper over the last
        30 % before it (instead of a brick wall) keeps the filter's impulse response short, so
        block-wise (overlap-save) filtering is exact. The change is below -57 dB everywhere.
        """
        f = np.abs(np.asarray(frequency_hz, dtype=np.float64))
        if self._zpk is None:
            return np.ones(f.shape, dtype=complex)
        edge = self.stopband_hz
        start = (1 - TAPER_FRACTION) * edge
        taper = np.where(f <= start, 1.0, 0.5 * (1 + np.cos(np.pi * np.clip((f - start) / (edge - start), 0, 1))))
        return self.analog_response(f) * taper

    def attenuation_hz(self, decibels: float) -> float:
        """Frequency where the Butterworth is ``decibels`` down: |H|^2 = 1 / (1 + (f/fc)^(2n));
        without a filter (order 0), the ADC's Nyquist frequency."""
        if self._zpk is None:
            return self.nyquist_hz
        return self.cutoff_hz * (10 ** (decibels / 10) - 1) ** (1 / (2 * self.order))

    @property
    def stopband_hz(self) -> float:
        """Frequency above which |H| < -60 dB: what the detector keeps of |x|^2."""
        return self.attenuation_hz(STOPBAND_DB)

    @property
    def settle_seconds(self) -> float:
        """Time for the impulse response to decay below ``SETTLE_FRACTION`` of its peak."""
        if self._zpk is None:
            return 0.0
        slowest = min(-p.real for p in self._zpk[1])
        return math.log(1 / SETTLE_FRACTION) / slowest

    def group_delay_seconds(self) -> float:
        """Group delay at DC; where the filter puts the envelope's centre of gravity."""
        return 0.0 if self._zpk is None else float(sum(-1 / p for p in self._zpk[1]).real)


def highpass_sos(config: FrontendConfig, sample_rate_hz: float) -> np.ndarray | None:
    """First-order AC-coupling high-pass at the ADC rate, or None when DC-coupled.

    At 50 Hz against a 1.92 MHz rate the bilinear transform is exact to ~1e-9, so applying
    the coupling after sampling equals applying it before.
    """
    if config.video_highpass_hz == 0:
        return None
    return scipy.signal.butter(1, config.video_highpass_hz, btype="highpass", fs=sample_rate_hz, output="sos")
