"""The analog video path after the diode: low-pass (anti-alias) filter and AC coupling.

The low-pass filter is an analog Butterworth applied through its exact frequency response
H(f) (see ``deepsync.frontend.square_law``), so the result does not depend on any simulation
rate: the simulated stream and the sync templates see the same filter to numerical precision.
Both filters are evaluated with real arithmetic and the C library's trigonometry
(``deepsync.frontend.portable``): the same coefficients on every CPU.
"""

from __future__ import annotations

import math

import numpy as np

from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.portable import multiply_double, phasor

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
        # the Butterworth poles on the left half of the circle of radius 2 pi f_c
        radius = 2 * math.pi * self.cutoff_hz
        self._poles = [complex(radius * math.cos(angle), radius * math.sin(angle))
                       for angle in (math.pi * (2 * k + self.order + 1) / (2 * self.order) for k in range(self.order))]

    def analog_response(self, frequency_hz: np.ndarray) -> np.ndarray:
        """Complex H(f) of the ideal analog Butterworth at the given frequencies (Hz); 1 for order 0.

        H = prod_k (-p_k) / (j 2 pi f - p_k): unit gain at DC, one factor per pole.
        """
        omega = 2 * math.pi * np.asarray(frequency_hz, dtype=np.float64)
        response = np.ones(omega.shape, dtype=np.complex128)
        for pole in self._poles:
            below = np.empty(omega.shape, dtype=np.complex128)  # j omega - p
            below.real = -pole.real
            below.imag = omega - pole.imag
            magnitude = below.real * below.real + below.imag * below.imag
            factor = multiply_double(-pole, below.conjugate())
            factor.real /= magnitude
            factor.imag /= magnitude
            response = multiply_double(response, factor)
        return response

    def response(self, frequency_hz: np.ndarray) -> np.ndarray:
        """H(f) as simulated: the analog response, tapered to zero where it is already < -57 dB.

        The detector keeps nothing above ``stopband_hz``; a raised-cosine taper over the last
        30 % before it (instead of a brick wall) keeps the filter's impulse response short, so
        block-wise (overlap-save) filtering is exact. The change is below -57 dB everywhere.
        """
        f = np.abs(np.asarray(frequency_hz, dtype=np.float64))
        if not self._poles:
            return np.ones(f.shape, dtype=complex)
        edge = self.stopband_hz
        start = (1 - TAPER_FRACTION) * edge
        cosine = phasor(np.pi * np.clip((f - start) / (edge - start), 0, 1)).real
        taper = np.where(f <= start, 1.0, 0.5 * (1 + cosine))
        return self.analog_response(f) * taper

    def attenuation_hz(self, decibels: float) -> float:
        """Frequency where the Butterworth is ``decibels`` down: |H|^2 = 1 / (1 + (f/fc)^(2n));
        without a filter (order 0), the ADC's Nyquist frequency."""
        if not self._poles:
            return self.nyquist_hz
        return self.cutoff_hz * (10 ** (decibels / 10) - 1) ** (1 / (2 * self.order))

    @property
    def stopband_hz(self) -> float:
        """Frequency above which |H| < -60 dB: what the detector keeps of |x|^2."""
        return self.attenuation_hz(STOPBAND_DB)

    @property
    def settle_seconds(self) -> float:
        """Time for the impulse response to decay below ``SETTLE_FRACTION`` of its peak."""
        if not self._poles:
            return 0.0
        slowest = min(-p.real for p in self._poles)
        return math.log(1 / SETTLE_FRACTION) / slowest

    def group_delay_seconds(self) -> float:
        """Group delay at DC; where the filter puts the envelope's centre of gravity."""
        return sum(-1 / p for p in self._poles).real if self._poles else 0.0


def highpass_sos(config: FrontendConfig, sample_rate_hz: float) -> np.ndarray | None:
    """First-order AC-coupling high-pass at the ADC rate, or None when DC-coupled.

    The bilinear transform of s / (s + w) with w pre-warped to the corner (what
    ``scipy.signal.butter(1, f, "highpass", fs=...)`` designs), as one second-order section. At
    50 Hz against a 1.92 MHz rate it is exact to ~1e-9, so applying the coupling after sampling
    equals applying it before.
    """
    if config.video_highpass_hz == 0:
        return None
    twice_rate = 2 * sample_rate_hz
    corner = twice_rate * math.tan(math.pi * config.video_highpass_hz / sample_rate_hz)
    gain = twice_rate / (twice_rate + corner)
    pole = (twice_rate - corner) / (twice_rate + corner)
    return np.array([[gain, -gain, 0.0, 1.0, -pole, 0.0]])


def highpass_settled_state(sos: np.ndarray, level: float) -> np.ndarray:
    """State of ``highpass_sos`` that has long seen a constant input ``level``: output 0."""
    return np.array([[-sos[0, 0] * level, 0.0]])
