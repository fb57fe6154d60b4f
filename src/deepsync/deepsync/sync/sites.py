"""Co-sited sectors found together: the site hypothesis of the known-PCI cell search.

Two sectors of one site on one carrier send their sync codes at the same instant, and at the
receiver the codes add before the square law:

    |x s_a + y s_b|^2 = |x|^2 |s_a|^2 + |y|^2 |s_b|^2 + Re(x y*) 2Re(s_a s_b*) - Im(x y*) 2Im(s_a s_b*)

The sectors' transmit chains and antennas fix x y* while the receiver stays put, so the cross
term survives stacking, and it dominates: a sync code's envelope is nearly constant, so |s|^2
varies little about its mean, while s_a s_b* is all variation. At equal power neither sector's
own template matches the sum (on the campus bag about 1 sigma, against 5 to 14 sigma for the pair).

So the pair's code is sought in the 4-dimensional span of those four shapes, coefficients
unknown. At every lag the four correlations c, whose noise covariance S is measured from the
stack itself (robustly, as the single templates' spreads are), give c' S^-1 c: chi-square with 4
degrees of freedom on noise alone. It enters the CFAR as the Gaussian z of the same tail
probability, beside the single templates' z. A peak counts as a pair only if the pair
explains significantly more than its better sector alone: one sector means E[c] = amplitude x
that sector's column g of the templates' Gram matrix, whose GLR statistic is
(g' S^-1 c)^2 / (g' S^-1 g); the pair's excess over it is chi-square with 3 degrees of freedom
(a generalised likelihood-ratio test), and must also be a fair share of it, since a lone
sector's template mismatch at high SNR leaks into the other shapes. Otherwise the single-cell
search keeps the peak. ``deepsync.sync.search`` decides when pairs are tried.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.special
import scipy.stats

from deepsync.frontend.templates import SyncTemplates, code_template, cosited_pair
from deepsync.numeric import mad_spread, parabolic_peak
from deepsync.sync.correlation import correlate_every, frame_code_windows, frame_spectra, unit_frame_parts

COMPONENTS = 4  # |s_a|^2, |s_b|^2, 2Re(s_a s_b*), 2Im(s_a s_b*)
COVARIANCE_STEP = 32  # every how many lags the pairs' noise covariances are measured on
_EXACT_FROM_Z = 2.9
_EXACT_FROM_CHI2 = float(scipy.stats.chi2.isf(scipy.stats.norm.sf(_EXACT_FROM_Z), COMPONENTS))


def chi2_4_z(statistic: np.ndarray) -> np.ndarray:
    """The Gaussian z with the same upper-tail probability as a chi-square(4) value, exact
    (closed form: log P(X > x) = -x/2 + log(1 + x/2)) from z = 2.9 up, where thresholds and
    peaks are. Below, where only the order matters, Fisher's sqrt(2x) - sqrt(7), capped at
    2.9 so the whole map stays monotonic, spares the exact inverse on every lag."""
    z = np.minimum(np.sqrt(2 * np.maximum(statistic, 0)) - math.sqrt(7), _EXACT_FROM_Z).astype(statistic.dtype)
    tail = statistic > _EXACT_FROM_CHI2
    x = statistic[tail].astype(np.float64)
    z[tail] = -scipy.special.ndtri_exp(-x / 2 + np.log1p(x / 2))
    return z


@dataclass(frozen=True)
class SiteFit:
    """Least-squares model of two co-sited sectors' coinciding codes."""

    pcis: tuple[int, int]
    coefficients: tuple[float, float, float, float]  # scales of |s_a|^2, |s_b|^2, 2Re(s_a s_b*), 2Im(s_a s_b*)

    def template(self, templates: SyncTemplates, subframe: int = 0, delay: float = 0.0) -> np.ndarray:
        """What the pair's code looks like in the envelope, starting at ``delay`` samples."""
        return code_template(templates, *self.pcis, self.coefficients, subframe, delay)


