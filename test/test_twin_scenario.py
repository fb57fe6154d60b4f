"""Scenario files: the bundled ones load, and every kind of mistake is a ConfigError that
names the field."""

from pathlib import Path

import pytest

from deepsync.configio import ConfigError
from deepsync.twin.scenario import Scenario, load_scenario

SCENARIOS = Path(__file__).resolve().parents[1] / "config" / "scenarios"

BASE = """\
name: test
seed: 3
origin: {latitude_deg: 38.9869, longitude_deg: -76.9426, height_m: 10.0}
environment: {model: UMa, los: auto}
channel: {profile_los: TDL-D, profile_nlos: TDL-A, delay_spread_ns: auto}
sites:
  - name: A
    latitude_deg: 38.9858
    longitude_deg: -76.9476
    height_m: 30
    timing_offset_us: 100.0
    cells:
      - {pci: 120, earfcn: 2000, bandwidth_mhz: 10, eirp_dbm: 61, azimuth_deg: 30,
         downtilt_deg: 6, load: 0.8}
  - name: B
    latitude_deg: 38.9921
    longitude_deg: -76.9402
    height_m: 25
    cells:
      - {pci: 301, earfcn: 2000, bandwidth_mhz: 10, eirp_dbm: 60, azimuth_deg: 205,
         downtilt_deg: 4}
receiver:
  height_m: 1.5
  position: {latitude_deg: 38.9869, longitude_deg: -76.9426}
frontend: {}
"""

SITE_B_CELLS = """\
    cells:
      - {pci: 301, earfcn: 2000, bandwidth_mhz: 10, eirp_dbm: 60, azimuth_deg: 205,
         downtilt_deg: 4}
"""
POSITION = "  position: {latitude_deg: 38.9869, longitude_deg: -76.9426}\n"
ROUTE = """\
  route:
    speed_mps: 1.4
    waypoints:
      - {latitude_deg: 38.9869, longitude_deg: -76.9426}
      - {latitude_deg: 38.9872, longitude_deg: -76.9420}
"""


def _write(tmp_path, text):
    path = tmp_path / "scenario.yaml"
    path.write_text(text)
    return path


def _edit(old, new, text=BASE):
    assert text.count(old) == 1, old
    return text.replace(old, new)


def test_base_scenario_is_valid(tmp_path):
    scenario = load_scenario(_write(tmp_path, BASE))
    assert isinstance(scenario, Scenario)
    first, second = scenario.cells
    assert (first.pci, first.earfcn, first.carrier_hz, first.band) == (120, 2000, 2115e6, 4)
    assert first.config.load == 0.8 and first.config.cfi == 2
    assert second.config.load == 1.0
    assert scenario.sites[0].timing_offset_us == 100.0
    assert scenario.sites[0].frequency_error_ppb is None  # auto by omission
    assert scenario.sites[1].timing_offset_us is None
    assert scenario.channel.delay_spread_ns is None
    assert scenario.receiver.route is None


def test_route_and_optional_sections(tmp_path):
    text = _edit(POSITION, ROUTE)
    text = _edit("channel: {profile_los: TDL-D, profile_nlos: TDL-A, delay_spread_ns: auto}\n",
                 "", text)
    text = _edit("environment: {model: UMa, los: auto}\n", "", text)
    text = _edit("frontend: {}\n", "frontend: {adc_bits: 10}\n", text)
    text = _edit("load: 0.8}", "load: 0.8, cfi: 3, modulation_weights: [1, 0, 0],\n"
                 "         antenna: {horizontal_beamwidth_deg: 90}}", text)
    scenario = load_scenario(_write(tmp_path, text))
    assert scenario.receiver.position is None
    assert scenario.receiver.route.speed_mps == 1.4
    assert len(scenario.receiver.route.waypoints) == 2
    assert not scenario.receiver.route.loop
    assert scenario.environment.model == "UMa" and scenario.channel.profile_nlos == "TDL-A"
    assert scenario.frontend.adc_bits == 10
    cell = scenario.cells[0]
    assert cell.config.cfi == 3 and cell.config.modulation_weights == (1.0, 0.0, 0.0)
    assert cell.antenna.horizontal_beamwidth_deg == 90.0


def test_same_pci_on_another_carrier_is_fine(tmp_path):
    text = _edit("{pci: 301, earfcn: 2000", "{pci: 120, earfcn: 2300")
    assert [c.pci for c in load_scenario(_write(tmp_path, text)).cells] == [120, 120]


@pytest.mark.parametrize("name", ["campus", "campus_walk"])
def test_bundled_scenarios_load(name):
    scenario = load_scenario(SCENARIOS / f"{name}.yaml")
    assert scenario.name == name
    assert [c.pci for c in scenario.cells] == [120, 121, 301, 56]
    assert [c.earfcn for c in scenario.cells] == [2000, 2000, 2000, 2300]
    assert [s.name for s in scenario.sites] == ["A", "B", "C"]
    assert all(s.timing_offset_us is not None and s.frequency_error_ppb is not None
               for s in scenario.sites)
    assert scenario.environment.model == "UMa"
    assert (scenario.receiver.route is None) == (name == "campus")


