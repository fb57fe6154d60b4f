"""Every node's parameters, and what their values become: core configs, a source, a database.

Pure Python (no rclpy): the nodes declare :class:`ParamSpec` s through rcl_interfaces
descriptors and hand the values they get to the builders here, which the tests run without ROS.
A value the core's own configs refuse is reported as :class:`ParameterError` naming the
parameter, ``cell_sync.towers: no such file 'x.yaml'``: each parameter is first tried alone
against the defaults, so the core's message (which names its field) is pinned to the parameter
that caused it, and only what no single value explains is reported for the node.

A parameter that sets a core config field is made from that field's setting
(:func:`from_setting`, ``deepsync.schema``): its description, unit, range and choices are
written once, on the config dataclass, and its value reaches the config by the field's name
(``PipelineConfig.with_choices``). Only what the core has no field for (topics, frames, QoS,
playback, aiding inputs) is written here.

Descriptor ranges are what ``ros2 param describe`` shows and rclpy enforces; the specs check
them too, so a value refused here is refused the same way with or without ROS. A descriptor's
range is inclusive, so an open bound (``false_alarm_rate`` in (0, 0.5)) is the setting's check.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from deepsync.bag.convert import ANTENNA_FRAME_ID, ENVELOPE_FRAME_ID, MAP_FRAME_ID
from deepsync.configio import build_dataclass, load_yaml
from deepsync.frontend.config import FrontendConfig
from deepsync.fusion.bias_map import BiasMap, load_bias_map
from deepsync.fusion.stage import FusionConfig
from deepsync.motion import DEFAULT_MOTION, MOTION
from deepsync.pipeline import PipelineConfig, places_sites, setting_paths
from deepsync.schema import Setting, of
from deepsync.sources import SampleFormat, Source, bag_frontend, open_source
from deepsync.sources.address import is_live_address
from deepsync.sources.bagfile import is_bag_path
from deepsync.sync.stage import SyncConfig
from deepsync.timing.stage import TimingConfig
from deepsync.towers import TowerDatabase, load_tower_database

from .playback import PlaybackConfig

ParamValue = bool | int | float | str
T = TypeVar("T")


_KINDS = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


class ParameterError(ValueError):
    """A parameter value the node cannot run with; the message starts with ``node.parameter``."""


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: its name, default (whose type is the parameter's), what it means, the
    inclusive range of a number, the values a string may take, and whether it may change
    while the node runs (``read_only``: the stage it configures is built once). ``setting``:
    the core setting it is made from (:func:`from_setting`); ``unset``: what its 0 or "" means
    (the field left at None), where that is allowed."""

    name: str
    default: ParamValue
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = True
    setting: Setting | None = None
    unset: str = ""

    @property
    def type(self) -> type:
        return type(self.default)

    @property
    def constraints(self) -> str:
        """The rule a person reads in ``ros2 param describe``."""
        if self.choices:
            return "one of: " + ", ".join(repr(choice) for choice in self.choices)
        if self.setting is not None and self.setting.bounds is not None:
            return self.setting.interval + (f", or {self.type()!r}" if self.unset else "")
        if self.range is not None:
            return f"{self.range[0]:g} to {self.range[1]:g}"
        return ""

    def is_unset(self, value: ParamValue) -> bool:
        """Whether ``value`` is this parameter's "not set" (0 or ""), where it has one."""
        return bool(self.unset) and value == self.type()

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
        if self.setting is not None:
            if not self.is_unset(value):
                try:
                    self.setting.check(value, self.name)
                except ValueError as error:
                    raise ParameterError(f"{where}: {error}") from None
            return value
        if self.range is not None and not self.range[0] <= value <= self.range[1]:
            raise ParameterError(f"{where}: {value!r} is outside {self.constraints}")
        if self.choices and value not in self.choices:
            raise ParameterError(f"{where}: {value!r} is not {self.constraints}")
        return value


