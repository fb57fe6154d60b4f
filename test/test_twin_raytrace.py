"""The ray-traced channel (deepsync.twin.raytrace) against geometry worked out by hand, on a
scene made here: one 20 x 30 m block, 15 m tall, on flat ground, from a GeoJSON footprint.
Tracing tests skip without the optional extra (the reason says what to install)."""

import json
import math

import numpy as np
import pytest

from deepsync.configio import ConfigError
from deepsync.geo import LocalFrame
from deepsync.twin import build_twin
from deepsync.twin.raytrace import backend, tracing
from deepsync.twin.scenario import RayTracingSettings, parse_scenario
from deepsync.types import SPEED_OF_LIGHT_M_S

ORIGIN = {"latitude_deg": 48.0, "longitude_deg": 11.0, "height_m": 500.0}
FRAME = LocalFrame(**ORIGIN)
BLOCK = [(0.0, 0.0), (20.0, 0.0), (20.0, 30.0), (0.0, 30.0)]  # east, north (m): the block's footprint
BLOCK_HEIGHT_M = 15.0
TX = np.array([-30.0, 10.0, 10.0])       # west of the block, below its roof
IN_VIEW = np.array([-10.0, 20.0, 1.5])   # between the antenna and the block's west wall
BEHIND = np.array([40.0, 15.0, 1.5])     # east of the block: hidden from the antenna
CARRIER_HZ = 2.115e9
QUICK = tracing.TraceSettings(max_depth=1, diffraction=False, refraction=False, samples_per_source=100_000)

needs_sionna = pytest.mark.skipif(backend.missing() is not None, reason=f"ray tracing: {backend.missing()}")


def _lat_lon(east: float, north: float) -> dict:
    lat, lon, _ = FRAME.enu_to_geodetic(np.array([east, north, 0.0]))
    return {"latitude_deg": float(lat), "longitude_deg": float(lon)}


@pytest.fixture(scope="module")
def footprints(tmp_path_factory):
    ring = [[_lat_lon(*corner)["longitude_deg"], _lat_lon(*corner)["latitude_deg"]] for corner in BLOCK + BLOCK[:1]]
    collection = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"name": "block", "height": f"{BLOCK_HEIGHT_M:g} m"},
         "geometry": {"type": "Polygon", "coordinates": [ring]}}]}
    path = tmp_path_factory.mktemp("city") / "block.geojson"
    path.write_text(json.dumps(collection))
    return path


@pytest.fixture(scope="module")
def scene(footprints, tmp_path_factory):
    if backend.missing():
        pytest.skip(f"ray tracing: {backend.missing()}")
    from deepsync.twin.raytrace.scenes import open_scene

    return open_scene(str(footprints), FRAME, tmp_path_factory.mktemp("cache"))


@pytest.fixture(scope="module")
def traced(scene):
    return tracing.trace_paths(scene, TX, CARRIER_HZ, [IN_VIEW, BEHIND], QUICK)


def _distance(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)))


@needs_sionna
def test_the_line_of_sight_delay_is_the_distance_over_c(traced):
    paths = traced.at(0)
    assert paths["los"].sum() == 1 and paths["los"][0]  # the direct path, and it comes first
    assert paths["delays_s"][0] * SPEED_OF_LIGHT_M_S == pytest.approx(_distance(TX, IN_VIEW), abs=1e-3)
    # free-space amplitude lambda / (4 pi d), carrier phase -2 pi f d / c
    d = _distance(TX, IN_VIEW)
    expected = SPEED_OF_LIGHT_M_S / CARRIER_HZ / (4 * math.pi * d) * np.exp(-2j * np.pi * CARRIER_HZ * d / SPEED_OF_LIGHT_M_S)
    assert abs(paths["gains"][0] - expected) < 1e-3 * abs(expected) * 50  # float32 phase of 100 cycles
    assert paths["arrival_enu"][0] == pytest.approx((TX - IN_VIEW) / d, abs=1e-5)


@needs_sionna
def test_single_reflections_are_at_their_mirror_image_distances(traced):
    paths = traced.at(0)
    reflected = paths["delays_s"][paths["interactions"] == tracing.Interaction.SPECULAR] * SPEED_OF_LIGHT_M_S
    wall_image = TX * [-1, 1, 1]    # the west wall is the plane east = 0
    ground_image = TX * [1, 1, -1]  # the ground is up = 0
    assert sorted(reflected) == pytest.approx(sorted([_distance(wall_image, IN_VIEW), _distance(ground_image, IN_VIEW)]),
                                              abs=1e-3)
    assert len(paths["delays_s"]) == 3  # depth 1: direct, wall, ground; nothing else


