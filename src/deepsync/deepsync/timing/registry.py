"""Every sub-sample timing estimator, by name: the one place they are listed.

The timing stage, ``deepsync evaluate-timing``, the CLI's ``--estimator`` and the timing node's
``estimator`` parameter all take their choices from ``ESTIMATORS``; adding an estimator is one
``register`` call here (and its function in ``timing.estimators``). An unknown name is a
ValueError that lists the known ones, never a fallback.

An estimator times a cell from one of three inputs (``Input``): its code windows alone (the
classical estimators: ``on_windows``), the stack's mean frame (``ml_frame``: the stage fits the
cell's whole known frame), or the timing network's estimate (``after_network`` turns the
network's offset and sigma into the cell's). Where its input is missing (no mean frame, a cell
outside the network's training range) a cell is timed by its ``fallback``, an estimator of
windows.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from deepsync.timing.estimators import TimingEstimate, estimate_fft_upsampled, estimate_ml, estimate_parabolic

# network_ml's sigma, added in quadrature: ML's own std covers noise and the lobe, not the
# first path that multipath hides behind the envelope's peak. 0.2 samples (31 m) puts 60-72 %
# of the errors within +-1 sigma in every SNR bin of the validation split (38.901 TDL-A..E).
MULTIPATH_FLOOR_SAMPLES = 0.2


class Input(enum.Enum):
    """What an estimator times a cell from."""

    WINDOWS = "windows"  # the cell's code windows (n_frames x length)
    FRAME = "frame"  # the stack's mean frame, with the cell's whole known frame as template
    NETWORK = "network"  # the timing network's offset and sigma for the cell's windows


class WindowsEstimate(Protocol):
    """A classical estimator: the code's offset in ``windows`` (template placed ``margin`` samples
    in), whitened by the rows' noise spectrum ``psd`` where the estimator uses it."""

    def __call__(self, windows: np.ndarray, template: np.ndarray, margin: int,
                 psd: np.ndarray) -> TimingEstimate: ...


class NetworkEstimate(Protocol):
    """What a network estimator makes of the network's ``offset`` and ``std`` for a cell;
    ``TimingEstimate.snr_db`` NaN: the stage measures the SNR at the offset."""

    def __call__(self, windows: np.ndarray, template: np.ndarray, margin: int, psd: np.ndarray,
                 offset: float, std: float) -> TimingEstimate: ...


@dataclass(frozen=True)
class Estimator:
    """A registered estimator; ``name`` is what configs, the CLI and a ``CellTiming`` carry."""

    name: str
    summary: str  # one line for help texts
    input: Input
    on_windows: WindowsEstimate | None = None  # Input.WINDOWS
    after_network: NetworkEstimate | None = None  # Input.NETWORK
    fallback: str | None = None  # the windows estimator for a cell this one's input misses

    def __post_init__(self) -> None:
        needs = {Input.WINDOWS: self.on_windows, Input.NETWORK: self.after_network, Input.FRAME: True}[self.input]
        if needs is None:
            raise ValueError(f"estimator {self.name}: an estimator of {self.input.value} needs its function")
        if self.input is not Input.WINDOWS and self.fallback is None:
            raise ValueError(f"estimator {self.name}: an estimator of {self.input.value} needs a windows fallback")

    @property
    def uses_network(self) -> bool:
        """Whether the stage must load the timing network (and torch) for it."""
        return self.input is Input.NETWORK

    @property
    def on_windows_only(self) -> Estimator:
        """The estimator that times this one's cells from their windows alone: itself, or its fallback."""
        return self if self.input is Input.WINDOWS else Estimator.named(self.fallback)

    @classmethod
    def named(cls, name: str) -> Estimator:
        """The estimator called ``name``; ValueError listing the names."""
        try:
            return ESTIMATORS[name]
        except (KeyError, TypeError):
            raise ValueError(f"estimator must be one of {', '.join(ESTIMATORS)}, got {name!r}") from None

    @staticmethod
    def names() -> tuple[str, ...]:
        """Every registered estimator's name."""
        return tuple(ESTIMATORS)


ESTIMATORS: dict[str, Estimator] = {}


def register(estimator: Estimator) -> Estimator:
    """Adds ``estimator`` to ``ESTIMATORS``; ValueError if its name or its fallback is not right."""
    if estimator.name in ESTIMATORS:
        raise ValueError(f"estimator {estimator.name} is registered already")
    if estimator.fallback is not None and (estimator.fallback not in ESTIMATORS
                                           or ESTIMATORS[estimator.fallback].input is not Input.WINDOWS):
        raise ValueError(f"estimator {estimator.name}: its fallback {estimator.fallback!r} must be a registered "
                         "estimator of windows")
    ESTIMATORS[estimator.name] = estimator
    return estimator


def refine_with_ml(windows: np.ndarray, template: np.ndarray, margin: int, psd: np.ndarray, offset: float,
                   std: float) -> TimingEstimate:
    """``network_ml``: ML's maximum within the network's ``offset`` +- 2 ``std`` (at least a
    sample; where the network is unsure, ML searches widely), its std with the multipath floor."""
    half = max(1.0, 2 * std)
    refined = estimate_ml(windows, template, margin, psd, within=(offset - half, offset + half))
    return TimingEstimate(refined.offset, math.hypot(refined.std, MULTIPATH_FLOOR_SAMPLES), refined.snr_db,
                          "network_ml")


def _network_as_is(windows: np.ndarray, template: np.ndarray, margin: int, psd: np.ndarray, offset: float,
                   std: float) -> TimingEstimate:
    return TimingEstimate(offset, std, math.nan, "network")


# the estimators of windows come first: the others' fallbacks must be registered before them
ML = register(Estimator("ml", "maximum likelihood, prewhitened by the noise spectrum measured from the rows",
                        Input.WINDOWS, on_windows=lambda w, t, m, psd: estimate_ml(w, t, m, psd)))
register(Estimator("ml_white", "maximum likelihood with white weights", Input.WINDOWS,
                   on_windows=lambda w, t, m, psd: estimate_ml(w, t, m)))
register(Estimator("fft_upsampled", "band-limited correlation on a 32x finer grid", Input.WINDOWS,
                   on_windows=lambda w, t, m, psd: estimate_fft_upsampled(w, t, m)))
register(Estimator("parabolic", "integer-lag correlation and a parabola through its peak", Input.WINDOWS,
                   on_windows=lambda w, t, m, psd: estimate_parabolic(w, t, m)))
ML_FRAME = register(Estimator("ml_frame", "ML over a known cell's whole frame (codes and CRS) where the tower "
                              "database gives its bandwidth, else ml", Input.FRAME, fallback="ml"))
register(Estimator("network", "the DeepSync timing network (needs torch); ml outside its training range",
                   Input.NETWORK, after_network=_network_as_is, fallback="ml"))
register(Estimator("network_ml", "ML's maximum inside the network's interval (estimate +- 2 sigma, at least a "
                   "sample; needs torch)", Input.NETWORK, after_network=refine_with_ml, fallback="ml"))
DEFAULT = ML_FRAME
