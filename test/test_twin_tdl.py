"""TDL profiles (TR 38.901 Tables 7.7.2-1..5), sum-of-sinusoids fading, sector antenna."""

import numpy as np
import pytest

from deepsync.twin.antenna import SectorAntenna, SectorPattern
from deepsync.twin.fading import SumOfSinusoids
from deepsync.twin.tdl import TDL_PROFILES
from deepsync.types import FRAME_SECONDS


@pytest.mark.parametrize(
    ("name", "rayleigh_taps", "k_db", "last_delay"),
    [("TDL-A", 23, None, 9.6586), ("TDL-B", 23, None, 4.7834), ("TDL-C", 24, None, 8.6523),
     ("TDL-D", 13, 13.3, 12.525), ("TDL-E", 14, 22.0, 20.6519)],
)
def test_profile_tables(name, rayleigh_taps, k_db, last_delay):
    profile = TDL_PROFILES[name]
    assert len(profile.delays) == len(profile.powers_db) == rayleigh_taps
    assert profile.delays[0] == 0.0 and min(profile.delays) == 0.0
    assert profile.delays[-1] == last_delay
    if k_db is None:
        assert profile.k_factor_db is None
        assert max(profile.powers_db) == 0.0  # NLOS tables peak at 0 dB
    else:
        assert profile.k_factor_db == pytest.approx(k_db, abs=1e-9)
    scattered, specular = profile.normalized_powers()
    assert scattered.sum() + specular == pytest.approx(1.0, abs=1e-12)
    assert (specular > 0) == (k_db is not None)


def test_tdl_a_first_tap_is_weak():
    scattered, _ = TDL_PROFILES["TDL-A"].normalized_powers()
    assert 10 * np.log10(scattered[0] / scattered.max()) == pytest.approx(-13.4)


def test_sum_of_sinusoids_unit_mean_power_and_doppler_range():
    fading = SumOfSinusoids.draw(np.random.default_rng(3), (20_000,), 16)
    f_max = 12.0
    for t in (0.0, 0.37, 5.0):
        power = np.abs(fading.gain(t, f_max)) ** 2
        assert power.mean() == pytest.approx(1.0, abs=0.03)
    doppler = fading.doppler_hz(f_max)
    assert np.all(np.abs(doppler) <= f_max)
    assert doppler.min() < -0.99 * f_max and doppler.max() > 0.99 * f_max
    # components are the sinusoids: they sum to the gain and rotate at their Doppler
    parts = fading.components(0.25, f_max)
    np.testing.assert_allclose(parts.sum(axis=-1), fading.gain(0.25, f_max))
    np.testing.assert_allclose(fading.components(0.26, f_max) / parts,
                               np.exp(2j * np.pi * doppler * FRAME_SECONDS))


def test_sum_of_sinusoids_time_autocorrelation_is_clarke():
    # E[g(t) g*(t + tau)] = J0(2 pi f_max tau) for uniformly distributed arrival angles.
    from scipy.special import j0

    fading = SumOfSinusoids.draw(np.random.default_rng(4), (20_000,), 16)
    f_max, tau = 10.0, 0.02
    correlation = np.mean(fading.gain(0.0, f_max) * np.conj(fading.gain(tau, f_max)))
    assert correlation.real == pytest.approx(j0(2 * np.pi * f_max * tau), abs=0.03)


def _direction(bearing_deg, depression_deg):
    b, e = np.radians(bearing_deg), np.radians(depression_deg)
    return np.array([np.sin(b) * np.cos(e), np.cos(b) * np.cos(e), -np.sin(e)])


def test_sector_antenna_pattern():
    antenna = SectorAntenna(azimuth_deg=30.0, downtilt_deg=6.0)
    assert antenna.gain_db(_direction(30.0, 6.0)) == pytest.approx(0.0, abs=1e-9)
    # half-power beamwidths: 65 deg horizontal, 10 deg vertical
    assert antenna.gain_db(_direction(30.0 + 32.5, 6.0)) == pytest.approx(-3.0, abs=1e-9)
    assert antenna.gain_db(_direction(30.0 - 32.5, 6.0)) == pytest.approx(-3.0, abs=1e-9)
    assert antenna.gain_db(_direction(30.0, 11.0)) == pytest.approx(-3.0, abs=1e-9)
    assert antenna.gain_db(_direction(30.0, 1.0)) == pytest.approx(-3.0, abs=1e-9)
    # front-back ratio, side-lobe level of the vertical cut, total floor
    assert antenna.gain_db(_direction(210.0, 6.0)) == pytest.approx(-30.0)
    assert antenna.gain_db(_direction(30.0, 60.0)) == pytest.approx(-20.0)
    assert antenna.gain_db(_direction(150.0, 60.0)) == pytest.approx(-30.0)
    # 12 (60/65)^2 at 60 deg off in azimuth, on the vertical beam peak
    assert antenna.gain_db(_direction(330.0, 6.0)) == pytest.approx(-12 * (60 / 65) ** 2)
    rng = np.random.default_rng(5)
    assert np.all(antenna.gain_db(rng.normal(size=(1000, 3))) <= 0.0)


def test_sector_pattern_is_configurable_and_validated():
    wide = SectorAntenna(0.0, 0.0, SectorPattern(horizontal_beamwidth_deg=90.0))
    assert wide.gain_db(_direction(45.0, 0.0)) == pytest.approx(-3.0)
    with pytest.raises(ValueError, match="vertical_beamwidth_deg"):
        SectorPattern(vertical_beamwidth_deg=0.0)
