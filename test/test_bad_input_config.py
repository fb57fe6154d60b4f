"""Bad input, configuration: one file of the project's bad-input matrix (``test/test_bad_input_*.py``,
issue "Nothing silent, nothing lost").

The matrix has one row per bad input, and each row asserts the outcome class that input must
get. Here, for configuration (the receiver chain ``FrontendConfig``, scenario files, tower
databases), the outcome is always a ConfigError/ValueError at load time whose message names the
field and its allowed range, never a value that passes silently and fails later (out of memory,
an OverflowError, a cell dropped from the search, a receiver on the other side of the Earth
still "in line of sight"). A few rows per table show that the edge values of each range still
pass. Later work (fusion, the timing network, the ROS nodes) adds its own files and rows.
"""

import copy
import dataclasses
import re
from pathlib import Path

import pytest
import yaml

from deepsync.configio import ConfigError
from deepsync.frontend.config import FrontendConfig
from deepsync.schema import settings
from deepsync.sync.search import SearchConfig
from deepsync.sync.stacking import StackConfig
from deepsync.sync.stage import SyncConfig
from deepsync.timing.stage import TimingConfig
from deepsync.towers import load_tower_database, parse_tower_database
from deepsync.twin.scenario import Scenario, load_scenario, parse_scenario

CONFIG = Path(__file__).resolve().parents[1] / "config"

# -- FrontendConfig ----------------------------------------------------------------------------

# (overrides, field, allowed range as the message gives it)
BAD_FRONTEND = [
    pytest.param({"adc_rate_hz": 1e10}, "adc_rate_hz", "[100000, 6.144e+07] Hz",
                 id="adc-rate-10GHz-out-of-memory"),
    pytest.param({"adc_rate_hz": 5e4, "video_cutoff_hz": 2e4, "video_highpass_hz": 0.0},
                 "adc_rate_hz", "[100000, 6.144e+07] Hz", id="adc-rate-50kHz"),
    pytest.param({"adc_bits": 17}, "adc_bits", "[2, 16] bits", id="adc-bits-17"),
    pytest.param({"adc_full_scale_v": 1000.0}, "adc_full_scale_v", "[0.1, 20] V",
                 id="full-scale-1kV"),
    pytest.param({"adc_full_scale_v": 1e-3}, "adc_full_scale_v", "[0.1, 20] V",
                 id="full-scale-1mV"),
    pytest.param({"adc_noise_lsb": 1000.0}, "adc_noise_lsb", "[0, 16] LSB RMS",
                 id="adc-noise-1000-lsb"),
    pytest.param({"clock_offset_ppm": 2000.0}, "clock_offset_ppm", "[-1000, 1000] ppm",
                 id="clock-offset-2000ppm"),
    pytest.param({"clock_drift_ppm_per_s": -11.0}, "clock_drift_ppm_per_s", "[-10, 10] ppm/s",
                 id="clock-drift-11ppm-per-s"),
    pytest.param({"video_cutoff_hz": 1e3, "video_highpass_hz": 0.0}, "video_cutoff_hz",
                 "[10000, 3.072e+07] Hz", id="video-cutoff-1kHz"),
    pytest.param({"video_highpass_hz": 5e3}, "video_highpass_hz", "[0, 1000] Hz",
                 id="highpass-5kHz"),
    pytest.param({"video_filter_order": 9}, "video_filter_order", "[0, 8]", id="filter-order-9"),
    pytest.param({"video_gain_db": 1e6}, "video_gain_db", "[-40, 100] dB", id="video-gain-1e6dB"),
    pytest.param({"video_gain_db": -200.0}, "video_gain_db", "[-40, 100] dB",
                 id="video-gain-minus-200dB"),
    pytest.param({"agc_target_dbfs": -0.5}, "agc_target_dbfs", "[-60, -1] dBFS",
                 id="agc-target-clips"),
    pytest.param({"agc_target_dbfs": -200.0}, "agc_target_dbfs", "[-60, -1] dBFS",
                 id="agc-target-minus-200dBFS"),
    pytest.param({"detector_responsivity_v_per_w": 1e9}, "detector_responsivity_v_per_w",
                 "[10, 100000] V/W", id="responsivity-1GV-per-W"),
    pytest.param({"detector_responsivity_v_per_w": 0.01}, "detector_responsivity_v_per_w",
                 "[10, 100000] V/W", id="responsivity-10mV-per-W"),
    pytest.param({"detector_nep_w_per_sqrt_hz": 1e-3}, "detector_nep_w_per_sqrt_hz",
                 "[0, 1e-09] W/sqrt(Hz)", id="nep-1mW"),
    pytest.param({"noise_figure_db": 1e6}, "noise_figure_db", "[0, 100] dB",
                 id="noise-figure-1e6dB-overflow"),
    pytest.param({"rf_gain_db": 61.0}, "rf_gain_db", "[0, 60] dB", id="rf-gain-61dB"),
    pytest.param({"rf_bandwidth_hz": 1e12}, "rf_bandwidth_hz", "[100000, 6e+09] Hz",
                 id="rf-bandwidth-1THz"),
    pytest.param({"rf_bandwidth_hz": 1e3}, "rf_bandwidth_hz", "[100000, 6e+09] Hz",
                 id="rf-bandwidth-1kHz"),
    pytest.param({"noise_temperature_k": 1e6}, "noise_temperature_k", "[0, 1000] K",
                 id="noise-temperature-1MK"),
]


