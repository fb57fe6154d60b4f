"""deepsync_ros.params: what the nodes' parameters are and what their values become, without ROS.

Every spec's default builds the core's default config; every bad value is refused naming
``node.parameter``; config/deepsync_nodes.yaml holds exactly the declared parameters, at their
defaults, in the type rclpy will declare them with (a double written as 2 would be refused).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml

from deepsync.frontend.config import FrontendConfig
from deepsync.motion import MOTION_MODELS
from deepsync.pipeline import PipelineConfig
from deepsync.sources import BagSource
from deepsync.timing.stage import Estimator, TimingConfig
from deepsync_ros import params
from deepsync_ros.playback import PlaybackConfig
from deepsync_ros.params import ParameterError

REPO = Path(__file__).resolve().parents[1]
CAMPUS_BAG = REPO / "bags" / "campus"
CAMPUS_TOWERS = REPO / "config" / "towers" / "campus.yaml"
NODES_YAML = REPO / "src" / "deepsync_ros" / "config" / "deepsync_nodes.yaml"
PATH_PARAMETERS = {"source", "towers", "frontend"}


def defaults(node: str) -> dict[str, params.ParamValue]:
    return params.checked(params.NODES[node], {}, node)


def build(node: str, values: dict[str, object]) -> None:
    """Everything a node builds from its values that reads no file."""
    given = params.checked(params.NODES[node], values, node)
    names = {spec.name for spec in params.NODES[node]}
    if "n_frames" in names:
        params.sync_config(given, node)
    if "estimator" in names:
        params.timing_config(given, node)
    if "tracking" in names:
        params.fusion_config(given, node)
    if "rate" in names:
        params.playback_config(given, node)


def test_the_defaults_are_the_cores() -> None:
    pipeline = defaults("deepsync_pipeline")
    # the split nodes' defaults are the one-process chain's: the default motion model's stacks,
    # and a tracker that counts their overlap
    assert params.sync_config(defaults("cell_sync")) == PipelineConfig().sync
    assert params.timing_config(defaults("cell_timing")) == TimingConfig()
    assert params.fusion_config(defaults("tdoa_fusion")) == PipelineConfig().fusion
    assert params.pipeline_config(pipeline) == PipelineConfig()
    assert params.playback_config(defaults("envelope_adc")) == PlaybackConfig()
    assert params.frontend(defaults("cell_timing"), "cell_timing") == FrontendConfig()
    assert params.towers(defaults("cell_sync"), "cell_sync") is None  # "": blind search


def test_the_pipeline_declares_what_the_separate_nodes_do() -> None:
    separate = {spec.name: spec for node in ("envelope_adc", "cell_sync", "cell_timing", "tdoa_fusion")
                for spec in params.NODES[node] if spec.name not in ("frontend", "towers")}
    pipeline = {spec.name: spec for spec in params.DEEPSYNC_PIPELINE}
    assert set(pipeline) - {"towers"} == set(separate)
    assert all(pipeline[name].default == spec.default for name, spec in separate.items())


@pytest.mark.parametrize("node, specs", params.NODES.items())
def test_every_parameter_is_described_and_every_number_has_a_range(node: str, specs: tuple) -> None:
    names = [spec.name for spec in specs]
    assert len(names) == len(set(names)), f"{node} declares a parameter twice"
    for spec in specs:
        assert spec.description, f"{node}.{spec.name} has no description"
        assert spec.type in (bool, int, float, str)
        if spec.type in (int, float):
            assert spec.range is not None and spec.range[0] <= spec.default <= spec.range[1], spec.name
        assert not spec.choices or spec.default in spec.choices


def test_the_estimator_choices_are_the_cores_estimators() -> None:
    (estimator,) = [spec for spec in params.CELL_TIMING if spec.name == "estimator"]
    assert set(estimator.choices) == set(Estimator.names())
    for choice in estimator.choices:
        assert params.timing_config({**defaults("cell_timing"), "estimator": choice}).estimator is Estimator.named(choice)


@pytest.mark.parametrize("node, name, value, says", [
    ("envelope_adc", "rate", 0.0, "outside"),
    ("envelope_adc", "rate", math.inf, "finite"),
    ("envelope_adc", "rate", "fast", "expected a number"),
    ("envelope_adc", "realtime", 1, "expected true or false"),
    ("envelope_adc", "sample_rate", -1.0, "outside"),
    ("envelope_adc", "sample_format", "wav", "not one of"),
    ("envelope_adc", "frame_id", 3, "expected a string"),
    ("envelope_adc", "replay_speed", 1.0, "no such parameter"),
    ("cell_sync", "n_frames", 1, "at least 2"),
    ("cell_sync", "motion", "bicycle", "must be one of"),
    ("tdoa_fusion", "motion", "car", "must be one of"),
    ("tdoa_fusion", "max_track_std_m", 0.0, "must be within"),
    ("tdoa_fusion", "bias_decorrelation_m", math.inf, "finite"),
    ("tdoa_fusion", "gnss_std_m", -5.0, "must be within"),
    ("tdoa_fusion", "use_gnss", "yes", "expected true or false"),
    ("tdoa_fusion", "odometry_timeout_s", 0.0, "outside"),
    ("tdoa_fusion", "learned_save_period_s", 0.5, "outside"),
    ("cell_sync", "n_frames", 10.0, "expected an integer"),
    ("cell_sync", "clock_ppm", math.nan, "finite"),
    ("cell_sync", "confirm_stacks", 0, "must be within"),
    ("cell_sync", "false_alarm_rate", 0.0, "false_alarm_rate must be within (0, 0.5)"),  # the core's open bound
    ("cell_sync", "false_alarm_rate", 0.5, "false_alarm_rate must be within (0, 0.5)"),
    ("cell_sync", "max_cells", 0, "must be within"),
    ("cell_sync", "track_clock", "yes", "expected true or false"),
    ("cell_timing", "estimator", "neural", "must be one of"),
    ("cell_timing", "weak_std_samples", 0.0, "weak_std_samples must be within (0, 1e+06] samples"),
    ("cell_timing", "min_snr_db", 70.0, "min_snr_db must be within [-60, 60] dB"),
    ("tdoa_fusion", "min_std_m", 0.0, "min_std_m must be within (0, 10000] m"),
    ("tdoa_fusion", "multipath_std_m", -1.0, "must be within"),
    ("tdoa_fusion", "receiver_height_m", 2e4, "must be within"),
    ("tdoa_fusion", "tracking", 0, "expected true or false"),
    ("deepsync_pipeline", "n_frames", 1001, "must be within"),
    ("deepsync_pipeline", "estimator", "ML", "must be one of"),
    ("deepsync_pipeline", "min_std_m", 0.0, "must be within (0,"),
])
def test_a_bad_value_is_refused_naming_the_parameter(node: str, name: str, value: object, says: str) -> None:
    with pytest.raises(ParameterError) as refused:
        build(node, {name: value})
    assert str(refused.value).startswith(f"{node}.{name}: ")
    assert says in str(refused.value)


def test_an_int_for_a_double_is_taken_as_the_double() -> None:
    assert params.checked(params.ENVELOPE_ADC, {"rate": 2}, "envelope_adc")["rate"] == 2.0


def test_a_missing_tower_file_is_named() -> None:
    with pytest.raises(ParameterError, match=r"^cell_sync\.towers: no such file 'x\.yaml'$"):
        params.towers({"towers": "x.yaml"}, "cell_sync")


def test_fusion_requires_a_database_that_places_its_sites(tmp_path: Path) -> None:
    with pytest.raises(ParameterError, match=r"^tdoa_fusion\.towers: required"):
        params.towers({"towers": ""}, "tdoa_fusion", required=True)
    unplaced = tmp_path / "unplaced.yaml"
    unplaced.write_text("name: pcis only\nsites:\n  - name: A\n    cells: [{pci: 120}]\n")
    assert params.towers({"towers": str(unplaced)}, "cell_sync").pcis == [120]  # enough for a search
    with pytest.raises(ParameterError, match=r"^tdoa_fusion\.towers: database 'pcis only' .* places no site"):
        params.towers({"towers": str(unplaced)}, "tdoa_fusion", required=True)
    assert params.towers({"towers": str(CAMPUS_TOWERS)}, "tdoa_fusion", required=True).name == "campus"


def test_a_malformed_tower_file_is_named(tmp_path: Path) -> None:
    broken = tmp_path / "broken.yaml"
    broken.write_text("name: [unclosed\n")
    with pytest.raises(ParameterError, match=r"^tdoa_fusion\.towers: .*broken\.yaml: invalid YAML"):
        params.towers({"towers": str(broken)}, "tdoa_fusion", required=True)


def test_load_frontend_of_the_campus_bag_is_the_bags_own() -> None:
    recorded = BagSource(CAMPUS_BAG).frontend
    assert params.load_frontend(str(CAMPUS_BAG)) == recorded
    assert params.load_frontend(CAMPUS_BAG / "campus.mcap") == recorded
    assert recorded != FrontendConfig()  # so the equality above says something
    assert params.load_frontend("") == FrontendConfig()


def test_load_frontend_of_a_yaml_of_fields(tmp_path: Path) -> None:
    good = tmp_path / "frontend.yaml"
    good.write_text("adc_rate_hz: 3.84e6\nrf_gain_db: 10.0\n")
    assert params.load_frontend(good) == FrontendConfig(adc_rate_hz=3.84e6, rf_gain_db=10.0)
    typo = tmp_path / "typo.yaml"
    typo.write_text("adc_rate: 3.84e6\n")
    with pytest.raises(ParameterError, match=r"^cell_timing\.frontend: .*unknown key adc_rate"):
        params.frontend({"frontend": str(typo)}, "cell_timing")
    with pytest.raises(ParameterError, match=r"^cell_sync\.frontend: no such file 'nowhere\.yaml'$"):
        params.frontend({"frontend": "nowhere.yaml"}, "cell_sync")
    other = tmp_path / "frontend.txt"
    other.write_text("adc_rate_hz: 3.84e6\n")
    with pytest.raises(ParameterError, match=r"^cell_sync\.frontend: .*neither a bag .* nor a YAML"):
        params.frontend({"frontend": str(other)}, "cell_sync")


def test_the_source_is_opened_or_named() -> None:
    values = defaults("envelope_adc")
    with pytest.raises(ParameterError, match=r"^envelope_adc\.source: required"):
        params.source(values)
    with pytest.raises(ParameterError, match=r"^envelope_adc\.source: no such file 'gone\.mcap'$"):
        params.source({**values, "source": "gone.mcap"})
    with pytest.raises(ParameterError, match=r"^deepsync_pipeline\.source: .*sample rate 1e\+06 Hz given, but "):
        params.source({**values, "source": str(CAMPUS_BAG), "sample_rate": 1e6}, "deepsync_pipeline")
    opened = params.source({**values, "source": str(CAMPUS_BAG)})
    assert opened.frontend == BagSource(CAMPUS_BAG).frontend


def test_the_source_may_be_a_live_receivers_address() -> None:
    values = defaults("envelope_adc")
    tuned = params.source({**values, "source": "rtl_tcp://192.0.2.7:1234?freq=1860e6&gain=30"})  # nothing connects
    assert tuned.frontend.adc_rate_hz == 1.92e6 and tuned.center_hz == 1860e6
    raw = params.source({**values, "source": "tcp://192.0.2.7:5000", "sample_format": "ci16_le",
                         "sample_rate": 3.84e6})
    assert raw.frontend.adc_rate_hz == 3.84e6
    with pytest.raises(ParameterError, match=r"^envelope_adc\.source: tcp://192\.0\.2\.7:5000: give the sample format"):
        params.source({**values, "source": "tcp://192.0.2.7:5000"})
    with pytest.raises(ParameterError, match=r"^envelope_adc\.source: udp://h:1: unknown scheme 'udp'"):
        params.source({**values, "source": "udp://h:1"})


def nodes_yaml() -> dict:
    """The YAML's sections by node name; its keys are ``/**/<node>``, for a node in any namespace."""
    document = yaml.safe_load(NODES_YAML.read_text())
    assert all(key.startswith("/**/") for key in document), list(document)
    return {key.removeprefix("/**/"): section for key, section in document.items()}


