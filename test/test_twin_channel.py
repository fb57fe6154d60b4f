"""The statistical channel: geometry, tap structure, fading, Doppler and determinism."""

import copy
import dataclasses

import numpy as np
import pytest
from pyproj import Geod

from deepsync.frontend.channel import ChannelProvider, Paths
from deepsync.twin import build_twin
from deepsync.twin.propagation import path_loss_db
from deepsync.types import FRAME_SECONDS, SPEED_OF_LIGHT_M_S
from deepsync.twin.scenario import parse_scenario
from deepsync.twin.tdl import TDL_PROFILES

GEOD = Geod(ellps="WGS84")
SITE = (38.9869, -76.9426)
SITE_HEIGHT, RX_HEIGHT, TILT = 30.0, 1.5, 6.0


def _offset(bearing_deg, distance_m, origin=SITE):
    lon, lat, _ = GEOD.fwd(origin[1], origin[0], bearing_deg, distance_m)
    return {"latitude_deg": lat, "longitude_deg": lon}


def _scenario(seed=7, los="auto", delay_spread_ns=None, route=None, bearing=30.0,
              distance=300.0, extra_sites=(), **channel):
    """One two-sector site at the origin, the receiver ``distance`` m away at ``bearing``."""
    cell = {"earfcn": 2000, "bandwidth_mhz": 10, "eirp_dbm": 60.0, "downtilt_deg": TILT}
    receiver = {"height_m": RX_HEIGHT}
    if route is None:
        receiver["position"] = _offset(bearing, distance)
    else:
        receiver["route"] = route
    data = {
        "name": "test",
        "seed": seed,
        "origin": {"latitude_deg": SITE[0], "longitude_deg": SITE[1], "height_m": 10.0},
        "environment": {"model": "UMa", "los": los},
        "channel": {"delay_spread_ns": delay_spread_ns or "auto", **channel},
        "sites": [{"name": "S", "latitude_deg": SITE[0], "longitude_deg": SITE[1],
                   "height_m": SITE_HEIGHT,
                   "cells": [{"pci": 0, "azimuth_deg": 30.0, **cell},
                             {"pci": 1, "azimuth_deg": 150.0, **cell}]},
                  *extra_sites],
        "receiver": receiver,
    }
    return parse_scenario(copy.deepcopy(data))


def _expected_scale_db(twin, index, t):
    """-(PL + SF - G) in dB, from the geometry, outside the channel's own code path."""
    channel = twin.channel
    site = twin.site(twin.emitters[index].site)
    offset = twin.receiver_enu(t) - site.position_enu
    d3d, d2d = np.linalg.norm(offset), np.hypot(offset[0], offset[1])
    link = channel.link_parameters(index)
    loss = path_loss_db("UMa", link.los, d2d, d3d, SITE_HEIGHT, RX_HEIGHT,
                        twin.emitters[index].carrier_hz)
    zenith = np.degrees(np.arctan2(d2d, offset[2]))
    bearing = np.degrees(np.arctan2(offset[0], offset[1]))
    azimuth = twin.cells[index].azimuth_deg
    phi = (bearing - azimuth + 180.0) % 360.0 - 180.0
    vertical = -min(12 * ((zenith - 90.0 - TILT) / 10.0) ** 2, 20.0)
    horizontal = -min(12 * (phi / 65.0) ** 2, 30.0)
    gain = -min(-(vertical + horizontal), 30.0)
    return -(loss + link.shadow_fading_db - gain)


def test_is_a_channel_provider():
    twin = build_twin(_scenario())
    channel: ChannelProvider = twin.channel
    assert isinstance(channel.paths(0, 0.0), Paths)


@pytest.mark.parametrize("los", ["los", "nlos"])
def test_first_path_is_the_geometric_delay(los):
    twin = build_twin(_scenario(los=los))
    for index in range(2):
        for t in (0.0, 0.5, 13.0):
            paths = twin.channel.paths(index, t)
            geometric = twin.geometric_delay_s(index, t)
            assert paths.first_delay_s == pytest.approx(geometric, abs=1e-15)
            assert paths.delays_s[0] == paths.first_delay_s
            assert np.all(paths.delays_s >= geometric)


def test_a_receiver_at_the_antenna_itself_has_paths():
    """Zero distance (a receiver at the antenna's own position and height) is no direction to
    move along: the specular path's Doppler is 0, not a division by zero."""
    scenario = _scenario(los="los", distance=0.0)
    twin = build_twin(dataclasses.replace(scenario, receiver=dataclasses.replace(scenario.receiver,
                                                                                  height_m=SITE_HEIGHT)))
    paths = twin.channel.paths(0, 0.0)
    assert paths.first_delay_s == pytest.approx(0.0, abs=1e-12)
    assert np.all(np.isfinite(paths.gains)) and np.all(np.isfinite(paths.doppler_hz))


