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

Cells found in one stack are tracked into the next: looked for near where their codes should
be (``CellSearch.search``'s expected cells), the confirmed ones at a lower threshold, since
only a few lags are tested (and, where the tower database gives their bandwidth, by their
whole known frame when their codes miss: ``SearchConfig.hold_by_frame``), and for
``hold_stacks`` more stacks after one they were missed in (a fade). With such a cell reported,
the stack's mean frame goes along (``StackWindows.frame``) for the timing stage's ``ml_frame``.
Where the database gives a confirmed cell no bandwidth, its stacks learn it
(``deepsync.sync.bandwidths``, ``learn_bandwidths``).
A confirmed cell held below ``report_z`` sigmas is kept but not reported: below about
5 sigmas the timing stage's ML estimate breaks down (on the dense walk with 10-frame stacks,
13-22 % of arrivals a sample or more off at 3.5-4.5 sigmas, 2 % at 5-6). The full search for
new cells, the costly part, runs every ``search_every`` stacks, on the stack after one where a
tracked cell was missed, and when none is tracked; between, a stack costs the few templates of
the cells it tracks. As a GNSS receiver backs off its acquisition once every satellite in view
is tracked, the gap between full searches doubles after each that finds no cell not already
tracked, up to ``max_search_interval_s`` of stream, and falls back to ``search_every`` as soon
as one does: where the cells heard stay the same, a new cell then waits at most that long to be
found.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.templates import SyncTemplates
from deepsync.lte.earfcn import downlink_frequency_hz
from deepsync.schema import check_settings, setting
from deepsync.sync.bandwidths import BandwidthLearner
from deepsync.sync.search import CellDetection, CellSearch, ExpectedCell, SearchConfig
from deepsync.sync.stacking import FrameStacker, Stack, StackConfig
from deepsync.sync.windows import extract_windows_at
from deepsync.towers import TowerDatabase
from deepsync.types import FRAME_SECONDS, EnvelopeChunk, Health, HealthKind, StackWindows, SyncWindow


