"""Every node's parameters, and what their values become: core configs, a source, a database.

Pure Python (no rclpy): the nodes declare :class:`ParamSpec` s through rcl_interfaces
descriptors and hand the values they get to the builders here, which the tests run without ROS.
A value the core's own configs refuse is reported as :class:`ParameterError` naming the
parameter, ``cell_sync.towers: no such file 'x.yaml'``: each parameter is first tried alone
against the defaults, so the core's message (which names its field) is pinned to the parameter
that caused it, and only what no single value explains is reported for the node.

Descriptor ranges are what ``ros2 param describe`` shows and rclpy enforces; the builders check
them too, so a value refused here is refused the same way with or without ROS. A range is
inclusive, so an open bound (``false_alarm_rate`` in (0, 0.5)) is left to the core's check.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from deepsync.bag.convert import ANTENNA_FRAME_ID, ENVELOPE_FRAME_ID, MAP_FRAME_ID
from deepsync.configio import build_dataclass, load_yaml
from deepsync.frontend.config import FRONTEND_RANGES, FrontendConfig
from deepsync.fusion.snapshot import SnapshotConfig
from deepsync.fusion.stage import FusionConfig
from deepsync.fusion.tracker import TrackerConfig
from deepsync.motion import DEFAULT_MOTION, MOTION_MODELS, motion_model
from deepsync.pipeline import PipelineConfig, moving, places_sites
from deepsync.sources import SampleFormat, Source, bag_frontend, open_source
from deepsync.sources.address import is_live_address
from deepsync.sources.bagfile import is_bag_path
from deepsync.sync.search import SearchConfig
from deepsync.sync.stacking import StackConfig
from deepsync.sync.stage import SyncConfig
from deepsync.timing.stage import Estimator, TimingConfig
from deepsync.towers import TowerDatabase, load_tower_database

from .health import PlaybackConfig

ParamValue = bool | int | float | str
T = TypeVar("T")


_KINDS = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


class ParameterError(ValueError):
    """A parameter value the node cannot run with; the message starts with ``node.parameter``."""


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: its name, default (whose type is the parameter's), what it means, the
    inclusive range of a number, the values a string may take, and whether it may change
    while the node runs (``read_only``: the stage it configures is built once)."""

    name: str
    default: ParamValue
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = True

    @property
    def type(self) -> type:
        return type(self.default)

    @property
    def constraints(self) -> str:
        """The rule a person reads in ``ros2 param describe``."""
        if self.choices:
            return "one of: " + ", ".join(repr(choice) for choice in self.choices)
        if self.range is not None:
            return f"{self.range[0]:g} to {self.range[1]:g}"
        return ""

    def check(self, value: object, node: str) -> ParamValue:
        """``value`` as this parameter's type, or ParameterError: wrong type, out of range, not a choice."""
        where = f"{node}.{self.name}"
        kind = self.type
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if type(value) is not kind:
            raise ParameterError(f"{where}: expected {_KINDS[kind]}, got {value!r}")
        if kind is float and not math.isfinite(value):
            raise ParameterError(f"{where}: must be a finite number, got {value!r}")
        if self.range is not None and not self.range[0] <= value <= self.range[1]:
            raise ParameterError(f"{where}: {value!r} is outside {self.constraints}")
        if self.choices and value not in self.choices:
            raise ParameterError(f"{where}: {value!r} is not {self.constraints}")
        return value


# --- the specs -----------------------------------------------------------------------------

_STACK = StackConfig()
_SEARCH = SearchConfig()
_SYNC = SyncConfig()
_TIMING = TimingConfig()
_FUSION = FusionConfig()
_TRACKER = TrackerConfig()
_SNAPSHOT = SnapshotConfig()

MOTION = ParamSpec("motion", DEFAULT_MOTION, "How the receiver moves: it sets the stacks (unless n_frames and "
                   "hop_frames are given) and the tracker's motion model. " + "; ".join(
                       f"{m.name}: {m.summary} ({m.n_frames}-frame stacks every {m.hop_frames})"
                       for m in MOTION_MODELS.values()) + ".", choices=tuple(MOTION_MODELS))

