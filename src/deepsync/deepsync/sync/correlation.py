"""Circular cross-correlation of a stacked frame with many templates, by FFT, in float32.

The timing search correlates one frame with dozens of templates at every lag, several times
per stack; the cost is memory traffic, so spectra and results are single precision (relative
error ~1e-7, far below any noise the z-scores are made of), which runs several times faster
than double precision on this project's machines.
"""

from __future__ import annotations

import numpy as np
import scipy.fft


def unit_frame_parts(parts: np.ndarray) -> np.ndarray:
    """Zero-mean each code (last axis) and scale each (..., 2, L) subframe-0/subframe-5 pair to
    unit norm: the two codes of a frame template, as the timing correlation uses them."""
    centred = parts - parts.mean(axis=-1, keepdims=True)
    return centred / np.linalg.norm(centred, axis=(-2, -1), keepdims=True)


def frame_code_windows(signal: np.ndarray, starts: np.ndarray, length: int) -> np.ndarray:
    """(len(starts), 2, length) what a frame template's two codes (``unit_frame_parts``) meet
    placed at each of ``starts``: the circular frame ``signal`` from each start and half a frame
    later. Their dot products with the parts are the timing correlation at those lags."""
    index = np.asarray(starts)[:, None, None] + np.array([0, len(signal) // 2])[None, :, None] + np.arange(length)
    return signal[index % len(signal)]


def parseval_weights(n: int) -> np.ndarray:
    """(n // 2 + 1,) weights w with sum_j x[j] y[j] = sum_k w_k Re(X_k conj(Y_k)) for real
    n-sample x and y and their rffts X and Y: each bin stands for itself and its negative-frequency
    twin, except DC and (n even) Nyquist; over n."""
    weights = np.full(n // 2 + 1, 2.0 / n)
    weights[0] = 1.0 / n
    if n % 2 == 0:
        weights[-1] = 1.0 / n
    return weights


def template_spectra(templates: np.ndarray, n: int) -> np.ndarray:
    """Conjugate spectra (complex64) of (..., L) templates starting at lag 0 of an n-periodic signal."""
    padded = np.zeros((*templates.shape[:-1], n))
    padded[..., : templates.shape[-1]] = templates
    return np.conj(scipy.fft.rfft(padded, axis=-1)).astype(np.complex64)


def frame_spectra(parts: np.ndarray, frame: int) -> np.ndarray:
    """Conjugate spectra (complex64) of frame templates from (..., 2, L) code parts: subframe
    0's code at 0, subframe 5's half a frame later."""
    templates = np.zeros((*parts.shape[:-2], frame))
    length = parts.shape[-1]
    templates[..., :length] = parts[..., 0, :]
    templates[..., frame // 2 : frame // 2 + length] = parts[..., 1, :]
    return template_spectra(templates, frame)


def correlate(spectrum: np.ndarray, spectra: np.ndarray, n: int) -> np.ndarray:
    """(..., n) float32 circular correlations at every lag, from a signal's rfft and templates'
    conjugate spectra."""
    return scipy.fft.irfft(spectrum.astype(np.complex64) * spectra, n=n, axis=-1)


def correlate_every(spectrum: np.ndarray, spectra: np.ndarray, n: int, step: int) -> np.ndarray:
    """``correlate(spectrum, spectra, n)[..., ::step]``, without the lags between: sampling the
    correlation every ``step`` lags folds its spectrum onto n / step bins (aliasing), so one
    transform of that length replaces the n-point one (about 2.5 times cheaper at step 32 of a
    frame). For a noise statistic that needs a sample of lags, not all of them."""
    if step == 1 or n % step:
        return correlate(spectrum, spectra, n)[..., ::step]
    product = spectrum.astype(np.complex64) * spectra
    # the whole spectrum of the real correlation: bins above n / 2 are the conjugates of those below
    whole = np.concatenate([product, np.conj(product[..., (n - 1) // 2 : 0 : -1])], axis=-1)
    folded = whole.reshape(*whole.shape[:-1], step, n // step).sum(axis=-2)
    return scipy.fft.irfft(folded[..., : n // step // 2 + 1], n // step, axis=-1) / np.float32(step)
