"""The receiver's clock and its ADC: when samples are taken, and what codes come out."""

from __future__ import annotations

import math

import numpy as np
import scipy.signal

from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.video import highpass_settled_state, highpass_sos
from deepsync.rng import ADC_NOISE, indexed_rng
from deepsync.types import FRAME_SECONDS


class ReceiverClock:
    """Receiver time tau versus true time t: tau = t (1 + e0) + e1 t^2 / 2, tau = t = 0 at start.

    e0 is the clock's frequency offset and e1 its drift (both from ppm). The ADC takes sample n
    at receiver time n / rate, so a fast clock (e0 > 0) samples early in true time.
    """

    def __init__(self, offset_ppm: float = 0.0, drift_ppm_per_s: float = 0.0) -> None:
        self.e0 = offset_ppm * 1e-6
        self.e1 = drift_ppm_per_s * 1e-6

    def receiver_time(self, true_time: np.ndarray | float) -> np.ndarray | float:
        t = np.asarray(true_time, dtype=np.float64)
        return t * (1 + self.e0) + 0.5 * self.e1 * t * t

    @property
    def nominal(self) -> bool:
        """Whether receiver time is true time (no offset, no drift)."""
        return self.e0 == 0.0 and self.e1 == 0.0

    def true_time(self, receiver_time: np.ndarray | float) -> np.ndarray | float:
        tau = np.asarray(receiver_time, dtype=np.float64)
        a = 1 + self.e0
        # Root of e1/2 t^2 + a t - tau = 0 in the form that stays exact as e1 -> 0.
        return 2 * tau / (a + np.sqrt(a * a + 2 * self.e1 * tau))


def cubic_sample(signal: np.ndarray, first_index: int, positions: np.ndarray) -> np.ndarray:
    """Signal (given from index ``first_index`` on) at fractional ``positions``, 4-point Lagrange."""
    base = np.floor(positions).astype(np.int64)
    u = positions - base
    i = base - first_index
    if i.size and (i.min() < 1 or i.max() + 2 >= len(signal)):
        raise ValueError("cubic_sample: positions too close to the ends of the signal")
    xm1, x0, x1, x2 = signal[i - 1], signal[i], signal[i + 1], signal[i + 2]
    return (
        -u * (u - 1) * (u - 2) / 6 * xm1
        + (u + 1) * (u - 1) * (u - 2) / 2 * x0
        - (u + 1) * u * (u - 2) / 2 * x1
        + (u + 1) * u * (u - 1) / 6 * x2
    )


class AdcStage:
    """Video amplifier (AC coupling + gain) and quantiser, applied to the stream in order.

    The gain is either fixed by config or, like a power-up AGC, set once from the first 10 ms
    so the signal's RMS sits at ``agc_target_dbfs``, then held: level changes after that are
    real level changes in the recording, not hidden by a moving gain.
    """

    def __init__(self, config: FrontendConfig, seed: int) -> None:
        self.config = config
        self.seed = seed
        self.noise_block = max(1, round(config.adc_rate_hz * FRAME_SECONDS))
        self.settling = self.noise_block
        self._sos = highpass_sos(config, config.adc_rate_hz)
        self._zi: np.ndarray | None = None
        self.gain = None if config.video_gain_db is None else 10 ** (config.video_gain_db / 20)
        self.lowest = -(2 ** (config.adc_bits - 1))
        self.highest = 2 ** (config.adc_bits - 1) - 1
        self.clipped = 0

    def couple(self, volts: np.ndarray) -> np.ndarray:
        """AC coupling (state carried across calls; starts settled on the mean of the first
        10 ms, so a stream starts the same however long it is)."""
        if self._sos is None:
            return volts
        if self._zi is None:
            self._zi = highpass_settled_state(self._sos, float(np.mean(volts[: self.settling])))
        out, self._zi = scipy.signal.sosfilt(self._sos, volts, zi=self._zi)
        return out

    def set_gain_from(self, coupled: np.ndarray) -> None:
        rms = float(np.sqrt(np.mean(coupled**2)))
        target = self.config.adc_full_scale_v / 2 * 10 ** (self.config.agc_target_dbfs / 20)
        self.gain = target / rms if rms > 0 else 1.0

    @property
    def gain_db(self) -> float:
        return 20 * math.log10(self.gain) if self.gain else float("nan")

    def quantize(self, first_sample: int, coupled: np.ndarray) -> np.ndarray:
        """ADC codes of samples ``first_sample ..``: gain, ADC noise, rounding, clipping.

        ADC noise is drawn per fixed 10 ms block of sample indices, so the codes do not
        depend on how the stream was cut into calls.
        """
        codes = coupled * (self.gain / self.config.volts_per_code)
        if self.config.adc_noise_lsb > 0:
            codes += self._adc_noise(first_sample, len(coupled))
        np.rint(codes, out=codes)
        inside = np.clip(codes, self.lowest, self.highest)
        self.clipped += len(codes) - int(np.count_nonzero(inside == codes))
        return inside.astype("<i2")

    def _adc_noise(self, first_sample: int, count: int) -> np.ndarray:
        noise = np.empty(count, dtype=np.float32)
        block = first_sample // self.noise_block
        position = 0
        while position < count:
            offset = (first_sample + position) - block * self.noise_block
            take = min(self.noise_block - offset, count - position)
            rng = indexed_rng(self.seed, ADC_NOISE, block)
            draws = rng.standard_normal(self.noise_block, dtype=np.float32)
            noise[position : position + take] = draws[offset : offset + take]
            position += take
            block += 1
        return noise * np.float32(self.config.adc_noise_lsb)