SOURCE = (
    ParamSpec("source", "", "Recording to publish: a rosbag2 bag (directory or .mcap), a SigMF recording, a raw "
              "I/Q or envelope file, or a scenario YAML (the live simulator); or a live receiver: "
              "rtl_tcp://HOST:PORT?freq=HZ, tcp://HOST:PORT, a serial device, soapy://DRIVER?freq=HZ "
              "(docs/live_receivers.md). Required."),
    ParamSpec("sample_format", "", "Sample format of a raw file or a tcp/serial stream; empty: from its extension "
              "or metadata (rtl_tcp: cu8).", choices=("", *(f.value for f in SampleFormat))),
    ParamSpec("sample_rate", 0.0, "Sample rate of a raw file or a live stream [Hz]; 0: from the recording "
              "(rtl_tcp, soapy: 1.92e6).",
              range=(0.0, FRONTEND_RANGES["adc_rate_hz"][1])),
    ParamSpec("realtime", True, "Pace the chunks by their stamps on a steady clock (true) or publish them as "
              "fast as they come (false).", read_only=False),
    ParamSpec("rate", 1.0, "Playback speed: 1 = real time, 2 = twice as fast (with realtime).",
              range=(0.01, 100.0), read_only=False),
    ParamSpec("loop", False, "At the end, start over as one continuous stream (sample indices and stamps go on).",
              read_only=False),
    ParamSpec("publish_clock", False, "Publish /clock (rosgraph_msgs/Clock) from the ADC stamps, for nodes "
              "running with use_sim_time."),
)
SOURCE_FRAME = ParamSpec("frame_id", ENVELOPE_FRAME_ID, "frame_id of the stream's headers (the ADC's frame).")

TOWERS = ParamSpec("towers", "", "Tower database YAML; empty: blind search over all 504 PCIs (and no fix).")
FRONTEND = ParamSpec("frontend", "", "Receiver chain the stream went through, for the templates: a bag "
                     "(its recorded front end), a YAML of FrontendConfig fields, or empty: the default chain.")
