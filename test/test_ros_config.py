"""The example configs for the ROS side: robot_localization's dual EKF and the Foxglove layout."""

from __future__ import annotations

import ast
import json
import re
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
EKF = REPO / "src" / "deepsync_ros" / "config" / "robot_localization_dual_ekf.yaml"
LAYOUT = REPO / "src" / "deepsync_ros" / "config" / "foxglove_layout.json"
DUAL_EKF_LAUNCH = REPO / "src" / "deepsync_ros" / "launch" / "dual_ekf.launch.py"
OVERLAY = REPO / "src" / "deepsync_ros" / "config" / "deepsync_ekf_poses.yaml"

# robot_localization's state order for every *_config vector
STATE = ("x", "y", "z", "roll", "pitch", "yaw", "vx", "vy", "vz", "vroll", "vpitch", "vyaw", "ax", "ay", "az")

# The parameters robot_localization's ekf_node declares, with their types, read from its
# src/ros_filter.cpp (cra-ros-pkg/robot_localization, branch ros2 at 1cb9533 "Update ukf.yaml to
# match ekf.yaml (#867)", package 3.6.0: RosFilter::loadParams, declare_parameter calls, and
# loadUpdateConfig for <sensor>_config) plus rclcpp's use_sim_time. rclcpp refuses a value of
# another type (an integer for a double: write 30.0, not 30), so the types are checked too.
BOOL, DOUBLE, INT, STRING, BOOLS, DOUBLES = "bool", "double", "int", "string", "bool[]", "double[]"
RL_PARAMETERS = {
    "use_sim_time": BOOL, "frequency": DOUBLE, "sensor_timeout": DOUBLE, "two_d_mode": BOOL,
    "transform_time_offset": DOUBLE, "transform_timeout": DOUBLE, "print_diagnostics": BOOL, "debug": BOOL,
    "debug_out_file": STRING, "publish_tf": BOOL, "publish_acceleration": BOOL,
    "permit_corrected_publication": BOOL, "map_frame": STRING, "odom_frame": STRING, "base_link_frame": STRING,
    "base_link_frame_output": STRING, "world_frame": STRING, "tf_prefix": STRING, "smooth_lagged_data": BOOL,
    "history_length": DOUBLE, "reset_on_time_jump": BOOL, "predict_to_current_time": BOOL, "use_control": BOOL,
    "control_timeout": DOUBLE, "control_config": BOOLS, "acceleration_limits": DOUBLES,
    "acceleration_gains": DOUBLES, "deceleration_limits": DOUBLES, "deceleration_gains": DOUBLES,
    "dynamic_process_noise_covariance": BOOL, "initial_state": DOUBLES, "disabled_at_startup": BOOL,
    "process_noise_covariance": DOUBLES, "initial_estimate_covariance": DOUBLES,
    "gravitational_acceleration": DOUBLE,
}
RL_SENSORS = {  # <kind><n> is the topic (a string); then <kind><n><suffix>
    "odom": {"_config": BOOLS, "_differential": BOOL, "_relative": BOOL, "_pose_use_child_frame": BOOL,
             "_pose_rejection_threshold": DOUBLE, "_twist_rejection_threshold": DOUBLE, "_queue_size": INT},
    "pose": {"_config": BOOLS, "_differential": BOOL, "_relative": BOOL, "_rejection_threshold": DOUBLE,
             "_queue_size": INT},
    "twist": {"_config": BOOLS, "_rejection_threshold": DOUBLE, "_queue_size": INT},
    "imu": {"_config": BOOLS, "_differential": BOOL, "_relative": BOOL, "_pose_rejection_threshold": DOUBLE,
            "_twist_rejection_threshold": DOUBLE, "_linear_acceleration_rejection_threshold": DOUBLE,
            "_remove_gravitational_acceleration": BOOL, "_queue_size": INT},
}
_SENSOR = re.compile(r"(odom|pose|twist|imu)(\d+)(.*)")