@pytest.mark.parametrize(("overrides", "field", "allowed"), BAD_FRONTEND)
def test_bad_frontend_config_names_the_field_and_range(overrides, field, allowed):
    with pytest.raises(ValueError) as error:
        FrontendConfig(**overrides)
    assert f"{field} must be within {allowed}, got" in str(error.value)


@pytest.mark.parametrize(("overrides", "field", "allowed"), BAD_FRONTEND)
def test_bad_frontend_section_of_a_scenario_names_the_path(overrides, field, allowed):
    data = _scenario()
    data["frontend"] = overrides
    with pytest.raises(ConfigError) as error:
        parse_scenario(data)
    assert f"scenario.frontend: {field} must be within {allowed}" in str(error.value)


@pytest.mark.parametrize("overrides", [
    pytest.param({"adc_rate_hz": 61.44e6}, id="adc-rate-61.44MHz"),
    pytest.param({"adc_rate_hz": 0.1e6, "video_cutoff_hz": 10e3, "video_highpass_hz": 0.0},
                 id="adc-rate-0.1MHz-cutoff-10kHz"),
    pytest.param({"noise_figure_db": 100.0, "noise_temperature_k": 1000.0}, id="noisiest"),
    pytest.param({"noise_temperature_k": 0.0, "detector_nep_w_per_sqrt_hz": 0.0,
                  "adc_noise_lsb": 0.0, "video_highpass_hz": 0.0}, id="noiseless"),
    pytest.param({"video_gain_db": 100.0, "agc_target_dbfs": -60.0}, id="gain-and-agc-edges"),
    pytest.param({"adc_bits": 2, "video_filter_order": 0, "rf_gain_db": 0.0}, id="int-edges"),
])
def test_frontend_edge_values_pass(overrides):
    config = FrontendConfig(**overrides)
    assert all(getattr(config, name) == value for name, value in overrides.items())


# -- scenario files ----------------------------------------------------------------------------

BASE = """\
name: bad-input
seed: 3
origin: {latitude_deg: 38.9869, longitude_deg: -76.9426, height_m: 10.0}
environment: {model: UMa, los: auto}
channel: {delay_spread_ns: auto, environment_doppler_hz: 1.0}
sites:
  - name: A
    latitude_deg: 38.9858
    longitude_deg: -76.9476
    height_m: 30
    timing_offset_us: 100.0
    frequency_error_ppb: 12.0
    cells:
      - {pci: 120, earfcn: 2000, bandwidth_mhz: 10, eirp_dbm: 61, azimuth_deg: 30,
         downtilt_deg: 6, antenna: {horizontal_beamwidth_deg: 65}}
receiver:
  height_m: 1.5
  position: {latitude_deg: 38.9869, longitude_deg: -76.9426}
frontend: {}
"""
ROUTE = {"speed_mps": 1.4, "waypoints": [{"latitude_deg": 38.9869, "longitude_deg": -76.9426},
                                         {"latitude_deg": 38.9872, "longitude_deg": -76.9420}]}
CELL = ("sites", 0, "cells", 0)
ANTIPODE = {"latitude_deg": -38.9869, "longitude_deg": 103.0574}  # 12,740 km through the Earth


def _scenario(*edits: tuple[tuple, object]) -> dict:
    """The base scenario as a mapping, with ``(key path, value)`` edits applied."""
    data = yaml.safe_load(BASE)
    for path, value in edits:
        node = data
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = copy.deepcopy(value)
    return data


def _route(*points: tuple[float, float], speed: float = 1.4) -> dict:
    return {"speed_mps": speed,
            "waypoints": [{"latitude_deg": lat, "longitude_deg": lon} for lat, lon in points]}


