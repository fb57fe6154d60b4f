"""The rclpy side the five DeepSync nodes share: parameters, diagnostics, playback, startup.

A node subclasses :class:`DeepSyncNode` with its name and :mod:`deepsync_ros.params` specs,
and builds its stage, publishers and subscriptions in ``setup(values)``. Parameters are declared
with descriptors (description, range, read-only); a value the node cannot run with raises
:class:`~deepsync_ros.params.ParameterError` (or rclpy's own parameter exception for a wrong type
or a value out of range), and :func:`run` logs it as one line and exits 1: a launch file then
shows the cause instead of a traceback, and nothing restarts a node that cannot start.
Writable parameters are checked by the same builders when changed at runtime and refused with
the reason; what they need (a network to load) is built while they are checked, and applied only
once rclpy has set them (its post-set callback), so a set that another callback refuses leaves
the node as it was. Input that does not convert is counted, logged (throttled) and dropped.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from diagnostic_updater import DiagnosticStatusWrapper, Updater
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import NavSatFix

from deepsync.bag.convert import ns_to_stamp
from deepsync.bag.topics import (
    GNSS_FIX_TOPIC,
    INITIAL_POSE_TOPIC,
    MAP_SITES_TOPIC,
    NAV_SAT_FIX_TOPIC,
    ODOMETRY_TOPIC,
    POSE_TOPIC,
    relative_name,
)
from deepsync.fusion.stage import FusionStage
from deepsync.geo import LocalFrame
from deepsync.towers import TowerDatabase
from deepsync.numeric import one_blas_thread
from deepsync.types import EnvelopeChunk, Fix, HealthKind, NoFix, Severity

from .aiding import AidingInputs, LearnedTowers
from .conversions import (
    RCLPY_TYPES,
    fix_to_navsat_msg,
    fix_to_pose_msg,
    no_fix_to_navsat_msg,
    prior_from_pose_msg,
)
from .health import CellTable, Report, StageHealth, sites_geojson
from .playback import Playback, chunk_end_ns
from .params import ParameterError, ParamSpec, ParamValue, checked

# Reliable keeps a message from being lost on the wire, not from being overwritten: a keep-last
# queue of N drops the oldest when a burst of N+1 waits for a busy reader. At start-up a node's
# first stack takes a second or more (its first full search, building templates), and meanwhile
# the upstream node's stacks pile up: 100 holds 20 s of pedestrian stacks (5 Hz), 10 s of vehicle
# ones, 1 s of sliding stacks every frame (a sync_windows message is about 0.1 MB).
RESULTS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
"""Stacks, arrivals and fixes: every message counts, a start-up burst included."""
# SensorDataQoS (best effort, volatile) with 2 s of chunks instead of its 5: the first search
# takes about a second and later ones tens of ms, while chunks keep coming every 10 ms, and a
# chunk dropped from the reader's queue drops every stack that spans it.
ENVELOPE_SUBSCRIBER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200,
                                     reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
# What rclcpp's ClockQoS and rosbag2's player offer on /clock.
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
                       durability=DurabilityPolicy.VOLATILE)
CLOCK_TOPIC = "/clock"
# GNSS fixes and odometry: best effort takes a reliable publisher's messages too; 50 messages
# hold a second of 50 Hz odometry while a stack is being fused
AIDING_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.BEST_EFFORT,
                        durability=DurabilityPolicy.VOLATILE)

# Topics every node has that are not its data: a subscriber there says nothing about the data's.
_INFRASTRUCTURE_TOPICS = frozenset({"/parameter_events", "/rosout", "/diagnostics", CLOCK_TOPIC})
# How often a gate looks for subscribers; it opens one look after it sees one, so that the
# reliable writer has matched the reader the graph announced.
SUBSCRIBER_POLL_S = 0.05
# Most messages a gate holds; beyond, it opens (publishing beats holding without end).
MAX_HELD = 1000

REJECTION_LOG_PERIOD_S = 5.0
# Steady-clock pacing: the tick bounds how late a due chunk goes out; the burst bounds how long
# one callback publishes before the executor serves the others (diagnostics, parameters).
TICK_S = 0.002
BURST_S = 0.05

_LEVELS = {Severity.OK: DiagnosticStatus.OK, Severity.WARN: DiagnosticStatus.WARN,
           Severity.ERROR: DiagnosticStatus.ERROR}


def descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """The rcl_interfaces descriptor of a parameter spec."""
    described = ParameterDescriptor(description=spec.description, additional_constraints=spec.constraints,
                                    read_only=spec.read_only)
    if spec.range is not None and spec.type is float:
        described.floating_point_range = [FloatingPointRange(from_value=float(spec.range[0]),
                                                             to_value=float(spec.range[1]), step=0.0)]
    elif spec.range is not None and spec.type is int:
        described.integer_range = [IntegerRange(from_value=int(spec.range[0]), to_value=int(spec.range[1]), step=1)]
    return described


class DeepSyncNode(Node):
    """A node with DeepSync's parameter, diagnostics and bad-input conventions."""

    NAME: str
    SPECS: tuple[ParamSpec, ...]

    def __init__(self, **node_options: Any) -> None:
        """``node_options``: rclpy Node keywords (``parameter_overrides``, ``namespace``, ...)."""
        super().__init__(self.NAME, **node_options)
        self._prepared: tuple[dict[str, ParamValue], dict[str, ParamValue], Callable[[], None]] | None = None
        try:
            declared = {spec.name: self.declare_parameter(spec.name, spec.default, descriptor(spec)).value
                        for spec in self.SPECS}
            self.values = checked(self.SPECS, declared, self.NAME)
            self.updater = Updater(self)
            self.updater.setHardwareID("none")  # software: no device of its own
            self._diagnostics_on_steady_time()
            self.setup(self.values)
        except BaseException:
            self.destroy_node()
            raise
        if any(not spec.read_only for spec in self.SPECS):
            self.add_on_set_parameters_callback(self._on_set_parameters)
            self.add_post_set_parameters_callback(self._after_set_parameters)
        # rclpy keeps a value given for a name the node never declares (a parameters file, -p) and
        # says nothing, so a misspelt parameter would run at its default unnoticed: one warning
        # names them (rclpy has no public accessor of the overrides: Node._parameter_overrides)
        self.unknown_overrides = sorted(name for name in getattr(self, "_parameter_overrides", {})
                                        if not self.has_parameter(name))
        if self.unknown_overrides:
            self.get_logger().warning(f"ignored, not parameters of {self.NAME}: {', '.join(self.unknown_overrides)} "
                                      f"(its own: {', '.join(spec.name for spec in self.SPECS)})")

    def _diagnostics_on_steady_time(self) -> None:
        """diagnostic_updater's timer runs on the node's clock, which under ``use_sim_time`` (the
        launch file's default) is /clock: it would stand still before a bag plays, after it ends
        and whenever it pauses, and with it the very diagnostics that say so ("no stack yet",
        "end of source"). Its period runs on the steady clock instead."""
        timer = getattr(self.updater, "timer", None)  # the updater's own, on the node's clock
        if timer is not None:
            timer.cancel()
            self.destroy_timer(timer)
        self.updater.timer = self.create_timer(self.updater.period, self.updater.update,
                                               clock=Clock(clock_type=ClockType.STEADY_TIME))

    def setup(self, values: Mapping[str, ParamValue]) -> None:
        """Build the stage, publishers and subscriptions; ParameterError for a value it cannot use."""
        raise NotImplementedError

    def prepare(self, values: Mapping[str, ParamValue]) -> Callable[[], None]:
        """Check new values of the writable parameters and build what they need, changing
        nothing; ParameterError to refuse. Returns what applies them once they are set."""
        raise NotImplementedError

    def _ours(self, parameters: list[Parameter]) -> dict[str, ParamValue]:
        return {p.name: p.value for p in parameters if any(spec.name == p.name for spec in self.SPECS)}

    def _on_set_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        # rclpy's contract: an on-set callback validates and leaves the node alone (another one
        # may still refuse the set); the change waits for the post-set callback
        changed = self._ours(parameters)
        if not changed:  # another part of the node's (use_sim_time, diagnostic_updater.period)
            return SetParametersResult(successful=True)
        try:
            values = checked(self.SPECS, {**self.values, **changed}, self.NAME)
            self._prepared = (changed, values, self.prepare(values))
        except ParameterError as error:
            self._prepared = None
            return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, parameters: list[Parameter]) -> None:
        prepared, self._prepared = self._prepared, None
        # only what was prepared for exactly this set: one refused after our check left a stale one
        if prepared is not None and prepared[0] == self._ours(parameters):
            _, self.values, apply = prepared
            apply()

    def add_diagnostic(self, name: str, report: Callable[[], Report]) -> None:
        """A diagnostic_updater task publishing ``report()`` each update period."""
        def task(stat: DiagnosticStatusWrapper) -> DiagnosticStatusWrapper:
            level, message, values = report()
            stat.summary(_LEVELS[level], message)
            for key, value in values:
                stat.add(key, value)
            return stat
        self.updater.add(name, task)

    def reject(self, health: StageHealth, error: Exception) -> None:
        """An input message that failed conversion: counted in diagnostics, logged, dropped."""
        health.reject(error)
        self.get_logger().warning(f"input rejected ({health.rejected} so far): {error}",
                                  throttle_duration_sec=REJECTION_LOG_PERIOD_S)


