"""What every source is (:class:`Source`), and the streaming shared by the file sources.

A source turns a recording into the stream a live receiver would publish: one
:class:`~deepsync.types.EnvelopeChunk` per LTE frame (10 ms, ``round(rate * FRAME_SECONDS)``
samples; the last may be shorter), ``first_sample_index`` contiguous from 0, ``stamp_ns``
advancing at the sample rate from the stamp of sample 0. The rate has one home: the source's
``frontend.adc_rate_hz``, the receiver chain the sync templates are built from.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from fractions import Fraction
from typing import Protocol, runtime_checkable

import numpy as np
from tqdm import tqdm

from deepsync.frontend.config import FrontendConfig
from deepsync.sync.stacking import check_stack_rate
from deepsync.types import FRAME_SECONDS, EnvelopeChunk
from .envelope import (
    NonFiniteSample,
    block_peak,
    check_scale,
    envelope_codes,
    scale_from_peak,
    squared_iq_frontend,
)
from .formats import SampleFormat

PEAK_BLOCK_SAMPLES = 1 << 20  # samples per read in the scale pass: bounded memory for any file
LONG_PASS = 1 << 26  # samples from which the scale pass shows a progress bar (35 s at 1.92 MS/s)


@runtime_checkable
class Source(Protocol):
    """Where envelope chunks come from: a recording of any kind, or a live receiver."""

    description: str
    """One line for people: what the stream is and where it comes from."""
    frontend: FrontendConfig
    """The receiver chain the stream went through; its ``adc_rate_hz`` is the stream's rate."""
    center_hz: float | None
    """The recording's centre (tuning) frequency, when known."""

    def chunks(self) -> Iterator[EnvelopeChunk]:
        """The stream, one LTE frame per chunk, from sample 0 (each call starts over)."""
        ...


def frame_samples(sample_rate: float) -> int:
    """Samples per chunk: one LTE frame at ``sample_rate``."""
    return max(1, round(sample_rate * FRAME_SECONDS))


def stamp_at(stamp_ns: int, index: int, sample_rate: float) -> int:
    """Receiver time (ns) of sample ``index``, exact in integers: a float product would drift by
    microseconds over a long recording (1e9 * index exceeds a double's 53 bits)."""
    return int(stamp_ns) + round(Fraction(int(index) * 10**9) / Fraction(sample_rate))


def check_rate(sample_rate: object, where: str) -> float:
    """``sample_rate`` as a float, or ValueError naming ``where`` (missing, or not one the cell
    search serves: ``sync.stacking.check_stack_rate``)."""
    if sample_rate is None:
        raise ValueError(f"{where}: the sample rate must be given (the file does not say it)")
    try:
        rate = float(sample_rate)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{where}: sample rate {sample_rate!r} is not a number") from None
    try:
        return check_stack_rate(rate)
    except ValueError as error:
        raise ValueError(f"{where}: {error}") from None


def centred_iq(values: np.ndarray, sample_format: SampleFormat) -> np.ndarray:
    """Interleaved stored I/Q values as complex64 ``(I - zero) + j (Q - zero)``."""
    comps = np.asarray(values).reshape(-1, 2)
    out = np.empty(comps.shape[0], dtype=np.complex64)
    zero = np.float32(sample_format.zero)
    out.real = comps[:, 0].astype(np.float32) - zero
    out.imag = comps[:, 1].astype(np.float32) - zero
    return out


def stream_frontend(sample_format: SampleFormat, sample_rate: float, where: str) -> FrontendConfig:
    """The receiver chain of a stream of stored samples: I/Q squared digitally
    (:func:`~deepsync.sources.envelope.squared_iq_frontend`), or the default envelope-detector
    chain for a real envelope format; ValueError naming ``where`` when none is at that rate."""
    try:
        if sample_format.is_complex:
            return squared_iq_frontend(sample_rate)
        return FrontendConfig(adc_rate_hz=sample_rate)
    except ValueError as error:
        raise ValueError(f"{where}: no receiver chain at {sample_rate:g} Hz: {error}") from None


BlockReader = Callable[[int, int], np.ndarray]
"""``read(start, stop)``: the stored values of samples ``start:stop``, interleaved (I0 Q0 ...)."""


@dataclass(frozen=True)
class Segment:
    """A run of a recording's samples that the receiver delivered without a break: samples
    ``start:stop`` of the file, the first of them sample ``index`` of the stream (the file's
    position plus every sample the receiver lost before it) at receiver time ``stamp_ns``.
    A recording that says it lost samples (a SigMF capture after a dropout) has several; the
    stream then jumps by what was lost, which the sync stage reports as a gap."""

    start: int
    stop: int
    index: int
    stamp_ns: int


