"""The RSSI baseline: a log-distance path-loss fit and a position from the sites' powers.

Powers are drawn from the model itself (known intercepts and exponent, Gaussian shadowing in
dB), so the fit must recover what was put in and the solver must land on the truth when there
is no shadowing.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from deepsync.fusion.anchors import SiteArrival
from deepsync.fusion.calibration import CalibrationObservation
from deepsync.fusion.rssi import PathLossModel, RssiAverager, RssiConfig, fit_path_loss, solve_rssi
from deepsync.types import Fix, NoFix, NoFixReason

# six sites (east m, north m, antenna height m) and their intercepts (dB at 1 m): EIRPs differ
SITES = {"A": (-900, 1200, 30), "B": (1500, 300, 25), "C": (400, -1300, 28), "D": (-1600, -500, 35),
         "E": (800, 1700, 22), "F": (2100, -1400, 40)}
INTERCEPTS = {"A": -20.0, "B": -26.0, "C": -17.5, "D": -31.0, "E": -23.0, "F": -28.5}
EXPONENT = 3.2
MODEL = PathLossModel(INTERCEPTS, EXPONENT, 0.0, 6.0, 0)
HEIGHT = 1.5


def arrival(site: str, receiver: np.ndarray, shadowing_db: float, rng: np.random.Generator,
            time_s: float = 0.0) -> SiteArrival:
    position = np.array(SITES[site], dtype=np.float64)
    distance = np.linalg.norm(receiver - position)
    power = INTERCEPTS[site] - 10 * EXPONENT * math.log10(distance) + rng.normal(0, shadowing_db)
    return SiteArrival(site, position, time_s, 0.0, 10.0, (1,), amplitude=10 ** (power / 10))


def receiver(rng: np.random.Generator) -> np.ndarray:
    return np.array([*rng.uniform(-1500, 1500, 2), HEIGHT])


def observations(rng: np.random.Generator, n: int, shadowing_db: float = 6.0) -> list[CalibrationObservation]:
    out = []
    for _ in range(n):
        truth = receiver(rng)
        out += [CalibrationObservation(arrival(site, truth, shadowing_db, rng), truth) for site in SITES]
    return out


# --------------------------------------------------------------------------- the fit


def test_fit_recovers_the_exponent_intercepts_and_shadowing():
    model = fit_path_loss(observations(np.random.default_rng(1), 600))
    errors = {site: model.intercept_db[site] - INTERCEPTS[site] for site in SITES}
    print(f"\nfit from {model.n_observations} arrivals: n = {model.exponent:.3f} +- {model.exponent_std:.3f} "
          f"(true {EXPONENT}), shadowing {model.shadowing_db:.2f} dB (true 6), intercept errors "
          + ", ".join(f"{site} {e:+.2f}" for site, e in errors.items()) + " dB")
    assert model.exponent == pytest.approx(EXPONENT, abs=0.3)
    assert abs(model.exponent - EXPONENT) < 3 * model.exponent_std
    assert all(abs(e) < 2.0 for e in errors.values())
    assert model.shadowing_db == pytest.approx(6.0, rel=0.05)
    assert model.n_observations == 3600


def test_fit_skips_arrivals_without_a_power():
    data = observations(np.random.default_rng(2), 100)
    model = fit_path_loss(data)
    silent = [CalibrationObservation(SiteArrival(o.arrival.site, o.arrival.position_enu, 0.0, 0.0, 10.0, (1,),
                                                 amplitude=amplitude), o.truth_enu)
              for o, amplitude in zip(data[:3], (math.nan, 0.0, -1e-3))]
    assert fit_path_loss(data + silent) == model


def test_fit_refuses_too_few_arrivals_and_positions_that_are_not_finite():
    with pytest.raises(ValueError, match="at least 9"):
        fit_path_loss(observations(np.random.default_rng(3), 1))
    with pytest.raises(ValueError, match="at least"):
        fit_path_loss([])
    data = observations(np.random.default_rng(3), 10)
    data[4] = CalibrationObservation(data[4].arrival, np.array([0.0, math.nan, 1.5]))
    with pytest.raises(ValueError, match=r"observations\[4\]"):
        fit_path_loss(data)


def test_a_model_without_shadowing_is_refused():
    with pytest.raises(ValueError, match="shadowing_db"):
        PathLossModel(INTERCEPTS, EXPONENT, 0.0, 0.0, 0)


# --------------------------------------------------------------------------- the position


def test_noiseless_powers_give_the_position():
    rng = np.random.default_rng(4)
    for _ in range(20):
        truth = receiver(rng)
        fix = solve_rssi([arrival(site, truth, 0.0, rng) for site in SITES], MODEL, stamp_ns=42)
        assert isinstance(fix, Fix) and fix.stamp_ns == 42
        assert np.linalg.norm(np.array(fix.position_enu) - truth) < 0.01
        assert fix.position_enu[2] == HEIGHT and sorted(fix.sites) == sorted(SITES)


def test_with_shadowing_the_errors_are_what_rssi_gives_and_the_covariance_says_so():
    rng = np.random.default_rng(5)
    model = fit_path_loss(observations(rng, 300))
    errors, squared = [], []
    for _ in range(300):
        truth = receiver(rng)
        fix = solve_rssi([arrival(site, truth, 6.0, rng) for site in SITES], model)
        assert isinstance(fix, Fix)
        error = np.array(fix.position_enu[:2]) - truth[:2]
        errors.append(float(np.linalg.norm(error)))
        squared.append(float(error @ np.linalg.solve(fix.covariance[:2, :2], error)))
    median = float(np.median(errors))
    print(f"\n6 dB shadowing, 6 sites over 3 x 3 km: median error {median:.0f} m, 90th percentile "
          f"{np.percentile(errors, 90):.0f} m; median squared Mahalanobis {np.median(squared):.2f} (chi2(2): 1.39)")
    # ranging by power: sigma_d / d = 6 dB * ln(10) / (10 n) = 43 %, at 1-2 km several hundred metres
    assert 200.0 < median < 800.0
    # the linearised covariance is a little optimistic: ranges from powers are log-normal, not Gaussian
    assert 0.8 < np.median(squared) / 1.386 < 1.8


def test_an_arrival_without_a_power_is_left_out():
    rng = np.random.default_rng(6)
    truth = receiver(rng)
    arrivals = [arrival(site, truth, 0.0, rng) for site in "ABCD"]
    arrivals[1] = SiteArrival("B", arrivals[1].position_enu, 0.0, 0.0, 10.0, (1,))  # amplitude NaN
    fix = solve_rssi(arrivals, MODEL)
    assert isinstance(fix, Fix) and fix.sites == ("A", "C", "D")
    assert np.linalg.norm(np.array(fix.position_enu) - truth) < 0.01


def test_fewer_than_three_sites_is_no_fix():
    rng = np.random.default_rng(7)
    truth = receiver(rng)
    arrivals = [arrival(site, truth, 0.0, rng) for site in "AB"]
    result = solve_rssi(arrivals, MODEL, stamp_ns=7)
    assert isinstance(result, NoFix) and result.reason is NoFixReason.TOO_FEW_SITES and result.stamp_ns == 7
    stranger = SiteArrival("Z", np.zeros(3), 0.0, 0.0, 10.0, (1,), amplitude=1e-6)
    result = solve_rssi([*arrivals, stranger], MODEL)
    assert result.reason is NoFixReason.TOO_FEW_SITES and "no path-loss model: Z" in result.message
    assert solve_rssi([stranger], MODEL).reason is NoFixReason.UNKNOWN_SITES
    assert solve_rssi([], MODEL).reason is NoFixReason.TOO_FEW_SITES
    with pytest.raises(ValueError, match="heard twice: A"):
        solve_rssi([arrivals[0], *arrivals], MODEL)


def test_sites_on_a_line_through_the_position_leave_it_undetermined():
    line = {"P": (-1000, 0, 30), "Q": (0, 0, 30), "R": (1000, 0, 30)}
    arrivals = [SiteArrival(name, np.array(p, dtype=float), 0.0, 0.0, 10.0, (1,),
                            amplitude=10 ** ((-20 - 32 * math.log10(math.dist(p, (300, 0, HEIGHT)))) / 10))
                for name, p in line.items()]
    model = PathLossModel(dict.fromkeys(line, -20.0), 3.2, 0.0, 6.0, 0)
    assert solve_rssi(arrivals, model).reason is NoFixReason.DEGENERATE_GEOMETRY


# --------------------------------------------------------------------------- averaging over stacks


def test_the_averager_gathers_the_sites_of_a_window_of_stacks():
    rng = np.random.default_rng(8)
    truth = receiver(rng)
    averager = RssiAverager(RssiConfig(window_s=1.0))
    heard = []
    for k in range(30):  # 3 s of 100 ms stacks, each hearing 1-2 sites with 6 dB of scatter
        t = 0.1 * k
        sites = rng.choice(list(SITES), rng.choice([1, 2]), replace=False)
        stack = [arrival(site, truth, 6.0, rng, t) for site in sites]
        heard.append(stack)
        averaged = averager.add(stack)
    now = max(a.time_s for stack in heard for a in stack)
    window = [a for stack in heard for a in stack if a.time_s > now - 1.0]
    assert [a.site for a in averaged] == sorted({a.site for a in window})
    for a in averaged:
        own = [10 * math.log10(w.amplitude) for w in window if w.site == a.site]
        assert 10 * math.log10(a.amplitude) == pytest.approx(np.mean(own), abs=1e-9)
        assert a.time_s == max(w.time_s for w in window if w.site == a.site)
    assert len(averaged) >= 4  # one stack hears 1-2 sites; a second of them, most of the six
    assert isinstance(solve_rssi(averaged, MODEL), Fix)
    # a site not heard for longer than the window drops out
    assert averager.add([]) == averaged
    later = [arrival("A", truth, 6.0, rng, 10.0)]
    assert [a.site for a in averager.add(later)] == ["A"]
    assert averager.add([SiteArrival("B", np.zeros(3), 10.1, 0.0, 10.0, (1,))]) == averager.add([])  # no power


def test_bad_config_names_the_field():
    for kwargs, field in (({"window_s": 0.0}, "window_s"), ({"window_s": math.nan}, "window_s"),
                          ({"receiver_height_m": math.inf}, "receiver_height_m")):
        with pytest.raises(ValueError, match=field):
            RssiConfig(**kwargs)
