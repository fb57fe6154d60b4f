"""The timing stage: each detected cell's windows in, its sub-sample arrival with an honest 1-sigma out.

``TimingStage.process(windows)`` takes the :class:`~deepsync.types.SyncWindow` s of one stack,
exactly what a ``SyncWindowArray`` message carries, so the timing node and bag replay call it
with what they received and the pipeline with what the sync stage produced. The template of
each cell is rebuilt from the window's own fields (``code_template``: its PCI, or a co-sited
pair's fitted model) for the front end the stage was built for; the margin of the windows is
what their length leaves around that template.

Per cell: ``toa`` = ``coarse_index`` + the estimator's offset (stream samples), its 1-sigma
(see ``timing.estimators``: main lobe, posterior beyond it, model floor), the SNR, the code's
fitted envelope amplitude (an RSSI: the square law makes it proportional to power), and the
Cramer-Rao bound at the measured amplitude and noise spectrum, so a consumer sees how far an
estimate is from the best possible. An ``ml_frame`` arrival whose correlation peak is wider than
the clean template's by more than ``peak_width_allowance_samples`` (``peak_excess_width``: paths
within a sample or two merged into one peak, whose maximum then need not be the first path's)
gets ``smear_std_per_sample`` of 1-sigma per sample beyond it, in quadrature, and a
``SMEARED_PEAK`` flag naming the cell: on the simulated city drive such peaks (0.5-0.7 samples
wider) came with half their arrivals locked more than a sample late, while the estimator's
sigma, which measures noise, claimed 0.03. A window that cannot be timed at all (no variation, a
length that fits no template) is reported as ``UNTIMEABLE`` and skipped, and so is a cell whose
code fits below ``min_snr_db`` (-30 dB) at the sync stage's lock: long stacks let a strong cell's
frame-periodic structure pass the search's threshold for the codes of PCIs the tower database
lists but nobody transmits, which then fit at -60 to -20 dB with 1-sigmas of kilometres (the
route set: 3010 such arrivals, 91 % below -30 dB; of the 47 411 arrivals of cells that exist,
0.18 % were below it, 99 % of them more than a sample off). The stage never raises on what it is
fed.

Estimators: every one registered in ``timing.registry`` (``Estimator.named``), chosen once by
what it times a cell from (``Input``): the classical ones of ``timing.estimators`` from the
windows; ``ml_frame`` (the default), ML over everything a known cell sends the same in every
frame, its codes and its CRS (``estimate_ml_frame``), in the stack's mean frame
(``StackWindows.frame``, sent by the sync stage when the tower database gives a reported cell's
bandwidth), searched within the windows' margin of the sync stage's code lock, which picks the
CRS comb's period; ``network`` and ``network_ml`` from the DeepSync timing network
(``timing.network``, all cells of a stack in one batch). Where an estimator's input is missing
(no frame or bandwidth; a cell outside the network's training range) its ``fallback`` times the
cell, and ``TimingResult.fallbacks`` says which network cells and why. torch is imported only
when a network estimator is chosen.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.fft

from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.templates import (
    SyncTemplates,
    code_template,
    cosited_pair,
    known_frame,
    pair_coefficients,
    pair_frame_folds,
    pair_frame_parts,
)
from deepsync.schema import check_settings, setting
from deepsync.timing import network_install_hint
from deepsync.timing.crlb import delay_crlb, fit_amplitude, snr_db
from deepsync.timing.estimators import SNR_FLOOR_DB, FrameTiming, estimate_ml_frame, frame_spectrum, noise_psd
from deepsync.timing.registry import DEFAULT, ESTIMATORS, Estimator, Input
from deepsync.types import FRAME_SECONDS, CellTiming, Health, HealthKind, StackWindows, SyncWindow


@dataclass(frozen=True)
class TimingConfig:
    estimator: Estimator = setting(DEFAULT, help="Sub-sample timing estimator.", choices=ESTIMATORS)
    weak_std_samples: float = setting(1.0, help="Flag an arrival whose 1-sigma exceeds this (1 sample = 156 m at "
                                      "1.92 MS/s).", unit="samples", bounds=(0.0, 1e6), open_low=True)
    min_snr_db: float = setting(
        -30.0, help="Drop an arrival whose code fits below this SNR (the stack's): nothing of the cell is at the "
        "sync stage's lock, a false detection (-60: keep every one).", unit="dB", bounds=(-60.0, 60.0))
    checkpoint: str | None = setting(None, help="Timing-network checkpoint for a network estimator.")
    peak_width_allowance_samples: float = setting(
        0.3, help="Excess width of a cell's full-frame correlation peak (at 30 % of it, beyond the clean template's) "
        "that noise and a close echo make; a wider peak is smeared.", unit="samples", bounds=(0.0, 100.0))
    smear_std_per_sample: float = setting(
        5.0, help="1-sigma added to an ml_frame arrival per sample its peak is smeared beyond the allowance (0: "
        "none): a smeared peak may lock samples late.", unit="samples per sample", bounds=(0.0, 1000.0))

    def __post_init__(self) -> None:
        if not isinstance(self.estimator, Estimator):  # a name is looked up by Estimator.named, never taken as is
            raise ValueError(f"estimator must be one of {', '.join(Estimator.names())}, got {self.estimator!r}")
        check_settings(self)


@dataclass(frozen=True)
class TimingResult:
    """The arrivals of one stack's cells, and the cells that could not be timed."""

    cells: tuple[CellTiming, ...]
    events: tuple[Health, ...] = field(default=())
    fallbacks: tuple[tuple[int, str], ...] = field(default=())  # (PCI, why) timed by ML instead of the network