# (edits, field path, the range or limit as the message gives it)
BAD_SCENARIO = [
    pytest.param([(CELL + ("eirp_dbm",), 300)], "scenario.sites[0].cells[0].eirp_dbm",
                 "300.0 is outside [-30, 80] dBm", id="eirp-plus-300dBm"),
    pytest.param([(CELL + ("eirp_dbm",), -300)], "scenario.sites[0].cells[0].eirp_dbm",
                 "-300.0 is outside [-30, 80] dBm", id="eirp-minus-300dBm"),
    pytest.param([(CELL + ("azimuth_deg",), 1e20)], "scenario.sites[0].cells[0].azimuth_deg",
                 "1e+20 is outside [-360, 360] deg", id="azimuth-1e20"),
    pytest.param([(CELL + ("azimuth_deg",), -400)], "scenario.sites[0].cells[0].azimuth_deg",
                 "is outside [-360, 360] deg", id="azimuth-minus-400"),
    pytest.param([(CELL + ("downtilt_deg",), 60)], "scenario.sites[0].cells[0].downtilt_deg",
                 "is outside [-20, 45] deg", id="downtilt-60"),
    pytest.param([(CELL + ("antenna",), {"horizontal_beamwidth_deg": 359})],
                 "scenario.sites[0].cells[0].antenna.horizontal_beamwidth_deg",
                 "is outside [10, 180] deg", id="beamwidth-359"),
    pytest.param([(CELL + ("antenna",), {"front_back_db": 1000})],
                 "scenario.sites[0].cells[0].antenna.front_back_db",
                 "is outside [5, 60] dB", id="front-back-1000dB"),
    pytest.param([(("sites", 0, "frequency_error_ppb"), 1e9)],
                 "scenario.sites[0].frequency_error_ppb",
                 "is outside [-1000, 1000] ppb", id="oscillator-1e9ppb"),
    pytest.param([(("sites", 0, "frequency_error_ppb"), -1500)],
                 "scenario.sites[0].frequency_error_ppb",
                 "is outside [-1000, 1000] ppb", id="oscillator-minus-1500ppb"),
    pytest.param([(("sites", 0, "height_m"), 5000)], "scenario.sites[0].height_m",
                 "is outside [1, 1000] m", id="site-height-5km"),
    pytest.param([(("sites", 0, "height_m"), 0.5)], "scenario.sites[0].height_m",
                 "is outside [1, 1000] m", id="site-height-half-metre"),
    pytest.param([(("receiver", "height_m"), 1000)], "scenario.receiver.height_m",
                 "is outside [0.1, 300] m", id="receiver-height-1km"),
    pytest.param([(("origin", "height_m"), 1e5)], "scenario.origin.height_m",
                 "is outside [-1000, 9000] m", id="ground-100km-up"),
    pytest.param([(("seed",), 2**64)], "scenario.seed",
                 "is outside [0, 9.22337e+18]", id="seed-beyond-int64"),
    pytest.param([(("channel", "delay_spread_ns"), 1e6)], "scenario.channel.delay_spread_ns",
                 "is outside [1, 5000] ns", id="delay-spread-1ms"),
    pytest.param([(("channel", "environment_doppler_hz"), 1e4)],
                 "scenario.channel.environment_doppler_hz", "is outside [0, 300] Hz",
                 id="environment-doppler-10kHz"),
    pytest.param([(("channel",), {"model": "raytraced", "scene": "munich", "samples_per_source": 10})],
                 "scenario.channel.samples_per_source", "is outside [10000, 1e+08]", id="raytrace-10-rays"),
    pytest.param([(("channel",), {"model": "raytraced", "scene": "munich", "default_building_height_m": -3})],
                 "scenario.channel.default_building_height_m", "is outside [1, 1000] m",
                 id="raytrace-negative-building-height"),
    pytest.param([(("channel",), {"model": "raytraced", "scene": "/nonexistent/city.geojson"})],
                 "scenario.channel.scene", "is neither a bundled scene", id="raytrace-missing-scene-file"),
    pytest.param([(("receiver", "position"), None), (("receiver", "route"), {**ROUTE, "speed_mps": 1e3})],
                 "scenario.receiver.route.speed_mps", "is outside [0.1, 140] m/s",
                 id="speed-1km-per-s"),
    pytest.param([(("receiver", "position"), None), (("receiver", "route"), {**ROUTE, "speed_mps": 0.01})],
                 "scenario.receiver.route.speed_mps", "is outside [0.1, 140] m/s",
                 id="speed-1cm-per-s"),
    pytest.param([(("receiver", "position"), None),
                  (("receiver", "route"), _route((38.9869, -76.9426), (39.3869, -76.9426), speed=0.2))],
                 "scenario.receiver.route", "outside [0.01, 86400] s", id="route-takes-2.5-days"),
    pytest.param([(("receiver", "position"), None),
                  (("receiver", "route"), _route((38.9869, -76.9426), (38.98690001, -76.9426)))],
                 "scenario.receiver.route", "outside [0.01, 86400] s", id="route-1mm-long"),
    pytest.param([(("receiver", "position"), ANTIPODE)], "scenario.receiver.position",
                 "km from the origin, beyond the 100 km", id="receiver-12000km"),
    pytest.param([(("environment", "los"), "los"), (("receiver", "position"), ANTIPODE)],
                 "scenario.receiver.position", "km from the origin, beyond the 100 km",
                 id="receiver-12000km-forced-los"),
    pytest.param([(("sites", 0, "latitude_deg"), 39.5869), (("sites", 0, "longitude_deg"), -76.9426),
                  (("receiver", "position"), {"latitude_deg": 38.3869, "longitude_deg": -76.9426})],
                 "scenario.receiver.position", "km from the nearest site ('A'), beyond the 100 km",
                 id="receiver-133km-from-the-only-site"),
    pytest.param([(("receiver", "position"), None),
                  (("receiver", "route"), _route((38.9869, -76.9426), (40.3369, -76.9426), speed=10))],
                 "scenario.receiver.route.waypoints[1]", "149.9 km from the origin, beyond the 100 km",
                 id="route-waypoint-150km"),
    pytest.param([(("sites", 0, "latitude_deg"), 40.5)], "scenario.sites[0]",
                 "site 'A' is 168", id="site-168km-from-origin"),
]


