"""The cell-search stage: ADC chunks in, detected cells with their windows out, per stack.

``SyncStage.process(chunk)`` is what the sync node calls for every EnvelopeSamples message
and what bag replay calls for every recorded one. Bad input never raises here: it ends up
as ``SyncResult.events`` (gaps, non-finite samples, rate changes) or ``flags`` (clipping,
silence, misalignment), next to whatever could still be detected.

Clock drift: a cell's code moves by N frames x (1 + receiver clock error) between stacks.
The stage measures that from cells seen in consecutive stacks (median over cells, smoothed)
and, with ``track_clock``, lets the stacker compensate it, so stacks stay aligned; until the
estimate is in, a stack whose drift would smear the code is flagged instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from deepsync.frontend.chunk import EnvelopeChunk
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.templates import SyncTemplates
from deepsync.sync.detection import CellSearch, SearchConfig
from deepsync.sync.stacking import FrameStacker, Stack, StackConfig, StreamEvent
from deepsync.sync.towers import TowerDatabase
from deepsync.sync.windows import CellWindows, extract_windows

DRIFT_SMOOTHING = 0.3  # weight of each new stack-to-stack drift measurement


@dataclass(frozen=True)
class SyncConfig:
    stack: StackConfig = field(default_factory=StackConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    window_margin: int = 10
    track_clock: bool = True

    def __post_init__(self) -> None:
        if not 0 <= self.window_margin <= 100:
            raise ValueError(f"window_margin must be 0..100 samples, got {self.window_margin!r}")


@dataclass(frozen=True)
class SyncResult:
    """The cells found in one stack."""

    stamp_ns: int  # receiver time of the stack's first sample
    first_sample_index: int
    n_frames: int
    aligned: bool
    flags: tuple[str, ...]
    events: tuple[StreamEvent, ...]  # input problems since the previous result
    cells: tuple[CellWindows, ...]
    clock_drift_ppm: float | None  # receiver clock error measured so far

    @property
    def pcis(self) -> list[int]:
        return [c.pci for c in self.cells if c.pci is not None]


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
        self.search = CellSearch(self.templates, self.config.search, None if towers is None else towers.pcis)
        self.stacker = FrameStacker(self.config.stack)
        self._reported_events = 0
        self._previous: dict[int, float] = {}  # pci -> fine code position in the previous stack
        self._previous_start: int | None = None

    def process(self, chunk: EnvelopeChunk) -> list[SyncResult]:
        """Feed one chunk; results for every stack it completes."""
        return [self._search(stack) for stack in self.stacker.push(chunk)]

    def process_samples(self, samples: np.ndarray, first_sample_index: int, sample_rate: float,
                        stamp_ns: int = 0) -> list[SyncResult]:
        """Feed float samples from another source (a recorded |x|^2, a test signal)."""
        return [self._search(stack) for stack in self.stacker.push_samples(samples, first_sample_index, sample_rate, stamp_ns)]

    def _new_events(self) -> tuple[StreamEvent, ...]:
        events = tuple(self.stacker.events[self._reported_events :])
        self._reported_events = len(self.stacker.events)
        return events

    def _search(self, stack: Stack) -> SyncResult:
        flags = list(stack.flags)
        cells: list[CellWindows] = []
        if not any(flag.startswith("no signal") for flag in flags):
            stacked = stack.stacked()
            for detection in self.search.search(stacked):
                windows = extract_windows(stack, detection, self.templates.length, self.config.window_margin)
                earfcn = self._earfcn(detection.pci)
                cells.append(CellWindows(
                    detection=detection,
                    coarse_index=stack.first_sample_index + detection.frame_offset,
                    margin=self.config.window_margin,
                    windows=windows,
                    stamp_ns=stack.stamp_ns,
                    earfcn=earfcn,
                    carrier_hz=None if earfcn is None else self.towers.cells_with_pci(detection.pci)[0].carrier_hz,
                ))
        self._track_clock(stack, cells)
        return SyncResult(
            stamp_ns=stack.stamp_ns,
            first_sample_index=stack.first_sample_index,
            n_frames=stack.n_frames,
            aligned=stack.aligned,
            flags=tuple(flags),
            events=self._new_events(),
            cells=tuple(cells),
            clock_drift_ppm=self.stacker.measured_drift_ppm,
        )

    def _earfcn(self, pci: int | None) -> int | None:
        if self.towers is None or pci is None:
            return None
        earfcns = {cell.earfcn for cell in self.towers.cells_with_pci(pci)}
        return earfcns.pop() if len(earfcns) == 1 else None

    def _track_clock(self, stack: Stack, cells: list[CellWindows]) -> None:
        """Update the receiver clock error from cells seen in this and the previous stack."""
        positions = {c.pci: c.coarse_index + c.detection.fraction for c in cells if c.pci is not None}
        if self._previous_start is not None and stack.first_sample_index > self._previous_start:
            nominal = stack.first_sample_index - self._previous_start  # where the stacker moved on
            frames = round(nominal / stack.frame_samples)
            moves = [positions[p] - self._previous[p] for p in positions.keys() & self._previous.keys()]
            # a cell's code moves frames x frame x (1 + e) samples in the stream
            drifts = [(move / (frames * stack.frame_samples) - 1) * 1e6 for move in moves
                      if abs(move - nominal) < stack.frame_samples / 4]
            if drifts:
                measured = float(np.median(drifts))
                previous = self.stacker.measured_drift_ppm
                smoothed = measured if previous is None else previous + DRIFT_SMOOTHING * (measured - previous)
                self.stacker.measured_drift_ppm = smoothed
                if self.config.track_clock and math.isfinite(smoothed):
                    self.stacker.clock_ppm = smoothed
        self._previous = positions
        self._previous_start = stack.first_sample_index