class FileSource:
    """A recording of stored samples (a raw file, a SigMF dataset) streamed as envelope codes.

    Subclasses open the file, then call :meth:`_setup` with how to read it. The default scale
    is found here, in one pass over the file (see :mod:`deepsync.sources.envelope`).
    """

    path: str
    sample_format: SampleFormat
    sample_rate: float
    n_samples: int
    scale: float
    stamp_ns: int
    center_hz: float | None
    frontend: FrontendConfig

    def _setup(self, path: str, sample_format: SampleFormat, sample_rate: float, n_samples: int,
               read: BlockReader, scale: float | None, stamp_ns: int, center_hz: float | None,
               segments: tuple[Segment, ...] | None = None) -> None:
        """``segments``: where the receiver lost samples (default: none, one segment from
        ``stamp_ns``)."""
        self.path = path
        self.sample_format = sample_format
        self.sample_rate = sample_rate
        self.n_samples = n_samples
        self.stamp_ns = int(stamp_ns)
        self.center_hz = center_hz
        self.segments = segments or (Segment(0, n_samples, 0, self.stamp_ns),)
        self._read = read
        try:
            given = check_scale(scale)
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None
        self.scale = self._default_scale() if given is None else given
        self.frontend = stream_frontend(sample_format, sample_rate, path)

    def _block(self, start: int, stop: int, convert: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """``convert`` of samples ``start:stop``; a non-finite sample raises with its file index."""
        try:
            return convert(self._read(start, stop))
        except NonFiniteSample as error:
            raise ValueError(
                f"{self.path}: sample {start + error.index} is not finite ({error.value}); an "
                "envelope code cannot carry NaN or inf (a broken recording?)"
            ) from None

    def _default_scale(self) -> float:
        if self.sample_format is SampleFormat.RI16_LE:
            return 1.0  # the values are ADC codes already
        peak = 0.0
        # a long recording's pass shows its progress (20 GB of cu8 took 10 silent minutes)
        with tqdm(total=self.n_samples, unit="S", unit_scale=True, leave=False, disable=self.n_samples < LONG_PASS,
                  desc=f"{os.path.basename(self.path)}: its peak, for the scale (--scale skips this)") as bar:
            for start in range(0, self.n_samples, PEAK_BLOCK_SAMPLES):
                stop = min(start + PEAK_BLOCK_SAMPLES, self.n_samples)
                peak = max(peak, self._block(start, stop, lambda v: block_peak(v, self.sample_format)))
                bar.update(stop - start)
        return scale_from_peak(peak)

    def chunks(self) -> Iterator[EnvelopeChunk]:
        """One chunk per LTE frame (none across the end of a segment); codes per
        :mod:`deepsync.sources.envelope`."""
        step = frame_samples(self.sample_rate)
        for segment in self.segments:
            for first in range(segment.start, segment.stop, step):
                stop = min(first + step, segment.stop)
                codes = self._block(first, stop, lambda v: envelope_codes(v, self.sample_format, self.scale))
                yield EnvelopeChunk(
                    stamp_ns=stamp_at(segment.stamp_ns, first - segment.start, self.sample_rate),
                    sample_rate=self.sample_rate,
                    first_sample_index=segment.index + first - segment.start,
                    adc_bits=16,
                    volts_per_code=self.scale,
                    samples=codes,
                )

    def read_iq(self) -> np.ndarray:
        """All samples as complex64 ``(I - zero) + j (Q - zero)`` (complex formats only)."""
        if not self.sample_format.is_complex:
            raise ValueError(
                f"{self.path}: {self.sample_format.value} is a real envelope format, not complex I/Q"
            )
        return centred_iq(self._read(0, self.n_samples), self.sample_format)

    def _describe(self, kind: str) -> str:
        seconds = self.n_samples / self.sample_rate
        what = "I/Q, envelope |x - zero|^2" if self.sample_format.is_complex else "envelope"
        centre = "" if self.center_hz is None else f" at {self.center_hz / 1e6:g} MHz"
        lost = self.segments[-1].index - self.segments[-1].start
        dropouts = (f", {len(self.segments) - 1} dropout(s) losing {lost} samples" if lost else "")
        return (f"{kind} {os.path.basename(self.path)}: {self.sample_format.value} {what}, "
                f"{self.n_samples} samples at {self.sample_rate / 1e6:g} MS/s ({seconds:.3f} s){centre}{dropouts}, "
                f"scale {self.scale:.6g} per code")