class SubscriberGate:
    """Holds a node's output until one of ``publishers`` has a subscriber, for at most
    ``wait_s`` of steady time (then it opens anyway and says which topics nobody read): DDS
    hands a volatile message published before a reader has matched to no one, and the nodes
    of a launch start in any order. Messages given to :meth:`publish` meanwhile are kept, in
    order, and published when it opens; a player asks :attr:`open` before it plays."""

    def __init__(self, node: Node, publishers: list[Any], wait_s: float) -> None:
        self.node = node
        self.publishers = publishers
        self.wait_s = wait_s
        self.open = wait_s <= 0 or not publishers
        self.started_s = time.monotonic()
        self._seen = False
        self._held: list[tuple[Any, Any]] = []
        self.timer = None if self.open else node.create_timer(SUBSCRIBER_POLL_S, self._poll,
                                                              clock=Clock(clock_type=ClockType.STEADY_TIME))

    def publish(self, publisher: Any, message: Any) -> None:
        """``message`` on ``publisher`` now, or when the gate opens."""
        if self.open:
            publisher.publish(message)
            return
        self._held.append((publisher, message))
        if len(self._held) >= MAX_HELD:
            self._release(f"{MAX_HELD} messages held")

    def _poll(self) -> None:
        if any(publisher.get_subscription_count() > 0 for publisher in self.publishers):
            if self._seen:
                self._release(None)
            self._seen = True
        elif time.monotonic() - self.started_s >= self.wait_s:
            self._release(f"no subscriber after {self.wait_s:g} s (wait_for_subscribers_s)")

    def _release(self, why: str | None) -> None:
        self.open = True
        if self.timer is not None:
            self.timer.cancel()
            self.node.destroy_timer(self.timer)
            self.timer = None
        if why is not None:
            topics = ", ".join(publisher.topic_name for publisher in self.publishers)
            self.node.get_logger().warning(f"publishing on {topics}: {why}")
        held, self._held = self._held, []
        for publisher, message in held:
            publisher.publish(message)


