"""A new user's first hour (#45): what the commands say about themselves and their output."""

from __future__ import annotations

from pathlib import Path

import numpy as np
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
    assert "docs/design/timing_network.md" in said_before["check"] and "1.00e-06" in capsys.readouterr().out


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


def test_the_route_map_draws_buildings_beneath_the_route_without_widening_the_view(walk):
    """A ray-traced scene's outlines (evaluate-route reads them from the recorded scenario): one
    block on the route, one a kilometre off, which must not zoom the map out."""
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    from deepsync.eval.route_figures import map_figure

    run, anchors = walk
    plain = map_figure(run, anchors)
    near = np.array(run.epochs[0].truth_enu[:2]) + np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 20.0], [0.0, 20.0]])
    figure = map_figure(run, anchors, [near, near + 5000.0])
    try:
        ax = figure.axes[0]
        (blocks,) = [c for c in ax.collections if isinstance(c, PolyCollection)]
        assert len(blocks.get_paths()) == 2 and blocks.get_zorder() < min(line.get_zorder() for line in ax.get_lines())
        assert "buildings" in ax.get_legend_handles_labels()[1]
        assert ax.get_xlim() == plain.axes[0].get_xlim() and ax.get_ylim() == plain.axes[0].get_ylim()
        assert any(isinstance(c, PolyCollection) for c in ax.child_axes[0].collections)  # in the zoom too
    finally:
        plt.close(figure)
        plt.close(plain)


def test_a_bag_of_a_statistical_scenario_has_no_buildings(monkeypatch):
    from deepsync.eval.route import recorded_buildings
    from deepsync.sources import BagSource

    monkeypatch.chdir(REPO)  # where the bag's provenance names its scenario from
    source = BagSource(REPO / "bags" / "campus_route")
    assert source.scenario_path().is_file()  # read, and found statistical: not an unreadable file
    assert recorded_buildings(source) == []


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


# -- scripts/debian_packages.sh (scripts/setup.sh's optional packages), against fake apt tools --

LOCKED = "E: Could not get lock /var/lib/dpkg/lock-frontend. It is held by process 4242 (unattended-upgr)"


def _debian_packages(where, apt_get: str, uid: int = 0, wait: int = 30, sudo: bool = False):
    """Runs the script in a fresh folder ``where`` with dpkg-query saying nothing is installed,
    ``apt_get`` as apt-get's body (its calls listed in ``calls``), ``id -u`` printing ``uid``,
    sleep returning at once; returns (exit code, output, calls)."""
    import subprocess

    bin_dir = where / "bin"
    bin_dir.mkdir(parents=True)
    calls = where / "calls"
    tools = {"dpkg-query": "echo unknown", "id": f'[ "$1" = -u ] && echo {uid} || /usr/bin/id "$@"',
             "apt-get": f'echo "$@" >> {calls}\nn=$(wc -l < {calls})\n{apt_get}', "sleep": "exit 0"}
    if sudo:
        tools["sudo"] = '[ "$1" = -n ] && shift; [ "$1" = true ] && exit 0; "$@"'
    for name, body in tools.items():
        (bin_dir / name).write_text(f"#!/bin/bash\n{body}\n")
        (bin_dir / name).chmod(0o755)
    env = {"PATH": f"{bin_dir}:/usr/bin:/bin", "DEEPSYNC_APT_WAIT": str(wait), "DEEPSYNC_APT_RETRY": "1",
           "HOME": str(where)}
    if not sudo:  # a machine without sudo: the fake bin comes first, and /usr/bin's is hidden
        env["PATH"] = f"{bin_dir}:{_without_sudo(where)}"
    done = subprocess.run(["bash", str(REPO / "scripts" / "debian_packages.sh")], capture_output=True, text=True,
                          env=env, timeout=60, stdin=subprocess.DEVNULL)
    return done.returncode, done.stdout + done.stderr, calls.read_text().splitlines() if calls.exists() else []


def _without_sudo(tmp_path) -> str:
    """A directory of links to /usr/bin's and /bin's tools, sudo left out."""
    import os

    tools = tmp_path / "tools"
    if not tools.exists():
        tools.mkdir()
        for root in ("/usr/bin", "/bin"):
            for name in os.listdir(root):
                if name != "sudo" and not (tools / name).exists():
                    (tools / name).symlink_to(os.path.join(root, name))
    return str(tools)


def test_setup_waits_for_the_dpkg_lock_and_says_what_it_installs_first(tmp_path):
    code, out, calls = _debian_packages(tmp_path / "held", f'[ "$n" -le 2 ] && {{ echo "{LOCKED}" >&2; exit 100; }}; exit 0')
    assert code == 0 and "Debian packages installed" in out, out
    assert out.index("installing them with") < out.index("apt-get update")  # said before it is done
    assert out.count("holds the dpkg lock (held by process 4242 (unattended-upgr)); waiting up to 30 s") == 1, out
    assert "E: Could not" not in out  # apt's raw error is not what the user reads
    assert [c.split()[1] for c in calls] == ["update", "update", "update", "install"]


def test_setup_skips_the_optional_packages_with_a_line_when_the_lock_stays_held_or_apt_fails(tmp_path):
    code, out, _ = _debian_packages(tmp_path / "held", f'echo "{LOCKED}" >&2; exit 100', wait=2)
    assert code == 0 and "still holds the dpkg lock after 2 s" in out and "tests will skip" in out, out
    code, out, calls = _debian_packages(tmp_path / "offline", 'echo "E: Failed to fetch http://deb.debian.org/x  '
                                        'Temporary failure" >&2; exit 100')
    assert code == 0 and "apt-get update failed" in out and "Temporary failure" in out and len(calls) == 1, out


def test_setup_without_root_or_sudo_says_how_to_add_the_packages_later(tmp_path):
    code, out, calls = _debian_packages(tmp_path / "user", "exit 0", uid=1000)
    assert code == 0 and "needs root or sudo" in out and "apt-get install python3-rosidl" in out and not calls, out
    code, out, calls = _debian_packages(tmp_path / "sudoer", "exit 0", uid=1000, sudo=True)
    assert code == 0 and "as root through sudo" in out and "Debian packages installed" in out, out


def _resolves(dotted: str) -> bool:
    """Whether ``a.b.c.Name`` is a module, or an attribute of the longest module prefix."""
    import importlib

    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            found = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for name in parts[cut:]:
            if not hasattr(found, name):
                return False
            found = getattr(found, name)
        return True
    return False


def test_every_module_a_config_files_comments_name_exists():
    """A copied training config's header named modules that did not exist: what the shipped
    configs point a reader to must be there."""
    import re

    files = [*(REPO / "config").rglob("*.yaml"), *(REPO / "src" / "deepsync_ros" / "config").rglob("*.yaml")]
    named = {(path.relative_to(REPO).as_posix(), dotted) for path in files for line in path.read_text().splitlines()
             if "#" in line for dotted in re.findall(r"\bdeepsync(?:_ros)?(?:\.\w+)+", line.split("#", 1)[1])}
    assert any(dotted == "deepsync.training.train.TrainConfig" for _, dotted in named)
    assert _resolves("deepsync.timing.model.TimingNetConfig") and not _resolves("deepsync.timing.model.NoSuch")
    missing = sorted(f"{path}: {dotted}" for path, dotted in named if not _resolves(dotted.rstrip(".")))
    assert not missing, f"config comments name what does not exist: {missing}"