def test_geometric_delay_is_the_3d_distance():
    twin = build_twin(_scenario(distance=300.0))
    # 300 m on the ground, antenna 28.5 m above the receiver
    assert twin.geometric_delay_s(0, 0.0) * SPEED_OF_LIGHT_M_S == pytest.approx(
        np.hypot(300.0, SITE_HEIGHT - RX_HEIGHT), abs=0.01)


def test_tap_structure_and_powers_los():
    twin = build_twin(_scenario(los="los", delay_spread_ns=100.0))
    paths = twin.channel.paths(0, 0.0)
    profile = TDL_PROFILES["TDL-D"]
    scattered, specular = profile.normalized_powers()
    assert len(paths.delays_s) == 1 + 16 * len(profile.delays)
    excess = paths.delays_s - twin.geometric_delay_s(0, 0.0)
    np.testing.assert_allclose(excess[1:], np.repeat(np.asarray(profile.delays) * 100e-9, 16),
                               atol=1e-15)
    scale = 10.0 ** (_expected_scale_db(twin, 0, 0.0) / 10.0)
    power = np.abs(paths.gains) ** 2
    assert power[0] == pytest.approx(scale * specular, rel=1e-9)
    np.testing.assert_allclose(power[1:].reshape(-1, 16).sum(axis=1), scale * scattered,
                               rtol=1e-9)
    # the specular path carries the carrier phase of the true distance (on top of the sector's
    # fixed transmit-chain phase, the same at any time)
    carrier = twin.emitters[0].carrier_hz

    def chain_phase(t):
        d = twin.geometric_delay_s(0, t) * SPEED_OF_LIGHT_M_S
        return np.angle(twin.channel.paths(0, t).gains[0] * np.exp(2j * np.pi * carrier * d / SPEED_OF_LIGHT_M_S))

    assert chain_phase(0.0) == pytest.approx(chain_phase(0.5), abs=1e-6)
    link = twin.channel.link_parameters(0)
    assert (link.los, link.profile) == (True, "TDL-D")
    assert link.delay_spread_s == pytest.approx(100e-9)


def test_tap_structure_nlos():
    twin = build_twin(_scenario(los="nlos", profile_nlos="TDL-C"))
    paths = twin.channel.paths(0, 0.0)
    assert len(paths.delays_s) == 16 * 24
    link = twin.channel.link_parameters(0)
    assert not link.los and link.profile == "TDL-C"
    # delay spread drawn from the UMa NLOS log-normal: within +-4 sigma of the median 364 ns
    assert 10 ** (-6.4387 - 4 * 0.39) < link.delay_spread_s < 10 ** (-6.4387 + 4 * 0.39)
    # shadowing is part of the path gain; with it switched off the gain is the path loss alone
    quiet = build_twin(_scenario(los="nlos", shadow_fading=False))
    assert quiet.channel.link_parameters(0).shadow_fading_db == 0.0


def test_los_state_is_drawn_with_the_los_probability():
    # below 18 m the LOS probability is 1; at 2 km it is ~1 %: count over seeds.
    assert all(build_twin(_scenario(seed=s, distance=15.0)).channel.link_parameters(0).los
               for s in range(20))
    los = [build_twin(_scenario(seed=s, distance=2000.0)).channel.link_parameters(0).los
           for s in range(100)]
    assert sum(los) < 10


def test_sectors_share_delays_and_fading_but_not_antenna_gain():
    twin = build_twin(_scenario(bearing=30.0))  # boresight of sector 0, 120 deg off sector 1
    phases = []
    for t in (0.0, 0.77):
        a, b = twin.channel.paths(0, t), twin.channel.paths(1, t)
        np.testing.assert_array_equal(a.delays_s, b.delays_s)
        np.testing.assert_array_equal(a.doppler_hz, b.doppler_hz)
        ratio = a.gains / b.gains
        # one fixed phase between the sectors' transmit chains, the same on every path and time
        np.testing.assert_allclose(np.angle(ratio), np.angle(ratio[0]), atol=1e-9)
        phases.append(np.angle(ratio[0]))
        # sector 1 is 120 deg off: horizontal attenuation capped at the 30 dB front-back ratio
        # and the total at 30 dB; sector 0 only loses its vertical attenuation.
        expected_db = _expected_scale_db(twin, 0, t) - _expected_scale_db(twin, 1, t)
        assert expected_db > 25.0
        np.testing.assert_allclose(20 * np.log10(np.abs(ratio)), expected_db, atol=1e-9)
    assert phases[0] == pytest.approx(phases[1], abs=1e-9) and abs(phases[0]) > 1e-3


