"""``cell_sync``: the ADC stream in, each stack's detected cells and their windows out.

Subscribes ``envelope`` (EnvelopeSamples, SensorDataQoS) and runs the core's
:class:`~deepsync.sync.stage.SyncStage`; every completed stack goes out on ``sync_windows``
(SyncWindowArray, reliable) with the stack's time base, stamped with its first sample's ADC time,
held until a reader has matched (``wait_for_subscribers_s``).
What is wrong with the stream (gaps, a restart, another sample rate, clipping, silence) is in the
diagnostics, never a crash.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

from deepsync_msgs.msg import EnvelopeSamples, SyncWindowArray

from deepsync.bag.topics import ENVELOPE_TOPIC, SYNC_WINDOWS_TOPIC, relative_name
from deepsync.sync.stage import SyncStage

from . import params
from .conversions import envelope_from_msg, sync_window_array_to_msg
from .health import StageHealth
from .node_base import ENVELOPE_SUBSCRIBER_QOS, RESULTS_QOS, DeepSyncNode, output_gate, run
from .params import ParameterError, ParamValue


class CellSyncNode(DeepSyncNode):
    NAME = "cell_sync"
    SPECS = params.CELL_SYNC

    def setup(self, values: Mapping[str, ParamValue]) -> None:
        towers = params.towers(values, self.NAME)
        frontend = params.frontend(values, self.NAME)
        config = params.sync_config(values, self.NAME)
        try:
            self.stage = SyncStage(frontend, config, towers)
        except ValueError as error:  # no templates for this front end (its ADC rate)
            raise ParameterError(f"{self.NAME}.frontend: {error}") from None
        self.frame_id = str(values["frame_id"])
        self.health = StageHealth()
        self.publisher = self.create_publisher(SyncWindowArray, relative_name(SYNC_WINDOWS_TOPIC), RESULTS_QOS)
        self.gate = output_gate(self)  # cell_timing may start later: hold the first stacks for it
        self.subscription = self.create_subscription(EnvelopeSamples, relative_name(ENVELOPE_TOPIC), self._on_envelope,
                                                     ENVELOPE_SUBSCRIBER_QOS)
        self.add_diagnostic("cell search", self.health.report)
        searched = "blind search" if towers is None else f"tower database {towers.name!r}"
        self.get_logger().info(f"cell search at {frontend.adc_rate_hz / 1e6:g} MS/s, {searched}")

    def _on_envelope(self, message: EnvelopeSamples) -> None:
        arrived = time.monotonic()
        try:
            chunk = envelope_from_msg(message)
        except ValueError as error:
            self.reject(self.health, error)
            return
        started = time.monotonic()
        results = self.stage.process(chunk)
        stage_s = time.monotonic() - started
        for result in results:
            try:
                out = sync_window_array_to_msg(result.stack_windows, self.frame_id)
            except ValueError as error:  # a stamp beyond what builtin_interfaces/Time holds
                self.reject(self.health, error)
            else:
                self.gate.publish(self.publisher, out)
            self.health.stack(result.pcis, events=result.events + result.flags,
                              latency_s=time.monotonic() - arrived, stage_s=stage_s)


def main(args: list[str] | None = None) -> int:
    return run(CellSyncNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
