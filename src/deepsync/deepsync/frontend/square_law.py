"""Square-law detection and the video filter, block by block, into the *video signal*.

Time runs in *ticks* of 1/1.92 MHz (every LTE rate is an integer number of samples per
tick). The video signal is produced in overlap-save blocks of ``BLOCK_TICKS``: for each
cluster, |x|^2 of its complex baseband is Fourier transformed, multiplied by the analog
filter's exact H(f), cropped to the video band and summed; one inverse FFT per block then
gives the detector output at ``video_rate`` (volts at the diode, before AC coupling and gain).

Noise:

* Detector noise (diode + video amplifier) is white at the diode output with density
  R * NEP (V/sqrt(Hz)), shaped by the video filter.
* RF thermal noise n (density kTF) reaches the output as 2 Re(x n*) and |n|^2. Their sum is
  Gaussian and white across the video band with two-sided density R^2 (2 P N0 + N0^2 B_rf),
  so it is added there analytically (``test_frontend`` checks this against a brute-force
  |x + n|^2). With the default detector this is 20-50 dB below the diode's own noise for
  any input inside the square-law region, which is why envelope detectors are insensitive.
  Simulating 10-20 MHz of explicit RF noise would cost a fifth of the run time for that.
* Noise is drawn independently per block, so its correlation across the ~10 us filter
  memory at block edges (0.1 % of samples) is not reproduced; and only up to where the video
  filter is 40 dB down, beyond which it holds ~1e-4 of the filtered noise power.
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np
import scipy.fft

from deepsync.frontend.channel import ChannelProvider, Emitter
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.plan import Cluster, plan_clusters
from deepsync.frontend.render import Frame, GroupRenderer
from deepsync.frontend.video import VideoFilter
from deepsync.lte.numerology import BASE_RATE_HZ
from deepsync.rng import DETECTOR_NOISE, indexed_rng

BOLTZMANN = 1.380649e-23
BLOCK_TICKS = 16384  # FFT span of one block (8.5 ms): a power of two times any cluster's multiplier
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
        self._frames: list[list[Frame]] = [[] for _ in self.renderers]
        self._next: list[int | None] = [None] * len(self.renderers)

    def power(self, first_tick: int, n_ticks: int) -> np.ndarray:
        """|x|^2 (W) at the cluster rate over [first_tick, first_tick + n_ticks)."""
        start = first_tick * self.m
        stop = start + n_ticks * self.m
        signal = np.zeros(stop - start, dtype=np.complex64)
        for r, renderer in enumerate(self.renderers):
            frames = [f for f in self._frames[r] if f.stop > start]
            if not frames or frames[0].start > start:
                frames, self._next[r] = [], renderer.frame_at(start)
            while not frames or frames[-1].stop < stop:
                frames.append(renderer.render(self._next[r]))
                self._next[r] += 1
            for frame in frames:
                a, b = max(frame.start, start), min(frame.stop, stop)
                if a < b:
                    signal[a - start : b - start] += frame.samples[a - frame.start : b - frame.start]
            self._frames[r] = frames
        return signal.real**2 + signal.imag**2


class Detector:
    """The video signal (volts at the diode output) in fixed overlap-save blocks."""

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
        # overlap-save guards: the filter's causal tail before each block, and the short
        # pre-ringing its tapered stop band adds, after it
        self.overlap_ticks = math.ceil(self.video.settle_seconds * BASE_RATE_HZ / 16) * 16
        self.guard_ticks = GUARD_TICKS
        self.step_ticks = BLOCK_TICKS - self.overlap_ticks - self.guard_ticks
        if self.step_ticks <= BLOCK_TICKS // 2:
            raise ValueError(
                f"video filter ({config.video_cutoff_hz:g} Hz, order {config.video_filter_order}) "
                "rings too long for the detector's block size; raise video_cutoff_hz"
            )
        self.clusters = [
            ClusterDetector(cluster, emitters, channel, seed)
            for cluster in plan_clusters(emitters, self.video.stopband_hz)
        ]
        self.block_length = BLOCK_TICKS * self.video_multiplier
        self.last_diode_power_w = 0.0
        bin_frequencies = np.arange(self.block_length // 2 + 1) * (BASE_RATE_HZ / BLOCK_TICKS)
        self.kept_bins = int(np.searchsorted(bin_frequencies, self.video.stopband_hz)) + 1
        self.noise_bins = int(np.searchsorted(bin_frequencies, self.video.attenuation_hz(NOISE_DB))) + 1
        # antenna |x|^2 (W) -> diode output (V): LNA power gain, responsivity, video filter
        self._response = (
            config.rf_power_gain
            * config.detector_responsivity_v_per_w
            * self.video.response(bin_frequencies[: self.kept_bins])
        ).astype(np.complex64)

    @property
    def block_samples(self) -> int:
        """Video samples each block contributes (its step)."""
        return self.step_ticks * self.video_multiplier

    def block_start_tick(self, block: int) -> int:
        return block * self.step_ticks

    def block(self, block: int) -> np.ndarray:
        """Video signal (V) for ticks [b * step, (b + 1) * step) at ``video_rate``."""
        first_tick = self.block_start_tick(block) - self.overlap_ticks
        spectrum = np.zeros(self.block_length // 2 + 1, dtype=np.complex64)
        antenna_power = 0.0
        for cluster in self.clusters:
            power = cluster.power(first_tick, BLOCK_TICKS)
            antenna_power += float(power.mean())
            bins = scipy.fft.rfft(power)[: self.kept_bins]
            spectrum[: len(bins)] += bins * (self.block_length / len(power))
        spectrum[: self.kept_bins] *= self._response
        self.last_diode_power_w = antenna_power * self.config.rf_power_gain
        density = output_noise_density(self.config, self.last_diode_power_w)
        if density > 0:
            spectrum[: self.noise_bins] += self._noise_bins(block, density)
        video = scipy.fft.irfft(spectrum, n=self.block_length)
        first = self.overlap_ticks * self.video_multiplier
        return video[first : first + self.block_samples]

    def _noise_bins(self, block: int, density: float) -> np.ndarray:
        """Spectrum of this block's noise (density in W^2/Hz at the diode), through the filter."""
        responsivity = self.config.detector_responsivity_v_per_w
        variance = responsivity**2 * density * self.video_rate  # V^2 per video sample
        scale = math.sqrt(self.block_length * variance / 2)
        rng = indexed_rng(self.seed, DETECTOR_NOISE, block)
        draws = rng.standard_normal((2, self.noise_bins), dtype=np.float32)
        noise = (draws[0] + 1j * draws[1]) * scale
        noise[0] = draws[0, 0] * scale * math.sqrt(2)
        filtered = self._response[: self.noise_bins] / (responsivity * self.config.rf_power_gain)
        return noise.astype(np.complex64) * filtered
