"""The delay Cramér-Rao bound: normalisation against closed forms, colour, stacking, units."""

import math

import numpy as np
import pytest

from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.templates import SyncTemplates
from deepsync.timing.crlb import (
    delay_crlb,
    delay_crlb_white,
    fisher_information,
    fit_amplitude,
    snr_db,
)
from deepsync.types import SPEED_OF_LIGHT_M_S

MARGIN = 10


@pytest.fixture(scope="module")
def templates():
    return SyncTemplates(FrontendConfig())


def wide(templates, length):
    """Templates over a longer window (the code and everything after it: filter and coupling tails)."""
    return SyncTemplates(templates.config, length=length)


def gaussian_pulse(length=64, centre=20.0, width=3.0):
    """A pulse that is band-limited to double precision, with its exact derivative."""
    n = np.arange(length)
    pulse = np.exp(-((n - centre) ** 2) / (2 * width**2))
    return pulse, -(n - centre) / width**2 * pulse


def test_white_noise_frequency_domain_bound_equals_time_domain_closed_form():
    pulse, derivative = gaussian_pulse()
    for amplitude, sigma, n_frames in [(1.0, 0.1, 1), (2.5, 0.7, 10)]:
        closed = delay_crlb_white(derivative, amplitude, sigma, n_frames).std_samples
        spectral = delay_crlb(pulse, amplitude, sigma**2, n_frames, window_length=96).std_samples
        assert spectral == pytest.approx(closed, rel=1e-6)
        # and by hand: var = sigma^2 / (n A^2 sum s'^2)
        assert closed == pytest.approx(sigma / (amplitude * math.sqrt(n_frames * np.sum(derivative**2))))


def test_white_bound_of_the_sync_template_matches_its_time_derivative(templates):
    """Same check on a real template, with s' from SyncTemplates' exact sub-sample shifts.

    PCI 0 agrees within 1 %. The templates are slightly aliased (a 0.9 MHz 4th-order video
    filter at 1.92 MS/s), so for some PCIs the continuous-time derivative carries a little more
    high-frequency energy than the band-limited model of the samples sees (PCI 357: 10 %).
    """
    length = templates.length + 2 * MARGIN
    step = 1e-3
    longer = wide(templates, length)
    for pci, tolerance in [(0, 0.01), (357, 0.12)]:
        derivative = (longer.template(pci, 0, MARGIN - step) - longer.template(pci, 0, MARGIN + step)) / (2 * step)
        closed = delay_crlb_white(derivative, 1.0, 1.0).std_samples
        spectral = delay_crlb(templates.template(pci, 0), 1.0, 1.0, window_length=length).std_samples
        assert spectral == pytest.approx(closed, rel=tolerance)
        assert spectral >= closed * 0.999  # aliasing only ever hides information from the model


def test_coloured_noise_where_the_template_has_its_timing_energy_costs_more(templates):
    template = templates.template(121, 0)
    length = template.size + 2 * MARGIN
    k = np.arange(length // 2 + 1)
    timing_energy = (2 * np.pi * k / length) ** 2 * np.abs(np.fft.rfft(template, length)) ** 2

    def equal_power(shape):
        shape = np.maximum(shape, 1e-6 * shape.max())
        shape[0] = shape[1]
        # per-sample variance (1/L) sum over all bins = 1, as for the white PSD of 1.0
        total = (shape[0] + 2 * shape[1:-1].sum() + shape[-1]) / length
        return shape / total

    white = delay_crlb(template, 1.0, 1.0, window_length=length).std_samples
    on_template = delay_crlb(template, 1.0, equal_power(np.sqrt(timing_energy))).std_samples
    away = 1 / np.sqrt(timing_energy + 1e-9 * timing_energy.max())
    off_template = delay_crlb(template, 1.0, equal_power(away)).std_samples
    assert on_template > 1.2 * white
    assert off_template < white


def test_stacking_units_and_amplitude():
    pulse, _ = gaussian_pulse()
    one = delay_crlb(pulse, 1.0, 0.04, window_length=80)
    ten = delay_crlb(pulse, 1.0, 0.04, n_frames=10, window_length=80)
    assert ten.std_samples == pytest.approx(one.std_samples / math.sqrt(10))
    assert one.std_metres == pytest.approx(one.std_samples * SPEED_OF_LIGHT_M_S / 1.92e6)
    assert SPEED_OF_LIGHT_M_S / 1.92e6 == pytest.approx(156.1, abs=0.1)
    assert delay_crlb(pulse, 3.0, 0.04, window_length=80).std_samples == pytest.approx(one.std_samples / 3)
    # an rfft-binned PSD infers the (even) window length; a flat one equals the scalar
    flat = np.full(80 // 2 + 1, 0.04)
    assert delay_crlb(pulse, 1.0, flat).std_samples == pytest.approx(one.std_samples)
    assert fisher_information(pulse, 1.0, 0.04, window_length=80) == pytest.approx(one.std_samples**-2)
    assert delay_crlb(pulse, 0.0, 0.04).std_samples == math.inf
    # the template's spectrum, where the caller keeps it, is the template's: the same bound
    kept = delay_crlb(pulse, 1.0, flat, template_spectrum=np.fft.rfft(pulse, 80))
    assert kept.std_samples == pytest.approx(one.std_samples, rel=1e-12)
    with pytest.raises(ValueError, match="rfft of a 80-sample window"):
        delay_crlb(pulse, 1.0, flat, template_spectrum=np.fft.rfft(pulse))


def test_amplitude_and_snr_helpers(templates):
    template = templates.template(33, 5)
    length = template.size + 2 * MARGIN
    window = 0.7 * wide(templates, length).template(33, 5, MARGIN + 1.3) + 5.0  # pedestal
    # within 1 %: the window holds the code's tail beyond the 276 template samples, and the
    # template's band-limited shift is not exactly the (slightly aliased) true one
    assert fit_amplitude(window, template, MARGIN, 1.3) == pytest.approx(0.7, rel=0.01)
    weighted = fit_amplitude(window, template, MARGIN, 1.3, noise_psd=np.linspace(1, 3, length // 2 + 1))
    assert weighted == pytest.approx(0.7, rel=0.01)
    t0 = template - template.mean()
    noise_variance = float(np.sum(t0**2)) / template.size  # equal energies: 0 dB
    assert snr_db(1.0, template, noise_variance) == pytest.approx(0.0, abs=1e-9)
    assert snr_db(10.0, template, noise_variance) == pytest.approx(20.0)


def test_bad_input_is_refused():
    pulse, derivative = gaussian_pulse()
    with pytest.raises(ValueError, match="rfft bins"):
        delay_crlb(pulse, 1.0, np.ones(7), window_length=80)
    with pytest.raises(ValueError, match="> 0"):
        delay_crlb(pulse, 1.0, np.zeros(41))
    with pytest.raises(ValueError, match="NaN"):
        delay_crlb(pulse, 1.0, np.full(41, np.nan))
    with pytest.raises(ValueError, match="shorter"):
        delay_crlb(pulse, 1.0, 1.0, window_length=10)
    with pytest.raises(ValueError, match="constant"):
        delay_crlb(np.ones(30), 1.0, 1.0)
    with pytest.raises(ValueError, match="n_frames"):
        delay_crlb(pulse, 1.0, 1.0, n_frames=0)
    with pytest.raises(ValueError, match="sample_rate"):
        delay_crlb(pulse, 1.0, 1.0, sample_rate=-1.0)
    with pytest.raises(ValueError, match="sigma"):
        delay_crlb_white(derivative, 1.0, 0.0)
