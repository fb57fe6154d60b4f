"""deepsync_ros.health: what the nodes' diagnostics report, on what the chain really produces.

The stack results come from running :class:`deepsync.pipeline.Pipeline` over the bundled campus
bag with its tower database (its first stacks hear nothing yet, then three sites, then fewer),
once as recorded and once with a chunk lost in the middle.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from deepsync.pipeline import Pipeline, PipelineConfig, StackResult
from deepsync.sources import BagSource
from deepsync.towers import load_tower_database
from deepsync.types import EnvelopeChunk, Fix, HealthKind, NoFix, NoFixReason, Severity
from deepsync_ros.health import StageHealth

REPO = Path(__file__).resolve().parents[1]
CAMPUS_BAG = REPO / "bags" / "campus"
CAMPUS_TOWERS = REPO / "config" / "towers" / "campus.yaml"
LOST_CHUNK = 150  # of 300: a stack in the middle of the recording spans it


def run_campus(chunks: list[EnvelopeChunk]) -> list[StackResult]:
    source = BagSource(CAMPUS_BAG)
    pipeline = Pipeline(source.frontend, PipelineConfig().with_choices(n_frames=10), load_tower_database(CAMPUS_TOWERS))
    return list(pipeline.run(chunks))


@pytest.fixture(scope="module")
def campus_chunks() -> list[EnvelopeChunk]:
    return list(BagSource(CAMPUS_BAG).chunks())


@pytest.fixture(scope="module")
def campus(campus_chunks: list[EnvelopeChunk]) -> list[StackResult]:
    return run_campus(campus_chunks)


@pytest.fixture(scope="module")
def campus_with_gap(campus_chunks: list[EnvelopeChunk]) -> list[StackResult]:
    return run_campus(campus_chunks[:LOST_CHUNK] + campus_chunks[LOST_CHUNK + 1:])


def values(report) -> dict[str, str]:
    return dict(report.values)


def fed(results: list[StackResult], window: int = 50) -> StageHealth:
    health = StageHealth(window)
    for result in results:
        health.result(result)
    return health


def test_the_campus_run_has_fixes_and_stacks_without(campus: list[StackResult]) -> None:
    fixes = [isinstance(result.fusion.published, Fix) for result in campus]
    assert any(fixes) and not all(fixes)  # what the tests below rely on


def test_fix_rate_cells_and_sites_over_the_window(campus: list[StackResult]) -> None:
    report = fed(campus).report()
    expected_rate = sum(isinstance(r.fusion.published, Fix) for r in campus) / len(campus)
    got = values(report)
    assert got["stacks"] == str(len(campus))
    assert got[f"fix rate (last {len(campus)} stacks)"] == f"{expected_rate:.2f}"
    assert got["fixes"] == str(round(expected_rate * len(campus)))
    last = campus[-1]
    assert got["cells heard (last stack)"] == " ".join(map(str, last.sync.pcis))
    heard = sorted({pci for result in campus for pci in result.sync.pcis})
    assert got[f"cells heard (last {len(campus)} stacks)"] == " ".join(map(str, heard))
    assert got["sites heard (last stack)"] == " ".join(site.site for site in last.fusion.sites)
    sites = sorted({site.site for result in campus for site in result.fusion.sites})
    assert got[f"sites heard (last {len(campus)} stacks)"] == " ".join(sites)
    assert report.level is Severity.OK
    assert f"fix rate {expected_rate:.0%}" in report.message


def test_the_last_no_fix_reason(campus: list[StackResult]) -> None:
    last_without = [r for r in campus if not isinstance(r.fusion.published, Fix)][-1]
    reason = last_without.fusion.published
    assert isinstance(reason, NoFix)
    health = fed(campus[: campus.index(last_without) + 1])
    assert values(health.report())["last no-fix reason"] == f"{reason.reason.value}: {reason.message}"


def test_a_window_without_a_fix_warns_why(campus: list[StackResult]) -> None:
    start = [r for r in campus[:2]]
    assert not any(isinstance(r.fusion.published, Fix) for r in start)
    report = fed(start).report()
    assert report.level is Severity.WARN
    assert f"no fix in the last 2 stacks ({NoFixReason.TOO_FEW_SITES.value}: " in report.message
    assert "no cell heard in the last 2 stacks" in report.message
    # once the window has moved past them, fixes make it OK again
    assert fed(campus, window=5).report().level is Severity.OK


def test_a_lost_chunk_is_counted_and_warns_until_the_window_passes(campus_with_gap: list[StackResult]) -> None:
    gaps = [(i, event) for i, result in enumerate(campus_with_gap) for event in result.health
            if event.kind is HealthKind.GAP]
    assert len(gaps) == 1
    index, gap = gaps[0]
    health = fed(campus_with_gap[: index + 1], window=5)
    report = health.report()
    assert report.level is Severity.WARN
    assert report.message == str(gap)
    assert values(report)["events: gap"] == "1"
    assert values(report)["last gap"] == gap.message
    for result in campus_with_gap[index + 1: index + 6]:
        health.result(result)
    later = health.report()
    assert later.level is Severity.OK  # five stacks on, the gap is history
    assert values(later)["events: gap"] == "1"


def test_rejected_input_is_counted_and_warns(campus: list[StackResult]) -> None:
    health = fed(campus[:5])
    health.reject(ValueError("SyncWindow of PCI 56: 3 window values, but n_frames x window_length = 10 x 301"))
    report = health.report()
    assert report.level is Severity.WARN
    assert "input rejected: SyncWindow of PCI 56" in report.message
    assert values(report)["rejected input messages"] == "1"


def test_nothing_yet_is_a_warning() -> None:
    report = StageHealth().report()
    assert report.level is Severity.WARN
    assert "waiting for input" in report.message


def test_latency_median_and_max(campus: list[StackResult]) -> None:
    health = StageHealth()
    for result, seconds in zip(campus[:3], (0.010, 0.030, 0.020)):
        health.result(result, latency_s=seconds, stage_s=seconds / 2)
    got = values(health.report())
    assert got["latency median (ms)"] == "20.0"
    assert got["latency max (ms)"] == "30.0"
    assert got["stage time median (ms)"] == "10.0"


def test_the_tracker_fix_is_published_before_the_snapshot(campus: list[StackResult]) -> None:
    both = [r.fusion for r in campus if isinstance(r.fusion.tracked, Fix) and isinstance(r.fusion.snapshot, Fix)]
    snapshot_only = [r.fusion for r in campus if isinstance(r.fusion.snapshot, Fix) and
                     not isinstance(r.fusion.tracked, Fix)]
    assert both and snapshot_only
    assert all(f.published is f.tracked for f in both)
    assert all(f.published is f.snapshot for f in snapshot_only)


# --- stacks lost between nodes ------------------------------------------------------------------

HOP = 20 * 19_200  # pedestrian stacks: every 20 frames of 19,200 samples


def test_stack_sequence_counts_the_stacks_that_never_came() -> None:
    from deepsync_ros.health import StackSequence
    sequence = StackSequence()
    for index in (0, 1, 2, 5, 6, 9):  # 3, 4, 7 and 8 lost
        sequence.arrived(1000 + index * HOP)
    assert sequence.lost == 4 and sequence.seen == 6


def test_stack_sequence_counts_a_gap_before_the_hop_is_known() -> None:
    """The very first step spans a lost stack: counted once a single hop shows the spacing."""
    from deepsync_ros.health import StackSequence
    sequence = StackSequence()
    sequence.arrived(0)
    sequence.arrived(2 * HOP)
    assert sequence.lost == 0  # one step: no telling yet
    sequence.arrived(3 * HOP + 1)  # a sample of clock drift does not make a gap
    assert sequence.lost == 1


def test_stack_sequence_starts_over_when_the_stream_does() -> None:
    from deepsync_ros.health import StackSequence
    sequence = StackSequence()
    for index in (0, 1, 3):
        sequence.arrived(index * HOP)
    for index in (0, 1, 2):  # ros2 bag play --loop: the indices start again, no loss in this pass
        sequence.arrived(index * HOP)
    assert sequence.lost == 1


def test_stage_health_warns_of_lost_stacks_and_counts_them() -> None:
    health = StageHealth()
    for index in (0, 1, 4):
        health.arrived(index * HOP)
        health.stack([301])
    level, message, values = health.report()
    assert level is Severity.WARN and "2 input stacks never arrived" in message
    assert dict(values)["lost input stacks"] == "2"


def test_a_node_fed_no_stacks_reports_no_lost_stack_count() -> None:
    health = StageHealth()
    health.stack([301])
    assert "lost input stacks" not in dict(health.report().values)


def test_the_cell_table_says_each_cells_site_snr_sigma_and_when_it_was_last_heard() -> None:
    from deepsync.fusion.anchors import SiteArrival
    from deepsync.types import CellTiming, StackArrivals
    from deepsync_ros.health import CellTable

    rate = 1.92e6
    table = CellTable()
    assert table.report().message == "no stack yet"
    site_a = SiteArrival("A", np.zeros(3), 0.0, 0.0, 5.0, (120, 121))
    first = StackArrivals(0, 0, rate, (CellTiming(120, 10.0, 0.05, 12.0, "ml_frame"),
                                       CellTiming(301, 20.0, 0.5, 3.0, "ml_frame")))
    table.heard(first, [site_a])
    later = StackArrivals(2_000_000_000, 3_840_000, rate, (CellTiming(120, 10.1, 0.04, 13.0, "ml_frame"),))
    table.heard(later)  # no fusion here: the site stays what it was
    level, message, values = table.report()
    assert level is Severity.OK and message == "1 of 2 cells heard in the latest stack"
    said = dict(values)
    assert said["PCI 120"].startswith("site A, SNR 13.0 dB, sigma 6.2 m (0.040 samples)")
    assert said["PCI 120"].endswith("last heard 0.0 s before the latest stack")
    assert said["PCI 301"].startswith("site unknown, SNR 3.0 dB, sigma 78.1 m")
    assert "last heard 2.0 s before" in said["PCI 301"]


def test_the_sites_map_marks_the_sites_heard_recently() -> None:
    """Foxglove's Map panel layer: every placed site of the database, green while heard."""
    import json

    from deepsync.fusion.anchors import SiteArrival
    from deepsync.towers import load_tower_database
    from deepsync.types import CellTiming, StackArrivals
    from deepsync_ros.health import HEARD_COLOR, SILENT_COLOR, CellTable, sites_geojson

    towers = load_tower_database(CAMPUS_TOWERS)
    table = CellTable()
    site_a = SiteArrival("A", np.zeros(3), 0.0, 0.0, 5.0, (120,))
    table.heard(StackArrivals(0, 0, 1.92e6, (CellTiming(120, 10.0, 0.05, 12.5, "ml_frame"),)), [site_a])
    features = json.loads(sites_geojson(towers, table))["features"]
    placed = [site for site in towers.sites if site.has_position]
    assert len(features) == len(placed)
    by_name = {feature["properties"]["name"].split(" ")[0]: feature for feature in features}
    assert by_name["A"]["properties"]["heard"] and by_name["A"]["properties"]["style"]["color"] == HEARD_COLOR
    assert "SNR 12.5 dB" in by_name["A"]["properties"]["name"]
    site = towers.site("A")
    assert by_name["A"]["geometry"]["coordinates"] == [site.longitude_deg, site.latitude_deg]  # GeoJSON: lon, lat
    assert all(not f["properties"]["heard"] and f["properties"]["style"]["color"] == SILENT_COLOR
               for name, f in by_name.items() if name != "A")
    later = StackArrivals(10_000_000_000, 19_200_000, 1.92e6, (CellTiming(301, 10.0, 0.05, 3.0, "ml_frame"),))
    table.heard(later)  # A last heard 10 s before: grey again
    assert not json.loads(sites_geojson(towers, table))["features"][0]["properties"]["heard"]