class TimingStage:
    """Times every detected cell with the configured estimator (``TimingConfig.estimator``)."""

    def __init__(self, frontend: FrontendConfig, config: TimingConfig | None = None,
                 templates: SyncTemplates | None = None) -> None:
        """``templates``: the front end's, where another stage of the process keeps them (the
        pipeline's sync stage): built once instead of twice (start-up, ~0.1-0.2 s)."""
        if templates is not None and templates.config != frontend:
            raise ValueError("the templates given are not those of this front end")
        self.config = config or TimingConfig()
        self.frontend = frontend
        self.templates = templates or SyncTemplates(frontend)
        self.sample_rate = frontend.adc_rate_hz
        self._single: dict[int, np.ndarray] = {}  # PCI -> template: 3 ms to compute, the same every stack
        # (PCI, MHz) -> known frame, its rfft and folds; (PCI, PCI, MHz) -> a pair's parts and theirs
        self._frames: dict[tuple, tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]] = {}
        self.network = None
        if self.config.estimator.uses_network:
            try:
                from deepsync.timing.network import NetworkEstimator  # torch is imported here only
            except ModuleNotFoundError as error:
                raise ValueError(f"the network estimator needs {error.name}: {network_install_hint(error.name)} "
                                 "(or choose a classical estimator)") from None
            self.network = NetworkEstimator(self.config.checkpoint)

    def with_config(self, config: TimingConfig) -> TimingStage:
        """A stage like this one with ``config`` (a parameter changed at run time), sharing its
        templates and, where the checkpoint is the same, its network; ValueError if a network
        must be loaded and cannot be. This stage is never changed, so a caller can build the new
        one first and switch to it only once every other check has passed."""
        if config.estimator.uses_network and (self.network is None or config.checkpoint != self.config.checkpoint):
            return TimingStage(self.frontend, config, self.templates)
        stage = copy.copy(self)
        stage.config = config
        if not config.estimator.uses_network:
            stage.network = None
        return stage

    def process(self, windows: StackWindows | Sequence[SyncWindow]) -> TimingResult:
        """Arrivals of one stack's cells (its windows alone, or with its mean frame, which
        ``ml_frame`` needs); what cannot be timed becomes an ``UNTIMEABLE`` event."""
        stack = windows if isinstance(windows, StackWindows) else None
        spectrum = self._frame_spectrum(stack)
        cells, events, fallbacks, for_network = [], [], [], []
        frame_fits: dict[tuple, FrameTiming] = {}  # a co-sited pair's two windows: one fit
        for window in (windows if stack is None else stack.windows):
            reason = None if self.network is None else self.network.refusal(
                window, self.sample_rate, self.templates.length)
            if self.network is not None and reason is None:
                for_network.append(window)
                continue
            if reason is not None:
                fallbacks.append((window.pci, reason))
            try:
                if spectrum is not None and window.bandwidth_mhz is not None:
                    cells.append(self._seen(self._frame_cell(window, stack, spectrum, frame_fits)))
                    continue
                cells.append(self._seen(self.time_cell(window, self.config.estimator.on_windows_only)))
            except ValueError as error:
                events.append(self._untimeable(window, error))
        if for_network:
            templates = [self._template(w) for w in for_network]
            estimates = self.network.estimate([w.windows for w in for_network], templates)
            for window, template, (offset, std) in zip(for_network, templates, estimates):
                try:
                    cells.append(self._seen(self._network_cell(window, template, offset, std)))
                except ValueError as error:
                    events.append(self._untimeable(window, error))
        return TimingResult(tuple(cells), tuple(events), tuple(fallbacks))

    def _network_cell(self, window: SyncWindow, template: np.ndarray, offset: float, std: float) -> CellTiming:
        psd = noise_psd(window.windows)
        estimator = self.config.estimator
        estimate = estimator.after_network(window.windows, template, self._margin(window, template), psd, offset, std)
        return self._cell(window, template, psd, estimate.offset, estimate.std, estimator,
                          None if math.isnan(estimate.snr_db) else estimate.snr_db)

    def _seen(self, cell: CellTiming) -> CellTiming:
        """The cell, if its code shows at the lock (``min_snr_db``); else ValueError saying so."""
        if cell.snr_db < self.config.min_snr_db:
            raise ValueError(f"its code fits at SNR {cell.snr_db:.0f} dB, below min_snr_db {self.config.min_snr_db:g} "
                             "dB: nothing of the cell is at the lock (a false detection)")
        return cell

    @staticmethod
    def _untimeable(window: SyncWindow, error: ValueError) -> Health:
        return Health(HealthKind.UNTIMEABLE, f"PCI {window.pci} at sample {window.coarse_index}: {error}",
                      window.coarse_index)

    def time_cell(self, window: SyncWindow, estimator: Estimator | None = None) -> CellTiming:
        """One cell's arrival from its windows alone, by ``estimator`` (default: the configured
        one) or, for one that needs more (the stack's frame, the network), by its fallback;
        ValueError if the windows cannot be timed."""
        estimator = (estimator or self.config.estimator).on_windows_only
        template = self._template(window)
        margin = self._margin(window, template)
        psd = noise_psd(window.windows)
        estimate = estimator.on_windows(window.windows, template, margin, psd)
        return self._cell(window, template, psd, estimate.offset, estimate.std, estimator, estimate.snr_db)

    def _frame_spectrum(self, stack: StackWindows | None) -> np.ndarray | None:
        """The spectrum of the stack's mean frame, if ``ml_frame`` is to use it: sent, one frame
        long at this stage's rate, finite and varying (else its cells are timed on their windows,
        which then say what is wrong)."""
        if (self.config.estimator.input is not Input.FRAME or stack is None or stack.frame is None
                or stack.frame.size != round(self.sample_rate * FRAME_SECONDS)):
            return None
        try:
            return frame_spectrum(stack.frame)
        except ValueError:
            return None

    def _frame_cell(self, window: SyncWindow, stack: StackWindows, spectrum: np.ndarray,
                    fits: dict[tuple, FrameTiming]) -> CellTiming:
        """A cell timed by its known frame (``estimate_ml_frame``) within the windows' margin
        of the sync stage's coarse code start. ``fits``: those of the stack so far, by what
        decides them (the two sectors of a pair found together share one window, template and fit)."""
        codes = self._template(window)
        coefficients = None if window.site_coefficients is None else tuple(map(float, window.site_coefficients))
        key = (frozenset((window.pci, window.cosited_pci)), window.coarse_index, window.bandwidth_mhz, coefficients)
        if key not in fits:
            template, template_spectrum, folds = self._known_frame(window)
            start = (window.coarse_index - stack.first_sample_index) % len(template)
            fits[key] = estimate_ml_frame(spectrum, template, start, self._margin(window, codes), template_spectrum,
                                          folds)
        timing = fits[key]
        estimate = timing.estimate
        noise = float(np.mean(timing.stacked_psd))
        config = self.config
        smear = config.smear_std_per_sample * max(timing.peak_excess - config.peak_width_allowance_samples, 0.0)
        std = math.hypot(estimate.std, smear)
        return CellTiming(
            pci=window.pci,
            # the mean frame holds the code frame_delay later than the first frame, the windows' time base
            toa=window.coarse_index + estimate.offset - stack.frame_delay,
            toa_std=std,
            # the codes' SNR at the fitted scale, as for the other estimators
            snr_db=max(snr_db(timing.amplitude, codes, noise), SNR_FLOOR_DB),
            estimator=self.config.estimator.name,
            crlb_std=timing.crlb_std,
            flags=self._weak(window, std) + self._smeared(window, timing.peak_excess, smear),
            earfcn=window.earfcn,
            amplitude=timing.amplitude * float(np.sqrt(np.mean(codes**2))),
        )

    def _known_frame(self, window: SyncWindow) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """The cell's known frame, its spectrum and what sampling folds into it
        (``SyncTemplates.crs_folds``): a single PCI's kept; a pair's built from its fit and the
        pair's kept parts (``pair_frame_parts``, ``pair_frame_folds``)."""
        if window.cosited_pci is None:
            key = (window.pci, window.bandwidth_mhz)
            if key not in self._frames:
                template = known_frame(self.templates, window.pci, window.bandwidth_mhz)
                self._frames[key] = (template, scipy.fft.rfft(template),
                                     self.templates.crs_folds(window.pci, window.bandwidth_mhz))
            return self._frames[key]
        coefficients = pair_coefficients(window.pci, window.cosited_pci, window.site_coefficients)
        pair = cosited_pair(window.pci, window.cosited_pci)
        key = (*pair, window.bandwidth_mhz)
        if key not in self._frames:
            parts = pair_frame_parts(self.templates, pair, window.bandwidth_mhz)
            self._frames[key] = (parts, scipy.fft.rfft(parts, axis=1), pair_frame_folds(self.templates, pair,
                                                                                          window.bandwidth_mhz))
        parts, spectra, (orders, folds) = self._frames[key]
        return coefficients @ parts, coefficients @ spectra, (orders, np.tensordot(coefficients, folds, axes=1))

    @staticmethod
    def _margin(window: SyncWindow, template: np.ndarray) -> int:
        spare = window.window_length - len(template)
        if spare < 2 or spare % 2:
            raise ValueError(f"windows of {window.window_length} samples do not hold the {len(template)}-sample "
                             "template with an equal margin either side (another sample rate?)")
        return spare // 2

    def _cell(self, window: SyncWindow, template: np.ndarray, psd: np.ndarray, offset: float, std: float,
              estimator: Estimator, snr: float | None = None) -> CellTiming:
        """The CellTiming of an estimate: its amplitude, SNR and Cramer-Rao bound measured here."""
        margin = self._margin(window, template)
        amplitude = fit_amplitude(window.windows.mean(axis=0), template, margin, offset, psd)
        bound = delay_crlb(template, amplitude, psd, window.n_frames, self.sample_rate, window.window_length)
        if snr is None:  # the estimators' definition: the fitted code against the stacked noise
            snr = max(snr_db(amplitude, template, float(np.mean(psd)) / window.n_frames), SNR_FLOOR_DB)
        return CellTiming(
            pci=window.pci,
            toa=window.coarse_index + offset,
            toa_std=std,
            snr_db=snr,
            estimator=estimator.name,
            crlb_std=bound.std_samples,
            flags=self._weak(window, std),
            earfcn=window.earfcn,
            # RMS volts of the fitted code envelope: comparable between a single code's
            # template and a co-sited pair's, whatever their scale
            amplitude=abs(amplitude) * float(np.sqrt(np.mean(template**2))),
        )

    def _weak(self, window: SyncWindow, std: float) -> tuple[Health, ...]:
        if std <= self.config.weak_std_samples:
            return ()
        return (Health(HealthKind.WEAK_TIMING, f"PCI {window.pci}: 1-sigma {std:.2f} samples, beyond the "
                       "estimator's threshold: the arrival may be far off", window.coarse_index),)

    def _smeared(self, window: SyncWindow, excess: float, smear: float) -> tuple[Health, ...]:
        if smear <= 0.0:
            return ()
        return (Health(HealthKind.SMEARED_PEAK, f"PCI {window.pci}: correlation peak {excess:.2f} samples wider than "
                       f"one path's: multipath may hold the arrival late; 1-sigma widened by {smear:.2f} samples",
                       window.coarse_index),)

    def _template(self, window: SyncWindow) -> np.ndarray:
        """The cell's code template; a pair's is cheap (cached shapes), a single PCI's is kept."""
        if window.cosited_pci is not None:
            return code_template(self.templates, window.pci, window.cosited_pci, window.site_coefficients)
        if window.pci not in self._single:
            self._single[window.pci] = code_template(self.templates, window.pci)
        return self._single[window.pci]
