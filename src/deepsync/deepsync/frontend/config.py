"""Parameters of the envelope-detector receiver, from antenna to ADC codes."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class FrontendConfig:
    """The receiver chain: LNA (+ RF noise) -> square-law diode -> video filter/amp -> ADC.

    Defaults describe a low-power LNA (30 dB, NF 6 dB: without gain ahead of it, a diode's
    own noise buries cells received at -60 dBm), a zero-bias Schottky detector (responsivity ~3 kV/W, noise-equivalent
    power ~5 pW/sqrt(Hz) into a high-impedance video amplifier), a 4th-order 0.9 MHz
    Butterworth anti-alias/video filter, AC coupling, and a 12-bit 1.92 MS/s ADC with a
    crystal clock. ``noise_temperature_k: 0`` and ``detector_nep_w_per_sqrt_hz: 0`` switch
    the RF and detector noise off (for checks of the noiseless chain). ``video_gain_db: null`` means the gain is set once, from the first 10 ms,
    so the signal sits at ``agc_target_dbfs`` (power-up AGC; held fixed afterwards).
    """

    adc_rate_hz: float = 1.92e6
    adc_bits: int = 12
    adc_full_scale_v: float = 2.0
    adc_noise_lsb: float = 0.3
    clock_offset_ppm: float = 0.0
    clock_drift_ppm_per_s: float = 0.0
    video_cutoff_hz: float = 0.9e6
    video_filter_order: int = 4
    video_highpass_hz: float = 50.0
    video_gain_db: float | None = None
    agc_target_dbfs: float = -20.0
    detector_responsivity_v_per_w: float = 3000.0
    detector_nep_w_per_sqrt_hz: float = 5e-12
    noise_figure_db: float = 6.0
    rf_gain_db: float = 30.0
    rf_bandwidth_hz: float = 200e6
    noise_temperature_k: float = 290.0

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        positive = (
            "adc_rate_hz", "adc_full_scale_v", "video_cutoff_hz",
            "detector_responsivity_v_per_w", "rf_bandwidth_hz",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("adc_noise_lsb", "video_highpass_hz", "detector_nep_w_per_sqrt_hz",
                     "noise_figure_db", "noise_temperature_k"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not 2 <= self.adc_bits <= 16:
            raise ValueError(f"adc_bits must be 2..16 (codes are int16), got {self.adc_bits!r}")
        if not 0 <= self.video_filter_order <= 8:
            raise ValueError(f"video_filter_order must be 0..8 (0: none), got {self.video_filter_order!r}")
        if self.video_cutoff_hz >= self.adc_rate_hz:
            raise ValueError(
                f"video_cutoff_hz ({self.video_cutoff_hz:g}) must be below adc_rate_hz "
                f"({self.adc_rate_hz:g}); the video filter is the ADC's anti-alias filter"
            )
        if self.video_highpass_hz >= self.video_cutoff_hz / 10:
            raise ValueError(
                f"video_highpass_hz ({self.video_highpass_hz:g}) must be far below "
                f"video_cutoff_hz ({self.video_cutoff_hz:g})"
            )
        if abs(self.clock_offset_ppm) > 1000 or abs(self.clock_drift_ppm_per_s) > 10:
            raise ValueError(
                "clock_offset_ppm must be within +-1000 and clock_drift_ppm_per_s within +-10"
            )
        if not 0 <= self.rf_gain_db <= 60:
            raise ValueError(f"rf_gain_db must be within 0..60 dB, got {self.rf_gain_db!r}")
        if self.agc_target_dbfs >= 0:
            raise ValueError(f"agc_target_dbfs must be < 0 dBFS, got {self.agc_target_dbfs!r}")

    @property
    def rf_power_gain(self) -> float:
        """Linear power gain from the antenna to the diode."""
        return 10 ** (self.rf_gain_db / 10)

    @property
    def volts_per_code(self) -> float:
        return self.adc_full_scale_v / 2**self.adc_bits