SYNC = (
    ParamSpec("n_frames", 0, "LTE frames (10 ms) stacked per search; 0: the motion model's. Longer stacks hear "
              "weaker sites (3 dB per doubling); the timing stage needs 2 to measure the noise.", range=(0, 1000)),
    ParamSpec("hop_frames", 0, "Frames from one stack's start to the next; 0: the motion model's, or with n_frames "
              "given, n_frames (back to back). Fewer gives sliding stacks: n_frames 100, hop_frames 20 hears as 100 "
              "frames do and answers at 5 Hz.", range=(0, 1000)),
    ParamSpec("clock_ppm", _STACK.clock_ppm, "Initial receiver clock error, compensated [ppm].",
              range=FRONTEND_RANGES["clock_offset_ppm"][:2]),
    ParamSpec("track_clock", _STACK.track_clock, "Follow the receiver clock drift measured on each stack."),
    ParamSpec("confirm_stacks", _SYNC.confirm_stacks, "Stacks in a row a cell must be found in, where its code "
              "should be, before it is reported.", range=(1, 100)),
    ParamSpec("search_every", _SYNC.search_every, "Stacks per full search for new cells; between, the cells "
              "found are only tracked where their codes should be (a few templates instead of dozens). 1 (with "
              "max_search_interval_s 0): every stack.", range=(1, 1000)),
    ParamSpec("max_search_interval_s", _SYNC.max_search_interval_s, "While full searches find no new cell, the gap "
              "between them doubles up to this much stream [s]; one that finds a cell brings it back to "
              "search_every. 0: every search_every stacks.", range=(0.0, 3600.0)),
    ParamSpec("hold_stacks", _SYNC.hold_stacks, "Stacks a confirmed cell is still looked for after a stack it "
              "was missed in (a fade).", range=(0, 100)),
    ParamSpec("report_z", _SYNC.report_z, "A confirmed cell found below this many sigmas is kept tracked but not "
              "reported: below about 5 the timing breaks down (arrivals a sample or more off).", range=(0.0, 100.0)),
    ParamSpec("false_alarm_rate", _SEARCH.false_alarm_rate, "Chance of a false timing peak anywhere in one stack.",
              range=(0.0, 0.5)),
    ParamSpec("max_cells", _SEARCH.max_cells, "Most cells searched for per stack.", range=(1, 64)),
    ParamSpec("full_code_timing", _SEARCH.full_code_timing, "With a tower database, time known cells by their "
              "whole codes (about +9 dB, slower)."),
    ParamSpec("crs_cancel_z", _SEARCH.crs_cancel_z, "A cell found this many sigmas out also has its CRS cancelled "
              "before weaker cells are sought: over long stacks a strong cell's CRS passes for other cells' codes. "
              "0: never.", range=(0.0, 1000.0)),
    ParamSpec("hold_by_frame", _SEARCH.hold_by_frame, "Hold a confirmed cell of known bandwidth whose codes a "
              "stack misses if its whole known frame (codes and CRS) is there."),
    ParamSpec("learn_bandwidths", _SYNC.learn_bandwidths, "Learn the bandwidth of confirmed cells the tower "
              "database gives none from their stacks."),
)
TIMING = (
    ParamSpec("estimator", _TIMING.estimator.name, "Sub-sample timing estimator.",
              choices=Estimator.names(), read_only=False),
    ParamSpec("weak_std_samples", _TIMING.weak_std_samples, "Flag an arrival whose 1-sigma exceeds this "
              "[samples] (1 sample = 156 m at 1.92 MS/s).", range=(0.0, 1e3), read_only=False),
    ParamSpec("checkpoint", "", "Timing-network checkpoint for estimator network; empty: the one shipped with "
              "deepsync.", read_only=False),
)
FUSION = (
    ParamSpec("tracking", _FUSION.track, "Run the tracker besides the snapshot solver; the published fix is the "
              "tracker's when it has one."),
    ParamSpec("max_track_std_m", _TRACKER.max_std_m, "Horizontal 1-sigma (DRMS) beyond which the track is "
              "reported lost and no pose is published for it [m].", range=(1.0, 1e6)),
    ParamSpec("bias_decorrelation_m", _TRACKER.bias_decorrelation_m, "Path over which a site's NLOS range bias "
              "changes (fades to 1/e) [m]: 38.901 UMa's delay-spread correlation distance is 40 m NLOS, UMi's "
              "10 m.", range=(1.0, 1e6)),
    ParamSpec("gnss_std_m", _FUSION.gnss_std_m, "Horizontal 1-sigma of a GNSS fix that states no covariance "
              "[m].", range=(0.01, 1e4)),
    ParamSpec("gnss_min_std_m", _FUSION.gnss_min_std_m, "No GNSS fix is taken as better than this per axis [m] "
              "(urban multipath a receiver's own covariance does not see).", range=(0.01, 1e4)),
    ParamSpec("multipath_std_m", _FUSION.multipath_std_m, "Range bias multipath and NLOS add to a site, beyond "
              "the timing sigma [m].", range=(0.0, 1e4)),
    ParamSpec("min_std_m", _FUSION.min_std_m, "Floor of each arrival's 1-sigma: the scatter multipath adds "
              "from stack to stack on the move [m].", range=(0.0, 1e4)),
    ParamSpec("receiver_height_m", _SNAPSHOT.receiver_height_m, "Antenna height above the map origin's ground "
              "in a 2-D fix [m].", range=(-500.0, 1e4)),
)
AIDING = (
    ParamSpec("use_gnss", False, "Take GNSS fixes (sensor_msgs/NavSatFix on gnss/fix) as anchors: each makes the "
              "heard sites' biases observable, and the tracker carries them on."),
    ParamSpec("gnss_frame", "", "Accept only NavSatFix messages in this frame_id; empty: any frame but the "
              "node's own antenna_frame (its own output fed back)."),
    ParamSpec("use_odometry", False, "Take odometry (nav_msgs/Odometry on odometry: a robot's wheel or visual "
              "odometry) as a velocity measurement; its frame's yaw and scale error are estimated."),
    ParamSpec("odometry_min_std_mps", 0.05, "No odometry velocity is taken as better than this per axis [m/s] "
              "(and one that states no covariance is taken with this).", range=(1e-4, 100.0)),
    ParamSpec("odometry_timeout_s", 1.0, "Odometry older than this is stale: the diagnostics say the tracker "
              "runs on its motion model alone [s].", range=(0.01, 3600.0)),
    ParamSpec("learned_towers", "", "Write what the tracker learned of each site (its range bias and clock) as a "
              "tower database to this YAML file, atomically, every learned_save_period_s and on shutdown; a next "
              "run can start from it (towers). Empty: not written."),
    ParamSpec("learned_save_period_s", 300.0, "Seconds between writes of learned_towers.", range=(1.0, 86400.0)),
)
"""What the fusion nodes take besides the arrivals, and where they write what they learn."""
STACK_OVERLAP = ParamSpec("stack_overlap", 0.0, "Stacks each ADC frame is in: cell_sync's n_frames / hop_frames "
                          "(sliding stacks share frames, so their timing noise repeats); the tracker counts each "
                          "arrival's timing variance that many times. 0: the motion model's stacks' "
                          "(deepsync_pipeline derives it).", range=(0.0, 1000.0))