def rl_type(name: str) -> str | None:
    """robot_localization's type of parameter ``name``; None: it declares no such parameter."""
    if name in RL_PARAMETERS:
        return RL_PARAMETERS[name]
    match = _SENSOR.fullmatch(name)
    if match is None:
        return None
    kind, _, suffix = match.groups()
    return STRING if suffix == "" else RL_SENSORS[kind].get(suffix)


def yaml_type(value: object) -> str:
    if isinstance(value, bool):
        return BOOL
    if isinstance(value, int):
        return INT
    if isinstance(value, float):
        return DOUBLE
    if isinstance(value, str):
        return STRING
    if isinstance(value, list) and value and all(isinstance(v, bool) for v in value):
        return BOOLS
    if isinstance(value, list) and value and all(isinstance(v, float) for v in value):
        return DOUBLES
    return f"unusable {value!r}"


def filters() -> dict[str, dict]:
    document = yaml.safe_load(EKF.read_text())
    assert set(document) == {"/**/ekf_filter_node_odom", "/**/ekf_filter_node_map"}
    return {key: entry["ros__parameters"] for key, entry in document.items()}


def test_rl_type_knows_robot_localizations_names() -> None:
    assert rl_type("pose0_rejection_threshold") == DOUBLE and rl_type("odom1_queue_size") == INT
    assert rl_type("pose0_pose_rejection_threshold") is None  # an odometry/IMU name, not a pose's
    assert rl_type("pose0_use_child_frame") is None and rl_type("sensor_timout") is None


def test_every_ekf_parameter_is_robot_localizations_with_its_type() -> None:
    for node, parameters in filters().items():
        for name, value in parameters.items():
            expected = rl_type(name)
            assert expected is not None, f"{node}: robot_localization has no parameter {name}"
            assert yaml_type(value) == expected, f"{node}.{name}: {value!r} is not a {expected}"
            if name.endswith("_config"):
                assert len(value) == len(STATE), f"{node}.{name}: {len(value)} values, not {len(STATE)}"
            if name.endswith("_covariance"):
                assert len(value) in (len(STATE), len(STATE) ** 2), f"{node}.{name}: {len(value)} values"


def _measured(parameters: dict, prefix: str) -> set[str]:
    return {name for name, on in zip(STATE, parameters[f"{prefix}_config"]) if on}


def test_the_odom_filter_takes_odometry_and_imu_and_the_map_filter_our_pose_besides() -> None:
    odom, map_ = filters()["/**/ekf_filter_node_odom"], filters()["/**/ekf_filter_node_map"]
    assert odom["world_frame"] == "odom" and map_["world_frame"] == "map"
    assert "pose0" not in odom and map_["pose0"] == _constant(_launch_tree(), "EKF_POSE_TOPIC")
    assert _measured(map_, "pose0") == {"x", "y"}  # z and orientation unmeasured (variance 1e6)
    assert map_["pose0_differential"] is False and map_["pose0_relative"] is False
    assert 2.0 <= map_["pose0_rejection_threshold"] <= 10.0
    for parameters in (odom, map_):
        frames = [parameters["map_frame"], parameters["odom_frame"], parameters["base_link_frame"]]
        assert len(set(frames)) == 3, "robot_localization needs three distinct frame names"
        assert parameters["two_d_mode"] is True and parameters["publish_tf"] is True
        # yaw or its rate measured by some input: else "Neither YAW nor its velocity is being measured"
        inputs = [key for key in parameters if rl_type(key) == STRING and _SENSOR.fullmatch(key)]
        assert any({"yaw", "vyaw"} & _measured(parameters, key) for key in inputs)
        assert any({"vx", "x"} & _measured(parameters, key) for key in inputs)