@needs_sionna
def test_a_receiver_behind_the_building_has_no_direct_path(scene):
    paths = tracing.trace_paths(scene, TX, CARRIER_HZ, [BEHIND], tracing.TraceSettings(samples_per_source=100_000)).at(0)
    assert len(paths["delays_s"]) > 0 and not paths["los"].any()
    # what reaches it goes through the walls (on the straight line, thin-slab refraction bends
    # no ray) and arrives far weaker than free space would bring it
    assert all(flags & tracing.Interaction.REFRACTION for flags in paths["interactions"])
    d = _distance(TX, BEHIND)
    assert paths["delays_s"][0] * SPEED_OF_LIGHT_M_S == pytest.approx(d, abs=1e-3)
    free_space = SPEED_OF_LIGHT_M_S / CARRIER_HZ / (4 * math.pi * d)
    assert abs(paths["gains"][0]) < free_space / 10


@needs_sionna
def test_round_a_corner_the_first_path_is_diffracted_at_the_edge(scene):
    receiver = np.array([40.0, -10.0, 1.5])  # south-east: the block's south-west edge (0, 0) sees both ends
    settings = tracing.TraceSettings(max_depth=1, refraction=False, samples_per_source=100_000)
    paths = tracing.trace_paths(scene, TX, CARRIER_HZ, [receiver], settings).at(0)
    assert not paths["los"].any()
    heights = np.linspace(0.0, BLOCK_HEIGHT_M, 150_001)  # the shortest way over the vertical edge (Keller's cone)
    via_edge = np.min(np.hypot(np.hypot(*TX[:2]), TX[2] - heights) + np.hypot(np.hypot(*receiver[:2]), receiver[2] - heights))
    assert paths["delays_s"][0] * SPEED_OF_LIGHT_M_S == pytest.approx(via_edge, abs=1e-3)
    assert paths["interactions"][0] == tracing.Interaction.DIFFRACTION


@needs_sionna
def test_the_cache_returns_the_same_paths_and_any_changed_input_misses(scene, tmp_path, monkeypatch):
    traces = []
    real = tracing._trace
    monkeypatch.setattr(tracing, "_trace", lambda *a: traces.append(a) or real(*a))
    first = tracing.trace_paths(scene, TX, CARRIER_HZ, [IN_VIEW], QUICK, tmp_path)
    again = tracing.trace_paths(scene, TX, CARRIER_HZ, [IN_VIEW], QUICK, tmp_path)
    assert len(traces) == 1
    for name in ("valid", "delays_s", "gains", "los", "interactions", "departure_enu", "arrival_enu"):
        assert np.array_equal(getattr(first, name), getattr(again, name)), name
    moved = IN_VIEW + [0.0, 0.01, 0.0]
    tracing.trace_paths(scene, TX, CARRIER_HZ, [moved], QUICK, tmp_path)
    tracing.trace_paths(scene, TX + [0.0, 0.0, 0.01], CARRIER_HZ, [IN_VIEW], QUICK, tmp_path)
    tracing.trace_paths(scene, TX, CARRIER_HZ + 1.0, [IN_VIEW], QUICK, tmp_path)
    tracing.trace_paths(scene, TX, CARRIER_HZ, [IN_VIEW], tracing.TraceSettings(max_depth=2, samples_per_source=100_000), tmp_path)
    assert len(traces) == 5
    # a damaged cache file is traced again and replaced, not an error
    [stored] = [p for p in (tmp_path / "paths").iterdir()
                if p.name == tracing.cache_key(scene, TX, CARRIER_HZ, np.array([IN_VIEW]), QUICK) + ".npz"]
    stored.write_bytes(stored.read_bytes()[:100])
    again = tracing.trace_paths(scene, TX, CARRIER_HZ, [IN_VIEW], QUICK, tmp_path)
    assert len(traces) == 6 and np.array_equal(again.delays_s, first.delays_s)
    assert tracing.TracedPaths.load(stored).delays_s.shape == first.delays_s.shape
    # the positions are stored in the map frame: another frame is another trace
    from deepsync.twin.raytrace.scenes import RayScene

    elsewhere = RayScene(scene.xml_path, scene.frame, LocalFrame(48.0001, 11.0, 500.0), scene.name)
    assert tracing.cache_key(elsewhere, TX, CARRIER_HZ, np.array([IN_VIEW]), QUICK) != \
        tracing.cache_key(scene, TX, CARRIER_HZ, np.array([IN_VIEW]), QUICK)