def test_the_yaml_declares_exactly_the_specd_parameters_at_their_defaults() -> None:
    document = nodes_yaml()
    assert set(document) == set(params.NODES)
    for node, specs in params.NODES.items():
        assert set(document[node]) == {"ros__parameters"}, node
        values = document[node]["ros__parameters"]
        assert set(values) == {spec.name for spec in specs}, node
        for spec in specs:
            value = values[spec.name]
            # exact types: rclpy declares the default's type and refuses an int for a double
            assert type(value) is spec.type, f"{node}.{spec.name}: {value!r} is not a {spec.type.__name__}"
            assert value == spec.default, f"{node}.{spec.name}: the YAML says {value!r}, the node {spec.default!r}"
            if spec.name in PATH_PARAMETERS:
                assert value == "", f"{node}.{spec.name}: paths are the launch file's to set"


def test_the_yaml_is_written_from_the_specs_and_repeats_no_help_by_hand() -> None:
    """The file's help is each spec's own description (what ``ros2 param describe`` shows),
    written by deepsync_ros.nodes_yaml: a parameter added, dropped or re-described shows here."""
    from deepsync_ros.nodes_yaml import nodes_yaml as written

    assert NODES_YAML.read_text() == written(), (
        "config/deepsync_nodes.yaml is not what the parameter specs write: run PYTHONPATH=src/deepsync:"
        "src/deepsync_ros python -m deepsync_ros.nodes_yaml > src/deepsync_ros/config/deepsync_nodes.yaml")
    assert written().count("# Hold the first output until a subscriber") == 1  # five nodes have it: said once


