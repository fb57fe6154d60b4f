"""Cell search in the envelope domain: PSS timing, then SSS identity, with a CFAR threshold.

Step 1 (timing). Blind, the PSS repeats every 5 ms, so the stacked frame is folded into
half-frames and correlated (circularly, by FFT) with the envelope of each of the three PSS
symbols. With a tower database (known PCIs), each candidate's whole frame template (both
SSS+PSS codes, twice the energy of the PSS alone) is correlated instead, unless
``full_code_timing`` is off (then faster, 9 dB less sensitive). The correlation of a
noise-like input is close to Gaussian; its spread is measured robustly (median absolute
deviation) and peaks are kept above the threshold for which the chance of *any* false peak in
the stack (all lags and templates) is ``false_alarm_rate``.

Step 2 (identity). At each peak the code sits at two places in the frame, one with subframe
0's SSS and one with subframe 5's; every PCI hypothesis is scored for both orders, by the
normalised correlation of both code windows with that PCI's two templates, over a few lags.
Found cells are fitted jointly (templates, pedestals and the cross terms of codes that overlap
in time) and cancelled before the next peak is examined, so a cell next to a stronger one, or
at the same timing, shows up in the residual.

A cell found far above the threshold (``crs_cancel_z``) also has its cell-specific reference
signals cancelled: stacking does not average them away, and over long stacks a strong cell's
CRS passes for weaker cells' codes (``CellSearch._crs_model``; at the bandwidth the tower
database gives the PCI, else at whichever LTE bandwidth fits best).

With a tower database, two sectors of one site (same carrier, same timing) are also sought as
one hypothesis, their codes and the cross term between them (``deepsync.sync.sites``): at
similar power that cross term dominates the envelope, and neither sector's template matches.

Real envelopes are not as tidy as Gaussian noise: every frame-synchronised cell leaves CRS and
PBCH structure, and cells missing from the database leave codes of their own. A peak therefore
only counts as a new cell if it is a PCI not yet found, shows a PSS at its PSS position, and
(with a database) is not better explained by a PCI outside it: the database limits what is
reported, not what is believed. (The stage then asks for a cell to persist over stacks.)

What the envelope can tell (``benchmarks/detection/cell_search.py``, ``docs/design/cell_search.md``): the PSS
envelopes of N_ID2 = 1 and 2 (roots 29 and 34, complex conjugates) are identical, and the SSS
envelopes of different N_ID1 correlate up to ~0.97, so identity is carried as ranked
candidates with scores and a tower database decides which may be reported.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.fft
import scipy.special

from deepsync.frontend.templates import SyncTemplates, sync_code_offset_seconds
from deepsync.lte.cell import N_CELL_IDS
from deepsync.lte.numerology import SUPPORTED_BANDWIDTHS_MHZ
from deepsync.numeric import mad_spread, parabolic_peak
from deepsync.schema import check_settings, setting
from deepsync.sync.correlation import (correlate, correlate_every, frame_code_windows, frame_spectra, parseval_weights,
                                       template_spectra, unit_frame_parts)
from deepsync.sync.sites import SiteFit, SiteMatch, SiteNoise, SiteSearch
from deepsync.sync.stacking import HELD_FRACTION, held_fraction

PHASES = np.array([0.0, 0.5])  # sub-sample delays at which every timing template is tried
_SPREAD_STEP = 4  # every how many lags a timing correlation's noise spread is measured on


# Each bound of a count sizes a loop or an array of the search (lags tried, cells kept), far
# beyond what a stack holds or a city's cells ask.
@dataclass(frozen=True)
class SearchConfig:
    false_alarm_rate: float = setting(1e-3, help="Chance of a false timing peak anywhere in one stack.",
                                      bounds=(0.0, 0.5), open_low=True, open_high=True)
    max_cells: int = setting(8, help="Most cells searched for per stack.", unit="cells", bounds=(1, 64))
    refine_lags: int = setting(3, help="Lags scored on either side of the PSS peak in the identity step.",
                               unit="samples", bounds=(1, 64))
    keep_candidates: int = setting(8, help="Ranked PCI candidates carried per detection.", unit="PCIs",
                                   bounds=(1, 504))
    cancel_spread: int = setting(1, help="Whole-sample shifts of a template used to cancel a found code.",
                                 unit="samples", bounds=(0, 16))
    pss_confirm: float = setting(0.15, help="PSS z-score needed at a detection's PSS position, per unit of its own "
                                 "z.", bounds=(0.0, 10.0))
    open_set_tolerance: float = setting(0.02, help="How much better a PCI outside the database may score.",
                                        bounds=(0.0, 1.0))
    max_examined: int = setting(24, help="Peaks examined per stack (found cells and rejected ones).", unit="peaks",
                                bounds=(1, 1024))
    full_code_timing: bool = setting(True, help="With a tower database, time known cells by their whole codes "
                                     "(about +9 dB, slower).")
    site_hypotheses: bool = setting(True, help="With full-code timing, also search the co-sited pairs given.")
    pair_false_alarm: float = setting(1e-3, help="Chance that one sector alone passes for a co-sited pair at a "
                                      "site peak.", bounds=(0.0, 0.5), open_low=True, open_high=True)
    pair_min_gain: float = setting(0.25, help="What a co-sited pair must add to one sector's statistic, "
                                   "relatively.", bounds=(0.0, 100.0))
    crs_cancel_z: float = setting(10.0, help="A cell found this many sigmas out also has its CRS cancelled before "
                                  "weaker cells are sought: over long stacks a strong cell's CRS passes for other "
                                  "cells' codes. 0: never.", unit="sigmas", bounds=(0.0, 1000.0))
    track_lags: int = setting(1, help="Samples a confirmed cell's code may have moved from where it should be, "
                              "either way.", unit="samples", bounds=(1, 64))
    hold_by_frame: bool = setting(True, help="Hold a confirmed cell of known bandwidth whose codes a stack misses "
                                  "if its whole known frame (codes and CRS) is there.")

    def __post_init__(self) -> None:
        check_settings(self)


@dataclass(frozen=True)
class Candidate:
    pci: int
    score: float  # normalised correlation of both code windows with the PCI's templates
    lag: int  # refinement of the code start relative to the PSS peak, samples


@dataclass(frozen=True)
class CellDetection:
    """One cell's sync code in a stack."""

    frame_offset: int  # where the subframe-0 code starts within the stack's frames (0..frame-1)
    fraction: float  # sub-sample refinement of frame_offset from the identity step (samples)
    pci: int  # the best-supported PCI among those allowed
    candidates: tuple[Candidate, ...]  # ranked, best first
    peak_metric: float  # timing-statistic peak in units of its noise spread (the CFAR statistic)
    snr_db: float  # code energy / residual energy in the stacked code windows
    amplitude: float  # least-squares scale of the template (volts per unit template)
    site: SiteFit | None = None  # found with a co-sited sector whose code coincides with this one's

    @property
    def score_margin(self) -> float:
        """Score of the best candidate minus the runner-up's: how sure the identity is."""
        if len(self.candidates) < 2:
            return math.inf
        return self.candidates[0].score - self.candidates[1].score


