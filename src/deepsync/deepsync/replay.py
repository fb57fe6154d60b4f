"""Replay a bag through the chain's stages into a bag of what the nodes publish.

``deepsync replay --in B --out OUT`` reads B's envelope stream and writes, per stack, what each
node would publish: the sync stage's cells (``/deepsync/sync_windows``, SyncWindowArray), the
timing stage's arrivals (``/deepsync/cell_timing``, CellTimingArray) and fusion's fix
(``/deepsync/pose``, PoseWithCovarianceStamped in ``map``; ``/deepsync/fix``, NavSatFix), all
stamped with the stack's ADC time, plus B's ground truth. The fix is the tracker's when it has
one, else the snapshot's; a stack with neither publishes no pose. Offline and as fast as the
stages go, through :class:`~deepsync.pipeline.Pipeline` and the message conversions of
``deepsync.bag`` that the nodes use, so the bag holds what the nodes would have published. It
plays with ``ros2 bag play`` (robot_localization or Nav2 consume the poses without the nodes)
and opens in Foxglove.

The chain can start later, from a stage's output already in B: ``stages=("timing", "fusion")``
reads ``/deepsync/sync_windows``, ``("fusion",)`` reads ``/deepsync/cell_timing``. The stages
are a contiguous part of sync -> timing -> fusion; the first one's input topic must be in B.

Written atomically: an interrupted replay (Ctrl-C, SIGTERM, an error) leaves nothing. A damaged
B is the exception that still gives a bag: whatever can be read before the damage is replayed
(:class:`~deepsync.bag.SalvageReader` for a bag that cannot even be opened, cut short or with a
corrupt summary), the output holds everything produced from it, and
:attr:`ReplaySummary.damage` says where the reading stopped.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

import deepsync
from deepsync.bag import (
    CELL_TIMING_TOPIC,
    ENVELOPE_TOPIC,
    NAV_SAT_FIX_TOPIC,
    POSE_TOPIC,
    SYNC_WINDOWS_TOPIC,
    TRUTH_CELL_TIMING_TOPIC,
    TRUTH_POSE_TOPIC,
    BagError,
    BagMessage,
    BagReader,
    BagWriter,
    SalvageReader,
    cell_timing_array_from_msg,
    cell_timing_array_to_msg,
    envelope_from_msg,
    fix_to_navsat_msg,
    fix_to_pose_msg,
    provenance_document,
    sync_window_array_from_msg,
    sync_window_array_to_msg,
)
from deepsync.bag.convert import CELL_TIMING_ARRAY, ENVELOPE_SAMPLES, SYNC_WINDOW_ARRAY
from deepsync.frontend.config import FrontendConfig
from deepsync.fusion.bias_map import BiasMap
from deepsync.fusion.stage import FusionResult, answer_counts, sites_per_stack
from deepsync.pipeline import Pipeline, PipelineConfig, TimedStack, places_sites
from deepsync.sources.bagfile import bag_dir, check_same_frame, recorded_frontend
from deepsync.towers import TowerDatabase
from deepsync.types import FRAME_SECONDS, Fix, Health, NoFix, StackArrivals

STAGES = ("sync", "timing", "fusion")
STAGE_INPUT: dict[str, tuple[str, str]] = {
    "sync": (ENVELOPE_TOPIC, ENVELOPE_SAMPLES),
    "timing": (SYNC_WINDOWS_TOPIC, SYNC_WINDOW_ARRAY),
    "fusion": (CELL_TIMING_TOPIC, CELL_TIMING_ARRAY),
}
"""The topic (and its type) each stage reads, as its node subscribes to it."""
STAGE_OUTPUT: dict[str, tuple[str, ...]] = {
    "sync": (SYNC_WINDOWS_TOPIC,),
    "timing": (CELL_TIMING_TOPIC,),
    "fusion": (POSE_TOPIC, NAV_SAT_FIX_TOPIC),
}
TRUTH_TOPICS = (TRUTH_POSE_TOPIC, TRUTH_CELL_TIMING_TOPIC)


def parse_stages(text: str) -> tuple[str, ...]:
    """``"timing,fusion"`` -> ``("timing", "fusion")``; ValueError unless the names are a
    contiguous part of sync -> timing -> fusion, in that order."""
    names = tuple(name.strip() for name in text.split(","))
    unknown = [name for name in names if name not in STAGES]
    if unknown:
        raise ValueError(f"stages {text!r}: no stage {', '.join(map(repr, unknown))}; the stages are "
                         f"{', '.join(STAGES)}")
    first = STAGES.index(names[0])
    if names != STAGES[first:first + len(names)]:
        raise ValueError(f"stages {text!r}: give a contiguous part of the chain {' -> '.join(STAGES)}, in that "
                         "order (e.g. sync,timing,fusion or timing,fusion or fusion)")
    return names


@dataclass(frozen=True)
class ReplaySummary:
    """What a replay read, wrote and saw."""

    out: str
    stages: tuple[str, ...]  # the stages that ran (fusion left out when it could not)
    inputs: int  # messages the first stage read
    stacks: int  # stacks that went through timing (or fusion, when it was the first stage)
    written: dict[str, int]  # topic -> messages written
    health: dict[str, int]  # health kind -> how often the stages reported it
    fixes: dict  # the published answers (``answer_counts``): fix rate and no-fix reasons; empty without fusion
    sites_heard_per_stack: dict[str, int]  # ``sites_per_stack`` of the fused stacks
    notes: tuple[str, ...]  # what the user should know: a blind search, fusion skipped, unknown PCIs
    damage: str | None  # where and why reading the input stopped early (None: it was read to its end)
    signal_seconds: float  # of ADC stream the input covered
    wall_seconds: float  # reading, the stages and writing

    @property
    def poses(self) -> int:
        return self.written.get(POSE_TOPIC, 0)

    @property
    def realtime_factor(self) -> float:
        """Seconds of signal replayed per second of wall time."""
        return self.signal_seconds / self.wall_seconds if self.wall_seconds > 0 else float("inf")


def open_input(path: str | Path) -> tuple[BagReader | SalvageReader, str | None]:
    """The bag to replay, opened whole when it can be, else salvaged up to its damage, with
    why it could not be opened whole (None: it could). A path that is no MCAP bag at all, or
    one with nothing readable, gets the reader's own error."""
    where = bag_dir(path)
    bag = BagReader(where)
    try:
        bag.open()
        return bag, None
    except BagError as refused:
        try:
            salvage = SalvageReader(where)
        except BagError:
            raise refused from None
        if not salvage.topics:
            raise refused from None
        return salvage, str(refused)


