"""A new user's first hour (#45): what the commands say about themselves and their output."""

from __future__ import annotations

from pathlib import Path

import pytest

from deepsync.cli import build_parser, main
from deepsync.eval.cell_search import runners_up
from deepsync.sync.search import Candidate

REPO = Path(__file__).resolve().parents[1]


def _help(capsys, *command: str) -> str:
    with pytest.raises(SystemExit):
        build_parser().parse_args([*command, "--help"])
    return " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize("command, option, said", [
    (("info",), "--bag", "message counts"),
    (("demo",), "--workers", "simulating a --simulate recording"),
    (("evaluate-timing",), "--split", "default test"),
    (("evaluate-timing",), "--data", "default data/timing"),
    (("train",), "--replace-shipped", "shipped"),
])
def test_every_option_says_what_it_does(capsys, command, option, said):
    text = _help(capsys, *command)
    assert said in text.split(option, 1)[1], text


def test_a_cell_is_never_its_own_runner_up():
    """The tower database may report a PCI from below the top of the ranking: its runners-up
    are the others, best first."""
    ranked = [Candidate(121, 0.9, 0), Candidate(120, 0.8, 0), Candidate(57, 0.5, 0), Candidate(407, 0.4, 0),
              Candidate(3, 0.3, 0)]
    assert runners_up(120, ranked) == [121, 57, 407]
    assert runners_up(121, ranked) == [120, 57, 407]
    assert runners_up(5, ranked[:1]) == [121] and runners_up(121, ranked[:1]) == []


def test_detect_explains_its_words_once(capsys):
    assert main(["detect", "--bag", str(REPO / "bags" / "campus"), "--towers",
                 str(REPO / "config" / "towers" / "campus.yaml"), "--frames", "10"]) == 0
    out = capsys.readouterr().out
    legend = [line for line in out.splitlines() if line.strip().startswith("tentative:")]
    assert len(legend) == 1 and "runners-up:" in legend[0] and "misaligned:" in legend[0]
    for line in out.splitlines():
        if "runners-up" in line and "PCI" in line:
            pci = line.split()[1]
            assert pci not in line.split("runners-up", 1)[1].split("(")[0].replace(",", " ").split(), line


def test_replay_says_how_many_stacks_gave_no_pose_and_why(tmp_path, capsys):
    """replay said "no stage reported a problem" while most stacks of a bag gave no pose: it now
    counts the published answers as evaluate-route does (one summary, ``answer_counts``)."""
    from deepsync.bag import POSE_TOPIC
    from deepsync.replay import replay_bag
    from deepsync.towers import load_tower_database

    towers = load_tower_database(REPO / "config" / "towers" / "campus.yaml")
    summary = replay_bag(REPO / "bags" / "campus_route", tmp_path / "out", towers, progress=False)
    fixes = summary.fixes
    assert fixes["fixes"] == summary.written[POSE_TOPIC] and fixes["epochs"] == summary.stacks
    assert sum(fixes["no_fix_reasons"].values()) == fixes["epochs"] - fixes["fixes"] > 0
    assert sum(summary.sites_heard_per_stack.values()) == summary.stacks
    assert main(["replay", "--in", str(REPO / "bags" / "campus_route"), "--towers",
                 str(REPO / "config" / "towers" / "campus.yaml"), "--out", str(tmp_path / "again"), "--quiet"]) == 0
    out = capsys.readouterr().out
    reasons = ", ".join(f"{reason} {n}" for reason, n in fixes["no_fix_reasons"].items())
    assert f"{fixes['fixes']} of {fixes['epochs']} stacks gave a pose" in out and f"no fix: {reasons}" in out
    assert "heard per stack" in out
    blind = replay_bag(REPO / "bags" / "campus_route", tmp_path / "blind", None, progress=False)
    assert blind.fixes == {}  # no fusion, nothing to count


def test_export_onnx_says_what_it_does_before_its_long_steps(tmp_path, capsys, monkeypatch):
    """The export takes a minute and a half: what it is doing is said before it starts."""
    pytest.importorskip("torch", reason="the export needs torch")
    from deepsync.timing import export

    said_before = {}

    def export_onnx(checkpoint, path):
        said_before["export"] = capsys.readouterr().out
        return tmp_path / "net.onnx"

    def check_onnx(path, checkpoint):
        said_before["check"] = capsys.readouterr().out
        return 1e-6

    monkeypatch.setattr(export, "export_onnx", export_onnx)
    monkeypatch.setattr(export, "check_onnx", check_onnx)
    assert main(["export-onnx", "--out", str(tmp_path / "net.onnx")]) == 0
    assert "exporting: torch's exporter traces the network" in said_before["export"]
    assert "done in" in said_before["check"] and "checking it in onnxruntime" in said_before["check"]
    assert "docs/timing_network.md" in said_before["check"] and "1.00e-06" in capsys.readouterr().out


