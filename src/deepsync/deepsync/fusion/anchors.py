"""Sites as anchors: cell arrivals become per-site ranges modulo one frame.

A cell's sync code leaves its site at the site's frame timing ``T_s`` plus the code's place in
the frame, once every 10 ms, and reaches the receiver ``d / c`` later, where the receiver's clock
(bias ``b``, unknown) reads it. So for an arrival read at receiver time ``tau``::

    c * (tau - T_s(tau) - code offset)  =  d + c * b   (modulo c * 10 ms = 2998 km)

The left side, taken modulo a frame, is what :class:`SiteArrival` carries (``range_mod_m``);
the solvers unwrap it next to a prediction (:func:`unwrap_range`), since sites are at most
100 km away and the clock bias is solved for. ``T_s`` is the tower database's frame timing of
the site (offset at the database's epoch plus its drift), a PCI maps to its site through the
database (with the carrier where a PCI is reused), and co-sited sectors heard in one stack are
one measurement of one site: they share antenna, timing and propagation, so their errors are
not independent and the site's range takes the best sector's sigma, not a smaller one.

The site timing is evaluated at the receiver's reading of the time, which is off network time
by the receiver clock's bias: a site drifting at 20 ns/s is then placed 20 ns x that bias off
(0.6 m for a receiver clock 0.1 s off UTC). Keep the receiver clock on NTP or GNSS time.

Times stay exact: receiver time is counted from a ``reference_ns`` that is a whole number of
frames (so the modulo is unchanged), in float seconds only after that subtraction (a Unix time
in float64 seconds would be 200 ns coarse: 60 m).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from deepsync.frontend.templates import sync_code_offset_seconds
from deepsync.geo import LocalFrame
from deepsync.towers import TowerDatabase, TowerSite
from deepsync.types import FRAME_SECONDS, SPEED_OF_LIGHT_M_S, CellTiming, StackArrivals

FRAME_NS = round(FRAME_SECONDS * 1e9)
# A site whose drift the database does not give drifts all the same: take its oscillator as a
# typical eNodeB's, 20 ppb (TS 36.104 allows 50), so its timing's sigma grows 20 ns (6 m) each
# second from the database's epoch and fusion trusts it less as it ages.
UNKNOWN_DRIFT_STD = 20e-9
FRAME_RANGE_M = SPEED_OF_LIGHT_M_S * FRAME_SECONDS  # 2998 km: ranges are known modulo this


@dataclass(frozen=True)
class Anchor:
    """A site that can anchor a fix: its antenna in the ``map`` frame and its frame clock."""

    name: str
    position_enu: np.ndarray = field(compare=False)  # (3,) m
    timing_offset_s: float  # frame timing at the database's epoch, modulo 10 ms
    timing_drift: float  # s per s
    timing_offset_std_s: float
    timing_drift_std: float  # s per s

    def timing_s(self, seconds_since_epoch: float) -> float:
        """The site's frame timing (s, modulo a frame) ``seconds_since_epoch`` after the epoch."""
        return self.timing_offset_s + self.timing_drift * seconds_since_epoch


@dataclass(frozen=True)
class SiteArrival:
    """One site heard in one stack: where it is, when its code arrived, and the range that says.

    ``time_s`` is the receiver time of the arrival after the fusion's reference instant;
    ``range_mod_m`` = c * (arrival - site timing - code offset), modulo :data:`FRAME_RANGE_M`;
    ``std_m`` its 1-sigma: the arrival's own (``timing_std_m``, white from stack to stack), the
    site clock's uncertainty at that time (``clock_std_m``, the same error for every stack; it
    grows at ``clock_drift_std_mps``, the uncertainty of the site clock's drift) and
    the range bias multipath and NLOS may add (``bias_std_m``, the same for a while: the
    envelope's peak lags a blocked first path by up to the channel's delay spread, which no
    timing sigma knows of). A tracker takes the last two into per-site states instead.
    """

    site: str
    position_enu: np.ndarray = field(compare=False)  # (3,) m
    time_s: float
    range_mod_m: float
    timing_std_m: float
    pcis: tuple[int, ...]
    clock_std_m: float = 0.0
    amplitude: float = math.nan  # the best sector's code amplitude (V), an RSSI
    snr_db: float = math.nan
    bias_std_m: float = 0.0
    clock_drift_std_mps: float = 0.0

    @property
    def std_m(self) -> float:
        return math.hypot(self.timing_std_m, self.clock_std_m, self.bias_std_m)


def unwrap_range(range_mod_m: float, predicted_m: float) -> float:
    """The range equivalent to ``range_mod_m`` (modulo a frame) nearest to ``predicted_m``."""
    return predicted_m + (range_mod_m - predicted_m + FRAME_RANGE_M / 2) % FRAME_RANGE_M - FRAME_RANGE_M / 2


