"""The pull statistics (deepsync.eval.pulls): what a route's sites read beyond the truth, their
semivariogram along the path, and the bias model fitted to it."""

import math

import numpy as np
import pytest

from deepsync.eval.pulls import SitePulls, describe_pulls, fit_pull_model, semivariogram, site_pulls
from deepsync.eval.route import RouteEpoch, RouteRun
from deepsync.types import SPEED_OF_LIGHT_M_S, NoFix, NoFixReason

SAMPLE_RATE = 1.92e6


def gauss_markov(path_m: np.ndarray, sigma_m: float, decorrelation_m: float, rng: np.random.Generator) -> np.ndarray:
    """A first-order Gauss-Markov process over the path (exact discretisation)."""
    values = np.empty(len(path_m))
    values[0] = sigma_m * rng.standard_normal()
    for k in range(1, len(path_m)):
        keep = math.exp(-(path_m[k] - path_m[k - 1]) / decorrelation_m)
        values[k] = keep * values[k - 1] + sigma_m * math.sqrt(1 - keep**2) * rng.standard_normal()
    return values


def simulated_sites(sigma_m: float, decorrelation_m: float, levels_m: list[float], seed: int = 3) -> list[SitePulls]:
    rng = np.random.default_rng(seed)
    path = np.arange(0.0, 400.0, 0.5)
    return [SitePulls(f"S{k}", path, level + gauss_markov(path, sigma_m, decorrelation_m, rng))
            for k, level in enumerate(levels_m)]


def test_the_fit_finds_the_sigma_and_decorrelation_of_gauss_markov_pulls():
    for sigma, decorrelation in ((60.0, 40.0), (120.0, 15.0)):
        model = fit_pull_model(simulated_sites(sigma, decorrelation, [0.0] * 12))
        assert model.sigma_m == pytest.approx(sigma, rel=0.2)
        assert model.decorrelation_m == pytest.approx(decorrelation, rel=0.35)
        assert model.sites == 12 and model.arrivals == 12 * 800


def test_the_sites_levels_are_their_spread_and_leave_the_changing_part_alone():
    levels = [0.0, 100.0, 200.0, 300.0]
    plain, shifted = (fit_pull_model(simulated_sites(50.0, 30.0, values)) for values in ([0.0] * 4, levels))
    assert shifted.sigma_m == pytest.approx(plain.sigma_m)  # a level is the same at every lag
    assert shifted.level_std_m == pytest.approx(np.std(levels), abs=30.0)


def test_the_semivariogram_of_pulls_that_rise_steadily_grows_as_the_square_of_the_lag():
    path = np.arange(0.0, 200.0, 1.0)
    lag, gamma, count = semivariogram([SitePulls("S", path, 0.5 * path)], (1.5, 3.0, 6.0, 12.0))
    assert np.all(count > 0)
    assert np.allclose(gamma, 0.5 * (0.5 * lag) ** 2, rtol=0.05)


def test_a_receiver_that_stands_has_no_path_to_fit_over():
    standing = [SitePulls("S", np.zeros(50), np.random.default_rng(1).normal(40.0, 3.0, 50))]
    with pytest.raises(ValueError, match="three are needed"):
        fit_pull_model(standing)


def test_a_report_gives_the_semivariogram_and_the_fit_or_why_there_is_none():
    walked = describe_pulls(simulated_sites(60.0, 40.0, [0.0, 50.0]))
    assert [row["pairs"] > 0 for row in walked["semivariogram"]] == [True] * 7
    assert walked["fit"]["sigma_m"] == pytest.approx(60.0, rel=0.35) and walked["fit"]["sites"] == 2
    stood = describe_pulls([SitePulls("S", np.zeros(5), np.full(5, 40.0))])
    assert stood["fit"] is None and "0 lag bins" in stood["why_no_fit"]
    assert all(row["lag_m"] is None and row["root_m"] is None for row in stood["semivariogram"])


def test_site_pulls_reads_the_timing_errors_in_metres_along_the_true_path():
    def epoch(k: int, errors: dict) -> RouteEpoch:
        return RouteEpoch(k, np.array([3.0 * k, 4.0 * k, 1.5]), 2, (), NoFix(k, NoFixReason.TOO_FEW_SITES, ""), None,
                          math.nan, timing_errors=errors)
    run = RouteRun("bag", [epoch(0, {"A": (0.5, 0.01), "B": (math.nan, 0.01)}),
                           epoch(1, {"A": (0.25, 0.01), "B": (20.0, 0.01)}),  # 3 km: a false lock
                           epoch(2, {"B": (-0.1, 0.01)})], None)
    pulls = {site.site: site for site in site_pulls(run, SAMPLE_RATE)}
    metres = SPEED_OF_LIGHT_M_S / SAMPLE_RATE
    assert np.allclose(pulls["A"].path_m, [0.0, 5.0]) and np.allclose(pulls["A"].pull_m, [0.5 * metres, 0.25 * metres])
    assert np.allclose(pulls["B"].path_m, [10.0]) and np.allclose(pulls["B"].pull_m, [-0.1 * metres])