INITIAL_POSE_MIN_STD = ParamSpec("initial_pose_min_std_m", 10.0, "Least 1-sigma an initial pose on /initialpose "
                                 "is taken with [m]: RViz's \"2D Pose Estimate\" claims 0.5 m, more than a click on "
                                 "a city map knows. 0: as the pose's covariance says.", range=(0.0, 1e5))
OUTPUT_FRAMES = (
    ParamSpec("map_frame", MAP_FRAME_ID, "frame_id of the pose (REP-105 map: ENU at the database's origin)."),
    ParamSpec("antenna_frame", ANTENNA_FRAME_ID, "frame_id of the NavSatFix (the receiver antenna)."),
)
WAIT_FOR_SUBSCRIBERS = ParamSpec("wait_for_subscribers_s", 10.0, "Hold the first output until a subscriber has "
                                 "matched (the next node of the chain, a recorder), for at most this long [s]; "
                                 "a message published before anyone listens is lost. 0: publish at once.",
                                 range=(0.0, 3600.0))
PUBLISH_NO_FIX = ParamSpec("publish_no_fix", True, "For a stack without a fix, publish a NavSatFix on fix with "
                           "status STATUS_NO_FIX and covariance type UNKNOWN (as GNSS drivers do), so a consumer "
                           "sees the receiver alive but without a position; false: publish nothing (no pose either "
                           "way).")
FUSION_TOWERS = ParamSpec("towers", "", "Tower database YAML placing the sites (origin, positions, timing "
                          "offsets). Required.")

ENVELOPE_ADC = (*SOURCE, SOURCE_FRAME, WAIT_FOR_SUBSCRIBERS)
CELL_SYNC = (TOWERS, FRONTEND, MOTION, *SYNC, ParamSpec("frame_id", ENVELOPE_FRAME_ID, "frame_id of the "
                                                        "published windows (the stream's frame)."),
             WAIT_FOR_SUBSCRIBERS)
CELL_TIMING = (FRONTEND, *TIMING, WAIT_FOR_SUBSCRIBERS)
TDOA_FUSION = (FUSION_TOWERS, MOTION, *FUSION, STACK_OVERLAP, *AIDING, INITIAL_POSE_MIN_STD, *OUTPUT_FRAMES,
               PUBLISH_NO_FIX, WAIT_FOR_SUBSCRIBERS)
DEEPSYNC_PIPELINE = (*SOURCE, SOURCE_FRAME, TOWERS, MOTION, *SYNC, *TIMING, *FUSION, *AIDING, INITIAL_POSE_MIN_STD,
                     *OUTPUT_FRAMES, PUBLISH_NO_FIX, WAIT_FOR_SUBSCRIBERS)

NODES: dict[str, tuple[ParamSpec, ...]] = {
    "envelope_adc": ENVELOPE_ADC,
    "cell_sync": CELL_SYNC,
    "cell_timing": CELL_TIMING,
    "tdoa_fusion": TDOA_FUSION,
    "deepsync_pipeline": DEEPSYNC_PIPELINE,
}
"""Node name -> its parameters, in the order they are declared."""


