"""deepsync_ros.aiding without ROS: NavSatFix and Odometry messages (rosbags' classes, the same
fields rclpy's carry) into the fusion stage, what is refused and why, the diagnostics, and the
learned tower database written atomically, a failed write said and tried again."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from deepsync.bag import typestore
from deepsync.bag.convert import gnss_fix_from_msg, make_header, odometry_from_msg
from deepsync.fusion.stage import FusionStage
from deepsync.towers import load_tower_database
from deepsync.types import Severity
from deepsync.fusion.tracker import OdometryFrame
from deepsync_ros.aiding import AidingInputs, LearnedTowers, describe_odometry_frame

REPO = Path(__file__).resolve().parents[1]
TOWERS = REPO / "config" / "towers" / "campus.yaml"
STAMP_NS = 1_767_225_600_500_000_000


def cls(name: str) -> type:
    return typestore().types[name]


def navsat(frame: str = "gnss", latitude: float = 38.98690, status: int = 0, covariance_type: int = 2,
           stamp_ns: int = STAMP_NS) -> object:
    return cls("sensor_msgs/msg/NavSatFix")(
        header=make_header(stamp_ns, frame), status=cls("sensor_msgs/msg/NavSatStatus")(status=status, service=1),
        latitude=latitude, longitude=-76.94260, altitude=10.0,
        position_covariance=np.diag([4.0, 9.0, 16.0]).ravel(), position_covariance_type=covariance_type)


def odometry(yaw: float = 0.0, vx: float = 1.0, vy: float = 0.0, frame: str = "odom",
             covariance: np.ndarray | None = None, stamp_ns: int = STAMP_NS, w: float | None = None) -> object:
    twist_covariance = np.zeros((6, 6)) if covariance is None else covariance
    orientation = cls("geometry_msgs/msg/Quaternion")(
        x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2) if w is None else w)
    pose = cls("geometry_msgs/msg/Pose")(position=cls("geometry_msgs/msg/Point")(x=0.0, y=0.0, z=0.0),
                                         orientation=orientation)
    vector = cls("geometry_msgs/msg/Vector3")
    twist = cls("geometry_msgs/msg/Twist")(linear=vector(x=vx, y=vy, z=0.0), angular=vector(x=0.0, y=0.0, z=0.0))
    return cls("nav_msgs/msg/Odometry")(
        header=make_header(stamp_ns, frame), child_frame_id="base_link",
        pose=cls("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=np.zeros(36)),
        twist=cls("geometry_msgs/msg/TwistWithCovariance")(twist=twist, covariance=twist_covariance.ravel()))


def test_a_navsatfix_becomes_a_gnss_fix_with_its_covariance_and_no_fix_is_none():
    fix = gnss_fix_from_msg(navsat())
    assert fix.stamp_ns == STAMP_NS and fix.frame_id == "gnss" and fix.latitude_deg == pytest.approx(38.98690)
    assert np.allclose(np.diag(fix.covariance_enu), [4.0, 9.0, 16.0])
    assert gnss_fix_from_msg(navsat(covariance_type=0)).covariance_enu is None  # unknown: fusion's sigma
    assert gnss_fix_from_msg(navsat(status=-1)) is None
    with pytest.raises(ValueError, match="NavSatFix in frame 'gnss': GnssFix.latitude_deg nan"):
        gnss_fix_from_msg(navsat(latitude=math.nan))


def test_odometry_is_turned_from_the_body_into_its_frame_with_its_covariance_floored():
    body_covariance = np.zeros((6, 6))
    body_covariance[0, 0], body_covariance[1, 1] = 0.04, 0.0001
    velocity = odometry_from_msg(odometry(yaw=math.pi / 2, vx=2.0, covariance=body_covariance), "map", 0.05)
    assert np.allclose(velocity.velocity, (0.0, 2.0), atol=1e-12)  # forward, the body turned 90 deg: north
    assert np.allclose(velocity.covariance, np.diag([0.05**2, 0.04]), atol=1e-12)  # turned with it, floored
    assert not velocity.in_map_frame
    assert velocity.heading_rad == pytest.approx(math.pi / 2)  # the pose's yaw: the body's heading
    assert odometry_from_msg(odometry(frame="/map"), "map", 0.05).in_map_frame
    with pytest.raises(ValueError, match="not a unit quaternion"):
        odometry_from_msg(odometry(w=3.0), "map", 0.05)
    with pytest.raises(ValueError, match="twist or twist covariance is not finite"):
        odometry_from_msg(odometry(vx=math.nan), "map", 0.05)


def inputs(**kwargs) -> AidingInputs:
    return AidingInputs(FusionStage(load_tower_database(TOWERS)), map_frame="map", antenna_frame="deepsync_antenna",
                        use_gnss=True, use_odometry=True, **kwargs)


def test_fixes_in_the_wrong_frame_our_own_or_without_a_position_are_refused_with_the_reason():
    aiding = inputs(gnss_frame="gnss")
    assert aiding.gnss(navsat()) is None and aiding.taken["gnss"] == 1
    assert "this node's own output" in aiding.gnss(navsat(frame="deepsync_antenna", stamp_ns=STAMP_NS + 1))
    assert "gnss_frame is 'gnss'" in aiding.gnss(navsat(frame="gps_link", stamp_ns=STAMP_NS + 2))
    assert "latitude_deg nan" in aiding.gnss(navsat(latitude=math.nan, stamp_ns=STAMP_NS + 3))
    assert aiding.gnss(navsat(status=-1, stamp_ns=STAMP_NS + 4)) is None and aiding.no_fix == 1
    assert "not after the one before" in aiding.gnss(navsat(stamp_ns=STAMP_NS - 1))
    assert aiding.refused["gnss"] == 4
    values = dict(aiding.report().values)
    assert values["GNSS fixes taken"] == "1" and values["GNSS NO_FIX messages"] == "1"
    assert "not after the one before" in values["last refusal"]


def test_odometry_back_in_time_is_refused_and_stale_odometry_warns():
    aiding = inputs(odometry_timeout_s=1.0)
    assert aiding.odometry(odometry()) is None
    assert "not after the one before" in aiding.odometry(odometry(stamp_ns=STAMP_NS - 10))
    aiding.stacked(STAMP_NS + 500_000_000, ())
    assert aiding.report().level is Severity.OK
    aiding.stacked(STAMP_NS + 3_000_000_000, ())
    report = aiding.report()
    assert report.level is Severity.WARN and "odometry stale (3.0 s" in report.message
    assert "motion model alone" in report.message


def test_the_diagnostics_say_the_odometry_frame_or_what_would_align_it():
    aiding = inputs()
    assert "not aligned yet" in dict(aiding.report().values)["odometry frame (yaw from map, scale error)"]
    assert describe_odometry_frame(OdometryFrame(2.0, 0.031, -0.069, 0.018)) == "+2.000 +- 0.031 rad, -6.9 +- 1.8 %"


def test_the_learned_database_is_written_atomically_and_a_failed_write_is_said_and_retried(tmp_path):
    stage = FusionStage(load_tower_database(TOWERS))
    learned = LearnedTowers(str(tmp_path / "learned.yaml"), period_s=60.0)
    assert not learned.due(0.0) and not learned.due(59.0) and learned.due(60.0)
    assert learned.save(stage, 60.0) is None and not (tmp_path / "learned.yaml").exists()  # nothing learned yet
    stage.reference_ns = stage.anchors.epoch_ns
    from test_fusion_aiding import biased_route, run

    run(biased_route(1, 3.0), stage.tracker)
    stage.tracker._sites = {name: site for name, site in zip(("A", "B", "C"), stage.tracker._sites.values())}
    blocked = LearnedTowers(str(tmp_path / "missing" / "learned.yaml"), period_s=60.0)
    error = blocked.save(stage, 0.0)
    assert error is not None and "could not write the learned tower database" in error and "missing" in error
    assert ("learned towers error", error) in blocked.values()
    blocked.path = tmp_path / "learned.yaml"  # the folder is back: the next period writes
    assert blocked.save(stage, 60.0) is None and blocked.error is None and blocked.written == 1
    again = load_tower_database(tmp_path / "learned.yaml")
    assert {site.name for site in again.sites} == {site.name for site in stage.anchors.towers.sites}
    assert not list(tmp_path.glob(".learned.yaml.*"))  # no temporary left behind
    aiding = AidingInputs(stage, map_frame="map", antenna_frame="deepsync_antenna", learned=blocked)
    blocked.error = "could not write the learned tower database 'x': disk full"
    report = aiding.report()
    assert report.level is Severity.WARN and "disk full" in report.message
    assert any(key.startswith("site A learned bias") for key, _ in report.values)