def test_determinism_and_seed_dependence():
    a = build_twin(_scenario(seed=11)).channel.paths(0, 1.25)
    b = build_twin(_scenario(seed=11)).channel.paths(0, 1.25)
    np.testing.assert_array_equal(a.gains, b.gains)
    np.testing.assert_array_equal(a.delays_s, b.delays_s)
    np.testing.assert_array_equal(a.doppler_hz, b.doppler_hz)
    c = build_twin(_scenario(seed=12)).channel.paths(0, 1.25)
    assert not np.array_equal(a.gains, c.gains)


def test_site_draws_do_not_depend_on_other_sites():
    other = {"name": "T", "latitude_deg": 38.99, "longitude_deg": -76.94, "height_m": 25.0,
             "cells": [{"pci": 7, "earfcn": 2000, "bandwidth_mhz": 10, "eirp_dbm": 60.0,
                        "azimuth_deg": 0.0, "downtilt_deg": 4.0}]}
    alone = build_twin(_scenario(seed=5))
    together = build_twin(_scenario(seed=5, extra_sites=[other]))
    np.testing.assert_array_equal(alone.channel.paths(0, 2.0).gains,
                                  together.channel.paths(0, 2.0).gains)
    assert alone.channel.link_parameters(1) == together.channel.link_parameters(1)


def _walk_twin(**kwargs):
    # walk from 300 m north-east of the site towards it and past, then turn east
    start = _offset(30.0, 300.0)
    corner = _offset(210.0, 100.0)
    end = _offset(90.0, 100.0, (corner["latitude_deg"], corner["longitude_deg"]))
    route = {"speed_mps": 1.4, "waypoints": [start, corner, end]}
    return build_twin(_scenario(route=route, **kwargs))


def test_moving_receiver_delay_and_doppler_follow_the_radial_speed():
    twin = _walk_twin(los="los", environment_doppler_hz=0.5)
    carrier = twin.emitters[0].carrier_hz
    site = twin.site("S").position_enu
    for t in (10.0, 150.0, 300.0):
        offset = twin.receiver_enu(t) - site
        radial_speed = np.dot(twin.receiver.velocity_enu(t), offset) / np.linalg.norm(offset)
        h = 1e-3
        rate = (twin.geometric_delay_s(0, t + h) - twin.geometric_delay_s(0, t - h)) / (2 * h)
        assert rate == pytest.approx(radial_speed / SPEED_OF_LIGHT_M_S, rel=1e-6, abs=1e-14)
        paths = twin.channel.paths(0, t)
        assert paths.doppler_hz[0] == pytest.approx(-radial_speed * carrier / SPEED_OF_LIGHT_M_S)
    # approaching the site: positive Doppler, the delay shrinks at ~1.4 m/s / c
    assert twin.channel.paths(0, 10.0).doppler_hz[0] == pytest.approx(
        1.4 * carrier / SPEED_OF_LIGHT_M_S, rel=0.01)


def test_gains_rotate_at_their_reported_doppler():
    twin = _walk_twin(los="los")
    t, dt = 20.0, 1e-3
    now, later = twin.channel.paths(0, t), twin.channel.paths(0, t + dt)
    rotation = np.angle(later.gains / now.gains)
    np.testing.assert_allclose(rotation, 2 * np.pi * now.doppler_hz * dt, atol=1e-6)


def test_doppler_spread_of_the_scattered_paths():
    twin = _walk_twin(los="nlos", environment_doppler_hz=1.0)
    wavelength = SPEED_OF_LIGHT_M_S / twin.emitters[0].carrier_hz
    f_max = 1.4 / wavelength + 1.0
    assert twin.channel.link_parameters(0).max_doppler_hz == pytest.approx(f_max)
    doppler = twin.channel.paths(0, 3.0).doppler_hz
    assert np.all(np.abs(doppler) <= f_max) and np.max(np.abs(doppler)) > 0.9 * f_max
    static = build_twin(_scenario(los="nlos", environment_doppler_hz=2.0))
    assert np.all(np.abs(static.channel.paths(0, 3.0).doppler_hz) <= 2.0)


def test_fading_has_unit_mean_power_over_seeds():
    ratios = []
    for seed in range(200):
        twin = build_twin(_scenario(seed=seed, los="nlos", shadow_fading=False))
        power = np.sum(np.abs(twin.channel.paths(0, 0.0).gains) ** 2)
        ratios.append(power / 10.0 ** (_expected_scale_db(twin, 0, 0.0) / 10.0))
    # 23 taps of unit mean power each: the sum has a small relative spread
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.05)


def test_paths_is_cheap():
    import time

    twin = build_twin(_scenario(los="los"))
    start = time.perf_counter()
    for k in range(1000):
        twin.channel.paths(k % 2, k * FRAME_SECONDS)
    assert time.perf_counter() - start < 1.0  # ~ tens of microseconds per call