# --- values -> what the node runs with -----------------------------------------------------

def checked(specs: tuple[ParamSpec, ...], values: Mapping[str, object], node: str) -> dict[str, ParamValue]:
    """Every parameter of ``specs``: the given value (checked) or the default; an unknown name
    is an error (a typo must not fall back to a default)."""
    known = {spec.name: spec for spec in specs}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ParameterError(f"{node}.{unknown[0]}: no such parameter (known: {', '.join(known)})")
    return {name: spec.check(values[name], node) if name in values else spec.default for name, spec in known.items()}


def _config(build: Callable[..., T], specs: tuple[ParamSpec, ...], values: Mapping[str, ParamValue],
            node: str) -> T:
    """``build(**values of specs)``; the core's ValueError pinned on the parameter that alone
    causes it (tried against the defaults), else reported for the node."""
    defaults = {spec.name: spec.default for spec in specs}
    chosen = {name: values[name] for name in defaults}
    for name in defaults:
        try:
            build(**{**defaults, name: chosen[name]})
        except ValueError as error:
            raise ParameterError(f"{node}.{name}: {error}") from None
    try:
        return build(**chosen)
    except ValueError as error:
        raise ParameterError(f"{node}: {error}") from None


def _stacking(motion: str, n_frames: int, hop_frames: int) -> tuple[int, int]:
    """Frames per stack and per hop: 0 and 0, the motion model's; n_frames alone, back to back."""
    if n_frames == 1:
        raise ValueError("n_frames 1: the timing stage measures the noise from how frames differ, so a stack needs "
                         "at least 2 (0: the motion model's)")
    model = motion_model(motion)
    frames = n_frames or model.n_frames
    return frames, hop_frames or (frames if n_frames else model.hop_frames)


def _sync(motion: str, n_frames: int, hop_frames: int, clock_ppm: float, track_clock: bool, confirm_stacks: int,
          search_every: int, max_search_interval_s: float, hold_stacks: int, report_z: float,
          false_alarm_rate: float, max_cells: int, full_code_timing: bool, crs_cancel_z: float, hold_by_frame: bool,
          learn_bandwidths: bool) -> SyncConfig:
    frames, hop = _stacking(motion, n_frames, hop_frames)
    return SyncConfig(
        stack=StackConfig(n_frames=frames, hop_frames=hop, clock_ppm=clock_ppm, track_clock=track_clock),
        search=SearchConfig(false_alarm_rate=false_alarm_rate, max_cells=max_cells, full_code_timing=full_code_timing,
                            crs_cancel_z=crs_cancel_z, hold_by_frame=hold_by_frame),
        confirm_stacks=confirm_stacks, search_every=search_every, max_search_interval_s=max_search_interval_s,
        hold_stacks=hold_stacks, report_z=report_z, learn_bandwidths=learn_bandwidths)


def _timing(estimator: str, weak_std_samples: float, checkpoint: str) -> TimingConfig:
    return TimingConfig(estimator=Estimator.named(estimator), weak_std_samples=weak_std_samples,
                        checkpoint=checkpoint or None)


def _fusion(motion: str, tracking: bool, max_track_std_m: float, bias_decorrelation_m: float, gnss_std_m: float,
            gnss_min_std_m: float, multipath_std_m: float, min_std_m: float, receiver_height_m: float,
            stack_overlap: float = 0.0) -> FusionConfig:
    model = motion_model(motion)
    tracker = TrackerConfig(stack_overlap=stack_overlap or model.n_frames / model.hop_frames,
                            max_std_m=max_track_std_m, bias_decorrelation_m=bias_decorrelation_m)
    fusion = FusionConfig(snapshot=SnapshotConfig(receiver_height_m=receiver_height_m), track=tracking,
                          min_std_m=min_std_m, multipath_std_m=multipath_std_m, gnss_std_m=gnss_std_m,
                          gnss_min_std_m=gnss_min_std_m, tracker=tracker)
    return moving(model, SyncConfig(), fusion)[1]


