"""The route commands on the bundled campus bag: ``evaluate-route`` and ``calibrate`` end to end.

The campus bag is 3 s of a static receiver hearing three LOS sites (one a co-sited pair): every
stack that hears all three fixes, and the fixes must agree with the position bound and the
ground truth. Bad input rows (no ground truth, a database that places no site) are here too.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from deepsync.bag import ENVELOPE_TOPIC, BagReader, BagWriter, envelope_from_msg
from deepsync.cli import main
from deepsync.eval.aiding import AidingPlan
from deepsync.eval.calibrate import calibrate_route, oracle_database
from deepsync.eval.route import InitialPose, evaluate_route, read_truth_track
from deepsync.fusion.stage import FusionConfig, FusionStage
from deepsync.sources import BagSource
from deepsync.towers import load_tower_database
from deepsync.types import PositionPrior

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "campus"
TOWERS = REPO / "config" / "towers" / "campus.yaml"


@pytest.fixture(scope="module")
def campus(tmp_path_factory) -> tuple[dict, list[Path]]:
    out = tmp_path_factory.mktemp("route")
    return evaluate_route(BagSource(BAG), load_tower_database(TOWERS), out, progress=False)


def test_campus_route_fixes_within_a_few_bounds(campus) -> None:
    summary, paths = campus
    snapshot = summary["methods"]["snapshot"]
    bound = summary["position_bound"]
    assert summary["sites_heard"] == ["A", "B", "C"]
    assert snapshot["fix_rate"] > 0.5
    # LOS multipath biases the envelope peak by ~0.1 sample (15 m): errors are a few bounds, not more
    assert bound["median_m"] < snapshot["median_m"] < 4 * bound["median_m"]
    assert snapshot["p95_m"] < 100
    tracked = summary["methods"]["tracked"]
    assert tracked["fix_rate"] > 0.5 and tracked["median_m"] < 3 * snapshot["median_m"]


def test_campus_route_report_files(campus) -> None:
    summary, paths = campus
    assert [p.name for p in paths] == ["route.json", "route_cdf.png", "route_map.png", "route_timeline.png"]
    for path in paths[1:]:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    document = json.loads(paths[0].read_text())  # strict JSON: NaN would not parse in other readers
    assert document["summary"]["stacks"] == len(document["stacks"]) == summary["stacks"]
    # the receiver stands: its sites' pulls have no path to change over, and the report says so
    pulls = document["summary"]["pulls"]
    assert pulls["fit"] is None and "three are needed" in pulls["why_no_fit"]
    assert pulls["assumed"]["multipath_std_m"] == FusionConfig().multipath_std_m
    fixed = [s for s in document["stacks"] if s["snapshot"]["fix"]]
    assert fixed and all(abs(s["snapshot"]["error_m"] - np.linalg.norm(
        np.array(s["snapshot"]["enu"][:2]) - s["truth_enu"][:2])) < 1e-6 for s in fixed)


def test_calibration_on_the_campus_bag_writes_a_database_that_fixes_better(tmp_path) -> None:
    """On one recording the calibration absorbs each site's multipath bias into its offset, so
    re-evaluating the same bag with it must be no worse; the oracle clocks are the yardstick."""
    source = BagSource(BAG)
    towers = load_tower_database(TOWERS)
    calibration = calibrate_route(source, towers, progress=False)
    result = calibration.result
    assert {s.site for s in result.sites} == {"A", "B", "C"}
    assert result.residual_rms_after_m < result.residual_rms_before_m
    out = tmp_path / "calibrated.yaml"
    assert main(["calibrate", "--bag", str(BAG), "--towers", str(TOWERS), "--out", str(out), "--quiet"]) == 0
    calibrated = load_tower_database(out)
    assert calibrated.timing_epoch_ns == calibration.database.timing_epoch_ns
    before, _ = evaluate_route(source, oracle_database(towers, source), tmp_path / "oracle", progress=False)
    after, _ = evaluate_route(source, calibrated, tmp_path / "after", progress=False)
    assert after["methods"]["snapshot"]["median_m"] <= 1.1 * before["methods"]["snapshot"]["median_m"]


def test_an_initial_pose_fixes_a_route_where_two_sites_alone_cannot(tmp_path, capsys) -> None:
    # the campus database without site C: A and B measure one range difference, a hyperbola
    database = yaml.safe_load(TOWERS.read_text())
    database["sites"] = [site for site in database["sites"] if site["name"] != "C"]
    towers = tmp_path / "two_sites.yaml"
    towers.write_text(yaml.safe_dump(database))
    out = tmp_path / "out"
    assert main(["evaluate-route", "--bag", str(BAG), "--towers", str(towers), "--out", str(out), "--quiet",
                 "--initial-pose-std", "10", "--frames", "10", "--multipath-std-m", "40"]) == 0
    assert "starts from the true start position" in capsys.readouterr().out
    summary = json.loads((out / "route.json").read_text())["summary"]
    assert summary["pulls"]["assumed"]["multipath_std_m"] == 40.0  # the flag's, over the motion model's
    assert summary["sites_heard"] == ["A", "B"]
    assert summary["methods"]["snapshot"]["fix_rate"] == 0.0
    tracked = summary["methods"]["tracked"]
    assert tracked["fix_rate"] > 0.9 and tracked["median_m"] < 30.0  # about the prior's 10 m: the receiver stands


def test_odometry_on_a_receiver_that_stands_aligns_no_frame_and_the_report_says_so(tmp_path) -> None:
    """Standing still reads 0 in any frame: the campus receiver's odometry tells the track
    that it stands, but no frame's yaw, and route.json says it never aligned (null)."""
    summary, paths = evaluate_route(BagSource(BAG), load_tower_database(TOWERS), tmp_path, progress=False,
                                    aiding=AidingPlan(0.0, 5.0, 0.05))
    assert summary["aiding"] == "GNSS at the start (5 m), odometry (5% error)"
    assert summary["odometry_frame"] is None
    assert json.loads(paths[0].read_text())["summary"]["odometry_frame"] is None


