"""Coherent (complex-domain) reference cell search (its I/Q reading is tested in test_sources)."""

from pathlib import Path

import numpy as np
import pytest

from deepsync.lte.cell import CellConfig
from deepsync.lte.frame import FrameGenerator
from deepsync.lte.numerology import Numerology, sync_code_start_base
from deepsync.lte.ofdm import modulate
from deepsync.lte.sequences import crs
from deepsync.testing import coherent as C
from deepsync.sources import read_iq

FS = 1.92e6
FRAME = 19200
REPO = Path(__file__).resolve().parents[1]
REAL = REPO / "../shared/data/real_lte/f1860_s1.92_g0_1s_strong_rtlsdr.bin"
NUM_14 = Numerology.for_bandwidth(1.4)


def cell_baseband(pci: int, frames: int, seed: int, load: float = 0.7) -> np.ndarray:
    """``frames`` frames of one 1.4 MHz cell at 1.92 Msps, unit power per RE."""
    gen = FrameGenerator(CellConfig(pci=pci, bandwidth_mhz=1.4, load=load), seed)
    return np.concatenate([modulate(gen.grid(i), NUM_14) for i in range(frames)])


def add_noise(x: np.ndarray, snr_db: float, rng: np.random.Generator) -> np.ndarray:
    power = np.mean(np.abs(x) ** 2) / 10 ** (snr_db / 10)
    noise = rng.standard_normal(x.size) + 1j * rng.standard_normal(x.size)
    return (x + np.sqrt(power / 2) * noise).astype(np.complex64)


def with_cfo(x: np.ndarray, cfo_hz: float, phase: float = 0.3) -> np.ndarray:
    return x * np.exp(2j * np.pi * (cfo_hz * np.arange(x.size) / FS + phase))


# --------------------------------------------------------------------------- synthetic search


def test_crs_table_matches_the_sequence_generator():
    table = C.crs_table()
    for pci in (0, 86, 142, 503):
        for slot in (0, 9, 19):
            for j, symbol in enumerate((0, 4)):
                np.testing.assert_allclose(table[pci, slot, j], crs(pci, slot, symbol)[104:116])


def test_two_cells_with_cfo_and_noise_are_found_exactly():
    rng = np.random.default_rng(11)
    frames = 8
    shift_a, shift_b = 5000, 12345
    a = np.roll(cell_baseband(142, frames + 1, seed=1), shift_a)[: frames * FRAME]
    b = np.roll(cell_baseband(86, frames + 1, seed=2), shift_b)[: frames * FRAME]
    x = add_noise(with_cfo(a + 0.5 * b, 37_000.0), snr_db=0.0, rng=rng)

    cells = C.search_cells(x, carrier_hz=1860e6)

    assert [c.pci for c in cells] == [142, 86]
    strong, weak = cells
    assert strong.sync_index == (shift_a + sync_code_start_base()) % FRAME
    assert weak.sync_index == (shift_b + sync_code_start_base()) % FRAME
    assert weak.first_subframe == 5  # 12345 + 686 > 9600: subframe 5's SSS comes first
    assert strong.pss_index == (shift_a + 832) % 9600
    for cell in cells:
        assert abs(cell.cfo_hz - 37_000.0) < 20.0
        assert cell.cfo_ppm == pytest.approx(37_000.0 / 1860e6 * 1e6, abs=0.02)
        assert abs(cell.clock_ppm) < 1.0 and cell.samples_per_frame == pytest.approx(FRAME, abs=0.02)
        assert cell.sss_z >= 10 and cell.sss_metric > 1.4 * cell.sss_runner_up
    assert 10 * np.log10(strong.power / weak.power) == pytest.approx(6.0, abs=1.5)

    for cell in cells:
        check = C.verify_pci(x, cell, wrong_pcis=[0, 87, 141, 143, 145, 400])
        assert check.confirmed, check
        assert check.best_wrong_z < 4.0, check
    # a 5 ms error in the frame timing renumbers the slots: the CRS no longer match
    metric, floor, _ = C.crs_scan(x, strong.sync_position + 9600, strong.cfo_hz, pcis=[142])
    assert metric[0] / floor[0] < 4.0


def test_receiver_clock_drift_is_followed():
    """A -45 ppm receiver (one crystal for LO and ADC): CFO +83.7 kHz at 1860 MHz and frames
    of 19199.14 samples; 30 frames drift by 26 samples."""
    ppm = -45.0
    frames, shift = 30, 2500
    s = np.roll(cell_baseband(77, frames + 1, seed=5, load=0.5), shift)
    n_out, block, pad = frames * FRAME, 960, 64
    freqs = np.fft.fftfreq(block + 2 * pad)
    y = np.empty(n_out, dtype=np.complex128)
    for start in range(0, n_out, block):  # receiver sample n <- transmitter time n / (1 + e)
        t = start / (1 + ppm * 1e-6)
        i0 = int(np.floor(t))
        seg = np.take(s, np.arange(i0 - pad, i0 + block + pad), mode="wrap")
        seg = np.fft.ifft(np.fft.fft(seg) * np.exp(2j * np.pi * freqs * (t - i0)))
        y[start : start + block] = seg[pad : pad + block]
    cfo = -ppm * 1e-6 * 1860e6
    x = add_noise(with_cfo(y, cfo), snr_db=0.0, rng=np.random.default_rng(2))

    (cell,) = C.search_cells(x, carrier_hz=1860e6)

    assert cell.pci == 77 and cell.sync_index == shift + sync_code_start_base()
    assert cell.clock_ppm == pytest.approx(ppm, abs=2.0)
    assert cell.cfo_ppm == pytest.approx(-ppm, abs=0.05)
    assert C.verify_pci(x, cell).confirmed