def data_publishers(node: Node) -> list[Any]:
    """The node's publishers of its own data (not /parameter_events, /diagnostics, /clock)."""
    return [publisher for publisher in node.publishers if publisher.topic_name not in _INFRASTRUCTURE_TOPICS]


def output_gate(node: DeepSyncNode, publishers: list[Any] | None = None) -> SubscriberGate:
    """A :class:`SubscriberGate` over ``publishers`` (default: the node's data publishers made so
    far), waiting the node's ``wait_for_subscribers_s``."""
    return SubscriberGate(node, data_publishers(node) if publishers is None else publishers,
                          float(node.values["wait_for_subscribers_s"]))


# The map layer of the sites: late joiners (Foxglove opened later) get the latest at once.
LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


class SitesMap:
    """The tower database's sites on ``map_sites`` (``foxglove_msgs/msg/GeoJSON``, transient
    local) for Foxglove's Map panel, green while heard (:func:`~deepsync_ros.health.sites_geojson`),
    published again when that changes. Without foxglove_msgs the node runs on and says so once."""

    def __init__(self, node: Node, towers: TowerDatabase, cells: CellTable) -> None:
        self.towers = towers
        self.cells = cells
        self.shown: str | None = None
        try:
            from foxglove_msgs.msg import GeoJSON
        except ImportError:
            node.get_logger().info("foxglove_msgs does not import (sudo apt install ros-jazzy-foxglove-msgs): no "
                                   f"{relative_name(MAP_SITES_TOPIC)} layer for Foxglove's Map panel")
            self.publisher = None
            return
        self.message = GeoJSON
        self.publisher = node.create_publisher(GeoJSON, relative_name(MAP_SITES_TOPIC), LATCHED_QOS)
        self.update()

    def update(self) -> None:
        if self.publisher is None:
            return
        text = sites_geojson(self.towers, self.cells)
        if text != self.shown:
            self.publisher.publish(self.message(geojson=text))
            self.shown = text