@pytest.mark.parametrize(("edits", "field", "allowed"), BAD_SCENARIO)
def test_bad_scenario_names_the_field_and_range(tmp_path, edits, field, allowed):
    path = tmp_path / "scenario.yaml"
    path.write_text(yaml.safe_dump(_scenario(*edits), sort_keys=False))  # as a user's file
    with pytest.raises(ConfigError) as error:
        load_scenario(path)
    message = str(error.value)
    assert message.startswith(f"{field}: ") and allowed in message, message


@pytest.mark.parametrize("edits", [
    pytest.param([(CELL + ("eirp_dbm",), 80), (CELL + ("azimuth_deg",), -360),
                  (CELL + ("downtilt_deg",), 45)], id="cell-edges-high"),
    pytest.param([(CELL + ("eirp_dbm",), -30), (CELL + ("azimuth_deg",), 360),
                  (CELL + ("downtilt_deg",), -20)], id="cell-edges-low"),
    pytest.param([(("sites", 0, "frequency_error_ppb"), -1000), (("sites", 0, "height_m"), 1000),
                  (("receiver", "height_m"), 300), (("origin", "height_m"), -1000)],
                 id="site-and-heights-edges"),
    pytest.param([(("channel", "delay_spread_ns"), 5000), (("channel", "environment_doppler_hz"), 300),
                  (("seed",), 2**63 - 1)], id="channel-and-seed-edges"),
    pytest.param([(("receiver", "position"), None),
                  (("receiver", "route"), _route((38.9869, -76.9426), (38.9969, -76.9426), speed=140))],
                 id="train-speed"),
    pytest.param([(("receiver", "position"), {"latitude_deg": 38.0869, "longitude_deg": -76.9426})],
                 id="receiver-99km-away"),
])
def test_scenario_edge_values_pass(edits):
    assert isinstance(parse_scenario(_scenario(*edits)), Scenario)


@pytest.mark.parametrize("name", ["campus", "campus_walk", "munich_walk"])
def test_bundled_scenarios_are_inside_every_range(name):
    assert load_scenario(CONFIG / "scenarios" / f"{name}.yaml").name == name


# -- tower databases ---------------------------------------------------------------------------


def _towers(*cells: dict, **site: object) -> dict:
    return {"name": "bad-input", "sites": [{"name": "A", **site, "cells": list(cells)}]}


