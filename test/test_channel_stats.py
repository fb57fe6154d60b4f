"""Channel statistics against hand-computed values."""

import math

import numpy as np
import pytest

from deepsync.eval.channel_stats import channel_statistics, direct_first, path_statistics
from deepsync.frontend.channel import Emitter, Paths
from deepsync.lte.cell import CellConfig
from deepsync.types import SPEED_OF_LIGHT_M_S

C = SPEED_OF_LIGHT_M_S


def test_one_direct_path_has_no_spread_and_no_excess():
    stats = path_statistics(Paths([2e-6], [1e-4], [0.0]), 2e-6)
    assert stats["delay_spread_ns"] == pytest.approx(0.0, abs=1e-9)
    assert stats["first_path_share"] == 1.0
    assert stats["first_path_excess_m"] == pytest.approx(0.0, abs=1e-6)
    assert stats["centroid_excess_m"] == pytest.approx(0.0, abs=1e-6)
    assert stats["direct_first"] == 1.0


def test_two_equal_paths_split_the_power_and_pull_the_centroid_halfway():
    stats = path_statistics(Paths([2e-6, 2.2e-6], [1e-4, 1e-4j], [0.0, 0.0]), 2e-6)
    assert stats["delay_spread_ns"] == pytest.approx(100.0, rel=1e-9)
    assert stats["first_path_share"] == pytest.approx(0.5)
    assert stats["centroid_excess_m"] == pytest.approx(0.1e-6 * C, rel=1e-9)


def test_a_blocked_direct_path_arrives_late():
    stats = path_statistics(Paths([2.1e-6, 2.3e-6], [1e-4, 1e-5], [0.0, 0.0]), 2e-6)
    assert stats["first_path_excess_m"] == pytest.approx(0.1e-6 * C, rel=1e-9)
    assert stats["direct_first"] == 0.0


class _TwoSectorChannel:
    """Sector 0 weak and direct, sector 1 strong and late, on one site."""

    def paths(self, emitter_index, t):
        return Paths([1e-6], [1e-5], [0.0]) if emitter_index == 0 else Paths([1.5e-6], [1e-3], [0.0])

    def geometric_delay_s(self, emitter_index, t):
        return 1e-6


def test_a_site_is_described_by_its_strongest_sector():
    emitters = [Emitter(CellConfig(pci, 10.0, 1.0), 2.1e9, 0.1, site="S1") for pci in (10, 11)]
    table = channel_statistics(_TwoSectorChannel(), emitters, np.linspace(0, 1, 5))
    row = table["S1"]
    assert row["instants"] == 5
    assert row["direct_first_share"] == 0.0  # the strong sector's first path is late
    assert row["first_path_excess_m"] == pytest.approx(0.5e-6 * C)
    assert row["received_dbm"] == pytest.approx(10 * math.log10(1e-6 * 0.1) + 30)


class _TurningChannel:
    """One site of two sectors: until t = 1 s sector 0 is the stronger and direct, after it
    sector 1 is, and its earliest path comes late (the direct one blocked)."""

    def paths(self, emitter_index, t):
        strong = (emitter_index == 0) == (t < 1.0)
        delay = 1e-6 if emitter_index == 0 else 1.2e-6
        return Paths([delay], [1e-3 if strong else 1e-5], [0.0])

    def geometric_delay_s(self, emitter_index, t):
        return 1e-6


def test_line_of_sight_follows_the_strongest_sector_at_each_moment():
    emitters = [Emitter(CellConfig(pci, 10.0, 1.0), 2.1e9, 0.1, site="S1") for pci in (10, 11)]
    assert direct_first(_TurningChannel(), emitters, "S1", 0.5)
    assert not direct_first(_TurningChannel(), emitters, "S1", 1.5)
