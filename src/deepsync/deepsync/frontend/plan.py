"""Which carriers must be simulated together, and at what rate.

The diode squares the sum of everything it hears. Two carriers' cross term lands at their
frequency difference, so it reaches the ADC band only if the gap between their occupied
bands is below the video filter's stop band; such carriers form a *cluster*, simulated as one
complex baseband whose |.|^2 then holds every in-band intermodulation product. Cross terms of
different clusters fall where the video filter has removed them (< -60 dB), so clusters are
squared separately and their detector outputs add. This assumes, as ACLR and the emission
mask require of a real eNodeB, that each transmitter keeps its emissions inside its channel:
the rect-pulse OFDM splatter of an unfiltered transmitter would reach tens of MHz out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from deepsync.frontend.channel import Emitter
from deepsync.lte.numerology import BASE_FFT, SUBCARRIER_SPACING_HZ, FftGrid, Numerology


@dataclass(frozen=True)
class Cluster(FftGrid):
    """Emitters squared together, on one FFT grid of ``fft_size`` bins of 15 kHz.

    Emitter i sits ``carrier_bins[i]`` bins from the cluster centre; ``residual_hz[i]`` is
    what whole bins cannot express (the carrier raster is 100 kHz, not 15 kHz, plus the site
    oscillator error), applied as a continuous rotation in true time.
    """

    emitter_indices: tuple[int, ...]
    center_hz: float
    fft_size: int
    carrier_bins: tuple[int, ...]
    residual_hz: tuple[float, ...]


def occupied_edges(emitter: Emitter) -> tuple[float, float]:
    half = Numerology.for_bandwidth(emitter.cell.bandwidth_mhz).occupied_bandwidth_hz / 2
    return emitter.carrier_hz - half, emitter.carrier_hz + half


def _smooth_multiplier(minimum: int) -> int:
    """Smallest integer >= minimum with no prime factor above 7 (fast FFT sizes)."""
    m = max(1, minimum)
    while True:
        rest = m
        for p in (2, 3, 5, 7):
            while rest % p == 0:
                rest //= p
        if rest == 1:
            return m
        m += 1


def plan_clusters(emitters: list[Emitter], stopband_hz: float) -> list[Cluster]:
    """Group emitters whose occupied bands come closer than ``stopband_hz``; size each grid.

    The grid rate must exceed the cluster span plus the kept band, so that |x|^2 (which
    spans +-span) aliases nowhere below ``stopband_hz``.
    """
    if not emitters:
        return []
    order = sorted(range(len(emitters)), key=lambda i: occupied_edges(emitters[i])[0])
    groups: list[list[int]] = [[order[0]]]
    high = occupied_edges(emitters[order[0]])[1]
    for i in order[1:]:
        low_i, high_i = occupied_edges(emitters[i])
        if low_i - high < stopband_hz:
            groups[-1].append(i)
            high = max(high, high_i)
        else:
            groups.append([i])
            high = high_i

    clusters = []
    for members in groups:
        members.sort()
        low = min(occupied_edges(emitters[i])[0] for i in members)
        high = max(occupied_edges(emitters[i])[1] for i in members)
        anchor = emitters[members[0]].carrier_hz
        # Centre near the middle of the span, but on the first carrier's 15 kHz grid.
        center = anchor - round((anchor - (low + high) / 2) / SUBCARRIER_SPACING_HZ) * SUBCARRIER_SPACING_HZ
        half_span = max(high - center, center - low)
        needed_rate = 2 * half_span + stopband_hz
        multiplier = _smooth_multiplier(math.ceil(needed_rate / (BASE_FFT * SUBCARRIER_SPACING_HZ)))
        offsets = np.array([emitters[i].carrier_hz - center for i in members])
        bins = np.round(offsets / SUBCARRIER_SPACING_HZ).astype(int)
        residual = offsets - bins * SUBCARRIER_SPACING_HZ
        residual += np.array([emitters[i].frequency_offset_hz for i in members])
        clusters.append(
            Cluster(
                emitter_indices=tuple(members),
                center_hz=center,
                fft_size=BASE_FFT * multiplier,
                carrier_bins=tuple(int(b) for b in bins),
                residual_hz=tuple(float(r) for r in residual),
            )
        )
    return clusters
