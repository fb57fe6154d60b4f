"""Reference *coherent* LTE cell search on complex baseband at 1.92 Msps.

This is the ground truth against which the envelope-domain search is checked on real
recordings, so it favours clarity and robustness over speed (a few seconds of CPU per second
of data). It works on the central 128 subcarriers of any LTE carrier (the 1.4 MHz numerology:
128-point FFT, CP 10/9 samples), where PSS and SSS sit whatever the bandwidth.

Steps (all on the recording's own sample grid, nominally 1.92 MHz):

1. **Coarse CFO**: PSS correlation power on a grid of frequency offsets (2.5 kHz steps over
   +-``max_cfo_hz``) on the first 50 ms. The PSS alone cannot settle the offset: a Zadoff-Chu
   sequence shifted by whole subcarriers is the same sequence delayed, so offsets ~15 kHz apart
   give almost equally strong (time-shifted) peaks. The best few local maxima are screened with
   steps 2-3 on the first 200 ms, then searched on the whole recording in that order until
   one gives cells: the SSS decides, since an SSS seen through a whole-subcarrier error matches
   no hypothesis consistent with the PSS. (The classic CP-correlation estimate of the offset
   modulo 15 kHz is not used: on the real RTL-SDR recording it is off by ~2.6 kHz, the lag-128
   correlation there being a mix of several carriers/cells with different alignments.)
2. **PSS timing**: time-domain correlation with the three PSS waveforms (roots 25/29/34) after
   CFO correction, power accumulated over all half-frames (5 ms). A cheap receiver's sample
   clock is off by the same ppm as its LO (an RTL-SDR has one crystal): 20 ppm moves the PSS by
   ~0.2 samples per half-frame, ~40 samples a second, so the drift is measured from the peak's
   track over 20 ms blocks and the accumulation follows it.
3. **SSS**: at each PSS peak the SSS symbol (one symbol earlier) is FFT'd and equalised with
   the channel seen on the PSS of the same half-frame (smoothed over frequency, which also
   rejects the PSS of co-timed neighbour cells), and all 168 ``N_ID1`` x 2 subframe-order
   hypotheses are correlated coherently over every half-frame. The magnitude of the sum is
   used, so a constant phase between the PSS and SSS channels (a residual CFO, or the two
   signals leaving different antennas) costs nothing. A cell is accepted only if the best
   hypothesis stands far out of the spread of the 336 (robust z-score) and well above the
   runner-up: this is what keeps noise from producing cells. The subframe order fixes the
   10 ms frame timing.
4. **Fine CFO** for the decided cell: the PSS power's peak over a fine offset grid (to a few
   hundred Hz), the CRS phase advance from slot to slot (unambiguous within +-1 kHz, precise to
   Hz), then the PSS phase advance from half-frame to half-frame (+-100 Hz, sub-Hz). Steps 2-3
   are then run once more at the final offset, which gives the reported metrics.

:func:`verify_pci` / :func:`crs_scan` confirm a PCI independently with the cell-specific
reference signals (CRS), whose sequence depends on the PCI *and* the slot number, so a
confirmation also confirms the 10 ms frame timing.

Sample indices: ``sync_index`` is our "sync code start": the first sample (CP included) of the
SSS symbol of subframe 0, ``sync_code_start_base() = 686`` samples after a frame start.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.fft as sfft

from deepsync.lte import grid as G
from deepsync.lte.cell import N_CELL_IDS
from deepsync.lte.numerology import (
    BASE_FFT,
    BASE_RATE_HZ,
    BASE_SAMPLES_PER_FRAME,
    HALF_FRAME_BASE_SAMPLES,
    SLOTS_PER_FRAME,
    Numerology,
    sync_code_start_base,
)
from deepsync.lte.ofdm import subcarrier_bins
from deepsync.lte.sequences import N_ID1_COUNT, pss, sss
from deepsync.numeric import mad_spread, parabolic_peak

NUM = Numerology.for_bandwidth(1.4)
FRAME = BASE_SAMPLES_PER_FRAME  # 19200
HALF = HALF_FRAME_BASE_SAMPLES  # 9600
SLOT = FRAME // SLOTS_PER_FRAME  # 960
SYMBOL = BASE_FFT + 9  # 137: SSS and PSS symbols (l = 5, 6) both have the 9-sample CP
SYNC_START = sync_code_start_base()  # 686: SSS CP start, from the frame start
PSS_USEFUL = SYNC_START + SYMBOL + 9  # 832: first useful PSS sample, from the frame start
PSS_TO_SYNC = PSS_USEFUL - SYNC_START  # 146: PSS useful start -> SSS CP start
_SYNC_BINS = subcarrier_bins(NUM)[G.sync_subcarriers(NUM)]  # FFT bins of PSS/SSS n = 0..61
_SYNC_OFFSETS = NUM.subcarrier_offsets()[G.sync_subcarriers(NUM)]  # -31..-1, 1..31
_WINDOW_BACKOFF = 2  # FFT windows start this many samples into the CP (guards early paths)
_BLOCK_HALF_FRAMES = 4  # drift tracking: PSS power folded over 20 ms blocks
_MAX_CLOCK_PPM = 300.0
_CRS_M = np.arange(2 * NUM.n_rb) + 110 - NUM.n_rb  # central 6 RBs: m' = 104..115
_CRS_SYMBOLS = [G.frame_symbol(s, l) for s in range(SLOTS_PER_FRAME) for l in G.CRS_SYMBOLS_IN_SLOT]


# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class CoherentCell:
    """One cell found by :func:`search_cells`.

    ``sync_index``: sample index (mod 19200) of the subframe-0 SSS symbol start (CP included)
    in the first frame of the recording; ``sync_position`` the same unrounded and unwrapped, in
    ``[0, samples_per_frame)``; later frames follow every ``samples_per_frame`` samples (19200
    scaled by the receiver's sample-clock error ``clock_ppm``, measured from the PSS drift).
    ``pss_index``: first useful sample of the PSS in the first half-frame, mod 9600.
    ``cfo_hz``: carrier frequency offset seen in the recording (the cell sits at +cfo_hz),
    ``cfo_std_hz`` its estimated standard error; ``cfo_ppm`` = cfo_hz / carrier_hz (NaN when no
    carrier frequency was given).
    ``power``: mean received power per PSS/SSS resource element (|iq|^2 per 128-point FFT bin,
    forward-normalised: compare cells of one recording); ``snr_db``: its ratio to the noise
    *plus interference* on those REs (co-timed neighbours' sync signals included).
    ``pss_metric``: accumulated PSS correlation peak over the profile's median. ``sss_metric``:
    |coherent SSS correlation| / sum of magnitudes for the decided hypothesis (1 = perfect),
    ``sss_runner_up`` the best of the other 335 hypotheses, ``sss_z`` the decided one's robust
    z-score among all 336, ``sss_phase_rad`` the phase of its sum (~0 when PSS and SSS see the
    same channel and the CFO is right). ``first_subframe``: 0 or 5, the subframe whose SSS comes
    first in the recording. ``half_frames``: how many were accumulated.
    """

    pci: int
    n_id_1: int
    n_id_2: int
    sync_index: int
    sync_position: float
    pss_index: int
    samples_per_frame: float
    clock_ppm: float
    cfo_hz: float
    cfo_ppm: float
    cfo_std_hz: float
    power: float
    snr_db: float
    pss_metric: float
    sss_metric: float
    sss_runner_up: float
    sss_z: float
    sss_phase_rad: float
    first_subframe: int
    half_frames: int


@dataclass(frozen=True)
class CrsCheck:
    """CRS correlation of one PCI at a cell's frame timing (:func:`verify_pci`).

    ``metric`` = |sum of differential CRS products| / sum of their magnitudes (1 = perfect,
    about ``floor`` for a wrong PCI or wrong slot numbering), ``z = metric / floor``.
    ``best_wrong_*``: the strongest of the other PCIs tested; a real neighbour cell whose frames
    are aligned with this one's (a synchronised network) legitimately scores high there.
    """

    pci: int
    metric: float
    floor: float
    z: float
    confirmed: bool
    best_wrong_pci: int
    best_wrong_metric: float
    best_wrong_z: float
    n_pairs: int


# --------------------------------------------------------------------------- helpers


def _check_input(iq: np.ndarray, sample_rate: float) -> np.ndarray:
    if abs(float(sample_rate) - BASE_RATE_HZ) > 1e-3:
        raise ValueError(
            f"coherent cell search works at {BASE_RATE_HZ / 1e6:g} Msps, got {sample_rate!r} "
            "(resample the recording first)"
        )
    x = np.asarray(iq)
    if x.ndim != 1:
        raise ValueError(f"iq must be 1-D, got shape {x.shape}")
    if x.size < 2 * FRAME:
        raise ValueError(f"need at least 2 frames ({2 * FRAME} samples), got {x.size}")
    x = x.astype(np.complex64)
    return x - x.mean()  # the RTL-SDR's DC spike


def _mix(x: np.ndarray, cfo_hz: float, index: np.ndarray | None = None) -> np.ndarray:
    """x * exp(-j 2 pi cfo n / fs) (at sample indices ``index`` if given): +cfo_hz -> 0 Hz."""
    n = np.arange(x.size, dtype=np.float64) if index is None else index.astype(np.float64)
    values = x if index is None else x[index]
    cycles = np.mod(cfo_hz / BASE_RATE_HZ * n, 1.0)
    return (values * np.exp(-2j * np.pi * cycles)).astype(np.complex64)


@lru_cache(maxsize=1)
def pss_waveforms() -> np.ndarray:
    """(3, 128) unit-energy time-domain PSS (useful part, no CP) for N_ID2 = 0, 1, 2."""
    spectra = np.zeros((3, BASE_FFT), dtype=np.complex128)
    for n_id_2 in range(3):
        spectra[n_id_2, _SYNC_BINS] = pss(n_id_2)
    waves = np.fft.ifft(spectra, axis=1)
    waves /= np.linalg.norm(waves, axis=1, keepdims=True)
    waves.flags.writeable = False
    return waves


def _pss_power(x: np.ndarray, cfo_hz: float = 0.0) -> np.ndarray:
    """|c[r, n]|^2, c = sum_m x(n + m) t_r*(m) exp(-j 2 pi cfo m / fs), n = 0 .. len(x) - 128.

    Correlating with templates moved to +cfo_hz has the magnitude of correlating the
    CFO-corrected signal with the plain templates (they differ by a phase ramp over n).
    """
    n_out = x.size - BASE_FFT + 1
    size = sfft.next_fast_len(x.size)
    spectrum = sfft.fft(x, size, workers=-1)
    ramp = np.exp(2j * np.pi * cfo_hz * np.arange(BASE_FFT) / BASE_RATE_HZ)
    out = np.empty((3, n_out), dtype=np.float32)
    for r in range(3):
        template = np.zeros(size, dtype=np.complex64)
        template[:BASE_FFT] = pss_waveforms()[r] * ramp
        c = sfft.ifft(spectrum * np.conj(sfft.fft(template)), overwrite_x=True, workers=-1)
        c = c[:n_out]
        out[r] = c.real**2 + c.imag**2
    return out


def _half_frame_starts(n_corr: int, half_period: float) -> np.ndarray:
    """Start of each half-frame whose 9600 correlation lags all exist (drift followed)."""
    count = int((n_corr - HALF) // half_period) + 1
    starts = np.rint(np.arange(count) * half_period).astype(np.int64)
    return starts[starts + HALF <= n_corr]


def _fold(power: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """sum over half-frames k of power[..., starts[k] + n], n = 0..9599."""
    out = np.zeros(power.shape[:-1] + (HALF,), dtype=np.float64)
    for s in starts:
        out += power[..., s : s + HALF]
    return out


def _estimate_half_period(power: np.ndarray) -> float:
    """Half-frame length in recording samples (9600 x (1 + clock error)) from the PSS track.

    ``power``: |PSS correlation|^2 of the strongest root. The peak is tracked over blocks of
    four half-frames (a drift of up to ~1 sample per half-frame stays within a block) and a
    line fitted with outliers (fades, a multipath tap taking over) dropped. Returns 9600 when
    the track is too short or too erratic to trust (as for noise).
    """
    n_blocks = power.size // (_BLOCK_HALF_FRAMES * HALF)
    if n_blocks < 4:
        return float(HALF)
    blocks = power[: n_blocks * _BLOCK_HALF_FRAMES * HALF].reshape(
        n_blocks, _BLOCK_HALF_FRAMES, HALF
    ).sum(axis=1)
    peaks = np.array([int(np.argmax(b)) + parabolic_peak(b, int(np.argmax(b))) for b in blocks])
    track = np.unwrap(peaks * (2 * np.pi / HALF)) * (HALF / (2 * np.pi))
    t = np.arange(n_blocks, dtype=np.float64)
    keep = np.ones(n_blocks, dtype=bool)
    slope = 0.0
    for _ in range(4):
        if keep.sum() < max(4, (2 * n_blocks) // 3):
            return float(HALF)
        slope, intercept = np.polyfit(t[keep], track[keep], 1)
        residual = np.abs(track - (slope * t + intercept))
        keep = residual <= max(1.5, 3 * np.median(residual[keep]))
    per_half = slope / _BLOCK_HALF_FRAMES
    if abs(per_half) > HALF * _MAX_CLOCK_PPM * 1e-6:
        return float(HALF)
    return HALF + per_half


def _local_peaks(profile: np.ndarray, count: int, exclusion: int = 3) -> list[int]:
    """Indices of the ``count`` largest local maxima, at least ``exclusion`` apart (circular)."""
    order = np.argsort(profile)[::-1]
    taken: list[int] = []
    for i in order[: 50 * count]:
        if all(min(abs(i - j), HALF - abs(i - j)) > exclusion for j in taken):
            taken.append(int(i))
            if len(taken) == count:
                break
    return taken


@lru_cache(maxsize=3)
def _sss_table(n_id_2: int) -> np.ndarray:
    """(2, 168, 62): SSS of subframe 0 and 5 for every N_ID1."""
    return np.array(
        [[sss(n1, n_id_2, sf) for n1 in range(N_ID1_COUNT)] for sf in (0, 5)], dtype=np.float64
    )


def _smooth_channel(h: np.ndarray, half_width: int) -> np.ndarray:
    """Moving average of per-subcarrier channel estimates over 2 * half_width + 1 subcarriers.

    A low-pass in the delay domain: it keeps paths within a few samples of the FFT window's
    timing and suppresses what is spread over all delays - noise, and above all the PSS of a
    co-timed neighbour cell, which after de-scrambling is a Zadoff-Chu chirp (flat in delay).
    The FFT windows start ``_WINDOW_BACKOFF`` samples early, a known linear phase that is
    removed before averaging and restored after. Edges average what exists.
    """
    if half_width <= 0:
        return h
    ramp = np.exp(2j * np.pi * _SYNC_OFFSETS * _WINDOW_BACKOFF / BASE_FFT)
    flat = h * ramp
    kernel = np.ones(2 * half_width + 1)
    total = np.apply_along_axis(lambda row: np.convolve(row, kernel, mode="same"), -1, flat)
    count = np.convolve(np.ones(h.shape[-1]), kernel, mode="same")
    return total / count / ramp


def _symbol_spectra(x: np.ndarray, starts: np.ndarray, cfo_hz: float = 0.0) -> np.ndarray:
    """128-point FFTs (norm="forward") of x[s : s + 128] for each start s, CFO-corrected."""
    index = starts[:, None] + np.arange(BASE_FFT)[None, :]
    return sfft.fft(_mix(x, cfo_hz, index), axis=1, norm="forward")


def _phase_estimate(products: np.ndarray) -> tuple[float, float]:
    """(angle of the mean, its standard error) of i.i.d. complex products."""
    z = np.asarray(products, dtype=np.complex128).ravel()
    mean = z.mean()
    spread = math.sqrt(np.mean(np.abs(z - mean) ** 2) / (2 * z.size))
    return float(np.angle(mean)), spread / max(abs(mean), 1e-300)


# --------------------------------------------------------------------------- search stages


@dataclass(frozen=True)
class _Candidate:
    n_id_1: int
    n_id_2: int
    peak: int  # PSS useful start in the first half-frame (index into the fold)
    parity: int  # 0: the first half-frame carries subframe 0
    pss_metric: float
    sss_metric: float
    sss_runner_up: float
    sss_z: float
    sss_phase: float
    power: float
    snr_db: float
    accepted: bool

    @property
    def pci(self) -> int:
        return 3 * self.n_id_1 + self.n_id_2


def _test_sss(
    x: np.ndarray,
    cfo_hz: float,
    starts: np.ndarray,
    n_id_2: int,
    peak: int,
    pss_metric: float,
    min_sss_z: float,
    min_sss_ratio: float,
    smoothing: int = 4,
) -> _Candidate | None:
    """All 336 SSS hypotheses at one PSS timing, coherent over the half-frames."""
    pss_at = starts + peak - _WINDOW_BACKOFF
    k = np.flatnonzero((pss_at - SYMBOL >= 0) & (pss_at + BASE_FFT <= x.size))
    if k.size < 2:
        return None
    y_pss = _symbol_spectra(x, pss_at[k], cfo_hz)[:, _SYNC_BINS]
    y_sss = _symbol_spectra(x, pss_at[k] - SYMBOL, cfo_hz)[:, _SYNC_BINS]
    h_ls = y_pss * np.conj(pss(n_id_2))  # channel on the 62 sync subcarriers, per half-frame
    z = y_sss * np.conj(_smooth_channel(h_ls, smoothing))  # ~ |H|^2 * SSS + noise, interference
    table = _sss_table(n_id_2)
    a0 = z @ table[0].T  # (K, 168): half-frame k taken as subframe 0
    a5 = z @ table[1].T  # ... as subframe 5
    even = (k % 2 == 0)[:, None]
    sums = np.stack([np.where(even, a0, a5).sum(axis=0), np.where(even, a5, a0).sum(axis=0)])
    score = np.abs(sums) / max(float(np.abs(z).sum()), 1e-30)  # (parity, N_ID1)
    flat = score.ravel()
    best = int(np.argmax(flat))
    parity, n_id_1 = divmod(best, N_ID1_COUNT)
    centre = float(np.median(flat))
    spread = float(mad_spread(flat)) + 1e-12
    sss_z = (float(flat[best]) - centre) / spread
    runner_up = float(np.delete(flat, best).max())
    accepted = bool(sss_z >= min_sss_z and flat[best] >= min_sss_ratio * runner_up)
    # Power and SINR on the sync REs: y_sss * d_sss and y_pss * conj(d_pss) are two noisy looks
    # at (nearly) the same channel; their difference is noise plus interference.
    seq = table[(k + parity) % 2, n_id_1]  # (K, 62): subframe 0 -> row 0, subframe 5 -> row 1
    h_sss = y_sss * seq
    noise = float(np.mean(np.abs(h_sss - h_ls) ** 2)) / 2
    power = max(float(np.mean(np.abs((h_sss + h_ls) / 2) ** 2)) - noise / 2, 1e-30)
    return _Candidate(
        n_id_1=n_id_1,
        n_id_2=n_id_2,
        peak=peak,
        parity=parity,
        pss_metric=pss_metric,
        sss_metric=float(flat[best]),
        sss_runner_up=runner_up,
        sss_z=sss_z,
        sss_phase=float(np.angle(sums[parity, n_id_1])),
        power=power,
        snr_db=10 * math.log10(power / max(noise, 1e-30)),
        accepted=accepted,
    )


@dataclass(frozen=True)
class _Hypothesis:
    cfo_hz: float
    half_period: float
    starts: np.ndarray
    candidates: tuple[_Candidate, ...]

    def cells(self) -> list[_Candidate]:
        """Accepted candidates, strongest first, one per PCI (echoes of a cell merge)."""
        by_pci: dict[int, _Candidate] = {}
        for cand in sorted((c for c in self.candidates if c.accepted), key=lambda c: -c.power):
            by_pci.setdefault(cand.pci, cand)
        return list(by_pci.values())

    def sync_position(self, cand: _Candidate) -> float:
        """Subframe-0 SSS start (CP included) in the first frame, in [0, 2 half-periods)."""
        position = cand.parity * self.half_period + cand.peak - PSS_TO_SYNC
        return position + 2 * self.half_period if position < 0 else position


def _search_at_cfo(
    x: np.ndarray, cfo_hz: float, peaks_per_root: int, min_sss_z: float, min_sss_ratio: float
) -> _Hypothesis:
    """PSS timing (drift followed) and SSS test of the strongest PSS peaks, at one CFO."""
    power = _pss_power(x, cfo_hz)
    total = _fold(power, _half_frame_starts(power.shape[1], HALF))
    strongest = int(np.argmax(total.max(axis=1) / np.median(total, axis=1)))
    half_period = _estimate_half_period(power[strongest])
    starts = _half_frame_starts(power.shape[1], half_period)
    profiles = _fold(power, starts)
    candidates = []
    for n_id_2 in range(3):
        profile = profiles[n_id_2]
        floor = float(np.median(profile)) + 1e-30
        for peak in _local_peaks(profile, peaks_per_root):
            cand = _test_sss(
                x, cfo_hz, starts, n_id_2, peak, profile[peak] / floor, min_sss_z, min_sss_ratio
            )
            if cand is not None:
                candidates.append(cand)
    return _Hypothesis(cfo_hz, half_period, starts, tuple(candidates))


def _coarse_cfo_candidates(
    x: np.ndarray, max_cfo_hz: float, step_hz: float, half_frames: int
) -> list[float]:
    """Local maxima of PSS evidence over a CFO grid, strongest first (>= 5 kHz apart).

    On the first ``half_frames`` only; the evidence of (offset, root) is the sum over
    half-frames of each one's correlation maximum (insensitive to clock drift), over the mean.
    The correlation is circular over the stretch (the last 127 lags wrap: harmless here), whose
    length is whole half-frames, so FFT bins are 200 / n_half Hz and moving the templates to an
    offset on the grid (rounded to a bin) is a roll of their spectra.
    """
    n_half = max(1, min(half_frames, x.size // HALF))
    size = n_half * HALF
    spectrum = sfft.fft(x[:size])
    templates = np.zeros((3, size), dtype=np.complex64)
    templates[:, :BASE_FFT] = pss_waveforms()
    template_spectra = np.conj(sfft.fft(templates, axis=1))
    bin_hz = BASE_RATE_HZ / size
    grid = np.arange(-max_cfo_hz, max_cfo_hz + step_hz / 2, step_hz)
    grid = np.rint(grid / bin_hz) * bin_hz
    evidence = np.empty((3, grid.size))
    for j, f in enumerate(grid):
        shifted = np.roll(template_spectra, int(round(f / bin_hz)), axis=1)
        c = sfft.ifft(spectrum[None, :] * shifted, axis=1, overwrite_x=True)
        power = c.real**2 + c.imag**2
        maxima = power.reshape(3, n_half, HALF).max(axis=2).sum(axis=1)
        evidence[:, j] = maxima / (power.mean(axis=1) * n_half + 1e-30)
    peaks = []
    for r in range(3):
        e = evidence[r]
        for j in range(grid.size):
            if e[j] >= e[max(j - 1, 0)] and e[j] >= e[min(j + 1, grid.size - 1)]:
                peaks.append((float(e[j]), float(grid[j])))
    chosen: list[float] = []
    for _, f in sorted(peaks, reverse=True):
        if all(abs(f - g) >= 5e3 for g in chosen):
            chosen.append(f)
    return chosen


def _symbol_grid(sync_position: float, half_period: float, n: int, symbols) -> np.ndarray:
    """(frames, len(symbols)) useful-part starts of the given frame symbols, rounded.

    Rows are consecutive frames, from the one before ``sync_position``'s frame if that starts
    inside the recording; entries may fall outside [0, n) and need checking.
    """
    scale = half_period / HALF
    frame0 = sync_position - SYNC_START * scale
    first = -1 if frame0 > 0 else 0
    last = int(math.ceil((n - frame0) / (2 * half_period)))
    useful = (NUM.symbol_starts + NUM.cp_lengths)[np.asarray(symbols)] * scale
    frames = np.arange(first, last + 1)
    return np.rint(frame0 + frames[:, None] * 2 * half_period + useful[None, :]).astype(np.int64)


def _crs_spectra(
    x: np.ndarray, cfo_hz: float, sync_position: float, half_period: float
) -> np.ndarray:
    """(frames, 20 slots, 2 symbols, 128) spectra of the CRS symbols (l = 0, 4) of whole frames."""
    starts = _symbol_grid(sync_position, half_period, x.size, _CRS_SYMBOLS) - _WINDOW_BACKOFF
    starts = starts[((starts >= 0) & (starts + BASE_FFT <= x.size)).all(axis=1)]
    spectra = _symbol_spectra(x, starts.ravel(), cfo_hz)
    return spectra.reshape(starts.shape[0], SLOTS_PER_FRAME, len(G.CRS_SYMBOLS_IN_SLOT), BASE_FFT)


def _crs_descrambled(spectra: np.ndarray, pci: int) -> np.ndarray:
    """(frames, 20, 2, 12): received central CRS REs times the conjugate CRS of ``pci``."""
    bins = subcarrier_bins(NUM)
    y = np.stack(
        [
            spectra[:, :, j, bins[G.crs_positions(NUM, pci, l)]]
            for j, l in enumerate(G.CRS_SYMBOLS_IN_SLOT)
        ],
        axis=2,
    )
    return y * np.conj(crs_table()[pci])[None]


def _pss_power_cfo(x: np.ndarray, hyp: _Hypothesis, cand: _Candidate) -> float:
    """CFO (to a few hundred Hz) maximising the cell's accumulated PSS power, +-2 kHz around."""
    deltas = np.arange(-2000.0, 2000.1, 250.0)
    lags = cand.peak + np.arange(-2, 3)
    at = (hyp.starts[:, None] + lags[None, :]).ravel()
    at = at[at + BASE_FFT <= x.size]
    index = at[:, None] + np.arange(BASE_FFT)[None, :]
    wave = np.conj(pss_waveforms()[cand.n_id_2])
    power = np.array(
        [np.sum(np.abs(_mix(x, hyp.cfo_hz + d, index) @ wave) ** 2) for d in deltas]
    )
    i = int(np.clip(np.argmax(power), 1, deltas.size - 2))
    shift = parabolic_peak(power, i)
    return hyp.cfo_hz + deltas[i] + float(np.clip(shift, -1, 1)) * (deltas[1] - deltas[0])


def _fine_cfo(x: np.ndarray, hyp: _Hypothesis, cand: _Candidate) -> tuple[float, float]:
    """(cfo_hz, standard error) for the decided cell; see the module docstring, step 4."""
    cfo = _pss_power_cfo(x, hyp, cand)
    std = 300.0  # what the PSS-power peak is good for
    # CRS of port 0 (l = 0 and l = 4 of every slot): phase advance over one slot (0.5 ms).
    spectra = _crs_spectra(x, cfo, hyp.sync_position(cand), hyp.half_period)
    if spectra.shape[0] >= 1:
        z = _crs_descrambled(spectra, cand.pci).reshape(-1, len(G.CRS_SYMBOLS_IN_SLOT), _CRS_M.size)
        slot_s = SLOT * hyp.half_period / HALF / BASE_RATE_HZ
        angle, angle_std = _phase_estimate(z[1:] * np.conj(z[:-1]))
        crs_std = angle_std / (2 * np.pi * slot_s)
        if crs_std < 150.0:
            cfo += angle / (2 * np.pi * slot_s)
            std = crs_std
    # PSS phase advance over one half-frame: unambiguous only within +-100 Hz.
    if std < 25.0:
        at = hyp.starts + cand.peak
        at = at[at + BASE_FFT <= x.size]
        index = at[:, None] + np.arange(BASE_FFT)[None, :]
        c = _mix(x, cfo, index) @ np.conj(pss_waveforms()[cand.n_id_2])
        period_s = hyp.half_period / BASE_RATE_HZ
        angle, angle_std = _phase_estimate(c[1:] * np.conj(c[:-1]))
        pss_std = angle_std / (2 * np.pi * period_s)
        if c.size >= 5 and pss_std < std:
            cfo += angle / (2 * np.pi * period_s)
            std = pss_std
    return cfo, std


# --------------------------------------------------------------------------- public API


def search_cells(
    iq: np.ndarray,
    sample_rate: float = BASE_RATE_HZ,
    max_cells: int = 4,
    *,
    carrier_hz: float | None = None,
    max_cfo_hz: float = 150e3,
    cfo_step_hz: float = 2.5e3,
    cfo_hypotheses: int = 6,
    peaks_per_root: int = 6,
    min_sss_z: float = 10.0,
    min_sss_ratio: float = 1.4,
    coarse_half_frames: int = 10,
    screen_half_frames: int = 40,
) -> list[CoherentCell]:
    """Coherent LTE cell search on complex baseband at 1.92 Msps; strongest cell first.

    ``carrier_hz`` only converts the CFO to ppm. ``max_cfo_hz`` bounds the frequency search
    (an RTL-SDR at 1.9 GHz can be ~100 kHz off), ``cfo_hypotheses`` how many coarse CFO
    candidates (local maxima of PSS power over a ``cfo_step_hz`` grid on the first
    ``coarse_half_frames``) are screened by PSS+SSS on the first ``screen_half_frames``.

    A cell is reported only when its SSS hypothesis has a robust z-score >= ``min_sss_z``
    among the 336 and beats the runner-up by ``min_sss_ratio`` (noise: z ~ 3-5, ratio ~ 1.1).
    At most ``max_cells`` cells, one per PCI (multipath echoes of a cell give the same PCI at
    nearby timings and are merged), each tested at up to ``peaks_per_root`` PSS peaks per
    N_ID2. All cells share one CFO and clock error, the receiver's, measured on the strongest.
    Limitation: a weak cell whose PSS (same N_ID2) coincides within a few samples with a
    stronger one's is masked by it; :func:`crs_scan` can reveal such frame-aligned cells.
    """
    if int(max_cells) < 1:
        raise ValueError(f"max_cells {max_cells!r} must be >= 1")
    x = _check_input(iq, sample_rate)
    coarse = _coarse_cfo_candidates(x, max_cfo_hz, cfo_step_hz, coarse_half_frames)
    # Screen the CFO candidates on a short stretch (the right one gives an SSS that stands
    # out), then search the whole recording at them, most promising first, until cells appear.
    short = x[: min(x.size, screen_half_frames * HALF + BASE_FFT)]
    screened = []
    for cfo in coarse[: max(1, cfo_hypotheses)]:
        hyp = _search_at_cfo(short, cfo, peaks_per_root, min_sss_z, min_sss_ratio)
        screened.append((max((c.sss_z for c in hyp.candidates), default=0.0), cfo))
    best: _Hypothesis | None = None
    for _, cfo in sorted(screened, reverse=True):
        best = _search_at_cfo(x, cfo, peaks_per_root, min_sss_z, min_sss_ratio)
        if best.cells():
            break
    if best is None or not best.cells():
        return []
    cfo, cfo_std = _fine_cfo(x, best, best.cells()[0])
    final = _search_at_cfo(x, cfo, peaks_per_root, min_sss_z, min_sss_ratio)
    if not final.cells():  # cannot happen for a real cell; keep the coarse result then
        final = best
    clock_ppm = (final.half_period / HALF - 1) * 1e6
    cells = []
    for cand in final.cells()[: int(max_cells)]:
        position = final.sync_position(cand)
        cells.append(
            CoherentCell(
                pci=cand.pci,
                n_id_1=cand.n_id_1,
                n_id_2=cand.n_id_2,
                sync_index=int(round(position)) % FRAME,
                sync_position=float(position),
                pss_index=cand.peak,
                samples_per_frame=2 * final.half_period,
                clock_ppm=float(clock_ppm),
                cfo_hz=float(cfo),
                cfo_ppm=float(cfo / carrier_hz * 1e6) if carrier_hz else float("nan"),
                cfo_std_hz=float(cfo_std),
                power=cand.power,
                snr_db=cand.snr_db,
                pss_metric=float(cand.pss_metric),
                sss_metric=cand.sss_metric,
                sss_runner_up=cand.sss_runner_up,
                sss_z=cand.sss_z,
                sss_phase_rad=cand.sss_phase,
                first_subframe=0 if cand.parity == 0 else 5,
                half_frames=int(final.starts.size),
            )
        )
    return cells


def _crs_bits(c_init: np.ndarray, start: int, length: int) -> np.ndarray:
    """Gold sequence bits c(start .. start+length-1) (36.211 §7.2) for many c_init at once."""
    total = 1600 + start + length
    x1 = np.zeros(total + 31, dtype=np.uint8)
    x1[0] = 1
    for n in range(total):
        x1[n + 31] = x1[n + 3] ^ x1[n]
    x2 = np.zeros((c_init.size, total + 31), dtype=np.uint8)
    x2[:, :31] = (c_init[:, None] >> np.arange(31)[None, :]) & 1
    for n in range(0, total, 28):  # x2(n+31) = x2(n+3) ^ x2(n+2) ^ x2(n+1) ^ x2(n)
        stop = min(n + 28, total)
        x2[:, n + 31 : stop + 31] = (
            x2[:, n + 3 : stop + 3]
            ^ x2[:, n + 2 : stop + 2]
            ^ x2[:, n + 1 : stop + 1]
            ^ x2[:, n:stop]
        )
    lo = 1600 + start
    return x1[lo : lo + length][None, :] ^ x2[:, lo : lo + length]


@lru_cache(maxsize=1)
def crs_table() -> np.ndarray:
    """(504, 20, 2, 12) port-0 CRS values on the central 6 RBs, for l = 0 and 4 of each slot.

    The values of :func:`deepsync.lte.sequences.crs` at m' = 104..115, computed for all PCIs at
    once; valid for any carrier bandwidth, since m' counts from the carrier centre.
    """
    pci = np.arange(N_CELL_IDS)[:, None, None]
    slot = np.arange(SLOTS_PER_FRAME)[None, :, None]
    symbol = np.array(G.CRS_SYMBOLS_IN_SLOT)[None, None, :]
    c_init = (2**10 * (7 * (slot + 1) + symbol + 1) * (2 * pci + 1) + 2 * pci + 1).ravel()
    bits = _crs_bits(c_init.astype(np.int64), 2 * int(_CRS_M[0]), 2 * _CRS_M.size)
    bits = bits.astype(np.float64)
    values = ((1 - 2 * bits[:, 0::2]) + 1j * (1 - 2 * bits[:, 1::2])) / np.sqrt(2)
    table = values.reshape(N_CELL_IDS, SLOTS_PER_FRAME, len(G.CRS_SYMBOLS_IN_SLOT), _CRS_M.size)
    table.flags.writeable = False
    return table


def crs_scan(
    iq: np.ndarray,
    sync_position: float,
    cfo_hz: float,
    samples_per_frame: float = float(FRAME),
    pcis=range(N_CELL_IDS),
    sample_rate: float = BASE_RATE_HZ,
) -> tuple[np.ndarray, np.ndarray, int]:
    """(metric, floor) for each PCI in ``pcis`` at the given frame timing, and the pair count.

    For every CRS symbol (l = 0 and 4 of each slot) of every whole frame, the received values on
    the PCI's 12 central CRS subcarriers are de-scrambled with the PCI's sequence for that slot
    and symbol, and neighbouring ones (90 kHz apart) multiplied, ``z(m+1) z*(m)``: the channel
    nearly cancels, so the right PCI leaves a common phase and a wrong one (or a wrong slot
    numbering) random phases. ``metric = |sum| / sum |.|``. ``floor`` is its RMS value for a
    wrong PCI: the CRS repeat every frame, so with a slowly changing channel a wrong PCI's
    products repeat as well, and only their sums over frames (one per slot, symbol and pair:
    440) have independent phases, ``floor = sqrt(sum |frame sums|^2) / sum |.|``. Needs the
    timing to within a few samples (inside the CP), not an accurate CFO.
    """
    x = _check_input(iq, sample_rate)
    spectra = _crs_spectra(x, cfo_hz, sync_position, samples_per_frame / 2)
    if spectra.shape[0] == 0:
        raise ValueError("the recording holds no whole frame at this timing")
    pcis = [int(p) for p in pcis]
    metric = np.empty(len(pcis))
    floor = np.empty(len(pcis))
    n_pairs = 0
    for i, pci in enumerate(pcis):
        z = _crs_descrambled(spectra, pci)
        d = z[..., 1:] * np.conj(z[..., :-1])  # (frames, 20, 2, 11)
        magnitude = float(np.abs(d).sum()) + 1e-30
        metric[i] = abs(d.sum()) / magnitude
        # The CRS repeat every frame and the channel changes slowly, so a wrong PCI's products
        # repeat too: only the 440 (slot, symbol, pair) sums are independent random phases.
        floor[i] = math.sqrt(float(np.sum(np.abs(d.sum(axis=0)) ** 2))) / magnitude
        n_pairs = d.size
    return metric, floor, n_pairs


def verify_pci(
    iq: np.ndarray,
    cell: CoherentCell,
    pci: int | None = None,
    *,
    wrong_pcis=None,
    min_z: float = 6.0,
    sample_rate: float = BASE_RATE_HZ,
) -> CrsCheck:
    """Confirm ``pci`` (default: the cell's own) by CRS correlation at ``cell``'s frame timing.

    ``wrong_pcis`` (default: all other 503) are scored the same way for comparison. A PCI is
    confirmed when its metric is ``min_z`` times the random-phase floor (wrong PCIs reach ~3 at
    most over 503 tries, unless a real neighbour cell is frame-aligned with this one: in a
    synchronised network its CRS line up too, and it scores like the cell itself).
    """
    pci = cell.pci if pci is None else int(pci)
    if wrong_pcis is None:
        wrong_pcis = range(N_CELL_IDS)
    wrong = [int(p) for p in wrong_pcis if int(p) != pci]
    metric, floor, n_pairs = crs_scan(
        iq, cell.sync_position, cell.cfo_hz, cell.samples_per_frame, [pci, *wrong], sample_rate
    )
    if wrong:
        j = int(np.argmax(metric[1:])) + 1
        best_wrong = (wrong[j - 1], float(metric[j]), float(metric[j] / floor[j]))
    else:
        best_wrong = (-1, float("nan"), float("nan"))
    z = float(metric[0] / floor[0])
    return CrsCheck(
        pci=pci,
        metric=float(metric[0]),
        floor=float(floor[0]),
        z=z,
        confirmed=bool(z >= min_z),
        best_wrong_pci=best_wrong[0],
        best_wrong_metric=best_wrong[1],
        best_wrong_z=best_wrong[2],
        n_pairs=n_pairs,
    )
