"""The twin built from the bundled scenarios: emitters, sites, truth geometry, auto values."""

from pathlib import Path

import numpy as np
import pytest

from deepsync.frontend.config import FrontendConfig
from deepsync.geo import geodetic_to_ecef
from deepsync.twin import build_twin, load_scenario
from deepsync.types import SPEED_OF_LIGHT_M_S
from deepsync.twin.scenario import parse_scenario

SCENARIOS = Path(__file__).resolve().parents[1] / "config" / "scenarios"


@pytest.fixture(scope="module")
def campus():
    return build_twin(load_scenario(SCENARIOS / "campus.yaml"))


@pytest.fixture(scope="module")
def walk():
    return build_twin(load_scenario(SCENARIOS / "campus_walk.yaml"))


def test_emitters_follow_the_scenario(campus):
    assert [e.cell.pci for e in campus.emitters] == [120, 121, 301, 56]
    assert [e.site for e in campus.emitters] == ["A", "A", "B", "C"]
    assert [e.carrier_hz for e in campus.emitters] == [2115e6, 2115e6, 2115e6, 2145e6]
    first = campus.emitters[0]
    # 61 dBm EIRP over 12 * 50 subcarriers of a 10 MHz carrier
    assert first.re_power_w == pytest.approx(10 ** (61 / 10) / 1000 / 600)
    assert first.timing_offset_s == pytest.approx(3120.4e-6)
    assert first.frequency_offset_hz == pytest.approx(12e-9 * 2115e6)
    assert first.cell.load == 0.4 and first.cell.bandwidth_mhz == 10.0
    a, b = campus.emitters[:2]
    assert (a.timing_offset_s, a.frequency_offset_hz) == (b.timing_offset_s, b.frequency_offset_hz)
    assert isinstance(campus.frontend, FrontendConfig)


def test_cell_metadata(campus):
    cell = campus.cells[3]
    assert (cell.pci, cell.earfcn, cell.band, cell.carrier_hz, cell.bandwidth_mhz, cell.site) == \
        (56, 2300, 4, 2145e6, 10.0, "C")
    assert [c.site for c in campus.cells] == [e.site for e in campus.emitters]


def test_geometry_matches_an_independent_ecef_computation(campus):
    scenario = campus.scenario
    ground = scenario.origin.height_m
    rx = scenario.receiver.position
    rx_ecef = geodetic_to_ecef(rx.latitude_deg, rx.longitude_deg,
                               ground + scenario.receiver.height_m)
    for index, emitter in enumerate(campus.emitters):
        spec = next(s for s in scenario.sites if s.name == emitter.site)
        site_ecef = geodetic_to_ecef(spec.latitude_deg, spec.longitude_deg, ground + spec.height_m)
        distance = np.linalg.norm(site_ecef - rx_ecef)
        assert campus.geometric_delay_s(index, 5.0) * SPEED_OF_LIGHT_M_S == pytest.approx(
            distance, abs=1e-3)
        np.testing.assert_allclose(campus.site(emitter.site).position_enu,
                                   campus.frame.ecef_to_enu(site_ecef), atol=1e-6)
    np.testing.assert_allclose(campus.receiver_enu(0.0), campus.receiver_enu(100.0))


def test_campus_geometry_is_as_documented(campus):
    rx = campus.receiver_enu(0.0)
    bearings = []
    for site in campus.sites:
        offset = site.position_enu - rx
        assert 300.0 <= np.hypot(offset[0], offset[1]) <= 700.0
        bearings.append(np.degrees(np.arctan2(offset[0], offset[1])) % 360.0)
    gaps = np.diff(np.sort(bearings + [min(bearings) + 360.0]))
    assert np.all(gaps > 90.0)  # sites spread around the receiver
    assert [s.height_m for s in campus.sites] == [30.0, 25.0, 28.0]


def test_walk_route(walk, campus):
    route = walk.scenario.receiver.route
    assert route.speed_mps == 1.4 and 4 <= len(route.waypoints) <= 6
    assert walk.receiver.length_m == pytest.approx(300.0, abs=30.0)
    np.testing.assert_allclose(walk.receiver_enu(0.0), campus.receiver_enu(0.0), atol=1e-6)
    assert np.linalg.norm(walk.receiver.velocity_enu(60.0)) == pytest.approx(1.4)
    lat, lon, _ = walk.receiver.position_llh(walk.receiver.duration_s)
    assert (float(lat), float(lon)) == pytest.approx(
        (route.waypoints[-1].latitude_deg, route.waypoints[-1].longitude_deg), abs=1e-9)
    assert [s.name for s in walk.sites] == [s.name for s in campus.sites]
    assert walk.channel.paths(0, 100.0).first_delay_s == pytest.approx(
        walk.geometric_delay_s(0, 100.0), abs=1e-15)


def _auto_scenario(seed, sites=("A", "B")):
    def site(name, k):
        return {"name": name, "latitude_deg": 38.98 + 0.003 * k, "longitude_deg": -76.94,
                "height_m": 25.0, "timing_offset_us": "auto",
                "cells": [{"pci": k, "earfcn": 2000, "bandwidth_mhz": 10, "eirp_dbm": 60.0,
                           "azimuth_deg": 180.0, "downtilt_deg": 4.0}]}

    return parse_scenario({
        "name": "auto", "seed": seed,
        "origin": {"latitude_deg": 38.97, "longitude_deg": -76.94, "height_m": 0.0},
        "sites": [site(name, k) for k, name in enumerate(sites)],
        "receiver": {"height_m": 1.5,
                     "position": {"latitude_deg": 38.97, "longitude_deg": -76.94}},
    })


def test_auto_timing_and_oscillator_are_drawn_from_the_seed():
    twin = build_twin(_auto_scenario(3))
    again = build_twin(_auto_scenario(3))
    other = build_twin(_auto_scenario(4))
    for site in twin.sites:
        assert 0.0 <= site.timing_offset_s < 10e-3
        assert -20.0 <= site.frequency_error_ppb <= 20.0
    assert twin.sites == again.sites
    assert twin.sites[0].timing_offset_s != twin.sites[1].timing_offset_s
    assert twin.sites[0].timing_offset_s != other.sites[0].timing_offset_s
    assert twin.emitters[1].frequency_offset_hz == pytest.approx(
        twin.sites[1].frequency_error_ppb * 1e-9 * 2115e6)
    # adding a site leaves the others' draws unchanged (streams are keyed by site name)
    more = build_twin(_auto_scenario(3, sites=("A", "B", "Z")))
    assert more.sites[1].timing_offset_s == twin.sites[1].timing_offset_s
    assert more.sites[1].frequency_error_ppb == twin.sites[1].frequency_error_ppb


def test_unknown_site_lookup(campus):
    with pytest.raises(KeyError, match="Q"):
        campus.site("Q")