class FixPublisher:
    """A stack's outcome: a fix on ``pose`` (PoseWithCovarianceStamped in ``map_frame``) and
    ``fix`` (NavSatFix in ``antenna_frame``, through the map origin ``frame``); a stack without
    one, with ``publish_no_fix``, a NavSatFix saying ``STATUS_NO_FIX``. Held, in order, until a
    reader of either topic has matched (``wait_for_subscribers_s``)."""

    def __init__(self, node: DeepSyncNode, values: Mapping[str, ParamValue]) -> None:
        self.map_frame = str(values["map_frame"])
        self.antenna_frame = str(values["antenna_frame"])
        self.no_fix = bool(values["publish_no_fix"])
        self.pose = node.create_publisher(PoseWithCovarianceStamped, relative_name(POSE_TOPIC), RESULTS_QOS)
        self.navsat = node.create_publisher(NavSatFix, relative_name(NAV_SAT_FIX_TOPIC), RESULTS_QOS)
        self.gate = output_gate(node, [self.pose, self.navsat])

    def publish(self, outcome: Fix | NoFix | None, stamp_ns: int, frame: LocalFrame) -> None:
        """The messages of one stack's outcome (None: no fusion ran), or ValueError (a stamp
        beyond builtin_interfaces/Time) and none."""
        if isinstance(outcome, Fix):
            pose = fix_to_pose_msg(outcome, self.map_frame)
            navsat = fix_to_navsat_msg(outcome, frame, self.antenna_frame)
            self.gate.publish(self.pose, pose)
            self.gate.publish(self.navsat, navsat)
        elif isinstance(outcome, NoFix) and self.no_fix:
            self.gate.publish(self.navsat, no_fix_to_navsat_msg(stamp_ns, self.antenna_frame))


