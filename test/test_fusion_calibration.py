"""Site clock calibration: synthetic recordings at known positions -> site offsets and drifts.

Arrivals are made from exact geometry and true site clocks (the database's timing plus a
known error) and read through ``Anchors`` as the pipeline reads them, so a wrong sign between
the database, the anchors and the calibration shows up as microseconds, not as a tolerance.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from deepsync.configio import load_yaml
from deepsync.frontend.templates import sync_code_offset_seconds
from deepsync.fusion.anchors import FRAME_RANGE_M, Anchors, frame_reference_ns
from deepsync.fusion.calibration import (
    CalibrationConfig,
    CalibrationObservation,
    calibrate_sites,
    calibrated_database,
    calibration_lifetime_s,
)
from deepsync.geo import LocalFrame
from deepsync.towers import load_tower_database, parse_tower_database, tower_database_to_dict, write_tower_database
from deepsync.types import SPEED_OF_LIGHT_M_S, CellTiming, StackArrivals

C = SPEED_OF_LIGHT_M_S
RATE = 1.92e6
SAMPLE_M = C / RATE  # 156 m
ORIGIN = {"latitude_deg": 38.9869, "longitude_deg": -76.9426, "height_m": 10.0}
FRAME = LocalFrame(ORIGIN["latitude_deg"], ORIGIN["longitude_deg"], ORIGIN["height_m"])
EPOCH_NS = 1_767_225_600 * 10**9  # 2026-01-01T00:00:00Z
REFERENCE_NS = frame_reference_ns(EPOCH_NS + 3600 * 10**9 + 123_456_789)  # an hour on: database drifts matter
# six sites around the route (east m, north m, antenna height m, database offset us, database drift ns/s)
SITES = [(-900, 1200, 30, 3120.4, -12.0), (1500, 300, 25, 7420.85, 7.5), (400, -1300, 28, 512.3, 0.0),
         (-1600, -500, 35, 9999.2, 3.0), (800, 1700, 22, 15.0, 0.0), (2100, -1400, 40, 4000.0, -20.0)]
# the true clocks minus the database's: offsets (us) and drifts (ns/s), as an uncalibrated network has them
OFFSET_ERRORS_US = np.array([2.1, -3.4, 0.7, 4.2, -1.5, 0.0])
DRIFT_ERRORS_NS = np.array([12.0, -5.0, 20.0, -17.0, 8.0, -9.5])


def database_dict() -> dict:
    sites = []
    for k, (east, north, height, offset, drift) in enumerate(SITES):
        lat, lon, _ = FRAME.enu_to_geodetic(np.array([east, north, 0.0]))
        sites.append({"name": f"S{k}", "latitude_deg": float(lat), "longitude_deg": float(lon), "height_m": height,
                      "timing_offset_us": offset, "timing_drift_ns_per_s": drift,
                      "cells": [{"pci": 3 * k + 30, "earfcn": 2000}, {"pci": 3 * k + 31, "earfcn": 2000}]})
    sites.append({"name": "far", "cells": [{"pci": 400, "earfcn": 2000}]})  # on the list, never heard
    return {"name": "test", "origin": ORIGIN, "timing_epoch_utc": "2026-01-01T00:00:00Z", "sites": sites}


TOWERS = parse_tower_database(database_dict())
ANCHORS = Anchors(TOWERS)


def route(t: float) -> np.ndarray:
    """The receiver: a 300 m circle at 8 m/s, antenna 1.5 m above the ground."""
    angle = 8.0 * t / 300.0
    return np.array([300.0 * math.cos(angle), 300.0 * math.sin(angle), 1.5])


def recording(seed: int, *, seconds: float = 60.0, noise_m: float = 0.1 * SAMPLE_M, clock_ppm: float = 15.0,
              clock_ppm_per_s: float = 0.05, outliers: float = 0.0, heard: tuple[int, ...] = (1, 2),
              sites: range = range(6)) -> list[CalibrationObservation]:
    """A recording centred on REFERENCE_NS: one stack every 100 ms hearing 1-2 random sites, each
    arrival read on a receiver clock ``clock_ppm`` fast (drifting ``clock_ppm_per_s``) with
    Gaussian timing noise; a fraction ``outliers`` of arrivals comes 100-500 m late (NLOS)."""
    rng = np.random.default_rng(seed)
    bias0_s = rng.uniform(0, 10e-3)

    def receiver_clock(t: float) -> float:  # receiver time minus true time (s)
        return bias0_s + 1e-6 * (clock_ppm * t + 0.5 * clock_ppm_per_s * t * t)

    observations = []
    for k, t_stack in enumerate(np.arange(-seconds / 2, seconds / 2, 0.1)):
        stamp_ns = REFERENCE_NS + round((t_stack + receiver_clock(t_stack)) * 1e9)
        first_index = 10_000_000 + 192_000 * k
        cells, truths = [], {}
        for s in rng.choice(list(sites), rng.choice(heard), replace=False):
            anchor = ANCHORS.anchors[f"S{s}"]
            since_epoch = (REFERENCE_NS - EPOCH_NS) * 1e-9 + t_stack
            timing = anchor.timing_s(since_epoch) + 1e-6 * OFFSET_ERRORS_US[s] + 1e-9 * DRIFT_ERRORS_NS[s] * t_stack
            truth = route(t_stack)
            flight = np.linalg.norm(truth - anchor.position_enu) / C
            arrival = t_stack + (timing + sync_code_offset_seconds() + flight - t_stack) % 10e-3
            error_m = rng.normal(0, noise_m) + (rng.uniform(100, 500) if rng.random() < outliers else 0.0)
            receiver_s = arrival + receiver_clock(arrival) + error_m / C
            toa = first_index + (receiver_s - (stamp_ns - REFERENCE_NS) * 1e-9) * RATE
            cells.append(CellTiming(3 * s + 30, toa, noise_m / SAMPLE_M, 5.0, "test", earfcn=2000, amplitude=1e-3))
            truths[f"S{s}"] = route(arrival)
        site_arrivals, problems = ANCHORS.site_arrivals(StackArrivals(stamp_ns, first_index, RATE, tuple(cells)),
                                                        REFERENCE_NS)
        assert not problems
        observations += [CalibrationObservation(a, truths[a.site]) for a in site_arrivals]
    return observations


def relative_truth(result, name: str) -> tuple[float, float]:
    """The true offset (s) and drift (s/s) corrections of ``name`` relative to the reference site."""
    s, r = int(name[1:]), int(result.reference_site[1:])
    return 1e-6 * (OFFSET_ERRORS_US[s] - OFFSET_ERRORS_US[r]), 1e-9 * (DRIFT_ERRORS_NS[s] - DRIFT_ERRORS_NS[r])


def normalised_errors(result) -> tuple[list[float], list[float]]:
    offsets, drifts = [], []
    for site in result.sites:
        if site.site == result.reference_site:
            continue
        offset, drift = relative_truth(result, site.site)
        offsets.append((site.offset_correction_s - offset) / site.offset_std_s)
        drifts.append((site.drift_correction - drift) / site.drift_std)
    return offsets, drifts


# --------------------------------------------------------------------------- the estimate


def test_calibration_recovers_relative_offsets_and_drifts_within_their_sigmas():
    result = calibrate_sites(recording(1))
    print(f"\nresidual RMS before {result.residual_rms_before_m:.0f} m, after {result.residual_rms_after_m:.1f} m "
          f"(noise {0.1 * SAMPLE_M:.1f} m), sigma scale {result.sigma_scale:.2f}, reference {result.reference_site}")
    for site in result.sites:
        print(f"  {site.site}: offset {site.offset_correction_s * 1e9:8.1f} +- {site.offset_std_s * 1e9:4.1f} ns, "
              f"drift {site.drift_correction * 1e9:7.2f} +- {site.drift_std * 1e9:4.2f} ns/s, "
              f"{site.n_arrivals} arrivals, residual {site.residual_rms_m:.1f} m")
    assert result.residual_rms_before_m > 300.0  # microseconds of offset error, minutes of drift
    assert result.residual_rms_after_m == pytest.approx(0.1 * SAMPLE_M, rel=0.15)
    assert result.sigma_scale == pytest.approx(1.0, rel=0.15)
    assert sorted(s.site for s in result.sites) == [f"S{k}" for k in range(6)]
    assert sum(s.n_arrivals for s in result.sites) == pytest.approx(900, rel=0.1)
    reference = result.site(result.reference_site)
    assert reference.n_arrivals == max(s.n_arrivals for s in result.sites)
    assert (reference.offset_correction_s, reference.offset_std_s, reference.drift_std) == (0.0, 0.0, 0.0)
    offsets, drifts = normalised_errors(result)
    assert np.all(np.abs(offsets) < 3) and np.all(np.abs(drifts) < 3)
    for site in result.sites:
        if site.site != result.reference_site:
            assert 1e-9 < site.offset_std_s < 30e-9 and 0.05e-9 < site.drift_std < 2e-9
    for t in (-25.0, 0.0, 25.0):  # the receiver clock fitted: 15 ppm + 0.05 ppm/s
        assert result.clock.rate(t) == pytest.approx(15e-6 + 0.05e-6 * t, abs=1e-8)


def test_sigmas_are_honest_over_many_recordings():
    offsets, drifts = [], []
    for seed in range(50):
        o, d = normalised_errors(calibrate_sites(recording(100 + seed, seconds=30.0)))
        offsets += o
        drifts += d
    rms_offset, rms_drift = float(np.sqrt(np.mean(np.square(offsets)))), float(np.sqrt(np.mean(np.square(drifts))))
    print(f"\nnormalised error RMS over {len(offsets)} site estimates: offset {rms_offset:.2f}, drift {rms_drift:.2f}")
    assert 0.7 <= rms_offset <= 1.4 and 0.7 <= rms_drift <= 1.4
    assert np.max(np.abs(offsets)) < 4.5 and np.max(np.abs(drifts)) < 4.5


def test_nlos_outliers_pull_a_bounded_amount():
    result = calibrate_sites(recording(7, outliers=0.05))
    offsets, drifts = normalised_errors(result)
    print(f"\n5 % NLOS arrivals: normalised offset errors {np.round(offsets, 2)}, drift {np.round(drifts, 2)}, "
          f"residual RMS {result.residual_rms_after_m:.0f} m")
    assert np.all(np.abs(offsets) < 3) and np.all(np.abs(drifts) < 3)


def test_one_polynomial_for_the_whole_recording_works_as_well():
    result = calibrate_sites(recording(3), CalibrationConfig(clock_segment_s=1000.0))
    assert len(result.clock.coefficients) == 1
    offsets, drifts = normalised_errors(result)
    assert np.all(np.abs(offsets) < 3) and np.all(np.abs(drifts) < 3)
    # one quadratic over 60 s pins the rate to 0.1 ppb: 15 ppm + 0.05 ppm/s, plus the reference
    # site's drift error, which the gauge hands the receiver clock
    for t in (-25.0, 0.0, 25.0):
        expected = 15e-6 + 0.05e-6 * t + 1e-9 * DRIFT_ERRORS_NS[int(result.reference_site[1:])]
        assert result.clock.rate(t) == pytest.approx(expected, abs=1e-9)


def test_a_fast_receiver_clock_wraps_the_ranges_and_is_unwrapped():
    # 100 ppm: the bias moves 1800 km in 60 s, more than half a frame (1499 km), across a frame's end
    observations = recording(5, clock_ppm=100.0)
    ranges = np.array([o.arrival.range_mod_m for o in observations if o.arrival.site == "S0"])
    assert np.max(np.abs(np.diff(ranges))) > FRAME_RANGE_M / 2  # the ranges wrap
    result = calibrate_sites(observations)
    offsets, drifts = normalised_errors(result)
    assert np.all(np.abs(offsets) < 3) and np.all(np.abs(drifts) < 3)
    assert result.residual_rms_after_m < 20.0


# --------------------------------------------------------------------------- bad input


def test_arrivals_from_one_site_are_refused():
    with pytest.raises(ValueError, match="at least 2"):
        calibrate_sites(recording(1, sites=range(1), heard=(1,)))
    with pytest.raises(ValueError, match="none"):
        calibrate_sites([])


def test_a_site_heard_once_is_named():
    observations = recording(1, seconds=10.0)
    once = [o for o in observations if o.arrival.site == "S3"][:1]
    rest = [o for o in observations if o.arrival.site != "S3"]
    with pytest.raises(ValueError, match="'S3' is heard at only 1 instant"):
        calibrate_sites(rest + once)


@pytest.mark.parametrize("field", ["time_s", "range_mod_m", "timing_std_m"])
def test_a_value_that_is_not_finite_is_named(field):
    observations = recording(1, seconds=5.0)
    observations[3] = replace(observations[3], arrival=replace(observations[3].arrival, **{field: math.nan}))
    with pytest.raises(ValueError, match=rf"observations\[3\].arrival.{field} is nan"):
        calibrate_sites(observations)


def test_a_truth_that_is_not_finite_is_named():
    observations = recording(1, seconds=5.0)
    observations[2] = replace(observations[2], truth_enu=np.array([1.0, math.nan, 0.0]))
    with pytest.raises(ValueError, match=r"observations\[2\].truth_enu"):
        calibrate_sites(observations)


def test_too_few_arrivals_for_the_unknowns_are_refused():
    observations = [o for o in recording(1, seconds=0.6) if o.arrival.site in ("S0", "S1", "S2")]
    with pytest.raises(ValueError, match="too few to calibrate"):
        calibrate_sites(observations)


def test_a_site_never_heard_with_another_is_named():
    # S5 only in the last 10 s, where nothing else is heard: its clock is the receiver's
    observations = [o for o in recording(2, seconds=40.0) if (o.arrival.site == "S5") == (o.arrival.time_s > 10.0)]
    with pytest.raises(ValueError, match="do not determine the clock of S5"):
        calibrate_sites(observations)


def test_bad_config_names_the_field():
    for kwargs, field in (({"clock_order": -1}, "clock_order"), ({"clock_order": 1.5}, "clock_order"),
                          ({"clock_segment_s": 0.0}, "clock_segment_s"), ({"min_timing_std_m": math.nan},
                                                                           "min_timing_std_m")):
        with pytest.raises(ValueError, match=field):
            CalibrationConfig(**kwargs)


# --------------------------------------------------------------------------- the database


def test_the_calibrated_database_puts_the_sites_on_the_reference_sites_clock(tmp_path):
    result = calibrate_sites(recording(11))
    calibrated = calibrated_database(TOWERS, result.sites, REFERENCE_NS)
    assert calibrated.timing_epoch_ns == REFERENCE_NS
    reference = calibrated.site(result.reference_site)
    new_anchors = Anchors(calibrated)
    for site in result.sites:
        s = int(site.site[1:])
        new = calibrated.site(site.site)
        assert 0.0 <= new.timing_offset_us < 10_000.0
        assert new.timing_offset_std_us == pytest.approx(site.offset_std_s * 1e6)
        assert new.timing_drift_std_ns_per_s == pytest.approx(site.drift_std * 1e9)
        # the new database's timing minus the true clock: the same for every site (the reference's error)
        for t in (-30.0, 0.0, 600.0):
            old = ANCHORS.anchors[site.site].timing_s((REFERENCE_NS - EPOCH_NS) * 1e-9 + t)
            true = old + 1e-6 * OFFSET_ERRORS_US[s] + 1e-9 * DRIFT_ERRORS_NS[s] * t
            r = int(result.reference_site[1:])
            old_ref = ANCHORS.anchors[result.reference_site].timing_s((REFERENCE_NS - EPOCH_NS) * 1e-9 + t)
            true_ref = old_ref + 1e-6 * OFFSET_ERRORS_US[r] + 1e-9 * DRIFT_ERRORS_NS[r] * t
            new_s, new_ref = new_anchors.anchors[site.site].timing_s(t), new_anchors.anchors[reference.name].timing_s(t)
            error = (new_s - true) - (new_ref - true_ref)
            error = (error + 5e-3) % 10e-3 - 5e-3
            sigma = math.hypot(site.offset_std_s, site.drift_std * t)
            assert abs(error) <= 3 * sigma + 1e-12, (site.site, t)
    # the site never heard keeps its entry; the file written loads back as the same database
    assert calibrated.site("far") == TOWERS.site("far")
    write_tower_database(calibrated, tmp_path / "calibrated.yaml")
    assert parse_tower_database(load_yaml(tmp_path / "calibrated.yaml")) == calibrated


def test_a_site_not_calibrated_is_moved_to_the_new_epoch():
    result = calibrate_sites([o for o in recording(4, seconds=20.0) if o.arrival.site != "S0"])
    calibrated = calibrated_database(TOWERS, result.sites, REFERENCE_NS)
    old, new = TOWERS.site("S0"), calibrated.site("S0")
    moved_s = (REFERENCE_NS - EPOCH_NS) * 1e-9
    assert new.timing_offset_us == pytest.approx((3120.4 - 12.0e-3 * moved_s) % 10_000.0, abs=1e-9)
    assert new.timing_drift_ns_per_s == old.timing_drift_ns_per_s
    assert new.timing_offset_std_us is None and new.timing_drift_std_ns_per_s is None


def test_a_drift_no_oscillator_has_is_not_written_and_the_site_keeps_its_own():
    # a site heard for half a second: its fitted drift (2e5 ns/s, sigma 1e5) says nothing, and
    # written it would make a database that does not load
    result = calibrate_sites(recording(4, seconds=10.0))
    wild = [replace(site, drift_correction=2e-4, drift_std=1e-4) if site.site == "S1" else site for site in result.sites]
    calibrated = calibrated_database(TOWERS, wild, REFERENCE_NS)
    assert calibrated.site("S1").timing_drift_ns_per_s == TOWERS.site("S1").timing_drift_ns_per_s
    assert calibrated.site("S1").timing_offset_std_us == pytest.approx(wild[1].offset_std_s * 1e6)
    assert calibrated.site("S2").timing_drift_std_ns_per_s == pytest.approx(result.sites[2].drift_std * 1e9)


def test_calibrated_database_refuses_what_it_cannot_apply():
    result = calibrate_sites(recording(4, seconds=10.0))
    with pytest.raises(ValueError, match="whole number of 10 ms frames"):
        calibrated_database(TOWERS, result.sites, REFERENCE_NS + 1)
    other = parse_tower_database({**database_dict(), "sites": database_dict()["sites"][1:]})
    with pytest.raises(ValueError, match="S0 are not in tower database"):
        calibrated_database(other, result.sites, REFERENCE_NS)


def test_tower_database_to_dict_round_trips_exactly(tmp_path):
    data = database_dict()
    data["sites"][0] |= {"timing_offset_std_us": 0.0123, "timing_drift_std_ns_per_s": 1e-5}
    data["sites"].append({"name": "plain", "cells": [{"pci": 7}, {"pci": 8, "bandwidth_mhz": 1.4}]})
    data["timing_epoch_utc"] = "2026-03-04T05:06:07.250001Z"
    towers = parse_tower_database(data)
    assert parse_tower_database(tower_database_to_dict(towers)) == towers
    assert tower_database_to_dict(towers)["timing_epoch_utc"] == "2026-03-04T05:06:07.250001Z"
    path = tmp_path / "towers.yaml"
    write_tower_database(towers, path)
    assert parse_tower_database(load_yaml(path)) == towers
    assert [p.name for p in tmp_path.iterdir()] == ["towers.yaml"]  # no temporary left behind
    bare = parse_tower_database({"name": "", "sites": [{"name": "A", "cells": [{"pci": 1}]}]})
    assert tower_database_to_dict(bare) == {"name": "", "sites": [{"name": "A", "cells": [{"pci": 1}]}]}
    assert parse_tower_database(tower_database_to_dict(bare)) == bare


@pytest.mark.parametrize("path", sorted((Path(__file__).resolve().parents[1] / "config" / "towers").glob("*.yaml")),
                         ids=lambda p: p.name)
def test_the_bundled_tower_databases_round_trip(path):
    towers = load_tower_database(path)
    assert parse_tower_database(tower_database_to_dict(towers)) == towers


def test_an_epoch_finer_than_a_microsecond_is_refused():
    with pytest.raises(ValueError, match="sub-microsecond"):
        tower_database_to_dict(replace(TOWERS, timing_epoch_ns=EPOCH_NS + 1))


def test_a_failed_write_leaves_the_old_file_whole(tmp_path, monkeypatch):
    path = tmp_path / "towers.yaml"
    write_tower_database(TOWERS, path)
    before = path.read_text()

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr("deepsync.outputs.os.replace", broken_replace)  # where the database is written whole
    with pytest.raises(OSError, match="disk full"):
        write_tower_database(replace(TOWERS, name="changed"), path)
    assert path.read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["towers.yaml"]


# --------------------------------------------------------------------------- how long it lasts


def test_calibration_lifetime():
    tolerance = SAMPLE_M / 4  # 39 m
    # offset only, a 20 ppb site: 39 m / (c * 20e-9) = 6.5 s
    assert calibration_lifetime_s(tolerance, 0.0, 0.0, 20e-9) == pytest.approx(tolerance / (C * 20e-9))
    # offset and drift: the drift's sigma limits, the offset's takes its share of the budget
    lifetime = calibration_lifetime_s(tolerance, 30e-9, 0.2e-9)
    assert C * math.hypot(30e-9, 0.2e-9 * lifetime) == pytest.approx(tolerance)
    assert calibration_lifetime_s(tolerance, 200e-9, 0.2e-9) == 0.0
    assert calibration_lifetime_s(tolerance, 10e-9, 0.0) == math.inf
    with pytest.raises(ValueError, match="drift_std"):
        calibration_lifetime_s(tolerance, 10e-9, math.nan)