# (database, field path, what the message must say)
BAD_TOWERS = [
    pytest.param(_towers({"pci": 120, "earfcn": 2000}, {"pci": 121}), "towers.sites[0].cells",
                 "earfcn given for cells[0] but not for cells[1]; give it for every sector of "
                 "site 'A' or for none (sectors of a site are paired by carrier)",
                 id="earfcn-on-one-sector-only"),
    pytest.param(_towers({"pci": 120}, {"pci": 121, "earfcn": 2000}, {"pci": 122, "earfcn": 2000}),
                 "towers.sites[0].cells", "earfcn given for cells[1], cells[2] but not for cells[0]",
                 id="earfcn-missing-on-first-sector"),
    pytest.param(_towers({"pci": 120, "earfcn": 2000}, {"pci": 120, "earfcn": 2000}),
                 "towers.sites[0].cells[1].pci",
                 "PCI 120 on EARFCN 2000 is already used by towers.sites[0].cells[0]",
                 id="same-pci-twice-on-one-carrier"),
    pytest.param(_towers({"pci": 7}, {"pci": 8}, {"pci": 7}), "towers.sites[0].cells[2].pci",
                 "PCI 7 without an EARFCN is already used by towers.sites[0].cells[0]",
                 id="same-pci-twice-without-carriers"),
    pytest.param(_towers({"pci": 1}, latitude_deg=38.98), "towers.sites[0]",
                 "give both latitude_deg and longitude_deg, or neither", id="half-a-position"),
    pytest.param(_towers({"pci": 1}, height_m=5000), "towers.sites[0].height_m",
                 "expected a number in [0, 1000]", id="site-height-5km"),
    pytest.param(_towers({"pci": 1}, timing_offset_us=-1), "towers.sites[0].timing_offset_us",
                 "expected a number in [0, 10000]", id="timing-offset-negative"),
    pytest.param(_towers({"pci": 1}, longitude_deg=200, latitude_deg=0),
                 "towers.sites[0].longitude_deg", "expected a number in [-180, 180]",
                 id="longitude-200"),
    pytest.param(_towers({"pci": 504}), "towers.sites[0].cells[0]",
                 "PCI 504 is out of range (valid: 0..503)", id="pci-504"),
    pytest.param(_towers({"pci": 1, "earfcn": 2000.5}), "towers.sites[0].cells[0]",
                 "EARFCN 2000.5 is not an integer", id="earfcn-fractional"),
    pytest.param(_towers({"pci": 1, "bandwidth_mhz": 12}), "towers.sites[0].cells[0].bandwidth_mhz",
                 "is not an LTE channel bandwidth; choose one of 1.4, 3, 5, 10, 15, 20", id="bandwidth-12MHz"),
    pytest.param(_towers({"pci": 1, "bandwidth_mhz": "10"}), "towers.sites[0].cells[0].bandwidth_mhz",
                 "expected a number of MHz, got '10'", id="bandwidth-as-text"),
    pytest.param(_towers({"pci": 1, "bandwith_mhz": 10}), "towers.sites[0].cells[0]",
                 "expected keys pci and optional earfcn, bandwidth_mhz", id="bandwidth-misspelt"),
]


CAMPUS_A = {"latitude_deg": 38.985851, "longitude_deg": -76.947617}  # a campus site, 0.5 km from its origin
CAMPUS_ORIGIN = {"latitude_deg": 38.9869, "longitude_deg": -76.9426, "height_m": 10.0}


def _placed(*sites: dict, origin: dict | None = None, **top: object) -> dict:
    """A database of ``sites`` (name, position, cells) around the campus origin."""
    return {"name": "bad-input", "origin": origin or CAMPUS_ORIGIN, **top,
            "sites": [{"timing_offset_us": 100.0, **site} for site in sites]}


# on main each of these was accepted, and fusion then said only "too_few_sites" or
# "degenerate_geometry", with no word about the site or the cause
BAD_TOWERS += [
    pytest.param(_placed({"name": "A", **CAMPUS_A, "cells": [{"pci": 120, "earfcn": 2000}]},
                         {"name": "B", "latitude_deg": 38.99, "longitude_deg": -76.94,
                          "cells": [{"pci": 120, "earfcn": 2000}]}),
                 "towers.sites[1].cells[0].pci", "PCI 120 on EARFCN 2000 is also on site 'A' (towers.sites[0].cells[0])",
                 id="pci-reused-on-another-site"),
    pytest.param(_placed({"name": "A", **CAMPUS_A, "cells": [{"pci": 120}, {"pci": 121}]},
                         {"name": "A-copy", **CAMPUS_A, "cells": [{"pci": 120}, {"pci": 121}]}),
                 "towers.sites[1].cells[0].pci", "PCI 120 is also on site 'A'", id="site-duplicated"),
    pytest.param(_placed({"name": "A", **CAMPUS_A, "cells": [{"pci": 120}]},
                         {"name": "far", "latitude_deg": 47.9869, "longitude_deg": -76.9426, "cells": [{"pci": 7}]}),
                 "towers.sites[1]", "site 'far' is 999 km from the origin, beyond the 100 km a cell reaches",
                 id="site-1000km-away"),
    pytest.param(_placed({"name": "A", **CAMPUS_A, "cells": [{"pci": 120}]},
                         {"name": "B", "latitude_deg": -76.947617, "longitude_deg": 38.985851, "cells": [{"pci": 7}]}),
                 "towers.sites[1]", "(with latitude and longitude swapped it would lie within reach: swapped?)",
                 id="latitude-longitude-swapped"),
    pytest.param(_placed({"name": "A", **CAMPUS_A, "cells": [{"pci": 120}]},
                         {"name": "B", "latitude_deg": 38.99, "longitude_deg": -76.94, "cells": [{"pci": 7}]},
                         origin={"latitude_deg": -38.9869, "longitude_deg": 103.0574, "height_m": 10.0}),
                 "towers.origin", "every site lies 12,7", id="origin-at-the-antipode"),
    pytest.param(_placed({"name": "A", **CAMPUS_A, "cells": [{"pci": 120}]}, timing_epoch_utc="9999-01-01T00:00:00Z"),
                 "towers.timing_epoch_utc", "lies outside 1980-01-06..2100-01-01", id="epoch-year-9999"),
]


