"""Where things sit in the downlink resource grid of one 10 ms FDD frame (normal CP).

A frame grid is a (140 symbols, K subcarriers) array indexed by the standard's subcarrier k
(0..K-1, DC not counted) and the frame's symbol index 7*slot + l.
"""

from __future__ import annotations

import numpy as np

from deepsync.lte.numerology import SYMBOLS_PER_SLOT, Numerology
from deepsync.lte.sequences import SYNC_LENGTH

SYNC_SLOTS = (0, 10)  # slots carrying PSS/SSS in FDD: subframes 0 and 5
PSS_SYMBOL_IN_SLOT = SYMBOLS_PER_SLOT - 1
SSS_SYMBOL_IN_SLOT = SYMBOLS_PER_SLOT - 2
CRS_SYMBOLS_IN_SLOT = (0, SYMBOLS_PER_SLOT - 3)  # antenna port 0: l = 0 and l = N_symb - 3
PBCH_SLOT = 1
PBCH_SYMBOLS_IN_SLOT = (0, 1, 2, 3)
CENTRAL_SUBCARRIERS = 72  # the 6 central RBs' worth carrying PSS/SSS (+ 5 reserved each side) and PBCH


def frame_symbol(slot: int, symbol: int) -> int:
    return slot * SYMBOLS_PER_SLOT + symbol


def sync_subcarriers(numerology: Numerology) -> np.ndarray:
    """k of PSS/SSS element n = 0..61: k = n - 31 + K/2 (§6.11.1.2), straddling DC."""
    return np.arange(SYNC_LENGTH) - 31 + numerology.n_subcarriers // 2


def central_subcarriers(numerology: Numerology) -> np.ndarray:
    """k of the 72 central subcarriers (sync codes with their reserved guards, PBCH)."""
    return np.arange(CENTRAL_SUBCARRIERS) - 36 + numerology.n_subcarriers // 2


def crs_positions(numerology: Numerology, n_cell_id: int, symbol_in_slot: int) -> np.ndarray:
    """k of port-0 CRS in an OFDM symbol that carries it: k = 6m + (v + v_shift) mod 6."""
    v = 0 if symbol_in_slot == 0 else 3
    m = np.arange(2 * numerology.n_rb)
    return 6 * m + (v + n_cell_id % 6) % 6


def pbch_reserved(numerology: Numerology, n_cell_id: int, symbol_in_slot: int) -> np.ndarray:
    """Central subcarriers PBCH leaves free for CRS of up to four ports (§6.6.4).

    In symbols 0 and 1 of slot 1, PBCH assumes four CRS ports whatever is configured, so every
    third subcarrier (k mod 3 = v_shift mod 3) is left out; symbols 2 and 3 reserve nothing.
    """
    if symbol_in_slot not in (0, 1):
        return np.empty(0, dtype=np.int64)
    central = central_subcarriers(numerology)
    return central[central % 3 == (n_cell_id % 6) % 3]
