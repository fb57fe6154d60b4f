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

The chain can also be entered later, where a bag or a node hands over a stage's output instead
of ADC chunks: :meth:`Pipeline.time_stack` takes a stack's cells (``SyncWindowArray``) through
timing and fusion, :meth:`Pipeline.fuse_arrivals` a stack's arrivals (``CellTimingArray``)
through fusion. :meth:`Pipeline.process` runs through the very same two methods, so a replay that
starts at timing or fusion makes what the whole chain makes. Without a front end there is no
sync or timing stage (fusion needs none).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace

from deepsync.frontend.config import FrontendConfig
from deepsync.fusion.bias_map import BiasMap
from deepsync.fusion.stage import FusionConfig, FusionResult, FusionStage
from deepsync.motion import DEFAULT_MOTION, MOTION, MotionModel, motion_model
from deepsync.schema import Setting, settings
from deepsync.sync.stage import SyncConfig, SyncResult, SyncStage
from deepsync.timing.stage import TimingConfig, TimingResult, TimingStage
from deepsync.towers import TowerDatabase
from deepsync.types import EnvelopeChunk, Health, StackArrivals, StackWindows


def moving(model: MotionModel, sync: SyncConfig, fusion: FusionConfig) -> tuple[SyncConfig, FusionConfig]:
    """``sync`` and ``fusion`` with a motion model's stacks, tracker process model, prior hold,
    start rule and bias sigma."""
    stack = replace(sync.stack, n_frames=model.n_frames, hop_frames=model.hop_frames)
    tracker = replace(fusion.tracker, acceleration_std_mps2=model.acceleration_std_mps2,
                      initial_speed_std_mps=model.initial_speed_std_mps, prior_hold_s=model.prior_hold_s,
                      spare_site_at_start=model.spare_site_at_start)
    return replace(sync, stack=stack), replace(fusion, tracker=tracker, multipath_std_m=model.multipath_std_m)


def _default_sync() -> SyncConfig:
    return moving(motion_model(DEFAULT_MOTION), SyncConfig(), FusionConfig())[0]


@dataclass(frozen=True)
class PipelineConfig:
    """Every stage's settings. The defaults are the default motion model's
    (``deepsync.motion``): its stacks, its tracker; :meth:`for_motion` gives another's."""

    sync: SyncConfig = field(default_factory=_default_sync)
    timing: TimingConfig = field(default_factory=TimingConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)

    def __post_init__(self) -> None:
        if self.sync.stack.n_frames < 2:
            raise ValueError(f"stacks of {self.sync.stack.n_frames} frame: the timing stage measures the noise "
                             "from how frames differ, so a stack needs at least 2 frames")
        # one source for the overlap of sliding stacks: the stacks themselves
        overlap = self.sync.stack.n_frames / self.sync.stack.hop
        if self.fusion.tracker.stack_overlap != overlap:
            tracker = replace(self.fusion.tracker, stack_overlap=overlap)
            object.__setattr__(self, "fusion", replace(self.fusion, tracker=tracker))

    @classmethod
    def for_motion(cls, motion: str) -> PipelineConfig:
        """The defaults with the motion model ``motion``'s stacks and tracker (ValueError listing
        the names)."""
        sync, fusion = moving(motion_model(motion), SyncConfig(), FusionConfig())
        return cls(sync=sync, fusion=fusion)

    def with_choices(self, n_frames: int | None = None, hop_frames: int | None = None, motion: str | None = None,
                     **chosen: object) -> PipelineConfig:
        """This config with what a user chose (None: not chosen): the motion model by name (its
        stacks and tracker), frames per stack (without ``hop_frames``: back to back), frames from
        one stack to the next (sliding stacks), and any stage config's setting by its field name
        (``deepsync.schema``: ``search_every=3``, ``estimator="ml"``, ``max_std_m=100.0``; a
        choice by its name). ValueError naming the setting for a value it refuses, or a name no
        stage config has."""
        sync, fusion = self.sync, self.fusion
        if motion is not None:
            MOTION.check(motion)
            sync, fusion = moving(motion_model(motion), sync, fusion)
        if n_frames is not None or hop_frames is not None:
            frames = sync.stack.n_frames if n_frames is None else n_frames
            hop = hop_frames if hop_frames is not None or n_frames is None else frames
            sync = replace(sync, stack=replace(sync.stack, n_frames=frames, hop_frames=hop))
        config = replace(self, sync=sync, fusion=fusion)
        for name, value in chosen.items():
            if value is not None:
                config = config._with_setting(name, value)
        return config

    def _with_setting(self, name: str, value: object) -> PipelineConfig:
        try:
            path, described = setting_paths()[name]
        except KeyError:
            raise ValueError(f"{name}: no stage config has such a setting") from None
        described.check(value)
        if isinstance(value, str) and described.choices is not None:
            value = described.choices[value]
        return _replaced(self, path, {name: value})

    def reconfiguration(self, pipeline: Pipeline) -> Callable[[], None]:
        """What running ``pipeline`` with this config takes, built now (ValueError if it cannot:
        ``pipeline`` unchanged), and the step that switches to it, which cannot fail. Only the
        timing stage's settings may change while stacks flow (a new estimator, a checkpoint):
        the sync and fusion stages hold state their settings shaped."""
        changed = [part for part in ("sync", "fusion") if getattr(self, part) != getattr(pipeline.config, part)]
        if changed:
            raise ValueError(f"the {' and '.join(changed)} settings cannot change while the pipeline runs: build a "
                             "new pipeline")
        timing = pipeline.timing
        if timing is not None and self.timing != pipeline.config.timing:
            timing = timing.with_config(self.timing)

        def switch() -> None:
            pipeline.config, pipeline.timing = self, timing
        return switch