@pytest.mark.parametrize(("data", "field", "expected"), BAD_TOWERS)
def test_bad_tower_database_names_the_field(data, field, expected):
    with pytest.raises(ConfigError) as error:
        parse_tower_database(data)
    message = str(error.value)
    assert message.startswith(f"{field}: ") and expected in message, message


@pytest.mark.parametrize(("data", "pairs"), [
    pytest.param(_towers({"pci": 1}, {"pci": 2}, {"pci": 3}), [(1, 2), (1, 3), (2, 3)],
                 id="no-carrier-anywhere-pairs-all"),
    pytest.param(_towers({"pci": 1, "earfcn": 2000}, {"pci": 1, "earfcn": 2300},
                         {"pci": 2, "earfcn": 2000.0}), [(1, 2)],
                 id="same-pci-on-two-carriers"),
    pytest.param(_towers({"pci": 1}, latitude_deg=-90, longitude_deg=180, height_m=0,
                         timing_offset_us=0), [], id="position-edges"),
    pytest.param(_placed({"name": "A", **CAMPUS_A, "cells": [{"pci": 120, "earfcn": 2000}]},
                         {"name": "B", "latitude_deg": 38.99, "longitude_deg": -76.94,
                          "cells": [{"pci": 120, "earfcn": 2300}]},
                         {"name": "C", "latitude_deg": 38.0869, "longitude_deg": -76.9426, "cells": [{"pci": 9}]},
                         timing_epoch_utc="2099-12-31T23:59:59Z"),
                 [], id="pci-on-two-carriers-a-site-99km-away-epoch-2099"),
])
def test_valid_tower_databases_pass(data, pairs):
    assert parse_tower_database(data).cosited_pairs() == pairs


@pytest.mark.parametrize("name", ["campus", "real_lte_1860"])
def test_bundled_tower_databases_pass(name):
    assert load_tower_database(CONFIG / "towers" / f"{name}.yaml").name == name


def test_yaml_exponents_without_a_dot_are_numbers():
    """PyYAML (YAML 1.1) reads 3.84e6 as text; a user writes it that way, and it is a number.
    Quoted text stays text."""
    from deepsync.configio import build_dataclass

    assert build_dataclass(FrontendConfig, {"adc_rate_hz": "3.84e6"}, "frontend").adc_rate_hz == 3.84e6
    assert build_dataclass(FrontendConfig, {"detector_nep_w_per_sqrt_hz": "5e-12"}, "f").detector_nep_w_per_sqrt_hz == 5e-12
    with pytest.raises(ConfigError, match="frontend.adc_rate_hz: expected a number, got 'fast'"):
        build_dataclass(FrontendConfig, {"adc_rate_hz": "fast"}, "frontend")


def test_an_origin_with_a_null_coordinate_names_it():
    data = _towers({"pci": 1})
    data["origin"] = {"latitude_deg": 38.98, "longitude_deg": -76.94, "height_m": None}
    with pytest.raises(ConfigError, match=r"towers.origin.height_m: required .* got null"):
        parse_tower_database(data, "towers")


def _alias_bomb(levels: int) -> str:
    """A YAML file of nested aliases: a few hundred bytes that expand to 9^levels values."""
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, levels + 1)]
    return "\n".join(lines) + f"\nname: *a{levels}\nsites: []\n"


@pytest.mark.parametrize("text, message", [
    (b"1: a\nname: x\nsites: []\n", "t.yaml: key 1 is not a string (quote it)"),
    (b"name: x\nsites:\n  - {name: A, cells: [{pci: 1, 5: 2}]}\n", "t.yaml.sites[0].cells[0]: key 5 is not a string"),
    (_alias_bomb(8).encode(), "expands to more than 1,000,000 values"),
    (b"name: " + b"[" * 70 + b"]" * 70 + b"\n", "t.yaml.name" + "[0]" * 63 + ": nested more than 64 levels deep"),
    (b"name: " + b"[" * 5000 + b"]" * 5000 + b"\n", "t.yaml: nested too deeply to read"),
    (b"name: \xff\xfe\n", "t.yaml: not UTF-8 text (byte 0xff at offset 6)"),
], ids=["int-key", "int-key-in-a-cell", "alias-bomb", "deep", "deeper-than-python", "not-utf8"])
def test_yaml_a_loader_cannot_use_is_refused_in_one_line(tmp_path, text, message):
    """Keys that are not strings, nesting, alias bombs and binary files: one short ConfigError
    naming the file and the place, not a TypeError, a RecursionError or a 250 MB message."""
    path = tmp_path / "t.yaml"
    path.write_bytes(text)
    with pytest.raises(ConfigError) as error:
        load_tower_database(path)
    assert message in str(error.value)
    assert len(str(error.value)) < 500


