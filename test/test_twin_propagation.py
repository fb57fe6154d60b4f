"""TR 38.901 large-scale parameters against values worked out by hand from Table 7.4.1-1,
Table 7.4.2-1 and Table 7.5-6 (fc = 2 GHz, h_UT = 1.5 m unless stated)."""

import numpy as np
import pytest

from deepsync.twin.propagation import (
    breakpoint_distance_m,
    delay_spread_lognormal,
    los_probability,
    path_loss_db,
    path_loss_los_db,
    path_loss_nlos_db,
    shadow_fading_std_db,
)

FC = 2e9


def test_breakpoint_distance_uses_effective_heights():
    # 4 * (25 - 1) * (1.5 - 1) * 2e9 / c
    assert breakpoint_distance_m(25.0, 1.5, FC) == pytest.approx(320.2215, abs=1e-3)
    assert breakpoint_distance_m(10.0, 1.5, FC) == pytest.approx(120.0831, abs=1e-3)


@pytest.mark.parametrize(
    ("model", "h_bs", "d2d", "los", "nlos"),
    [
        # UMa, d3D = sqrt(100^2 + 23.5^2) = 102.724 (below d'BP = 320 m):
        # PL1 = 28 + 22 log10(102.724) + 20 log10(2) = 78.277
        # PL'NLOS = 13.54 + 39.08 log10(102.724) + 20 log10(2) = 98.177
        ("UMa", 25.0, 100.0, 78.2774, 98.1768),
        # UMa, d3D = 1000.276 (beyond d'BP):
        # PL2 = 28 + 40 log10(1000.276) + 20 log10(2) - 9 log10(320.22^2 + 23.5^2) = 108.906
        # PL'NLOS = 13.54 + 39.08 log10(1000.276) + 6.0206 = 136.805
        ("UMa", 25.0, 1000.0, 108.9063, 136.8053),
        # UMi, d3D = sqrt(50^2 + 8.5^2) = 50.717 (below d'BP = 120 m):
        # PL1 = 32.4 + 21 log10(50.717) + 20 log10(2) = 74.229
        # PL'NLOS = 22.4 + 35.3 log10(50.717) + 21.3 log10(2) = 89.004
        ("UMi", 10.0, 50.0, 74.2289, 89.0040),
        # UMi, d3D = 500.072 (beyond d'BP):
        # PL2 = 32.4 + 40 log10(500.072) + 6.0206 - 9.5 log10(120.08^2 + 8.5^2) = 106.851
        # PL'NLOS = 22.4 + 35.3 log10(500.072) + 21.3 log10(2) = 124.088
        ("UMi", 10.0, 500.0, 106.8511, 124.0878),
    ],
)
def test_path_loss_reference_points(model, h_bs, d2d, los, nlos):
    d3d = np.hypot(d2d, h_bs - 1.5)
    assert path_loss_los_db(model, d2d, d3d, h_bs, 1.5, FC) == pytest.approx(los, abs=1e-3)
    assert path_loss_nlos_db(model, d2d, d3d, h_bs, 1.5, FC) == pytest.approx(nlos, abs=1e-3)
    assert path_loss_db(model, True, d2d, d3d, h_bs, 1.5, FC) == pytest.approx(los, abs=1e-3)
    assert path_loss_db(model, False, d2d, d3d, h_bs, 1.5, FC) == pytest.approx(nlos, abs=1e-3)


def test_nlos_is_never_below_los():
    # UMa, h_UT = 22.5 m, d2D = 20 m, d3D = 20.156: PL'NLOS = 13.54 + 39.08 log10(20.156)
    # + 6.0206 - 0.6 * 21 = 57.936 is below PL_LOS = 28 + 22 log10(20.156) + 6.0206 = 62.717.
    d3d = np.hypot(20.0, 2.5)
    assert path_loss_nlos_db("UMa", 20.0, d3d, 25.0, 22.5, FC) == pytest.approx(62.7173, abs=1e-3)
    d2d = np.linspace(10, 5000, 500)
    for model, h_bs in (("UMa", 25.0), ("UMi", 10.0)):
        d3d = np.hypot(d2d, h_bs - 1.5)
        assert np.all(path_loss_nlos_db(model, d2d, d3d, h_bs, 1.5, FC)
                      >= path_loss_los_db(model, d2d, d3d, h_bs, 1.5, FC))


def test_los_path_loss_is_continuous_at_the_breakpoint():
    for model, h_bs in (("UMa", 25.0), ("UMi", 10.0)):
        d_bp = breakpoint_distance_m(h_bs, 1.5, FC)
        d2d = np.array([d_bp - 1e-6, d_bp + 1e-6])
        loss = path_loss_los_db(model, d2d, np.hypot(d2d, h_bs - 1.5), h_bs, 1.5, FC)
        assert loss[1] - loss[0] == pytest.approx(0.0, abs=0.02)


def test_los_probability_limits_and_values():
    for model in ("UMa", "UMi"):
        np.testing.assert_array_equal(los_probability(model, [0.0, 10.0, 18.0], 1.5), 1.0)
        p = los_probability(model, np.linspace(18, 5000, 1000), 1.5)
        assert np.all(np.diff(p) < 0) and np.all(p > 0)
    # 18/100 + exp(-100/36) (1 - 18/100)
    assert los_probability("UMi", 100.0, 1.5) == pytest.approx(0.230985, abs=1e-6)
    # 18/100 + exp(-100/63) (1 - 18/100)
    assert los_probability("UMa", 100.0, 1.5) == pytest.approx(0.347671, abs=1e-6)
    assert los_probability("UMa", 100.0, 13.0) == pytest.approx(0.347671, abs=1e-6)
    # C'(18 m) = 0.5^1.5: x (1 + C' 5/4 (100/100)^3 exp(-100/150))
    assert los_probability("UMa", 100.0, 18.0) == pytest.approx(0.426558, abs=1e-6)


def test_shadow_fading_std():
    assert shadow_fading_std_db("UMa", True) == 4.0
    assert shadow_fading_std_db("UMa", False) == 6.0
    assert shadow_fading_std_db("UMi", True) == 4.0
    assert shadow_fading_std_db("UMi", False) == 7.82


@pytest.mark.parametrize(
    ("model", "los", "fc", "mu", "sigma"),
    [
        ("UMa", True, 2.115e9, -7.029936, 0.66),   # fc -> 6 GHz: -6.955 - 0.0963 log10(6)
        ("UMa", False, 2.115e9, -6.438743, 0.39),  # -6.28 - 0.204 log10(6)
        ("UMa", False, 28e9, -6.575220, 0.39),     # -6.28 - 0.204 log10(28)
        ("UMi", True, 1.0e9, -7.254509, 0.38),     # fc -> 2 GHz: -0.24 log10(3) - 7.14
        ("UMi", False, 1.0e9, -6.944509, 0.356339),  # sigma = 0.16 log10(3) + 0.28
        ("UMi", False, 3.5e9, -6.986771, 0.384514),  # log10(4.5)
    ],
)
def test_delay_spread_parameters(model, los, fc, mu, sigma):
    got_mu, got_sigma = delay_spread_lognormal(model, los, fc)
    assert got_mu == pytest.approx(mu, abs=1e-6)
    assert got_sigma == pytest.approx(sigma, abs=1e-6)


def test_unknown_model():
    with pytest.raises(ValueError, match="RMa"):
        los_probability("RMa", 100.0, 1.5)