@dataclass(frozen=True)
class ExpectedCell:
    """A cell found in earlier stacks and where its code should be in this one: what the stage
    asks the search to track (:meth:`CellSearch.search`)."""

    pci: int
    frame_offset: float  # predicted subframe-0 code start within the stack's frames (sub-sample)
    cosited_pci: int | None = None  # found together with this co-sited sector, as a pair
    held: bool = False  # confirmed: held at the tracking threshold (else the search's own, and plausibility)


_SINGLE, _SITE = 0, 1  # rows of _SearchState.given_up


@dataclass(frozen=True)
class _KnownFrame:
    """A known cell's whole frame (``SyncTemplates.frame_template``) as the hold tests it."""

    spectra: np.ndarray  # conjugate spectra of the unit-norm template at each of PHASES
    norm: float  # the template's norm (volts per unit RE power): a fit's z x spread / norm is its amplitude
    code_share: float  # the codes' share of its energy per code sample: z^2 x this is the codes' SNR


@dataclass
class _SearchState:
    """One stack's search in progress."""

    centred: np.ndarray  # the stacked frame, zero-mean
    residual: np.ndarray  # what remains once the detections so far are cancelled
    crs: np.ndarray  # the fitted CRS of the strongest detections, cancelled with them
    period: int  # of the timing statistic's lag axis (a frame, or a half-frame blind)
    correlations: np.ndarray | None  # single-template timing correlations of the residual (None: tracking only)
    z: np.ndarray | None  # and their z-scores (tracking only: ``CellSearch._timing_block`` where needed)
    spreads: np.ndarray  # their noise spreads, measured on the first pass
    pss_z: np.ndarray | None  # PSS z-scores of the residual (plausibility check; None: not needed)
    pss_spreads: np.ndarray | None
    threshold: float  # CFAR threshold, in sigmas
    given_up: np.ndarray  # (2, period): lags whose single / site peak could not be explained
    near_new: np.ndarray  # (period,) single lags overlapping cells found since the last cancellation
    site_noise: SiteNoise | None
    site_z: np.ndarray | None = None  # the pairs' statistic, once the single peaks are exhausted
    site_pairs: np.ndarray | None = None  # the pairs (indices) site_z tests: those with no sector found
    detections: list[CellDetection] = field(default_factory=list)
    cancelled: int = 0  # how many of the detections the residual has cancelled


def cfar_threshold(false_alarm_rate: float, tests: int) -> float:
    """Gaussian threshold (in sigmas) so that ``tests`` one-sided tests give one false alarm
    with probability ``false_alarm_rate`` (independent tests: conservative for correlated lags)."""
    return float(-scipy.special.ndtri(false_alarm_rate / tests))  # the normal's isf, without its overhead


