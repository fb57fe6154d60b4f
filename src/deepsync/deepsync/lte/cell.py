"""Per-cell downlink configuration: what decides the content of a cell's resource grid."""

from __future__ import annotations

import math
from dataclasses import dataclass

from deepsync.lte.numerology import check_bandwidth
from deepsync.types import MAX_PCI

N_CELL_IDS = MAX_PCI + 1  # TS 36.211 6.11: 168 groups x 3 identities
MODULATIONS = ("QPSK", "16QAM", "64QAM")


def check_pci(pci: object) -> int:
    """Return ``pci`` as an int, or raise naming the valid range (TS 36.211 §6.11: 0..503)."""
    if isinstance(pci, bool) or not isinstance(pci, (int,)) and not (
        isinstance(pci, float) and pci.is_integer()
    ):
        raise ValueError(f"PCI {pci!r} is not an integer (valid: 0..{N_CELL_IDS - 1})")
    value = int(pci)
    if not 0 <= value < N_CELL_IDS:
        raise ValueError(f"PCI {value} is out of range (valid: 0..{N_CELL_IDS - 1})")
    return value


def split_pci(pci: int) -> tuple[int, int]:
    """(N_ID^(1), N_ID^(2)) of a physical cell identity: PCI = 3 N_ID1 + N_ID2."""
    pci = check_pci(pci)
    return pci // 3, pci % 3


@dataclass(frozen=True)
class CellConfig:
    """What one cell transmits.

    ``load`` is the fraction of PDSCH resource blocks scheduled in each subframe (and of
    control-region REGs in use); ``cfi`` the number of control symbols per subframe;
    ``modulation_weights`` the probability that a scheduled RB carries QPSK, 16QAM or 64QAM.
    All resource elements are sent at the same EPRE (no PDSCH power offsets, port 0 only).
    """

    pci: int
    bandwidth_mhz: float = 10.0
    load: float = 1.0
    cfi: int = 2
    modulation_weights: tuple[float, float, float] = (1 / 3, 1 / 3, 1 / 3)

    def __post_init__(self) -> None:
        object.__setattr__(self, "pci", check_pci(self.pci))
        object.__setattr__(self, "bandwidth_mhz", check_bandwidth(self.bandwidth_mhz))
        if not (isinstance(self.load, (int, float)) and 0.0 <= self.load <= 1.0):
            raise ValueError(f"load {self.load!r} must be a fraction in [0, 1]")
        low, high = (2, 4) if self.bandwidth_mhz == 1.4 else (1, 3)
        if self.cfi not in range(low, high + 1):
            raise ValueError(
                f"cfi {self.cfi!r} must be {low}..{high} for a {self.bandwidth_mhz:g} MHz carrier"
            )
        weights = tuple(float(w) for w in self.modulation_weights)
        if (
            len(weights) != len(MODULATIONS)
            or any(not math.isfinite(w) or w < 0 for w in weights)
            or sum(weights) <= 0
        ):
            raise ValueError(
                f"modulation_weights {self.modulation_weights!r} must be three non-negative "
                f"numbers (for {', '.join(MODULATIONS)}) with a positive sum"
            )
        object.__setattr__(self, "modulation_weights", tuple(w / sum(weights) for w in weights))