def test_the_map_filter_waits_for_poses_as_late_as_a_stack_makes_them() -> None:
    """A pose is stamped at its stack's first sample and published after the stack (the default
    motion model's n_frames of 10 ms) and the processing: history_length must cover that."""
    from deepsync.motion import DEFAULT_MOTION, motion_model
    map_ = filters()["/**/ekf_filter_node_map"]
    stack_s = motion_model(DEFAULT_MOTION).n_frames * 0.01
    assert map_["smooth_lagged_data"] is True
    assert map_["history_length"] >= 2 * stack_s
    assert map_["reset_on_time_jump"] is True and map_["use_sim_time"] is True
    assert 0 < map_["sensor_timeout"] < stack_s  # the odometry keeps the filter fed between poses


def test_the_deepsync_overlay_feeds_the_ekf_independent_fixes() -> None:
    """What the map filter takes from DeepSync must not be counted twice (benchmarks/experiments/ekf_example_nees.py):
    no tracker (its poses carry the ones before) and stacks that share no frame."""
    from deepsync.motion import DEFAULT_MOTION, motion_model
    from deepsync_ros import params
    overlay = yaml.safe_load(OVERLAY.read_text())
    sync = overlay["/**/cell_sync"]["ros__parameters"]
    fusion = overlay["/**/tdoa_fusion"]["ros__parameters"]
    assert fusion["tracking"] is False
    values = {spec.name: spec.default for spec in params.CELL_SYNC} | sync
    stack = params.sync_config(values).stack
    assert stack.hop_frames >= stack.n_frames == motion_model(DEFAULT_MOTION).n_frames
    assert "stack_overlap" not in fusion  # the arrivals say which stacks they came from (CellTimingArray)
    for node, entry in overlay.items():  # only names the nodes have, with their types
        specs = {spec.name: spec for spec in params.NODES[node.split("/")[-1]]}
        for name, value in entry["ros__parameters"].items():
            assert name in specs and type(value) is specs[name].type, f"{node}.{name}"


def _launch_tree() -> ast.Module:
    return ast.parse(DUAL_EKF_LAUNCH.read_text(), filename=str(DUAL_EKF_LAUNCH))


def _constant(tree: ast.Module, name: str) -> object:
    (value,) = [node.value for node in tree.body if isinstance(node, ast.Assign)
                and any(getattr(target, "id", None) == name for target in node.targets)]
    return ast.literal_eval(value)


def test_the_dual_ekf_launch_starts_the_filters_the_yaml_configures() -> None:
    tree = _launch_tree()
    assert {f"/**/{name}" for name in _constant(tree, "FILTERS")} == set(filters())
    for parameters in filters().values():  # the inputs it remaps are the topics the YAML names
        assert parameters["odom0"] == _constant(tree, "ODOMETRY_INPUT")
        assert parameters["imu0"] == _constant(tree, "IMU_INPUT")
    assert _constant(tree, "POSE_TOPIC") == "/deepsync/pose"  # the throttle's input: tdoa_fusion's pose
    assert 0 < _constant(tree, "EKF_POSES_PER_S") <= 0.2  # one fix per 5 s at most (the NEES check)
    source = DUAL_EKF_LAUNCH.read_text()
    assert '"deepsync_ekf_poses.yaml"' in source and '"deepsync.launch.py"' in source
    assert '"robot_localization_dual_ekf.yaml"' in source
    imported = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, (ast.Import, ast.ImportFrom))
                for alias in (node.names if isinstance(node, ast.Import) else [ast.alias(node.module or "")])}
    assert imported <= {"launch", "launch_ros"}, imported  # it runs on ros2 launch's interpreter


def test_ekf_yaml_explains_its_choices() -> None:
    comments = [line for line in EKF.read_text().splitlines() if line.lstrip().startswith("#")]
    assert len(comments) >= 30
    said = " ".join(comments)
    for word in ("smooth_lagged_data", "history_length", "use_sim_time", "REP-105", "map -> odom", "Mahalanobis",
                 "YAW", "tracking: false", "ekf_example_nees", "ros_filter.cpp", "throttle"):
        assert word in said, f"no comment explains {word}"


def _layout() -> dict:
    return json.loads(LAYOUT.read_text())


