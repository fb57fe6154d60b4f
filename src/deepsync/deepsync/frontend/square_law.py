"""Square-law detection and the video filter, chunk by chunk, into the detector output.

Time runs in *ticks* of 1/1.92 MHz (every LTE rate is an integer number of samples per
tick). The output is produced per *chunk* of ``CHUNK_TICKS`` (10 ms): each cluster's |x|^2
over the chunk, plus the filter's memory on either side, is cut into overlapping blocks (the
overlap-save method), Fourier transformed, cropped to the video band, multiplied by the analog
filter's exact H(f) and summed over clusters; one inverse FFT per block then gives the detector
output (volts at the diode, before AC coupling and gain). The output comes at any whole number
of samples per tick: at the ADC's instants, when they fall on the tick grid, the spectrum is
first folded onto the ADC's band, which is what sampling the filtered signal there gives
(aliasing included) at a fraction of the work; otherwise at the video rate, which the ADC
stage interpolates.

Noise (``DetectorNoise``), added at the ADC's samples:

* Detector noise (diode + video amplifier) is white at the diode output with density
  R * NEP (V/sqrt(Hz)), shaped by the video filter.
* RF thermal noise n (density kTF) reaches the output as 2 Re(x n*) and |n|^2. Their sum is
  Gaussian and white across the video band with two-sided density R^2 (2 P N0 + N0^2 B_rf),
  so it is added there analytically (``test_frontend`` checks this against a brute-force
  |x + n|^2). With the default detector this is 20-50 dB below the diode's own noise for
  any input inside the square-law region, which is why envelope detectors are insensitive.
  Simulating 10-20 MHz of explicit RF noise would cost a fifth of the run time for that.
* Both are drawn in the frequency domain at the ADC rate, per 10 ms block of ADC samples,
  with the filtered spectrum folded onto the ADC's band (every alias up to where the video
  filter is 40 dB down): one normal deviate per sample. Blocks are independent, so the
  noise's correlation across the ~10 us filter memory at block edges (0.1 % of samples) is
  not reproduced. A receiver clock off its nominal rate samples a stationary noise at
  instants ppm off the uniform grid: the same statistics to a few ppm, so the noise is drawn
  on the uniform grid.
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np
import scipy.fft

from deepsync.frontend.channel import ChannelProvider, Emitter
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.plan import Cluster, plan_clusters
from deepsync.frontend.portable import multiply, squared_magnitude
from deepsync.frontend.render import Frame, GroupRenderer
from deepsync.frontend.video import VideoFilter
from deepsync.lte.numerology import BASE_RATE_HZ
from deepsync.rng import DETECTOR_NOISE, indexed_rng
from deepsync.types import FRAME_SECONDS

BOLTZMANN = 1.380649e-23
CHUNK_TICKS = round(BASE_RATE_HZ * FRAME_SECONDS)  # 10 ms of output per chunk
STEP_TICKS = 960  # output of one filter block: 20 blocks per chunk
GUARD_TICKS = 32  # 17 us after each block for the tapered filter's pre-ringing
NOISE_DB = 40.0  # noise is drawn up to where the video filter is this far down


def video_multiplier(config: FrontendConfig, video: VideoFilter) -> int:
    """Video-signal samples per tick: a power of two >= 8x the ADC rate and 2x the stop band.

    8x oversampling keeps the ADC's cubic interpolation error below -65 dB at 0.96 MHz.
    """
    needed = max(8 * config.adc_rate_hz, 2 * video.stopband_hz) / BASE_RATE_HZ
    return 2 ** math.ceil(math.log2(needed))


def output_noise_density(config: FrontendConfig, diode_power_w: float) -> float:
    """Two-sided noise density at the diode output, in W^2/Hz of |x|^2 (x V^2/W^2 -> V^2/Hz).

    Detector noise NEP^2 / 2, RF noise through the square law 2 P N0 (signal x noise) and
    N0^2 B_rf (noise x noise, near DC), with N0 = k T F G the RF noise density the LNA
    delivers and P the signal power at the diode.
    """
    n0 = BOLTZMANN * config.noise_temperature_k * 10 ** (config.noise_figure_db / 10) * config.rf_power_gain
    return config.detector_nep_w_per_sqrt_hz**2 / 2 + 2 * diode_power_w * n0 + n0**2 * config.rf_bandwidth_hz


class ClusterDetector:
    """|x|^2 of one cluster's complex baseband over any span of ticks."""

    def __init__(
        self,
        cluster: Cluster,
        emitters: list[Emitter],
        channel: ChannelProvider,
        seed: int,
    ) -> None:
        self.cluster = cluster
        self.m = cluster.oversampling
        groups: dict[tuple, list[int]] = defaultdict(list)
        for i in cluster.emitter_indices:
            e = emitters[i]
            key = (e.site or f"#{i}", e.carrier_hz, e.cell.bandwidth_mhz, e.timing_offset_s, e.frequency_offset_hz)
            groups[key].append(i)
        self.renderers = [GroupRenderer(cluster, members, emitters, channel, seed) for members in groups.values()]
        # |x|^2 only sees the groups' carriers relative to one another: the first stays put
        for renderer in self.renderers[1:]:
            renderer.turns_per_sample = (renderer.offset_hz - self.renderers[0].offset_hz) / cluster.sample_rate_hz
        self._frames: list[list[Frame]] = [[] for _ in self.renderers]
        self._next: list[int | None] = [None] * len(self.renderers)

    def power(self, first_tick: int, n_ticks: int) -> np.ndarray:
        """|x|^2 (W) at the cluster rate over [first_tick, first_tick + n_ticks)."""
        start = first_tick * self.m
        stop = start + n_ticks * self.m
        signal = None
        for r in range(len(self.renderers)):
            pieces = [f.samples[max(f.start, start) - f.start : min(f.stop, stop) - f.start]
                      for f in self._frames_over(r, start, stop) if f.stop > start and f.start < stop]
            if signal is None:  # the first group's samples; written to only if another group follows
                signal = pieces[0] if len(pieces) == 1 else np.concatenate(pieces)
                if len(self.renderers) > 1 and len(pieces) == 1:
                    signal = signal.copy()
            else:
                at = 0
                for piece in pieces:
                    signal[at : at + len(piece)] += piece
                    at += len(piece)
        power = np.square(signal.real)
        power += np.square(signal.imag)
        return power

    def _frames_over(self, r: int, start: int, stop: int) -> list[Frame]:
        """Group r's frames from the one holding ``start`` to the one holding ``stop - 1``."""
        renderer = self.renderers[r]
        frames = [f for f in self._frames[r] if f.stop > start]
        if not frames or frames[0].start > start:
            frames, self._next[r] = [], renderer.frame_at(start)
        while not frames or frames[-1].stop < stop:
            frames.append(renderer.render(self._next[r]))
            self._next[r] += 1
        self._frames[r] = frames
        return frames