@dataclass(frozen=True)
class SyncConfig:
    stack: StackConfig = field(default_factory=StackConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    window_margin: int = setting(10, help="Samples kept on either side of a cell's code in its windows.",
                                 unit="samples", bounds=(0, 100))
    confirm_stacks: int = setting(3, help="Stacks in a row a cell must be found in, where its code should be, "
                                  "before it is reported.", unit="stacks", bounds=(1, 1000))
    confirm_tolerance: float = setting(2.0, help="How far a cell may move between stacks beyond the clock drift.",
                                       unit="samples", bounds=(0.0, 1000.0))
    search_every: int = setting(5, help="Stacks per full search for new cells; between, the cells found are only "
                                "tracked where their codes should be (a few templates instead of dozens).",
                                unit="stacks", bounds=(1, 100_000))
    max_search_interval_s: float = setting(2.0, help="While full searches find no new cell, the gap between them "
                                           "doubles up to this much stream; one that finds a cell brings it back "
                                           "to search_every. 0: every search_every stacks.", unit="s",
                                           bounds=(0.0, 3600.0))
    hold_stacks: int = setting(2, help="Stacks a confirmed cell is still looked for after a stack it was missed in "
                               "(a fade).", unit="stacks", bounds=(0, 1000))
    report_z: float = setting(5.0, help="A confirmed cell found below this many sigmas is kept tracked but not "
                              "reported: below about 5 the timing breaks down (arrivals a sample or more off).",
                              unit="sigmas", bounds=(0.0, 1000.0))
    learn_bandwidths: bool = setting(True, help="Learn the bandwidth of confirmed cells the tower database gives "
                                     "none from their stacks.")

    def __post_init__(self) -> None:
        check_settings(self)

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
class _Track:
    """A cell found in an earlier stack, followed from stack to stack."""

    cell: DetectedCell  # as last found
    start: int  # first sample index of the stack it was last found in
    streak: int  # stacks in a row it was found in where its code should be (misses held through not counted)
    missed: int = 0  # stacks it has been missed in since


@dataclass(frozen=True)
class SyncResult:
    """The cells found in one stack."""

    stamp_ns: int  # receiver time of the stack's first sample
    first_sample_index: int
    sample_rate: float
    n_frames: int
    hop_frames: int  # frames from this stack's start to the next's
    aligned: bool
    flags: tuple[Health, ...]  # what makes this stack less trustworthy
    events: tuple[Health, ...]  # input problems since the previous result
    cells: tuple[DetectedCell, ...]  # confirmed cells
    tentative: tuple[DetectedCell, ...]  # found but not reported: not confirmed yet, or held too weakly to time
    clock_drift_ppm: float | None  # receiver clock error measured so far
    searched: bool  # searched for new cells (else only the cells found before were tracked)
    frame: np.ndarray | None = None  # the stack's mean frame, when a reported cell's bandwidth is known
    frame_delay: float = 0.0  # samples what repeats sits later in ``frame`` than in the first row (StackWindows)

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
                            self.clock_drift_ppm, self.frame, self.frame_delay, (self.n_frames, self.hop_frames))


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
                                 None if towers is None else towers.cosited_pairs(),
                                 None if towers is None else towers.bandwidths())
        # the search's bandwidths are the one source: the database's, and those learned into it
        self.learner = (BandwidthLearner(self.templates, self.search.bandwidths, towers.unsized_pcis())
                        if towers is not None and self.config.learn_bandwidths else None)
        self.stacker = FrameStacker(frontend.adc_rate_hz, self.config.stack)
        self._tracks: dict[int, _Track] = {}  # by PCI
        self._since_search = 0  # stacks since the last full search
        self._search_interval = self.config.search_every  # stacks from one full search to the next
        stack_seconds = self.config.stack.hop * FRAME_SECONDS
        # (the epsilon: 2 s over 0.1 s stacks is 19.999... in floating point, and means 20)
        self._longest_interval = max(self.config.search_every,
                                     math.floor(self.config.max_search_interval_s / stack_seconds + 1e-9))
        self._lost = False  # a tracked cell was not found in the last stack

    def process(self, chunk: EnvelopeChunk) -> list[SyncResult]:
        """Feed one chunk; results for every stack it completes."""
        return [self._search(stack) for stack in self.stacker.push(chunk)]

    def process_samples(self, samples: np.ndarray, first_sample_index: int, sample_rate: float,
                        stamp_ns: int = 0) -> list[SyncResult]:
        """Feed float samples from another source (a recorded |x|^2, a test signal)."""
        return [self._search(stack) for stack in self.stacker.push_samples(samples, first_sample_index, sample_rate, stamp_ns)]

    def take_events(self) -> tuple[Health, ...]:
        """The stream's events (gaps, resets, bad samples) since they were last taken: every
        result takes them, so at the end of a stream this holds what came after the last stack.
        Taken, not copied: a long run keeps none."""
        events = tuple(self.stacker.events)
        self.stacker.events.clear()
        return events

    def _search(self, stack: Stack) -> SyncResult:
        cells: list[DetectedCell] = []
        expected = self._expected(stack)
        discover = not expected or self._lost or self._since_search + 1 >= self._search_interval
        if not any(flag.kind is HealthKind.NO_SIGNAL for flag in stack.flags):
            detections = self.search.search(stack.stacked(), expected, discover)
            # by code start, cut together: a co-sited pair's two sectors share theirs
            starts = list(dict.fromkeys(d.frame_offset for d in detections))
            cut = extract_windows_at(stack, starts, self.templates.length, self.config.window_margin) if starts else []
            windows = dict(zip(starts, cut))
            cells = [DetectedCell(d, self._window(stack, d, windows[d.frame_offset])) for d in detections]
        self._since_search = 0 if discover else self._since_search + 1
        if discover:
            self._back_off(found_new=not {c.pci for c in cells} <= {e.pci for e in expected})
        self._lost = not {e.pci for e in expected} <= {c.pci for c in cells}
        streaks = {c.pci: self._streak(stack, c) for c in cells}
        reported = {c.pci for c in cells if streaks[c.pci] >= self.config.confirm_stacks
                    and c.detection.peak_metric >= self.config.report_z}
        self._follow(stack, cells, streaks)
        if self.learner is not None:
            self.learner.observe(stack.mean, [c.detection for c in cells if c.pci in reported])
        frame_wanted = any(c.window.bandwidth_mhz is not None for c in cells if c.pci in reported)
        return SyncResult(
            stamp_ns=stack.stamp_ns,
            first_sample_index=stack.first_sample_index,
            sample_rate=self.stacker.sample_rate,
            n_frames=stack.n_frames,
            hop_frames=self.config.stack.hop,
            aligned=stack.aligned,
            flags=stack.flags,
            events=self.take_events(),
            cells=tuple(c for c in cells if c.pci in reported),
            tentative=tuple(c for c in cells if c.pci not in reported),
            clock_drift_ppm=self.stacker.measured_drift_ppm,
            searched=discover,
            frame=stack.mean if frame_wanted else None,
            frame_delay=stack.mean_delay,
        )

    def _back_off(self, found_new: bool) -> None:
        """After a full search: the next one as soon as ``search_every`` allows if it found a
        cell not tracked before, else twice as late as the last (up to the longest interval)."""
        self._search_interval = (self.config.search_every if found_new
                                 else min(2 * self._search_interval, self._longest_interval))

    def _window(self, stack: Stack, detection: CellDetection, windows: np.ndarray) -> SyncWindow:
        earfcn = self._earfcn(detection.pci)
        site = detection.site
        return SyncWindow(
            stamp_ns=stack.stamp_ns,
            pci=detection.pci,
            coarse_index=stack.first_sample_index + detection.frame_offset,
            windows=windows,
            peak_metric=detection.peak_metric,
            snr_db=detection.snr_db,
            earfcn=earfcn,
            carrier_hz=None if earfcn is None else downlink_frequency_hz(earfcn),
            cosited_pci=None if site is None else next(pci for pci in site.pcis if pci != detection.pci),
            site_coefficients=None if site is None else site.coefficients,
            bandwidth_mhz=self._bandwidth(detection),
        )

    def _follow(self, stack: Stack, cells: list[DetectedCell], streaks: dict[int, int]) -> None:
        """Tracks after a stack: the cells found, and the confirmed ones missed in fewer than
        ``hold_stacks`` stacks in a row."""
        held = {pci: replace(track, missed=track.missed + 1) for pci, track in self._tracks.items()
                if track.streak >= self.config.confirm_stacks and track.missed < self.config.hold_stacks}
        found = {c.pci: _Track(c, stack.first_sample_index, streaks[c.pci]) for c in cells}
        self._tracks = {**held, **found}

    def _predicted(self, stack: Stack, pci: int) -> float | None:
        """Stream sample index where the code of a tracked cell should start in this stack (its
        position when last found moved on by the frames since and the clock); None if it is
        not tracked or the stream started over since."""
        track = self._tracks.get(pci)
        if track is None:
            return None
        frames = round((stack.first_sample_index - track.start) / stack.frame_samples)
        if frames <= 0:
            return None
        drift = (stack.drift_ppm if stack.drift_ppm is not None else self.stacker.clock_ppm) * 1e-6
        return track.cell.code_position + frames * stack.frame_samples * (1 + drift)

    def _expected(self, stack: Stack) -> list[ExpectedCell]:
        """The tracked cells where this stack should have them, strongest first."""
        expected = []
        for pci, track in sorted(self._tracks.items(), key=lambda item: -item[1].cell.detection.peak_metric):
            position = self._predicted(stack, pci)
            if position is not None:
                expected.append(ExpectedCell(pci, (position - stack.first_sample_index) % stack.frame_samples,
                                             track.cell.window.cosited_pci, track.streak >= self.config.confirm_stacks))
        return expected

    def _streak(self, stack: Stack, cell: DetectedCell) -> int:
        """In how many stacks in a row, this one included, the PCI was found where its code
        should be (a confirmed cell's misses held through break no streak, nor count).

        Real cells persist; the envelope's other structure (cells missing from the tower
        database, CRS and PBCH of synchronised cells) rarely lines up with one PCI for long.
        """
        expected = self._predicted(stack, cell.pci)
        if expected is None or abs(cell.code_position - expected) > self.config.confirm_tolerance:
            return 1
        return self._tracks[cell.pci].streak + 1

    def _bandwidth(self, detection: CellDetection) -> float | None:
        """The channel bandwidth the tower database gives the cell, or that was learned (and its
        co-sited sector's, if found as a pair: both must agree)."""
        bandwidths = {self.search.bandwidths.get(pci)
                      for pci in (detection.site.pcis if detection.site else (detection.pci,))}
        return bandwidths.pop() if len(bandwidths) == 1 else None

    def _earfcn(self, pci: int) -> int | None:
        """The EARFCN the tower database gives a PCI, if it gives exactly one."""
        if self.towers is None:
            return None
        earfcns = {cell.earfcn for cell in self.towers.cells_with_pci(pci)}
        return earfcns.pop() if len(earfcns) == 1 else None