def _panel_ids(tree) -> list[str]:
    if isinstance(tree, str):
        return [tree]
    return _panel_ids(tree["first"]) + _panel_ids(tree["second"])


def test_foxglove_layout_is_a_layout_of_its_panels() -> None:
    layout = _layout()
    assert set(layout) >= {"configById", "layout"}
    ids = _panel_ids(layout["layout"])
    assert sorted(ids) == sorted(layout["configById"]), "every configured panel is placed, once"
    assert all("!" in panel for panel in ids)  # "<panel type>!<id>"


def test_foxglove_layout_shows_our_topics() -> None:
    config = _layout()["configById"]
    by_type = {panel.split("!")[0]: settings for panel, settings in config.items()}
    assert by_type["map"]["followTopic"] == "/deepsync/fix"
    from deepsync.bag.topics import MAP_SITES_TOPIC
    assert {"/deepsync/fix", MAP_SITES_TOPIC} <= set(by_type["map"]["topicColors"])  # the pose and the sites
    assert set(by_type["3D"]["topics"]) == {"/deepsync/pose", "/deepsync/truth/pose"}
    plotted = {path["value"] for path in by_type["Plot"]["paths"]}
    assert {"/deepsync/pose.pose.pose.position.x", "/deepsync/pose.pose.pose.position.y"} <= plotted
    assert by_type["DiagnosticSummary"]["topicToRender"] == "/diagnostics"
    text = LAYOUT.read_text()
    for topic in ("/deepsync/pose", "/deepsync/fix", "/deepsync/truth/pose", "/diagnostics"):
        assert f'"{topic}' in text


def _nees_script():
    """benchmarks/experiments/ekf_example_nees.py as a module (it is a script, not a package)."""
    import importlib.util
    path = REPO / "benchmarks" / "experiments" / "ekf_example_nees.py"
    spec = importlib.util.spec_from_file_location("ekf_example_nees", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(spec.name, module)  # its dataclasses look their module up there
    spec.loader.exec_module(sys.modules[spec.name])
    return sys.modules[spec.name]


def _standing_filter_nees(bias_block_s: float) -> float:
    """The script's filter, set up as the example's map filter, on a receiver standing still:
    odometry (0.05 m/s, 20 Hz) and 30 m position fixes once a second whose error is redrawn
    every ``bias_block_s`` (1: independent fixes; longer: a bias the fixes repeat)."""
    import numpy as np
    script = _nees_script()
    settings = script.map_filter_settings(EKF)
    states = list(script.STATE)
    ekf = script.PlaneEkf(np.asarray(settings["process_noise_covariance"])[states],
                          np.asarray(settings["initial_estimate_covariance"])[states],
                          float(settings["pose0_rejection_threshold"]))
    rng = np.random.default_rng(7)
    nees, bias = [], np.zeros(2)
    for second in range(3000):
        if second % bias_block_s == 0:
            bias = rng.normal(0.0, 30.0, 2)
        t_ns = second * 1_000_000_000
        ekf.update(t_ns, script.POSITION, bias, np.eye(2) * 900.0, gated=True)
        if second > 30:  # past the start
            nees.append(float(ekf.x[:2] @ np.linalg.solve(ekf.p[:2, :2], ekf.x[:2])))
        for k in range(1, 20):
            ekf.update(t_ns + k * 50_000_000, script.VELOCITY, rng.normal(0.0, 0.05, 2), np.eye(2) * 0.0025,
                       gated=False)
    return float(np.mean(nees))


def test_the_nees_check_passes_independent_fixes_and_catches_repeated_ones() -> None:
    """The filter of benchmarks/experiments/ekf_example_nees.py reads 2 or less when its inputs are what they
    claim (less: its process noise allows for motion a standing receiver does not make), and far
    more when the same error comes back fix after fix, as a tracker's does."""
    assert 0.8 < _standing_filter_nees(1) < 2.5
    assert _standing_filter_nees(30) > 10.0
