"""Windows around a detected cell's sync code, one row per stacked frame.

Row f is the envelope of frame f from ``margin`` samples before the coarse code start to
``margin`` after the template's end (the paper's 286 = 276 + 5 + 5 with margin 5; the default
here is larger, to cover the coarse error the timing network is trained for). Rows are cut
circularly within their frame: the code pattern repeats every frame, so a code near a frame
edge is read whole. With a compensated receiver clock each frame starts a fraction of a sample
off the integer grid (``Stack.row_shifts``); that remainder is removed by a band-limited
(FFT) shift, so all rows put the code at the same place and average coherently. It is exact
for content below the ADC's Nyquist frequency; what the video filter lets alias (a few % of
the code's energy with the default filter) is shifted by the wrong amount.
"""

from __future__ import annotations

import numpy as np
import scipy.fft
import scipy.signal

from deepsync.sync.stacking import Stack

_PAD = 64  # samples either side, tapered, so the circular FFT shift does not wrap an edge


def extract_windows(stack: Stack, code_start: int, template_length: int, margin: int) -> np.ndarray:
    """(n_frames, template_length + 2 margin) rows around a code starting at ``code_start``
    samples into each frame (a detection's ``frame_offset``)."""
    if margin < 0 or 2 * margin + template_length > stack.frame_samples:
        raise ValueError(f"margin {margin} does not fit a {stack.frame_samples}-sample frame")
    length = template_length + 2 * margin
    first = code_start - margin
    if not np.any(stack.row_shifts):
        index = (first + np.arange(length)) % stack.frame_samples
        return stack.rows[:, index].astype(np.float32)
    index = (first - _PAD + np.arange(length + 2 * _PAD)) % stack.frame_samples
    padded = stack.rows[:, index].astype(np.float64)
    means = padded.mean(axis=1, keepdims=True)
    padded -= means
    padded *= scipy.signal.windows.tukey(padded.shape[1], 2 * (_PAD - 8) / padded.shape[1])[None, :]
    frequencies = scipy.fft.rfftfreq(padded.shape[1])
    # row f's true frame start is row_shifts[f] samples after its integer start: read it that
    # much later so every row sees the code at the same position
    ramp = np.exp(2j * np.pi * frequencies[None, :] * stack.row_shifts[:, None])
    shifted = scipy.fft.irfft(scipy.fft.rfft(padded, axis=1) * ramp, n=padded.shape[1], axis=1)
    return (shifted[:, _PAD : _PAD + length] + means).astype(np.float32)
