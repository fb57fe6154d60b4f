"""``deepsync replay`` against MCAP bags: the bundled campus bag through every stage, checked
against its ground truth, against itself (determinism), against replays that start later in the
chain (from the sync windows, from the cell timing) and against outside readers (the ``mcap``
package); a truncated input still gives a valid bag of what came before the damage.

One full replay of the campus bag is shared by the module (about 3 s on 2 cores).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from deepsync.bag import (
    CELL_TIMING_TOPIC,
    ENVELOPE_TOPIC,
    NAV_SAT_FIX_TOPIC,
    POSE_TOPIC,
    SYNC_WINDOWS_TOPIC,
    TRUTH_CELL_TIMING_TOPIC,
    TRUTH_POSE_TOPIC,
    BagReader,
    stamp_to_ns,
    typestore,
)
from deepsync.cli import main
from deepsync.eval.route import read_truth_track
from deepsync.pipeline import Pipeline, PipelineConfig
from deepsync.replay import parse_stages, replay_bag
from deepsync.towers import load_tower_database
from test_bad_input_cli import campus_bag

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "campus"
TOWERS = REPO / "config" / "towers" / "campus.yaml"
# the stacks the counts and errors below were measured with: 10 frames back to back (the
# defaults, the pedestrian's 100-frame stacks, give a 3 s bag a third as many)
CONFIG = PipelineConfig().with_choices(n_frames=10)
PRODUCED = (SYNC_WINDOWS_TOPIC, CELL_TIMING_TOPIC, POSE_TOPIC, NAV_SAT_FIX_TOPIC)


def raw_messages(bag: Path) -> dict[str, list[tuple[int, bytes]]]:
    """Per topic, (log time, CDR bytes) of every message, read with the ``mcap`` package alone."""
    found: dict[str, list[tuple[int, bytes]]] = {}
    with (bag / f"{bag.name}.mcap").open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            found.setdefault(channel.topic, []).append((message.log_time, message.data))
    return found


def poses(bag: Path) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(stamp, position, 6x6 covariance) of every published pose."""
    with BagReader(bag) as reader:
        return [(stamp_to_ns(m.message.header.stamp),
                 np.array([getattr(m.message.pose.pose.position, k) for k in "xyz"]),
                 np.asarray(m.message.pose.covariance).reshape(6, 6))
                for m in reader.messages([POSE_TOPIC])]


@pytest.fixture(scope="module")
def full(tmp_path_factory) -> tuple[Path, object]:
    out = tmp_path_factory.mktemp("replay") / "full"
    summary = replay_bag(BAG, out, load_tower_database(TOWERS), CONFIG, progress=False)
    return out, summary


def test_the_published_poses_follow_the_truth(full) -> None:
    """README's campus numbers: tracked 8.3 m median (90 % of stacks), snapshot 18 m (73 %).
    Replay publishes the tracker's fix, else the snapshot's: measured 28 poses, 8.3 m median,
    10.7 m p90. The bounds (12 m, 20 m) leave room for a stack or two more from the snapshot
    and fail if the tracker stops working (the snapshot's 18 m) or timing degrades."""
    out, summary = full
    assert summary.damage is None and summary.stacks == 30 and not summary.health
    truth = read_truth_track(BAG)
    published = poses(out)
    assert len(published) >= 25  # 90 % tracked, and the snapshot fills in before the tracker starts
    errors = np.array([np.linalg.norm(position[:2] - truth.at(stamp)[:2]) for stamp, position, _ in published])
    assert np.median(errors) < 12.0
    assert np.percentile(errors, 90) < 20.0
    # a covariance in metres, not millimetres, and never vaguer than a published pose may be
    limit = PipelineConfig().fusion.tracker.max_std_m
    for _, _, covariance in published:
        assert 1.0 < np.sqrt(np.trace(covariance[:2, :2])) <= limit


def test_the_output_holds_every_stage_and_the_truth_with_the_nodes_types(full) -> None:
    out, summary = full
    with BagReader(out) as reader:
        topics, counts = reader.topics, reader.message_counts
        assert reader.verify().complete  # sealed with CRCs like every DeepSync bag
    assert topics == {
        SYNC_WINDOWS_TOPIC: "deepsync_msgs/msg/SyncWindowArray",
        CELL_TIMING_TOPIC: "deepsync_msgs/msg/CellTimingArray",
        POSE_TOPIC: "geometry_msgs/msg/PoseWithCovarianceStamped",
        NAV_SAT_FIX_TOPIC: "sensor_msgs/msg/NavSatFix",
        TRUTH_POSE_TOPIC: "geometry_msgs/msg/PoseStamped",
        TRUTH_CELL_TIMING_TOPIC: "deepsync_msgs/msg/CellTimingArray",
    }
    assert ENVELOPE_TOPIC not in topics  # only with --copy-inputs
    assert counts[SYNC_WINDOWS_TOPIC] == counts[CELL_TIMING_TOPIC] == 30
    assert counts[POSE_TOPIC] == counts[NAV_SAT_FIX_TOPIC] == summary.poses
    with BagReader(BAG) as recorded:
        assert counts[TRUTH_POSE_TOPIC] == recorded.message_counts[TRUTH_POSE_TOPIC]


