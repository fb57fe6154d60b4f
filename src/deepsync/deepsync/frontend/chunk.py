"""The ADC stream in core form: what the envelope source emits and cell search consumes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class EnvelopeChunk:
    """A contiguous run of raw ADC codes.

    ``first_sample_index`` counts samples since the stream began and is monotonic across
    chunks, so a gap shows up as a jump; ``stamp_ns`` is the receiver-clock time of the first
    sample (ns). ``samples`` are the raw int16 codes; volts = code * ``volts_per_code``.
    """

    stamp_ns: int
    sample_rate: float
    first_sample_index: int
    adc_bits: int
    volts_per_code: float
    samples: np.ndarray

    def __post_init__(self) -> None:
        samples = np.ascontiguousarray(self.samples, dtype="<i2")
        if samples.ndim != 1:
            raise ValueError(f"EnvelopeChunk.samples must be 1-D, got shape {samples.shape}")
        if not (np.isfinite(self.sample_rate) and self.sample_rate > 0):
            raise ValueError(f"EnvelopeChunk.sample_rate {self.sample_rate!r} must be > 0")
        if self.first_sample_index < 0:
            raise ValueError("EnvelopeChunk.first_sample_index must be >= 0")
        if not 1 <= self.adc_bits <= 16:
            raise ValueError(f"EnvelopeChunk.adc_bits {self.adc_bits!r} must be 1..16")
        if not (np.isfinite(self.volts_per_code) and self.volts_per_code > 0):
            raise ValueError(f"EnvelopeChunk.volts_per_code {self.volts_per_code!r} must be > 0")
        object.__setattr__(self, "samples", samples)

    @property
    def end_sample_index(self) -> int:
        """Index one past the last sample: the next chunk's ``first_sample_index`` if no gap."""
        return self.first_sample_index + len(self.samples)