class CellSearch:
    """Searches stacks for cells; ``allowed_pcis`` restricts identities (tower database),
    ``cosited_pairs`` (PCIs of one site and carrier, see ``TowerDatabase.cosited_pairs``) adds
    the site hypothesis of ``deepsync.sync.sites`` to the known-PCI search, and ``bandwidths``
    (PCI -> MHz, ``TowerDatabase.bandwidths``) says at which bandwidth a strong cell's CRS is
    modelled."""

    def __init__(self, templates: SyncTemplates, config: SearchConfig | None = None,
                 allowed_pcis: list[int] | None = None, cosited_pairs: list[tuple[int, int]] | None = None,
                 bandwidths: dict[int, float] | None = None) -> None:
        self.templates = templates
        self.config = config or SearchConfig()
        self.bandwidths = dict(bandwidths or {})
        self.allowed = np.arange(N_CELL_IDS) if allowed_pcis is None else np.unique(allowed_pcis)
        if self.allowed.size == 0 or self.allowed.min() < 0 or self.allowed.max() >= N_CELL_IDS:
            raise ValueError("allowed_pcis must be PCIs in 0..503")
        # template spectra by kind and length (CRS: PCI, bandwidth), known frames by PCI
        self._cache: dict[tuple, np.ndarray | _KnownFrame] = {}
        self.sites = (SiteSearch(templates, cosited_pairs, self.allowed, PHASES)
                      if cosited_pairs and self.full_code_timing and self.config.site_hypotheses else None)

    @cached_property
    def _code_templates(self) -> tuple[np.ndarray, np.ndarray]:
        """(2P, L) zero-mean templates of the allowed PCIs, subframe 0's rows then subframe
        5's, and (P,) the energy of each PCI's two."""
        full = self.templates.all()[self.allowed]
        centred = full - full.mean(axis=2, keepdims=True)
        return np.concatenate([centred[:, 0], centred[:, 1]]), np.sum(centred**2, axis=(1, 2))

    @property
    def known_pcis(self) -> bool:
        """True when identities are restricted (tower database)."""
        return len(self.allowed) < N_CELL_IDS

    @property
    def full_code_timing(self) -> bool:
        """Time by each known PCI's whole frame template rather than by the three PSS."""
        return self.known_pcis and self.config.full_code_timing

    def _pss_spectra(self, half: int) -> np.ndarray:
        """(3 x phases, half/2+1) conjugate spectra of the unit-norm, zero-mean PSS templates."""
        key = ("pss", half)
        if key not in self._cache:
            shapes = np.array([self.templates.pss(u, PHASES) for u in range(3)]).reshape(3 * len(PHASES), -1)
            shapes -= shapes.mean(axis=1, keepdims=True)
            self._cache[key] = template_spectra(shapes / np.linalg.norm(shapes, axis=1, keepdims=True), half)
        return self._cache[key]

    @cached_property
    def _frame_parts(self) -> np.ndarray:
        """(P x phases, 2, L) each allowed PCI's frame template as its two codes: the zero-mean
        subframe-0 code (at 0) and subframe-5 code (half a frame later), unit norm together."""
        parts = np.array([[self.templates.template(int(pci), subframe, PHASES) for subframe in (0, 5)]
                          for pci in self.allowed])  # (P, 2, phases, L)
        return unit_frame_parts(np.swapaxes(parts, 1, 2)).reshape(-1, 2, self.templates.length)

    def _frame_spectra(self, frame: int) -> np.ndarray:
        """(P x phases, frame/2+1) conjugate spectra of the frame templates (``_frame_parts``)."""
        key = ("frame", frame)
        if key not in self._cache:
            self._cache[key] = frame_spectra(self._frame_parts, frame)
        return self._cache[key]

    def pss_correlations(self, centred: np.ndarray) -> np.ndarray:
        """(3 x phases, half) PSS correlations of the half-frame fold (lag = PSS start)."""
        half = len(centred) // 2
        folded = centred[:half] + centred[half : 2 * half]
        return correlate(scipy.fft.rfft(folded), self._pss_spectra(half), half)

    def pss_statistic(self, centred: np.ndarray, spreads: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(3 x phases, half) PSS correlation z-scores of the half-frame fold, and their spreads."""
        return _normalised(self.pss_correlations(centred), spreads)

    def _plausible(self, residual: np.ndarray, found: CellDetection, detections: list[CellDetection],
                   pss_z: np.ndarray) -> bool:
        """Is a new detection a cell, rather than what remains of stronger ones?

        It must be a PCI not found yet (a cell has one code per half-frame); its PSS must show at
        its PSS position in the residual, in proportion to its strength (a real code gives
        0.25-0.6 of its whole-code z; a template lined up with other structure, often less);
        and, when the PCIs are restricted to a tower database, no PCI outside it may explain
        the code clearly better: that would be a cell missing from the database, not ours.
        """
        if found.amplitude <= 0 or any(d.pci == found.pci for d in detections):
            return False
        half = len(residual) // 2
        lag = (found.frame_offset + self.templates.pss_offset + np.arange(-2, 3)) % half
        if pss_z[np.ix_(_pss_rows(found.pci), lag)].max() < self.config.pss_confirm * found.peak_metric:
            return False
        if self.known_pcis:
            rivals = self._open_set_search._identify(residual, found.frame_offset % half, found.peak_metric)
            if rivals.candidates[0].score - found.candidates[0].score > self.config.open_set_tolerance:
                return False
        return True

    @cached_property
    def _open_set_search(self) -> CellSearch:
        """The same search over all 504 PCIs, to check a database PCI against everyone else."""
        return CellSearch(self.templates, self.config)

    def timing_correlations(self, centred: np.ndarray, spectrum: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        """Correlations over candidate code positions and the period of the lag axis. Blind:
        the three PSS templates against the half-frame fold (lag = PSS start, mod a half-frame).
        Known PCIs: each PCI's full frame template (lag = subframe-0 code start, mod a frame),
        twice the code energy. Every template is also tried half a sample later: the envelope
        has energy near Nyquist, and a code between two samples would otherwise lose up to 3 dB
        of correlation. (Divided by their noise spreads, they are the timing statistic, in
        sigmas.) ``spectrum``: the rfft of ``centred``, if the caller has it."""
        if not self.full_code_timing:
            return self.pss_correlations(centred), len(centred) // 2
        period = len(centred)
        spectrum = scipy.fft.rfft(centred) if spectrum is None else spectrum
        return correlate(spectrum, self._frame_spectra(period), period), period

    def _timing_block(self, state: _SearchState, rows: np.ndarray, lags: np.ndarray) -> np.ndarray:
        """(rows, lags) timing statistic of the residual: from the whole statistic where the pass
        has it, else (a stack that only tracks) the frame templates' dot products with the
        residual's code windows at those lags, over the first pass's spreads."""
        if state.z is not None:
            return state.z[np.ix_(rows, lags)]
        windows = frame_code_windows(state.residual, lags, self.templates.length)  # (lags, 2, L)
        return _over_spreads(np.einsum("rsl,nsl->rn", self._frame_parts[rows], windows), state.spreads[rows])

    def _tracked_rows(self, expected: Sequence[ExpectedCell]) -> np.ndarray | None:
        """The timing rows a stack that only tracks ``expected`` needs (None: all of them)."""
        if not self.full_code_timing:
            return None  # blind: three PSS templates, nothing to spare
        pcis = {e.pci for e in expected} | {e.cosited_pci for e in expected if e.cosited_pci is not None}
        if self.sites is not None:  # a tentative sector's partners: its pairs are tried as the search tries them
            pcis |= {pci for e in expected if not e.held
                     for k in self.sites.pairs_with(e.pci) for pci in self.sites.pairs[k]}
        index = np.flatnonzero(np.isin(self.allowed, list(pcis)))
        return (index[:, None] * len(PHASES) + np.arange(len(PHASES))).ravel()

    def search(self, stacked: np.ndarray, expected: Sequence[ExpectedCell] = (),
               discover: bool = True) -> list[CellDetection]:
        """Cells in one stacked frame (the mean of a stack's rows): the ``expected`` ones that
        are still there (:meth:`_track`), then, if ``discover``, new ones, strongest first.

        Peaks of the single templates are examined first, strongest first
        (:meth:`_single_pass`). Found cells are cancelled, and the statistics recomputed on the
        residual, before the strongest peak left overlaps one of them (or none is left): a
        peak clear of them is the same on the residual (cells apart in time do not mix, and
        their joint fit is their separate fits), so several cells often cost one
        recomputation, and a peak next to a found cell is examined on the residual. When no
        single peak passes the threshold, the co-sited pairs' statistic
        (if any) is computed on what remains, and a pair found there is cancelled the same way
        (:meth:`_site_pass`), after which single peaks are looked at again. The threshold
        counts both kinds of test.

        Without ``discover`` only the expected cells are looked for, at their few lags: only
        their templates' noise spreads are measured (on every 4th lag, by a transform a quarter
        of a frame long), their statistic is the templates' dot products with the residual at
        those lags, and a cancellation recomputes no correlation."""
        if not np.all(np.isfinite(stacked)):
            raise ValueError("stacked frame contains NaN or inf")
        centred = stacked - stacked.mean()
        if held_fraction(centred) > HELD_FRACTION:
            return []  # (mostly) constant input: no noise level to set a threshold by
        if discover:
            state = self._start(centred)
        else:  # the PSS check is only needed for cells not confirmed yet
            state = self._start(centred, self._tracked_rows(expected), pss=not all(e.held for e in expected))
        self._track(state, expected, discover)
        examined = 0
        while discover and examined < self.config.max_examined and len(state.detections) < self.config.max_cells:
            before = len(state.detections)
            peak = self._strongest_single(state)
            if state.cancelled < before and (peak is None or state.near_new[peak]):
                self._cancel(state)  # the peak may be what is left of a found cell, or a cell under it
                continue
            if peak is not None:
                kind, added = _SINGLE, self._single_pass(state, peak)
            else:
                site = self._site_pass(state)
                if site is None:
                    break
                kind, (peak, added) = _SITE, site
            examined += 1
            if not added:
                state.given_up[kind, (peak + np.arange(-2, 3)) % state.period] = True
            elif kind == _SITE:
                self._cancel(state)
            else:
                self._mark_new(state, before)
        if self.config.hold_by_frame:
            self._hold_by_frame(state, expected)
        return state.detections

    def _hold_by_frame(self, state: _SearchState, expected: Sequence[ExpectedCell]) -> None:
        """Confirmed cells of known bandwidth that their codes no longer show: held if their whole
        known frame (codes and CRS, ``SyncTemplates.frame_template``) is where their code
        should be, at the tracking threshold over the same ``track_lags`` and phases.

        The CRS adds 40 symbols per frame to the codes' 4: at 10 MHz about 8 dB of SNR for a
        tracked cell at the same false-alarm rate (``benchmarks/detection/full_frame_template.py``), the
        difference between hearing 3 sites per stack or 5 on the dense walk
        (``benchmarks/detection/full_frame_tracking.py``). Only for tracked cells: the comb of the CRS
        repeats the template's fit every 21.3 samples, so a search over all positions would
        lock a period off; a track knows the period. Each cell is tested on what the search
        left of the stack (codes found, and strong cells' CRS, cancelled), its noise the
        robust spread of that correlation over the frame."""
        missing = [e for e in expected if e.held and e.pci in self.bandwidths
                   and all(d.pci != e.pci for d in state.detections)]
        if not missing:
            return
        frame = len(state.residual)
        spectrum = scipy.fft.rfft(state.residual)
        for cell in missing:
            if len(state.detections) >= self.config.max_cells:
                return
            known = self._known_frame(cell.pci, frame)
            correlations = correlate(spectrum, known.spectra, frame)
            spread = mad_spread(correlations[:, ::_SPREAD_STEP], centre=0.0)  # the lags _normalised takes
            lags = self._tracked_lags(cell) % frame
            block = correlations[:, lags] / spread  # (PHASES, lags)
            if block.max() < cfar_threshold(self.config.false_alarm_rate, block.size):
                continue
            # interleaved by phase: code starts every 1 / len(PHASES) sample, in time order
            fine = block.T.ravel()
            best = int(np.argmax(fine))
            start = lags[0] + (best + parabolic_peak(fine, best)) / len(PHASES)
            z = float(block.max())
            state.detections.append(CellDetection(
                frame_offset=int(math.floor(start)) % frame, fraction=start - math.floor(start), pci=cell.pci,
                candidates=(), peak_metric=z, snr_db=10 * math.log10(z * z * known.code_share),
                amplitude=float(fine[best]) * spread / known.norm))

    def _known_frame(self, pci: int, frame: int) -> _KnownFrame:
        """A PCI's whole known frame at the search's ``PHASES``, as the hold tests it. Cached."""
        key = ("frame", pci)
        if key not in self._cache:
            full = self.templates.frame_template(pci, self.bandwidths[pci], PHASES)
            norm = float(np.linalg.norm(full[0]))
            codes = sum(float(np.sum((t - t.mean()) ** 2))
                        for t in (self.templates.template(pci, subframe, 0.0) for subframe in (0, 5)))
            self._cache[key] = _KnownFrame(template_spectra(full / norm, frame), norm,
                                           codes / norm**2 / (2 * self.templates.length))
        return self._cache[key]

    def _start(self, centred: np.ndarray, rows: np.ndarray | None = None, pss: bool = True) -> _SearchState:
        """The first pass's statistics, noise spreads and CFAR threshold of a stack (the
        threshold of a full search, whichever ``rows`` are computed); the PSS statistic of
        known-PCI timing if ``pss``. With ``rows`` (a stack that only tracks: their few
        lags are all it tests), the noise spreads of those rows alone, and the statistic is
        taken where it is needed (``_timing_block``)."""
        spectrum = scipy.fft.rfft(centred)  # the correlations' and the pairs' noise's
        if rows is None:
            correlations, period = self.timing_correlations(centred, spectrum)
            z, spreads = _normalised(correlations, None)
            single, step = correlations, 1
        else:  # only the noise spreads, from the lags they are measured on: one transform a quarter long
            period = len(centred)
            spectra = self._frame_spectra(period)
            step = _SPREAD_STEP if period % _SPREAD_STEP == 0 else 1
            single = np.zeros((len(spectra), period // step), dtype=np.float32)  # by row, as SiteNoise gathers pairs
            single[rows] = correlate_every(spectrum, spectra[rows], period, step)
            spreads = np.zeros(len(spectra))
            spreads[rows] = mad_spread(single[rows, :: _SPREAD_STEP // step], axis=1, centre=0.0)
            correlations = z = None
        if not self.full_code_timing:
            pss_z, pss_spreads = z, spreads
        else:
            pss_z, pss_spreads = self.pss_statistic(centred) if pss else (None, None)
        tests = len(spreads) * period + (0 if self.sites is None else self.sites.rows * period)
        return _SearchState(
            centred=centred, residual=centred, crs=np.zeros(len(centred)), period=period,
            correlations=correlations, z=z, spreads=spreads, pss_z=pss_z, pss_spreads=pss_spreads,
            threshold=cfar_threshold(self.config.false_alarm_rate, tests), given_up=np.zeros((2, period), dtype=bool),
            near_new=np.zeros(period, dtype=bool),
            site_noise=None if self.sites is None else SiteNoise(self.sites, spectrum, single, step),
        )

    def _mark_new(self, state: _SearchState, before: int) -> None:
        """Lags that overlap the detections found since index ``before``: a peak there waits
        for the residual."""
        for d in state.detections[before:]:
            state.near_new[self._overlapping_lags(d.frame_offset, state.period)] = True

    def _track(self, state: _SearchState, expected: Sequence[ExpectedCell], discover: bool) -> None:
        """Look for each expected cell where its code should be: the confirmed ones first, in
        the order given (strongest first is best: weaker ones are then seen on the residual).

        A confirmed (held) cell is looked for within ``track_lags`` of where its code should be,
        and only has to beat the false-alarm rate over those few lags and its own templates, not
        over a whole frame of them: about 3.6 sigmas instead of 6, so a cell once found is kept
        through fades that a new one could not be found in. A cell not yet confirmed must pass
        the full search's threshold and plausibility checks, on the residual of the cells
        found (and the CRS of the strong ones), so that tracking confirms no more than searching
        every stack would. A co-sited pair is tracked as a pair, and as two sectors if the pair
        no longer explains its codes; with ``discover``, a sector held alone has its pairs tried
        too, as the search tries a sector found alone (else one held alone would keep its
        partner from ever being found)."""
        for cell in sorted(expected, key=lambda e: not e.held):  # stable: the given order within each
            if len(state.detections) >= self.config.max_cells:
                return
            if any(d.pci == cell.pci for d in state.detections):
                continue  # found with its co-sited partner
            lags = self._tracked_lags(cell)
            overlaps = state.near_new[self._timing_lags(lags, state.period)].any()
            if state.cancelled < len(state.detections) and (overlaps or not cell.held):
                self._cancel(state)
            before = len(state.detections)
            if not self._track_pair(state, cell, lags):
                self._track_single(state, cell, lags, discover)
            self._mark_new(state, before)

    def _tracked_lags(self, cell: ExpectedCell) -> np.ndarray:
        """The whole-sample code starts an expected cell is looked for at: ``track_lags`` either
        side of where it should be."""
        return round(cell.frame_offset) + np.arange(-self.config.track_lags, self.config.track_lags + 1)

    def _timing_lags(self, code_starts: np.ndarray, period: int) -> np.ndarray:
        """Lags of the timing statistic at which a code starting at ``code_starts`` peaks."""
        return (code_starts + (0 if self.full_code_timing else self.templates.pss_offset)) % period

    def _timing_rows(self, pci: int) -> np.ndarray:
        """Rows of the timing statistic that time ``pci``: its frame templates, or blind, its PSS."""
        if not self.full_code_timing:
            return _pss_rows(pci)
        return int(np.searchsorted(self.allowed, pci)) * len(PHASES) + np.arange(len(PHASES))

    def _track_single(self, state: _SearchState, cell: ExpectedCell, lags: np.ndarray, pairs: bool) -> None:
        """One expected cell, by its own timing templates at ``lags`` (code starts); a held
        cell's code is placed within them (and its co-sited pairs tried if ``pairs``), a
        tentative one's as the search places a peak's."""
        if cell.pci not in self.allowed:
            return
        block = self._timing_block(state, self._timing_rows(cell.pci), self._timing_lags(lags, state.period))
        best = block.max(axis=0)
        peak = int(np.argmax(best))
        if cell.held:
            if best[peak] < cfar_threshold(self.config.false_alarm_rate, block.size):
                return
            centre = int(lags[len(lags) // 2]) % len(state.centred)
            self._admit(state, self._identify(state.residual, centre, float(best[peak]), cell.pci,
                                              self.config.track_lags), held=True, pairs=pairs)
        elif best[peak] >= state.threshold:
            found = self._identify(state.residual, int(lags[peak]) % len(state.centred), float(best[peak]))
            if found.pci == cell.pci:
                self._admit(state, found)

    def _track_pair(self, state: _SearchState, cell: ExpectedCell, lags: np.ndarray) -> bool:
        """An expected co-sited pair, by the site hypothesis at ``lags``: whether it was added."""
        if cell.cosited_pci is None or self.sites is None:
            return False
        pair = self.sites.pair_index(cell.pci, cell.cosited_pci)
        if pair is None or any(d.pci == cell.cosited_pci for d in state.detections):
            return False
        pairs = np.array([pair])
        match = self.sites.identify(state.residual, int(lags[len(lags) // 2]) % len(state.centred), pairs,
                                    state.site_noise.covariances(pairs), self.config.pair_false_alarm,
                                    self.config.pair_min_gain, reach=self.config.track_lags)
        if match is None:
            return False
        tests = len(lags) * len(PHASES)
        threshold = cfar_threshold(self.config.false_alarm_rate, tests) if cell.held else state.threshold
        return match.z >= threshold and self._add_site(match, match.z, state.detections)

    def _strongest_single(self, state: _SearchState) -> int | None:
        """Lag of the strongest single-template peak not given up, if it passes the threshold."""
        best = np.where(state.given_up[_SINGLE], -np.inf, state.z.max(axis=0))
        peak = int(np.argmax(best))
        return peak if best[peak] >= state.threshold else None

    def _single_pass(self, state: _SearchState, peak: int) -> bool:
        """Examine a single-template peak: whether a cell, or the co-sited pair it belongs to,
        was added."""
        # (a template half a sample late peaks at the same integer lag, so the lag stands)
        half = len(state.centred) // 2
        code_start = (peak - (0 if self.full_code_timing else self.templates.pss_offset)) % half
        return self._admit(state, self._identify(state.residual, code_start, float(state.z[:, peak].max())))

    def _admit(self, state: _SearchState, found: CellDetection, held: bool = False, pairs: bool = True) -> bool:
        """Add a detection, or (if ``pairs``) the co-sited pair it belongs to if its partner's
        code is there too: whether anything was added. A new cell must be plausible; a held one
        only a PCI not found yet, with a positive amplitude."""
        match = None if state.site_noise is None or not pairs else self._pair_of(state.residual, found,
                                                                                  state.site_noise)
        if match is not None:  # a sector whose co-sited partner is there too
            return self._add_site(match, found.peak_metric, state.detections)
        if held:
            plausible = found.amplitude > 0 and all(d.pci != found.pci for d in state.detections)
        else:
            plausible = self._plausible(state.residual, found, state.detections, state.pss_z)
        if plausible:
            state.detections.append(found)
        return plausible

    def _site_pass(self, state: _SearchState) -> tuple[int, bool] | None:
        """Examine the strongest co-sited pair peak of what the single templates left: (its
        lag, whether the pair was added); None without pairs or above-threshold peaks. The
        pairs' statistic, the costliest part of the search, is computed once per stack."""
        if self.sites is None:
            return None
        if state.site_z is None:
            # a pair with a sector found already cannot be added (``_add_site``): only the others
            # are hypotheses; once a site is heard, that spares most of the stack's costliest work
            found = {d.pci for d in state.detections}
            state.site_pairs = np.array([k for k, pair in enumerate(self.sites.pairs) if not found & set(pair)],
                                        dtype=int)
            if not state.site_pairs.size:
                return None
            correlations = self.sites.correlations(scipy.fft.rfft(state.residual), state.correlations,
                                                   state.site_pairs)
            covariances = state.site_noise.covariances(state.site_pairs, correlations)
            state.site_z = self.sites.statistic(correlations, covariances)
        best = np.where(state.given_up[_SITE], -np.inf, state.site_z)
        peak = int(np.argmax(best))
        if best[peak] < state.threshold:
            return None
        match = self.sites.identify(state.residual, peak, state.site_pairs,
                                    state.site_noise.covariances(state.site_pairs),
                                    self.config.pair_false_alarm, self.config.pair_min_gain)
        return peak, match is not None and self._add_site(match, float(best[peak]), state.detections)

    def _cancel(self, state: _SearchState) -> None:
        """Cancel every detection from the stack, and the CRS of the strong ones, and recompute
        the statistics on the residual (with the first pass's noise spreads)."""
        new = state.detections[state.cancelled :]
        state.cancelled = len(state.detections)
        state.near_new[:] = False
        strong = [d for d in new if self.config.crs_cancel_z and d.peak_metric >= self.config.crs_cancel_z]
        for d in strong:
            state.crs = state.crs + self._crs_model(state.residual, d)
        if strong:
            state.site_z = None  # the CRS spans the whole frame: the pairs' statistic is computed again
        known = state.centred - state.crs
        state.residual = known - self._fit(known, state.detections)
        if state.z is not None:  # (tracking only, the statistic is taken from the residual where needed)
            state.correlations, _ = self.timing_correlations(state.residual)
            state.z, _ = _normalised(state.correlations, state.spreads)
        if not self.full_code_timing:
            state.pss_z = state.z
        elif state.pss_spreads is not None:
            state.pss_z = self.pss_statistic(state.residual, state.pss_spreads)[0]
        if state.site_z is not None:
            # cancelling changes the residual only around the new codes: the site rows stay
            # valid elsewhere and are not recomputed
            for d in new:
                state.given_up[_SITE, self._overlapping_lags(d.frame_offset, state.period)] = True

    def _crs_model(self, signal: np.ndarray, found: CellDetection) -> np.ndarray:
        """A strong cell's CRS in the stacked frame, fitted to ``signal``.

        Stacking averages the data away but not the CRS: over long stacks a strong cell's CRS
        stands out as far as the codes of weak cells do, at places fixed to its frame timing
        (its symbols 0 and 4 of each slot), and some database PCI's code template always
        matches part of it, in every stack: false cells that persist, which confirmation cannot
        remove. Its frame timing is known from its code; its bandwidth is the one the tower
        database gives, or, where it gives none, each LTE bandwidth is tried and the one that
        explains the most energy kept (the fits by Parseval, on the spectra). Per-symbol
        pedestals are left out (the template is zero-mean per symbol)."""
        frame = len(signal)
        start = found.frame_offset + found.fraction - sync_code_offset_seconds() * self.templates.sample_rate
        delay = np.exp(-2j * np.pi * scipy.fft.rfftfreq(frame) * start)
        weights = parseval_weights(frame)
        spectrum = np.conj(scipy.fft.rfft(signal)) * weights
        best, fitted = 0.0, None
        known = self.bandwidths.get(found.pci)
        for bandwidth in SUPPORTED_BANDWIDTHS_MHZ if known is None else (known,):
            key = ("crs", found.pci, round(10 * bandwidth))
            if key not in self._cache:
                self._cache[key] = scipy.fft.rfft(self.templates.crs_envelope(found.pci, bandwidth))
            shifted = self._cache[key] * delay
            dot = float(np.real(spectrum @ shifted))
            energy = float(np.abs(shifted) ** 2 @ weights)
            if dot > 0 and dot * dot / energy > best:
                best, fitted = dot * dot / energy, dot / energy * shifted
        return np.zeros(frame) if fitted is None else scipy.fft.irfft(fitted, frame)

    def _overlapping_lags(self, code_start: int, period: int) -> np.ndarray:
        """Lags at which a timing template overlaps either code of a cell whose subframe-0 code
        starts at ``code_start`` (with the cancellation's spread): a frame template at either
        code, or blind, a PSS template in the half-frame fold, lag = PSS start."""
        reach = self.templates.length + self.config.cancel_spread + 1
        near = code_start + np.arange(-reach, reach + 1)
        if not self.full_code_timing:
            return (near + self.templates.pss_offset) % period
        return np.concatenate([near, near + period // 2]) % period

    def _pair_of(self, residual: np.ndarray, found: CellDetection, noise: SiteNoise) -> SiteMatch | None:
        """The co-sited pair a single detection belongs to, if its partner's code is there too
        (strong pairs often raise a sector's own template first)."""
        pairs = self.sites.pairs_with(found.pci)
        if not pairs.size or found.amplitude <= 0:
            return None
        return self.sites.identify(residual, found.frame_offset, pairs, noise.covariances(pairs),
                                   self.config.pair_false_alarm, self.config.pair_min_gain)

    def _add_site(self, match: SiteMatch, peak_metric: float, detections: list[CellDetection]) -> bool:
        """Both sectors of a pair become detections carrying the pair's fit; False if either
        was found already (what is left of a cancelled cell is not its pair)."""
        if any(d.pci in match.fit.pcis for d in detections):
            return False
        candidates: list[Candidate] = []
        for pair, score, lag in match.ranked:
            candidates += [Candidate(pci, score, lag) for pci in pair if pci not in {c.pci for c in candidates}]
        for own, pci in enumerate(match.fit.pcis):
            ranked = [c for c in candidates if c.pci == pci] + [c for c in candidates if c.pci != pci]
            detections.append(CellDetection(
                frame_offset=match.frame_offset,
                fraction=match.fraction,
                pci=pci,
                candidates=tuple(ranked[: self.config.keep_candidates]),
                peak_metric=peak_metric,
                snr_db=match.snr_db,
                amplitude=match.fit.coefficients[own],
                site=match.fit,
            ))
        return True

    def _fit(self, centred: np.ndarray, detections: list[CellDetection]) -> np.ndarray:
        """Joint least-squares model of every detected cell's codes, for cancelling them.

        Per cell: its template at the fitted delay and a few whole-sample shifts of it
        (multipath and filter mismatch smear a real code over a few samples), with one
        amplitude for both of its codes, plus a level under each code (the load-dependent
        pedestal). Per pair of codes that overlap in time: the two shapes of their square-law
        cross term (``SyncTemplates.cross_terms``), which a stable relative phase (sectors of
        a site, a synchronised network) keeps in every frame. What remains of strong cells
        then does not pass for more cells next to them.
        """
        frame, half, length = len(centred), len(centred) // 2, self.templates.length
        spread = self.config.cancel_spread
        columns: list[list[tuple[np.ndarray, int]]] = []  # each column: shapes placed at starts (mod frame)

        for d in detections:
            # row k: the code moved by k - spread whole samples within a padding of spread either
            # side (windows, latest first, over the code padded by twice the spread: no copies)
            moved = []
            for sf in (0, 5):
                padded = np.zeros(length + 4 * spread)
                padded[2 * spread : 2 * spread + length] = self.templates.shifted(d.pci, sf, d.fraction)
                moved.append(np.lib.stride_tricks.sliding_window_view(padded, length + 2 * spread)[::-1])
            columns += [[(moved[0][k], d.frame_offset - spread), (moved[1][k], d.frame_offset + half - spread)]
                        for k in range(2 * spread + 1)]
            pedestal = np.ones(length + 2 * spread)
            columns += [[(pedestal, start - spread)] for start in (d.frame_offset, d.frame_offset + half)]
        for i, a in enumerate(detections):
            for b in detections[i + 1 :]:
                gap = (b.frame_offset + b.fraction - a.frame_offset - a.fraction + half) % frame - half
                if abs(gap) >= length:
                    continue  # codes apart in time do not mix (and the other subframe's are a half-frame off)
                if gap == 0:  # co-sited sectors found together: cached shapes
                    shapes = [self.templates.shifted_cross_terms(a.pci, b.pci, sf, a.fraction) for sf in (0, 5)]
                    columns += [[(shapes[0][k], a.frame_offset), (shapes[1][k], a.frame_offset + half)] for k in range(2)]
                    continue
                origin = a.frame_offset + min(0, math.floor(gap)) - spread
                span = length + abs(math.floor(gap)) + 2 * spread + 1
                delay_a = a.frame_offset + a.fraction - origin
                shapes = [self.templates.cross_terms(a.pci, b.pci, sf, delay_a, delay_a + gap, span) for sf in (0, 5)]
                columns += [[(shapes[0][k], origin), (shapes[1][k], origin + half)] for k in range(2)]
        # the codes cover a few hundred samples of the frame: the fit is solved on those alone
        # (a cell's shifts share their places: each place is indexed once)
        places = {(start % frame, len(shape)) for column in columns for shape, start in column}
        spans = {place: (place[0] + np.arange(place[1])) % frame for place in places}
        rows = np.unique(np.concatenate(list(spans.values())))
        at = {place: np.searchsorted(rows, span) for place, span in spans.items()}
        basis = np.zeros((len(rows), len(columns)))
        for j, column in enumerate(columns):
            for shape, start in column:
                basis[at[start % frame, len(shape)], j] += shape
        coefficients, *_ = np.linalg.lstsq(basis, centred[rows], rcond=None)
        fitted = np.zeros(frame)
        fitted[rows] = basis @ coefficients
        return fitted

    def _windows(self, centred: np.ndarray, start: int, lags: np.ndarray, length: int) -> np.ndarray:
        """(len(lags), length) zero-mean windows of the circular signal starting at start + lag."""
        index = (start + lags[:, None] + np.arange(length)[None, :]) % len(centred)
        windows = centred[index]
        return windows - windows.mean(axis=1, keepdims=True)

    def _identify(self, centred: np.ndarray, code_start: int, peak_metric: float,
                  pci: int | None = None, reach: int | None = None) -> CellDetection:
        """The PCI, subframe order and sub-sample position of the code starting within
        ``reach`` (default ``refine_lags``) of ``code_start`` (mod a half-frame), scored over
        every allowed PCI; with ``pci`` (a tracked cell), the position and scale are that
        PCI's, whichever ranks first."""
        cfg = self.config
        frame, half = len(centred), len(centred) // 2
        codes, template_energy = self._code_templates
        pcis, length = len(template_energy), codes.shape[1]
        reach = cfg.refine_lags if reach is None else reach
        lags = np.arange(-reach, reach + 1)
        first = self._windows(centred, code_start, lags, length)  # the code at code_start
        second = self._windows(centred, code_start + half, lags, length)  # and half a frame on
        energy = np.sum(first**2, axis=1) + np.sum(second**2, axis=1)  # (lags,)
        products = codes @ np.concatenate([first, second]).T  # (2P, 2 lags): (sf0, sf5) x (first, second)
        t0_first, t0_second = products[:pcis, : len(lags)], products[:pcis, len(lags) :]
        t5_first, t5_second = products[pcis:, : len(lags)], products[pcis:, len(lags) :]
        # order 0: subframe 0's code at code_start; order 1: subframe 5's there
        dots = np.stack([t0_first + t5_second, t5_first + t0_second])  # (2, P, lags)
        rho = dots / np.sqrt(template_energy[None, :, None] * energy[None, None, :])
        if pci is None:
            order, best, lag_i = np.unravel_index(np.argmax(rho), rho.shape)
        else:
            best = int(np.searchsorted(self.allowed, pci))
            order, lag_i = np.unravel_index(np.argmax(rho[:, best]), (2, len(lags)))
        per_pci = rho.max(axis=(0, 2))
        ranked = np.argsort(per_pci)[::-1][: cfg.keep_candidates]
        candidates = tuple(
            Candidate(int(self.allowed[i]), float(per_pci[i]), int(lags[rho[:, i].max(axis=0).argmax()]))
            for i in ranked
        )
        fraction = parabolic_peak(rho[order, best], lag_i) if 0 < lag_i < len(lags) - 1 else 0.0
        dot = dots[order, best, lag_i]
        amplitude = dot / template_energy[best]
        explained = amplitude * dot
        unexplained = energy[lag_i] - explained
        snr_db = 10 * math.log10(explained / unexplained) if unexplained > 0 and explained > 0 else -math.inf
        sf0_at = code_start + lags[lag_i] + (0 if order == 0 else half)
        return CellDetection(
            frame_offset=int(sf0_at % frame),
            fraction=float(fraction),
            pci=int(self.allowed[best]),
            candidates=candidates,
            peak_metric=peak_metric,
            snr_db=snr_db,
            amplitude=float(amplitude),
        )


def _pss_rows(pci: int) -> np.ndarray:
    """Rows of the PSS statistic (3 roots x phases) that a PCI's PSS raises: roots 29 and 34
    (N_ID2 1 and 2) have the same envelope."""
    return np.arange(len(PHASES)) if pci % 3 == 0 else np.arange(len(PHASES), 3 * len(PHASES))


def _normalised(c: np.ndarray, spreads: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Correlation rows in units of their noise spread (median absolute deviation about zero,
    where a zero-mean template's circular correlation is centred; measured here unless given:
    later passes keep the first pass's spread), and the spreads. Every ``_SPREAD_STEP``-th lag
    is enough for the median (thousands of lags), at a fraction of the cost."""
    if spreads is None:
        spreads = mad_spread(c[:, ::_SPREAD_STEP], axis=1, centre=0.0)
    return _over_spreads(c, spreads), spreads


def _over_spreads(c: np.ndarray, spreads: np.ndarray) -> np.ndarray:
    """Rows of ``c`` over their spreads, in ``c``'s precision (the correlations' float32); 0
    where a row has none (a constant stretch)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        out = c / spreads[:, None].astype(c.dtype)
    out[spreads <= 0] = 0.0  # (rows, not a select over every element: six times cheaper)
    return out