_STAGE_CONFIGS = (("sync",), ("sync", "stack"), ("sync", "search"), ("timing",), ("fusion",), ("fusion", "tracker"),
                  ("fusion", "snapshot"))


@functools.cache
def setting_paths() -> dict[str, tuple[tuple[str, ...], Setting]]:
    """Every stage config's setting by field name (no two share one), with where its config
    sits in a :class:`PipelineConfig`."""
    found: dict[str, tuple[tuple[str, ...], Setting]] = {}
    defaults = PipelineConfig()
    for path in _STAGE_CONFIGS:
        part = functools.reduce(getattr, path, defaults)
        for name, described in settings(type(part)).items():
            if name in found:
                raise RuntimeError(f"{name} is a setting of {'.'.join(found[name][0])} and {'.'.join(path)}")
            found[name] = (path, described)
    return found


def _replaced(config: object, path: tuple[str, ...], changes: dict[str, object]) -> object:
    """``config`` with ``changes`` made to the config at ``path`` inside it, every config on the
    way rebuilt (so each checks itself, and ``PipelineConfig`` derives what it derives)."""
    if not path:
        return replace(config, **changes)
    return replace(config, **{path[0]: _replaced(getattr(config, path[0]), path[1:], changes)})


@dataclass(frozen=True)
class TimedStack:
    """What timing and fusion made of one stack's cells (:meth:`Pipeline.time_stack`)."""

    windows: StackWindows
    timing: TimingResult
    arrivals: StackArrivals
    fusion: FusionResult | None = None  # None without a tower database that places its sites

    @property
    def stamp_ns(self) -> int:
        """Receiver time of the stack's first sample."""
        return self.windows.stamp_ns

    @property
    def health(self) -> tuple[Health, ...]:
        """Cells that could not be timed, weak arrivals and cells fusion could not place."""
        weak = tuple(flag for cell in self.timing.cells for flag in cell.flags)
        fusion = () if self.fusion is None else self.fusion.events
        return self.timing.events + weak + fusion


@dataclass(frozen=True)
class StackResult:
    """What the chain made of one stack of frames: the sync stage's result and what timing and
    fusion made of its cells."""

    sync: SyncResult
    timed: TimedStack

    @property
    def timing(self) -> TimingResult:
        return self.timed.timing

    @property
    def arrivals(self) -> StackArrivals:
        return self.timed.arrivals

    @property
    def fusion(self) -> FusionResult | None:
        """None without a tower database that places its sites."""
        return self.timed.fusion

    @property
    def stamp_ns(self) -> int:
        """Receiver time of the stack's first sample: the stamp of everything derived from it."""
        return self.sync.stamp_ns

    @property
    def health(self) -> tuple[Health, ...]:
        """Everything the stages reported on this stack: stream events since the previous
        stack, the stack's flags, cells that could not be timed, weak arrivals and cells fusion
        could not place."""
        return self.sync.events + self.sync.flags + self.timed.health


