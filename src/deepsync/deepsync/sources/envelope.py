"""From stored samples to the envelope ADC codes the sync stage reads: the one rule, stated so that
anyone can reproduce the codes of a recording from its bytes.

**Why |x|^2 of complex baseband is the envelope.** A carrier received as the passband signal
``s(t) = Re{x(t) exp(j 2 pi f_c t)}`` gives, after a square-law detector and the video
(low-pass) filter that removes the ``2 f_c`` term, ``s^2 -> |x(t)|^2 / 2``. An I/Q receiver
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

Squaring digitally has no video filter and no AC coupling after it (the radio's channel filter
acts *before* the square), so templates for such a stream come from :func:`squared_iq_frontend`.

**The rule.** For a complex format with components ``I, Q`` as stored and the format's zero
``z`` (127.5 for ``cu8``, 0 otherwise)::

    p     = (I - z)^2 + (Q - z)^2                       # |x - zero|^2, in float64
    code  = rint(p / scale)   as int16, adc_bits 16, volts_per_code = scale
    code  = 32767             where I or Q sits at a rail of an integer format
    code  = min(code, 32767)  (only reached with a given scale that is too small)

``rint`` rounds half to even (numpy's). The default ``scale`` is taken from the recording
itself, in one pass over it before streaming: the largest ``p`` among the samples with neither
component at a rail maps to code 32766, i.e. ``scale = peak / 32766`` (``scale = 1`` for a
recording whose peak is 0). The codes then use the whole int16 range whatever the format's
width, and a recording that uses the full 8-bit range fits (a fixed ``p / 0.5`` would not).

A sample clipped in the recording (a component at a rail: 0 or 255 for ``cu8``, -128 or 127
for ``ci8``, -32768 or 32767 for ``ci16_le``) says only that the signal was *at least* that
strong; it becomes code 32767, the int16 rail, so the sync stage flags clipping exactly as it
does for an envelope ADC driven past full scale. Code 32767 is reached by nothing else with the
default scale; a given ``scale`` small enough to push an unclipped sample past int16 saturates
it there too, which is what such an ADC would read.

For a real envelope format the value already is the envelope: ``code = rint(value / scale)``,
saturated to the int16 range; ``ri16_le`` values are ADC codes (default scale 1: codes pass
unchanged), and a value at an int16 rail stays at that rail whatever the scale (it was clipped
when recorded). ``rf32_le`` gets ``scale = peak |value| / 32766`` by default.

**A live stream** (a socket, a pipe, a receiver) cannot be read twice, so there is no pass to
find its peak: its default scale is the format's full scale, :func:`full_scale`, the largest
``p`` (or ``|value|``) an unclipped sample can take mapping to code 32766: ``cu8``
``2 * 126.5^2 / 32766`` (about 0.977), ``ci8`` ``2 * 127^2 / 32766``, ``ci16_le``
``2 * 32767^2 / 32766``, ``ri16_le`` 1 (codes pass unchanged); float formats take components
within +-1 as full scale (what SDR drivers deliver: ``cf32_le`` ``2 / 32766``, ``rf32_le``
``1 / 32766``). A given ``scale`` replaces it.

**Non-finite samples** (NaN or inf in a float recording) have no code: an int16 chunk cannot
carry them, and turning them into numbers would hide a broken recording from the stage, which
reports NaN as an event. A source raises ValueError naming the file and the sample index instead
(when it computes the default scale, before streaming; with a given scale, when the chunk that
holds the sample is read).
"""

from __future__ import annotations

import math

import numpy as np

from deepsync.frontend.config import FrontendConfig
from .formats import SampleFormat

CODE_PEAK = 32766  # the default scale maps a recording's largest unclipped sample here
CODE_RAIL = 32767  # int16 rail: clipped samples, read by the stage as an ADC at full scale
_CODE_LOW = -32768


class NonFiniteSample(ValueError):
    """A float sample is NaN or inf; ``index`` counts samples from the start of the block."""

    def __init__(self, index: int, value: object) -> None:
        super().__init__(f"sample {index} is not finite ({value})")
        self.index = index
        self.value = value


def check_scale(scale: float | None) -> float | None:
    """``scale`` (units of |x|^2, or of the value, per code), or ValueError unless finite and > 0."""
    if scale is None:
        return None
    try:
        value = float(scale)
    except (TypeError, ValueError):
        raise ValueError(f"scale {scale!r} must be a number > 0") from None
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"scale {scale!r} must be finite and > 0 (units of |x|^2 or of the value per code)")
    return value