_DEFAULTS = PipelineConfig()


def from_setting(described: Setting, *, name: str | None = None, unset: str = "", read_only: bool = True) -> ParamSpec:
    """The parameter that sets a core setting: its description, range and choices are the
    setting's, its default the default pipeline's (a choice by its name); ``unset``: what 0 or
    "" means (the core's None: the field left to what else decides it), which is then the
    default; ``name`` where the node calls it otherwise than the field."""
    if unset:
        default = described.kind()
    elif described is MOTION:
        default = DEFAULT_MOTION
    else:
        path, _ = setting_paths()[described.name]
        default = described.name_of(getattr(functools.reduce(getattr, path, _DEFAULTS), described.name))
    text = described.described
    if unset:
        text += f" {'Empty' if described.kind is str else '0'}: {unset}."
    bounds = None
    if described.bounds is not None:
        bounds = (min(described.bounds[0], 0) if unset else described.bounds[0], described.bounds[1])
    return ParamSpec(name or described.name, default, text, bounds, described.names, read_only, described, unset)


def _core(field: str, **how: object) -> ParamSpec:
    """The parameter of a stage config's field (``deepsync.pipeline.setting_paths``)."""
    return from_setting(setting_paths()[field][1], **how)


# --- the specs -----------------------------------------------------------------------------

MOTION_PARAM = from_setting(MOTION)

