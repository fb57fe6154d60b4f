"""`deepsync simulate`: the bag it writes, its ground truth, and what it does with bad input."""

from pathlib import Path

import numpy as np
import pytest

from deepsync.bag import (
    ENVELOPE_TOPIC,
    TRUTH_CELL_TIMING_TOPIC,
    TRUTH_POSE_TOPIC,
    BagReader,
    cell_timing_array_from_msg,
    position_from_pose_msg,
    read_envelope,
)
from deepsync.cli import main
from deepsync.frontend import simulator as simulator_module
from deepsync.recording import EPOCH_NS, record_scenario
from deepsync.twin import build_twin
from deepsync.twin.scenario import load_scenario

REPO = Path(__file__).resolve().parents[1]
CAMPUS = REPO / "config" / "scenarios" / "campus.yaml"
WALK = REPO / "config" / "scenarios" / "campus_walk.yaml"


@pytest.fixture(scope="module")
def walk_bag(tmp_path_factory):
    out = tmp_path_factory.mktemp("bags") / "walk"
    summary = record_scenario(WALK, 0.25, out, workers=1, progress=False)
    return out, summary


def test_stream_is_contiguous_and_stamped_on_the_receiver_clock(walk_bag):
    out, summary = walk_bag
    chunks = list(read_envelope(out))
    assert sum(len(c.samples) for c in chunks) == summary.samples == 480_000
    expected_first = 0
    for chunk in chunks:
        assert chunk.first_sample_index == expected_first
        assert chunk.sample_rate == 1.92e6 and chunk.adc_bits == 12
        assert chunk.stamp_ns == EPOCH_NS + round(chunk.first_sample_index * 1e9 / 1.92e6)
        expected_first = chunk.end_sample_index
    codes = np.concatenate([c.samples for c in chunks])
    assert 50 < codes.std() < 500  # the power-up AGC's level
    clipped = np.count_nonzero((codes == 2047) | (codes == -2048))
    assert clipped == summary.stats.clipped < 1e-4 * len(codes)  # heavy-tailed envelope, rare peaks


def test_ground_truth_follows_geometry_and_clock(walk_bag):
    out, _ = walk_bag
    twin = build_twin(load_scenario(WALK))
    toas: dict[int, list[float]] = {}
    positions = []
    with BagReader(out) as bag:
        for item in bag.messages([TRUTH_CELL_TIMING_TOPIC, TRUTH_POSE_TOPIC]):
            if item.topic == TRUTH_POSE_TOPIC:
                positions.append((item.log_time_ns, position_from_pose_msg(item.message)))
                continue
            for record in cell_timing_array_from_msg(item.message).cells:
                toas.setdefault(record.pci, []).append(record.toa)
    assert sorted(toas) == sorted(c.pci for c in twin.cells)
    for i, cell in enumerate(twin.cells):
        series = np.array(toas[cell.pci])
        assert len(series) == 25  # one subframe-0 code per 10 ms frame
        # frame to frame: 19200 samples plus the change of the line-of-sight delay (walking)
        steps = np.diff(series) - 19200
        assert np.all(np.abs(steps) < 0.01)
        # absolute: frame timing + sync offset (686 samples) + distance / c, at 1.92 MHz
        delay = twin.geometric_delay_s(i, 0.0)
        timing = twin.emitters[i].timing_offset_s
        phase = (timing + 686 / 1.92e6 + delay) * 1.92e6 % 19200
        assert series[0] % 19200 == pytest.approx(phase, abs=0.01)
    stamp, (x, y, _) = positions[1]
    t = (stamp - EPOCH_NS) / 1e9
    np.testing.assert_allclose([x, y], twin.receiver_enu(t)[:2], atol=1e-6)


def test_failure_mid_run_leaves_no_bag(tmp_path, monkeypatch):
    calls = {"n": 0}
    original = simulator_module.AdcStage.quantize

    def failing(self, first, coupled):
        calls["n"] += 1
        if calls["n"] > 1:
            raise RuntimeError("simulated crash")
        return original(self, first, coupled)

    monkeypatch.setattr(simulator_module.AdcStage, "quantize", failing)
    monkeypatch.setattr(simulator_module, "WORK_UNIT_SECONDS", 0.05)
    out = tmp_path / "crashed"
    with pytest.raises(RuntimeError, match="simulated crash"):
        record_scenario(CAMPUS, 0.2, out, progress=False)
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []  # no temporary directory left behind either


@pytest.mark.parametrize(
    "mutation, message",
    [
        (("pci: 120,", "pci: 777,"), "sites[0].cells[0]"),
        (("bandwidth_mhz: 10, eirp_dbm: 60.0", "bandwidth_mhz: 12, eirp_dbm: 60.0"), "bandwidth"),
        (("timing_offset_us: 512.3", "timing_offset_us: .nan"), "timing_offset_us"),
        (("seed: 7", "seed: [7"), "invalid YAML"),
        (("rf_gain_db: 10.0", "rf_gain_db: 10.0, adc_bits: 40"), "adc_bits"),
    ],
)
def test_bad_scenarios_fail_cleanly_naming_the_field(tmp_path, capsys, mutation, message):
    text = CAMPUS.read_text()
    assert mutation[0] in text
    broken = tmp_path / "broken.yaml"
    broken.write_text(text.replace(mutation[0], mutation[1], 1))
    out = tmp_path / "never"
    assert main(["simulate", "--scenario", str(broken), "--seconds", "0.1", "--out", str(out), "--quiet"]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_existing_output_is_refused_unless_overwrite(tmp_path, capsys):
    out = tmp_path / "bag"
    args = ["simulate", "--scenario", str(CAMPUS), "--seconds", "0.02", "--out", str(out), "--quiet", "--workers", "1"]
    assert main(args) == 0
    before = (out / "bag.mcap").read_bytes()
    assert main(args) == 2
    assert "exists" in capsys.readouterr().err
    assert main([*args, "--overwrite"]) == 0
    assert (out / "bag.mcap").read_bytes() == before  # reproducible by seed, bit for bit
    assert main(["info", "--bag", str(out)]) == 0
    assert ENVELOPE_TOPIC in capsys.readouterr().out


def test_a_cell_no_path_reaches_at_the_start_is_summarised_as_unheard():
    # a ray-traced route can start where a site's every path is blocked: one path of zero gain
    import math
    from dataclasses import replace
    from types import SimpleNamespace

    from deepsync.frontend.channel import Paths
    from deepsync.recording import cell_summaries

    twin = build_twin(load_scenario(Path(__file__).resolve().parents[1] / "config" / "scenarios" / "campus.yaml"))
    silent = SimpleNamespace(paths=lambda i, t: Paths([1e-6], [0.0], [0.0]), los_at=lambda i, t: False,
                             geometric_delay_s=twin.channel.geometric_delay_s)
    rows = cell_summaries(replace(twin, channel=silent))
    assert rows and all(row.re_power_dbm == -math.inf for row in rows)
    assert all(math.isfinite(row.re_power_dbm) for row in cell_summaries(twin))
