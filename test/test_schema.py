"""One parameter schema (deepsync.schema): settings checked from their fields, derived stacks
carried by the messages, Pipeline.reconfigure keeping its config true, bags of an older
definition read on."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from deepsync.bag import TRUTH_CELL_TIMING_TOPIC, BagReader
from deepsync.bag.convert import (cell_timing_array_from_msg, cell_timing_array_to_msg, sync_window_array_from_msg,
                                  sync_window_array_to_msg)
from deepsync.pipeline import Pipeline, PipelineConfig
from deepsync.sources import BagSource
from deepsync.sync.search import SearchConfig
from deepsync.sync.stacking import StackConfig
from deepsync.timing.registry import Estimator
from deepsync.towers import load_tower_database
from deepsync.types import StackArrivals

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "campus"
TOWERS = REPO / "config" / "towers" / "campus.yaml"


@pytest.mark.parametrize("build, says", [
    (lambda: StackConfig(n_frames=0), "n_frames must be within [1, 1000] frames, got 0"),
    (lambda: SearchConfig(false_alarm_rate=0.5), "false_alarm_rate must be within (0, 0.5), got 0.5"),
    (lambda: SearchConfig(full_code_timing=1), "full_code_timing must be true or false"),
    (lambda: PipelineConfig().with_choices(search_every=0), "search_every must be within [1, 100000] stacks"),
    (lambda: PipelineConfig().with_choices(estimator="neural"), "estimator must be one of"),
    (lambda: PipelineConfig().with_choices(no_such_setting=1), "no stage config has such a setting"),
])
def test_a_setting_is_checked_from_its_field(build, says):
    with pytest.raises(ValueError) as refused:
        build()
    assert says in str(refused.value)


def test_with_choices_reaches_every_stage_by_field_name():
    config = PipelineConfig().with_choices(n_frames=20, hop_frames=5, estimator="ml", max_std_m=90.0,
                                           receiver_height_m=2.0)
    assert config.timing.estimator is Estimator.named("ml")
    assert config.fusion.tracker.max_std_m == 90.0
    assert config.fusion.tracker.snapshot.receiver_height_m == 2.0  # fusion keeps the tracker's in step
    assert config.fusion.tracker.stack_overlap == 4.0


def test_the_stacks_travel_with_the_windows_and_a_fusing_pipeline_follows_them():
    source = BagSource(BAG)
    towers = load_tower_database(TOWERS)
    config = PipelineConfig().with_choices(n_frames=20, hop_frames=10)
    results = list(Pipeline(source.frontend, config, towers).run(source.chunks()))
    windows = results[-1].sync.stack_windows
    assert windows.stack == (20, 10) and results[-1].arrivals.stack == (20, 10)
    assert sync_window_array_from_msg(sync_window_array_to_msg(windows)).stack == (20, 10)
    message = cell_timing_array_to_msg(results[-1].arrivals)
    assert (message.stack_frames, message.stack_hop_frames) == (20, 10)
    fusing = Pipeline(None, PipelineConfig(), towers)  # the motion model's stacks: 100 every 20
    assert fusing.config.fusion.tracker.stack_overlap == 5.0
    fusing.fuse_arrivals(cell_timing_array_from_msg(message))
    assert fusing.config.sync.stack.n_frames == 20 and fusing.config.sync.stack.hop == 10
    assert fusing.config.fusion.tracker.stack_overlap == 2.0 == fusing.fusion.tracker.config.stack_overlap


def test_a_message_that_does_not_say_its_stacks_leaves_them_and_a_bad_one_is_refused():
    towers = load_tower_database(TOWERS)
    fusing = Pipeline(None, PipelineConfig(), towers)
    fusing.fuse_arrivals(StackArrivals(0, 0, 1.92e6, ()))
    assert fusing.config == PipelineConfig()
    message = cell_timing_array_to_msg(StackArrivals(0, 0, 1.92e6, (), stack=(10, 10)))
    message.stack_hop_frames = 11
    with pytest.raises(ValueError, match="stack_hop_frames 11"):
        cell_timing_array_from_msg(message)


def test_a_bag_recorded_before_the_stacks_were_said_reads_on_with_them_unsaid():
    with BagReader(BAG) as bag:  # its ground truth is a CellTimingArray without stack_frames
        first = next(bag.messages([TRUTH_CELL_TIMING_TOPIC]))
    assert first.message.stack_frames == first.message.stack_hop_frames == 0
    assert cell_timing_array_from_msg(first.message).stack is None


def test_reconfigure_swaps_the_timing_stage_and_keeps_the_config_true():
    source = BagSource(BAG)
    pipeline = Pipeline(source.frontend, PipelineConfig())
    sync = pipeline.sync
    config = replace(pipeline.config, timing=replace(pipeline.config.timing, estimator=Estimator.named("parabolic")))
    pipeline.reconfigure(config)
    assert pipeline.config.timing.estimator.name == "parabolic" == pipeline.timing.config.estimator.name
    assert pipeline.sync is sync
    with pytest.raises(ValueError, match="the sync and fusion settings cannot change"):
        pipeline.reconfigure(config.with_choices(n_frames=10))
    assert pipeline.config == config
