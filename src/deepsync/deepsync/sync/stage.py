"""The cell-search stage: ADC chunks in, detected cells with their windows out, per stack.

``SyncStage.process(chunk)`` is what the sync node calls for every EnvelopeSamples message
and what bag replay calls for every recorded one. What is wrong with the stream never raises
here: it ends up as ``SyncResult.events`` (gaps, non-finite samples, going back in time, chunks
at another sample rate than the templates') or ``flags`` (clipping, silence, misalignment),
typed :class:`~deepsync.types.Health`, next to whatever could still be found.

The sample rate comes from one place, the front end the templates are built for: a chunk at
any other rate is reported and never stacked.

The receiver clock is measured and compensated by the stacker (see ``sync.stacking``). A cell
is reported once it has been found in ``confirm_stacks`` stacks in a row where its code should
be (real cells persist; the envelope's other structure rarely lines up with one PCI for long);
the unconfirmed ones are in ``SyncResult.tentative``. Each cell goes on as a
:class:`~deepsync.types.SyncWindow`, exactly what a ``SyncWindow`` message carries.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.templates import SyncTemplates
from deepsync.lte.earfcn import downlink_frequency_hz
from deepsync.sync.search import CellDetection, CellSearch, SearchConfig
from deepsync.sync.stacking import FrameStacker, Stack, StackConfig
from deepsync.sync.windows import extract_windows
from deepsync.towers import TowerDatabase
from deepsync.types import EnvelopeChunk, Health, HealthKind, StackWindows, SyncWindow


@dataclass(frozen=True)
class SyncConfig:
    stack: StackConfig = field(default_factory=StackConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    window_margin: int = 10
    confirm_stacks: int = 3  # stacks in a row a PCI must be found in, where its code should be, to be reported
    confirm_tolerance: float = 2.0  # samples a cell may move between stacks beyond the clock drift

    def __post_init__(self) -> None:
        if not 0 <= self.window_margin <= 100:
            raise ValueError(f"window_margin must be 0..100 samples, got {self.window_margin!r}")
        if self.confirm_stacks < 1:
            raise ValueError(f"confirm_stacks must be >= 1, got {self.confirm_stacks!r}")


@dataclass(frozen=True)
class DetectedCell:
    """A cell found in a stack: what the search knows of it (identity candidates, sub-sample
    position, a co-sited fit) and what goes on to the timing stage."""

    detection: CellDetection
    window: SyncWindow

    @property
    def pci(self) -> int:
        return self.window.pci

    @property
    def code_position(self) -> float:
        """Stream sample index of the subframe-0 code start in the stack's first frame, to the
        search's sub-sample precision (the timing stage does better)."""
        return self.window.coarse_index + self.detection.fraction


@dataclass(frozen=True)
class SyncResult:
    """The cells found in one stack."""

    stamp_ns: int  # receiver time of the stack's first sample
    first_sample_index: int
    sample_rate: float
    n_frames: int
    aligned: bool
    flags: tuple[Health, ...]  # what makes this stack less trustworthy
    events: tuple[Health, ...]  # input problems since the previous result
    cells: tuple[DetectedCell, ...]  # confirmed cells
    tentative: tuple[DetectedCell, ...]  # detected in this stack only, so far
    clock_drift_ppm: float | None  # receiver clock error measured so far

    @property
    def pcis(self) -> list[int]:
        return [c.pci for c in self.cells]

    @property
    def windows(self) -> tuple[SyncWindow, ...]:
        """The confirmed cells as the timing stage takes them."""
        return tuple(c.window for c in self.cells)

    @property
    def stack_windows(self) -> StackWindows:
        """The confirmed cells with the stack's time base: what ``cell_sync`` publishes."""
        return StackWindows(self.stamp_ns, self.first_sample_index, self.sample_rate, self.windows,
                            self.clock_drift_ppm)


