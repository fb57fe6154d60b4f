"""``envelope_adc``: a recording (or the live simulator) as the ADC stream on ``envelope``.

Publishes ``deepsync_msgs/EnvelopeSamples`` with SensorDataQoS, one chunk per LTE frame, stamped
with the chunks' own ADC sample times; paced by those stamps on a steady clock (``realtime``,
``rate``), looped into one continuous stream (``loop``), and, with ``publish_clock``, driving
/clock for nodes that run on simulated time. Diagnostics: chunks published, real-time factor,
lag, "cannot keep up with real time", end of source.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from deepsync_msgs.msg import EnvelopeSamples
from rclpy.qos import qos_profile_sensor_data

from deepsync.bag.topics import ENVELOPE_TOPIC, relative_name
from deepsync.types import EnvelopeChunk

from . import params
from .conversions import envelope_to_msg
from .playback import Playback
from .node_base import REJECTION_LOG_PERIOD_S, DeepSyncNode, PacedPlayer, run
from .params import ParamValue


class EnvelopeAdcNode(DeepSyncNode):
    NAME = "envelope_adc"
    SPECS = params.ENVELOPE_ADC

    def setup(self, values: Mapping[str, ParamValue]) -> None:
        source = params.source(values, self.NAME)
        self.playback = Playback(source, params.playback_config(values, self.NAME))
        self.frame_id = str(values["frame_id"])
        self.publisher = self.create_publisher(EnvelopeSamples, relative_name(ENVELOPE_TOPIC), qos_profile_sensor_data)
        self.updater.setHardwareID(str(values["source"]))  # the recording stands in for the ADC
        self.add_diagnostic("source", self.playback.report)
        self.player = PacedPlayer(self, self.playback, self._publish, bool(values["publish_clock"]))
        self.get_logger().info(f"publishing {source.description}")

    def prepare(self, values: Mapping[str, ParamValue]) -> Callable[[], None]:
        playback = params.playback_config(values, self.NAME)
        return lambda: self.playback.reconfigure(playback)

    def _publish(self, chunk: EnvelopeChunk, now_s: float) -> None:
        try:
            message = envelope_to_msg(chunk, self.frame_id)
        except ValueError as error:  # a stamp beyond what builtin_interfaces/Time holds
            self.playback.mark_unpublishable(chunk, error)
            self.get_logger().error(f"chunk not published: {error}", throttle_duration_sec=REJECTION_LOG_PERIOD_S)
            return
        self.publisher.publish(message)
        self.playback.mark_published(chunk, now_s)


def main(args: list[str] | None = None) -> int:
    return run(EnvelopeAdcNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
