"""The DeepSync chain, envelope chunks -> sync -> timing -> fusion, built from one config.

This is the only place where stages are chained: the ``deepsync`` command, bag replay and the
ROS nodes all run the chain through :class:`Pipeline` (a node that wraps one stage uses that
stage alone, fed with what the previous node published). Where the chunks come from is a
source's business (``deepsync.sources``); the source also says which front end the stream went
through, and every template is built for that front end and its sample rate.

Each completed stack gives one :class:`StackResult`: the sync stage's cells, events and flags,
the timing stage's arrivals and, with a tower database that places its sites (an ``origin``,
positions, timing offsets), fusion's fixes. Nothing in the chain raises on a bad stream; what
went wrong is in :attr:`StackResult.health`.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

from deepsync.frontend.config import FrontendConfig
from deepsync.fusion.stage import FusionConfig, FusionResult, FusionStage
from deepsync.sync.stage import SyncConfig, SyncResult, SyncStage
from deepsync.timing.stage import TimingConfig, TimingResult, TimingStage
from deepsync.towers import TowerDatabase
from deepsync.types import EnvelopeChunk, Health, StackArrivals


@dataclass(frozen=True)
class PipelineConfig:
    """Every stage's settings."""

    sync: SyncConfig = field(default_factory=SyncConfig)
    timing: TimingConfig = field(default_factory=TimingConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)

    def __post_init__(self) -> None:
        if self.sync.stack.n_frames < 2:
            raise ValueError(f"stacks of {self.sync.stack.n_frames} frame: the timing stage measures the noise "
                             "from how frames differ, so a stack needs at least 2 frames")


@dataclass(frozen=True)
class StackResult:
    """What the chain made of one stack of frames."""

    sync: SyncResult
    timing: TimingResult
    arrivals: StackArrivals
    fusion: FusionResult | None = None  # None without a tower database that places its sites

    @property
    def stamp_ns(self) -> int:
        """Receiver time of the stack's first sample: the stamp of everything derived from it."""
        return self.sync.stamp_ns

    @property
    def health(self) -> tuple[Health, ...]:
        """Everything the stages reported on this stack: stream events since the previous
        stack, the stack's flags, cells that could not be timed and weak arrivals."""
        weak = tuple(flag for cell in self.timing.cells for flag in cell.flags)
        fusion = () if self.fusion is None else self.fusion.events
        return self.sync.events + self.sync.flags + self.timing.events + weak + fusion


class Pipeline:
    """Sync, timing and fusion stages for one front end (and one tower database, if any)."""

    def __init__(self, frontend: FrontendConfig, config: PipelineConfig | None = None,
                 towers: TowerDatabase | None = None) -> None:
        self.config = config or PipelineConfig()
        self.frontend = frontend
        self.sync = SyncStage(frontend, self.config.sync, towers)
        self.timing = TimingStage(frontend, self.config.timing)
        self.fusion = FusionStage(towers, self.config.fusion) if places_sites(towers) else None

    def process(self, chunk: EnvelopeChunk) -> list[StackResult]:
        """Feed one chunk; a result for every stack it completes."""
        return [self._fuse(result, self.timing.process(result.windows)) for result in self.sync.process(chunk)]

    def _fuse(self, sync: SyncResult, timing: TimingResult) -> StackResult:
        arrivals = sync.stack_windows.arrivals(timing.cells)
        fusion = None if self.fusion is None else self.fusion.process(arrivals)
        return StackResult(sync, timing, arrivals, fusion)

    def run(self, chunks: Iterable[EnvelopeChunk]) -> Iterator[StackResult]:
        """Results stack by stack as the chunks (a source's ``chunks()``, a bag) stream in."""
        for chunk in chunks:
            yield from self.process(chunk)


def places_sites(towers: TowerDatabase | None) -> bool:
    """Whether a tower database can anchor fixes: a map origin and a site with position and timing."""
    return towers is not None and towers.origin is not None and any(
        site.has_position and site.timing_offset_us is not None for site in towers.sites)
