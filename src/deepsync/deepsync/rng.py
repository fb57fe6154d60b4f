"""Reproducible random streams addressed by index.

Every random draw in the simulator belongs to a (purpose, index) pair: frame k of a cell,
noise of block b, ADC noise of block b. Seeding each from ``(seed, purpose, index)`` makes
any piece regenerable on its own, so chunks computed in parallel, in any order, give the
same numbers as one sequential run.
"""

from __future__ import annotations

import numpy as np

FRAME_CONTENT = 0xF4A3E
DETECTOR_NOISE = 0xD17E
ADC_NOISE = 0xADC


def indexed_rng(seed: int, purpose: int, index: int) -> np.random.Generator:
    """Generator for draw ``index`` (any integer, negative too) of stream ``purpose``."""
    return np.random.default_rng([int(seed), purpose, int(index) & 0xFFFFFFFFFFFFFFFF])
