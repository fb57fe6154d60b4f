"""TS 36.211 structure of the downlink generator: sequences, mapping, frames, OFDM."""

import numpy as np
import pytest

from deepsync.lte import grid as G
from deepsync.lte.cell import CellConfig, split_pci
from deepsync.lte.frame import FrameGenerator
from deepsync.lte.numerology import (
    SUPPORTED_BANDWIDTHS_MHZ,
    SYNC_CODE_BASE_SAMPLES,
    Numerology,
    check_bandwidth,
    sync_code_start_base,
)
from deepsync.lte.ofdm import demodulate, modulate
from deepsync.lte.sequences import crs, gold_sequence, pss, sss, sss_indices
from deepsync.types import FRAME_SECONDS


def test_numerology_matches_36_101_and_36_211():
    expected = {1.4: (6, 128), 3: (15, 256), 5: (25, 512), 10: (50, 1024), 15: (75, 1536), 20: (100, 2048)}
    for bw, (n_rb, fft) in expected.items():
        num = Numerology.for_bandwidth(bw)
        assert (num.n_rb, num.fft_size) == (n_rb, fft)
        assert num.sample_rate_hz == fft * 15e3
        # 20 slots of 7 symbols fill exactly 10 ms; CP 160/144 Ts scaled to the FFT size
        assert num.samples_per_frame == round(num.sample_rate_hz * FRAME_SECONDS)
        assert (num.cp_lengths + fft).sum() == num.samples_per_frame
        assert num.cp_lengths[0] * 2048 == 160 * fft and num.cp_lengths[1] * 2048 == 144 * fft
    assert sync_code_start_base() == 686 and SYNC_CODE_BASE_SAMPLES == 274
    assert set(SUPPORTED_BANDWIDTHS_MHZ) == {1.4, 3.0, 5.0, 10.0, 15.0, 20.0}
    with pytest.raises(ValueError, match="not an LTE channel bandwidth"):
        check_bandwidth(7)


def test_pss_is_punctured_zadoff_chu_with_conjugate_roots():
    for n_id_2, u in ((0, 25), (1, 29), (2, 34)):
        d = pss(n_id_2)
        assert d.shape == (62,)
        np.testing.assert_allclose(np.abs(d), 1.0, atol=1e-12)
        full = np.exp(-1j * np.pi * u * np.arange(63) * np.arange(1, 64) / 63)  # ZC of length 63
        np.testing.assert_allclose(d, np.delete(full, 31), atol=1e-12)
    # u = 29 and u = 34 = 63 - 29 are conjugates: the envelope cannot tell them apart
    np.testing.assert_allclose(pss(1), np.conj(pss(2)), atol=1e-12)


def test_sss_index_table_and_distinctness():
    assert sss_indices(0) == (0, 1)
    assert sss_indices(29) == (29, 30)
    assert sss_indices(30) == (0, 2)
    assert sss_indices(167) == (2, 9)
    pairs = {sss_indices(n) for n in range(168)}
    assert len(pairs) == 168
    codes = set()
    for n_id_1 in range(168):
        for n_id_2 in range(3):
            d0, d5 = sss(n_id_1, n_id_2, 0), sss(n_id_1, n_id_2, 5)
            assert set(np.unique(d0)) <= {-1.0, 1.0}
            assert not np.array_equal(d0, d5)
            # the halves swap: even elements of subframe 5 use s1 where subframe 0 uses s0
            codes.add(d0.tobytes())
            codes.add(d5.tobytes())
    assert len(codes) == 2 * 504


def test_gold_sequence_known_start():
    # c_init = 0 leaves x2 at zero, so c(n) is x1 advanced by Nc = 1600: periodic with 2^31 - 1
    c = gold_sequence(0, 64)
    x1 = np.zeros(1600 + 64 + 31, dtype=np.uint8)
    x1[0] = 1
    for n in range(1600 + 64):
        x1[n + 31] = x1[n + 3] ^ x1[n]
    np.testing.assert_array_equal(c, x1[1600 : 1600 + 64])


@pytest.mark.parametrize("length", [440, 1000])  # a CRS's (the kept x2 bases) and beyond them
def test_gold_sequence_is_the_two_registers_of_36_211_bit_by_bit(length):
    rng = np.random.default_rng(3)
    for c_init in [1, 2**30, 2**31 - 1, *rng.integers(0, 2**31, 5).tolist()]:
        x1 = [1] + [0] * 30
        x2 = [(c_init >> i) & 1 for i in range(31)]
        for n in range(1600 + length):
            x1.append(x1[n + 3] ^ x1[n])
            x2.append(x2[n + 3] ^ x2[n + 2] ^ x2[n + 1] ^ x2[n])
        expected = [x1[n + 1600] ^ x2[n + 1600] for n in range(length)]
        np.testing.assert_array_equal(gold_sequence(c_init, length), expected)


def test_crs_is_qpsk_and_depends_on_cell_slot_symbol():
    r = crs(7, 3, 4)
    assert r.shape == (220,)
    np.testing.assert_allclose(np.abs(r), 1.0)
    assert set(np.round(r.real * np.sqrt(2)).astype(int)) == {-1, 1}
    assert not np.allclose(r, crs(8, 3, 4))
    assert not np.allclose(r, crs(7, 4, 4))
    assert not np.allclose(r, crs(7, 3, 0))