def _provenance(recorded: str | None, path: Path, stages: Sequence[str], towers: TowerDatabase | None,
                frontend: FrontendConfig | None, bias_map: BiasMap | None) -> str:
    """The input's provenance (its truth: sites, origin) with what this replay did added, so
    the output bag can be replayed again and scored like the input."""
    try:
        document = dict(provenance_document(recorded, path))
    except BagError:  # the input's own, unreadable: this replay's provenance alone
        document = {}
    document["replay"] = {"input": str(path), "input_generator": document.get("generator"), "stages": list(stages),
                          "towers": None if towers is None else towers.name,
                          "bias_map": None if bias_map is None else bias_map.made_by}
    document["generator"] = f"deepsync {deepsync.__version__} replay"
    if frontend is not None:
        document["frontend"] = asdict(frontend)
    return json.dumps(document, sort_keys=True)


@dataclass
class _Replayer:
    """One replay's state: the stages (built on the first input message, which gives the rate
    when the bag does not say its front end), the output bag and the tallies."""

    bag: BagReader | SalvageReader
    out: BagWriter
    stages: tuple[str, ...]
    towers: TowerDatabase | None
    bias_map: BiasMap | None
    config: PipelineConfig
    on_stack: Callable[[TimedStack, Pipeline], None] | None
    pipeline: Pipeline | None = None
    inputs: int = 0
    stacks: int = 0
    cells: int = 0
    samples: int = 0
    sample_rate: float = 0.0
    stamps: list[int] = field(default_factory=list)
    written: Counter = field(default_factory=Counter)
    health: Counter = field(default_factory=Counter)
    unknown_pcis: set[int] = field(default_factory=set)
    invalid: list[str] = field(default_factory=list)
    answers: list[Fix | NoFix] = field(default_factory=list)  # what fusion published (or why not) per stack
    site_counts: list[int] = field(default_factory=list)  # sites fusion heard per stack

    def write(self, topic: str, message: Any) -> None:
        self.out.write(topic, message)
        self.written[topic] += 1

    def _pipeline(self, sample_rate: float) -> Pipeline:
        if self.pipeline is None:
            frontend = None if self.stages[0] == "fusion" else recorded_frontend(
                self.bag.provenance, sample_rate, self.bag.path)
            try:
                self.pipeline = Pipeline(frontend, self.config, self.towers, bias_map=self.bias_map)
            except ValueError as error:  # a rate the stages cannot serve: the whole replay stops, naming the bag
                raise ValueError(f"{self.bag.path}: {error}") from None
            self.out.set_provenance(_provenance(self.bag.provenance, self.bag.path, self.stages, self.towers,
                                                frontend, self.bias_map))
        return self.pipeline

    def _count(self, health: Sequence[Health]) -> None:
        self.health.update(h.kind.value for h in health)

    def feed(self, item: BagMessage) -> None:
        """One message of the first stage's input topic through the stages."""
        self.inputs += 1
        stage = self.stages[0]
        try:
            if stage == "sync":
                data = envelope_from_msg(item.message)
            elif stage == "timing":
                data = sync_window_array_from_msg(item.message)
            else:
                data = cell_timing_array_from_msg(item.message)
        except ValueError as error:  # a value no such message can hold: skipped, said, and counted
            self.invalid.append(f"{item.topic} at {item.log_time_ns} ns: {error}")
            return
        pipeline = self._pipeline(data.sample_rate)
        if stage == "sync":
            self.samples += len(data.samples)
            self.sample_rate = data.sample_rate
            for result in pipeline.process(data):
                self._count(result.sync.events + result.sync.flags)
                if "sync" in self.stages:
                    self.write(SYNC_WINDOWS_TOPIC, sync_window_array_to_msg(result.sync.stack_windows,
                                                                            store=self.out.store))
                self._timed(result.timed)
        elif stage == "timing":
            self._timed(pipeline.time_stack(data))
        else:
            self._fused(data, pipeline.fuse_arrivals(data))
            self.stacks += 1

    def _timed(self, timed: TimedStack) -> None:
        self.stacks += 1
        self.stamps.append(timed.stamp_ns)
        self.cells += len(timed.arrivals.cells)
        self._count(timed.timing.events + tuple(f for cell in timed.timing.cells for f in cell.flags))
        if "timing" in self.stages:
            self.write(CELL_TIMING_TOPIC, cell_timing_array_to_msg(timed.arrivals, store=self.out.store))
        if "fusion" in self.stages:
            self._fused(timed.arrivals, timed.fusion)
        if self.on_stack is not None:
            assert self.pipeline is not None
            self.on_stack(timed, self.pipeline)

    def _fused(self, arrivals: StackArrivals, fusion: FusionResult | None) -> None:
        if self.stages[0] == "fusion":
            self.stamps.append(arrivals.stamp_ns)
            self.cells += len(arrivals.cells)
        if fusion is None:
            return
        self._count(fusion.events)
        if self.towers is not None:
            self.unknown_pcis |= {cell.pci for cell in arrivals.cells} - set(self.towers.pcis)
        fix = fusion.published
        self.answers.append(fix)
        self.site_counts.append(len(fusion.sites))
        if isinstance(fix, Fix):
            assert self.pipeline is not None and self.pipeline.fusion is not None
            self.write(POSE_TOPIC, fix_to_pose_msg(fix, store=self.out.store))
            self.write(NAV_SAT_FIX_TOPIC, fix_to_navsat_msg(fix, self.pipeline.fusion.frame, store=self.out.store))


