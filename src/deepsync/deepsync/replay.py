"""Replay a recording through the whole chain into a bag of what the nodes publish.

``deepsync replay --bag B --towers T --out OUT`` runs the pipeline over B's envelope stream and
writes, per stack, the timing stage's arrivals (``/deepsync/cell_timing``, CellTimingArray) and
fusion's fix (``/deepsync/pose``, PoseWithCovarianceStamped in ``map``; ``/deepsync/fix``,
NavSatFix), stamped with the stack's ADC time, plus the ground truth pose if B has one. The
result plays with ``ros2 bag play`` (so robot_localization or Nav2 can consume the poses without
the nodes) and opens in Foxglove. The fix is the tracker's when it has one, else the snapshot's;
a stack with neither publishes no pose. Written atomically: an interrupted replay leaves nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from deepsync.bag import (
    CELL_TIMING_TOPIC,
    NAV_SAT_FIX_TOPIC,
    POSE_TOPIC,
    TRUTH_POSE_TOPIC,
    BagReader,
    BagWriter,
    cell_timing_array_to_msg,
    fix_to_navsat_msg,
    fix_to_pose_msg,
)
from deepsync.pipeline import Pipeline, PipelineConfig
from deepsync.sources import BagSource
from deepsync.towers import TowerDatabase
from deepsync.types import Fix


@dataclass(frozen=True)
class ReplaySummary:
    out: str
    stacks: int
    poses: int
    truth_poses: int


def replay_bag(source: BagSource, towers: TowerDatabase, out_dir: str | Path, config: PipelineConfig | None = None,
               *, overwrite: bool = False, progress: bool = True) -> ReplaySummary:
    """Replay ``source`` into the bag ``out_dir`` (see the module docstring)."""
    pipeline = Pipeline(source.frontend, config, towers)
    if pipeline.fusion is None:
        raise ValueError(f"tower database {towers.name!r} places no site (it needs an origin and sites with "
                         "position and timing offset): there would be no pose to publish")
    frame = pipeline.fusion.frame
    stacks = poses = truth = 0
    with BagWriter(out_dir, overwrite=overwrite, provenance=f"deepsync replay of {source.path}") as bag:
        bar = tqdm(total=source.n_chunks, unit="chunk", disable=not progress, desc="replay")
        for chunk in source.chunks():
            for result in pipeline.process(chunk):
                stacks += 1
                bag.write(CELL_TIMING_TOPIC, cell_timing_array_to_msg(result.arrivals, store=bag.store))
                fusion = result.fusion
                fix = fusion.tracked if isinstance(fusion.tracked, Fix) else fusion.snapshot
                if isinstance(fix, Fix):
                    bag.write(POSE_TOPIC, fix_to_pose_msg(fix, store=bag.store))
                    bag.write(NAV_SAT_FIX_TOPIC, fix_to_navsat_msg(fix, frame, store=bag.store))
                    poses += 1
            bar.update(1)
        bar.close()
        with BagReader(source.path) as recorded:
            if TRUTH_POSE_TOPIC in recorded.topics:
                for item in recorded.messages([TRUTH_POSE_TOPIC]):
                    bag.write(TRUTH_POSE_TOPIC, item.message)
                    truth += 1
    return ReplaySummary(str(out_dir), stacks, poses, truth)
