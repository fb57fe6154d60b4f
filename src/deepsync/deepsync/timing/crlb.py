"""Cramér-Rao bound on the sub-sample delay of a known sync template in coloured noise.

Model (one stacked window of L samples; n is the sample index, L the window length):

    x[n] = A * s(n - tau) + b + e[n]

with ``s`` the ADC-domain template (``SyncTemplates.template``), ``A`` its amplitude, ``b`` a DC
pedestal (unknown, dropped with the DC bin) and ``e`` stationary zero-mean Gaussian noise of
two-sided power spectral density P(f). The bound on ``tau`` comes from the Whittle
(frequency-domain) Fisher information: the DFT bins E_k of the noise are treated as
independent complex Gaussians with E|E_k|^2 = L P_k, so for a real signal

    I(tau) = sum_{k=1}^{ceil(L/2)-1} 2 (2 pi k / L)^2 A^2 |T_k|^2 / (L P_k),

T = DFT of the template zero-padded to L, and var(tau_hat) >= 1 / I. The DC bin (pedestal) and
the Nyquist bin (no phase information about a delay) are left out.

Units and normalisation: ``P_k`` is a PSD *per sample*, i.e. variance per unit of normalised
frequency (cycles per sample): white noise of variance sigma^2 has P_k = sigma^2 in every bin.
A PSD in V^2/Hz (two-sided) times the sample rate is in these units. Check (``test_crlb``):
for white noise the bound equals the time-domain form sigma^2 / (A^2 sum_n s'[n]^2), with s' the
band-limited derivative of the template, because sum_n s'[n]^2 = (1/L) sum_k (2 pi k/L)^2 |T_k|^2.

Stacking n frames averages the noise of n frames: the stacked window carries P_k / n (frame-to-
frame independent interference, as for LTE data re-drawn every 10 ms), which is how
``n_frames`` enters.

Assumptions (all of them matter at some level):

* Gaussian noise. The interference of an envelope detector is data self-mixing, heavier-tailed
  than Gaussian (excess kurtosis ~1 per frame for a loaded 10 MHz cell); the average over n
  frames is closer to Gaussian, and the bound is the Gaussian one for the measured spectrum.
* Stationary within the window, and the Whittle approximation (DFT bins independent): exact
  for circular noise, a good approximation for a smooth spectrum over a ~300-sample window.
* Amplitude known. With ``A`` unknown (and the pedestal unknown: it only touches the DC bin),
  the bound is the same: the Whittle cross-information of (tau, A) is
  sum_k 2 Re(-j w_k A |T_k|^2) / (L P_k) = 0, identically (each term is imaginary); in the
  time domain it is A sum_n s[n] s'[n] / sigma^2, zero to first order for a template that lies
  inside the window (the sum is a boundary term).
* The template is exactly the band-limited signal. A sampled template of an aliased envelope
  (the default 0.9 MHz 4th-order video filter leaves ~-31 dB of the code's energy above 0.96
  MHz) is not: its fractional shifts differ slightly from its band-limited interpolation, a
  deterministic error of ~0.001 (median over PCIs) to 0.02 (worst PCI) samples that no noise
  bound accounts for.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from deepsync.lte.numerology import BASE_RATE_HZ
from deepsync.types import SPEED_OF_LIGHT_M_S



@dataclass(frozen=True)
class Bound:
    """1-sigma lower bound on a delay estimate."""

    std_samples: float
    std_metres: float


def check_template(template: np.ndarray, min_length: int = 4) -> np.ndarray:
    """A template as float64, or ValueError: 1-D, finite, not constant (else it has no timing)."""
    try:
        t = np.asarray(template, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"template must be a numeric array: {error}") from None
    if t.ndim != 1 or t.size < min_length:
        raise ValueError(f"template must be a 1-D array of at least {min_length} samples, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("template contains NaN or inf")
    if not t.max() > t.min():  # (t - t.mean() could be a rounding error away from zero)
        raise ValueError("template is constant: it carries no timing information")
    return t


def psd_bins(noise_psd: float | np.ndarray, window_length: int) -> np.ndarray:
    """Validated PSD at the ``window_length // 2 + 1`` rfft bins (a scalar means white noise)."""
    n_bins = window_length // 2 + 1
    psd = np.asarray(noise_psd, dtype=np.float64)
    if psd.ndim == 0:
        psd = np.full(n_bins, float(psd))
    if psd.shape != (n_bins,):
        raise ValueError(
            f"noise_psd must be a scalar or have {n_bins} rfft bins for a window of {window_length} "
            f"samples, got shape {psd.shape}"
        )
    if not np.all(np.isfinite(psd)):
        raise ValueError("noise_psd contains NaN or inf")
    if np.any(psd[1 : (window_length + 1) // 2] <= 0):
        raise ValueError("noise_psd must be > 0 in every bin between DC and Nyquist")
    return psd


def _resolve_length(template: np.ndarray, noise_psd: float | np.ndarray, window_length: int | None) -> int:
    if window_length is None:
        psd = np.asarray(noise_psd)
        window_length = len(template) if psd.ndim == 0 else 2 * (psd.size - 1)
    window_length = int(window_length)
    if window_length < len(template):
        raise ValueError(f"window_length ({window_length}) is shorter than the template ({len(template)})")
    return window_length


def fisher_information(
    template: np.ndarray,
    amplitude: float,
    noise_psd: float | np.ndarray,
    n_frames: int = 1,
    window_length: int | None = None,
    template_spectrum: np.ndarray | None = None,
) -> float:
    """Whittle Fisher information of the delay (1 / samples^2); see the module docstring.

    ``noise_psd``: per-frame two-sided PSD per sample, a scalar (white, = variance) or the
    ``window_length // 2 + 1`` rfft bins of the window (``window_length`` defaults to
    ``2 * (len(noise_psd) - 1)``, or to the template length for a scalar).
    ``template_spectrum``: the template's rfft at ``window_length``, if the caller keeps it.
    """
    t = check_template(template)
    if not (math.isfinite(amplitude)):
        raise ValueError(f"amplitude must be finite, got {amplitude!r}")
    if int(n_frames) != n_frames or n_frames < 1:
        raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
    length = _resolve_length(t, noise_psd, window_length)
    psd = psd_bins(noise_psd, length) / n_frames
    if template_spectrum is None:
        spectrum = np.fft.rfft(t, length)
    elif np.shape(template_spectrum) == (length // 2 + 1,):
        spectrum = np.asarray(template_spectrum)
    else:
        raise ValueError(f"template_spectrum ({np.shape(template_spectrum)}) is not the rfft of a "
                         f"{length}-sample window")
    k = slice(1, (length + 1) // 2)
    return fisher_information_bins(amplitude, np.abs(spectrum[k]) ** 2, psd[k], length)


def fisher_information_bins(amplitude: float, power: np.ndarray, psd: np.ndarray, length: int) -> float:
    """The Whittle sum of :func:`fisher_information` itself, unchecked, for a caller that holds
    its terms at the bins between DC and Nyquist (k = 1 .. ceil(L/2) - 1): ``power`` = |T_k|^2,
    ``psd`` the stacked noise PSD there, ``length`` = L."""
    return float(np.sum(2 * bin_omega(length) ** 2 * amplitude**2 * power / (length * psd)))


@lru_cache(maxsize=32)
def bin_omega(length: int) -> np.ndarray:
    """Angular frequencies (radians per sample) of a ``length``-point rfft's bins strictly between
    DC and Nyquist (k = 1 .. ceil(L/2) - 1), where the delay information lives; read-only."""
    omega = 2 * np.pi * np.arange(1, (length + 1) // 2) / length
    omega.flags.writeable = False
    return omega


def std_from_fisher(info: float) -> float:
    """The 1-sigma bound (samples) of a Fisher information (1 / samples^2); inf where it is none."""
    return math.inf if info <= 0 else 1 / math.sqrt(info)


def delay_crlb(
    template: np.ndarray,
    amplitude: float,
    noise_psd: float | np.ndarray,
    n_frames: int = 1,
    sample_rate: float = BASE_RATE_HZ,
    window_length: int | None = None,
    template_spectrum: np.ndarray | None = None,
) -> Bound:
    """CRLB of the delay of ``amplitude * template(t - tau)`` in Gaussian noise of ``noise_psd``.

    ``noise_psd`` is the per-frame PSD (see :func:`fisher_information`); the stacked window of
    ``n_frames`` frames carries ``noise_psd / n_frames``. Returns the 1-sigma bound in samples
    and in metres (``c / sample_rate`` per sample: 156 m at 1.92 MHz).
    """
    if not (math.isfinite(sample_rate) and sample_rate > 0):
        raise ValueError(f"sample_rate must be a positive number, got {sample_rate!r}")
    info = fisher_information(template, amplitude, noise_psd, n_frames, window_length, template_spectrum)
    std = std_from_fisher(info)
    return Bound(std, std * SPEED_OF_LIGHT_M_S / sample_rate)


def delay_crlb_white(
    derivative: np.ndarray,
    amplitude: float,
    sigma: float,
    n_frames: int = 1,
    sample_rate: float = BASE_RATE_HZ,
) -> Bound:
    """Time-domain bound for white noise: var >= sigma^2 / (n_frames A^2 sum_n s'[n]^2).

    ``derivative`` is ds/dt of the template in 1/sample units at the sample instants (e.g. a
    central difference of ``SyncTemplates.template`` at small +- delays), ``sigma`` the per-frame
    noise standard deviation per sample.
    """
    d = np.asarray(derivative, dtype=np.float64)
    if d.ndim != 1 or not np.all(np.isfinite(d)):
        raise ValueError("derivative must be a finite 1-D array")
    if not (sigma > 0 and math.isfinite(sigma)):
        raise ValueError(f"sigma must be a positive number, got {sigma!r}")
    info = n_frames * amplitude**2 * float(np.sum(d**2)) / sigma**2
    std = std_from_fisher(info)
    return Bound(std, std * SPEED_OF_LIGHT_M_S / sample_rate)


def fit_amplitude(
    window: np.ndarray,
    template: np.ndarray,
    margin: int,
    offset: float,
    noise_psd: float | np.ndarray | None = None,
) -> float:
    """Least-squares amplitude of the template at ``margin + offset`` in a (stacked) window.

    Fitted in the frequency domain over the bins between DC and Nyquist, so the pedestal drops
    out and the fractional shift is the template's band-limited one; with ``noise_psd`` (rfft
    bins of the window) the fit is weighted by 1 / P (generalised least squares).
    """
    x = np.asarray(window, dtype=np.float64)
    t = check_template(template)
    if x.ndim != 1 or not np.all(np.isfinite(x)):
        raise ValueError("window must be a finite 1-D array")
    if len(x) < len(t):
        raise ValueError(f"window ({len(x)}) is shorter than the template ({len(t)})")
    length = len(x)
    k = np.arange(1, (length + 1) // 2)
    weights = np.ones(k.size) if noise_psd is None else 1 / psd_bins(noise_psd, length)[k]
    wx = np.fft.rfft(x - x.mean())[k]
    tk = np.fft.rfft(t, length)[k]
    shift = np.exp(-2j * np.pi * k * (margin + offset) / length)
    return float(np.sum(np.real(wx * np.conj(tk * shift)) * weights) / np.sum(np.abs(tk) ** 2 * weights))


def snr_db(amplitude: float, template: np.ndarray, noise_variance: float) -> float:
    """SNR of ``amplitude * template`` over its own length against noise of ``noise_variance``.

    Same definition as ``docs/results/sync_snr.json``: energy of the mean-removed expected code
    over the template length, divided by the noise energy over the same samples.
    """
    t = check_template(template)
    signal = amplitude**2 * float(np.sum((t - t.mean()) ** 2))
    noise = noise_variance * len(t)
    if noise <= 0:
        return math.inf
    return 10 * math.log10(signal / noise) if signal > 0 else -math.inf