def _check_input(bag: BagReader | SalvageReader, stages: tuple[str, ...]) -> None:
    """The first stage's topic is in the bag, with the type that stage reads."""
    stage = stages[0]
    topic, wanted = STAGE_INPUT[stage]
    carried = bag.topics.get(topic)
    if carried is None:
        could = [",".join(STAGES[i:]) for i, s in enumerate(STAGES) if STAGE_INPUT[s][0] in bag.topics]
        hint = (f"; it could start at --stages {' or '.join(could)}" if could
                else "; it holds no topic any stage reads")
        raise BagError(f"{bag.path}: no {topic} ({wanted}), which the {stage} stage reads (the bag has "
                       f"{', '.join(sorted(bag.topics)) or 'no topics'}){hint}")
    if carried != wanted:
        raise BagError(f"{bag.path}: {topic} carries {carried}, but the {stage} stage reads {wanted} there")


def _check_output_apart(bag: str | Path, out_dir: str | Path) -> None:
    """ValueError where ``out_dir`` is the input bag's own directory: replaying into it, even
    with ``overwrite``, would replace the recording being read."""
    source = Path(bag)
    bag_dir = source if source.is_dir() else source.parent
    out = Path(out_dir)
    if out.exists() and bag_dir.exists() and out.resolve() == bag_dir.resolve():
        raise ValueError(f"{out_dir}: the output is the input bag {bag}; replaying into it would replace the "
                         "recording: choose another output directory")


