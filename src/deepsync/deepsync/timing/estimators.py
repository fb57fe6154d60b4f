"""Fine (sub-sample) timing of a detected cell's sync code, with an honest 1-sigma.

Input: ``windows`` (n_frames, L_w), row f the envelope of 10 ms frame f cut around the coarse
code position, L_w = L_t + 2 * margin with L_t = len(template); the code nominally starts at
index ``margin`` and truly at ``margin + offset``. Every estimator works on the stacked window
(the mean of the rows) and returns :class:`TimingEstimate` with ``offset`` in samples
(toa = c + offset). The DC pedestal of each row is ignored: rows are made zero-mean and the
DC bin never enters a correlation, so a pedestal changes nothing.

Three estimators of increasing quality:

* :func:`estimate_parabolic`: integer-lag correlation, parabola through the peak and its
  neighbours. Cheap and biased: the parabola does not describe the correlation peak of a
  wide-band template (bias up to ~0.09 samples, zero at integer and near half-integer
  offsets); the bias is a known function of the template and is put into the reported std.
* :func:`estimate_fft_upsampled`: the same correlation at ``factor`` x finer lags by
  zero-padding the cross-spectrum (band-limited interpolation), peak + local parabola.
* :func:`estimate_ml`: continuous maximisation of the band-limited, optionally prewhitened
  correlation r(tau) = sum_k 2 Re(W_k conj(T_k) e^{j w_k (margin + tau)}) / P_k over the
  bins between DC and Nyquist. White weights: the ML delay with unknown amplitude and
  pedestal in white Gaussian noise; weights 1 / P (the measured spectrum, :func:`noise_psd`):
  the Whittle ML in coloured noise, which reaches the bound of ``crlb.delay_crlb``.

The noise + interference spectrum is measured from the rows themselves (:func:`noise_psd`):
the sync code is the same in every row, the interference (LTE data self-mixing) is redrawn
every frame, so the frame-to-frame fluctuation around the row mean is pure interference; what
remains of it in the stacked window is that spectrum / n_frames.

The reported std (the root-mean-square error to expect) is built from

* a *main-lobe* std. Parabolic and FFT-upsampled: delete-a-group jackknife over the rows,
  each delete-a-group estimate confined to within a sample of the full one (they are not
  efficient and no bound gives their error; the jackknife measures it on the data, with the
  interference's real statistics). ML: the sandwich variance of the maximiser of r at the
  measured amplitude A and stacked noise PSD S,
  sum 2 w^2 |T|^2 c_k^2 L S_k / (A sum 2 w^2 |T|^2 c_k)^2 for weights c_k; with c = 1 / S it
  is exactly 1 / Fisher information (``crlb.delay_crlb`` at the measured A and spectrum), with
  white weights it is the correct variance of the white estimator in coloured noise. It has
  no resampling noise (a jackknife over 10 rows has 9 degrees of freedom) and the ML is
  efficient above threshold (Monte-Carlo RMSE within a few % of the bound, ``test_estimators``);
* the *posterior* over the search range, for what lies beyond the main lobe: with the
  measured A and S, the Whittle log-likelihood of the code at lag l is 2 A u(l) + const,
  u(l) = sum_k Re(W_k conj(T_k) e^{j w_k l}) / (L S_k); with a flat prior over the range, the
  posterior mass more than a sample from the estimate, times the squared distance, is added,
  and the main-lobe variance is weighted by the mass within a sample. By Bayes, the posterior
  mean-square distance is the estimator's mean-square error averaged over the prior. In the
  2-3 dB where outliers set in it errs on the safe side (A is measured, and exp(-2 A du) is
  convex in it): RMSE / RMS std down to ~0.35 there in ``benchmarks/timing/fine_timing.py``, 0.6-1.15
  everywhere else. A window without a code gets a posterior spread over the whole range and
  a std of ~margin / sqrt(3) or more, not a confident number;
* parabolic only: its deterministic interpolation bias at the estimated fraction
  (:func:`parabolic_bias`, computed from the template's autocorrelation);
* a model floor ``MODEL_FLOOR_SAMPLES`` (in quadrature): the sampled template of an aliased
  envelope is not exactly band-limited (the 0.9 MHz 4th-order video filter leaves ~-31 dB of
  the code's energy above the 0.96 MHz Nyquist frequency), so its band-limited fractional
  shifts differ from the true ones: a noise-free bias of ~0.001 samples (median over the 504
  PCIs at the worst fraction; 90th percentile 0.004, worst PCI 0.024; 0.003 RMS over PCIs).

Amplitudes are bias-corrected (A^2 - var(A), floored at 0) before they enter the std, the
posterior and the SNR, so pure noise gives a small amplitude, a large std and a low SNR.

Caveats: the rows must be aligned to a fraction of a sample (the stacker's ``row_shifts``):
a code that moves between rows blurs the stack and leaks into the measured noise spectrum.
The noise spectrum from n_frames rows has 2 (n_frames - 1) degrees of freedom per bin and is
smoothed over neighbouring bins; for n_frames < ~6 the jackknife std is itself very noisy.
The interference of a loaded cell is nearly white over the video band (+-1 dB), so the
prewhitened ML gains little over the white one on simulated data; it matters for coloured
noise (``test_estimators``). Rows that are all constant raise ValueError (nothing to time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
import scipy.fft
import scipy.ndimage
import scipy.optimize

from deepsync.numeric import parabolic_offset
from deepsync.timing.crlb import bin_omega, check_template, fisher_information_bins, psd_bins, std_from_fisher

MODEL_FLOOR_SAMPLES = 0.003
MAX_JACKKNIFE_GROUPS = 20
PSD_TARGET_DOF = 64  # degrees of freedom per smoothed PSD bin (smoothing over neighbours)
SNR_FLOOR_DB = -60.0
# share of errors within +-1 reported sigma that counts as an honest sigma (a Gaussian's: 0.683)
SIGMA_CALIBRATION_BAND = (0.60, 0.76)


@dataclass(frozen=True)
class TimingEstimate:
    offset: float  # code start minus the nominal position `margin`, in samples (toa = c + offset)
    std: float  # honest 1-sigma of offset (samples)
    snr_db: float  # estimated post-stacking SNR of the code in the window (template energy vs noise)
    estimator: str  # "parabolic" | "fft_upsampled" | "ml"


# -- input -----------------------------------------------------------------------------------


def _as_template(template: np.ndarray) -> np.ndarray:
    return check_template(template, min_length=8)


def _as_windows(windows: np.ndarray) -> np.ndarray:
    try:
        w = np.asarray(windows, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"windows must be a numeric array: {error}") from None
    if w.ndim != 2:
        raise ValueError(f"windows must be 2-D (n_frames, window_length), got shape {w.shape}")
    if w.shape[0] < 2:
        raise ValueError(
            f"need at least 2 frames (rows), got {w.shape[0]}: the noise spectrum and the jackknife "
            "are measured from the frame-to-frame fluctuation"
        )
    if not np.all(np.isfinite(w)):
        bad = np.argwhere(~np.isfinite(w))[0]
        raise ValueError(f"windows contain NaN or inf (first at frame {bad[0]}, sample {bad[1]})")
    return w


def max_margin(template_length: int) -> int:
    """Largest margin accepted: a quarter of the template (beyond it the SSS half of the code
    starts to line up with the PSS half, 137 samples on, and the search is no longer local)."""
    return template_length // 4


def _check_margin(margin: int, template_length: int, window_length: int) -> int:
    if isinstance(margin, bool) or not isinstance(margin, (int, np.integer)):
        raise ValueError(f"margin must be an integer number of samples, got {margin!r}")
    margin = int(margin)
    if margin < 1:
        raise ValueError(f"margin must be >= 1, got {margin}")
    if margin > max_margin(template_length):
        raise ValueError(
            f"margin {margin} is too large for a {template_length}-sample template (at most "
            f"{max_margin(template_length)}): the coarse position must already be local"
        )
    if window_length != template_length + 2 * margin:
        raise ValueError(
            f"window length {window_length} does not match the template ({template_length}) + "
            f"2 * margin ({margin}) = {template_length + 2 * margin}"
        )
    return margin


# -- noise spectrum ----------------------------------------------------------------------------


def _smooth_bins(n_frames: int, n_bins: int) -> int:
    half = math.ceil((PSD_TARGET_DOF / (2 * (n_frames - 1)) - 1) / 2)
    return int(np.clip(half, 0, max(0, n_bins // 16)))


def _psd_from_rows(rows0: np.ndarray, smooth_half_width: int | None) -> np.ndarray:
    n_frames, length = rows0.shape
    residual = rows0 - rows0.mean(axis=0)
    periodogram = np.abs(np.fft.rfft(residual, axis=1)) ** 2 / length
    psd = periodogram.mean(axis=0) * n_frames / (n_frames - 1)
    return _smoothed(psd, _smooth_bins(n_frames, psd.size) if smooth_half_width is None else int(smooth_half_width))


def _smoothed(psd: np.ndarray, half: int) -> np.ndarray:
    """A periodogram averaged over ``2 * half + 1`` neighbouring bins (mirrored at the band's
    ends); its DC bin, empty for zero-mean data and never used, copies the next one."""
    if half > 0:
        psd = np.concatenate([psd[:1], scipy.ndimage.uniform_filter1d(psd[1:], 2 * half + 1, mode="mirror")])
    psd[0] = psd[1]
    return psd


def noise_psd(windows: np.ndarray, template: np.ndarray | None = None, smooth_bins: int | None = None) -> np.ndarray:
    """Per-frame noise + interference PSD at the ``L_w // 2 + 1`` rfft bins of the windows.

    Measured from the rows: each row is made zero-mean (its pedestal removed), the row mean
    (the code and whatever else repeats every frame) is subtracted, and the periodograms of
    what remains are averaged, scaled by n / (n - 1) for the mean taken out, and smoothed over
    ``2 * smooth_bins + 1`` neighbouring bins (default: enough for ~64 degrees of freedom,
    at most 1/16 of the band). Units: variance per sample per unit of normalised frequency
    (white noise of variance s^2 gives s^2 everywhere), as ``crlb.delay_crlb`` expects. The
    stacked window carries this / n_frames. ``template`` (optional) only checks the length.
    """
    w = _as_windows(windows)
    if template is not None and _as_template(template).size > w.shape[1]:
        raise ValueError(f"windows ({w.shape[1]} samples) are shorter than the template ({len(template)})")
    if smooth_bins is not None and (int(smooth_bins) != smooth_bins or smooth_bins < 0):
        raise ValueError(f"smooth_bins must be a non-negative integer, got {smooth_bins!r}")
    return _psd_from_rows(w - w.mean(axis=1, keepdims=True), smooth_bins)


# -- shared machinery -------------------------------------------------------------------------


@dataclass
class _Problem:
    n_frames: int
    length: int  # window length L_w (the DFT length)
    margin: int
    template: np.ndarray
    t_spec: np.ndarray  # rfft of the template zero-padded to the window length
    row_cross: np.ndarray  # (n_frames, bins) rfft(zero-mean row) * conj(t_spec)
    psd: np.ndarray  # measured per-frame noise PSD, rfft bins

    @cached_property
    def cross(self) -> np.ndarray:
        """Cross-spectrum of the stacked (row-mean) window with the template."""
        return self.row_cross[0] if self.n_frames == 1 else self.row_cross.mean(axis=0)

    @cached_property
    def power(self) -> np.ndarray:
        """|T_k|^2 of the template at the bins between DC and Nyquist."""
        return np.abs(self.t_spec[self.inner]) ** 2

    @property
    def inner(self) -> slice:
        """Bins strictly between DC and Nyquist (a slice: their arrays are views, not copies)."""
        return slice(1, (self.length + 1) // 2)

    @property
    def omega(self) -> np.ndarray:
        """Their angular frequencies (radians per sample)."""
        return bin_omega(self.length)


def _problem(windows: np.ndarray, template: np.ndarray, margin: int) -> _Problem:
    w = _as_windows(windows)
    t = _as_template(template)
    margin = _check_margin(margin, t.size, w.shape[1])
    rows0 = w - w.mean(axis=1, keepdims=True)
    if not np.any(rows0):
        raise ValueError("windows carry nothing: every row is constant (a dead or saturated input?)")
    t_spec = np.fft.rfft(t, w.shape[1])
    row_cross = np.fft.rfft(rows0, axis=1) * np.conj(t_spec)
    return _Problem(w.shape[0], w.shape[1], margin, t, t_spec, row_cross, _psd_from_rows(rows0, None))


def _groups(n_frames: int) -> list[np.ndarray]:
    return np.array_split(np.arange(n_frames), min(n_frames, MAX_JACKKNIFE_GROUPS))


def _jackknife(problem: _Problem, estimate) -> float:
    """Delete-a-group jackknife std of ``estimate(cross_spectra (G, bins)) -> (G,) lags``."""
    total = problem.row_cross.sum(axis=0)
    groups = _groups(problem.n_frames)
    left_out = np.array(
        [(total - problem.row_cross[g].sum(axis=0)) / (problem.n_frames - len(g)) for g in groups]
    )
    values = estimate(left_out)
    g = len(groups)
    return float(math.sqrt((g - 1) / g * np.sum((values - values.mean()) ** 2)))


GRID_STEP = 1 / 16  # samples: lag grid of the posterior (and of the ML coarse search)
NEWTON_STEPS = 8  # Newton steps to the ML maximum from its grid point (on the campus bag it settles in 2-4)


def _phases(omega: np.ndarray, lag: float) -> np.ndarray:
    """exp(j omega lag) for the bins' omega = k omega_1, k = 1, 2, ... (every caller's): for
    long windows as the outer product of two short ramps, a few hundred complex exponentials
    instead of one per bin (a frame's 9,599 cost 0.25 ms), equal to rounding."""
    if omega.size < 1024:
        return np.exp(1j * omega * lag)
    step, width = float(omega[0]) * lag, 64
    rows = -(-(omega.size + 1) // width)
    ramp = np.exp(1j * step * width * np.arange(rows))[:, None] * np.exp(1j * step * np.arange(width))[None, :]
    return ramp.ravel()[1 : omega.size + 1]


@lru_cache(maxsize=32)
def _phase_grid(length: int, margin: int) -> tuple[np.ndarray, np.ndarray]:
    """Lags 0..2*margin every ``GRID_STEP`` and exp(j w_k lag) for the bins between DC and Nyquist."""
    lags = np.arange(0.0, 2 * margin + 1e-9, GRID_STEP)
    phases = np.exp(1j * np.outer(lags, bin_omega(length)))
    phases.flags.writeable = False
    return lags, phases


@dataclass(frozen=True)
class _Fit:
    amplitude: float  # bias-corrected (>= 0)
    sandwich_std: float
    snr_db: float


def _fit(problem: _Problem, lag: float, weights: np.ndarray, stacked_psd: np.ndarray,
         phases: np.ndarray | None = None) -> _Fit:
    """Amplitude, sandwich std and SNR at the estimated ``lag`` (= margin + offset);
    ``phases``: ``_phases(problem.omega, lag)``, if the caller has them."""
    k, omega, length = problem.inner, problem.omega, problem.length
    phases = _phases(omega, lag) if phases is None else phases
    s = stacked_psd[k]
    weighted_power = 2 * problem.power * weights  # 2 w |T|^2
    spread = weighted_power * weights * (length * s)  # 2 w^2 |T|^2 L S: the variance each bin adds
    total = float(np.sum(weighted_power))
    a_hat = float(np.real(problem.cross[k] * phases) @ weights) * 2 / total
    a_var = float(np.sum(spread)) / total**2
    amplitude = math.sqrt(max(a_hat**2 - a_var, 0.0)) if a_hat > 0 else 0.0

    omega_sq = omega**2
    curvature = amplitude * float(omega_sq @ weighted_power)
    slope_var = float(omega_sq @ spread)
    sandwich = math.sqrt(slope_var) / curvature if curvature > 0 else math.inf

    noise_var = (2 * float(np.sum(s)) + (stacked_psd[-1] if length % 2 == 0 else 0.0)) / length
    t0 = problem.template - problem.template.mean()
    snr = amplitude**2 * float(np.sum(t0**2)) / (problem.template.size * noise_var) if noise_var > 0 else math.inf
    snr_db = 10 * math.log10(snr) if snr > 10 ** (SNR_FLOOR_DB / 10) else SNR_FLOOR_DB
    return _Fit(amplitude, sandwich, snr_db)


@dataclass(frozen=True)
class _Posterior:
    lags: np.ndarray  # grid over the search range (lag units, 0..2*margin)
    probability: np.ndarray  # posterior mass of each grid point (sums to 1)


def _posterior(problem: _Problem, stacked_psd: np.ndarray, allowed: np.ndarray | None = None) -> _Posterior | None:
    """Where the code may be, given the data: the Whittle posterior over the search range.

    Log-likelihood at the measured amplitude A (the pedestal lives in the DC bin):
    l(lag) = 2 A u(lag) + const, u(lag) = sum_k Re(W_k conj(T_k) e^{j w_k lag}) / (L S_k),
    S the stacked noise PSD; A = max u / E, E = sum_k |T_k|^2 / (L S_k), bias-corrected by its
    variance 1 / (2 E) (for pure noise u ~ N(0, E / 2) at every lag).
    The amplitude is held at its measured value rather than profiled lag by lag: a profile
    would treat "no code here" (A = 0) as a hypothesis at every lag and spread the posterior
    far too wide at moderate SNR. Flat prior over lags 0..2*margin (or over the ``allowed``
    ones), integrated on a ``GRID_STEP`` grid (trapezoid). None when the window carries no noise at all.
    """
    k = problem.inner
    s = stacked_psd[k]
    if not np.any(s > 0):
        return None
    s = np.maximum(s, 1e-12 * float(np.max(s)))
    length = problem.length
    z = problem.cross[k] / (length * s)
    energy = float(np.sum(problem.power / (length * s)))
    lags, phases = _phase_grid(length, problem.margin)
    return _posterior_of(lags, np.real(phases @ z), energy, allowed)


def _posterior_of(lags: np.ndarray, u: np.ndarray, energy: float, allowed: np.ndarray | None = None) -> _Posterior:
    """The posterior from the weighted correlation ``u`` on an evenly spaced grid of ``lags``
    and the template's weighted energy (``_posterior``)."""
    amplitude = float((u if allowed is None else u[allowed]).max()) / energy  # at the best lag, var 1 / (2 E): bias-corrected
    amplitude = math.sqrt(max(amplitude**2 - 1 / (2 * energy), 0.0)) if amplitude > 0 else 0.0
    log_like = 2 * amplitude * u
    if allowed is not None:
        log_like = np.where(allowed, log_like, -np.inf)
    mass = np.exp(log_like - log_like.max())
    mass[[0, -1]] *= 0.5
    return _Posterior(lags, mass / mass.sum())


def _total_std(lag: float, core: float, posterior: _Posterior | None, bias: float = 0.0) -> float:
    """Main-lobe std, weighted by the posterior mass within a sample of the estimate, plus the
    posterior's mean square distance from the estimate elsewhere, plus bias and model floor."""
    var = core**2
    if posterior is not None:
        distance = posterior.lags - lag
        main = np.abs(distance) < 1.0
        p_main = float(posterior.probability[main].sum())
        spread = float(np.sum(posterior.probability[~main] * distance[~main] ** 2))
        if p_main > 0 and not math.isfinite(core):  # no amplitude left: the main lobe's own spread
            core = math.sqrt(float(np.sum(posterior.probability[main] * distance[main] ** 2)) / p_main)
        var = (p_main * core**2 if p_main > 0 else 0.0) + spread
    return float(math.sqrt(var + bias**2 + MODEL_FLOOR_SAMPLES**2))


# -- parabolic ---------------------------------------------------------------------------------


def _integer_correlation(problem: _Problem, cross: np.ndarray) -> np.ndarray:
    """Zero-mean correlation at integer lags 0..2*margin (time domain, every bin)."""
    return np.fft.irfft(cross, problem.length, axis=-1)[..., : 2 * problem.margin + 1]


def _parabola(values: np.ndarray, near: float | None = None, reach: float = 0.0) -> np.ndarray:
    """Vertex of the parabola through each row's maximum and its neighbours (index units);
    with ``near``, the maximum is looked for only within ``reach`` indices of it."""
    values = np.atleast_2d(values)
    n = values.shape[1]
    searched = values
    if near is not None:
        index = np.arange(n)
        searched = np.where(np.abs(index - near) <= reach, values, -np.inf)
    peak = np.clip(np.argmax(searched, axis=1), 1, n - 2)
    rows = np.arange(values.shape[0])
    step = parabolic_offset(values[rows, peak - 1], values[rows, peak], values[rows, peak + 1])
    return np.clip(peak + np.clip(step, -1.0, 1.0), 0, n - 1)


def _autocorrelation(problem: _Problem, delays: np.ndarray) -> np.ndarray:
    """Band-limited template autocorrelation sum_k |T_k|^2 e^{j w_k d} over every bin but DC."""
    power = np.abs(problem.t_spec) ** 2
    length = problem.length
    bins = np.arange(1, power.size)
    factor = np.full(bins.size, 2.0)
    if length % 2 == 0:
        factor[-1] = 1.0
    return np.cos(np.outer(delays, 2 * np.pi * bins / length)) @ (factor * power[1:])


def _parabolic_bias(problem: _Problem, offset: float) -> float:
    lag = problem.margin + offset
    centre = math.floor(lag + 0.5)
    delays = np.array([centre - 1, centre, centre + 1]) - lag
    return float(centre + parabolic_offset(*_autocorrelation(problem, delays)) - lag)


def parabolic_bias(template: np.ndarray, offset: float, margin: int = 10) -> float:
    """Noise-free error of the parabolic estimator at true ``offset`` (samples).

    Exact for a band-limited template: the integer-lag correlation of the code with the template
    is the template's autocorrelation sampled at integer lags minus the true lag, and the
    parabola's vertex through its three largest values misses the true lag by this much.
    """
    t = _as_template(template)
    length = t.size + 2 * _check_margin(margin, t.size, t.size + 2 * margin)
    bins = length // 2 + 1
    problem = _Problem(1, length, margin, t, np.fft.rfft(t, length), np.zeros((1, bins)), np.ones(bins))
    return _parabolic_bias(problem, float(offset))


def _parabolic_lags(problem: _Problem, cross: np.ndarray, near: float | None = None) -> np.ndarray:
    return _parabola(_integer_correlation(problem, cross), near, 1.0)


def estimate_parabolic(windows: np.ndarray, template: np.ndarray, margin: int) -> TimingEstimate:
    """Integer-lag zero-mean correlation over lags -margin..margin, parabola through the peak.

    std: main-lobe jackknife over the rows (+ the posterior beyond the main lobe, the parabola's
    own deterministic bias at the estimated fraction, and the model floor; module docstring).
    """
    problem = _problem(windows, template, margin)
    lag = float(_parabolic_lags(problem, problem.cross)[0])
    # main-lobe jackknife: each delete-a-group estimate stays within a sample of the full one
    # (jumps to other peaks are the posterior's business, see _total_std)
    core = _jackknife(problem, lambda cross: _parabolic_lags(problem, cross, near=round(lag)))
    # the bias is a function of the true fraction: invert lag = true + bias(true)
    true = lag
    for _ in range(3):
        true = lag - _parabolic_bias(problem, true - problem.margin)
    bias = _parabolic_bias(problem, true - problem.margin)
    stacked = problem.psd / problem.n_frames
    fit = _fit(problem, lag, np.ones(problem.omega.size), stacked)
    std = _total_std(lag, core, _posterior(problem, stacked), bias)
    return TimingEstimate(lag - problem.margin, std, fit.snr_db, "parabolic")


# -- FFT-upsampled -----------------------------------------------------------------------------


def _upsampled_lags(problem: _Problem, cross: np.ndarray, factor: int) -> np.ndarray:
    cross = np.atleast_2d(cross)
    fine = problem.length * factor
    padded = np.zeros((cross.shape[0], fine // 2 + 1), dtype=np.complex128)
    padded[:, : cross.shape[1]] = cross
    padded[:, 0] = 0.0
    if problem.length % 2 == 0:
        padded[:, problem.length // 2] *= 0.5  # the Nyquist bin splits into +- half
    correlation = np.fft.irfft(padded, fine, axis=1)[:, : 2 * problem.margin * factor + 1]
    return _parabola(correlation) / factor


def _upsampled_lags_near(problem: _Problem, cross: np.ndarray, factor: int, near: float) -> np.ndarray:
    """The same band-limited correlation as ``_upsampled_lags``, evaluated directly on the
    fine lags within a sample of ``near`` only (what the main-lobe jackknife needs)."""
    fine = near + np.arange(-factor, factor + 1) / factor
    bins = np.arange(1, problem.length // 2 + 1)
    scale = np.full(bins.size, 2.0)
    if problem.length % 2 == 0:
        scale[-1] = 1.0
    phases = np.exp(2j * np.pi * np.outer(bins, fine) / problem.length) * scale[:, None]
    correlation = np.real(np.atleast_2d(cross)[:, bins] @ phases)
    return near - 1 + _parabola(correlation) / factor


def estimate_fft_upsampled(windows: np.ndarray, template: np.ndarray, margin: int, factor: int = 32) -> TimingEstimate:
    """Correlation at ``factor`` x finer lags (zero-padded cross-spectrum), peak + local parabola.

    The interpolation is band-limited, so the only bias left is the parabola over 1/factor
    sample (< 1e-4 samples at factor 32). std: main-lobe jackknife over the rows (+ the
    posterior beyond the main lobe and the model floor; module docstring).
    """
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or not 2 <= factor <= 1024:
        raise ValueError(f"factor must be an integer in 2..1024, got {factor!r}")
    problem = _problem(windows, template, margin)
    lag = float(_upsampled_lags(problem, problem.cross, int(factor))[0])
    core = _jackknife(problem, lambda cross: _upsampled_lags_near(problem, cross, int(factor), lag))
    stacked = problem.psd / problem.n_frames
    fit = _fit(problem, lag, np.ones(problem.omega.size), stacked)
    std = _total_std(lag, core, _posterior(problem, stacked))
    return TimingEstimate(lag - problem.margin, std, fit.snr_db, "fft_upsampled")


# -- maximum likelihood ------------------------------------------------------------------------


def _allowed_lags(problem: _Problem, within: tuple[float, float]) -> np.ndarray:
    """Grid lags inside the offset interval ``within`` (clipped to the margin; at least the
    grid point nearest its middle)."""
    low, high = (float(v) for v in within)
    if not (math.isfinite(low) and math.isfinite(high) and low <= high):
        raise ValueError(f"within: {within!r} must be an increasing pair of finite offsets")
    grid, _ = _phase_grid(problem.length, problem.margin)
    allowed = (grid >= problem.margin + low) & (grid <= problem.margin + high)
    if not allowed.any():
        allowed[np.argmin(np.abs(grid - problem.margin - np.clip((low + high) / 2, -problem.margin, problem.margin)))] = True
    return allowed


def _ml_lag(problem: _Problem, weights: np.ndarray, allowed: np.ndarray | None = None) -> float:
    """The maximum of the weighted correlation: the best point of the 1/16-sample grid, then
    Newton's method from it (the maximum is smooth, and the grid point within 1/32 sample of
    it: a few steps); a bounded Brent search around the grid point where Newton does not
    settle inside that bracket (the maximum at its edge, a flat top)."""
    z = problem.cross[problem.inner] * weights
    omega = problem.omega
    top = 2.0 * problem.margin
    grid, phases = _phase_grid(problem.length, problem.margin)
    values = np.real(phases @ z)
    if allowed is not None:  # a prior interval: the maximum inside it
        values = np.where(allowed, values, -np.inf)
    best = float(grid[np.argmax(values)])
    low, high = max(0.0, best - 2 * GRID_STEP), min(top, best + 2 * GRID_STEP)
    if allowed is not None:
        inside = grid[allowed]
        low, high = max(low, float(inside[0])), min(high, float(inside[-1]))
    return _maximum_near(z, omega, best, low, high)


def _maximum_near(z: np.ndarray, omega: np.ndarray, best: float, low: float, high: float,
                  tolerance: float = 1e-9, shifts: np.ndarray | None = None) -> float:
    """The maximum of sum Re(z e^{j omega lag}) in [low, high], from its grid point ``best``
    (Newton's method, settled when a step falls below ``tolerance`` samples). With ``shifts``
    (R,), z is (R, bins) and row r's frequencies are omega + shifts[r] (a template's folds)."""
    lag = _newton(z, omega, best, low, high, NEWTON_STEPS, tolerance=tolerance, shifts=shifts)
    if lag is not None:
        return lag
    result = scipy.optimize.minimize_scalar(
        lambda x: -float(np.sum(np.real(_turned(z, omega, x, shifts)))), bounds=(low, high), method="bounded",
        options={"xatol": 1e-6})
    # Brent stops at its tolerance
    polished = _newton(z, omega, float(result.x), low, high, 2, settle=False, shifts=shifts)
    return float(result.x) if polished is None else polished


def _turned(z: np.ndarray, omega: np.ndarray, lag: float, shifts: np.ndarray | None) -> np.ndarray:
    """z e^{j (omega + shift) lag}: each term of the correlation at ``lag``."""
    turned = z * _phases(omega, lag)
    return turned if shifts is None else turned * np.exp(1j * shifts * lag)[:, None]


def _folded_derivatives(z: np.ndarray, omega: np.ndarray, lag: float, shifts: np.ndarray) -> tuple[float, float]:
    """Slope and curvature in the lag of sum Re(z e^{j (omega + shifts[r]) lag}) over rows r and
    bins: three sums over the bins per row (matrix-vector products), each row then turned by its
    own shift, instead of a rows x bins array of terms."""
    phases = _phases(omega, lag)
    weighted = phases * omega
    plain, first, second = z @ phases, z @ weighted, z @ (weighted * omega)
    turn = np.exp(1j * shifts * lag)
    slope = -float(np.sum((turn * (first + shifts * plain)).imag))
    curvature = -float(np.sum((turn * (second + 2 * shifts * first + shifts**2 * plain)).real))
    return slope, curvature


def _newton(z: np.ndarray, omega: np.ndarray, lag: float, low: float, high: float, steps: int,
            settle: bool = True, tolerance: float = 1e-9, shifts: np.ndarray | None = None) -> float | None:
    """Newton's method on the correlation's slope from ``lag``, at most ``steps`` steps: the
    point where a step falls below ``tolerance`` samples (else, unless ``settle``, the last one);
    None if a step leaves [low, high] or meets a point where the correlation is not concave.
    ``shifts``: as ``_maximum_near``'s."""
    omega_sq = omega**2
    for _ in range(steps):
        if shifts is None:
            phase = z * _phases(omega, lag)
            slope = -float(omega @ phase.imag)  # d/dlag of sum Re(phase)
            curvature = -float(omega_sq @ phase.real)
        else:
            slope, curvature = _folded_derivatives(z, omega, lag, shifts)
        if curvature >= 0:
            return None
        step = -slope / curvature
        if not low <= lag + step <= high:
            return None
        lag += step
        if abs(step) < tolerance:
            return lag
    return None if settle else lag


def estimate_ml(
    windows: np.ndarray,
    template: np.ndarray,
    margin: int,
    noise_psd: np.ndarray | float | None = None,
    within: tuple[float, float] | None = None,
) -> TimingEstimate:
    """Maximum-likelihood fractional delay (band-limited correlation, maximised continuously).

    ``within`` (low, high offsets, samples): a prior interval (the timing network's estimate
    +- its uncertainty): the maximum is looked for inside it only, and the posterior of the
    std is the flat prior over it rather than over the whole margin.

    Maximises r(tau) = sum_k Re(W_k conj(T_k) e^{j w_k (margin + tau)}) / P_k over the bins
    between DC and Nyquist (W, T: DFTs of the zero-mean stacked window and of the template
    zero-padded to the window length) with a bounded Brent search around the best point of a
    1/16-sample grid, then a Newton polish. ``noise_psd`` None: white weights (the ML delay
    with unknown amplitude and pedestal in white Gaussian noise). ``noise_psd`` = the per-frame
    PSD at the window's rfft bins, e.g. ``noise_psd(windows)``: prewhitened, the Whittle ML in
    coloured Gaussian noise.

    std: the sandwich variance at the measured amplitude and spectrum, which for prewhitened
    weights is 1 / Fisher information, i.e. ``crlb.delay_crlb`` at the measured A and PSD. Why
    not a jackknife: the ML is efficient above threshold (Monte-Carlo RMSE within a few % of
    the bound in ``test_estimators``), so the bound *is* its error, and the plug-in bound has
    no resampling noise. Below threshold the posterior term takes over; plus the model floor
    (module docstring). The spectrum for the std is the given one, else the measured one.
    """
    problem = _problem(windows, template, margin)
    if noise_psd is None:
        weights = np.ones(problem.omega.size)
        stacked = problem.psd / problem.n_frames
    else:
        given = psd_bins(noise_psd, problem.length)
        given = np.maximum(given, 1e-12 * float(np.max(given)))
        weights = 1 / given[problem.inner]
        weights = weights / weights.mean()
        stacked = given / problem.n_frames
    allowed = None if within is None else _allowed_lags(problem, within)
    lag = _ml_lag(problem, weights, allowed)
    fit = _fit(problem, lag, weights, stacked)
    std = _total_std(lag, fit.sandwich_std, _posterior(problem, stacked, allowed))
    return TimingEstimate(lag - problem.margin, std, fit.snr_db, "ml")


# -- maximum likelihood over a known cell's whole frame -----------------------------------------

FRAME_PSD_HALF_WIDTH = 32  # bins either side over which the frame residual's periodogram is averaged (~130 dof)
FRAME_GRID_FACTOR = 2  # points per sample of the full-frame posterior's lag grid
# samples either side of the coarse start the full-frame posterior spans: three periods of the
# CRS comb, whose sidelobes (0.62, 0.45, 0.41 of the peak) would lock a code start that far off
FRAME_POSTERIOR_REACH = 64


@dataclass(frozen=True)
class FrameTiming:
    """A full-frame ML estimate with its Cramer-Rao bound and what that bound rests on: the
    template's fitted scale and the stacked frame's noise spectrum."""

    estimate: TimingEstimate  # offset from the ``start`` searched around
    amplitude: float  # fitted scale of the template, bias-corrected (>= 0)
    stacked_psd: np.ndarray  # of the frame's residual, rfft bins of the frame
    crlb_std: float  # samples: ``crlb.delay_crlb`` of the template at ``amplitude`` in ``stacked_psd``
    peak_excess: float  # samples: ``peak_excess_width`` at the estimate


def frame_spectrum(frame: np.ndarray) -> np.ndarray:
    """The rfft of a stack's mean frame, its mean removed: what ``estimate_ml_frame`` takes,
    computed once for all the stack's cells. ValueError if it is not one finite, varying frame."""
    f = np.asarray(frame, dtype=np.float64)
    if f.ndim != 1 or f.size < 16:
        raise ValueError(f"frame must be one frame of samples, got shape {f.shape}")
    if not np.all(np.isfinite(f)):
        raise ValueError("frame contains NaN or inf")
    f = f - f.mean()
    if not np.any(f):
        raise ValueError("frame carries nothing: it is constant (a dead or saturated input?)")
    return scipy.fft.rfft(f)


PEAK_WIDTH_LEVEL = 0.3  # of the peak: where the correlation's width is read (below the main lobe's shoulders)
PEAK_WIDTH_FACTOR = 4  # points per sample at which the width is read (edges interpolated: 0.01 samples from 8)
PEAK_WIDTH_REACH = 12  # samples either side of the peak searched for the edges (within the CRS comb's period)


def _width_at(correlation: np.ndarray, peak: int, level: float) -> float:
    """Width (grid points) of ``correlation`` around index ``peak`` where it stays above
    ``level``, each edge interpolated between the grid points that bracket it; the whole array
    where it never falls that low."""
    below = correlation <= level
    left = np.flatnonzero(below[:peak])
    right = np.flatnonzero(below[peak:])
    edges = []
    for outside, step in ((left[-1] if left.size else None, 1), (peak + right[0] if right.size else None, -1)):
        if outside is None:
            edges.append(0.0 if step == 1 else correlation.size - 1.0)
            continue
        inside = outside + step
        fraction = (level - correlation[outside]) / (correlation[inside] - correlation[outside])
        edges.append(outside + step * fraction)
    return edges[1] - edges[0]


def _fine_correlation(cross: np.ndarray, n: int, centre: float) -> tuple[np.ndarray, int]:
    """The circular correlation of a cross-spectrum (rfft bins of an ``n``-sample frame) on a
    1/``PEAK_WIDTH_FACTOR``-sample grid over +-``PEAK_WIDTH_REACH`` samples of ``centre``
    (band-limited interpolation), and the grid index of its maximum within a sample of ``centre``."""
    points = n * PEAK_WIDTH_FACTOR
    padded = np.zeros(points // 2 + 1, dtype=np.complex128)
    padded[1: cross.size - 1] = cross[1:-1]  # the bins between DC and Nyquist, as the ML fit reads them
    steps = round(centre * PEAK_WIDTH_FACTOR) + np.arange(-PEAK_WIDTH_REACH * PEAK_WIDTH_FACTOR,
                                                          PEAK_WIDTH_REACH * PEAK_WIDTH_FACTOR + 1)
    correlation = scipy.fft.irfft(padded, points)[steps % points]
    middle = PEAK_WIDTH_REACH * PEAK_WIDTH_FACTOR
    near = slice(middle - PEAK_WIDTH_FACTOR, middle + PEAK_WIDTH_FACTOR + 1)
    return correlation, near.start + int(np.argmax(correlation[near]))


def peak_excess_width(spectrum: np.ndarray, template_spectrum: np.ndarray, lag: float, n: int) -> float:
    """How much wider (samples) the correlation of a frame with a cell's known frame is at
    ``PEAK_WIDTH_LEVEL`` of its peak near ``lag`` than the template's own autocorrelation: 0 for
    a single clean path, positive where echoes within a few samples of it (multipath, a blocked
    first path) smear the peak, whose maximum then need not sit on the first arrival. Noise moves
    it by a fraction of that (both widths are read on the same grid, edges interpolated).
    ``spectrum``: ``frame_spectrum`` of the frame; ``template_spectrum``: the rfft of the
    cell's known frame, ``n`` samples long."""
    widths = []
    for cross, centre in ((spectrum * np.conj(template_spectrum), lag), (np.abs(template_spectrum) ** 2, 0.0)):
        correlation, peak = _fine_correlation(cross, n, centre)
        widths.append(_width_at(correlation, peak, PEAK_WIDTH_LEVEL * correlation[peak]))
    return (widths[0] - widths[1]) / PEAK_WIDTH_FACTOR


def estimate_ml_frame(spectrum: np.ndarray, template: np.ndarray, start: int, reach: int,
                      template_spectrum: np.ndarray | None = None,
                      folds: tuple[np.ndarray, np.ndarray] | None = None) -> FrameTiming:
    """Maximum-likelihood code start of a known cell within ``reach`` samples of ``start``, from
    everything the cell sends the same in every frame.

    ``spectrum``: ``frame_spectrum`` of a stack's mean frame (N samples). ``template`` (N,): the
    cell's known frame (``frontend.templates.known_frame``: codes and CRS), its subframe-0 code
    starting at sample 0; ``template_spectrum`` its rfft, if the caller keeps it; ``folds``:
    ``(orders, spectra)`` of what the ADC's sampling folds into it (``SyncTemplates.crs_folds``),
    so that the template at a lag between samples is the one sampled there (the sum of its
    folds, each turned by its own frequency), not the one at a whole sample moved by a phase
    ramp: up to 0.08 samples apart at 5-20 MHz, where the CRS envelope reaches past Nyquist.
    Both repeat every frame, so the circular correlation is exact and the template has no edges.
    The sync codes are 4 of a frame's 140 symbols, the CRS 40 more: at 10 MHz the template
    carries ~10 dB more matched-filter energy than the codes alone
    (``benchmarks/detection/full_frame_template.py``). Its autocorrelation has sidelobes at the CRS comb's
    period (21.3 samples), beyond the +-``reach`` searched around a code lock.

    White weights (the correlation's maximum, found as ``estimate_ml`` finds it: the best
    integer lag, where every fold is as at lag 0, then Newton's method with the folds, here to
    1e-6 samples). The noise: one stacked frame has no frame-to-frame fluctuation to measure it
    from, so it is the periodogram of what the
    fitted template leaves of the frame, averaged over ``2 FRAME_PSD_HALF_WIDTH + 1`` bins. That
    residual holds everything in the stack that is not this cell: detector noise, the data's
    self-mixing that stacking did not remove, and the other cells' deterministic envelopes.
    Those are not noise, but their correlation with this template acts as noise on its delay,
    so counting them keeps the std honest next to a strong cell. std: sandwich and posterior as
    in ``estimate_ml``, the posterior on a 1/``FRAME_GRID_FACTOR``-sample grid over
    +-``FRAME_POSTERIOR_REACH`` samples, wider than the search: a code lock a comb period or more
    off (where the template fits nearly as well) leaves its mass on the true start, and the std
    says so; where the best fit over that span is within the reach searched, the code lock is
    believed and the posterior spans the reach only (else stacks the comb's sidelobes nearly
    pass would all be told they might be a period off). Lags below are positions in the frame
    (any real number; the frame is periodic).
    """
    t = check_template(template, min_length=16)
    n = t.size
    if np.shape(spectrum) != (n // 2 + 1,):
        raise ValueError(f"spectrum ({np.shape(spectrum)}) is not that of a frame as long as the template ({n})")
    if isinstance(reach, bool) or not isinstance(reach, (int, np.integer)) or not 1 <= reach <= n // 4:
        raise ValueError(f"reach must be 1..{n // 4} samples, got {reach!r}")
    t_spec = scipy.fft.rfft(t) if template_spectrum is None else template_spectrum
    cross = spectrum * np.conj(t_spec)
    cross[0] = 0.0
    problem = _Problem(1, n, int(reach), t, t_spec, cross[None], np.ones(spectrum.size))
    inner, omega = problem.inner, problem.omega
    lags = int(start) - reach + np.arange(2 * reach + 1)  # whole-sample code starts searched
    correlation = scipy.fft.irfft(cross, n)[lags % n]
    best = int(np.clip(np.argmax(correlation), 1, 2 * reach - 1))
    near = lags[best] + float(np.clip(parabolic_offset(*correlation[best - 1 : best + 2]), -0.5, 0.5))
    z = cross[inner]
    orders, folded = (np.zeros(0, dtype=int), np.zeros((0, t_spec.size))) if folds is None else folds
    if np.shape(folded) != (len(orders), t_spec.size):
        raise ValueError(f"folds ({np.shape(folded)}) are not those of {len(orders)} orders "
                         "of this template's bins")
    folded = folded[:, inner]
    # the in-band part, exact at whole-sample lags (where every fold turns by a whole turn),
    # and the folds, each a correlation of its own at its own frequencies
    terms = np.concatenate([(t_spec[inner] - folded.sum(axis=0))[None], folded])
    shifts = 2 * np.pi * np.concatenate([[0], orders])
    lag = _maximum_near(spectrum[inner] * np.conj(terms), omega, near, max(lags[0], lags[best] - 1.0),
                        min(lags[-1], lags[best] + 1.0), tolerance=1e-6, shifts=shifts)

    power = problem.power
    phases = _phases(omega, lag)
    moved = (np.exp(-1j * shifts * lag) @ terms) * np.conj(phases)  # the template with its code at `lag`
    scale = float(np.sum(np.real(spectrum[inner] * np.conj(moved)))) / float(np.sum(np.abs(moved) ** 2))
    residual = np.abs(spectrum) ** 2
    residual[inner] = np.abs(spectrum[inner] - scale * moved) ** 2
    problem.psd = _smoothed(residual / n, FRAME_PSD_HALF_WIDTH)
    fit = _fit(problem, lag, np.ones(omega.size), problem.psd, phases)

    s = np.maximum(problem.psd[inner], 1e-12 * float(np.max(problem.psd[inner])))
    points = n * FRAME_GRID_FACTOR
    # single precision: its rounding (1e-7 of the correlation) moves the posterior by far less
    # than its own grid, at half the cost of this transform (the estimator's largest)
    weighted = np.zeros(points // 2 + 1, dtype=np.complex64)
    inverse = 1 / (n * s)
    weighted[inner] = z * inverse
    span = max(FRAME_POSTERIOR_REACH, reach)
    steps = np.arange((int(start) - span) * FRAME_GRID_FACTOR, (int(start) + span) * FRAME_GRID_FACTOR + 1)
    u = scipy.fft.irfft(weighted, points)[steps % points] * (points / 2)  # circular: the frame repeats
    lags = steps / FRAME_GRID_FACTOR
    searched = np.abs(lags - int(start)) <= reach
    if searched[np.argmax(u)]:  # the code lock agrees with the frame: the prior is the reach searched
        lags, u = lags[searched], u[searched]
    posterior = _posterior_of(lags, u, float(power @ inverse))
    std = _total_std(lag, fit.sandwich_std, posterior)
    bound = std_from_fisher(fisher_information_bins(fit.amplitude, power, problem.psd[inner], n))
    return FrameTiming(TimingEstimate(lag - int(start), std, fit.snr_db, "ml_frame"), fit.amplitude, problem.psd, bound,
                       peak_excess_width(spectrum, t_spec, lag, n))