@needs_sionna
def test_a_building_removed_from_a_mitsuba_scene_no_longer_blocks_and_is_another_trace(scene, tmp_path):
    """Sionna's Scene.edit takes the named object out: the footprint scene's meshes as a user's
    Mitsuba scene (shapes 'buildings' and 'ground', here of one material, which Sionna would merge
    into one object) without its buildings lets the direct path reach the receiver the block hid;
    the cache key changes with the removal."""
    import shutil

    from deepsync.twin.raytrace.scenes import open_scene

    shutil.copytree(scene.xml_path.parent / "meshes", tmp_path / "meshes")
    xml = tmp_path / "user.xml"
    xml.write_text(scene.xml_path.read_text().replace('ref id="mat-medium_dry_ground"', 'ref id="mat-concrete"'))
    assert xml.read_text().count('ref id="mat-concrete"') == 2
    origin = (FRAME.latitude_deg, FRAME.longitude_deg)
    whole = open_scene(str(xml), FRAME, tmp_path, scene_origin=origin)
    bare = open_scene(str(xml), FRAME, tmp_path, scene_origin=origin, remove=["buildings"])
    assert [b.name for b in whole.buildings.buildings] == ["buildings"] and bare.buildings.buildings == ()
    assert bare.digest != whole.digest
    assert tracing.cache_key(bare, TX, CARRIER_HZ, np.array([BEHIND]), QUICK) != \
        tracing.cache_key(whole, TX, CARRIER_HZ, np.array([BEHIND]), QUICK)
    hidden = tracing.trace_paths(whole, TX, CARRIER_HZ, [BEHIND], QUICK, tmp_path).at(0)
    opened = tracing.trace_paths(bare, TX, CARRIER_HZ, [BEHIND], QUICK, tmp_path).at(0)
    assert not hidden["los"].any()
    assert opened["los"][0] and opened["delays_s"][0] * SPEED_OF_LIGHT_M_S == pytest.approx(_distance(TX, BEHIND), abs=1e-3)
    # the whole scene is still whole: the removal edited its own loaded copy
    assert not tracing.trace_paths(whole, TX, CARRIER_HZ, [BEHIND], QUICK).at(0)["los"].any()
    with pytest.raises(ConfigError, match=r"remove_buildings\[1\]: scene .* has no building 'tower'"):
        open_scene(str(xml), FRAME, tmp_path, scene_origin=origin, remove=["buildings", "tower"])


@needs_sionna
def test_a_footprint_removed_by_name_is_left_out_of_the_extruded_scene(tmp_path):
    from deepsync.twin.raytrace.scenes import open_scene

    def feature(name, corners, height):
        ring = [[_lat_lon(*c)["longitude_deg"], _lat_lon(*c)["latitude_deg"]] for c in corners + corners[:1]]
        return {"type": "Feature", "properties": {"name": name, "height": height},
                "geometry": {"type": "Polygon", "coordinates": [ring]}}

    path = tmp_path / "two.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [
        feature("block", BLOCK, BLOCK_HEIGHT_M), feature("shed", [(40, 0), (45, 0), (45, 10), (40, 10)], 6.0)]}))
    whole = open_scene(str(path), FRAME, tmp_path / "cache")
    less = open_scene(str(path), FRAME, tmp_path / "cache", remove=["shed"])
    assert sorted(b.name for b in whole.buildings.buildings) == ["block", "shed"]
    assert [b.name for b in less.buildings.buildings] == ["block"]
    assert less.xml_path != whole.xml_path and less.digest != whole.digest
    with pytest.raises(ConfigError, match="removes every building"):
        open_scene(str(path), FRAME, tmp_path / "cache", remove=["shed", "block"])
    # a scenario names the key in its error
    scenario = _scenario(path, [(-10, -5), (-10, 40)], cache_dir=tmp_path / "cache", remove_buildings=["barn"])
    with pytest.raises(ConfigError, match=r"scenario.channel.remove_buildings\[0\]: scene .* has no building 'barn'"):
        build_twin(scenario)