class Pipeline:
    """Sync, timing and fusion stages for one front end (and one tower database, if any).

    ``frontend`` None builds no sync or timing stage: a pipeline that only fuses arrivals (a
    bag of ``CellTimingArray``) needs no templates and so no front end. ``bias_map``: the sites'
    range biases known from a survey, for fusion (``deepsync.fusion.bias_map``); ValueError
    with one but no fusion, or one made in another frame than the database's.
    """

    def __init__(self, frontend: FrontendConfig | None, config: PipelineConfig | None = None,
                 towers: TowerDatabase | None = None, *, bias_map: BiasMap | None = None) -> None:
        self.config = config or PipelineConfig()
        self.frontend = frontend
        fusing = places_sites(towers)
        if bias_map is not None and not fusing:
            raise ValueError("a bias map corrects fusion's site ranges, and there is no fusion without a tower "
                             "database that places its sites (an origin, positions and timing offsets)")
        self.sync = None if frontend is None else SyncStage(frontend, self.config.sync, towers)
        self.timing = None if frontend is None else TimingStage(frontend, self.config.timing, self.sync.templates)
        self.fusion = FusionStage(towers, self.config.fusion, bias_map=bias_map) if fusing else None

    def reconfigure(self, config: PipelineConfig) -> None:
        """Run on with ``config`` (:meth:`PipelineConfig.reconfiguration`: only what needs no
        rebuilt state may change); ValueError leaves the pipeline as it was."""
        config.reconfiguration(self)()

    def process(self, chunk: EnvelopeChunk) -> list[StackResult]:
        """Feed one chunk; a result for every stack it completes."""
        if self.sync is None:
            raise ValueError("this pipeline has no front end, so no sync stage: it cannot take ADC chunks")
        return [StackResult(sync, self.time_stack(sync.stack_windows)) for sync in self.sync.process(chunk)]

    def time_stack(self, windows: StackWindows) -> TimedStack:
        """One stack's cells (what the sync stage, or a ``SyncWindowArray``, gives) through timing
        and fusion."""
        if self.timing is None:
            raise ValueError("this pipeline has no front end, so no timing stage: it cannot time windows")
        timing = self.timing.process(windows)
        arrivals = windows.arrivals(timing.cells)
        return TimedStack(windows, timing, arrivals, self.fuse_arrivals(arrivals))

    def fuse_arrivals(self, arrivals: StackArrivals) -> FusionResult | None:
        """One stack's arrivals (the timing stage's, or a ``CellTimingArray``'s) through fusion;
        None without a tower database that places its sites. Arrivals that say which stacks
        they came from (``StackArrivals.stack``) set ``config.sync.stack`` to those, and the
        tracker's overlap with it: a node that only fuses follows what the sync node used."""
        if self.fusion is None:
            return None
        stack = self.config.sync.stack
        if arrivals.stack is not None and arrivals.stack != (stack.n_frames, stack.hop):
            self.config = self.config.with_choices(*arrivals.stack)
            self.fusion.follow_stacks(self.config.fusion.tracker.stack_overlap)
        return self.fusion.process(arrivals)

    def pending_events(self) -> tuple[Health, ...]:
        """Stream events the sync stage has seen since its last completed stack, taken (a second
        call returns none): they travel with the next stack, so at the end of a stream (a gap or
        a reset in its last frames) this is the only place they are."""
        return () if self.sync is None else self.sync.take_events()

    def run(self, chunks: Iterable[EnvelopeChunk]) -> Iterator[StackResult]:
        """Results stack by stack as the chunks (a source's ``chunks()``, a bag) stream in."""
        for chunk in chunks:
            yield from self.process(chunk)


def places_sites(towers: TowerDatabase | None) -> bool:
    """Whether a tower database can anchor fixes: a map origin and a site with position and timing."""
    return towers is not None and towers.origin is not None and any(
        site.has_position and site.timing_offset_us is not None for site in towers.sites)