class Anchors:
    """The tower database's sites in the ``map`` frame, and the PCI -> site lookup.

    ``frame`` defaults to the database's ``origin``; a site without position or timing offset
    still names its cells (they are recognised, not used).
    """

    def __init__(self, towers: TowerDatabase, frame: LocalFrame | None = None) -> None:
        if frame is None:
            if towers.origin is None:
                raise ValueError(f"tower database {towers.name!r} has no origin: fusion needs the map frame's "
                                 "origin (add 'origin: {latitude_deg, longitude_deg, height_m}')")
            origin = towers.origin
            frame = LocalFrame(origin.latitude_deg, origin.longitude_deg, origin.height_m)
        self.towers = towers
        self.frame = frame
        self.epoch_ns = towers.timing_epoch_ns
        self.anchors = {site.name: self._anchor(site) for site in towers.sites
                        if site.has_position and site.timing_offset_us is not None}

    def _anchor(self, site: TowerSite) -> Anchor:
        height = self.frame.height_m + (site.height_m or 0.0)
        position = self.frame.geodetic_to_enu(site.latitude_deg, site.longitude_deg, height)
        return Anchor(
            name=site.name,
            position_enu=np.asarray(position, dtype=np.float64),
            timing_offset_s=site.timing_offset_us * 1e-6,
            timing_drift=(site.timing_drift_ns_per_s or 0.0) * 1e-9,
            timing_offset_std_s=(site.timing_offset_std_us or 0.0) * 1e-6,
            timing_drift_std=(UNKNOWN_DRIFT_STD if site.timing_drift_ns_per_s is None
                              else (site.timing_drift_std_ns_per_s or 0.0) * 1e-9),
        )

    def sites_of(self, cell: CellTiming) -> list[TowerSite]:
        """Database sites that carry ``cell``'s PCI (on its carrier, if the cell's is known)."""
        return [site for site in self.towers.sites
                if any(c.pci == cell.pci and (cell.earfcn is None or c.earfcn in (None, cell.earfcn))
                       for c in site.cells)]

    def site_arrivals(self, arrivals: StackArrivals, reference_ns: int, min_std_m: float = 0.0,
                      bias_std_m: float = 0.0) -> tuple[list[SiteArrival], list[str]]:
        """One :class:`SiteArrival` per anchored site heard in the stack, and a sentence for each
        cell that could not be used (unknown PCI, ambiguous, site without position or timing).

        ``reference_ns`` must be a whole number of frames (see :func:`frame_reference_ns`);
        ``min_std_m`` floors each arrival's own 1-sigma (ground truth carries 0); ``bias_std_m``
        is the multipath / NLOS range bias every arrival may carry (see :class:`SiteArrival`).
        """
        if reference_ns % FRAME_NS:
            raise ValueError(f"reference_ns {reference_ns} is not a whole number of 10 ms frames")
        metres_per_sample = SPEED_OF_LIGHT_M_S / arrivals.sample_rate
        by_site: dict[str, list[CellTiming]] = {}
        problems = []
        for cell in arrivals.cells:
            sites = self.sites_of(cell)
            carrier = "" if cell.earfcn is None else f" on EARFCN {cell.earfcn}"
            if not sites:
                problems.append(f"PCI {cell.pci}{carrier} is not in tower database {self.towers.name!r}")
            elif len(sites) > 1:
                problems.append(f"PCI {cell.pci}{carrier} is on sites {', '.join(s.name for s in sites)}: "
                                "ambiguous without the carrier")
            elif sites[0].name not in self.anchors:
                missing = "position" if not sites[0].has_position else "timing offset"
                problems.append(f"PCI {cell.pci}: site {sites[0].name!r} has no {missing} in the tower database")
            else:
                by_site.setdefault(sites[0].name, []).append(cell)
        out = []
        stamp_s = (arrivals.stamp_ns - reference_ns) * 1e-9
        since_epoch = 0.0 if self.epoch_ns is None else (reference_ns - self.epoch_ns) * 1e-9
        code_offset = sync_code_offset_seconds()
        for name, cells in by_site.items():
            anchor = self.anchors[name]
            best = min(cells, key=lambda c: c.toa_std)
            time_s = stamp_s + arrivals.seconds_after_stamp(best)
            elapsed = since_epoch + time_s
            timing = anchor.timing_s(elapsed) + code_offset
            range_mod = (SPEED_OF_LIGHT_M_S * (time_s - timing)) % FRAME_RANGE_M
            clock_std_s = math.hypot(anchor.timing_offset_std_s, anchor.timing_drift_std * elapsed)
            out.append(SiteArrival(name, anchor.position_enu, time_s, range_mod,
                                   max(best.toa_std * metres_per_sample, min_std_m), tuple(sorted(c.pci for c in cells)),
                                   SPEED_OF_LIGHT_M_S * clock_std_s, best.amplitude, best.snr_db, bias_std_m,
                                   SPEED_OF_LIGHT_M_S * anchor.timing_drift_std))
        return out, problems


def frame_reference_ns(stamp_ns: int) -> int:
    """The whole frame at or before ``stamp_ns``: a time origin that keeps ranges modulo a frame."""
    return stamp_ns - stamp_ns % FRAME_NS


def site_names(arrivals: Sequence[SiteArrival]) -> tuple[str, ...]:
    return tuple(a.site for a in arrivals)