def test_calibrate_keeps_the_tower_files_comments_and_layout(tmp_path, capsys):
    """calibrate wrote its database with yaml.safe_dump: every comment of the input was lost.
    Now only the values that changed are written into the input's text, and the file still
    reads back as the calibrated database exactly."""
    import dataclasses

    from deepsync.towers import load_tower_database, tower_database_to_dict, write_tower_database

    source = REPO / "config" / "towers" / "campus.yaml"
    original = source.read_text()
    out = tmp_path / "calibrated.yaml"
    assert main(["calibrate", "--bag", str(REPO / "bags" / "campus_route"), "--towers", str(source),
                 "--out", str(out), "--quiet"]) == 0
    assert "without the comments" not in capsys.readouterr().out
    written = out.read_text()
    comments = [line for line in original.splitlines() if line.lstrip().startswith("#")]
    assert comments and all(line in written.splitlines() for line in comments)
    assert "- {pci: 120, earfcn: 2000, bandwidth_mhz: 10}" in written  # the flow style kept
    calibrated = load_tower_database(out)
    assert calibrated.sites[1].timing_drift_ns_per_s is not None  # the calibration is in it
    # a changed value, a key added and one removed: read back exactly, the rest untouched
    site = dataclasses.replace(calibrated.sites[0], timing_offset_us=1.25, timing_drift_ns_per_s=None)
    changed = dataclasses.replace(calibrated, sites=(site, *calibrated.sites[1:]))
    again = tmp_path / "again.yaml"
    assert write_tower_database(changed, again, like=out)
    assert tower_database_to_dict(load_tower_database(again)) == tower_database_to_dict(changed)
    assert all(line in again.read_text().splitlines() for line in comments)
    assert write_tower_database(load_tower_database(source), again, like=source) and again.read_text() == original


@pytest.fixture(scope="module")
def walk():
    """The demo's walk replayed and fused, as the demo's figures see it."""
    from deepsync.eval.route import replay_route
    from deepsync.fusion.anchors import Anchors
    from deepsync.sources import BagSource
    from deepsync.towers import load_tower_database

    towers = load_tower_database(REPO / "config" / "towers" / "campus.yaml")
    return replay_route(BagSource(REPO / "bags" / "campus_route"), towers, progress=False), Anchors(towers)


def test_the_route_map_draws_every_fix_and_its_zoom_has_units_and_hides_no_site(walk):
    import matplotlib.pyplot as plt

    from deepsync.eval.route_figures import map_figure

    run, anchors = walk
    figure = map_figure(run, anchors)
    try:
        ax = figure.axes[0]
        labels = ax.get_legend_handles_labels()[1]
        assert "snapshot fixes" in labels and "tracked fixes" in labels
        (inset,) = ax.child_axes  # the walk is metres long among sites hundreds of metres apart
        assert "(m)" in inset.get_xlabel() and "(m)" in inset.get_ylabel()
        assert any(line.get_label() == "snapshot fixes" for line in inset.get_lines())
        figure.canvas.draw()
        box = inset.get_tightbbox()
        names = [text for text in ax.texts if text.get_text() in anchors.anchors]
        assert len(names) == len(anchors.anchors)
        assert not [t.get_text() for t in names if t.get_window_extent().overlaps(box)]
        assert "campus_route" in ax.get_title()
    finally:
        plt.close(figure)


def test_the_cdf_names_its_bag_and_the_timeline_has_a_title_integer_site_counts_and_says_what_nees_is(walk):
    import matplotlib.pyplot as plt

    from deepsync.eval.route_figures import cdf_figure, timeline_figure

    run, _ = walk
    cdf = cdf_figure(run)
    timeline = timeline_figure(run)
    try:
        assert "campus_route" in cdf.axes[0].get_title()
        errors, sites, scores = timeline.axes[:3]
        assert "campus_route" in errors.get_title()
        timeline.canvas.draw()
        ticks = [t for t in sites.get_yticks() if sites.get_ylim()[0] <= t <= sites.get_ylim()[1]]
        assert ticks and all(float(t).is_integer() for t in ticks)
        assert "covariance" in scores.get_ylabel()
        assert any("honest" in label for label in scores.get_legend_handles_labels()[1])
    finally:
        plt.close(cdf)
        plt.close(timeline)