@dataclass(frozen=True)
class SiteMatch:
    """A site peak explained by two sectors."""

    fit: SiteFit
    frame_offset: int  # subframe-0 code start within the frame
    fraction: float  # sub-sample refinement, samples
    snr_db: float  # pair model energy / residual energy in the two code windows
    z: float  # the pair statistic there, as the Gaussian z of its tail probability
    ranked: tuple[tuple[tuple[int, int], float, int], ...]  # (pair, multiple correlation, lag), best first


class SiteSearch:
    """The site hypotheses of a known-PCI search: one per co-sited pair, per template phase."""

    def __init__(self, templates: SyncTemplates, pairs: list[tuple[int, int]], allowed: np.ndarray,
                 phases: np.ndarray) -> None:
        unknown = sorted({pci for pair in pairs for pci in pair} - {int(pci) for pci in allowed})
        if unknown:
            raise ValueError(f"co-sited PCIs {unknown} are not among the allowed PCIs")
        self.templates = templates
        self.pairs = [tuple(sorted(pair)) for pair in pairs]
        self.phases = phases
        parts = np.empty((len(pairs), len(phases), COMPONENTS, 2, templates.length))
        for k, (a, b) in enumerate(self.pairs):  # exact shapes (the fraction grids are built on demand)
            for s, subframe in enumerate((0, 5)):
                parts[k, :, 0, s] = templates.template(a, subframe, phases)
                parts[k, :, 1, s] = templates.template(b, subframe, phases)
                for p, phase in enumerate(phases):
                    parts[k, p, 2:, s] = templates.cross_terms(a, b, subframe, phase, phase, templates.length)
        self._parts = unit_frame_parts(parts)  # (pairs, phases, 4, 2, L)
        self._gram = np.einsum("kpisl,kpjsl->kpij", self._parts, self._parts)  # (pairs, phases, 4, 4)
        # orthonormal bases of each pair's span over both code windows, for candidate scores
        flat = self._parts.reshape(*self._parts.shape[:3], -1)
        self._bases = np.linalg.qr(np.swapaxes(flat, -1, -2))[0]  # (pairs, phases, 2L, 4)
        # the sectors' own shapes are the single-template search's (same unit frame templates):
        # their correlations are taken from it, rows (index in allowed) x phases + phase
        position = {int(pci): i for i, pci in enumerate(allowed)}
        own = np.array([[position[pci] for pci in pair] for pair in self.pairs], dtype=int).reshape(-1, 2)
        self._own_rows = own[:, None, :] * len(phases) + np.arange(len(phases))[None, :, None]  # (pairs, phases, 2)
        self._spectra: dict[int, np.ndarray] = {}  # cross-term shapes' spectra, by frame length

    @property
    def rows(self) -> int:
        """Hypotheses tested at every lag: one per pair and template phase."""
        return len(self.pairs) * len(self.phases)

    def pair_index(self, a: int, b: int) -> int | None:
        """Index of the pair of sectors ``a`` and ``b``, if they are one."""
        pair = cosited_pair(a, b)
        return self.pairs.index(pair) if pair in self.pairs else None

    def pairs_with(self, pci: int) -> np.ndarray:
        """Indices of the pairs ``pci`` belongs to."""
        return np.array([k for k, pair in enumerate(self.pairs) if pci in pair], dtype=int)

    def correlations(self, spectrum: np.ndarray, single: np.ndarray, pairs: np.ndarray, step: int = 1,
                     single_step: int = 1) -> np.ndarray:
        """(pairs, phases, 4, frame / step) correlations with the given pairs' unit frame
        templates at every ``step``-th lag, of the frame whose rfft is ``spectrum`` and whose
        correlations with the single-cell search's frame templates (all allowed PCIs x phases)
        are ``single``, at every ``single_step``-th lag (a divisor of ``step``): only the cross
        terms are new."""
        frame = single.shape[-1] * single_step
        if frame not in self._spectra:
            self._spectra[frame] = frame_spectra(self._parts[:, :, 2:], frame)
        own = single[:, :: step // single_step][self._own_rows[pairs]]  # sampled before the rows are gathered (copied)
        out = np.empty((*own.shape[:2], COMPONENTS, own.shape[-1]), dtype=np.float32)
        out[:, :, :2] = own
        out[:, :, 2:] = correlate_every(spectrum, self._spectra[frame][pairs], frame, step)
        return out

    def statistic(self, correlations: np.ndarray, covariances: np.ndarray) -> np.ndarray:
        """(frame,) Gaussian-equivalent z of c' S^-1 c at every lag, for the best of the pair
        hypotheses there: the correlations whitened (S = R R', w = R^-1 c), then |w|^2; the
        map to z is monotonic, so it is applied to the best hypothesis only."""
        whitening = np.linalg.inv(np.linalg.cholesky(covariances)).astype(np.float32)
        whitened = np.matmul(whitening, correlations)  # (pairs, phases, 4, frame)
        chi2 = np.einsum("kpcn,kpcn->kpn", whitened, whitened)
        return chi2_4_z(chi2.reshape(-1, chi2.shape[-1]).max(axis=0))

    def identify(self, centred: np.ndarray, code_start: int, pairs: np.ndarray, covariances: np.ndarray,
                 pair_false_alarm: float, min_gain: float, reach: int = 1) -> SiteMatch | None:
        """Which of ``pairs`` (indices; ``covariances`` their noise), at which sub-sample
        position and with which coefficients, explains a code within ``reach`` samples of
        ``code_start`` (subframe-0 code start, mod a frame); None if one sector alone explains
        it about as well: the pair must add significantly (at ``pair_false_alarm``, shared
        among the pairs tried) and at least ``min_gain`` x the sector's own statistic (template
        mismatch at high SNR leaks a little of a lone sector into the other shapes)."""
        frame, length = len(centred), self.templates.length
        lags = np.arange(-reach, reach + 1)
        windows = frame_code_windows(centred, code_start + lags, length)  # (lags, 2, L)
        c = np.einsum("kpcsl,nsl->kpcn", self._parts[pairs], windows)  # (pairs, phases, 4, lags)
        precisions = np.linalg.inv(covariances)
        full = np.einsum("kpin,kpij,kpjn->kpn", c, precisions, c)
        # one sector alone (module docstring): (g' S^-1 c)^2 / (g' S^-1 g), the better of the two
        gram = self._gram[pairs][..., :2]  # (pairs, phases, 4, sector)
        weights = np.einsum("kpij,kpjm->kpim", precisions, gram)
        alone = (np.einsum("kpim,kpin->kpmn", weights, c) ** 2
                 / np.einsum("kpim,kpim->kpm", weights, gram)[..., None]).max(axis=2)  # (pairs, phases, lags)
        k, p, n = np.unravel_index(np.argmax(full), full.shape)
        gain = full[k, p, n] - alone[k, p, n]
        # chdtri is chi2's isf without scipy.stats' overhead (0.2 ms a call)
        if gain < scipy.special.chdtri(COMPONENTS - 1, pair_false_alarm / len(pairs)) or gain < min_gain * alone[k, p, n]:
            return None
        # positions lag + phase on a half-sample grid; a parabola through the best and its neighbours
        positions = (lags[:, None] + self.phases[None, :]).ravel()
        order = np.argsort(positions)
        values = full[k].T.ravel()[order]
        best = int(np.argmax(values))
        refined = float(positions[order][best])
        if 0 < best < len(values) - 1:
            refined += 0.5 * parabolic_peak(values, best)  # grid step: half a sample
        whole = round(refined)
        offset, fraction = int((code_start + whole) % frame), refined - whole
        fit, snr_db = fit_site(self.templates, centred, self.pairs[pairs[k]], offset, fraction)
        flat = windows.reshape(len(lags), -1)
        flat = flat - flat.mean(axis=1, keepdims=True)
        explained = np.einsum("kpmc,nm->kpcn", self._bases[pairs], flat)  # (pairs, phases, 4, lags)
        score = np.sqrt(np.sum(explained**2, axis=2) / np.sum(flat**2, axis=1))  # multiple correlation
        best_per_pair = score.max(axis=1)  # (pairs, lags)
        ranked = sorted(
            ((self.pairs[pair], float(best_per_pair[j].max()), int(lags[best_per_pair[j].argmax()]))
             for j, pair in enumerate(pairs)),
            key=lambda item: -item[1],
        )
        z = float(chi2_4_z(np.array([full[k, p, n]]))[0])
        return SiteMatch(fit, offset, fraction, snr_db, z, tuple(ranked))


def fit_site(templates: SyncTemplates, centred: np.ndarray, pair: tuple[int, int], offset: int,
             fraction: float) -> tuple[SiteFit, float]:
    """Least squares of a co-sited ``pair``'s four shapes (one set of coefficients for both
    codes) plus a pedestal under each code, on the two code windows of the zero-mean stacked
    frame ``centred`` whose subframe-0 code starts ``offset + fraction`` samples in; the fit and
    its SNR (model energy over residual energy, dB)."""
    length = templates.length
    shapes = np.concatenate([templates.pair_shapes(pair, sf, fraction) for sf in (0, 5)], axis=1)
    pedestals = np.kron(np.eye(2), np.ones(length))
    basis = np.vstack([shapes, pedestals]).T  # (2L, 6)
    window = frame_code_windows(centred, np.array([offset]), length).ravel()
    coefficients, *_ = np.linalg.lstsq(basis, window, rcond=None)
    model = shapes.T @ coefficients[:COMPONENTS]
    residual = window - basis @ coefficients
    energy, rest = float(model @ model), float(residual @ residual)
    snr_db = 10 * math.log10(energy / rest) if energy > 0 and rest > 0 else -math.inf
    return SiteFit(pair, tuple(float(x) for x in coefficients[:COMPONENTS])), snr_db


class SiteNoise:
    """Noise covariances of each pair's four correlations (per template phase) in one stack,
    measured when a pass first needs the pair and kept for the stack's later passes, as the
    single templates' spreads are."""

    def __init__(self, search: SiteSearch, spectrum: np.ndarray, single: np.ndarray, single_step: int = 1) -> None:
        """``spectrum``: the rfft of the stack's first pass (its centred frame); ``single``: its
        correlations with the single-cell search's frame templates, at every ``single_step``-th
        lag (a divisor of ``COVARIANCE_STEP``)."""
        self._search, self._spectrum, self._single, self._single_step = search, spectrum, single, single_step
        self._covariances: dict[int, np.ndarray] = {}  # pair index -> (phases, 4, 4)

    def covariances(self, pairs: np.ndarray, correlations: np.ndarray | None = None) -> np.ndarray:
        """(pairs, phases, 4, 4); those not measured yet are measured on ``correlations`` (of
        the same pairs, any pass) or else on the stack's first pass."""
        missing = np.array([i for i, k in enumerate(pairs) if int(k) not in self._covariances], dtype=int)
        if missing.size:
            if correlations is None:
                measured = _covariances(self._search.correlations(self._spectrum, self._single, pairs[missing],
                                                                  COVARIANCE_STEP, self._single_step))
            else:
                measured = _covariances(correlations[..., ::COVARIANCE_STEP][missing])
            self._covariances.update(zip((int(k) for k in pairs[missing]), measured))
        return np.stack([self._covariances[int(k)] for k in pairs])


def _covariances(correlations: np.ndarray) -> np.ndarray:
    """(..., 4, 4) covariance of the four correlations (a sample of lags: every
    ``COVARIANCE_STEP``-th is enough) over the lags where none stands out (5 robust sigmas about
    zero, where correlations with zero-mean shapes are centred): codes occupy a few lags of
    thousands."""
    sample = correlations.astype(np.float64)
    spread = mad_spread(sample, axis=-1, keepdims=True, centre=0.0)
    quiet = np.all(np.abs(sample) < 5 * spread, axis=-2, keepdims=True)  # (..., 1, lags)
    count = quiet.sum(axis=-1, keepdims=True)
    mean = np.sum(sample * quiet, axis=-1, keepdims=True) / count
    centred = (sample - mean) * quiet
    return np.einsum("...il,...jl->...ij", centred, centred) / (count - 1)
