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
estimate is from the best possible. A window that cannot be timed at all (no variation, a
length that fits no template) is reported as ``UNTIMEABLE`` and skipped; the stage never raises
on what it is fed.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.templates import SyncTemplates, code_template
from deepsync.timing.crlb import delay_crlb, fit_amplitude
from deepsync.timing.estimators import (
    TimingEstimate,
    estimate_fft_upsampled,
    estimate_ml,
    estimate_parabolic,
    noise_psd,
)
from deepsync.types import CellTiming, Health, HealthKind, SyncWindow


class Estimator(enum.Enum):
    """The classical sub-sample estimators (``timing.estimators``); the value is the name a
    ``CellTiming`` carries."""

    ML = "ml"  # maximum likelihood, prewhitened by the noise spectrum measured from the rows
    ML_WHITE = "ml_white"  # maximum likelihood with white weights
    FFT_UPSAMPLED = "fft_upsampled"  # band-limited correlation on a 32x finer grid
    PARABOLIC = "parabolic"  # integer-lag correlation and a parabola through its peak


@dataclass(frozen=True)
class TimingConfig:
    estimator: Estimator = Estimator.ML
    weak_std_samples: float = 1.0  # flag an arrival whose 1-sigma exceeds this (1 sample = 156 m at 1.92 MHz)

    def __post_init__(self) -> None:
        if not isinstance(self.estimator, Estimator):
            raise ValueError(f"estimator must be one of {', '.join(e.value for e in Estimator)}, got {self.estimator!r}")
        if not (math.isfinite(self.weak_std_samples) and self.weak_std_samples > 0):
            raise ValueError(f"weak_std_samples must be a positive number, got {self.weak_std_samples!r}")


@dataclass(frozen=True)
class TimingResult:
    """The arrivals of one stack's cells, and the cells that could not be timed."""

    cells: tuple[CellTiming, ...]
    events: tuple[Health, ...] = field(default=())


class TimingStage:
    """Times every detected cell with one classical estimator (``TimingConfig.estimator``)."""

    def __init__(self, frontend: FrontendConfig, config: TimingConfig | None = None) -> None:
        self.config = config or TimingConfig()
        self.templates = SyncTemplates(frontend)
        self.sample_rate = frontend.adc_rate_hz
        self._single: dict[int, np.ndarray] = {}  # PCI -> template: 3 ms to compute, the same every stack

    def process(self, windows: Sequence[SyncWindow]) -> TimingResult:
        """Arrivals of the given cells; what cannot be timed becomes an ``UNTIMEABLE`` event."""
        cells, events = [], []
        for window in windows:
            try:
                cells.append(self.time_cell(window))
            except ValueError as error:
                events.append(Health(HealthKind.UNTIMEABLE, f"PCI {window.pci} at sample {window.coarse_index}: {error}",
                                     window.coarse_index))
        return TimingResult(tuple(cells), tuple(events))

    def time_cell(self, window: SyncWindow) -> CellTiming:
        """One cell's arrival; ValueError if its windows cannot be timed."""
        template = self._template(window)
        spare = window.window_length - len(template)
        if spare < 2 or spare % 2:
            raise ValueError(f"windows of {window.window_length} samples do not hold the {len(template)}-sample "
                             "template with an equal margin either side (another sample rate?)")
        margin = spare // 2
        psd = noise_psd(window.windows)
        estimate = self._estimate(window.windows, template, margin, psd)
        amplitude = fit_amplitude(window.windows.mean(axis=0), template, margin, estimate.offset, psd)
        bound = delay_crlb(template, amplitude, psd, window.n_frames, self.sample_rate, window.window_length)
        flags = ()
        if estimate.std > self.config.weak_std_samples:
            flags = (Health(HealthKind.WEAK_TIMING, f"PCI {window.pci}: 1-sigma {estimate.std:.2f} samples, beyond "
                            "the estimator's threshold: the arrival may be far off", window.coarse_index),)
        return CellTiming(
            pci=window.pci,
            toa=window.coarse_index + estimate.offset,
            toa_std=estimate.std,
            snr_db=estimate.snr_db,
            estimator=self.config.estimator.value,
            crlb_std=bound.std_samples,
            flags=flags,
            earfcn=window.earfcn,
            # RMS volts of the fitted code envelope: comparable between a single code's
            # template and a co-sited pair's, whatever their scale
            amplitude=abs(amplitude) * float(np.sqrt(np.mean(template**2))),
        )

    def _template(self, window: SyncWindow) -> np.ndarray:
        """The cell's code template; a pair's is cheap (cached shapes), a single PCI's is kept."""
        if window.cosited_pci is not None:
            return code_template(self.templates, window.pci, window.cosited_pci, window.site_coefficients)
        if window.pci not in self._single:
            self._single[window.pci] = code_template(self.templates, window.pci)
        return self._single[window.pci]

    def _estimate(self, windows: np.ndarray, template: np.ndarray, margin: int, psd: np.ndarray) -> TimingEstimate:
        estimator = self.config.estimator
        if estimator is Estimator.ML:
            return estimate_ml(windows, template, margin, psd)
        if estimator is Estimator.ML_WHITE:
            return estimate_ml(windows, template, margin)
        if estimator is Estimator.FFT_UPSAMPLED:
            return estimate_fft_upsampled(windows, template, margin)
        return estimate_parabolic(windows, template, margin)