def test_ordinary_yaml_anchors_still_load(tmp_path):
    """Aliases and merge keys that expand to a few values are what YAML users write: they load."""
    path = tmp_path / "t.yaml"
    path.write_text("name: t\nsites:\n  - &a {name: A, cells: [{pci: 1}]}\n"
                    "  - {<<: *a, name: B, cells: [{pci: 2}]}\n")
    assert [s.name for s in load_tower_database(path).sites] == ["A", "B"]


# -- the timing network's training run (config/timing/*.yaml) ------------------------------------

TRAINING_YAML = CONFIG / "timing" / "timing_net.yaml"


def _run_yaml(tmp_path, section: str, key: str, value: object) -> Path:
    data = yaml.safe_load(TRAINING_YAML.read_text())
    data[section][key] = value
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.mark.parametrize(("section", "key", "value", "message"), [
    pytest.param("training", "steps", 1e308, "steps must be within [1, 1e+07] steps", id="steps-1e308"),
    pytest.param("training", "huber_delta", 0, "huber_delta must be within [0.001, 1000] samples", id="huber-0"),
    pytest.param("training", "huber_delta", -1, "huber_delta must be within", id="huber-negative"),
    pytest.param("training", "threads", -1, "threads must be within [0, 1024] threads", id="threads-negative"),
    pytest.param("training", "learning_rate", 1e308, "learning_rate must be within [1e-09, 1]", id="lr-1e308"),
    pytest.param("training", "batch_size", 100_000_000, "batch_size must be within [1, 65536]", id="batch-1e8"),
    pytest.param("training", "batch_size", 20_000, "a batch would take about", id="batch-beyond-memory"),
    pytest.param("training", "train_shards", 90_000, "in memory, beyond the 16 GiB bound", id="dataset-beyond-memory"),
    pytest.param("training", "seed", 2**64, "seed must be within", id="seed-beyond-int64"),
    pytest.param("training", "workers", 0, "workers must be within [1, 64]", id="workers-0"),
    pytest.param("model", "hidden", [2e6, 32], "hidden must be within [1, 65536]", id="hidden-2e6"),
    pytest.param("model", "hidden", [60000, 32], "weights, more than the 16,000,000 allowed", id="hidden-params"),
    pytest.param("model", "channels", [8, 16, 2048], "channels must be within [1, 1024]", id="channels-2048"),
    pytest.param("dataset", "examples_per_shard", 10**9, "examples_per_shard must be within", id="examples-1e9"),
    pytest.param("dataset", "carrier_hz", 1e15, "carrier_hz must be within", id="carrier-1PHz"),
    pytest.param("dataset", "re_power_dbm", [-110, 1e300], "re_power_dbm must be within", id="power-1e300"),
])
def test_a_training_run_that_cannot_work_is_refused_when_read(tmp_path, section, key, value, message):
    """On main these trained for minutes (steps 1e308: 137 s), then ended in a traceback, or
    allocated 10 GB first (batch_size 1e8): every number of the run now has its range."""
    from deepsync.training.train import load_run_config

    with pytest.raises(ConfigError) as error:
        load_run_config(_run_yaml(tmp_path, section, key, value))
    assert message in str(error.value) and str(tmp_path / "run.yaml") in str(error.value)


def test_the_shipped_training_run_is_inside_every_range():
    from deepsync.training.train import load_run_config

    assert load_run_config(TRAINING_YAML).training.steps == 8000


@pytest.mark.parametrize("module, cls", [
    ("deepsync.frontend.config", "FrontendConfig"),
    ("deepsync.training.train", "TrainConfig"),
    ("deepsync.training.dataset", "DatasetConfig"),
    ("deepsync.timing.model", "TimingNetConfig"),
])
def test_every_field_of_a_front_end_or_training_config_is_a_setting_and_every_number_bounded(module, cls):
    import importlib

    config = getattr(importlib.import_module(module), cls)
    described = settings(config)
    assert set(described) == {field.name for field in dataclasses.fields(config)}
    assert all(setting.help.endswith(".") for setting in described.values())
    numbers = {name for name, setting in described.items() if setting.kind in (int, float) and not setting.choices}
    assert numbers and all(described[name].bounds is not None for name in numbers)
    assert all(low < high for low, high in (described[name].bounds for name in numbers))