def test_the_readmes_node_table_lists_every_parameter_and_estimator() -> None:
    """Users read docs/ros.md's parameter table, not params.py: a parameter or estimator added
    to a node must appear in its row (the one-process node's row refers to the others'; the
    table is the last in the file to name each node)."""
    rows = {line.split("`")[1]: line for line in (REPO / "docs" / "ros.md").read_text().splitlines()
            if line.startswith("| `") and line.split("`")[1] in params.NODES}
    assert set(rows) == set(params.NODES)
    for node, specs in params.NODES.items():
        if node != "deepsync_pipeline":
            missing = [spec.name for spec in specs if f"`{spec.name}`" not in rows[node]]
            assert not missing, f"docs/ros.md's {node} row lacks {missing}"
    assert all(f"`{name}`" in rows["cell_timing"] for name in Estimator.names())


def test_the_yaml_with_the_campus_paths_builds_every_node() -> None:
    document = nodes_yaml()
    paths = {"source": str(CAMPUS_BAG), "towers": str(CAMPUS_TOWERS), "frontend": str(CAMPUS_BAG)}
    for node in params.NODES:
        values = {name: paths.get(name, value) for name, value in document[node]["ros__parameters"].items()}
        given = params.checked(params.NODES[node], values, node)
        build(node, given)
        if "towers" in given:
            assert params.towers(given, node, required=node == "tdoa_fusion") is not None
        if "frontend" in given:
            assert params.frontend(given, node) == BagSource(CAMPUS_BAG).frontend
        if "source" in given:
            assert params.source(given, node).frontend == BagSource(CAMPUS_BAG).frontend


