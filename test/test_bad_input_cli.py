"""Bad-input matrix: the ``deepsync`` command and the signals that stop it (one file of
``test/test_bad_input_*.py``; the module docstring of ``test_bad_input_streams.py`` explains the
matrix).

Outcome class here: a clear one-line error naming the cause, exit status 2 (argparse's own
usage errors are 2 as well), no traceback, and nothing written; an interrupt (Ctrl-C, SIGTERM)
exits with 130 within a second, leaves no partial bag and no worker process behind. Replay adds
one class: a damaged input (cut short, a corrupt chunk) is replayed up to the damage into a valid
bag, the damage named, exit status 1; stage events (gaps, resets) are counted per kind.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from deepsync.cli import main

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "campus"
SCENARIO = REPO / "config" / "scenarios" / "campus.yaml"
TOWERS = REPO / "config" / "towers" / "campus.yaml"
DEEPSYNC = Path(sys.executable).parent / "deepsync"


def fails(args: list[str], capsys, message: str) -> None:
    """``deepsync args`` ends with exit status 2 and one error line that says ``message``."""
    try:
        status = main(args)
    except SystemExit as stop:  # argparse refuses before the command runs
        status = stop.code
    err = capsys.readouterr().err
    assert status == 2, err
    assert message in err, err
    assert "Traceback" not in err
    assert len(err) < 2000, f"{len(err)} characters"  # argparse's usage, and one line


@pytest.fixture
def cu8(tmp_path) -> Path:
    path = tmp_path / "noise.cu8"
    np.random.default_rng(1).integers(100, 156, 2 * 25 * 19200).astype(np.uint8).tofile(path)
    return path


@pytest.mark.parametrize("args, message", [
    (["--workers", "0"], "0 workers: give 1..64"),
    (["--workers", "1000"], "give 1..64"),
    (["--workers", "two"], "not a whole number"),
    (["--seconds", "1e-9"], "at least one 10 ms frame"),
    (["--seconds", "nan"], "must be a positive number"),
    (["--seconds", "-1"], "must be a positive number"),
    (["--seconds", "1e308"], "argument --seconds: '1e308' s is more than a day"),  # OverflowError on main
    (["--seed", "x"], "argument --seed: 'x' is not a whole number"),
    (["--seed=-1"], "argument --seed: must be in [0, 9223372036854775807]"),
    (["--seed", str(2**64)], "argument --seed: must be in [0, 9223372036854775807]"),
    (["--seed", str(10**308)], "], got 100000000000000000...0000000000000000000"),  # on main: all 309 digits
], ids=["workers_0", "workers_1000", "workers_word", "seconds_tiny", "seconds_nan", "seconds_negative",
        "seconds_1e308", "seed_word", "seed_negative", "seed_beyond_int64", "seed_309_digits"])
def test_simulate_flags(tmp_path, capsys, args, message):
    out = tmp_path / "bag"
    fails(["simulate", "--scenario", str(SCENARIO), "--seconds", "0.1", "--out", str(out), "--quiet", *args],
          capsys, message)
    assert not any(tmp_path.iterdir())


def test_simulate_a_run_that_cannot_fit_on_disk_is_refused_before_it_starts(tmp_path, capsys):
    """On main, --seconds 1e6 spent minutes before any progress showed (and would fill the disk);
    a day, the most --seconds takes, is a 250 GB bag."""
    if shutil.disk_usage(tmp_path).free > 2.4e11:
        pytest.skip("more than 240 GB free here: a day-long bag would fit")
    started = time.monotonic()
    fails(["simulate", "--scenario", str(SCENARIO), "--seconds", "86400", "--out", str(tmp_path / "bag")], capsys,
          "is free there")
    assert time.monotonic() - started < 10 and not any(tmp_path.iterdir())


@pytest.mark.parametrize("out, message", [
    (lambda tmp: tmp / "a_file" / "bag", "not a writable directory"),
    (lambda tmp: Path("/proc/deepsync_test_bag"), "/proc/deepsync_test_bag"),
    (lambda tmp: BAG, "exists already"),
], ids=["under_a_file", "proc", "exists"])
def test_simulate_unwritable_output(tmp_path, capsys, out, message):
    (tmp_path / "a_file").write_text("not a directory")
    fails(["simulate", "--scenario", str(SCENARIO), "--seconds", "0.1", "--out", str(out(tmp_path)), "--quiet"],
          capsys, message)


@pytest.mark.parametrize("scenario, message", [
    ("missing.yaml", "file not found"),
    ("bad.yaml", "invalid YAML"),
    ("eirp.yaml", "eirp_dbm"),
], ids=["missing", "not_yaml", "eirp_300"])
def test_simulate_bad_scenarios(tmp_path, capsys, scenario, message):
    (tmp_path / "bad.yaml").write_text("sites: [\n")
    (tmp_path / "eirp.yaml").write_text(SCENARIO.read_text().replace("eirp_dbm: 61", "eirp_dbm: 300", 1))
    assert "eirp_dbm: 300" in (tmp_path / "eirp.yaml").read_text()
    fails(["simulate", "--scenario", str(tmp_path / scenario), "--seconds", "0.1", "--out", str(tmp_path / "bag"),
           "--quiet"], capsys, message)


@pytest.mark.parametrize("args, message", [
    ([], "give one recording: --bag BAG or --input FILE"),
    (["--bag", str(BAG), "--input", str(BAG)], "give one recording"),
    (["--bag", str(BAG), "--frames", "1"], "at least 2 frames"),
    (["--bag", str(BAG), "--frames", "0"], "n_frames must be within [1, 1000] frames, got 0"),
    (["--bag", str(BAG), "--frames", "400"], "less than one 400-frame stack"),
    (["--bag", "/nonexistent/bag"], "/nonexistent/bag"),
    (["--input", "/nonexistent/file.cu8", "--rate", "1.92e6"], "no such file"),
    (["--input", str(BAG), "--format", "cu8"], "a bag carries ADC codes already"),
    (["--bag", str(BAG), "--towers", "/nonexistent/towers.yaml"], "file not found"),
    (["--bag", str(BAG), "--scale", "0"], "must be a positive number"),
    (["--bag", str(BAG), "--format", "cu9"], "invalid choice"),
], ids=["no_recording", "two_recordings", "frames_1", "frames_0", "frames_beyond_input", "bag_missing",
        "input_missing", "format_for_a_bag", "towers_missing", "scale_0", "format_unknown"])
def test_detect_flags(capsys, args, message):
    fails(["detect", *args], capsys, message)


def test_detect_raw_recordings_that_do_not_say_enough(tmp_path, capsys, cu8):
    ambiguous = tmp_path / "capture.bin"
    shutil.copy(cu8, ambiguous)
    fails(["detect", "--input", str(ambiguous), "--rate", "1.92e6"], capsys, "cannot tell the sample format")
    fails(["detect", "--input", str(cu8)], capsys, "the sample rate must be given")
    fails(["detect", "--input", str(cu8), "--rate", "2.4e6"], capsys, "divides 30.72 MHz")
    odd = tmp_path / "odd.cu8"
    odd.write_bytes(cu8.read_bytes()[:-1])
    fails(["detect", "--input", str(odd), "--rate", "1.92e6"], capsys, "not a whole number of cu8 samples")
    broken = tmp_path / "nan.cf32"
    samples = np.ones(2 * 19200 * 3, dtype=np.float32)
    samples[1001] = np.nan
    samples.tofile(broken)
    fails(["detect", "--input", str(broken), "--rate", "1.92e6"], capsys, "sample 500 is not finite")


def test_detect_bad_tower_databases(tmp_path, capsys):
    (tmp_path / "broken.yaml").write_text("sites: {")
    fails(["detect", "--bag", str(BAG), "--towers", str(tmp_path / "broken.yaml")], capsys, "invalid YAML")
    (tmp_path / "mixed.yaml").write_text(
        "sites:\n  - name: A\n    cells: [{pci: 120, earfcn: 2000}, {pci: 121}]\n")
    fails(["detect", "--bag", str(BAG), "--towers", str(tmp_path / "mixed.yaml")], capsys, "but not for cells[1]")


def test_info_of_a_missing_bag(capsys):
    fails(["info", "--bag", "/nonexistent/bag"], capsys, "/nonexistent/bag")


def test_a_closed_pipe_stops_quietly_with_one_line():
    """``deepsync info | head -1`` ended in a BrokenPipeError traceback on main. ``detect`` writes
    its 20 kB as it searches, so ``head`` has gone before the rest is written; ``info`` writes its
    few lines at once, which may all reach the pipe before ``head`` closes it."""
    run = subprocess.run(f"set -o pipefail; '{DEEPSYNC}' detect --bag '{BAG}' --towers '{TOWERS}' | head -1",
                         shell=True, executable="/bin/bash", capture_output=True, text=True, timeout=120)
    assert run.returncode == 1 and run.stdout.startswith("cell search over ")
    assert run.stderr.strip() == "deepsync detect: output closed early (broken pipe); stopped"
    run = subprocess.run(f"set -o pipefail; '{DEEPSYNC}' info --bag '{BAG}' | head -1", shell=True,
                         executable="/bin/bash", capture_output=True, text=True, timeout=120)
    assert run.stdout.startswith("bag ") and len(run.stdout.splitlines()) == 1
    assert (run.returncode, run.stderr.strip()) in ((0, ""), (1, "deepsync info: output closed early (broken pipe); "
                                                             "stopped"))


# -- interrupts: SIGTERM (timeout, systemd, ros2 launch) and Ctrl-C -----------------------------


def children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (from /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry.name))
    return found


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads worker processes from /proc")
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["sigterm", "sigint"])
def test_an_interrupted_simulate_stops_within_a_second_and_leaves_nothing(tmp_path, signum):
    """On main, SIGTERM left a .NAME.*.partial directory and orphaned the worker processes
    (~180 MB each, alive minutes later); Ctrl-C took 5-7 s. The signal goes to the main process only."""
    process = subprocess.Popen(
        [str(DEEPSYNC), "simulate", "--scenario", str(SCENARIO), "--seconds", "60", "--out", str(tmp_path / "bag"),
         "--workers", "2", "--quiet"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
        # as from a terminal: a suite started in the background (`.ci/run &`) ignores SIGINT, and
        # an ignored signal is inherited, which would make Ctrl-C here a no-op
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        deadline = time.monotonic() + 120
        while len(children(process.pid)) < 2 and time.monotonic() < deadline and process.poll() is None:
            time.sleep(0.1)
        workers = children(process.pid)
        assert len(workers) == 2, "the worker processes never started"
        time.sleep(1.0)  # mid-run: chunks on their way into the bag
        sent = time.monotonic()
        process.send_signal(signum)
        status = process.wait(timeout=30)
        stopped = time.monotonic() - sent
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert status == 130 and stopped < 1.0, (status, stopped)
    assert process.stderr.read().strip() == "deepsync simulate: interrupted; nothing was written"
    assert not any(tmp_path.iterdir())  # no bag, no .bag.*.partial
    deadline = time.monotonic() + 2
    while any(Path(f"/proc/{pid}").exists() for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(Path(f"/proc/{pid}").exists() for pid in workers), "a worker outlived the command"


def test_info_says_where_metadata_yaml_disagrees_with_the_file(tmp_path, capsys):
    """On main, wrong counts in metadata.yaml were printed as the truth."""
    bag = tmp_path / "campus"
    shutil.copytree(BAG, bag)
    metadata = bag / "metadata.yaml"
    text = metadata.read_text()
    assert "\n  message_count: 630\n" in text  # the bag's total
    metadata.write_text(text.replace("\n  message_count: 630\n", "\n  message_count: 9999\n"))
    assert main(["info", "--bag", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "630 messages" in out and "9999" in out and "the file's value is used" in out
    assert "integrity: CRCs on all" in out


# -- replay: refused at the door, or replayed as far as the input allows ------------------------


def campus_bag(out: Path, n_chunks: int, *, drop: range = range(0)) -> Path:
    """The first ``n_chunks`` envelope messages of the campus bag (less those whose index is in
    ``drop``) and the truth up to them, with the campus provenance (its front end)."""
    from deepsync.bag import ENVELOPE_TOPIC, TRUTH_POSE_TOPIC, BagReader, BagWriter

    with BagReader(BAG) as reader, BagWriter(out, provenance=reader.provenance) as writer:
        for k, item in enumerate(reader.messages([ENVELOPE_TOPIC])):
            if k == n_chunks:
                break
            if k not in drop:
                writer.write(ENVELOPE_TOPIC, item.message)
            last = item.log_time_ns
        for item in reader.messages([TRUTH_POSE_TOPIC]):
            if item.log_time_ns <= last:
                writer.write(TRUTH_POSE_TOPIC, item.message)
    return out


def replay_args(bag: Path, out: Path, *more: str) -> list[str]:
    return ["replay", "--in", str(bag), "--out", str(out), "--frames", "10", "--quiet", *more]


def test_replay_refuses_what_it_cannot_start_on_and_writes_nothing(tmp_path, capsys):
    from deepsync.bag import BagWriter, cell_timing_array_to_msg
    from deepsync.types import CellTiming, StackArrivals

    out = tmp_path / "out"
    fails(replay_args(Path("/nonexistent/bag"), out), capsys, "/nonexistent/bag")
    fails(replay_args(BAG, out, "--towers", "/nonexistent/towers.yaml"), capsys, "file not found")
    fails(replay_args(BAG, out, "--stages", "fusion,sync"), capsys, "contiguous part of the chain")
    fails(replay_args(BAG, out, "--frames", "10", "--hop", "20"), capsys, "hop_frames must be 1..n_frames (10)")
    fails(replay_args(BAG, out, "--hop", "0"), capsys, "hop_frames must be within [1, 1000] frames")
    wrong = tmp_path / "wrong"
    arrivals = StackArrivals(10**18, 0, 1.92e6, (CellTiming(56, 10.0, 0.1, 0.0, "ml"),))
    with BagWriter(wrong) as bag:
        bag.write("/deepsync/envelope", cell_timing_array_to_msg(arrivals))
    fails(replay_args(wrong, out), capsys, "/deepsync/envelope carries deepsync_msgs/msg/CellTimingArray, but the "
                                           "sync stage reads deepsync_msgs/msg/EnvelopeSamples there")
    fails(replay_args(wrong, out, "--stages", "fusion"), capsys, "no /deepsync/cell_timing")
    timing = tmp_path / "timing"
    with BagWriter(timing) as bag:
        bag.write("/deepsync/cell_timing", cell_timing_array_to_msg(arrivals))
    fails(replay_args(timing, out, "--stages", "fusion"), capsys, "fusion alone, but no tower database")
    assert not out.exists()


def test_replay_of_a_bag_with_a_corrupt_chunk_keeps_what_came_before_it(tmp_path, capsys):
    """The bag opens (its summary is intact); the reading meets the corrupt chunk halfway: what
    came before is replayed into a valid bag, the damage named, exit status 1."""
    from deepsync.bag import CELL_TIMING_TOPIC, BagReader

    from test_bad_input_bags import chunk_indexes, compressed_span, copy_bag, flip, mcap_of

    bag = copy_bag(BAG, tmp_path / "corrupt")
    chunks = chunk_indexes(mcap_of(bag))
    start, end = compressed_span(chunks[len(chunks) // 2])
    flip(mcap_of(bag), (start + end) // 2)
    out = tmp_path / "out"
    assert main(replay_args(bag, out, "--towers", str(TOWERS))) == 1
    captured = capsys.readouterr()
    assert "the input is damaged" in captured.err and str(mcap_of(bag)) in captured.err
    with BagReader(out) as reader:
        assert reader.verify().complete
        assert 3 <= reader.message_counts[CELL_TIMING_TOPIC] < 30


def test_replay_without_a_tower_database_searches_blind_and_skips_fusion(tmp_path, capsys):
    from deepsync.bag import BagReader, sync_window_array_from_msg

    bag = campus_bag(tmp_path / "short", 40)
    out = tmp_path / "out"
    assert main(replay_args(bag, out)) == 0
    printed = capsys.readouterr().out
    assert "fusion skipped: no tower database" in printed and "runs blind" in printed
    with BagReader(out) as reader:
        assert "/deepsync/pose" not in reader.topics and reader.message_counts["/deepsync/cell_timing"] == 4
        found = {w.pci for m in reader.messages(["/deepsync/sync_windows"])
                 for w in sync_window_array_from_msg(m.message).windows}
    assert 56 in found and found <= {56, 120, 121, 301}  # the campus cells, found without their list


def test_replay_with_a_database_that_lists_none_of_the_heard_cells_says_so(tmp_path, capsys):
    bag = campus_bag(tmp_path / "short", 40)
    foreign = tmp_path / "foreign.yaml"
    text = TOWERS.read_text()
    for pci in ("120", "121", "122", "301", "302", "300", "56", "57"):
        text = text.replace(f"pci: {pci},", f"pci: {int(pci) + 100},")
    foreign.write_text(text)
    assert main(replay_args(bag, tmp_path / "out", "--towers", str(foreign))) == 0
    assert "no cell of tower database 'campus' was found in 4 stacks" in capsys.readouterr().out


def test_replay_fusion_names_the_heard_cells_the_database_cannot_place(tmp_path, capsys):
    """Fusion alone from a CellTimingArray bag (the truth's, here) with a database that lacks PCI 301."""
    from deepsync.bag import TRUTH_CELL_TIMING_TOPIC, BagReader, BagWriter

    bag = tmp_path / "timing"
    with BagReader(BAG) as reader, BagWriter(bag) as writer:
        for k, item in enumerate(reader.messages([TRUTH_CELL_TIMING_TOPIC])):
            if k % 10 == 0:
                writer.write("/deepsync/cell_timing", item.message)
    lacking = tmp_path / "lacking.yaml"
    lacking.write_text(TOWERS.read_text().replace("{pci: 301, earfcn: 2000", "{pci: 309, earfcn: 2000"))
    assert main(replay_args(bag, tmp_path / "out", "--towers", str(lacking), "--stages", "fusion")) == 0
    printed = capsys.readouterr().out
    assert "heard but not in tower database 'campus', so left out of the fixes: PCI 301" in printed
    assert "unanchored 30" in printed  # the fusion stage's health, counted per kind


def test_replay_counts_the_stream_events_per_kind(tmp_path, capsys):
    """A gap in the envelope (5 chunks lost) is the sync stage's to report: replay prints the count."""
    bag = campus_bag(tmp_path / "gappy", 60, drop=range(30, 35))
    assert main(replay_args(bag, tmp_path / "out", "--towers", str(TOWERS))) == 0
    health = [line for line in capsys.readouterr().out.splitlines() if line.startswith("  health")]
    assert health and "gap 1" in health[0]


def test_replay_into_its_own_input_bag_is_refused_and_the_recording_kept(tmp_path, capsys):
    """--out naming the input bag (its directory or the directory of its .mcap) would replace
    the recording being read, --overwrite or not."""
    bag = tmp_path / "bag"
    shutil.copytree(BAG, bag)
    before = sorted((p.name, p.stat().st_size) for p in bag.iterdir())
    for source in (bag, next(bag.glob("*.mcap"))):
        fails(replay_args(source, bag, "--overwrite"), capsys, "replaying into it would replace the recording")
    assert sorted((p.name, p.stat().st_size) for p in bag.iterdir()) == before


def test_compare_poses_of_a_topic_without_covariance_says_so(capsys):
    fails(["compare-poses", "--reference", str(BAG), "--other", str(BAG), "--topic", "/deepsync/truth/pose"],
          capsys, "/deepsync/truth/pose holds geometry_msgs/msg/PoseStamped, not "
                  "geometry_msgs/msg/PoseWithCovarianceStamped")


@pytest.mark.parametrize("args, message", [
    (["demo", "--simulate", "1e308"], "argument --simulate: '1e308' s is more than a day"),  # OverflowError on main
    (["evaluate-timing", "--frames", "abc"], "argument --frames: 'abc' is not a whole number"),
    (["evaluate-timing", "--frames", "5,0"], "argument --frames: n_frames must be within [1, 1000] frames, got 0"),
    (["evaluate-route", "--bag", str(BAG), "--towers", str(TOWERS), "--initial-pose-std", "1e-320"],
     "argument --initial-pose-std: '1e-320' m: give 0.01...10000 m"),  # found by the fuzzing pass
    (["evaluate-route", "--bag", str(BAG), "--towers", str(TOWERS), "--initial-pose-std", "1e308"],
     "argument --initial-pose-std: '1e308' m: give 0.01...10000 m"),
    (["detect", "--bag", str(BAG), "--scale", "9" * 400], "argument --scale: '9999999999"),
    (["evaluate-route", "--bag", str(BAG), "--towers", str(TOWERS), "--multipath-std-m", "0"],
     "argument --multipath-std-m: multipath_std_m must be within (0, 10000] m, got 0"),
    (["evaluate-route", "--bag", str(BAG), "--towers", str(TOWERS), "--odometry-in-map"],
     "--odometry-in-map turns the odometry --odometry-std gives: give --odometry-std F too"),
    (["evaluate-route", "--bag", str(BAG), "--towers", str(TOWERS), "--initial-heading-std", "0.1"],
     "--initial-heading-std goes with the initial pose: give --initial-pose-std M too"),
    (["evaluate-route", "--bag", str(BAG), "--towers", str(TOWERS), "--initial-heading-std", "4"],
     "argument --initial-heading-std: '4' rad: give more than 0, at most pi"),
], ids=["demo_simulate_1e308", "evaluate_timing_frames_word", "evaluate_timing_frames_0", "initial_std_1e-320",
        "initial_std_1e308", "scale_400_digits", "multipath_std_0", "odometry_in_map_alone",
        "heading_without_pose", "heading_std_4"])
def test_flags_out_of_range_are_refused_naming_the_flag(capsys, args, message):
    fails(args, capsys, message)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs named pipes")
def test_simulate_reads_its_scenario_once_so_a_fifo_works(tmp_path):
    """On main the scenario was read, then opened again to hash it for the provenance: on a FIFO
    the second open waited forever (a process substitution recorded the hash of nothing)."""
    import hashlib
    import json
    import threading

    from deepsync.bag import BagReader

    fifo = tmp_path / "scenario.yaml"
    os.mkfifo(fifo)
    text = SCENARIO.read_bytes()

    def write_once() -> None:
        with open(fifo, "wb") as handle:
            handle.write(text)

    writer = threading.Thread(target=write_once, daemon=True)
    writer.start()
    run = subprocess.run([str(DEEPSYNC), "simulate", "--scenario", str(fifo), "--seconds", "0.05", "--out",
                          str(tmp_path / "bag"), "--quiet", "--workers", "1"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    with BagReader(tmp_path / "bag") as bag:
        provenance = json.loads(bag.provenance)
    assert provenance["scenario_sha256"] == hashlib.sha256(text).hexdigest()


@pytest.mark.parametrize("command", ["evaluate-route", "calibrate", "replay"])
def test_a_tower_database_in_another_frame_than_the_bag_is_refused(tmp_path, capsys, command):
    """A database whose origin lies 50 km from the bag's (simulated) one: on main evaluate-route
    reported a 49,971 m median error for fixes 7 m off, and calibrate wrote site offsets of -2.9
    and -3.7 us into a database, exit 0. Both frames are "map"; only their origins tell them apart."""
    moved = tmp_path / "moved.yaml"
    text = TOWERS.read_text()
    assert "latitude_deg: 38.98690, longitude_deg: -76.94260" in text
    moved.write_text(text.replace("latitude_deg: 38.98690, longitude_deg: -76.94260",
                                  "latitude_deg: 39.43690, longitude_deg: -76.94260", 1))
    out = tmp_path / ("out.yaml" if command == "calibrate" else "out")
    bag_flag = "--in" if command == "replay" else "--bag"
    fails([command, bag_flag, str(BAG), "--towers", str(moved), "--out", str(out), "--quiet"], capsys,
          "m apart: the ground truth and the fixes would be compared in two frames")
    assert not out.exists()
    # the same origin, written otherwise, is the same frame
    moved.write_text(text.replace("height_m: 10.0}", "height_m: 10.000001}", 1))
    from deepsync.sources import BagSource
    from deepsync.towers import load_tower_database

    BagSource(BAG).check_frame(load_tower_database(moved))


@pytest.mark.parametrize("command", [["export-onnx"], ["calibrate", "--bag", str(BAG), "--towers", str(TOWERS)]],
                         ids=["export-onnx", "calibrate"])
def test_an_output_that_cannot_be_written_is_refused_before_the_work(capsys, command):
    """On main export-onnx failed after 50 s naming a torch temporary file, and calibrate after
    the whole replay: the folder is tried first (a file made there and removed)."""
    started = time.monotonic()
    fails([*command, "--out", "/proc/deepsync_test/out.yaml"], capsys,
          "/proc/deepsync_test/out.yaml: cannot write the")
    assert time.monotonic() - started < 30


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads worker processes from /proc")
def test_what_a_killed_simulate_left_is_removed_by_the_next_write_of_that_bag(tmp_path):
    """SIGKILL (no handler runs) left a hidden .NAME.*.partial folder that nobody removed; the
    next writer of the bag removes those of writers that no longer run, and only those."""
    out = tmp_path / "bag"
    process = subprocess.Popen([str(DEEPSYNC), "simulate", "--scenario", str(SCENARIO), "--seconds", "60", "--out",
                                str(out), "--workers", "1", "--quiet"], stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not list(tmp_path.glob(".bag.*.partial")) and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(1.0)
    finally:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait(timeout=30)
    (left,) = tmp_path.glob(".bag.*.partial")
    alive = tmp_path / f".bag.{os.getpid()}.someone-writing.partial"  # a live writer's (this process)
    alive.mkdir()
    assert main(["simulate", "--scenario", str(SCENARIO), "--seconds", "0.05", "--out", str(out), "--quiet",
                 "--workers", "1"]) == 0
    assert not left.exists() and alive.exists() and (out / "metadata.yaml").is_file()


@pytest.mark.parametrize("command", ["evaluate-route", "calibrate"])
def test_a_ground_truth_pose_holding_nan_is_refused(tmp_path, capsys, command):
    """A NaN in the truth made every error NaN, which passes every comparison that scores a route
    (the comparisons family's other member): refused naming the pose."""
    from deepsync.bag import TRUTH_POSE_TOPIC, BagReader, BagWriter

    bag = tmp_path / "nan_truth"
    with BagReader(BAG) as reader, BagWriter(bag, provenance=reader.provenance) as writer:
        for k, item in enumerate(reader.messages(["/deepsync/envelope", TRUTH_POSE_TOPIC])):
            if item.topic == TRUTH_POSE_TOPIC and k > 50:
                item.message.pose.position.x = float("nan")
            writer.write(item.topic, item.message)
            if k > 120:
                break
    out = tmp_path / ("out.yaml" if command == "calibrate" else "out")
    fails([command, "--bag", str(bag), "--towers", str(TOWERS), "--out", str(out), "--quiet"], capsys,
          "ns holds NaN or inf")


@pytest.mark.parametrize("args, message", [
    (["--seeds", "0-1000000000000"], "argument --seeds: '0-1000000000000': 1000000000001 seeds; give 1..10000"),
    (["--seeds", f"1-{2**64}"], "seeds must be in [0, 9223372036854775807]"),
    (["--seeds", "5-3"], "0 seeds; give 1..10000"),
    (["--seeds", "1", "--seconds", "1e308"], "argument --seconds: '1e308' s is more than a day"),
], ids=["a-trillion-seeds", "beyond-int64", "none", "seconds-1e308"])
def test_a_route_set_of_what_cannot_be_made_is_refused_before_any_list_is_built(tmp_path, capsys, args, message):
    """A route set's seeds were built as a list before anything was checked (a range of 10^12
    seeds filled the memory); its --seconds took 1e308, which simulate refuses."""
    base = {"--seeds": "1", "--seconds": "0.05"}
    for flag, value in zip(args[::2], args[1::2]):
        base[flag] = value
    fails(["simulate-set", "--scenario", str(SCENARIO), "--out", str(tmp_path / "set"),
           *[item for pair in base.items() for item in pair]], capsys, message)