def replay_bag(bag: str | Path, out_dir: str | Path, towers: TowerDatabase | None = None,
               config: PipelineConfig | None = None, *, stages: Sequence[str] = STAGES, copy_inputs: bool = False,
               overwrite: bool = False, progress: bool = True, say: Callable[[str], None] | None = None,
               on_stack: Callable[[TimedStack, Pipeline], None] | None = None,
               bias_map: BiasMap | None = None) -> ReplaySummary:
    """Replay ``bag`` through ``stages`` into the bag ``out_dir`` (see the module docstring).

    ``towers`` None: the cell search runs blind and fusion is left out. ``copy_inputs`` copies
    every input topic (the envelope too) beside the truth, except those the replay produces.
    ``bias_map`` corrects fusion's site ranges (refused where fusion does not run, or for a map
    made in another frame than ``towers``').
    ``say`` gets each note as it arises (a blind search, fusion skipped); ``on_stack`` every
    stack that went through timing, with its fusion, and the pipeline (what the demo scores). Raises BagError / ValueError, leaving
    nothing, for input it cannot start on (no such topic, a wrong type, a stage list that is no
    part of the chain, fusion alone without a database that places sites).
    """
    stages = parse_stages(",".join(stages))
    _check_output_apart(bag, out_dir)
    config = config or PipelineConfig()
    notes: list[str] = []

    def note(text: str) -> None:
        notes.append(text)
        if say is not None:
            say(text)

    started = time.perf_counter()
    source, refused = open_input(bag)
    try:
        if refused is not None:
            note(f"the input cannot be opened whole ({refused}); replaying what can be read of it from its start")
        _check_input(source, stages)
        if "fusion" in stages and not places_sites(towers):
            why = ("no tower database" if towers is None else
                   f"tower database {towers.name!r} places no site (it needs an origin and sites with position "
                   "and timing offset)")
            if stages == ("fusion",):
                raise ValueError(f"fusion alone, but {why}: there is nothing to replay")
            stages = stages[:-1]
            note(f"fusion skipped: {why}; no pose is published")
        if "fusion" in stages:  # the poses beside the copied truth, both in "map": one frame
            check_same_frame(source.provenance, bag, towers)
        if bias_map is not None:
            if "fusion" not in stages:
                raise ValueError(f"a bias map corrects fusion, which this replay does not run (stages "
                                 f"{','.join(stages)})")
            bias_map.check_database(towers)
        if stages[0] == "sync" and towers is None:
            note("no tower database: the cell search runs blind (all 504 PCIs)")
        produced = {topic for stage in stages for topic in STAGE_OUTPUT[stage]}
        copied = _copied_topics(source, stages, copy_inputs, produced, note)
        input_topic = STAGE_INPUT[stages[0]][0]
        with BagWriter(out_dir, overwrite=overwrite) as out:
            replayer = _Replayer(source, out, stages, towers, bias_map, config, on_stack)
            out.set_provenance(_provenance(source.provenance, source.path, stages, towers, None, bias_map))
            total = source.message_counts.get(input_topic) if isinstance(source, BagReader) else None
            bar = tqdm(total=total, unit="msg", disable=not progress, desc="replay")
            damage = None
            messages = source.messages(sorted(copied | {input_topic}), skipped=replayer.invalid.append)
            try:
                while True:
                    try:
                        item = next(messages, None)
                    except BagError as error:  # a corrupt chunk met while reading: what came before it stands
                        damage = str(error)
                        break
                    if item is None:
                        break
                    if item.topic == input_topic:
                        replayer.feed(item)
                        bar.update(1)
                    if item.topic in copied:
                        replayer.write(item.topic, item.message)
            finally:
                bar.close()
            if isinstance(source, SalvageReader):
                damage = source.damage
            if replayer.pipeline is not None:
                replayer._count(replayer.pipeline.pending_events())
    finally:
        if isinstance(source, BagReader):
            source.close()
    _closing_notes(replayer, note)
    return ReplaySummary(
        out=str(out_dir), stages=stages, inputs=replayer.inputs, stacks=replayer.stacks,
        written=dict(replayer.written), health=dict(replayer.health.most_common()),
        fixes=answer_counts(replayer.answers) if replayer.answers else {},
        sites_heard_per_stack=sites_per_stack(replayer.site_counts), notes=tuple(notes),
        damage=damage, signal_seconds=_signal_seconds(replayer, config), wall_seconds=time.perf_counter() - started)