def test_sync_codes_straddle_dc_in_the_grid():
    num = Numerology.for_bandwidth(10)
    k = G.sync_subcarriers(num)
    assert k[30] == num.n_subcarriers // 2 - 1 and k[31] == num.n_subcarriers // 2
    offsets = num.subcarrier_offsets()[k]
    np.testing.assert_array_equal(offsets, np.r_[-31:0, 1:32])  # DC (offset 0) unused

    pci = 301
    n_id_1, n_id_2 = split_pci(pci)
    fixed = FrameGenerator(CellConfig(pci=pci, bandwidth_mhz=10), seed=0).fixed_grid()
    for slot, subframe in ((0, 0), (10, 5)):
        np.testing.assert_allclose(fixed[G.frame_symbol(slot, 6), k], pss(n_id_2))
        np.testing.assert_allclose(fixed[G.frame_symbol(slot, 5), k], sss(n_id_1, n_id_2, subframe))
        # five empty guard subcarriers each side of the 62
        guard = np.r_[k[0] - 5 : k[0], k[-1] + 1 : k[-1] + 6]
        assert not fixed[G.frame_symbol(slot, 6), guard].any()
    # port-0 CRS: symbols 0 and 4 of every slot, every 6th subcarrier shifted by PCI mod 6
    crs_symbols = np.flatnonzero(np.abs(fixed[:, 0:6]).sum(axis=1) > 0)
    expected = sorted(G.frame_symbol(s, l) for s in range(20) for l in (0, 4))
    assert sorted(set(crs_symbols) - {5, 6, 75, 76}) == expected
    positions = np.flatnonzero(fixed[G.frame_symbol(3, 0)])
    np.testing.assert_array_equal(positions, 6 * np.arange(100) + pci % 6)


@pytest.mark.parametrize("bandwidth", SUPPORTED_BANDWIDTHS_MHZ)
def test_frame_modulates_and_demodulates_exactly(bandwidth):
    generator = FrameGenerator(CellConfig(pci=17, bandwidth_mhz=bandwidth, load=0.7), seed=5)
    grid = generator.grid(11)
    samples = modulate(grid, generator.numerology)
    assert samples.shape == (generator.numerology.samples_per_frame,)
    np.testing.assert_allclose(demodulate(samples, generator.numerology), grid, atol=1e-12)
    # physical scaling (Parseval): each symbol's mean |x|^2 is the summed power of its REs
    num = generator.numerology
    useful = (num.symbol_starts + num.cp_lengths)[:, None] + np.arange(num.fft_size)
    np.testing.assert_allclose(
        np.mean(np.abs(samples[useful]) ** 2, axis=1), np.sum(np.abs(grid.astype(np.complex128)) ** 2, axis=1), rtol=1e-9
    )


def test_frames_are_reproducible_and_load_controls_pdsch():
    cell = CellConfig(pci=33, bandwidth_mhz=5, load=0.4, modulation_weights=(0, 0, 1))
    a, b = FrameGenerator(cell, seed=1), FrameGenerator(cell, seed=1)
    np.testing.assert_array_equal(a.grid(7), b.grid(7))
    np.testing.assert_array_equal(a.grid(-3), b.grid(-3))
    assert not np.array_equal(a.grid(7), a.grid(8))
    assert not np.array_equal(a.grid(7), FrameGenerator(cell, seed=2).grid(7))

    grid = a.grid(0)
    data = grid[G.frame_symbol(2, 2) : G.frame_symbol(2, 7)]  # subframe 1, data symbols, no CRS at l=2,3,5,6
    data = np.delete(data, 2, axis=0)  # l=4 carries CRS
    rb_used = np.abs(data).reshape(4, 25, 12).sum(axis=(0, 2)) > 0
    assert rb_used.sum() == round(0.4 * 25)
    levels = np.unique(np.round(np.abs(data[data != 0].real) * np.sqrt(42)).astype(int))
    np.testing.assert_array_equal(levels, [1, 3, 5, 7])  # 64QAM only

    empty = FrameGenerator(CellConfig(pci=33, bandwidth_mhz=5, load=0.0), seed=1).grid(0)
    fixed = a.fixed_grid()
    pbch = np.zeros_like(empty, dtype=bool)
    for l in range(4):
        pbch[G.frame_symbol(1, l), G.central_subcarriers(a.numerology)] = True
    np.testing.assert_array_equal(empty[~pbch], fixed[~pbch])  # unloaded: only PSS/SSS/CRS/PBCH


def test_cell_config_rejects_bad_values():
    for kwargs, message in (
        ({"pci": 504}, "out of range"),
        ({"pci": -1}, "out of range"),
        ({"pci": 1.5}, "not an integer"),
        ({"pci": 1, "bandwidth_mhz": 12}, "not an LTE channel bandwidth"),
        ({"pci": 1, "load": 1.2}, "load"),
        ({"pci": 1, "cfi": 4}, "cfi"),
        ({"pci": 1, "modulation_weights": (1, float("nan"), 0)}, "modulation_weights"),
    ):
        with pytest.raises(ValueError, match=message):
            CellConfig(**kwargs)
