"""Full 10 ms downlink frames of one cell: sync codes, CRS, PBCH, control region and PDSCH.

The deterministic part (PSS, SSS, CRS) is the same in every frame and computed once; the
random part (PBCH payload, control channels, scheduled PDSCH with its modulation) is drawn
per frame from ``(seed, frame_index)``, so any frame can be regenerated on its own, which is
what lets long recordings be produced in parallel chunks and reproduced bit for bit.
"""

from __future__ import annotations

import numpy as np

from deepsync.lte import grid as G
from deepsync.lte.cell import CellConfig, split_pci
from deepsync.lte.numerology import (
    SLOTS_PER_FRAME,
    SUBCARRIERS_PER_RB,
    SUBFRAMES_PER_FRAME,
    SYMBOLS_PER_FRAME,
    SYMBOLS_PER_SLOT,
    Numerology,
)
from deepsync.lte.sequences import crs, pss, sss
from deepsync.rng import FRAME_CONTENT, indexed_rng

SYMBOLS_PER_SUBFRAME = 2 * SYMBOLS_PER_SLOT

# All points of QPSK, 16QAM and 64QAM (TS 36.211 §7.1, unit average power), 64 entries per
# modulation so that one uniform 6-bit draw picks a point: 3 bits per I/Q rail, of which QPSK
# uses 1 and 16QAM 2. Equiprobable bits give equiprobable points, as scrambled data does.
_RAIL = np.arange(64)
_CONSTELLATIONS = np.concatenate(
    [
        ((2 * (_RAIL >> 3 & 1) - 1) + 1j * (2 * (_RAIL & 1) - 1)) / np.sqrt(2),
        ((2 * (_RAIL >> 3 & 3) - 3) + 1j * (2 * (_RAIL & 3) - 3)) / np.sqrt(10),
        ((2 * (_RAIL >> 3) - 7) + 1j * (2 * (_RAIL & 7) - 7)) / np.sqrt(42),
        np.zeros(64),  # entries 192 and on: an unused resource element
    ]
).astype(np.complex64)
_UNUSED = 192
_DOUBLE = 2.0**-53  # Generator.random: the top 53 bits of a 64-bit draw, as a fraction


