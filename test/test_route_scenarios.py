"""The route scenarios (a hard urban walk and its denser variant) and their tower databases: what
they promise in their comments, checked from the files."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from deepsync.geo import LocalFrame
from deepsync.twin import build_twin
from deepsync.twin.scenario import load_scenario

REPO = Path(__file__).resolve().parents[1]
ROUTES = {  # name -> site distances from every point of the route (m)
    "route_urban": (200.0, 1000.0),
    "route_dense": (150.0, 450.0),
}


@pytest.fixture(scope="module", params=sorted(ROUTES))
def route(request):
    name = request.param
    scenario = load_scenario(REPO / "config" / "scenarios" / f"{name}.yaml")
    towers = yaml.safe_load((REPO / "config" / "towers" / f"{name}.yaml").read_text())
    return name, scenario, build_twin(scenario), towers


def test_a_walk_of_about_a_minute_and_a_half(route):
    _, scenario, twin, _ = route
    assert scenario.receiver.route.speed_mps == 1.4
    assert 80.0 <= twin.receiver.duration_s <= 100.0


def test_at_least_six_sites_on_two_carriers_with_co_sited_sectors(route):
    _, scenario, _, _ = route
    assert len(scenario.sites) >= 6
    assert {cell.earfcn for cell in scenario.cells} == {2000, 2300}  # band 4, 2115 and 2145 MHz
    assert {cell.bandwidth_mhz for cell in scenario.cells} == {10}
    pairs = 0
    for site in scenario.sites:
        for earfcn in {cell.earfcn for cell in site.cells}:
            pcis = [cell.pci for cell in site.cells if cell.earfcn == earfcn]
            if len(pcis) > 1:  # sectors of one mast: one PCI group, different N_ID2
                assert len({pci // 3 for pci in pcis}) == 1 and len({pci % 3 for pci in pcis}) == len(pcis)
                pairs += 1
    assert pairs >= 2
    assert all(site.timing_offset_us is not None for site in scenario.sites)  # the database repeats them
    assert all(site.frequency_error_ppb is not None and abs(site.frequency_error_ppb) <= 20 for site in scenario.sites)


def test_every_site_stays_within_its_distance_band_along_the_whole_route(route):
    name, _, twin, _ = route
    low, high = ROUTES[name]
    walk = twin.receiver.position_enu(np.linspace(0.0, twin.receiver.duration_s, 400))
    for site in twin.sites:
        horizontal = np.hypot(*(walk[:, :2] - site.position_enu[:2]).T)
        assert low <= horizontal.min() and horizontal.max() <= high, (site.name, horizontal.min(), horizontal.max())


def test_the_tower_database_lists_every_cell_at_its_site_plus_unheard_neighbours(route):
    name, scenario, twin, towers = route
    origin = scenario.origin
    assert towers["name"] == name
    assert towers["origin"] == {"latitude_deg": origin.latitude_deg, "longitude_deg": origin.longitude_deg,
                                "height_m": origin.height_m}
    assert towers["timing_epoch_utc"] == "2026-01-01T00:00:00Z"  # a simulated recording's first sample
    frame = LocalFrame(origin.latitude_deg, origin.longitude_deg, origin.height_m)

    def position(site) -> np.ndarray:
        return frame.geodetic_to_enu(site["latitude_deg"], site["longitude_deg"], origin.height_m + site["height_m"])

    listed = {(cell["pci"], cell["earfcn"]): site for site in towers["sites"] for cell in site["cells"]}
    for spec, site in zip(scenario.sites, twin.sites):
        for cell in spec.cells:
            entry = listed[(cell.pci, cell.earfcn)]
            assert np.linalg.norm(position(entry) - site.position_enu) < 1.0, (cell.pci, spec.name)
            assert entry["timing_offset_us"] == spec.timing_offset_us
            assert "timing_drift_ns_per_s" not in entry  # calibration's to estimate, not the database's
    scenario_cells = {(cell.pci, cell.earfcn) for cell in scenario.cells}
    neighbours = [site for site in towers["sites"]
                  if min(np.linalg.norm(position(site) - s.position_enu) for s in twin.sites) > 1.0]
    assert len(neighbours) >= 2
    for site in neighbours:  # on the air, not simulated: nothing of theirs is in the scenario
        assert not {(cell["pci"], cell["earfcn"]) for cell in site["cells"]} & scenario_cells


def test_the_reference_station_hears_the_dense_routes_network_from_a_fixed_rooftop():
    """route_dense_reference must share route_dense's sites and frame clocks exactly (else its
    calibration is of another network) and stand still above the street, in line of sight."""
    route = load_scenario(REPO / "config" / "scenarios" / "route_dense.yaml")
    station = load_scenario(REPO / "config" / "scenarios" / "route_dense_reference.yaml")
    assert station.sites == route.sites
    assert (station.origin, station.seed) == (route.origin, route.seed)
    assert station.receiver.route is None and station.receiver.height_m >= 10.0
    assert station.environment.los == "los"