def _split(values: np.ndarray, sample_format: SampleFormat) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(envelope p or value in float64, clipped mask, stored components (n, k)) of a block."""
    v = np.asarray(values)
    if v.ndim != 1 or v.size % sample_format.components:
        raise ValueError(
            f"{sample_format.value} values must be 1-D and hold {sample_format.components} "
            f"component(s) per sample, got shape {v.shape}"
        )
    comps = v.reshape(-1, sample_format.components)
    rails = sample_format.rails
    clipped = np.zeros(comps.shape[0], dtype=bool)
    if rails is not None:
        clipped = np.any((comps == rails[0]) | (comps == rails[1]), axis=1)
    x = comps.astype(np.float64)
    if sample_format.is_complex:
        x -= sample_format.zero
        envelope = x[:, 0] * x[:, 0] + x[:, 1] * x[:, 1]
    else:
        envelope = x[:, 0]
    if sample_format.component_dtype.kind == "f":
        bad = ~np.isfinite(envelope)
        if bad.any():
            first = int(np.argmax(bad))
            raise NonFiniteSample(first, tuple(comps[first].tolist()) if sample_format.is_complex else comps[first, 0])
    return envelope, clipped, comps


def block_peak(values: np.ndarray, sample_format: SampleFormat) -> float:
    """The largest envelope ``p`` (or ``|value|``) of a block among its unclipped samples (0 if
    none). Raises :class:`NonFiniteSample` for NaN or inf."""
    envelope, clipped, _ = _split(values, sample_format)
    kept = np.abs(envelope[~clipped])
    return float(kept.max()) if kept.size else 0.0


def scale_from_peak(peak: float) -> float:
    """The default scale: ``peak`` maps to code 32766; a recording with a zero peak gets 1."""
    return peak / CODE_PEAK if peak > 0 else 1.0


def full_scale(sample_format: SampleFormat | str) -> float:
    """The default scale of a live stream: the largest envelope an unclipped sample of the format
    can have maps to code 32766 (float formats: components within +-1)."""
    sample_format = SampleFormat.parse(sample_format)
    if sample_format is SampleFormat.RI16_LE:
        return 1.0  # the values are ADC codes already
    rails = sample_format.rails
    zero = sample_format.zero
    # the widest unclipped component: one step inside either rail
    widest = 1.0 if rails is None else max(rails[1] - 1 - zero, zero - (rails[0] + 1))
    peak = sample_format.components * widest * widest if sample_format.is_complex else widest
    return peak / CODE_PEAK


def envelope_codes(values: np.ndarray, sample_format: SampleFormat | str, scale: float) -> np.ndarray:
    """Int16 envelope codes of stored samples under the module's rule.

    ``values`` are the recording's numbers as stored, in file order (I0 Q0 I1 Q1 ... for complex
    formats), of any numeric dtype that holds them exactly. Raises :class:`NonFiniteSample` (a
    ValueError) for a NaN or inf sample, ValueError for a scale that is not finite and > 0.
    """
    sample_format = SampleFormat.parse(sample_format)
    scale = check_scale(scale)
    if scale is None:
        raise ValueError("scale must be given (a number > 0)")
    envelope, clipped, comps = _split(values, sample_format)
    with np.errstate(over="ignore"):  # a tiny given scale overflows to inf: the rail, as below
        codes = np.rint(envelope / scale)
    np.clip(codes, _CODE_LOW, CODE_RAIL, out=codes)  # an ADC driven past full scale reads its rail
    if sample_format.is_complex:
        codes[clipped] = CODE_RAIL
    elif sample_format.rails is not None:
        low, high = sample_format.rails
        codes[comps[:, 0] == high] = CODE_RAIL
        codes[comps[:, 0] == low] = _CODE_LOW
    return codes.astype(np.int16)


def squared_iq_frontend(sample_rate: float) -> FrontendConfig:
    """The front end equivalent to squaring an I/Q recording digitally: no video filter (the
    radio's channel filter acts before the square), no AC coupling, and an RF passband as wide
    as the sample rate: the radio saw only the middle of a wider carrier, so a cell's CRS
    template holds only the subcarriers there. Templates built with it match the envelope codes
    of such a recording at ``sample_rate``."""
    default = FrontendConfig.video_cutoff_hz
    # The cutoff is unused without a video filter, but FrontendConfig wants it below the rate.
    cutoff = default if default < sample_rate else sample_rate / 2
    return FrontendConfig(adc_rate_hz=sample_rate, video_filter_order=0, video_highpass_hz=0.0,
                          video_cutoff_hz=cutoff, rf_bandwidth_hz=sample_rate)