def test_sliding_stacks_set_the_trackers_overlap_in_one_process_and_through_the_messages_apart() -> None:
    def values(node: str, **chosen) -> dict:
        return params.checked(params.NODES[node], chosen, node)

    sliding = params.pipeline_config(values("deepsync_pipeline", n_frames=50, hop_frames=10))
    assert sliding.fusion.tracker.stack_overlap == 5.0
    back_to_back = params.pipeline_config(values("deepsync_pipeline", n_frames=10))
    assert back_to_back.sync.stack.hop == 10 and back_to_back.fusion.tracker.stack_overlap == 1.0
    assert not any(spec.name == "stack_overlap" for specs in params.NODES.values() for spec in specs)
    # unset on both sides, the split nodes agree through the motion model: its stacks, their overlap
    for motion in MOTION_MODELS.values():
        stack = params.sync_config(values("cell_sync", motion=motion.name)).stack
        fusion = params.fusion_config(values("tdoa_fusion", motion=motion.name))
        tracker = fusion.tracker
        assert (stack.n_frames, stack.hop) == (motion.n_frames, motion.hop_frames)
        assert tracker.stack_overlap == stack.n_frames / stack.hop
        assert tracker.acceleration_std_mps2 == motion.acceleration_std_mps2
        assert fusion.multipath_std_m == motion.multipath_std_m  # unset (0): the model's
        assert params.fusion_config(values("tdoa_fusion", motion=motion.name, multipath_std_m=25.0)).multipath_std_m == 25.0
