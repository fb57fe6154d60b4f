"""EARFCN <-> downlink frequency against TS 36.101 Table 5.7.3-1."""

import pytest

from deepsync.lte.earfcn import (
    BANDS,
    band_of,
    check_channel,
    downlink_frequency_hz,
    earfcn_for,
)


@pytest.mark.parametrize(
    ("earfcn", "band", "mhz"),
    [
        (0, 1, 2110.0),
        (300, 1, 2140.0),
        (625, 2, 1932.5),
        (1300, 3, 1815.0),
        (1575, 3, 1842.5),
        (2000, 4, 2115.0),
        (2300, 4, 2145.0),
        (2525, 5, 881.5),
        (3100, 7, 2655.0),
        (3625, 8, 942.5),
        (5110, 12, 739.0),
        (5230, 13, 751.0),
        (5330, 14, 763.0),
        (5790, 17, 740.0),
        (5925, 18, 867.5),
        (6075, 19, 882.5),
        (6300, 20, 806.0),
        (8665, 25, 1992.5),
        (8865, 26, 876.5),
        (9410, 28, 778.0),
        (66486, 66, 2115.0),
        (67335, 66, 2199.9),
        (68661, 71, 624.5),
    ],
)
def test_known_points(earfcn, band, mhz):
    assert band_of(earfcn) == band
    assert downlink_frequency_hz(earfcn) == pytest.approx(mhz * 1e6, abs=1e-3)


def test_band_edges_match_the_standard_band_table():
    # TS 36.101 Table 5.5-1 downlink operating bands (MHz).
    edges = {1: (2110, 2170), 2: (1930, 1990), 3: (1805, 1880), 4: (2110, 2155),
             5: (869, 894), 7: (2620, 2690), 8: (925, 960), 12: (729, 746), 13: (746, 756),
             14: (758, 768), 17: (734, 746), 18: (860, 875), 19: (875, 890), 20: (791, 821),
             25: (1930, 1995), 26: (859, 894), 28: (758, 803), 66: (2110, 2200),
             71: (617, 652)}
    assert set(edges) == set(BANDS)
    for number, (low, high) in edges.items():
        band = BANDS[number]
        assert band.dl_low_hz == pytest.approx(low * 1e6)
        assert band.dl_high_hz == pytest.approx(high * 1e6)
        assert downlink_frequency_hz(band.n_offs_dl) == pytest.approx(low * 1e6)
        assert downlink_frequency_hz(band.n_dl_max) == pytest.approx(high * 1e6 - 100e3)


@pytest.mark.parametrize("earfcn", [-1, 600.5, True, "2000", 2650, 6600, 9660, 65535, 68936])
def test_invalid_earfcn_raises_naming_it(earfcn):
    with pytest.raises(ValueError, match="EARFCN"):
        downlink_frequency_hz(earfcn)


def test_earfcn_for_round_trips_every_band():
    for number, band in BANDS.items():
        for earfcn in (band.n_offs_dl, (band.n_offs_dl + band.n_dl_max) // 2, band.n_dl_max):
            frequency = downlink_frequency_hz(earfcn)
            assert earfcn_for(frequency, number) == earfcn
            assert downlink_frequency_hz(earfcn_for(frequency)) == frequency


def test_earfcn_for_overlapping_bands():
    assert earfcn_for(2115e6, band=4) == 2000
    assert earfcn_for(2115e6, band=66) == 66486
    assert earfcn_for(2115e6) == 50  # lowest band number that contains it: band 1


@pytest.mark.parametrize(
    ("frequency", "band", "message"),
    [
        (2115.05e6, None, "raster"),
        (2115e6, 3, "band 3"),
        (100e6, None, "any supported"),
        (2115e6, 6, "not a supported"),
        (float("nan"), None, "finite"),
    ],
)
def test_earfcn_for_errors(frequency, band, message):
    with pytest.raises(ValueError, match=message):
        earfcn_for(frequency, band)


def test_check_channel_band_edges():
    check_channel(2000, 10)      # 2110-2120 MHz: fits band 4 exactly at its lower edge
    check_channel(2349, 10)      # 2149.9 +- 5: ends at 2154.9, under 2155
    check_channel(2300, 20)      # 2145 +- 10: ends exactly at the upper edge
    with pytest.raises(ValueError, match="does not fit in band 4"):
        check_channel(1990, 10)  # 2114 MHz: 2109-2119
    with pytest.raises(ValueError, match="does not fit in band 4"):
        check_channel(2399, 1.4)  # 2154.9 + 0.7 > 2155