@needs_sionna
def test_a_cache_that_cannot_be_written_is_a_warning_not_a_lost_trace(scene, tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    with pytest.warns(UserWarning, match="ray-tracing cache: cannot write"):
        traced = tracing.trace_paths(scene, TX, CARRIER_HZ, [IN_VIEW], QUICK, blocked)
    assert traced.at(0)["los"][0]


@needs_sionna
def test_rooftops_and_three_sector_sites_make_a_scenario_site(scene):
    from deepsync.twin.raytrace.sites import rooftops, three_sector_site

    [roof] = rooftops(scene, 3, min_area_m2=100.0)  # the one building
    assert roof.building == "block" and roof.height_m == pytest.approx(BLOCK_HEIGHT_M)
    east, north, up = roof.position_enu
    assert 0 < east < 20 and 0 < north < 30 and up == pytest.approx(BLOCK_HEIGHT_M, abs=0.01)
    assert rooftops(scene, 3, max_height_m=10.0) == []  # too tall a roof is no candidate
    lat, lon, _ = FRAME.enu_to_geodetic(roof.position_enu)
    site = three_sector_site("R", float(lat), float(lon), roof.height_m + 3.0, n_id_1=7, earfcn=300)
    parsed = parse_scenario({"name": "x", "seed": 1, "origin": ORIGIN, "sites": [site],
                             "receiver": {"height_m": 1.5, "position": _lat_lon(-10, 5)}})
    assert [c.pci for c in parsed.sites[0].cells] == [21, 22, 23]
    assert [c.azimuth_deg for c in parsed.sites[0].cells] == [0.0, 120.0, 240.0]


def _scenario(footprints, waypoints, *, cache_dir, loop=False, site_height_m=10.0, **channel):
    site = {"name": "W", **_lat_lon(*TX[:2]), "height_m": site_height_m,
            "cells": [{"pci": 3, "earfcn": 300, "bandwidth_mhz": 10.0, "eirp_dbm": 60.0,
                       "azimuth_deg": 90.0, "downtilt_deg": 0.0}]}
    return parse_scenario({
        "name": "block", "seed": 1, "origin": ORIGIN, "sites": [site],
        "channel": {"model": "raytraced", "scene": str(footprints), "cache_dir": str(cache_dir),
                    "max_depth": 1, "diffraction": False, "refraction": False, "samples_per_source": 100_000,
                    **channel},
        "receiver": {"height_m": 1.5, "route": {"speed_mps": 1.0, "loop": loop,
                                                "waypoints": [_lat_lon(*p) for p in waypoints]}}})


@needs_sionna
@pytest.mark.parametrize(("waypoints", "loop", "named"), [
    ([(-10, -5), (10, 15), (-10, 40)], False, "scenario.receiver.route.waypoints[1]: inside building 'block'"),
    ([(-10, 5), (30, 5)], False, "the leg from waypoint 0 to waypoint 1 passes through building 'block'"),
    ([(-5, -5), (-5, 40), (25, 40)], True, "the leg from waypoint 2 to waypoint 0 passes through building 'block'"),
])
def test_a_route_through_a_building_is_refused_naming_the_point(footprints, tmp_path, waypoints, loop, named):
    with pytest.raises(ConfigError, match=named.replace("[", r"\[").replace("]", r"\]")):
        build_twin(_scenario(footprints, waypoints, cache_dir=tmp_path, loop=loop))


@needs_sionna
def test_an_antenna_inside_a_building_is_refused(footprints, tmp_path):
    scenario = _scenario(footprints, [(-10, -5), (-10, 40)], cache_dir=tmp_path)
    site = scenario.sites[0]
    inside = {"name": "W", **_lat_lon(10.0, 10.0), "height_m": 12.0, "cells": [
        {"pci": 3, "earfcn": 300, "bandwidth_mhz": 10.0, "eirp_dbm": 60.0, "azimuth_deg": 90.0, "downtilt_deg": 0.0}]}
    data = {"name": "block", "seed": 1, "origin": ORIGIN, "sites": [inside],
            "channel": {"model": "raytraced", "scene": scenario.channel.scene, "cache_dir": str(tmp_path)},
            "receiver": {"height_m": 1.5, "position": _lat_lon(-10, 5)}}
    with pytest.raises(ConfigError, match=r"scenario.sites\[0\].height_m: the antenna .* inside building 'block'"):
        build_twin(parse_scenario(data))
    assert site.height_m == 10.0


@needs_sionna
def test_the_twin_moves_paths_with_the_receiver_between_traced_points(footprints, tmp_path):
    # a walk north along the west wall: the direct path stays clear all the way
    twin = build_twin(_scenario(footprints, [(-10, 0), (-10, 30)], cache_dir=tmp_path, route_step_m=2.0))
    channel = twin.channel
    for t in (0.2, 4.9, 7.3, 29.5):  # between traced points (every 2 m at 1 m/s)
        paths = channel.paths(0, t)
        assert channel.los_at(0, t)
        first = int(np.argmin(paths.delays_s))
        # the first-order move keeps the direct path on the true distance, within the second-order
        # term (half a step)^2 / (2 d) (2.3 cm here) and float32's millimetre
        d = twin.geometric_delay_s(0, t) * SPEED_OF_LIGHT_M_S
        moved = np.linalg.norm(twin.receiver_enu(t) - channel.traced(0).receivers_enu[channel.sample_index(t)])
        assert moved <= 1.0 + 1e-9
        assert paths.delays_s[first] * SPEED_OF_LIGHT_M_S == pytest.approx(d, abs=moved**2 / (2 * d) + 1e-3)
        if moved > 0.5:  # and plainly better than holding the sample point's delay
            assert abs(paths.delays_s[first] * SPEED_OF_LIGHT_M_S - d) < 0.1 * moved
        # its Doppler is the rate of its delay, -f d(delay)/dt, up to the turn of the direction
        # between the sample point and here (moved / d rad of the 7 Hz that 1 m/s gives)
        dt = 1e-3
        rate = (twin.geometric_delay_s(0, t + dt) - twin.geometric_delay_s(0, t - dt)) / (2 * dt)
        full = CARRIER_HZ_OF_EARFCN_300 * 1.0 / SPEED_OF_LIGHT_M_S
        assert paths.doppler_hz[first] == pytest.approx(-rate * CARRIER_HZ_OF_EARFCN_300, abs=full * moved / d + 0.01)
        # and the phase moves with it: exp(j 2 pi f_D dt) over a millisecond
        later = channel.paths(0, t + dt)
        turn = np.angle(later.gains[first] / paths.gains[first])
        assert turn == pytest.approx(2 * np.pi * paths.doppler_hz[first] * dt, abs=1e-3)


CARRIER_HZ_OF_EARFCN_300 = 2.14e9  # band 1: 2110 MHz + 0.1 MHz x 300


@needs_sionna
def test_the_sector_pattern_and_chain_phase_weight_the_traced_gains(footprints, tmp_path):
    twin = build_twin(_scenario(footprints, [(-10, 0), (-10, 30)], cache_dir=tmp_path))
    channel, tx = twin.channel, twin.channel._links[0].transmitter
    k = channel.sample_index(3.0)
    traced = channel.traced(0)
    order = traced.path_order(k)
    ratio = channel.paths(0, twin.receiver.duration_s * 0 + 3.0).gains / traced.gains[k, order]
    expected = 10 ** (tx.antenna.gain_db(traced.departure_enu[k, order]) / 20)
    # at a traced point itself the move is nil: only the pattern and one common phase remain
    position_offset = np.linalg.norm(twin.receiver_enu(3.0) - traced.receivers_enu[k])
    assert position_offset < 1e-9
    assert np.abs(ratio) == pytest.approx(expected, rel=1e-9)
    assert np.ptp(np.angle(ratio)) < 1e-9
    # a receiver standing at that point gets the same paths without Doppler
    from deepsync.twin.raytrace.channel import static_paths

    standing = static_paths(traced, k, tx.antenna)
    assert np.array_equal(standing.delays_s, traced.delays_s[k, order]) and not standing.doppler_hz.any()
    turned = channel.paths(0, 3.0).gains / standing.gains  # only the chain phase differs
    assert np.abs(turned) == pytest.approx(1.0, abs=1e-9) and np.ptp(np.angle(turned)) < 1e-9


@pytest.mark.parametrize(("channel", "named"), [
    ({"model": "raytrace", "scene": "munich"}, "scenario.channel.model: unknown value 'raytrace'"),
    ({"model": "raytraced"}, "scenario.channel.scene: required but missing"),
    ({"model": "raytraced", "scene": "atlantis"}, "scenario.channel.scene: 'atlantis' is neither a bundled scene"),
    ({"model": "raytraced", "scene": "munich", "max_depth": 12}, "scenario.channel.max_depth: 12 is outside"),
    ({"model": "raytraced", "scene": "munich", "diffraction": "yes"}, "scenario.channel.diffraction: expected true or false"),
    ({"model": "raytraced", "scene": "munich", "route_step_m": 0}, "scenario.channel.route_step_m: 0.0 is outside"),
    ({"model": "raytraced", "scene": "munich", "profile_los": "TDL-D"}, "scenario.channel: unknown key profile_los"),
    ({"model": "raytraced", "scene": "munich", "scene_origin": {"latitude_deg": 95, "longitude_deg": 0}},
     "scenario.channel.scene_origin.latitude_deg: 95.0 is outside"),
    ({"model": "raytraced", "scene": "munich", "cache_dir": " "}, "scenario.channel.cache_dir: must not be empty"),
    ({"model": "statistical", "scene": "munich"}, "scenario.channel: unknown key scene"),
    ({"model": "raytraced", "scene": "munich", "remove_buildings": "St__Peter-itu_marble"},
     "scenario.channel.remove_buildings: expected a list"),
])
def test_scenario_errors_name_the_channel_field(channel, named):
    data = {"name": "x", "seed": 1, "origin": ORIGIN, "channel": channel,
            "sites": [{"name": "A", **_lat_lon(0, 0), "height_m": 20.0, "cells": [
                {"pci": 1, "earfcn": 300, "bandwidth_mhz": 10.0, "eirp_dbm": 60.0, "azimuth_deg": 0.0,
                 "downtilt_deg": 0.0}]}],
            "receiver": {"height_m": 1.5, "position": _lat_lon(50, 50)}}
    with pytest.raises(ConfigError, match=named.replace("[", r"\[")):
        parse_scenario(data)


def test_a_mitsuba_scene_needs_its_origin_and_a_geojson_scene_parses(tmp_path, footprints):
    xml = tmp_path / "scene.xml"
    xml.write_text("<scene version='2.1.0'/>")
    base = {"name": "x", "seed": 1, "origin": ORIGIN,
            "sites": [{"name": "A", **_lat_lon(0, 0), "height_m": 20.0, "cells": [
                {"pci": 1, "earfcn": 300, "bandwidth_mhz": 10.0, "eirp_dbm": 60.0, "azimuth_deg": 0.0,
                 "downtilt_deg": 0.0}]}],
            "receiver": {"height_m": 1.5, "position": _lat_lon(50, 50)}}
    with pytest.raises(ConfigError, match="scenario.channel.scene: .* needs scene_origin"):
        parse_scenario({**base, "channel": {"model": "raytraced", "scene": str(xml)}})
    parsed = parse_scenario({**base, "channel": {"model": "raytraced", "scene": str(xml),
                                                 "scene_origin": {"latitude_deg": 48, "longitude_deg": 11}}})
    assert parsed.channel.scene_origin.latitude_deg == 48.0
    parsed = parse_scenario({**base, "channel": {"model": "raytraced", "scene": str(footprints), "max_depth": 2}})
    assert isinstance(parsed.channel, RayTracingSettings)
    assert parsed.channel.trace_settings == tracing.TraceSettings(max_depth=2)
    assert parse_scenario({**base}).channel.profile_los == "TDL-D"  # statistical stays the default


def test_footprints_without_a_height_are_refused_naming_the_feature(tmp_path):
    pytest.importorskip("shapely", reason="the optional extra deepsync[raytrace] is not installed")
    from deepsync.twin.raytrace.buildings import read_footprints

    ring = [[11.0, 48.0], [11.0001, 48.0], [11.0001, 48.0001], [11.0, 48.0]]
    path = tmp_path / "f.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"building:levels": "4"}, "geometry": {"type": "Polygon", "coordinates": [ring]}},
        {"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [ring]}}]}))
    with pytest.raises(ConfigError, match=r"features\[1\]: has neither 'height' nor 'building:levels'"):
        read_footprints(path, FRAME)
    heights = [b.height_m for b in read_footprints(path, FRAME, default_height_m=7.0)]
    assert heights == [12.0, 7.0]  # 4 levels of 3 m, then the default


@needs_sionna
def test_our_interaction_flags_are_sionnas():
    constants = backend.sionna_rt().constants.InteractionType
    for flag in tracing.Interaction:
        assert int(flag) == getattr(constants, flag.name)


def test_the_munich_example_scenario_parses_as_a_ray_traced_walk():
    from pathlib import Path

    from deepsync.twin import load_scenario

    scenario = load_scenario(Path(__file__).resolve().parents[1] / "config" / "scenarios" / "munich_walk.yaml")
    assert isinstance(scenario.channel, RayTracingSettings) and scenario.channel.scene == "munich"
    assert len(scenario.sites) == 6 and all(len(site.cells) == 3 for site in scenario.sites)
    assert scenario.channel.trace_settings == tracing.TraceSettings()


@needs_sionna
def test_the_munich_drive_is_a_drive_among_the_walks_sites_that_stays_in_the_streets():
    from pathlib import Path

    from deepsync.twin import load_scenario
    from deepsync.twin.raytrace.build import scenario_scene
    from deepsync.twin.raytrace.channel import route_samples
    from deepsync.twin.raytrace.sites import check_route
    from deepsync.twin.world import receiver_trajectory, twin_cells

    scenarios = Path(__file__).resolve().parents[1] / "config" / "scenarios"
    walk, drive = (load_scenario(scenarios / f"munich_{name}.yaml") for name in ("walk", "drive"))
    assert drive.sites == walk.sites and drive.origin == walk.origin  # one tower database serves both
    cells = twin_cells(drive)
    route = receiver_trajectory(drive.receiver, cells.frame)
    assert 12.0 <= route.speed_mps <= 15.0 and route.duration_s >= 60.0
    assert len(route_samples(route, drive.channel.route_step_m)[1]) >= 200
    check_route(scenario_scene(drive.channel, cells.frame), route.waypoints_enu, "munich_drive")  # raises inside a building


@needs_sionna
def test_a_static_receivers_street_grid_is_a_disc_less_the_building(scene):
    from deepsync.twin.raytrace.sites import street_grid

    centre = np.array([10.0, 15.0, 1.5])  # the block's middle
    nodes = street_grid(scene, [centre], 30.0, 1.5, 5.0)
    # the lattice (10 + 5i, 15 + 5j) with i^2 + j^2 <= 36 (Gauss's circle: 113 points), less the
    # 3 x 5 strictly inside the block (a point on a wall is outside)
    assert len(nodes) == 113 - 15
    assert np.all(np.hypot(*(nodes[:, :2] - centre[:2]).T) <= 30.0 + 1e-6)
    inside = (nodes[:, 0] > 0) & (nodes[:, 0] < 20) & (nodes[:, 1] > 0) & (nodes[:, 1] < 30)
    assert not inside.any() and np.all(nodes[:, 2] == 1.5)
    for bad in ({"step_m": 0.0}, {"margin_m": -1.0}):
        with pytest.raises(ValueError, match="positive step, a margin >= 0"):
            street_grid(scene, [centre], **{"margin_m": 5.0, "height_m": 1.5, "step_m": 1.0, **bad})


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    along = np.clip((points - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return np.linalg.norm(points - (a + along[:, None] * (b - a)), axis=1)


@needs_sionna
def test_a_traced_maps_nodes_follow_an_l_shaped_route_not_its_box(footprints, tmp_path):
    from deepsync.eval.traced_map import TracedMapConfig, map_nodes
    from deepsync.twin.raytrace.build import scenario_scene
    from deepsync.twin.world import twin_cells

    corners = [(-10.0, -5.0), (-10.0, 40.0), (35.0, 40.0)]  # north past the block's west wall, then east
    scenario = _scenario(footprints, corners, cache_dir=tmp_path)
    cells = twin_cells(scenario)
    nodes = map_nodes(scenario, cells, scenario_scene(scenario.channel, cells.frame),
                      TracedMapConfig(margin_m=8.0, node_step_m=2.0))[:, :2]
    legs = [(np.array(a), np.array(b)) for a, b in zip(corners, corners[1:])]
    nearest = np.min([_segment_distance(nodes, a, b) for a, b in legs], axis=0)
    assert np.all(nearest <= 8.0 + 1e-3)  # the waypoints went through latitude and longitude
    assert np.any(nodes[:, 1] < 20.0) and np.any(nodes[:, 0] > 20.0)  # along the first leg and the second
    # the box's south-east, inside the L's bend, is more than 8 m from both legs
    assert not np.any((nodes[:, 0] > -2.0 + 1e-3) & (nodes[:, 1] < 32.0 - 1e-3))


@needs_sionna
def test_a_traced_map_reads_the_straight_line_where_the_site_is_in_view(footprints, tmp_path):
    """The whole chain at every street node, one site: where the antenna sees the node the lock
    is on the direct path (bias near 0, well inside a sample's 156 m); the map holds it."""
    import yaml

    from deepsync.eval.traced_map import TracedMapConfig, traced_bias_map
    from deepsync.fusion.bias_map import load_bias_map

    scenario = _scenario(footprints, [(-10, -5), (-10, 40)], cache_dir=tmp_path / "cache")
    site = scenario.sites[0]
    path = tmp_path / "block.yaml"
    path.write_text(yaml.safe_dump({
        "name": "block", "seed": 1, "origin": ORIGIN,
        "sites": [{"name": "W", "latitude_deg": site.latitude_deg, "longitude_deg": site.longitude_deg,
                   "height_m": site.height_m, "cells": [{"pci": 3, "earfcn": 300, "bandwidth_mhz": 10.0,
                                                         "eirp_dbm": 60.0, "azimuth_deg": 90.0,
                                                         "downtilt_deg": 0.0, "load": 0.3}]}],
        "channel": {"model": "raytraced", "scene": str(footprints), "cache_dir": str(tmp_path / "cache"),
                    "max_depth": 1, "diffraction": False, "refraction": False, "samples_per_source": 100_000},
        "receiver": {"height_m": 1.5, "route": {"speed_mps": 1.0, "waypoints": [_lat_lon(-10, -5),
                                                                                 _lat_lon(-10, 40)]}}}))
    config = TracedMapConfig(margin_m=10.0, node_step_m=15.0, stack_frames=4, hop_frames=2, stacks=4)
    out = tmp_path / "map.npz"
    traced = traced_bias_map(path, out, config, progress=False)
    assert traced.path == out and not (tmp_path / "map.npz.parts").exists()  # the jobs' parts go
    # x -20 (10 m off the route): y 0, 15, 30; x -5: y 0 ... 45 (y -15 lies 11 m from its start)
    assert traced.nodes == 7  # all in view of the antenna
    assert set(traced.heard) == {"W"} and traced.heard["W"] >= 5  # 4-frame stacks may miss a node
    bias_map = load_bias_map(out)
    assert set(bias_map.sites) == {"W"}
    for east, north in ((-20.0, 0.0), (-5.0, 30.0)):
        bias, _ = bias_map.at("W", east, north)
        assert abs(bias) < 15.0


def test_a_traced_map_refuses_a_statistical_scenario_and_bad_settings(tmp_path):
    from pathlib import Path

    from deepsync.eval.traced_map import TracedMapConfig, traced_bias_map

    campus = Path(__file__).resolve().parents[1] / "config" / "scenarios" / "campus.yaml"
    with pytest.raises(ConfigError, match="channel model is statistical"):
        traced_bias_map(campus, tmp_path / "map.npz")
    assert not list(tmp_path.iterdir())
    with pytest.raises(ValueError, match="node_step_m"):
        TracedMapConfig(node_step_m=0.0)


@needs_sionna
def test_a_scenarios_building_outlines_come_in_the_map_frame(footprints, tmp_path):
    from deepsync.twin.raytrace.build import scenario_footprints

    scenario = _scenario(footprints, [(-10, -5), (-10, 40)], cache_dir=tmp_path)
    (ring,) = scenario_footprints(scenario.channel, FRAME)
    assert ring.shape[1] == 2
    assert np.allclose(ring.min(axis=0), [0.0, 0.0], atol=0.05) and np.allclose(ring.max(axis=0), [20.0, 30.0], atol=0.05)