class Detector:
    """The detector output (volts at the diode output, noiseless) in 10 ms chunks."""

    def __init__(
        self,
        emitters: list[Emitter],
        channel: ChannelProvider,
        config: FrontendConfig,
        seed: int,
    ) -> None:
        if config.video_filter_order == 0:
            raise ValueError("video_filter_order 0 (no video filter) describes recordings only: an ADC "
                             "needs an anti-alias filter in front of it to be simulated")
        self.config = config
        self.seed = seed
        self.video = VideoFilter(config)
        self.video_multiplier = video_multiplier(config, self.video)
        self.video_rate = self.video_multiplier * BASE_RATE_HZ
        # overlap-save: the filter's causal tail before each block, and the short pre-ringing
        # its tapered stop band adds, after it
        self.overlap_ticks = math.ceil(self.video.settle_seconds * BASE_RATE_HZ / 16) * 16
        self.block_ticks = scipy.fft.next_fast_len(STEP_TICKS + self.overlap_ticks + GUARD_TICKS, real=True)
        self.clusters = [
            ClusterDetector(cluster, emitters, channel, seed)
            for cluster in plan_clusters(emitters, self.video.stopband_hz)
        ]
        # the video band: every bin below the stop band and the first one at or above it
        spacing = BASE_RATE_HZ / self.block_ticks
        self.kept_bins = math.ceil(self.video.stopband_hz / spacing) + 1
        bin_frequencies = np.arange(self.kept_bins) * spacing
        # antenna |x|^2 (W) -> diode output (V): LNA power gain, responsivity, video filter
        self._response = (
            config.rf_power_gain
            * config.detector_responsivity_v_per_w
            * self.video.response(bin_frequencies[: self.kept_bins])
        ).astype(np.complex64)

    def output(self, chunk: int, per_tick: int | float) -> np.ndarray:
        """Detector output (V) at ``per_tick`` samples per tick over chunk ``chunk``: ticks
        [chunk, chunk + 1) x CHUNK_TICKS. ``per_tick`` must give whole samples per block step
        and overlap (``aligned``)."""
        first_tick = chunk * CHUNK_TICKS - self.overlap_ticks
        n_ticks = CHUNK_TICKS - STEP_TICKS + self.block_ticks
        by_rate: dict[int, np.ndarray] = {}  # clusters at one rate are filtered together
        for cluster in self.clusters:
            power = cluster.power(first_tick, n_ticks)
            by_rate[cluster.m] = power if cluster.m not in by_rate else by_rate[cluster.m] + power
        spectra = np.zeros((CHUNK_TICKS // STEP_TICKS, self.kept_bins), dtype=np.complex64)
        for m, power in by_rate.items():
            blocks = np.lib.stride_tricks.sliding_window_view(power, self.block_ticks * m)[:: STEP_TICKS * m]
            bins = scipy.fft.rfft(blocks, axis=1, workers=1)[:, : self.kept_bins]
            bins *= np.float32(1 / m)  # every cluster's transform on the same scale
            spectra[:, : bins.shape[1]] += bins  # a narrow cluster's |x|^2 ends below the stop band
        spectra = multiply(spectra, self._response, out=spectra)
        return self._inverse(spectra, per_tick)

    def _inverse(self, spectra: np.ndarray, per_tick: int | float) -> np.ndarray:
        """The blocks' signals (their steps, concatenated) at ``per_tick`` samples per tick."""
        length = round(self.block_ticks * per_tick)
        # fold the two-sided spectrum onto ``length`` bins (Z[-k] = conj Z[k]); bin 0 is real
        spectra[:, 0] *= 0.5
        padded = np.zeros((len(spectra), -(-self.kept_bins // length) * length), dtype=np.complex64)
        padded[:, : self.kept_bins] = spectra
        folded = padded.reshape(len(spectra), -1, length).sum(axis=1)
        mirror = np.roll(folded[:, ::-1], 1, axis=1)  # folded[-q]
        hermitian = folded[:, : length // 2 + 1] + np.conj(mirror[:, : length // 2 + 1])
        blocks = scipy.fft.irfft(hermitian, n=length, axis=1, workers=1) * np.float32(per_tick)
        first = round(self.overlap_ticks * per_tick)
        return blocks[:, first : first + round(STEP_TICKS * per_tick)].reshape(-1).astype(np.float64)

    def aligned(self, per_tick: float) -> bool:
        """Whether ``per_tick`` samples per tick fall whole on every block step and overlap."""
        return all(abs(n * per_tick - round(n * per_tick)) < 1e-9
                   for n in (STEP_TICKS, self.overlap_ticks, self.block_ticks))


class DetectorNoise:
    """Detector and RF noise at the ADC's samples, drawn per 10 ms block of sample indices."""

    def __init__(self, config: FrontendConfig, seed: int) -> None:
        self.config = config
        self.seed = seed
        self.block = max(1, round(config.adc_rate_hz * FRAME_SECONDS))
        video = VideoFilter(config)
        rate = config.adc_rate_hz
        frequencies = np.arange(self.block // 2 + 1) * (rate / self.block)
        # every alias of the filtered white noise, up to where the filter is NOISE_DB down
        cutoff = video.attenuation_hz(NOISE_DB)
        aliases = np.arange(-math.ceil(cutoff / rate) - 1, math.ceil(cutoff / rate) + 2)
        shifted = np.abs(frequencies[None, :] + aliases[:, None] * rate)
        gain = squared_magnitude(video.response(shifted)) * (shifted < cutoff)
        # white noise of unit two-sided density at the diode, filtered and sampled: the spectrum's
        # standard deviation per bin (irfft's 1/block included); bins 0 and block/2 are real
        self._spread = np.sqrt(gain.sum(axis=0) * self.block * rate / 2)
        self._spread[0] *= math.sqrt(2)
        if self.block % 2 == 0:
            self._spread[-1] *= math.sqrt(2)

    def samples(self, block: int, diode_power_w: float) -> np.ndarray:
        """Noise (V) of ADC samples [block, block + 1) x ``block`` for a block whose signal
        carries ``diode_power_w`` at the diode."""
        density = output_noise_density(self.config, diode_power_w)  # W^2/Hz of |x|^2
        if density <= 0:
            return np.zeros(self.block)
        rng = indexed_rng(self.seed, DETECTOR_NOISE, block)
        draws = rng.standard_normal((2, len(self._spread)))
        spectrum = np.empty(len(self._spread), dtype=np.complex128)
        scale = self._spread * (self.config.detector_responsivity_v_per_w * math.sqrt(density))
        spectrum.real = draws[0] * scale
        spectrum.imag = draws[1] * scale
        return scipy.fft.irfft(spectrum, n=self.block, workers=1)
