"""The example configs for the ROS side: robot_localization's ekf_node and the Foxglove layout."""

from __future__ import annotations

import json
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
EKF = REPO / "src" / "deepsync_ros" / "config" / "robot_localization_ekf.yaml"
LAYOUT = REPO / "src" / "deepsync_ros" / "config" / "foxglove_layout.json"

# robot_localization's state order for every *_config vector
STATE = ("x", "y", "z", "roll", "pitch", "yaw", "vx", "vy", "vz", "vroll", "vpitch", "vyaw", "ax", "ay", "az")


def ekf_parameters() -> dict:
    document = yaml.safe_load(EKF.read_text())
    assert isinstance(document, dict) and len(document) == 1, "one node entry expected"
    (key,) = document
    # the ekf_node executable's node name, in any namespace (rclcpp wildcard matching)
    assert key == "/**/ekf_filter_node"
    return document[key]["ros__parameters"]


def test_ekf_fuses_our_pose_x_y_only() -> None:
    params = ekf_parameters()
    assert params["pose0"] == "/deepsync/pose"
    config = params["pose0_config"]
    assert len(config) == len(STATE) and all(isinstance(v, bool) for v in config)
    assert {name for name, on in zip(STATE, config) if on} == {"x", "y"}
    assert params["pose0_differential"] is False and params["pose0_relative"] is False
    assert 2.0 <= params["pose0_rejection_threshold"] <= 10.0


def test_ekf_frames_are_distinct_and_the_world_is_map() -> None:
    params = ekf_parameters()
    frames = [params["map_frame"], params["odom_frame"], params["base_link_frame"]]
    assert len(set(frames)) == 3, "robot_localization needs three distinct frame names"
    assert params["map_frame"] == "map" and params["world_frame"] == "map"


def test_ekf_handles_our_latency_and_the_looping_recording() -> None:
    params = ekf_parameters()
    assert params["two_d_mode"] is True
    assert params["smooth_lagged_data"] is True
    assert params["history_length"] >= 0.5  # seconds; our poses arrive ~0.1 s after their stamps
    assert params["reset_on_time_jump"] is True
    assert params["use_sim_time"] is True
    assert params["frequency"] > 0 and params["sensor_timeout"] > 0


def test_ekf_yaml_explains_its_choices() -> None:
    comments = [line for line in EKF.read_text().splitlines() if line.lstrip().startswith("#")]
    assert len(comments) >= 30
    said = " ".join(comments)
    for word in ("smooth_lagged_data", "history_length", "use_sim_time", "REP-105", "TF", "Mahalanobis",
                 "two_d_mode", "orientation"):
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
    assert set(by_type["3D"]["topics"]) == {"/deepsync/pose", "/deepsync/truth/pose"}
    plotted = {path["value"] for path in by_type["Plot"]["paths"]}
    assert {"/deepsync/pose.pose.pose.position.x", "/deepsync/pose.pose.pose.position.y"} <= plotted
    assert by_type["DiagnosticSummary"]["topicToRender"] == "/diagnostics"
    text = LAYOUT.read_text()
    for topic in ("/deepsync/pose", "/deepsync/fix", "/deepsync/truth/pose", "/diagnostics"):
        assert f'"{topic}' in text
