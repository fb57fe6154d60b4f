"""``deepsync_pipeline``: the whole chain in one process, for a tracker too small to move ADC
samples through DDS.

Plays a source as ``envelope_adc`` does (same parameters, pacing and /clock) straight into
:class:`deepsync.pipeline.Pipeline`, and publishes what the separate nodes would: ``cell_timing``
for every stack, ``pose`` and ``fix`` for every stack with a fix. Without a tower database that
places its sites there is no fusion, and only ``cell_timing`` is published. A pose on
``/initialpose`` restarts the tracker from there, GNSS fixes and odometry aid it and the learned
tower database is written, and a ``bias_map`` corrects the sites' ranges, as in ``tdoa_fusion``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import replace

from deepsync_msgs.msg import CellTimingArray

from deepsync.bag.topics import CELL_TIMING_TOPIC, relative_name
from deepsync.pipeline import Pipeline
from deepsync.types import EnvelopeChunk

from . import params
from .conversions import cell_timing_array_to_msg
from .health import CellTable, StageHealth
from .playback import Playback
from .node_base import (
    RESULTS_QOS,
    AidingListener,
    DeepSyncNode,
    FixPublisher,
    InitialPoseListener,
    PacedPlayer,
    SitesMap,
    run,
)
from .params import ParameterError, ParamValue


class PipelineNode(DeepSyncNode):
    NAME = "deepsync_pipeline"
    SPECS = params.DEEPSYNC_PIPELINE

    def setup(self, values: Mapping[str, ParamValue]) -> None:
        towers = params.towers(values, self.NAME)
        bias_map = params.bias_map(values, self.NAME, towers)
        config = params.pipeline_config(values, self.NAME)
        source = params.source(values, self.NAME)
        try:
            self.pipeline = Pipeline(source.frontend, config, towers, bias_map=bias_map)
        except ValueError as error:  # no templates for the recording's front end (its rate)
            raise ParameterError(f"{self.NAME}.source: {error}") from None
        self.frame_id = str(values["frame_id"])
        self.health = StageHealth()
        self.playback = Playback(source, params.playback_config(values, self.NAME))
        self.timing_publisher = self.create_publisher(CellTimingArray, relative_name(CELL_TIMING_TOPIC), RESULTS_QOS)
        self.cells = CellTable()
        self.fixes = FixPublisher(self, values)
        self.sites_map = None if self.pipeline.fusion is None else SitesMap(self, towers, self.cells)
        self.initial_pose = InitialPoseListener(self, str(values["map_frame"]), self.pipeline.fusion,
                                                float(values["initial_pose_min_std_m"]))
        self.aiding = AidingListener(self, values, self.pipeline.fusion)
        self.updater.setHardwareID(str(values["source"]))  # the recording stands in for the ADC
        self.add_diagnostic("source", self.playback.report)
        self.add_diagnostic("localization", self.health.report)
        self.add_diagnostic("cells", self.cells.report)
        self.player = PacedPlayer(self, self.playback, self._process, bool(values["publish_clock"]))
        self.get_logger().info(f"running the chain on {source.description}")
        if self.pipeline.fusion is None:
            self.get_logger().warning("no tower database that places its sites (origin, positions, timing "
                                      "offsets): publishing cell_timing only, no pose")

    def prepare(self, values: Mapping[str, ParamValue]) -> Callable[[], None]:
        playback = params.playback_config(values, self.NAME)
        config = replace(self.pipeline.config, timing=params.timing_config(values, self.NAME))
        try:
            switch = config.reconfiguration(self.pipeline)
        except ValueError as error:  # a network that cannot be loaded: the running stage stays
            raise ParameterError(f"{self.NAME}.estimator: {error}") from None

        def apply() -> None:
            switch()
            self.playback.reconfigure(playback)
        return apply

    def _process(self, chunk: EnvelopeChunk, now_s: float) -> None:
        results = self.pipeline.process(chunk)
        stage_s = time.monotonic() - now_s
        self.playback.mark_published(chunk, now_s)
        for result in results:
            try:
                self.timing_publisher.publish(cell_timing_array_to_msg(result.arrivals, self.frame_id))
                if result.fusion is not None:
                    self.fixes.publish(result.fusion.published, result.stamp_ns, self.pipeline.fusion.frame)
            except ValueError as error:  # a stamp beyond what builtin_interfaces/Time holds
                self.reject(self.health, error)
            self.cells.heard(result.arrivals, () if result.fusion is None else result.fusion.sites)
            if self.sites_map is not None:
                self.sites_map.update()
            if result.fusion is not None:
                self.aiding.stacked(result.stamp_ns, result.fusion.events)
            self.health.result(result, latency_s=time.monotonic() - now_s, stage_s=stage_s)

    def destroy_node(self) -> None:
        if hasattr(self, "aiding"):
            self.aiding.shutdown()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run(PipelineNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