SOURCE = (
    ParamSpec("source", "", "Recording to publish: a rosbag2 bag (directory or .mcap), a SigMF recording, a raw "
              "I/Q or envelope file, or a scenario YAML (the live simulator); or a live receiver: "
              "rtl_tcp://HOST:PORT?freq=HZ, tcp://HOST:PORT, a serial device, soapy://DRIVER?freq=HZ "
              "(docs/live_receivers.md). Required."),
    ParamSpec("sample_format", "", "Sample format of a raw file or a tcp/serial stream; empty: from its extension "
              "or metadata (rtl_tcp: cu8).", choices=("", *(f.value for f in SampleFormat))),
    ParamSpec("sample_rate", 0.0, "Sample rate of a raw file or a live stream [Hz]; 0: from the recording "
              "(rtl_tcp, soapy: 1.92e6).",
              range=(0.0, of(FrontendConfig, "adc_rate_hz").bounds[1])),
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
    _core("n_frames", unset="the motion model's"),
    _core("hop_frames", unset="the motion model's, or with n_frames given, n_frames (back to back)"),
    _core("clock_ppm"),
    _core("track_clock"),
    _core("confirm_stacks"),
    _core("search_every"),
    _core("max_search_interval_s"),
    _core("hold_stacks"),
    _core("report_z"),
    _core("false_alarm_rate"),
    _core("max_cells"),
    _core("full_code_timing"),
    _core("crs_cancel_z"),
    _core("hold_by_frame"),
    _core("learn_bandwidths"),
)
TIMING = (
    _core("estimator", read_only=False),
    _core("weak_std_samples", read_only=False),
    _core("min_snr_db", read_only=False),
    _core("peak_width_allowance_samples", read_only=False),
    _core("smear_std_per_sample", read_only=False),
    _core("checkpoint", unset="the one shipped with deepsync", read_only=False),
)
FUSION = (
    _core("track", name="tracking"),
    _core("max_std_m", name="max_track_std_m"),
    _core("bias_decorrelation_m"),
    _core("gnss_std_m"),
    _core("gnss_min_std_m"),
    _core("multipath_std_m", unset="the motion model's"),
    _core("min_std_m"),
    _core("receiver_height_m"),
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
BIAS_MAP = ParamSpec("bias_map", "", "Site bias map (.npz, deepsync survey-map or trace-map) for the same tower "
                     "database: each mapped site's range bias comes off its ranges where the map knows it. Empty: none.")

ENVELOPE_ADC = (*SOURCE, SOURCE_FRAME, WAIT_FOR_SUBSCRIBERS)
CELL_SYNC = (TOWERS, FRONTEND, MOTION_PARAM, *SYNC, ParamSpec("frame_id", ENVELOPE_FRAME_ID, "frame_id of the "
                                                        "published windows (the stream's frame)."),
             WAIT_FOR_SUBSCRIBERS)
CELL_TIMING = (FRONTEND, *TIMING, WAIT_FOR_SUBSCRIBERS)
TDOA_FUSION = (FUSION_TOWERS, BIAS_MAP, MOTION_PARAM, *FUSION, *AIDING, INITIAL_POSE_MIN_STD, *OUTPUT_FRAMES,
               PUBLISH_NO_FIX, WAIT_FOR_SUBSCRIBERS)
DEEPSYNC_PIPELINE = (*SOURCE, SOURCE_FRAME, TOWERS, BIAS_MAP, MOTION_PARAM, *SYNC, *TIMING, *FUSION, *AIDING,
                     INITIAL_POSE_MIN_STD, *OUTPUT_FRAMES, PUBLISH_NO_FIX, WAIT_FOR_SUBSCRIBERS)

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


def _pipeline(specs: tuple[ParamSpec, ...]) -> Callable[..., PipelineConfig]:
    """What builds the pipeline config from the values of ``specs`` (the others at the core's
    defaults): each setting's value by its field's name; 0 or "" of one that may be unset, None."""
    made = tuple(spec for spec in specs if spec.setting is not None)

    def build(**values: ParamValue) -> PipelineConfig:
        chosen = {spec.setting.name: None if spec.is_unset(values[spec.name]) else values[spec.name] for spec in made}
        return PipelineConfig().with_choices(**chosen)
    return build


def _node_config(specs: tuple[ParamSpec, ...], values: Mapping[str, ParamValue], node: str) -> PipelineConfig:
    return _config(_pipeline(specs), specs, values, node)


def sync_config(values: Mapping[str, ParamValue], node: str = "cell_sync") -> SyncConfig:
    """The sync stage's config; checked as a whole chain's (a stack the timing stage can use)."""
    return _node_config((MOTION_PARAM, *SYNC), values, node).sync


def timing_config(values: Mapping[str, ParamValue], node: str = "cell_timing") -> TimingConfig:
    return _node_config(TIMING, values, node).timing


def fusing_config(values: Mapping[str, ParamValue], node: str = "tdoa_fusion") -> PipelineConfig:
    """The chain's config from the fusion parameters ``node`` declares, with the motion model's
    stacks: the tracker counts their overlap until the arrivals say which stacks they came from
    (``CellTimingArray``: ``Pipeline.fuse_arrivals``)."""
    return _node_config((MOTION_PARAM, *FUSION), values, node)


def fusion_config(values: Mapping[str, ParamValue], node: str = "tdoa_fusion") -> FusionConfig:
    return fusing_config(values, node).fusion


def pipeline_config(values: Mapping[str, ParamValue], node: str = "deepsync_pipeline") -> PipelineConfig:
    return _node_config((MOTION_PARAM, *SYNC, *TIMING, *FUSION), values, node)


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


def bias_map(values: Mapping[str, ParamValue], node: str, towers: TowerDatabase | None) -> BiasMap | None:
    """The bias map ``bias_map`` names, for fusion with ``towers``; None for "". Refused where
    there is no fusion (no database that places its sites) or the map was made in another frame."""
    path = str(values["bias_map"])
    if not path:
        return None
    _existing(path, node, "bias_map")
    if not places_sites(towers):
        raise ParameterError(f"{node}.bias_map: a bias map corrects fusion's site ranges, and there is no fusion "
                             "without a tower database that places its sites (towers)")
    try:
        loaded = load_bias_map(path)
        loaded.check_database(towers)
    except ValueError as error:
        raise ParameterError(f"{node}.bias_map: {error}") from None
    return loaded


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