@pytest.mark.parametrize("module, cls, field, value, message", [
    ("deepsync.timing.model", "TimingNetConfig", "channels", (8, 16), "channels must be 3 integers, got (8, 16)"),
    ("deepsync.timing.model", "TimingNetConfig", "kernels", (14, 7.5, 5), "kernels must be an integer, got 7.5"),
    ("deepsync.timing.model", "TimingNetConfig", "fusion", "sum", "fusion must be one of cross_attention, "),
    ("deepsync.training.dataset", "DatasetConfig", "channel", "fading", "channel must be one of tdl, clean"),
    ("deepsync.training.dataset", "DatasetConfig", "frame_means", (1, 5), "frame_means must be within [2, 100] "
                                                                          "frames, got 1"),
    ("deepsync.training.train", "TrainConfig", "run_dir", 5, "run_dir must be a string, got 5"),
    ("deepsync.frontend.config", "FrontendConfig", "adc_bits", 12.5, "adc_bits must be an integer, got 12.5"),
    ("deepsync.frontend.config", "FrontendConfig", "video_gain_db", float("inf"), "video_gain_db must be a finite"),
])
def test_a_bad_field_of_a_training_or_front_end_config_is_named(module, cls, field, value, message):
    import importlib

    with pytest.raises(ValueError) as refused:
        getattr(importlib.import_module(module), cls)(**{field: value})
    assert message in str(refused.value)


def test_a_choice_given_by_name_is_held_as_its_kind():
    from deepsync.timing.model import Fusion, Head, TimingNetConfig
    from deepsync.training.dataset import Channel, DatasetConfig

    config = TimingNetConfig(fusion="correlation", head="soft_argmax")
    assert config.fusion is Fusion.CORRELATION and config.head is Head.SOFT_ARGMAX
    assert config == TimingNetConfig(fusion=Fusion.CORRELATION, head=Head.SOFT_ARGMAX)
    assert DatasetConfig(channel="clean").channel is Channel.CLEAN


def test_a_network_config_counts_its_weights_without_building_them():
    """The bound on a network's size is judged before it is built: the count must be the
    network's own, for every fusion and head."""
    torch = pytest.importorskip("torch")
    from deepsync.timing.model import Fusion, Head, TimingNet, TimingNetConfig

    for fusion in Fusion:
        for head in Head:
            for config in (TimingNetConfig(fusion=fusion, head=head),
                           TimingNetConfig(fusion=fusion, head=head, channels=(4, 8, 16), heads=2, pool=3,
                                           window_length=300, template_length=250, hidden=(10, 7))):
                assert config.parameter_count == sum(p.numel() for p in TimingNet(config).parameters())
    del torch


# -- the stages' own configs: every number bounded ------------------------------------------------


@pytest.mark.parametrize("cls, values, message", [
    (SearchConfig, {"refine_lags": 10**9}, "refine_lags must be within [1, 64] samples"),
    (SearchConfig, {"max_examined": 0}, "max_examined must be within [1, 1024] peaks"),
    (SyncConfig, {"confirm_tolerance": float("nan")}, "confirm_tolerance must be a finite number, got nan"),
    (SyncConfig, {"search_every": 10**30}, "search_every must be within [1, 100000] stacks"),
    (SyncConfig, {"search_every": 10**400}, "search_every must be within [1, 100000] stacks"),  # past a float
    (StackConfig, {"clip_fraction": 2.0}, "clip_fraction must be within [0, 1], got 2.0"),
    (TimingConfig, {"weak_std_samples": 1e300}, "weak_std_samples must be within (0, 1e+06] samples"),
    (TimingConfig, {"min_snr_db": -100.0}, "min_snr_db must be within [-60, 60] dB"),
], ids=["refine-lags-1e9", "max-examined-0", "confirm-tolerance-nan", "search-every-1e30", "search-every-1e400",
        "clip-fraction-2",
        "weak-std-1e300", "min-snr-minus-100"])
def test_a_stage_config_number_outside_its_range_names_it(cls, values, message):
    """On main these were taken (a billion lags sized the search's arrays; NaN compared false)."""
    with pytest.raises(ValueError, match=re.escape(message)):
        cls(**values)


def test_a_huge_value_is_quoted_short_in_the_error(tmp_path):
    """Found by the fuzzing pass: a 10,000-character value was quoted whole in the one-line error."""
    data = _towers({"pci": 1}, latitude_deg="x" * 10_000, longitude_deg=0)
    with pytest.raises(ConfigError) as error:
        parse_tower_database(data)
    assert "towers.sites[0].latitude_deg: expected a number in [-90, 90], got 'xxxxxx" in str(error.value)
    assert len(str(error.value)) < 200
    with pytest.raises(ConfigError) as error:
        parse_scenario(_scenario((("receiver", "position", "longitude_deg"), "y" * 10_000)))
    assert len(str(error.value)) < 200
