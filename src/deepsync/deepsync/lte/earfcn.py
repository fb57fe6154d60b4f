"""Downlink EARFCN <-> carrier frequency (TS 36.101 §5.7.3, Table 5.7.3-1), FDD bands.

F_DL = F_DL_low + 0.1 (N_DL - N_Offs-DL) MHz. Frequencies are computed in integer units of
the 100 kHz channel raster, so every EARFCN maps to an exact multiple of 100 kHz.

Several bands overlap (1/4/66, 2/25, 5/26, 12/17, 18/19/26, 14/28): one frequency has one
EARFCN per band that contains it, so :func:`earfcn_for` takes the band to use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

RASTER_HZ = 100e3


@dataclass(frozen=True)
class Band:
    """One FDD operating band's downlink row of Table 5.7.3-1 (frequencies in 100 kHz)."""

    number: int
    dl_low_100khz: int
    n_offs_dl: int
    n_dl_max: int

    @property
    def dl_low_hz(self) -> float:
        """Lower edge of the downlink band (Hz)."""
        return self.dl_low_100khz * RASTER_HZ

    @property
    def dl_high_hz(self) -> float:
        """Upper edge of the downlink band (Hz): one raster step above the last EARFCN."""
        return (self.dl_low_100khz + self.n_dl_max - self.n_offs_dl + 1) * RASTER_HZ

    def contains(self, earfcn: int) -> bool:
        return self.n_offs_dl <= earfcn <= self.n_dl_max


# Band: (F_DL_low in MHz * 10, N_Offs-DL, last N_DL), TS 36.101 Table 5.7.3-1.
BANDS: dict[int, Band] = {
    number: Band(number, low, offset, last)
    for number, low, offset, last in (
        (1, 21100, 0, 599),
        (2, 19300, 600, 1199),
        (3, 18050, 1200, 1949),
        (4, 21100, 1950, 2399),
        (5, 8690, 2400, 2649),
        (7, 26200, 2750, 3449),
        (8, 9250, 3450, 3799),
        (12, 7290, 5010, 5179),
        (13, 7460, 5180, 5279),
        (14, 7580, 5280, 5379),
        (17, 7340, 5730, 5849),
        (18, 8600, 5850, 5999),
        (19, 8750, 6000, 6149),
        (20, 7910, 6150, 6449),
        (25, 19300, 8040, 8689),
        (26, 8590, 8690, 9039),
        (28, 7580, 9210, 9659),
        (66, 21100, 66436, 67335),
        (71, 6170, 68586, 68935),
    )
}


def _check_earfcn(earfcn: object) -> int:
    if isinstance(earfcn, bool) or not (
        isinstance(earfcn, int) or isinstance(earfcn, float) and earfcn.is_integer()
    ):
        raise ValueError(f"EARFCN {earfcn!r} is not an integer")
    return int(earfcn)


def band_of(earfcn: int) -> int:
    """Operating band of a downlink EARFCN; ValueError naming it if no supported band has it."""
    value = _check_earfcn(earfcn)
    for band in BANDS.values():
        if band.contains(value):
            return band.number
    raise ValueError(
        f"EARFCN {value} is not a downlink EARFCN of a supported FDD band "
        f"({', '.join(str(b) for b in BANDS)})"
    )


def downlink_frequency_hz(earfcn: int) -> float:
    """Downlink carrier frequency (Hz) of ``earfcn``."""
    band = BANDS[band_of(earfcn)]
    return (band.dl_low_100khz + int(earfcn) - band.n_offs_dl) * RASTER_HZ


def earfcn_for(frequency_hz: float, band: int | None = None) -> int:
    """Downlink EARFCN of a carrier at ``frequency_hz`` in ``band``.

    ``band=None`` picks the lowest-numbered supported band containing the frequency (e.g.
    2115 MHz -> band 1, EARFCN 50, although band 4 EARFCN 2000 is the same carrier). The
    frequency must sit on the 100 kHz raster (within 1 Hz).
    """
    if not math.isfinite(frequency_hz):
        raise ValueError(f"frequency {frequency_hz!r} Hz is not a finite number")
    steps = round(float(frequency_hz) / RASTER_HZ)
    if abs(frequency_hz - steps * RASTER_HZ) > 1.0:
        raise ValueError(f"{frequency_hz / 1e6:.4f} MHz is not on the 100 kHz channel raster")
    if band is not None and band not in BANDS:
        raise ValueError(
            f"band {band!r} is not a supported FDD band ({', '.join(map(str, BANDS))})"
        )
    candidates = [BANDS[band]] if band is not None else list(BANDS.values())
    for candidate in candidates:
        earfcn = candidate.n_offs_dl + steps - candidate.dl_low_100khz
        if candidate.contains(earfcn):
            return earfcn
    where = f"band {band}" if band is not None else "any supported FDD band"
    raise ValueError(f"{frequency_hz / 1e6:.4f} MHz is not a downlink carrier of {where}")


def check_channel(earfcn: int, bandwidth_mhz: float) -> None:
    """Raise ValueError if a ``bandwidth_mhz`` channel centred on ``earfcn`` leaves its band.

    The channel edges are the carrier +- half the channel bandwidth (TS 36.101 §5.6).
    """
    band = BANDS[band_of(earfcn)]
    centre = downlink_frequency_hz(earfcn)
    half = bandwidth_mhz * 1e6 / 2
    if centre - half < band.dl_low_hz - 1.0 or centre + half > band.dl_high_hz + 1.0:
        raise ValueError(
            f"a {bandwidth_mhz:g} MHz channel at EARFCN {int(earfcn)} ({centre / 1e6:.1f} MHz) "
            f"does not fit in band {band.number} "
            f"({band.dl_low_hz / 1e6:.1f}-{band.dl_high_hz / 1e6:.1f} MHz)"
        )