def test_the_mcap_package_reads_the_output_with_standard_schemas(full) -> None:
    """Foxglove and ros2 bag play read the file through the MCAP format, not through us."""
    out, _ = full
    with (out / f"{out.name}.mcap").open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        schemas = {channel.topic: summary.schemas[channel.schema_id] for channel in summary.channels.values()}
        assert summary.statistics.message_count == sum(len(v) for v in raw_messages(out).values())
    assert schemas[POSE_TOPIC].name == "geometry_msgs/msg/PoseWithCovarianceStamped"
    assert schemas[NAV_SAT_FIX_TOPIC].name == "sensor_msgs/msg/NavSatFix"
    assert all(schema.encoding == "ros2msg" for schema in schemas.values())
    store = typestore()
    pose = store.deserialize_cdr(raw_messages(out)[POSE_TOPIC][0][1], "geometry_msgs/msg/PoseWithCovarianceStamped")
    assert pose.header.frame_id == "map"


def test_two_replays_write_identical_messages(full, tmp_path) -> None:
    out, _ = full
    again = tmp_path / "again"
    replay_bag(BAG, again, load_tower_database(TOWERS), CONFIG, progress=False)
    first, second = raw_messages(out), raw_messages(again)
    assert set(first) == set(second)
    for topic in PRODUCED:
        assert first[topic] == second[topic], topic


def test_fusion_alone_from_the_replayed_cell_timing_gives_the_same_poses(full, tmp_path) -> None:
    out, _ = full
    fused = tmp_path / "fused"
    summary = replay_bag(out, fused, load_tower_database(TOWERS), CONFIG, stages=["fusion"], progress=False)
    assert summary.stages == ("fusion",) and summary.inputs == 30
    full_messages, fused_messages = raw_messages(out), raw_messages(fused)
    assert SYNC_WINDOWS_TOPIC not in fused_messages and CELL_TIMING_TOPIC not in fused_messages
    for topic in (POSE_TOPIC, NAV_SAT_FIX_TOPIC):  # float64 arrivals on the wire: bit for bit
        assert fused_messages[topic] == full_messages[topic], topic


def test_timing_and_fusion_from_the_replayed_sync_windows_match_the_full_chain(full, tmp_path) -> None:
    """The windows travel as float32 (as they do in the pipeline), so the arrivals match to
    float rounding in the estimator, far below the 1e-3 samples that would move a pose by 15 cm."""
    out, _ = full
    timed = tmp_path / "timed"
    summary = replay_bag(out, timed, load_tower_database(TOWERS), CONFIG, stages=["timing", "fusion"], progress=False)
    assert summary.stages == ("timing", "fusion") and summary.stacks == 30
    with BagReader(out) as a, BagReader(timed) as b:
        mine = [m.message for m in a.messages([CELL_TIMING_TOPIC])]
        theirs = [m.message for m in b.messages([CELL_TIMING_TOPIC])]
    assert len(mine) == len(theirs) == 30
    for x, y in zip(mine, theirs):
        assert [c.pci for c in x.cells] == [c.pci for c in y.cells]
        np.testing.assert_allclose([c.toa for c in x.cells], [c.toa for c in y.cells], atol=1e-6, rtol=0)
    full_poses, timed_poses = poses(out), poses(timed)
    assert [p[0] for p in full_poses] == [p[0] for p in timed_poses]
    for (_, x, cx), (_, y, cy) in zip(full_poses, timed_poses):
        np.testing.assert_allclose(x, y, atol=1e-4, rtol=0)
        np.testing.assert_allclose(cx, cy, rtol=1e-6, atol=1e-9)


def test_copy_inputs_keeps_the_envelope(tmp_path) -> None:
    source = tmp_path / "short"
    campus_bag(source, 35)
    out = tmp_path / "copied"
    summary = replay_bag(source, out, load_tower_database(TOWERS), CONFIG, copy_inputs=True, progress=False)
    assert summary.written[ENVELOPE_TOPIC] == 35 and summary.stacks == 3
    assert raw_messages(out)[ENVELOPE_TOPIC] == raw_messages(source)[ENVELOPE_TOPIC]