def test_an_initial_position_needs_the_tracker() -> None:
    stage = FusionStage(load_tower_database(TOWERS), FusionConfig(track=False))
    with pytest.raises(ValueError, match="tracking is off"):
        stage.start_from(PositionPrior((0.0, 0.0, 0.0), np.eye(3)))
    with pytest.raises(ValueError, match="std_m"):
        InitialPose(0.0)


def test_each_recording_draws_its_own_initial_pose() -> None:
    """A set of routes started from one InitialPose drew one offset for all: with seed 0, 0.9 m for
    a claimed 5 m, and every start looked better than an operator's."""
    pose = InitialPose(5.0, heading_std_rad=0.1)
    truth = np.array([100.0, -50.0, 1.5])
    offsets = np.array([np.subtract(pose.for_recording(f"walk_s{k}").prior(truth, 0.0).position_enu[:2], truth[:2])
                        for k in range(400)])
    assert np.sqrt(np.mean(offsets**2, axis=0)) == pytest.approx([5.0, 5.0], rel=0.15)  # N(0, 5^2) per axis
    headings = [pose.for_recording(f"walk_s{k}").prior(truth, 0.0).heading_rad for k in range(400)]
    assert np.std(headings) == pytest.approx(0.1, rel=0.15)
    again = pose.for_recording("walk_s1")
    # the same recording, the same draws in any process on any machine (not Python's salted hash)
    assert again.seed == 3485779497
    assert again.prior(truth).position_enu == pose.for_recording("walk_s1").prior(truth).position_enu
    assert (again.std_m, again.heading_std_rad) == (5.0, 0.1)


def envelope_only_bag(path: Path) -> Path:
    with BagReader(BAG) as reader, BagWriter(path) as writer:
        for k, item in enumerate(reader.messages([ENVELOPE_TOPIC])):
            writer.write_envelope(envelope_from_msg(item.message))
            if k == 20:
                break
    return path