def test_channel_pickles_for_worker_processes():
    import pickle

    twin = _walk_twin(los="los")
    clone = pickle.loads(pickle.dumps(twin.channel))
    np.testing.assert_array_equal(clone.paths(1, 42.0).gains, twin.channel.paths(1, 42.0).gains)


def test_without_spatial_consistency_shadowing_and_delay_spread_keep_their_first_draw():
    twin = _walk_twin(los="nlos")
    spread0 = twin.channel.paths(0, 0.0).delays_s - twin.geometric_delay_s(0, 0.0)
    spread1 = twin.channel.paths(0, 200.0).delays_s - twin.geometric_delay_s(0, 200.0)
    np.testing.assert_allclose(spread1, spread0, rtol=0, atol=1e-15)


def test_spatially_consistent_parameters_start_from_the_same_draws_and_change_along_the_route():
    fixed, moving = _walk_twin(los="nlos"), _walk_twin(los="nlos", spatial_consistency=True)
    assert fixed.channel.link_parameters(0) == moving.channel.link_parameters(0)
    for index in range(2):  # where the route starts, the paths are the very same
        a, b = fixed.channel.paths(index, 0.0), moving.channel.paths(index, 0.0)
        np.testing.assert_allclose(b.delays_s, a.delays_s, rtol=0, atol=1e-15)
        np.testing.assert_allclose(b.gains, a.gains, rtol=1e-12)
    link = moving.channel.link_parameters(0)
    normalised = np.repeat(np.asarray(TDL_PROFILES["TDL-A"].delays), 16)
    spreads, shadows = [], []
    for t in np.arange(0.0, 250.0, 10.0):  # 350 m walked, 7-9 correlation distances
        paths_fixed, paths_moving = fixed.channel.paths(0, t), moving.channel.paths(0, t)
        excess = paths_moving.delays_s - moving.geometric_delay_s(0, t)
        spread = excess[-1] / normalised[-1]  # every tap's delay scaled by one delay spread
        np.testing.assert_allclose(excess, normalised * spread, rtol=1e-9, atol=1e-15)
        spreads.append(spread)
        # the gains differ by the shadowing alone (the same fading, delays aside)
        ratio_db = 20 * np.log10(np.abs(paths_moving.gains) / np.abs(paths_fixed.gains))
        np.testing.assert_allclose(ratio_db, ratio_db[0], atol=1e-9)
        shadows.append(link.shadow_fading_db + ratio_db[0])
    assert spreads[0] == pytest.approx(link.delay_spread_s)
    # UMa NLOS: lgDS sigma 0.39 and SF sigma 6 dB; over 350 m both wander by a good part of that
    assert np.ptp(np.log10(spreads)) > 0.2 and np.ptp(shadows) > 3.0
    # and they change smoothly: within 1.4 m (one second) by far less than their sigma
    near = moving.channel.paths(0, 101.0).delays_s - moving.geometric_delay_s(0, 101.0)
    here = moving.channel.paths(0, 100.0).delays_s - moving.geometric_delay_s(0, 100.0)
    assert abs(np.log10(near[-1] / here[-1])) < 0.1


def test_spatially_consistent_parameters_stay_put_for_a_fixed_receiver():
    fixed = build_twin(_scenario(los="nlos"))
    consistent = build_twin(_scenario(los="nlos", spatial_consistency=True))
    for t in (0.0, 30.0, 300.0):
        a, b = fixed.channel.paths(0, t), consistent.channel.paths(0, t)
        np.testing.assert_allclose(b.delays_s, a.delays_s, rtol=0, atol=1e-15)
        np.testing.assert_allclose(b.gains, a.gains, rtol=1e-12)


def test_correlated_normal_along_has_the_exponential_autocorrelation():
    from deepsync.twin.statistical_channel import ALONG_ROUTE_STEP_M, correlated_normal_along

    rng = np.random.default_rng(3)
    correlation_m = 30.0
    runs = np.array([correlated_normal_along(rng, rng.standard_normal(), 150.0, correlation_m)
                     for _ in range(3000)])
    assert runs.shape == (3000, int(150.0 / ALONG_ROUTE_STEP_M) + 1)
    np.testing.assert_allclose(runs.std(axis=0)[[0, 50, 150]], 1.0, atol=0.05)  # stationary
    for lag_m in (10.0, 30.0, 90.0):
        lag = int(lag_m / ALONG_ROUTE_STEP_M)
        rho = np.corrcoef(runs[:, 20], runs[:, 20 + lag])[0, 1]
        assert rho == pytest.approx(np.exp(-lag_m / correlation_m), abs=0.05)
