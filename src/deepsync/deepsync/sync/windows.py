"""Windows around a detected cell's sync code, one row per stacked frame.

Row f is the envelope of frame f from ``margin`` samples before the coarse code start to
``margin`` after the template's end (the paper's 286 = 276 + 5 + 5 with margin 5; the default
here is larger, to cover the coarse error the timing network is trained for). Rows are cut
circularly within their frame: the code pattern repeats every frame, so a code near a frame
edge is read whole. With a compensated receiver clock each frame starts a fraction of a sample
off the integer grid (``Stack.row_shifts``); what each row's remainder differs from row 0's is
removed by a band-limited (FFT) shift, so all rows put the code where row 0 has it, on row 0's
sample grid (the stream indices the stack's positions count in), and average coherently. It is exact
for content below the ADC's Nyquist frequency; what the video filter lets alias (a few % of
the code's energy with the default filter) is shifted by the wrong amount.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import numpy as np
import scipy.fft
import scipy.signal

from deepsync.sync.stacking import Stack

_PAD = 64  # samples either side, tapered, so the circular FFT shift does not wrap an edge


def extract_windows(stack: Stack, code_start: int, template_length: int, margin: int) -> np.ndarray:
    """(n_frames, template_length + 2 margin) rows around a code starting at ``code_start``
    samples into each frame (a detection's ``frame_offset``)."""
    return extract_windows_at(stack, [code_start], template_length, margin)[0]


def extract_windows_at(stack: Stack, code_starts: Sequence[int], template_length: int, margin: int) -> np.ndarray:
    """(len(code_starts), n_frames, template_length + 2 margin): ``extract_windows`` for several
    code starts at once (a stack's cells: one gather and one pair of transforms for all)."""
    if margin < 0 or 2 * margin + template_length > stack.frame_samples:
        raise ValueError(f"margin {margin} does not fit a {stack.frame_samples}-sample frame")
    length = template_length + 2 * margin
    first = np.asarray(code_starts, dtype=int) - margin
    shifts = stack.row_shifts - stack.row_shifts[0]
    whole = np.round(shifts).astype(int)  # read by indexing; the remainder by a band-limited shift
    shifts = shifts - whole
    pad = _PAD if np.any(shifts) else 0
    span = length + 2 * pad
    index = (first[None, :, None] + whole[:, None, None] - pad + np.arange(span)) % stack.frame_samples
    rows = stack.columns(index.reshape(len(whole), -1)).reshape(len(whole), len(first), span)
    rows = np.ascontiguousarray(rows.transpose(1, 0, 2))  # (code starts, frames, span)
    if not pad:
        return rows.astype(np.float32)
    padded = rows.astype(np.float64)
    means = padded.mean(axis=2, keepdims=True)
    padded -= means
    padded *= _taper(span)
    frequencies = scipy.fft.rfftfreq(span)
    # row f's true frame start is row_shifts[f] samples after its integer start: read it as
    # much later than row 0 is read, so every row sees the code where row 0 does
    ramp = np.exp(2j * np.pi * frequencies[None, :] * shifts[:, None])
    shifted = scipy.fft.irfft(scipy.fft.rfft(padded, axis=2) * ramp, n=span, axis=2)
    return (shifted[:, :, _PAD : _PAD + length] + means).astype(np.float32)


@lru_cache(maxsize=8)
def _taper(length: int) -> np.ndarray:
    """The rows' taper: flat but for ``_PAD - 8`` samples at either end (the same every stack)."""
    taper = scipy.signal.windows.tukey(length, 2 * (_PAD - 8) / length)
    taper.flags.writeable = False
    return taper
