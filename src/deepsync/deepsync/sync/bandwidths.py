"""A cell's channel bandwidth, learned from its stacks where the tower database does not give it.

Public cell databases list a cell's identity, carrier and position, rarely its bandwidth; but
a cell's CRS fills its whole carrier, and the envelope shows how wide that is. With the code
position known (a confirmed cell), each LTE bandwidth's known frame (codes and CRS,
``frontend.templates.known_frame``) is fitted to the stack there, and the one that explains the
most of it gets the stack's vote: a template narrower than the carrier misses part of the CRS,
a wider one carries subcarriers that are not sent. Once ``VOTES`` stacks have voted and one
bandwidth has ``AGREEMENT`` of them, it is the cell's, for the rest of the stream: the search
holds the cell by its whole frame, and the timing stage times it so (``ml_frame``).

Through an I/Q radio's passband every carrier of 3 MHz or more looks the same
(``squared_iq_frontend``), and the narrowest one that fits what the radio saw wins, which is
what its templates should be.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

import numpy as np
import scipy.fft

from deepsync.frontend.templates import SyncTemplates, known_frame
from deepsync.lte.numerology import SUPPORTED_BANDWIDTHS_MHZ
from deepsync.sync.correlation import parseval_weights
from deepsync.sync.search import CellDetection

VOTES = 5  # stacks a cell's bandwidth is judged on
AGREEMENT = 0.8  # share of them the winner needs


class BandwidthLearner:
    """Learns the bandwidth of confirmed cells that ``known`` (PCI -> MHz: the database's, and
    what was learned, updated in place) does not give, of the PCIs in ``learnable`` (those
    whose database cells give none: a PCI whose cells give different ones stays unknown)."""

    def __init__(self, templates: SyncTemplates, known: dict[int, float], learnable: set[int]) -> None:
        self.templates = templates
        self.known = known
        self.learnable = learnable
        self._votes: dict[int, list[float]] = {}
        self._spectra: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # PCI -> (bandwidths, bins) conj spectra, energies

    def observe(self, frame: np.ndarray, cells: Sequence[CellDetection]) -> None:
        """One stack (its mean frame) and the confirmed cells found in it: each cell of unknown
        bandwidth votes, and a bandwidth enough votes agree on becomes the cell's."""
        pending = [cell for cell in cells if cell.pci not in self.known and cell.pci in self.learnable]
        if not pending:
            return
        weighted = scipy.fft.rfft(frame - frame.mean()) * parseval_weights(len(frame))
        omega = 2 * np.pi * scipy.fft.rfftfreq(len(frame))
        for cell in pending:
            spectra, energies = self._known_frames(cell.pci)
            # each template's correlation with the frame at the cell's code start, by Parseval
            correlation = np.real(spectra @ (weighted * np.exp(1j * omega * (cell.frame_offset + cell.fraction))))
            explained = np.where(correlation > 0, correlation**2 / energies, 0.0)
            votes = self._votes.setdefault(cell.pci, [])
            votes.append(SUPPORTED_BANDWIDTHS_MHZ[int(np.argmax(explained))])
            if len(votes) >= VOTES:
                best, count = Counter(votes[-VOTES:]).most_common(1)[0]
                if count >= AGREEMENT * VOTES:
                    self.known[cell.pci] = best
                    del self._votes[cell.pci]

    def _known_frames(self, pci: int) -> tuple[np.ndarray, np.ndarray]:
        """Conjugate spectra (bandwidths, bins) of a PCI's known frame at every LTE bandwidth,
        code at sample 0, and their energies. Cached."""
        if pci not in self._spectra:
            templates = np.stack([known_frame(self.templates, pci, bandwidth) for bandwidth in SUPPORTED_BANDWIDTHS_MHZ])
            self._spectra[pci] = np.conj(scipy.fft.rfft(templates, axis=1)), np.sum(templates**2, axis=1)
        return self._spectra[pci]