class FrameGenerator:
    """Resource grids of successive frames of one cell.

    ``grid(frame_index)`` returns a (140, K) complex64 array; every resource element carries
    unit average power (all channels at the same EPRE), so the cell's total power is the
    number of occupied REs times the per-RE power the caller applies.
    """

    def __init__(self, cell: CellConfig, seed: int) -> None:
        self.cell = cell
        self.seed = int(seed)
        self.numerology = Numerology.for_bandwidth(cell.bandwidth_mhz)
        self._fixed, reserved = self._fixed_signals()
        self._pbch = self._pbch_mask(reserved)
        self._control = self._control_mask(reserved)
        self._pdsch = ~(reserved | self._pbch | self._control) & self._data_symbols()[:, None]
        self._modulation_cdf = np.cumsum(cell.modulation_weights)[:-1]
        self._control_rows = self._control.any(axis=1)
        self._pbch_symbols = np.flatnonzero(self._pbch.any(axis=1))
        self._reserved_at = np.flatnonzero(reserved)
        self._reserved_values = self._fixed.reshape(-1)[self._reserved_at]

    @property
    def shape(self) -> tuple[int, int]:
        return SYMBOLS_PER_FRAME, self.numerology.n_subcarriers

    @property
    def deterministic_grid(self) -> np.ndarray:
        """(140, K) PSS, SSS and CRS: what the cell sends the same in every frame (a copy)."""
        return self._fixed.copy()

    def _fixed_signals(self) -> tuple[np.ndarray, np.ndarray]:
        """PSS/SSS/CRS grid, and the mask of REs no other channel may use."""
        num = self.numerology
        n_id_1, n_id_2 = split_pci(self.cell.pci)
        fixed = np.zeros(self.shape, dtype=np.complex64)
        reserved = np.zeros(self.shape, dtype=bool)
        sync_k = G.sync_subcarriers(num)
        central = G.central_subcarriers(num)
        for slot, subframe in zip(G.SYNC_SLOTS, (0, 5)):
            pss_l = G.frame_symbol(slot, G.PSS_SYMBOL_IN_SLOT)
            sss_l = G.frame_symbol(slot, G.SSS_SYMBOL_IN_SLOT)
            fixed[pss_l, sync_k] = pss(n_id_2)
            fixed[sss_l, sync_k] = sss(n_id_1, n_id_2, subframe)
            reserved[pss_l, central] = True  # the 5 guard subcarriers each side stay empty
            reserved[sss_l, central] = True
        offset = 110 - num.n_rb  # m' = m + N_RB^max - N_RB
        for slot in range(SLOTS_PER_FRAME):
            for l in G.CRS_SYMBOLS_IN_SLOT:
                k = G.crs_positions(num, self.cell.pci, l)
                values = crs(self.cell.pci, slot, l)[offset : offset + 2 * num.n_rb]
                fixed[G.frame_symbol(slot, l), k] = values
                reserved[G.frame_symbol(slot, l), k] = True
        for l in G.PBCH_SYMBOLS_IN_SLOT:
            reserved[G.frame_symbol(G.PBCH_SLOT, l), G.pbch_reserved(num, self.cell.pci, l)] = True
        return fixed, reserved

    def _pbch_mask(self, reserved: np.ndarray) -> np.ndarray:
        mask = np.zeros(self.shape, dtype=bool)
        central = G.central_subcarriers(self.numerology)
        for l in G.PBCH_SYMBOLS_IN_SLOT:
            mask[G.frame_symbol(G.PBCH_SLOT, l), central] = True
        return mask & ~reserved

    def _control_mask(self, reserved: np.ndarray) -> np.ndarray:
        in_control = (np.arange(SYMBOLS_PER_FRAME) % SYMBOLS_PER_SUBFRAME) < self.cell.cfi
        return in_control[:, None] & ~reserved

    def _data_symbols(self) -> np.ndarray:
        return (np.arange(SYMBOLS_PER_FRAME) % SYMBOLS_PER_SUBFRAME) >= self.cell.cfi

    def rng(self, frame_index: int) -> np.random.Generator:
        return indexed_rng(self.seed, FRAME_CONTENT, frame_index)

    def grid(self, frame_index: int) -> np.ndarray:
        """The (140, K) resource grid of frame ``frame_index`` (any integer)."""
        n_rb = self.numerology.n_rb
        n_scheduled = int(round(self.cell.load * n_rb))
        per_subframe = SUBFRAMES_PER_FRAME * n_rb
        n_doubles = 2 * per_subframe + SYMBOLS_PER_FRAME * n_rb
        size = SYMBOLS_PER_FRAME * self.numerology.n_subcarriers
        # The frame's randomness in one draw, taken as Generator.random (doubles) and then
        # Generator.bytes would take it from the same stream: a third of their calls' cost.
        raw = self.rng(frame_index).bit_generator.random_raw(n_doubles + -(-size // 8))
        uniform = (raw[:n_doubles] >> np.uint64(11)) * _DOUBLE

        # Scheduler: each subframe, a random set of `load * N_RB` PDSCH RBs, each with a
        # modulation drawn from the cell's mix. Control REGs are in use with probability `load`.
        order = uniform[:per_subframe].reshape(SUBFRAMES_PER_FRAME, n_rb).argsort(axis=1)
        modulation = np.searchsorted(self._modulation_cdf, uniform[per_subframe : 2 * per_subframe])
        pdsch = np.full((SUBFRAMES_PER_FRAME, n_rb), _UNUSED, dtype=np.uint8)
        chosen = order[:, :n_scheduled]
        picked = np.take_along_axis(modulation.reshape(SUBFRAMES_PER_FRAME, n_rb), chosen, axis=1)
        np.put_along_axis(pdsch, chosen, picked.astype(np.uint8) * np.uint8(64), axis=1)
        in_use = uniform[2 * per_subframe :].reshape(SYMBOLS_PER_FRAME, n_rb) < self.cell.load

        # Each RE's point: 6 random bits and its modulation's offset into _CONSTELLATIONS
        # (QPSK outside the PDSCH), or _UNUSED. Reserved REs take the fixed signals afterwards.
        per_rb = np.repeat(pdsch, SYMBOLS_PER_SUBFRAME, axis=0)
        per_rb[self._control_rows] = np.where(in_use[self._control_rows], 0, _UNUSED)
        offset = np.repeat(per_rb, SUBCARRIERS_PER_RB, axis=1)
        offset[self._pbch_symbols] = np.where(self._pbch[self._pbch_symbols], 0, offset[self._pbch_symbols])
        points = raw[n_doubles:].astype("<u8", copy=False).view(np.uint8)[:size].reshape(self.shape) & np.uint8(63)
        points |= offset
        grid = _CONSTELLATIONS.take(points.astype(np.intp))
        grid.reshape(-1)[self._reserved_at] = self._reserved_values
        return grid

    def fixed_grid(self) -> np.ndarray:
        """The deterministic part of every frame: PSS, SSS and CRS (read-only view)."""
        view = self._fixed.view()
        view.flags.writeable = False
        return view
