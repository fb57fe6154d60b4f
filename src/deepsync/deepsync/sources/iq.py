"""Complex baseband (I/Q) recordings, and the envelope stream a square-law detector makes of them.

Why ``|x|^2`` of complex baseband *is* the envelope: a carrier received as the passband signal
``s(t) = Re{x(t) exp(j 2 pi f_c t)}`` gives, after a square-law detector and the video
(low-pass) filter that removes the ``2 f_c`` term, ``s^2 -> |x(t)|^2 / 2``. The I/Q receiver
mixes with its own local oscillator, which is off by ``df`` (crystal error: tens of ppm for an
RTL-SDR) and has some phase ``phi(t)``, so what it records is
``x(t) exp(j (2 pi df t + phi(t)))``. That factor has unit modulus, so ``|x|^2`` does not depend
on it: the carrier frequency offset and the LO phase noise vanish, exactly as they do for a
detector that has no oscillator at all. What does *not* vanish:

* the receiver's sample clock error (on an RTL-SDR the same crystal drives LO and ADC, so an
  LO error of ``e`` ppm comes with frames that last ``19200 (1 + e 1e-6)`` samples); and
* the receiver's bandwidth: an I/Q recording at 1.92 Msps holds only the central ~1.9 MHz of
  the carrier, whereas a wideband envelope detector squares the whole carrier (all subcarriers,
  and other carriers within its RF filter). ``|x|^2`` is therefore the envelope of a
  1.92 MHz-wide slice: a single carrier as seen through a narrow RF filter.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import numpy as np

from deepsync.types import EnvelopeChunk
from deepsync.frontend.config import FrontendConfig

RTLSDR_ZERO = 127.5
ENVELOPE_VOLTS_PER_CODE = 2.0
_INT16_MAX = np.iinfo(np.int16).max


def load_rtlsdr_u8(path: str | os.PathLike) -> np.ndarray:
    """Read an RTL-SDR capture: unsigned 8-bit interleaved I/Q (I0 Q0 I1 Q1 ...), no header.

    Returns complex64 samples ``(I - 127.5) + j (Q - 127.5)`` (the unsigned bytes' zero is
    127.5, so every sample has both rails at half-odd-integer values). Raises ``ValueError``
    naming the path when the file is missing or holds an odd number of bytes (a truncated
    capture or not an I/Q file).
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"RTL-SDR capture {path!r} does not exist or is not a file")
    raw = np.fromfile(path, dtype=np.uint8)
    if raw.size % 2:
        raise ValueError(
            f"RTL-SDR capture {path!r} has {raw.size} bytes, an odd count: interleaved 8-bit "
            "I/Q needs two bytes per sample (truncated file, or not an RTL-SDR capture?)"
        )
    samples = np.empty(raw.size // 2, dtype=np.complex64)
    samples.real = raw[0::2].astype(np.float32) - np.float32(RTLSDR_ZERO)
    samples.imag = raw[1::2].astype(np.float32) - np.float32(RTLSDR_ZERO)
    return samples


def envelope_codes(iq: np.ndarray, volts_per_code: float = ENVELOPE_VOLTS_PER_CODE) -> np.ndarray:
    """``round(|x|^2 / volts_per_code)`` as int16 codes (the envelope in arbitrary units).

    With the default 2.0, 8-bit I/Q (``|x|^2 <= 2 * 127.5^2``) gives codes <= 16256. Raises
    ``ValueError`` if a code would not fit int16 (pick a larger ``volts_per_code``).
    """
    if not (np.isfinite(volts_per_code) and volts_per_code > 0):
        raise ValueError(f"volts_per_code {volts_per_code!r} must be > 0")
    x = np.asarray(iq)
    power = x.real.astype(np.float64) ** 2 + x.imag.astype(np.float64) ** 2
    codes = np.rint(power / volts_per_code)
    if codes.size and codes.max() > _INT16_MAX:
        raise ValueError(
            f"|x|^2 / {volts_per_code:g} reaches {codes.max():.0f}, beyond int16 "
            f"({_INT16_MAX}); scale the I/Q down or raise volts_per_code"
        )
    return codes.astype(np.int16)


def envelope_chunks(
    iq: np.ndarray,
    sample_rate: float,
    chunk_samples: int = 19200,
    stamp_ns: int = 0,
    volts_per_code: float = ENVELOPE_VOLTS_PER_CODE,
) -> Iterator[EnvelopeChunk]:
    """The envelope an ideal square-law detector would output for this single carrier.

    Yields :class:`EnvelopeChunk` s of ``chunk_samples`` int16 codes (the last one may be
    shorter), ``codes = round(|x|^2 / volts_per_code)`` (``volts_per_code`` 2.0 by default,
    arbitrary units), ``adc_bits`` 16, ``first_sample_index`` contiguous from 0 and
    ``stamp_ns`` advancing with the nominal sample rate. See the module docstring for why
    ``|x|^2`` is the envelope (the carrier frequency offset vanishes) and what it leaves out.
    """
    if not (np.isfinite(sample_rate) and sample_rate > 0):
        raise ValueError(f"sample_rate {sample_rate!r} must be > 0")
    if int(chunk_samples) != chunk_samples or chunk_samples < 1:
        raise ValueError(f"chunk_samples {chunk_samples!r} must be a positive integer")
    chunk_samples = int(chunk_samples)
    x = np.asarray(iq)
    if x.ndim != 1:
        raise ValueError(f"iq must be 1-D, got shape {x.shape}")
    for first in range(0, x.size, chunk_samples):
        yield EnvelopeChunk(
            stamp_ns=int(stamp_ns) + int(round(first * 1e9 / sample_rate)),
            sample_rate=float(sample_rate),
            first_sample_index=first,
            adc_bits=16,
            volts_per_code=float(volts_per_code),
            samples=envelope_codes(x[first : first + chunk_samples], volts_per_code),
        )


def recording_frontend(sample_rate: float = 1.92e6) -> FrontendConfig:
    """The front end equivalent to squaring an I/Q recording digitally: no video filter (the
    radio's channel filter acts before the square) and no AC coupling. Templates built with it
    match ``envelope_chunks`` of such a recording."""
    return FrontendConfig(adc_rate_hz=sample_rate, video_filter_order=0, video_highpass_hz=0.0)