class InitialPoseListener:
    """``/initialpose`` (PoseWithCovarianceStamped in ``map_frame``: RViz's "2D Pose Estimate",
    Nav2's initial pose) restarts the fusion stage's tracker from that position: where too few
    sites are heard to start alone (two sites give a hyperbola), one is then enough. No
    direction is taken as better known than ``min_std_m`` (RViz's tool claims 0.5 m). A pose in
    another frame, without a usable covariance, or for a node without a tracker is refused
    with the reason in the log (the node looks up no transforms)."""

    def __init__(self, node: DeepSyncNode, map_frame: str, fusion: FusionStage | None, min_std_m: float) -> None:
        self.node = node
        self.map_frame = map_frame
        self.fusion = fusion
        self.min_std_m = min_std_m
        self.subscription = node.create_subscription(PoseWithCovarianceStamped, INITIAL_POSE_TOPIC,
                                                     self._on_pose, RESULTS_QOS)

    def _on_pose(self, message: PoseWithCovarianceStamped) -> None:
        logger = self.node.get_logger()
        try:
            if message.header.frame_id.lstrip("/") != self.map_frame:
                raise ValueError(f"it is in frame {message.header.frame_id!r}, fixes are in {self.map_frame!r} "
                                 "(map_frame)")
            claimed = prior_from_pose_msg(message)
            if self.fusion is None:
                raise ValueError("this node runs no fusion (a tower database that places its sites is needed)")
            prior = claimed.widened(self.min_std_m)
            self.fusion.start_from(prior)
        except ValueError as error:
            logger.warning(f"initial pose refused: {error}")
            return
        east, north, _ = prior.position_enu
        spread = math.sqrt(prior.covariance[0, 0] + prior.covariance[1, 1])
        widened = (f"; it claimed {claimed.tightest_std_m:.2g} m, taken as at least {self.min_std_m:g} m "
                   "(initial_pose_min_std_m)" if prior is not claimed else "")
        logger.info(f"tracking starts again from the initial pose ({east:.1f}, {north:.1f}) m, {spread:.1f} m DRMS"
                    f"{widened}")