def test_noise_and_a_tone_give_no_cells():
    rng = np.random.default_rng(5)
    n = 4 * FRAME
    noise = (rng.standard_normal(n) + 1j * rng.standard_normal(n)).astype(np.complex64)
    assert C.search_cells(noise) == []
    tone = noise + 3 * np.exp(2j * np.pi * 123_456 * np.arange(n) / FS)
    assert C.search_cells(tone) == []


def test_search_rejects_other_sample_rates_and_short_input():
    with pytest.raises(ValueError, match="1.92 Msps"):
        C.search_cells(np.zeros(4 * FRAME, complex), sample_rate=3.84e6)
    with pytest.raises(ValueError, match="at least 2 frames"):
        C.search_cells(np.zeros(FRAME, complex))


# --------------------------------------------------------------------------- real recording


@pytest.fixture(scope="module")
def real_cells():
    if not REAL.is_file():
        pytest.skip(f"real RTL-SDR recording not present at {REAL.resolve()} (test data)")
    iq = read_iq(REAL, "cu8")
    return iq, C.search_cells(iq, carrier_hz=1860e6)


@pytest.mark.slow
def test_real_recording_finds_pci_142_and_86(real_cells, record_property):
    iq, cells = real_cells
    by_pci = {c.pci: c for c in cells}
    assert set(by_pci) == {142, 86}, cells  # the recording author's cell-search result
    a, b = by_pci[142], by_pci[86]
    report = {
        "sync_index_142": a.sync_index,
        "sync_index_86": b.sync_index,
        "separation_samples": a.sync_index - b.sync_index,
        "cfo_hz": round(a.cfo_hz, 1),
        "cfo_ppm": round(a.cfo_ppm, 3),
        "clock_ppm": round(a.clock_ppm, 3),
        "power_142_over_86_db": round(10 * np.log10(a.power / b.power), 2),
        "sss_142": (round(a.sss_metric, 3), round(a.sss_runner_up, 3), round(a.sss_z, 1)),
        "sss_86": (round(b.sss_metric, 3), round(b.sss_runner_up, 3), round(b.sss_z, 1)),
        "first_subframe": (a.first_subframe, b.first_subframe),
    }
    for key, value in report.items():
        record_property(key, value)
    print("real recording:", report)

    # As measured (2 cells of a frame-synchronised network, 7 samples = 3.6 us apart).
    assert a.sync_index == pytest.approx(4246, abs=2)
    assert b.sync_index == pytest.approx(4239, abs=2)
    assert a.sync_index - b.sync_index == pytest.approx(7, abs=1)
    assert a.first_subframe == b.first_subframe == 0
    assert a.sync_index == (a.pss_index - 146) % FRAME
    # The cells sit at -41.78 kHz: the LO is 22.46 ppm high at 1860 MHz. Frames last 19200.43
    # samples: the sample clock is 22.2 ppm fast. One crystal, as expected of an RTL-SDR.
    assert a.cfo_hz == pytest.approx(-41_778, abs=50) and a.cfo_std_hz < 20
    assert a.clock_ppm == pytest.approx(-a.cfo_ppm, abs=1.0)
    for cell in cells:
        assert cell.sss_z > 15 and cell.sss_metric > 1.8 * cell.sss_runner_up
        assert abs(cell.sss_phase_rad) < 0.3  # PSS and SSS see the same channel
    assert 0 < 10 * np.log10(a.power / b.power) < 3


@pytest.mark.slow
def test_real_recording_pcis_are_confirmed_by_crs(real_cells, record_property):
    iq, cells = real_cells
    wrong = [0, 1, 85, 87, 141, 143, 145, 89, 250, 503]
    for cell in cells:
        check = C.verify_pci(iq, cell, wrong_pcis=wrong)
        record_property(f"crs_{cell.pci}", (round(check.z, 1), round(check.best_wrong_z, 1)))
        print(f"CRS PCI {cell.pci}: z {check.z:.1f} (metric {check.metric:.3f}); best wrong "
              f"of {wrong}: PCI {check.best_wrong_pci} z {check.best_wrong_z:.1f}")
        assert check.confirmed and check.z > 12
        assert check.best_wrong_z < 4
        # the other found cell is frame-aligned: its CRS line up at this timing as well
        other = next(c.pci for c in cells if c.pci != cell.pci)
        assert C.verify_pci(iq, cell, other, wrong_pcis=[]).confirmed