# (old text, new text, field path that the error must name)
BROKEN = [
    ("seed: 3\n", "seed: 3\ncolour: blue\n", "scenario: unknown key colour"),
    ("load: 0.8}", "load: 0.8, power: 3}", "scenario.sites[0].cells[0]: unknown key power"),
    ("height_m: 1.5\n", "height_m: 1.5\n  speed: 2\n", "scenario.receiver: unknown key speed"),
    ("seed: 3\n", "", "scenario.seed: required but missing"),
    ("name: test\n", "", "scenario.name: required but missing"),
    ("{pci: 301, ", "{", "scenario.sites[1].cells[0].pci: required but missing"),
    ("    height_m: 30\n", "", "scenario.sites[0].height_m: required but missing"),
    ("origin: {latitude_deg: 38.9869, longitude_deg: -76.9426, height_m: 10.0}\n", "",
     "scenario.origin: required but missing"),
    ("pci: 120", "pci: one-twenty", "scenario.sites[0].cells[0].pci: expected an integer"),
    ("pci: 120", "pci: 120.5", "scenario.sites[0].cells[0].pci: expected an integer"),
    ("eirp_dbm: 61", "eirp_dbm: high", "scenario.sites[0].cells[0].eirp_dbm: expected a number"),
    ("seed: 3", "seed: [3]", "scenario.seed"),
    ("name: test", "name: 5", "scenario.name: expected a string"),
    ("frontend: {}", "frontend: []", "scenario.frontend: expected a mapping"),
    ("load: 0.8}", "load: 0.8, cfi: two}", "scenario.sites[0].cells[0].cfi"),
    (SITE_B_CELLS, "    cells: 3\n", "scenario.sites[1].cells: expected a list"),
    (SITE_B_CELLS, "    cells: []\n", "scenario.sites[1].cells: must not be empty"),
    (SITE_B_CELLS, "    cells: [7]\n", "scenario.sites[1].cells[0]: expected a mapping"),
    ("latitude_deg: 38.9858", "latitude_deg: .nan", "scenario.sites[0].latitude_deg"),
    ("eirp_dbm: 61", "eirp_dbm: .inf", "scenario.sites[0].cells[0].eirp_dbm"),
    ("height_m: 10.0}", "height_m: -.inf}", "scenario.origin.height_m"),
    ("frontend: {}", "frontend: {adc_rate_hz: .nan}", "scenario.frontend.adc_rate_hz"),
    ("timing_offset_us: 100.0", "timing_offset_us: .nan", "scenario.sites[0].timing_offset_us"),
    ("delay_spread_ns: auto", "delay_spread_ns: .inf", "scenario.channel.delay_spread_ns"),
    ("load: 0.8}", "load: .nan}", "scenario.sites[0].cells[0].load"),
    ("pci: 120", "pci: .nan", "scenario.sites[0].cells[0].pci"),
    ("pci: 120", "pci: 504", "scenario.sites[0].cells[0].pci: PCI 504 is out of range"),
    ("pci: 120", "pci: -1", "scenario.sites[0].cells[0].pci"),
    ("pci: 301", "pci: 120", "scenario.sites[1].cells[0].pci: PCI 120 on EARFCN 2000 is already "
     "used by scenario.sites[0].cells[0]"),
    ("earfcn: 2000, bandwidth_mhz: 10, eirp_dbm: 61",
     "earfcn: 6600, bandwidth_mhz: 10, eirp_dbm: 61",
     "scenario.sites[0].cells[0].earfcn: EARFCN 6600"),
    ("earfcn: 2000, bandwidth_mhz: 10, eirp_dbm: 61",
     "earfcn: 99999, bandwidth_mhz: 10, eirp_dbm: 61", "scenario.sites[0].cells[0].earfcn"),
    ("bandwidth_mhz: 10, eirp_dbm: 61", "bandwidth_mhz: 7, eirp_dbm: 61",
     "scenario.sites[0].cells[0].bandwidth_mhz: bandwidth 7"),
    ("earfcn: 2000, bandwidth_mhz: 10, eirp_dbm: 61",
     "earfcn: 1990, bandwidth_mhz: 10, eirp_dbm: 61",
     "scenario.sites[0].cells[0].bandwidth_mhz: a 10 MHz channel at EARFCN 1990"),
    ("load: 0.8}", "load: 1.5}", "scenario.sites[0].cells[0].load"),
    ("load: 0.8}", "load: 0.8, cfi: 4}", "scenario.sites[0].cells[0].cfi"),
    ("load: 0.8}", "load: 0.8, modulation_weights: [0, 0, 0]}",
     "scenario.sites[0].cells[0].modulation_weights"),
    ("load: 0.8}", "load: 0.8, antenna: {front_back_db: -3}}",
     "scenario.sites[0].cells[0].antenna"),
    ("downtilt_deg: 6", "downtilt_deg: 95", "scenario.sites[0].cells[0].downtilt_deg"),
    ("latitude_deg: 38.9858", "latitude_deg: 95", "scenario.sites[0].latitude_deg"),
    ("longitude_deg: -76.9402", "longitude_deg: -190", "scenario.sites[1].longitude_deg"),
    ("origin: {latitude_deg: 38.9869", "origin: {latitude_deg: -91",
     "scenario.origin.latitude_deg"),
    (POSITION, "  position: {latitude_deg: 38.9869, longitude_deg: 181}\n",
     "scenario.receiver.position.longitude_deg"),
    ("    height_m: 30\n", "    height_m: -30\n", "scenario.sites[0].height_m"),
    ("  height_m: 1.5\n", "  height_m: -1.5\n", "scenario.receiver.height_m"),
    ("seed: 3", "seed: -3", "scenario.seed"),
    ("timing_offset_us: 100.0", "timing_offset_us: 10000", "scenario.sites[0].timing_offset_us"),
    ("timing_offset_us: 100.0", "timing_offset_us: -1", "scenario.sites[0].timing_offset_us"),
    ("timing_offset_us: 100.0", "timing_offset_us: soon", "scenario.sites[0].timing_offset_us"),
    ("delay_spread_ns: auto", "delay_spread_ns: 0", "scenario.channel.delay_spread_ns"),
    ("delay_spread_ns: auto", "delay_spread_ns: auto, environment_doppler_hz: -1",
     "scenario.channel.environment_doppler_hz"),
    ("model: UMa", "model: RMa", "scenario.environment.model: unknown value 'RMa'"),
    ("los: auto", "los: maybe", "scenario.environment.los"),
    ("profile_nlos: TDL-A", "profile_nlos: TDL-Z", "scenario.channel.profile_nlos"),
    ("profile_los: TDL-D", "profile_los: tdl-d", "scenario.channel.profile_los"),
    ("  - name: B\n", "  - name: A\n", "scenario.sites[1].name: site name 'A' is already used"),
    (POSITION, POSITION + ROUTE, "scenario.receiver: give exactly one of"),
    (POSITION, "", "scenario.receiver: give exactly one of"),
    (POSITION, ROUTE.replace("1.4", "-1.4"), "scenario.receiver.route.speed_mps"),
    (POSITION, ROUTE.replace("1.4", "0"), "scenario.receiver.route.speed_mps"),
    (POSITION, ROUTE.replace("1.4", ".nan"), "scenario.receiver.route.speed_mps"),
    (POSITION, ROUTE.replace("      - {latitude_deg: 38.9872, longitude_deg: -76.9420}\n", ""),
     "scenario.receiver.route.waypoints: a route needs at least 2 waypoints, got 1"),
    (POSITION, ROUTE.replace("38.9872, longitude_deg: -76.9420",
                             "38.9869, longitude_deg: -76.9426"),
     "scenario.receiver.route.waypoints: all waypoints are the same point"),
    (POSITION, ROUTE.replace("38.9872", "100"),
     "scenario.receiver.route.waypoints[1].latitude_deg"),
    (POSITION, ROUTE.replace("    speed_mps: 1.4\n", "    speed_mps: 1.4\n    loop: sometimes\n"),
     "scenario.receiver.route.loop: expected true or false"),
    (POSITION, ROUTE.replace("    speed_mps: 1.4\n", ""),
     "scenario.receiver.route.speed_mps: required but missing"),
]


@pytest.mark.parametrize(("old", "new", "message"), BROKEN,
                         ids=[f"{i:02d}-{case[2][:40]}" for i, case in enumerate(BROKEN)])
def test_broken_scenarios_name_the_field(tmp_path, old, new, message):
    with pytest.raises(ConfigError) as error:
        load_scenario(_write(tmp_path, _edit(old, new)))
    assert message in str(error.value)


@pytest.mark.parametrize(("sites", "message"), [
    ("sites: 5\n", "scenario.sites: expected a list, got int"),
    ("sites: {name: A}\n", "scenario.sites: expected a list, got dict"),
    ("sites: []\n", "scenario.sites: must not be empty"),
    ("sites:\n", "scenario.sites: expected a list, got NoneType"),
])
def test_sites_must_be_a_list(tmp_path, sites, message):
    before, rest = BASE.split("sites:\n")
    text = before + sites + "receiver:" + rest.split("receiver:")[1]
    with pytest.raises(ConfigError) as error:
        load_scenario(_write(tmp_path, text))
    assert message in str(error.value)


def test_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        load_scenario(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_scenario(_write(tmp_path, "name: [unclosed\n"))
