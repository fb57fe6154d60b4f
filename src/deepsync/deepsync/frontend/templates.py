"""Sync templates: what the SSS+PSS pair of each PCI looks like after the receiver chain.

A cell's envelope is |s + d|^2 with s its sync code and d everything else; on average this is
|s|^2 + E|d|^2 (the cross term has zero mean). The part that identifies the cell and carries
its timing is |s|^2, so the template of a PCI is |s|^2 of its SSS+PSS symbols alone, through
the same analog video filter (exact H(f)) and AC coupling as the simulated stream, sampled at
the ADC rate with the code's first sample (SSS cyclic prefix) at t = 0. The load-dependent
pedestal E|d|^2 is the same for every PCI and is left to the detectors to remove.

Units: volts at the diode output per watt of received (antenna) power per resource element,
through the LNA and detector, i.e. at unit
video gain. Length: ``TEMPLATE_LENGTH`` = the 274-sample code + 2 samples of filter tail (the
video filter delays the envelope by about one sample at 1.92 MHz).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import lru_cache

import numpy as np
import scipy.fft
import scipy.signal

from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.video import VideoFilter, highpass_sos
from deepsync.lte import grid as G
from deepsync.lte.cell import N_CELL_IDS, CellConfig, split_pci
from deepsync.lte.frame import FrameGenerator
from deepsync.lte.numerology import (
    BASE_FFT,
    BASE_RATE_HZ,
    SUBCARRIER_SPACING_HZ,
    SYNC_CODE_BASE_SAMPLES,
    Numerology,
    sync_code_start_base,
)
from deepsync.lte.ofdm import modulate, subcarrier_bins
from deepsync.lte.sequences import pss, sss

TEMPLATE_LENGTH = SYNC_CODE_BASE_SAMPLES + 2
PSS_OFFSET_BASE = SYNC_CODE_BASE_SAMPLES // 2  # the PSS symbol follows the SSS symbol (137 samples)
PSS_TEMPLATE_LENGTH = PSS_OFFSET_BASE + 2
_OVERSAMPLING = 16  # template waveform rate: 16 x 1.92 MHz, far above any ADC rate used
_RING_BASE = 64  # base samples (33 us) left after the shapes for the video filter's ringing: it lasts a few us
_WAVEFORM_RATE = _OVERSAMPLING * BASE_RATE_HZ
# a fold order of the CRS envelope (``SyncTemplates.crs_folds``) is kept where the video filter
# passes its band above this: at 1.92 MS/s the order -1 alone (0.96-1.92 MHz, -4 to -26 dB);
# the ones left out change a 5-20 MHz template by 1.6-1.8 % in norm and a clean cell's timing by
# under 0.003 samples (with +1 kept, 0.4 % and 0.001), at a third less of the fit's extra cost
FOLD_FLOOR_DB = -20.0
_FOLD_FLOOR = 10 ** (FOLD_FLOOR_DB / 20)
FRACTION_GRID = 32


def _sync_symbols(values: list[np.ndarray], oversampling: int) -> np.ndarray:
    """Complex baseband of consecutive sync symbols (62 values each, unit power per RE), CPs included."""
    num = Numerology.for_bandwidth(1.4, fft_size=BASE_FFT * oversampling)
    bins = subcarrier_bins(num)[G.sync_subcarriers(num)]
    symbols = np.zeros((len(values), num.fft_size), dtype=np.complex128)
    for row, value in zip(symbols, values):
        row[bins] = value
    waveform = scipy.fft.ifft(symbols, axis=1, norm="forward")
    cp = num.cp_lengths[G.SSS_SYMBOL_IN_SLOT]  # both sync symbols use the short CP
    return np.concatenate([np.concatenate([w[-cp:], w]) for w in waveform])


def sync_code_waveform(pci: int, subframe: int, oversampling: int = _OVERSAMPLING) -> np.ndarray:
    """Complex baseband of the SSS and PSS symbols of ``pci`` (unit power per RE), CPs included."""
    n_id_1, n_id_2 = split_pci(pci)
    return _sync_symbols([sss(n_id_1, n_id_2, subframe), pss(n_id_2)], oversampling)


def pss_waveform(n_id_2: int, oversampling: int = _OVERSAMPLING) -> np.ndarray:
    """Complex baseband of the PSS symbol alone, CP included: the same every 5 ms."""
    return _sync_symbols([pss(n_id_2)], oversampling)


def check_template_rate(sample_rate: float) -> float:
    """``sample_rate`` (Hz), or ValueError naming the rates templates can be built for.

    Templates are computed on a 30.72 MHz waveform (16 x 1.92 MHz) and sampled at the ADC
    rate, which must therefore divide it: 0.96, 1.92, 3.84, 7.68, 15.36 MHz and a few others
    (2.048, 2.56, 3.072, 6.144, ... MHz), but not, e.g., 2.4 or 2.5 MHz.
    """
    ratio = _WAVEFORM_RATE / sample_rate if math.isfinite(sample_rate) and sample_rate > 0 else math.nan
    if not (ratio >= 1 and abs(ratio - round(ratio)) <= 1e-9 * ratio):
        raise ValueError(
            f"sample rate {sample_rate:g} Hz: sync templates need a rate that divides "
            f"{_WAVEFORM_RATE / 1e6:g} MHz by a whole factor (e.g. 1.92e6, 2.048e6, 3.84e6, 7.68e6)"
        )
    return float(sample_rate)


class SyncTemplates:
    """Templates of all 504 PCIs for subframes 0 and 5, for one front-end configuration."""

    def __init__(self, config: FrontendConfig, length: int | None = None) -> None:
        """``length`` (ADC samples) defaults to the code plus its filter tail; longer windows
        show what follows the code too (the filter's and the AC coupling's tails)."""
        check_template_rate(config.adc_rate_hz)
        self.config = config
        self.sample_rate = config.adc_rate_hz
        default = int(round(TEMPLATE_LENGTH * config.adc_rate_hz / BASE_RATE_HZ))
        self.length = default if length is None else int(length)
        self._video = VideoFilter(config)
        self._highpass = highpass_sos(config, config.adc_rate_hz)
        self._grid: dict[tuple[int, ...], np.ndarray] = {}  # shapes on a fraction grid, by PCI(s) and subframe
        self._filters: dict[tuple[int, float], tuple[np.ndarray, np.ndarray]] = {}  # (n_fft, rate) -> (f, H(f))
        self._crs: dict[tuple[int, ...], np.ndarray] = {}  # (PCI(s), 10 x bandwidth) -> CRS envelope(s) of a frame
        self._code_aligned_crs: dict[tuple, np.ndarray] = {}  # the same, its code starting at 0
        self._folds: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}  # the same key -> ``crs_folds``

    def response(self, envelopes: np.ndarray, rate_hz: float, delays_s: np.ndarray | float = 0.0,
                 length: int | None = None) -> np.ndarray:
        """ADC-rate samples of video-filtered envelopes that start at t = delay.

        ``envelopes`` is (B, L) |s|^2 at ``rate_hz`` starting at t = 0; the result is
        (B, D, length) for D delays, sampled at t = n / adc_rate (length defaults to the
        template's). Fractional delays are applied exactly, as a phase ramp on the filtered
        spectrum, over an analysis window that holds the envelopes, their delays, the output
        and the filter's ringing (a quarter of it before t = 0), and no longer: a longer one
        changes the shapes by ~1e-13 and costs in proportion.
        """
        length = self.length if length is None else length
        envelopes = np.atleast_2d(envelopes)
        delays = np.atleast_1d(np.asarray(delays_s, dtype=np.float64))
        ratio = rate_hz / self.sample_rate
        if abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(f"ADC rate {self.sample_rate:g} Hz does not divide {rate_hz:g} Hz")
        ratio = round(ratio)
        ring = _RING_BASE * rate_hz / BASE_RATE_HZ
        late, early = max(0.0, delays.max() * rate_hz), max(0.0, -delays.min() * rate_hz)
        content = max(envelopes.shape[1] + late, length * ratio) + early + ring
        n_fft = 2 ** math.ceil(math.log2(4 / 3 * content))
        lead = n_fft // 4  # room before t = 0 for negative delays and the filter's pre-ringing
        padded = np.zeros((len(envelopes), n_fft))
        padded[:, lead : lead + envelopes.shape[1]] = envelopes
        if (n_fft, rate_hz) not in self._filters:  # the same grid on every call: evaluated once
            frequencies = scipy.fft.rfftfreq(n_fft, 1 / rate_hz)
            self._filters[n_fft, rate_hz] = frequencies, self._video.response(frequencies)
        frequencies, video = self._filters[n_fft, rate_hz]
        spectrum = scipy.fft.rfft(padded, axis=1) * video
        shift = np.exp(-2j * np.pi * frequencies[None, :] * delays[:, None])
        filtered = scipy.fft.irfft(spectrum[:, None, :] * shift[None], n=n_fft, axis=2)
        sampled = filtered[:, :, lead : lead + length * ratio : ratio]
        if self._highpass is not None:
            sampled = scipy.signal.sosfilt(self._highpass, sampled, axis=2)
        return sampled * (self.config.detector_responsivity_v_per_w * self.config.rf_power_gain)

    def template(self, pci: int, subframe: int = 0, delay_samples: np.ndarray | float = 0.0) -> np.ndarray:
        """Template(s) of one PCI; fractional ``delay_samples`` (ADC samples) shift the code."""
        envelope = np.abs(sync_code_waveform(pci, subframe)) ** 2
        out = self.response(envelope, _WAVEFORM_RATE, np.asarray(delay_samples) / self.sample_rate)[0]
        return out[0] if np.ndim(delay_samples) == 0 else out

    def cross_terms(self, pci_a: int, pci_b: int, subframe: int, delay_a: float, delay_b: float,
                    length: int) -> np.ndarray:
        """(2, length) responses of 2 Re(s_a s_b*) and 2 Im(s_a s_b*), codes at the given delays.

        Two codes on one carrier that overlap in time add up before the square law:
        |x s_a + y s_b|^2 = |x|^2 |s_a|^2 + |y|^2 |s_b|^2 + Re(x y*) 2Re(s_a s_b*) - Im(x y*) 2Im(s_a s_b*).
        With a stable relative phase (sectors of a site, a time-synchronised network) the cross
        term survives stacking; these are its two shapes, in the templates' units.
        """
        step = int(round((delay_b - delay_a) * _OVERSAMPLING))  # b's start relative to a's, waveform samples
        envelopes, first = _cross_envelopes(pci_a, pci_b, subframe, step)
        start = delay_a + first / _OVERSAMPLING  # where the product array begins, ADC samples
        return self.response(envelopes, _WAVEFORM_RATE, start / self.sample_rate, length)[:, 0]

    def all(self) -> np.ndarray:
        """(504, 2, length) templates for subframes 0 and 5, cached per configuration."""
        return _all_templates(self.config)

    def shifted(self, pci: int, subframe: int, delay_samples: float) -> np.ndarray:
        """The template with its code starting at ``delay_samples`` (any real), fast: from a
        cached grid of 1/``FRACTION_GRID`` sample steps, so within 1/(2 x grid) sample of exact."""
        key = (pci, subframe)
        if key not in self._grid:
            self._grid[key] = self.template(pci, subframe, np.arange(FRACTION_GRID) / FRACTION_GRID)
        return _from_grid(self._grid[key], delay_samples)

    def shifted_cross_terms(self, pci_a: int, pci_b: int, subframe: int, delay_samples: float) -> np.ndarray:
        """``cross_terms`` of two codes that both start at ``delay_samples`` (co-sited sectors),
        ``length`` long, fast: from a cached grid, as ``shifted``."""
        key = (pci_a, pci_b, subframe)
        if key not in self._grid:
            envelopes, _ = _cross_envelopes(pci_a, pci_b, subframe, 0)
            grid = self.response(envelopes, _WAVEFORM_RATE, np.arange(FRACTION_GRID) / FRACTION_GRID / self.sample_rate)
            self._grid[key] = np.swapaxes(grid, 0, 1)  # (fractions, 2, length)
        return _from_grid(self._grid[key], delay_samples)

    def pair_shapes(self, pcis: tuple[int, int], subframe: int, delay_samples: float) -> np.ndarray:
        """(4, length) the component shapes of two co-sited sectors' coinciding codes, both
        starting at ``delay_samples``: |s_a|^2, |s_b|^2, 2Re(s_a s_b*), 2Im(s_a s_b*)."""
        a, b = pcis
        own = [self.shifted(pci, subframe, delay_samples) for pci in pcis]
        return np.stack([*own, *self.shifted_cross_terms(a, b, subframe, delay_samples)])

    def pss(self, n_id_2: int, delay_samples: np.ndarray | float = 0.0) -> np.ndarray:
        """Template of the PSS symbol alone (its CP start at t = delay), ``pss_length`` long;
        one row per delay if ``delay_samples`` is an array."""
        envelope = np.abs(pss_waveform(n_id_2)) ** 2
        out = self.response(envelope, _WAVEFORM_RATE, np.asarray(delay_samples) / self.sample_rate)[0]
        out = out[:, : self.pss_length]
        return out[0] if np.ndim(delay_samples) == 0 else out

    def crs_envelope(self, pci: int, bandwidth_mhz: float) -> np.ndarray:
        """(frame,) one frame of a cell's cell-specific reference signals (port 0) in the
        envelope, the frame starting at sample 0: |CRS|^2 of the subcarriers within the front
        end's RF passband (``rf_bandwidth_hz``), through the video filter and the AC coupling,
        per unit RE power, with its mean over each of the cell's OFDM symbols removed (the
        load-dependent pedestal of the data there is unknown). Sent the same in every
        frame, it survives stacking as the sync codes do; a strong cell's, over long stacks,
        rises above the search's threshold (``deepsync.sync.search``). Cached."""
        key = (pci, round(10 * bandwidth_mhz))
        if key not in self._crs:
            envelope, rate = self._crs_square_law(pci, bandwidth_mhz)
            self._crs[key] = self._symbol_demeaned(self._periodic_response(envelope, rate))
        return self._crs[key]

    def crs_cross_envelopes(self, pci_a: int, pci_b: int, bandwidth_mhz: float) -> np.ndarray:
        """(2, frame) the envelopes of 2Re(x_a x_b*) and 2Im(x_a x_b*) of two co-sited sectors'
        CRS (``crs_envelope``'s units and treatment), frames starting at sample 0: what the
        square law makes of the two together beyond each one's own, scaled by the channels'
        product as the codes' cross terms are (``cross_terms``). Cached."""
        key = (pci_a, pci_b, round(10 * bandwidth_mhz))
        if key not in self._crs:
            envelopes, rate = self._crs_square_law(pci_a, bandwidth_mhz, pci_b)
            self._crs[key] = np.stack([self._symbol_demeaned(self._periodic_response(part, rate))
                                       for part in envelopes])
        return self._crs[key]

    def _crs_square_law(self, pci: int, bandwidth_mhz: float,
                        cosited_pci: int | None = None) -> tuple[np.ndarray, float]:
        """One frame of |CRS|^2 at the numerology's rate, or with a ``cosited_pci`` (2, ...)
        2Re and 2Im of the two sectors' CRS product, and that rate."""
        waveform, rate = self._crs_waveform(pci, bandwidth_mhz)
        if cosited_pci is None:
            return np.abs(waveform) ** 2, rate
        product = 2 * waveform * np.conj(self._crs_waveform(cosited_pci, bandwidth_mhz)[0])
        return np.stack([product.real, product.imag]), rate

    def crs_folds(self, pci: int, bandwidth_mhz: float,
                  cosited_pci: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """What sampling at the ADC rate folds into ``code_aligned_crs`` (same arguments):
        ``(orders, spectra)``, spectra (M, frame // 2 + 1), with a ``cosited_pci`` (2, M, ...).

        The CRS comb spans the whole carrier, so its envelope holds content above the ADC's
        Nyquist frequency that the video filter passes in part (-4 dB at 0.96 MHz, -26 dB at
        1.92 MHz at 1.92 MS/s); sampling folds it onto the bins below. Spectrum bin k of the
        envelope sampled with its code starting at p samples is sum_m A_m(k) e^{-j (w_k + 2 pi m) p}
        over the orders m (frequency k + m x frame bins); a template built at p = 0 and moved by
        a phase ramp takes every A_m as in band, and is off by up to 0.08 samples at p between
        whole samples (docs/design/timing_network.md). These are the A_m, m != 0, of the orders whose
        band the video filter passes above ``FOLD_FLOOR_DB`` (none for 1.4 MHz, whose envelope
        is made at the ADC rate), code-aligned as ``code_aligned_crs`` and in its units but with
        no per-symbol mean removed: the folded content is far above the symbol rate. Cached."""
        key = (pci, round(10 * bandwidth_mhz), cosited_pci)
        if key not in self._folds:
            envelopes, rate = self._crs_square_law(pci, bandwidth_mhz, cosited_pci)
            self._folds[key] = self._folded(envelopes, rate)
        return self._folds[key]

    def _folded(self, envelopes: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """``crs_folds`` of a periodic envelope (..., L) at ``rate_hz`` (``_periodic_response``'s)."""
        ratio = round(rate_hz / self.sample_rate)
        length = envelopes.shape[-1]
        frame = length // ratio
        video = self._video.response(scipy.fft.rfftfreq(length, 1 / rate_hz))
        spectrum = scipy.fft.rfft(envelopes, axis=-1) * video
        bins = np.arange(frame // 2 + 1)
        coupling = 1.0 if self._highpass is None else scipy.signal.sosfreqz(
            self._highpass, scipy.fft.rfftfreq(frame, 1 / self.sample_rate), fs=self.sample_rate)[1]
        scale = coupling * (self.config.detector_responsivity_v_per_w * self.config.rf_power_gain) / ratio
        start = -sync_code_offset_seconds() * self.sample_rate  # where the frame starts, its code at 0
        orders, folds = [], []
        for order in range(-ratio, ratio + 1):
            signed = bins + order * frame  # the envelope's frequency, in bins of the frame
            inside = (signed > -(length // 2)) & (signed <= length // 2)  # the DFT's own frequencies, once each
            if order == 0 or not inside.any() or np.max(np.abs(video[np.abs(signed[inside])])) < _FOLD_FLOOR:
                continue
            index = np.minimum(np.abs(signed), length // 2)
            values = np.where(signed < 0, np.conj(spectrum[..., index]), spectrum[..., index])
            orders.append(order)
            folds.append(np.where(inside, values, 0) * scale * np.exp(-2j * np.pi * signed * start / frame))
        return np.array(orders, dtype=int), np.stack(folds, axis=-2) if folds else np.zeros(
            (*envelopes.shape[:-1], 0, frame // 2 + 1), dtype=complex)

    def _crs_waveform(self, pci: int, bandwidth_mhz: float) -> tuple[np.ndarray, float]:
        """One frame of a cell's port-0 CRS at its numerology's rate, the subcarriers outside the
        front end's RF passband left out (an envelope detector behind a band filter sees all of
        any carrier, an I/Q radio squared afterwards only its middle), and that rate."""
        numerology = _numerology_for_rate(bandwidth_mhz, self.sample_rate)
        grid = FrameGenerator(CellConfig(pci=pci, bandwidth_mhz=bandwidth_mhz), seed=0).deterministic_grid
        for slot in G.SYNC_SLOTS:  # the sync codes have templates of their own
            grid[[G.frame_symbol(slot, G.SSS_SYMBOL_IN_SLOT), G.frame_symbol(slot, G.PSS_SYMBOL_IN_SLOT)]] = 0
        outside = np.abs(numerology.subcarrier_offsets()) * SUBCARRIER_SPACING_HZ > self.config.rf_bandwidth_hz / 2
        grid[:, outside] = 0
        return modulate(grid, numerology), numerology.sample_rate_hz

    def _symbol_demeaned(self, shape: np.ndarray) -> np.ndarray:
        """A frame's envelope less its mean over each OFDM symbol (ADC rate)."""
        starts = np.round(Numerology.for_bandwidth(1.4).symbol_starts * self.sample_rate / BASE_RATE_HZ)
        symbol = np.searchsorted(starts.astype(int), np.arange(len(shape)), side="right") - 1
        return shape - (np.bincount(symbol, shape) / np.bincount(symbol))[symbol]

    def frame_template(self, pci: int, bandwidth_mhz: float, phases: Sequence[float]) -> np.ndarray:
        """(phases, frame) everything a cell sends the same in every frame, as the envelope
        shows it: its two sync codes (each zero-mean) and its CRS (``crs_envelope``), with the
        subframe-0 code starting at each of the sub-sample ``phases`` (0 <= phase < 1), per unit
        RE power.

        The codes are 4 of the frame's 140 symbols; the CRS adds 40 (port 0), so a known cell
        carries several times the matched-filter energy of its codes alone, more the wider the
        carrier (the codes always span 62 subcarriers, the CRS comb the whole band). Its comb
        (every 6th subcarrier) repeats the CRS envelope every 21.3 samples, so this template's
        autocorrelation has sidelobes there that the codes' does not."""
        delays = np.asarray(phases, dtype=float)
        crs = self.placed_crs(pci, bandwidth_mhz, delays)
        return place_codes(crs.shape[1], lambda subframe: self.template(pci, subframe, delays)) + crs

    def code_aligned_crs(self, pci: int, bandwidth_mhz: float, cosited_pci: int | None = None) -> np.ndarray:
        """(frame,) ``placed_crs`` with the subframe-0 code starting at sample 0; with a
        ``cosited_pci``, (2, frame) the two sectors' ``crs_cross_envelopes`` so placed. Cached."""
        key = (pci, round(10 * bandwidth_mhz), cosited_pci)
        if key not in self._code_aligned_crs:
            envelope = (self.crs_envelope(pci, bandwidth_mhz) if cosited_pci is None
                        else self.crs_cross_envelopes(pci, cosited_pci, bandwidth_mhz))
            self._code_aligned_crs[key] = self._placed(envelope, np.zeros(1))[..., 0, :]
        return self._code_aligned_crs[key]

    def placed_crs(self, pci: int, bandwidth_mhz: float, delays: np.ndarray) -> np.ndarray:
        """(delays, frame) ``crs_envelope`` moved so that the subframe-0 code would start at
        each of ``delays`` samples (band-limited shifts)."""
        return self._placed(self.crs_envelope(pci, bandwidth_mhz), delays)

    def _placed(self, envelopes: np.ndarray, delays: np.ndarray) -> np.ndarray:
        """(..., delays, frame) frame envelopes (..., frame), their frame starting at sample 0,
        moved so that the subframe-0 code would start at each of ``delays`` samples."""
        frame = envelopes.shape[-1]
        shift = np.asarray(delays, dtype=float)[:, None] - sync_code_offset_seconds() * self.sample_rate  # the frame's start
        ramp = np.exp(-2j * np.pi * scipy.fft.rfftfreq(frame) * shift)
        return scipy.fft.irfft(scipy.fft.rfft(envelopes, axis=-1)[..., None, :] * ramp, frame, axis=-1)

    def _periodic_response(self, envelope: np.ndarray, rate_hz: float) -> np.ndarray:
        """ADC-rate samples of one period of a periodic envelope (at ``rate_hz``, a whole number
        of ADC samples long) through the video filter and the AC coupling in their steady
        state: filtered circularly, which is exact for a periodic signal, then sampled."""
        ratio = round(rate_hz / self.sample_rate)
        frequencies = scipy.fft.rfftfreq(len(envelope), 1 / rate_hz)
        filtered = scipy.fft.irfft(scipy.fft.rfft(envelope) * self._video.response(frequencies), len(envelope))
        sampled = filtered[::ratio]
        if self._highpass is not None:
            coupling = scipy.signal.sosfreqz(self._highpass, scipy.fft.rfftfreq(len(sampled), 1 / self.sample_rate),
                                             fs=self.sample_rate)[1]
            sampled = scipy.fft.irfft(scipy.fft.rfft(sampled) * coupling, len(sampled))
        return sampled * (self.config.detector_responsivity_v_per_w * self.config.rf_power_gain)

    @property
    def pss_length(self) -> int:
        return int(round(PSS_TEMPLATE_LENGTH * self.sample_rate / BASE_RATE_HZ))

    @property
    def pss_offset(self) -> int:
        """Samples from the code start (SSS CP) to the PSS symbol's CP start."""
        return int(round(PSS_OFFSET_BASE * self.sample_rate / BASE_RATE_HZ))


def code_template(
    templates: SyncTemplates,
    pci: int,
    cosited_pci: int | None = None,
    site_coefficients: Sequence[float] | None = None,
    subframe: int = 0,
    delay_samples: float = 0.0,
) -> np.ndarray:
    """What a detected cell's sync code looks like in the envelope, code start at
    ``delay_samples``: its PCI's template, or, for two co-sited sectors found together, the
    pair's fitted model (``site_coefficients`` scale |s_a|^2, |s_b|^2, 2Re(s_a s_b*) and
    2Im(s_a s_b*), a the lower PCI). Everything it needs is in a ``SyncWindow`` message, so a
    timing stage fed from one rebuilds the very template the sync stage saw."""
    if cosited_pci is None:
        return templates.template(pci, subframe, delay_samples)
    coefficients = pair_coefficients(pci, cosited_pci, site_coefficients)
    return coefficients @ templates.pair_shapes(cosited_pair(pci, cosited_pci), subframe, delay_samples)


def cosited_pair(pci: int, cosited_pci: int) -> tuple[int, int]:
    """Two co-sited sectors as their templates key them: the lower PCI first (sector a)."""
    return min(pci, cosited_pci), max(pci, cosited_pci)


def pair_coefficients(pci: int, cosited_pci: int, site_coefficients: Sequence[float] | None) -> np.ndarray:
    """(4,) a co-sited pair's site coefficients as floats, or ValueError naming the pair."""
    if site_coefficients is None or len(site_coefficients) != 4:
        raise ValueError(f"PCI {pci} with co-sited PCI {cosited_pci}: the pair's 4 site coefficients are needed")
    return np.asarray(site_coefficients, dtype=np.float64)


def place_codes(frame: int, codes: Callable[[int], np.ndarray]) -> np.ndarray:
    """(..., frame) the sync codes of subframes 0 and 5 (``codes(subframe)`` -> (..., L)), each
    made zero-mean, at the start and the middle of a frame."""
    first = np.asarray(codes(0))
    placed = np.zeros((*first.shape[:-1], frame))
    for subframe, start in ((0, 0), (5, frame // 2)):
        part = first if subframe == 0 else np.asarray(codes(subframe))
        placed[..., start : start + part.shape[-1]] = part - part.mean(axis=-1, keepdims=True)
    return placed


def known_frame(
    templates: SyncTemplates,
    pci: int,
    bandwidth_mhz: float,
    cosited_pci: int | None = None,
    site_coefficients: Sequence[float] | None = None,
) -> np.ndarray:
    """(frame,) everything a detected cell of known bandwidth sends the same in every frame, its
    subframe-0 code starting at sample 0: ``SyncTemplates.frame_template``, or for two co-sited
    sectors found together (``code_template``) their fitted code model in subframes 0 and 5,
    and their CRS with the same four coefficients: each sector's own (|s_a|^2 and |s_b|^2: CRS
    and codes are sent at the same power per RE) and the two sectors' cross terms (2Re and
    2Im: the same product of their channels, taken as flat across the carrier)."""
    if cosited_pci is None:
        return templates.frame_template(pci, bandwidth_mhz, [0.0])[0]
    coefficients = pair_coefficients(pci, cosited_pci, site_coefficients)
    return coefficients @ pair_frame_parts(templates, cosited_pair(pci, cosited_pci), bandwidth_mhz)


def pair_frame_folds(templates: SyncTemplates, pair: tuple[int, int],
                     bandwidth_mhz: float) -> tuple[np.ndarray, np.ndarray]:
    """(orders, (4, M, frame // 2 + 1)) the folds of ``pair_frame_parts``' four parts, which
    the pair's site coefficients scale as they scale the parts."""
    lower, higher = pair
    orders, own_a = templates.crs_folds(lower, bandwidth_mhz)
    own_b = templates.crs_folds(higher, bandwidth_mhz)[1]
    cross = templates.crs_folds(lower, bandwidth_mhz, higher)[1]
    return orders, np.concatenate([own_a[None], own_b[None], cross])


def pair_frame_parts(templates: SyncTemplates, pair: tuple[int, int], bandwidth_mhz: float) -> np.ndarray:
    """(4, frame) the parts of two co-sited sectors' known frame (``known_frame``) that their
    four site coefficients scale, the subframe-0 codes starting at sample 0: the codes' and
    CRS's |s_a|^2, |s_b|^2, 2Re(s_a s_b*) and 2Im(s_a s_b*) (a the lower PCI). Fixed for a pair
    and bandwidth: a stage that keeps them (and their spectra) builds a pair's frame as one
    small product per stack."""
    lower, higher = pair
    crs = np.concatenate([templates.code_aligned_crs(lower, bandwidth_mhz)[None],
                          templates.code_aligned_crs(higher, bandwidth_mhz)[None],
                          templates.code_aligned_crs(lower, bandwidth_mhz, higher)])
    return place_codes(crs.shape[1], lambda subframe: templates.pair_shapes(pair, subframe, 0.0)) + crs


def _numerology_for_rate(bandwidth_mhz: float, adc_rate_hz: float) -> Numerology:
    """The carrier's numerology at the smallest FFT size (its own or a power-of-two multiple,
    or of 2048: 30.72 MHz, which every ADC rate templates allow divides) whose sample rate
    the ADC rate divides, so its envelope can be sampled at the ADC rate."""
    standard = Numerology.for_bandwidth(bandwidth_mhz).fft_size
    sizes = sorted({standard << k for k in range(6)} | {BASE_FFT * _OVERSAMPLING << k for k in range(2)})
    for size in (s for s in sizes if s >= standard):
        rate = size * BASE_RATE_HZ / BASE_FFT
        if abs(rate / adc_rate_hz - round(rate / adc_rate_hz)) < 1e-9 and rate >= adc_rate_hz:
            return Numerology.for_bandwidth(bandwidth_mhz, fft_size=size)
    raise ValueError(f"no FFT size puts a {bandwidth_mhz:g} MHz carrier at a multiple of {adc_rate_hz:g} Hz")


def _cross_envelopes(pci_a: int, pci_b: int, subframe: int, step: int) -> tuple[np.ndarray, int]:
    """2Re and 2Im of s_a s_b* with b starting ``step`` waveform samples after a, and where
    the product array begins relative to a's start (waveform samples)."""
    a, b = sync_code_waveform(pci_a, subframe), sync_code_waveform(pci_b, subframe)
    first = min(0, step)
    aligned_a = np.zeros(len(a) + abs(step), dtype=np.complex128)
    aligned_b = np.zeros_like(aligned_a)
    aligned_a[-first : -first + len(a)] = a
    aligned_b[step - first : step - first + len(b)] = b
    product = aligned_a * np.conj(aligned_b)
    return np.stack([2 * product.real, 2 * product.imag]), first


def _from_grid(grid: np.ndarray, delay_samples: float) -> np.ndarray:
    """Row of a (FRACTION_GRID, ..., length) grid of shapes starting at k / FRACTION_GRID,
    moved by whole samples so the shape starts at ``delay_samples`` (zeros shifted in)."""
    whole = math.floor(delay_samples)
    step = int(round((delay_samples - whole) * FRACTION_GRID))
    whole, step = whole + step // FRACTION_GRID, step % FRACTION_GRID
    base = grid[step]
    length = base.shape[-1]
    out = np.zeros_like(base)
    if 0 <= whole < length:
        out[..., whole:] = base[..., : length - whole]
    elif -length < whole < 0:
        out[..., :whole] = base[..., -whole:]
    return out


@lru_cache(maxsize=4)
def _all_templates(config: FrontendConfig) -> np.ndarray:
    templates = SyncTemplates(config)
    envelopes = np.array(
        [np.abs(sync_code_waveform(pci, sf)) ** 2 for pci in range(N_CELL_IDS) for sf in (0, 5)]
    )
    out = np.concatenate(
        [templates.response(batch, _WAVEFORM_RATE)[:, 0] for batch in np.array_split(envelopes, 18)]
    )
    out = out.reshape(N_CELL_IDS, 2, templates.length)
    out.flags.writeable = False
    return out


def sync_code_offset_seconds() -> float:
    """Time from a frame's start to its (subframe 0) sync code: the SSS symbol's CP start."""
    return sync_code_start_base() / BASE_RATE_HZ