@pytest.mark.parametrize("command", ["evaluate-route", "calibrate"])
def test_route_commands_refuse_a_bag_without_ground_truth(tmp_path, capsys, command) -> None:
    bag = envelope_only_bag(tmp_path / "no_truth")
    out = tmp_path / ("out.yaml" if command == "calibrate" else "out")
    assert main([command, "--bag", str(bag), "--towers", str(TOWERS), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "no ground truth" in err and "Traceback" not in err
    assert not out.exists()
    with pytest.raises(ValueError, match="no ground truth"):
        read_truth_track(bag)


def test_route_commands_refuse_a_database_that_places_no_site(tmp_path, capsys) -> None:
    towers = tmp_path / "towers.yaml"
    towers.write_text((REPO / "config" / "towers" / "real_lte_1860.yaml").read_text())
    out = tmp_path / "out"
    assert main(["evaluate-route", "--bag", str(BAG), "--towers", str(towers), "--out", str(out), "--quiet"]) == 2
    assert "places no site" in capsys.readouterr().err and not out.exists()


def test_true_clocks_place_a_database_without_timing_offsets(tmp_path, capsys) -> None:
    """A simulated bag's sites take their clocks from its truth: a database holding positions
    alone (as config/towers/munich_walk.yaml) places no site without it and fixes with it."""
    data = yaml.safe_load(TOWERS.read_text())
    for site in data["sites"]:
        site.pop("timing_offset_us", None)  # D and E, not simulated, have none either
    towers = tmp_path / "positions_only.yaml"
    towers.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    assert main(["evaluate-route", "--bag", str(BAG), "--towers", str(towers), "--out", str(out), "--quiet"]) == 2
    assert "places no site" in capsys.readouterr().err
    assert main(["evaluate-route", "--bag", str(BAG), "--towers", str(towers), "--out", str(out), "--quiet",
                 "--true-clocks"]) == 0
    assert "true site clocks" in capsys.readouterr().out
    summary = json.loads((out / "route.json").read_text())["summary"]
    assert summary["sites_heard"] == ["A", "B", "C"] and summary["methods"]["snapshot"]["fix_rate"] > 0.5
    no_truth = envelope_only_bag(tmp_path / "no_truth")
    assert main(["evaluate-route", "--bag", str(no_truth), "--towers", str(towers), "--out", str(tmp_path / "o2"),
                 "--quiet", "--true-clocks"]) == 2
    assert "no true sites (a real recording?)" in capsys.readouterr().err


def test_replay_writes_what_the_nodes_publish_into_a_bag_ros_can_play(tmp_path) -> None:
    """``deepsync replay``: per stack the arrivals, and per fix a PoseWithCovarianceStamped in map
    (orientation unmeasured) and a NavSatFix at the same place in WGS84, next to the truth."""
    from deepsync.bag import CELL_TIMING_TOPIC, NAV_SAT_FIX_TOPIC, POSE_TOPIC, TRUTH_POSE_TOPIC, stamp_to_ns
    from deepsync.geo import LocalFrame
    from deepsync.types import UNMEASURED_VARIANCE

    out = tmp_path / "replayed"
    assert main(["replay", "--bag", str(BAG), "--towers", str(TOWERS), "--out", str(out), "--frames", "10",
                 "--quiet"]) == 0
    with BagReader(out) as bag:
        counts = bag.message_counts
        items = list(bag.messages([POSE_TOPIC, NAV_SAT_FIX_TOPIC]))
    poses = [item.message for item in items if item.topic == POSE_TOPIC]
    fixes = [item.message for item in items if item.topic == NAV_SAT_FIX_TOPIC]
    assert {item.msgtype for item in items} == {"geometry_msgs/msg/PoseWithCovarianceStamped",
                                                "sensor_msgs/msg/NavSatFix"}
    assert counts[CELL_TIMING_TOPIC] == 30 and counts[TRUTH_POSE_TOPIC] == 30
    assert 20 <= counts[POSE_TOPIC] == counts[NAV_SAT_FIX_TOPIC] <= 30
    towers = load_tower_database(TOWERS)
    frame = LocalFrame(towers.origin.latitude_deg, towers.origin.longitude_deg, towers.origin.height_m)
    truth = read_truth_track(BAG)
    for pose, fix in zip(poses, fixes):
        assert pose.header.frame_id == "map" and stamp_to_ns(pose.header.stamp) == stamp_to_ns(fix.header.stamp)
        covariance = np.asarray(pose.pose.covariance).reshape(6, 6)
        assert np.all(np.diag(covariance)[3:] == UNMEASURED_VARIANCE) and np.allclose(covariance, covariance.T)
        p = pose.pose.pose.position
        assert np.linalg.norm(np.array([p.x, p.y]) - truth.at(stamp_to_ns(pose.header.stamp))[:2]) < 100
        enu = frame.geodetic_to_enu(fix.latitude, fix.longitude, fix.altitude)
        assert np.allclose(enu, [p.x, p.y, p.z], atol=1e-3)  # the same place, in WGS84
        assert fix.position_covariance_type == 3 and np.allclose(np.reshape(fix.position_covariance, (3, 3)),
                                                                  covariance[:3, :3])


def test_sites_that_place_nothing_leave_the_evaluation_running(tmp_path) -> None:
    """Three sites at one mast cannot place the receiver: the snapshot says degenerate geometry,
    the bound is NaN or huge where rounding leaves it (it once stopped the run on a negative
    trace: "math domain error"), and the report is written."""
    data = yaml.safe_load(TOWERS.read_text())
    first = data["sites"][0]
    for site in data["sites"][1:]:
        site["latitude_deg"], site["longitude_deg"] = first["latitude_deg"], first["longitude_deg"]
    towers = tmp_path / "one_mast.yaml"
    towers.write_text(yaml.safe_dump(data))
    summary, written = evaluate_route(BagSource(BAG), load_tower_database(towers), tmp_path / "out", progress=False)
    assert summary["methods"]["snapshot"]["fix_rate"] == 0
    assert all(path.exists() for path in written)
