"""``tdoa_fusion``: each stack's arrivals in, the receiver's position out.

Subscribes ``cell_timing`` (CellTimingArray) and runs the core's
:class:`~deepsync.fusion.stage.FusionStage` against the tower database; the fix (the tracker's
when it has one, else the stack's own snapshot) goes out on ``pose``
(PoseWithCovarianceStamped in ``map_frame``, reliable) and ``fix`` (NavSatFix in
``antenna_frame``), stamped with the stack's ADC time. A stack without a fix publishes no pose,
and on ``fix`` a NavSatFix saying ``STATUS_NO_FIX`` (``publish_no_fix``); the diagnostics say
why (too few sites, unknown PCIs, geometry, a lost track, ...), and list every cell heard
(``cells``); ``map_sites`` draws the database's sites for Foxglove's Map panel. A pose on
``/initialpose`` (RViz's "2D Pose Estimate") restarts the tracker from there: one heard site is
then enough. With ``use_gnss`` it takes ``gnss/fix`` (NavSatFix) as anchors, with
``use_odometry`` ``odometry`` (Odometry) as velocities (``deepsync_ros.aiding``); with
``learned_towers`` it writes what it learned of the sites to that file; with ``bias_map`` a
site bias map (``deepsync survey-map`` or ``trace-map``) corrects the sites' ranges. The tracker counts the
overlap of the stacks each ``CellTimingArray`` says it came from (``stack_frames`` /
``stack_hop_frames``: cell_sync's), the motion model's where a message does not say.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

from deepsync_msgs.msg import CellTimingArray

from deepsync.bag.topics import CELL_TIMING_TOPIC, relative_name
from deepsync.pipeline import Pipeline

from . import params
from .conversions import cell_timing_array_from_msg
from .health import CellTable, StageHealth
from .node_base import (
    RESULTS_QOS,
    AidingListener,
    DeepSyncNode,
    FixPublisher,
    InitialPoseListener,
    SitesMap,
    run,
)
from .params import ParamValue


class TdoaFusionNode(DeepSyncNode):
    NAME = "tdoa_fusion"
    SPECS = params.TDOA_FUSION

    def setup(self, values: Mapping[str, ParamValue]) -> None:
        towers = params.towers(values, self.NAME, required=True)
        bias_map = params.bias_map(values, self.NAME, towers)
        # fusion alone: it follows the stacks the arrivals say cell_sync used (Pipeline.fuse_arrivals)
        self.pipeline = Pipeline(None, params.fusing_config(values, self.NAME), towers, bias_map=bias_map)
        self.stage = self.pipeline.fusion
        self.health = StageHealth()
        self.cells = CellTable()
        self.fixes = FixPublisher(self, values)
        self.sites_map = SitesMap(self, towers, self.cells)
        self.initial_pose = InitialPoseListener(self, str(values["map_frame"]), self.stage,
                                                float(values["initial_pose_min_std_m"]))
        self.aiding = AidingListener(self, values, self.stage)
        self.subscription = self.create_subscription(CellTimingArray, relative_name(CELL_TIMING_TOPIC),
                                                     self._on_arrivals, RESULTS_QOS)
        self.add_diagnostic("position fix", self.health.report)
        self.add_diagnostic("cells", self.cells.report)
        self.get_logger().info(f"fixes against tower database {towers.name!r} ({len(towers.sites)} sites)"
                               + ("" if bias_map is None else f", bias map of {len(bias_map.sites)} sites "
                                  f"({bias_map.made_by})"))

    def _on_arrivals(self, message: CellTimingArray) -> None:
        arrived = time.monotonic()
        self.health.arrived(message.first_sample_index)
        try:
            arrivals = cell_timing_array_from_msg(message)
        except ValueError as error:
            self.reject(self.health, error)
            return
        started = time.monotonic()
        result = self.pipeline.fuse_arrivals(arrivals)
        stage_s = time.monotonic() - started
        fix = result.published
        try:
            self.fixes.publish(fix, arrivals.stamp_ns, self.stage.frame)
        except ValueError as error:
            self.reject(self.health, error)
        self.cells.heard(arrivals, result.sites)
        self.sites_map.update()
        self.aiding.stacked(arrivals.stamp_ns, result.events)
        self.health.stack([cell.pci for cell in arrivals.cells], events=result.events,
                          sites=[site.site for site in result.sites], fix=fix,
                          latency_s=time.monotonic() - arrived, stage_s=stage_s)

    def destroy_node(self) -> None:
        if hasattr(self, "aiding"):
            self.aiding.shutdown()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run(TdoaFusionNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