class AidingListener:
    """GNSS fixes (``gnss/fix``, with ``use_gnss``) and odometry (``odometry``, with
    ``use_odometry``) into a fusion stage through :class:`~deepsync_ros.aiding.AidingInputs`, its
    "aiding" diagnostics, and the learned tower database (``learned_towers``) written every
    ``learned_save_period_s`` of steady time and at shutdown. What is refused is logged
    (throttled) with the reason; the node runs on."""

    def __init__(self, node: DeepSyncNode, values: Mapping[str, ParamValue], fusion: FusionStage | None) -> None:
        self.node = node
        self.fusion = fusion
        path = str(values["learned_towers"])
        self.learned = LearnedTowers(path, float(values["learned_save_period_s"])) if path and fusion else None
        self.inputs = None if fusion is None else AidingInputs(
            fusion, map_frame=str(values["map_frame"]), antenna_frame=str(values["antenna_frame"]),
            gnss_frame=str(values["gnss_frame"]), odometry_min_std_mps=float(values["odometry_min_std_mps"]),
            odometry_timeout_s=float(values["odometry_timeout_s"]), use_gnss=bool(values["use_gnss"]),
            use_odometry=bool(values["use_odometry"]), learned=self.learned)
        if self.inputs is None:
            if values["use_gnss"] or values["use_odometry"] or path:
                node.get_logger().warning("use_gnss, use_odometry and learned_towers need fusion (a tower database "
                                          "that places its sites): ignored")
            return
        if values["use_gnss"]:
            self.gnss = node.create_subscription(NavSatFix, relative_name(GNSS_FIX_TOPIC),
                                                 self._taking(self.inputs.gnss), AIDING_QOS)
        if values["use_odometry"]:
            self.odometry = node.create_subscription(Odometry, relative_name(ODOMETRY_TOPIC),
                                                     self._taking(self.inputs.odometry), AIDING_QOS)
        if values["use_gnss"] or values["use_odometry"] or self.learned is not None:
            node.add_diagnostic("aiding", self.inputs.report)
        if self.learned is not None:
            self.timer = node.create_timer(1.0, self._save_when_due, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _taking(self, take: Callable[[Any], str | None]) -> Callable[[Any], None]:
        def callback(message: Any) -> None:
            refused = take(message)
            if refused is not None:
                self.node.get_logger().warning(f"aiding refused: {refused}", throttle_duration_sec=REJECTION_LOG_PERIOD_S)
        return callback

    def stacked(self, stamp_ns: int, events: tuple) -> None:
        """A stack was fused (see :meth:`AidingInputs.stacked`)."""
        if self.inputs is not None:
            self.inputs.stacked(stamp_ns, events)
            for event in events:
                if event.kind is HealthKind.AIDING_REFUSED:
                    self.node.get_logger().warning(f"aiding refused: {event.message}",
                                                   throttle_duration_sec=REJECTION_LOG_PERIOD_S)

    def _save_when_due(self) -> None:
        now = time.monotonic()
        if self.learned is not None and self.learned.due(now):
            self._save(now)

    def _save(self, now: float) -> None:
        error = self.learned.save(self.fusion, now)
        if error is not None:
            self.node.get_logger().error(error)

    def shutdown(self) -> None:
        """Write the learned database one last time (the node is going)."""
        if self.learned is not None:
            self._save(time.monotonic())


class PacedPlayer:
    """Plays a :class:`~deepsync_ros.playback.Playback` into ``consume`` from a steady-clock timer
    (a ROS-time timer would wait on the very /clock this player may publish), optionally
    publishing /clock at each chunk's end: the receiver time at which its last sample exists."""

    def __init__(self, node: DeepSyncNode, playback: Playback, consume: Callable[[EnvelopeChunk, float], None],
                 publish_clock: bool) -> None:
        self.node = node
        self.playback = playback
        self.consume = consume
        # the first chunk waits for a reader of what the node publishes (made before the player)
        self.gate = output_gate(node)
        self.clock_publisher = node.create_publisher(ClockMsg, CLOCK_TOPIC, CLOCK_QOS) if publish_clock else None
        self._pending: EnvelopeChunk | None = None
        self.timer = node.create_timer(TICK_S, self._tick, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _tick(self) -> None:
        if not self.gate.open:  # the pace starts with the first chunk played, not before
            return
        deadline = time.monotonic() + BURST_S
        while True:
            chunk = self._pending if self._pending is not None else self.playback.next_chunk()
            self._log_source_events()
            if chunk is None:
                if not self.playback.ended:  # a live source has nothing yet: the next tick looks again
                    return
                self.timer.cancel()
                self._log_end()
                return
            now = time.monotonic()
            if self.playback.due_in(chunk, now) > 0:
                self._pending = chunk
                return
            self._pending = None
            if self._publish_clock(chunk):
                self.consume(chunk, now)
            if now >= deadline:
                return

    def _publish_clock(self, chunk: EnvelopeChunk) -> bool:
        """/clock at the chunk's end (if asked); False for a chunk no ROS time can stamp."""
        if self.clock_publisher is None:
            return True
        try:
            message = ClockMsg(clock=ns_to_stamp(chunk_end_ns(chunk), RCLPY_TYPES))
        except ValueError as error:
            self.playback.mark_unpublishable(chunk, error)
            return False
        self.clock_publisher.publish(message)
        return True

    def _log_source_events(self) -> None:
        logger = self.node.get_logger()
        for event in self.playback.new_source_events:
            (logger.error if event.severity is Severity.ERROR else logger.warning)(str(event))
        self.playback.new_source_events.clear()

    def _log_end(self) -> None:
        logger = self.node.get_logger()
        if self.playback.error is not None:
            logger.error(f"source failed after {self.playback.published} chunks: {self.playback.error}")
        else:
            logger.info(f"end of source: {self.playback.published} chunks; diagnostics go on")


def run(node_class: type[DeepSyncNode], args: list[str] | None = None) -> int:
    """rclpy.init, build the node, spin until shutdown, BLAS on one thread all along
    (``deepsync.numeric.one_blas_thread``: several nodes share the computer's cores); 1 (after
    one error line) when the node cannot start with its parameters, else 0."""
    with one_blas_thread():
        return _spin(node_class, args)


def _spin(node_class: type[DeepSyncNode], args: list[str] | None) -> int:
    rclpy.init(args=args)
    try:
        node = node_class()
    except ParameterError as error:
        get_logger(node_class.NAME).error(str(error))
        rclpy.try_shutdown()
        return 1
    except ParameterException as error:  # rclpy's: a value of the wrong type or out of its range
        get_logger(node_class.NAME).error(f"{node_class.NAME}: invalid parameter: {error}")
        rclpy.try_shutdown()
        return 1
    except KeyboardInterrupt:
        rclpy.try_shutdown()
        return 0
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
