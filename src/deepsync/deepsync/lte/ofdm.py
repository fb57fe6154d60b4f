"""OFDM modulation with normal cyclic prefix, and its exact inverse.

Scaling is physical: a subcarrier with complex amplitude a contributes a * exp(j 2 pi f t), so
with REs in sqrt(W) the mean of |x|^2 is the total power (the IFFT uses ``norm="forward"``).
"""

from __future__ import annotations

import numpy as np
import scipy.fft

from deepsync.lte.numerology import SYMBOLS_PER_FRAME, Numerology


def subcarrier_bins(numerology: Numerology, shift: int = 0) -> np.ndarray:
    """FFT bin of each occupied subcarrier k, optionally shifted by ``shift`` bins."""
    return (numerology.subcarrier_offsets() + shift) % numerology.fft_size


def symbol_index_map(numerology: Numerology, first_sample_shift: int = 0) -> np.ndarray:
    """For each sample of a frame, the flat index (symbol * N + n) into the per-symbol IFFTs.

    Sample j of the frame belongs to the symbol whose span [start, start + CP + N) holds j and
    takes IFFT sample (j - start - CP + ``first_sample_shift``) mod N: the CP is the cyclic
    tail, and a shift of one reads the symbol one sample later, which is how a sub-sample
    delay keeps every symbol boundary exact (see ``deepsync.frontend.render``).
    """
    n = numerology.fft_size
    lengths = numerology.cp_lengths + n
    symbol = np.repeat(np.arange(SYMBOLS_PER_FRAME), lengths)
    within = np.arange(lengths.sum()) - np.repeat(numerology.symbol_starts, lengths)
    position = (within - np.repeat(numerology.cp_lengths, lengths) + first_sample_shift) % n
    return symbol * n + position


def modulate(grid: np.ndarray, numerology: Numerology) -> np.ndarray:
    """Time samples (with CPs) of a (140, K) frame grid at the numerology's sample rate."""
    if grid.shape != (SYMBOLS_PER_FRAME, numerology.n_subcarriers):
        raise ValueError(
            f"grid shape {grid.shape} != {(SYMBOLS_PER_FRAME, numerology.n_subcarriers)}"
        )
    bins = np.zeros((SYMBOLS_PER_FRAME, numerology.fft_size), dtype=np.complex128)
    bins[:, subcarrier_bins(numerology)] = grid
    symbols = scipy.fft.ifft(bins, axis=1, norm="forward")
    return symbols.reshape(-1)[symbol_index_map(numerology)]


def demodulate(samples: np.ndarray, numerology: Numerology) -> np.ndarray:
    """The (140, K) grid of one frame of time samples: drop each CP, FFT, pick subcarriers."""
    if samples.shape != (numerology.samples_per_frame,):
        raise ValueError(f"expected {numerology.samples_per_frame} samples, got {samples.shape}")
    starts = numerology.symbol_starts + numerology.cp_lengths
    useful = samples[starts[:, None] + np.arange(numerology.fft_size)[None, :]]
    return scipy.fft.fft(useful, axis=1, norm="forward")[:, subcarrier_bins(numerology)]