class SyncStage:
    """Stacks the stream, searches each stack for cells, cuts their windows."""

    def __init__(
        self,
        frontend: FrontendConfig,
        config: SyncConfig | None = None,
        towers: TowerDatabase | None = None,
    ) -> None:
        self.config = config or SyncConfig()
        self.towers = towers
        self.templates = SyncTemplates(frontend)
        self.search = CellSearch(self.templates, self.config.search, None if towers is None else towers.pcis,
                                 None if towers is None else towers.cosited_pairs())
        self.stacker = FrameStacker(frontend.adc_rate_hz, self.config.stack)
        self._previous: dict[int, tuple[float, int]] = {}  # pci -> (code position, streak) last stack
        self._previous_start: int | None = None

    def process(self, chunk: EnvelopeChunk) -> list[SyncResult]:
        """Feed one chunk; results for every stack it completes."""
        return [self._search(stack) for stack in self.stacker.push(chunk)]

    def process_samples(self, samples: np.ndarray, first_sample_index: int, sample_rate: float,
                        stamp_ns: int = 0) -> list[SyncResult]:
        """Feed float samples from another source (a recorded |x|^2, a test signal)."""
        return [self._search(stack) for stack in self.stacker.push_samples(samples, first_sample_index, sample_rate, stamp_ns)]

    def _new_events(self) -> tuple[Health, ...]:
        """The stacker's events since the previous result (taken: a long run keeps none)."""
        events = tuple(self.stacker.events)
        self.stacker.events.clear()
        return events

    def _search(self, stack: Stack) -> SyncResult:
        cells: list[DetectedCell] = []
        if not any(flag.kind is HealthKind.NO_SIGNAL for flag in stack.flags):
            for detection in self.search.search(stack.stacked()):
                cells.append(DetectedCell(detection, self._window(stack, detection)))
        streaks = {c.pci: self._streak(stack, c) for c in cells}
        confirmed = [c for c in cells if streaks[c.pci] >= self.config.confirm_stacks]
        self._previous = {c.pci: (c.code_position, streaks[c.pci]) for c in cells}
        self._previous_start = stack.first_sample_index
        return SyncResult(
            stamp_ns=stack.stamp_ns,
            first_sample_index=stack.first_sample_index,
            sample_rate=self.stacker.sample_rate,
            n_frames=stack.n_frames,
            aligned=stack.aligned,
            flags=stack.flags,
            events=self._new_events(),
            cells=tuple(confirmed),
            tentative=tuple(c for c in cells if streaks[c.pci] < self.config.confirm_stacks),
            clock_drift_ppm=self.stacker.measured_drift_ppm,
        )

    def _window(self, stack: Stack, detection: CellDetection) -> SyncWindow:
        earfcn = self._earfcn(detection.pci)
        site = detection.site
        return SyncWindow(
            stamp_ns=stack.stamp_ns,
            pci=detection.pci,
            coarse_index=stack.first_sample_index + detection.frame_offset,
            windows=extract_windows(stack, detection.frame_offset, self.templates.length, self.config.window_margin),
            peak_metric=detection.peak_metric,
            snr_db=detection.snr_db,
            earfcn=earfcn,
            carrier_hz=None if earfcn is None else downlink_frequency_hz(earfcn),
            cosited_pci=None if site is None else next(pci for pci in site.pcis if pci != detection.pci),
            site_coefficients=None if site is None else site.coefficients,
        )

    def _streak(self, stack: Stack, cell: DetectedCell) -> int:
        """In how many stacks in a row, this one included, the PCI was found where its code
        should be (the previous position moved on by the frames in between and the clock).

        Real cells persist; the envelope's other structure (cells missing from the tower
        database, CRS and PBCH of synchronised cells) rarely lines up with one PCI for long.
        """
        if cell.pci not in self._previous or self._previous_start is None:
            return 1
        frames = round((stack.first_sample_index - self._previous_start) / stack.frame_samples)
        position, streak = self._previous[cell.pci]
        drift = (stack.drift_ppm if stack.drift_ppm is not None else self.stacker.clock_ppm) * 1e-6
        expected = position + frames * stack.frame_samples * (1 + drift)
        moved = abs(cell.code_position - expected)
        return streak + 1 if frames > 0 and moved <= self.config.confirm_tolerance else 1

    def _earfcn(self, pci: int) -> int | None:
        """The EARFCN the tower database gives a PCI, if it gives exactly one."""
        if self.towers is None:
            return None
        earfcns = {cell.earfcn for cell in self.towers.cells_with_pci(pci)}
        return earfcns.pop() if len(earfcns) == 1 else None
