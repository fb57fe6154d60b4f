"""``cell_timing``: each stack's cell windows in, sub-sample arrivals with an honest 1-sigma out.

Subscribes ``sync_windows`` (SyncWindowArray) and runs the core's
:class:`~deepsync.timing.stage.TimingStage`; the arrivals go out on ``cell_timing``
(CellTimingArray, reliable) on the stack's time base, stamped and framed as the windows came.
``estimator``, ``checkpoint``, ``weak_std_samples``, ``min_snr_db`` and how a smeared peak
widens an arrival's 1-sigma (``peak_width_allowance_samples``, ``smear_std_per_sample``) may
change while the node runs (an A/B comparison on live data).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping

from deepsync_msgs.msg import CellTimingArray, SyncWindowArray

from deepsync.bag.topics import CELL_TIMING_TOPIC, SYNC_WINDOWS_TOPIC, relative_name
from deepsync.timing.stage import TimingStage

from . import params
from .conversions import cell_timing_array_to_msg, sync_window_array_from_msg
from .health import StageHealth
from .node_base import RESULTS_QOS, DeepSyncNode, output_gate, run
from .params import ParameterError, ParamValue


class CellTimingNode(DeepSyncNode):
    NAME = "cell_timing"
    SPECS = params.CELL_TIMING

    def setup(self, values: Mapping[str, ParamValue]) -> None:
        frontend = params.frontend(values, self.NAME)
        config = params.timing_config(values, self.NAME)
        try:
            self.stage = TimingStage(frontend, config)
        except ValueError as error:  # no templates for this front end (its ADC rate), or no usable network
            parameter = "estimator" if config.estimator.uses_network else "frontend"
            raise ParameterError(f"{self.NAME}.{parameter}: {error}") from None
        self.health = StageHealth()
        self.publisher = self.create_publisher(CellTimingArray, relative_name(CELL_TIMING_TOPIC), RESULTS_QOS)
        self.gate = output_gate(self)  # tdoa_fusion may start later: hold the first stacks for it
        self.subscription = self.create_subscription(SyncWindowArray, relative_name(SYNC_WINDOWS_TOPIC),
                                                     self._on_windows, RESULTS_QOS)
        self.add_diagnostic("cell timing", self.health.report)

    def prepare(self, values: Mapping[str, ParamValue]) -> Callable[[], None]:
        try:
            stage = self.stage.with_config(params.timing_config(values, self.NAME))
        except ValueError as error:  # a network that cannot be loaded: the running stage stays
            raise ParameterError(f"{self.NAME}.estimator: {error}") from None

        def apply() -> None:
            self.stage = stage
        return apply

    def _on_windows(self, message: SyncWindowArray) -> None:
        arrived = time.monotonic()
        self.health.arrived(message.first_sample_index)
        try:
            stack = sync_window_array_from_msg(message)
            started = time.monotonic()
            result = self.stage.process(stack)
            stage_s = time.monotonic() - started
            out = cell_timing_array_to_msg(stack.arrivals(result.cells), message.header.frame_id)
        except ValueError as error:
            self.reject(self.health, error)
            return
        self.gate.publish(self.publisher, out)
        weak = tuple(flag for cell in result.cells for flag in cell.flags)
        self.health.stack([cell.pci for cell in result.cells], events=result.events + weak,
                          latency_s=time.monotonic() - arrived, stage_s=stage_s)


def main(args: list[str] | None = None) -> int:
    return run(CellTimingNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