def test_a_truncated_input_gives_a_valid_bag_of_what_came_before_the_damage(full, tmp_path, capsys) -> None:
    """The whole chain up to the cut, then exit 1 with the damage named: the output is sealed
    and its poses are exactly the full replay's first ones."""
    out, _ = full
    cut = tmp_path / "cut"
    cut.mkdir()
    for f in BAG.iterdir():
        (cut / f.name.replace("campus", "cut")).write_bytes(f.read_bytes())
    (cut / "metadata.yaml").write_text((BAG / "metadata.yaml").read_text().replace("campus.mcap", "cut.mcap"))
    mcap = cut / "cut.mcap"
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    partial = tmp_path / "partial"
    assert main(["replay", "--in", str(cut), "--towers", str(TOWERS), "--out", str(partial), "--frames", "10",
                 "--quiet"]) == 1
    captured = capsys.readouterr()
    assert "cut short" in captured.err and str(mcap) in captured.err and "Traceback" not in captured.err
    assert "cannot be opened whole" in captured.out
    with BagReader(partial) as reader:
        assert reader.verify().complete
        counts = reader.message_counts
    assert 5 <= counts[CELL_TIMING_TOPIC] < 30
    got, want = poses(partial), poses(out)
    assert 0 < len(got) < len(want)
    for (s1, x1, c1), (s2, x2, c2) in zip(got, want):
        assert s1 == s2 and np.array_equal(x1, x2) and np.array_equal(c1, c2)


@pytest.mark.parametrize("text, message", [
    ("sync,fusion", "contiguous part of the chain"),
    ("fusion,timing", "contiguous part of the chain"),
    ("sync,sync", "contiguous part of the chain"),
    ("timing,", "no stage ''"),
    ("track", "no stage 'track'"),
])
def test_a_wrong_stage_list_is_refused(text, message) -> None:
    with pytest.raises(ValueError, match=message):
        parse_stages(text)


def test_a_stage_list_that_starts_where_the_bag_has_no_data_is_refused(tmp_path, capsys) -> None:
    out = tmp_path / "out"
    assert main(["replay", "--in", str(BAG), "--towers", str(TOWERS), "--out", str(out),
                 "--stages", "timing,fusion", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"no {SYNC_WINDOWS_TOPIC} (deepsync_msgs/msg/SyncWindowArray)" in err
    assert "could start at --stages sync,timing,fusion" in err and "Traceback" not in err
    assert not out.exists()
    assert main(["replay", "--in", str(BAG), "--towers", str(TOWERS), "--out", str(out),
                 "--stages", "sync,fusion", "--quiet"]) == 2
    assert "contiguous part of the chain" in capsys.readouterr().err and not out.exists()


def test_an_interrupted_replay_leaves_nothing(tmp_path) -> None:
    out = tmp_path / "interrupted"

    def interrupt(timed, pipeline: Pipeline) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        replay_bag(BAG, out, load_tower_database(TOWERS), CONFIG, progress=False, on_stack=interrupt)
    assert not out.exists() and not list(tmp_path.iterdir())


def test_the_demo_replays_the_bundled_walk_into_a_bag_a_map_a_cdf_and_a_table(tmp_path, capsys) -> None:
    """``deepsync demo``: the walk (bags/campus_route, 5.5 s, 3 LOS sites) through every stage
    with the default, a pedestrian's 100-frame stacks every 20 frames. Measured: 21 poses of 23
    stacks (the first two before the cells are confirmed), published median 5.5 m, p90 8.0 m;
    the bounds leave room for the snapshot taking over a few stacks (9 m median), not for a
    broken tracker."""
    import json

    assert main(["demo", "--out", str(tmp_path), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "4 cells (PCI 56, 120, 121, 301) on 3 sites (A, B, C)" in printed
    assert "published" in printed and "x real time" in printed
    summary = json.loads((tmp_path / "route.json").read_text())["summary"]
    tracked = summary["methods"]["tracked"]
    assert summary["stacks"] == 23 and tracked["fix_rate"] > 0.8 and tracked["median_m"] < 8.0
    for name in ("route_map.png", "route_cdf.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with BagReader(tmp_path / "replay") as reader:
        counts = reader.message_counts
    assert counts[POSE_TOPIC] == counts[NAV_SAT_FIX_TOPIC] >= 19 and counts[TRUTH_POSE_TOPIC] == 55