def sync_config(values: Mapping[str, ParamValue], node: str = "cell_sync") -> SyncConfig:
    return _config(_sync, (MOTION, *SYNC), values, node)


def timing_config(values: Mapping[str, ParamValue], node: str = "cell_timing") -> TimingConfig:
    return _config(_timing, TIMING, values, node)


def fusion_config(values: Mapping[str, ParamValue], node: str = "tdoa_fusion") -> FusionConfig:
    """From the fusion parameters ``node`` declares: the one-process pipeline declares no
    stack overlap, which its stacks give (``PipelineConfig``)."""
    specs = tuple(spec for spec in NODES[node] if spec in (MOTION, *FUSION, STACK_OVERLAP))
    return _config(_fusion, specs, values, node)


def pipeline_config(values: Mapping[str, ParamValue], node: str = "deepsync_pipeline") -> PipelineConfig:
    sync, timing, fusion = sync_config(values, node), timing_config(values, node), fusion_config(values, node)
    try:
        return PipelineConfig(sync=sync, timing=timing, fusion=fusion)
    except ValueError as error:
        raise ParameterError(f"{node}: {error}") from None


def playback_config(values: Mapping[str, ParamValue], node: str = "envelope_adc") -> PlaybackConfig:
    return _config(PlaybackConfig, tuple(s for s in SOURCE if s.name in ("realtime", "rate", "loop")), values, node)


def _existing(path: str, node: str, name: str) -> str:
    if not os.path.exists(path):
        raise ParameterError(f"{node}.{name}: no such file {path!r}")
    return path


def towers(values: Mapping[str, ParamValue], node: str, *, required: bool = False) -> TowerDatabase | None:
    """The tower database ``towers`` names; None for "" unless ``required``, which also needs a
    database that places its sites (a map origin, positions and timing offsets): fusion's anchors."""
    path = str(values["towers"])
    if not path:
        if required:
            raise ParameterError(f"{node}.towers: required: a tower database YAML with the sites' origin, "
                                 "positions and timing offsets")
        return None
    _existing(path, node, "towers")
    try:
        database = load_tower_database(path)
    except ValueError as error:
        raise ParameterError(f"{node}.towers: {error}") from None
    if required and not places_sites(database):
        raise ParameterError(f"{node}.towers: database {database.name!r} ({path}) places no site: fixes need a map "
                             "origin and sites with position and timing_offset_us")
    return database


def load_frontend(path: str | os.PathLike) -> FrontendConfig:
    """The receiver chain a ``frontend`` parameter names: "" the default chain; a bag (directory
    or ``.mcap``) the chain it was recorded with; a YAML mapping of FrontendConfig fields.
    ValueError naming the path otherwise."""
    name = os.fspath(path)
    if not name:
        return FrontendConfig()
    if not os.path.exists(name):
        raise ValueError(f"no such file {name!r}")
    if is_bag_path(name):
        return bag_frontend(name)
    if Path(name).suffix.lower() in (".yaml", ".yml"):
        return build_dataclass(FrontendConfig, load_yaml(name), name)
    raise ValueError(f"{name}: neither a bag (directory or .mcap) nor a YAML of front-end fields")


def frontend(values: Mapping[str, ParamValue], node: str) -> FrontendConfig:
    try:
        return load_frontend(str(values["frontend"]))
    except ValueError as error:
        raise ParameterError(f"{node}.frontend: {error}") from None


def source(values: Mapping[str, ParamValue], node: str = "envelope_adc") -> Source:
    """The source ``source`` names (a path, or a live receiver's address), read with
    ``sample_format`` and ``sample_rate`` (unset: "" and 0)."""
    path = str(values["source"])
    if not path:
        raise ParameterError(f"{node}.source: required: a bag, a SigMF or raw recording, a scenario YAML or a "
                             "live receiver's address")
    if not is_live_address(path):
        _existing(path, node, "source")
    sample_format = str(values["sample_format"]) or None
    sample_rate = float(values["sample_rate"]) or None
    try:
        return open_source(path, sample_format, sample_rate)
    except ValueError as error:
        raise ParameterError(f"{node}.source: {error}") from None