def _copied_topics(source: BagReader | SalvageReader, stages: tuple[str, ...], copy_inputs: bool,
                   produced: set[str], note: Callable[[str], None]) -> set[str]:
    """The truth, and with ``copy_inputs`` every input topic, less what the replay produces."""
    wanted = set(source.topics) if copy_inputs else {t for t in TRUTH_TOPICS if t in source.topics}
    replaced = sorted(wanted & produced)
    if replaced:
        note(f"the input's {', '.join(replaced)} replaced by what this replay produces")
    store = source.store
    # a message is written at its header's stamp: types DeepSync cannot decode, or without a
    # header (tf2_msgs/TFMessage), cannot be copied by this writer
    left = sorted(t for t in wanted - produced if source.topics[t] not in store.types or not any(
        name == "header" and kind[1] == "std_msgs/msg/Header" for name, kind in store.fielddefs[source.topics[t]][1]))
    if left:
        note("not copied (a type DeepSync cannot decode, or without a std_msgs/Header): "
             + ", ".join(f"{t} ({source.topics[t]})" for t in left))
    return wanted - produced - set(left)


def _closing_notes(replayer: _Replayer, note: Callable[[str], None]) -> None:
    """What the tallies say a user should know."""
    for problem in replayer.invalid[:3]:
        note(f"skipped a message no stage can take: {problem}")
    if len(replayer.invalid) > 3:
        note(f"... and {len(replayer.invalid) - 3} more such messages")
    towers = replayer.towers
    if towers is not None and replayer.stages[0] == "sync" and replayer.stacks and not replayer.cells:
        note(f"no cell of tower database {towers.name!r} was found in {replayer.stacks} stacks: if it is not the "
             "database of this place, replay without --towers (a blind search) to see which PCIs are on the air")
    if replayer.unknown_pcis:
        note(f"heard but not in tower database {towers.name!r}, so left out of the fixes: PCI "
             + ", ".join(map(str, sorted(replayer.unknown_pcis))))


def _signal_seconds(replayer: _Replayer, config: PipelineConfig) -> float:
    """Seconds of ADC stream the input covered: its samples, or the span of its stacks."""
    if replayer.samples:
        return replayer.samples / replayer.sample_rate
    if not replayer.stamps:
        return 0.0
    return (max(replayer.stamps) - min(replayer.stamps)) * 1e-9 + config.sync.stack.n_frames * FRAME_SECONDS
