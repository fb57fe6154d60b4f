"""Received complex baseband of co-located cells, one 10 ms frame at a time.

A *group* is the cells of one site on one carrier (its sectors): same position, frame timing
and oscillator, hence the same propagation delays. Their grids are weighted by their own
channels, summed, and sent through a single IFFT per OFDM symbol.

What is exact and what is approximated:

* The bulk delay (frame timing + first-path delay) is applied exactly, sub-sample part
  included: each symbol's waveform is evaluated at the true sample instants through a phase
  ramp on its subcarriers, and every symbol boundary falls on the right sample (see
  ``lte.ofdm.symbol_index_map``). The ground-truth arrival time is therefore the waveform's.
* Later paths are applied per subcarrier within each symbol (a cyclic channel). This is exact
  except in the first (path excess delay) of each symbol's CP, where the true signal still
  holds the previous symbol's tail; TR 38.901 delay spreads keep that inside the 4.7 us CP.
* Delays are held for a frame (10 ms) and path gains rotate by their Doppler: per slot
  (0.5 ms) up to 20 Hz (<= 0.03 rad from the slot's mid-time), per symbol above (71 us:
  <= 0.05 rad at 100 Hz). A moving receiver's bulk delay
  changes by ~1 ns per frame, so frame boundaries may move by one sample when it crosses a
  sample boundary; the frame then ends one sample early or late, continuing its last symbol.
* A site's frame clock may drift (``Emitter.frame_rate_error``): frame starts follow it
  exactly, while the samples within a frame keep their nominal spacing (<= 10 ns off by the
  frame's end at 1000 ppb); the frame then ends a sample early or late now and then, as above.
* Carrier offsets that are not whole 15 kHz bins (100 kHz raster, oscillator error) rotate
  the samples continuously in true time.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.fft

from deepsync.frontend.channel import ChannelProvider, Emitter, Paths
from deepsync.frontend.plan import Cluster
from deepsync.lte.frame import FrameGenerator
from deepsync.lte.numerology import SLOTS_PER_FRAME, SUBCARRIER_SPACING_HZ, Numerology
from deepsync.lte.ofdm import symbol_index_map
from deepsync.types import FRAME_SECONDS

STATIC_DOPPLER_CYCLES = 1e-4  # below this many cycles per frame, gains are held constant
SLOT_DOPPLER_CYCLES = 0.01  # below this many cycles per slot (20 Hz), gains change per slot
ON_SAMPLE = 1e-9  # arrivals this close to a sample instant are on it (float noise, not physics)
# steering matrices kept for path delays seen before: a static receiver's repeat frame after
# frame; a moving one's change every frame, and an unbounded cache grew by ~70 MB per second of
# a six-site walk (14 GB for three minutes)
STEERING_CACHE = 32


def _contiguous_runs(bins: np.ndarray) -> list[tuple[slice, slice]]:
    """(FFT-bin slice, subcarrier slice) pairs covering ``bins``, which wrap and skip DC."""
    breaks = np.flatnonzero(np.diff(bins) != 1) + 1
    edges = np.concatenate(([0], breaks, [len(bins)]))
    return [(slice(int(bins[a]), int(bins[b - 1]) + 1), slice(int(a), int(b))) for a, b in zip(edges[:-1], edges[1:])]


def _first_sample(arrival: float) -> int:
    """First sample at or after a (fractional) arrival instant."""
    return int(np.ceil(arrival - ON_SAMPLE))


def emitter_seed(seed: int, emitter_index: int) -> int:
    """Seed of one cell's random content, independent of how cells are grouped."""
    return int(np.random.SeedSequence([seed, 0x5EED, emitter_index]).generate_state(1)[0])


@dataclass(frozen=True)
class Frame:
    """Samples ``start .. start + len(samples)`` of a cluster's complex baseband."""

    start: int
    samples: np.ndarray

    @property
    def stop(self) -> int:
        return self.start + len(self.samples)


class GroupRenderer:
    """Renders the frames of one site's cells on one carrier into a cluster's sample grid."""

    def __init__(
        self,
        cluster: Cluster,
        members: list[int],
        emitters: list[Emitter],
        channel: ChannelProvider,
        seed: int,
    ) -> None:
        first = emitters[members[0]]
        for i in members[1:]:  # one site: one frame clock
            if (emitters[i].timing_offset_s, emitters[i].frame_rate_error) != (
                    first.timing_offset_s, first.frame_rate_error):
                raise ValueError(f"emitters {members[0]} and {i} of site {first.site!r} disagree in "
                                 "frame timing: the sectors of a site share one frame clock")
        position = cluster.emitter_indices.index(members[0])
        self.members = members
        self.clock = first  # the group's frame clock (Emitter.frame_start_s and friends)
        self.channel = channel
        self.carrier_bin = cluster.carrier_bins[position]
        self.residual_hz = cluster.residual_hz[position]
        self.timing_offset_s = first.timing_offset_s
        self.num = Numerology.for_bandwidth(first.cell.bandwidth_mhz, fft_size=cluster.fft_size)
        self.rate = self.num.sample_rate_hz
        self.frame_length = self.num.samples_per_frame
        self.generators = [FrameGenerator(emitters[i].cell, emitter_seed(seed, i)) for i in members]
        self.amplitudes = [np.sqrt(emitters[i].re_power_w) for i in members]

        offsets = self.num.subcarrier_offsets()
        self.frequencies = offsets * SUBCARRIER_SPACING_HZ
        self._bin_runs = _contiguous_runs((offsets + self.carrier_bin) % self.num.fft_size)
        self.useful_start = self.num.symbol_starts + self.num.cp_lengths
        self.symbol_times = (self.useful_start + self.num.fft_size / 2) / self.rate
        self.slot_times = self.symbol_times.reshape(SLOTS_PER_FRAME, -1).mean(axis=1)
        self._symbols = np.zeros((len(self.useful_start), self.num.fft_size), dtype=np.complex64)
        self._index_maps: dict[int, np.ndarray] = {}
        self._steering: OrderedDict[bytes, np.ndarray] = OrderedDict()  # least recently used first
        self._paths: dict[int, list[Paths]] = {}
        self._rotation = None
        if self.residual_hz != 0.0:
            n = np.arange(self.frame_length + 1)
            self._rotation = np.exp(2j * np.pi * self.residual_hz * n / self.rate).astype(np.complex64)

    # -- timing -----------------------------------------------------------------------------

    def frame_time(self, k: int) -> float:
        """True time at which frame k leaves the antennas (drifting with the site clock)."""
        return self.clock.frame_start_s(k)

    def paths(self, k: int) -> list[Paths]:
        if k not in self._paths:
            if len(self._paths) > 4:
                self._paths.pop(min(self._paths))
            self._paths[k] = [self.channel.paths(i, self.frame_time(k)) for i in self.members]
        return self._paths[k]

    def _arrival(self, k: int) -> float:
        """Arrival of frame k's first sample (first path), in cluster samples (fractional)."""
        first_delay = min(p.first_delay_s for p in self.paths(k))
        # the nominal frame grid in whole samples, less the site clock's slip (0.0 without
        # drift, which keeps this bit-exact); equal to (frame_time(k) + first_delay) * rate
        nominal = k * self.frame_length + (self.timing_offset_s + first_delay) * self.rate
        return nominal - self.clock.frame_slip_s(k) * self.rate

    def bounds(self, k: int) -> tuple[int, int]:
        """[start, stop) of the samples frame k occupies; stop is frame k+1's start."""
        return _first_sample(self._arrival(k)), _first_sample(self._arrival(k + 1))

    def frame_at(self, sample: int) -> int:
        """Index of the frame that covers cluster sample ``sample``."""
        k = self.clock.frame_index_at(sample / self.rate)  # a guess: arrivals come later
        while self.bounds(k)[0] > sample:
            k -= 1
        while self.bounds(k)[1] <= sample:
            k += 1
        return k

    # -- waveform ---------------------------------------------------------------------------

    def _index_map(self, shift: int) -> np.ndarray:
        """Flat IFFT index for each frame sample, plus one continuing the last symbol."""
        if shift not in self._index_maps:
            index = symbol_index_map(self.num, shift)
            last_symbol = (len(self.useful_start) - 1) * self.num.fft_size
            extra = last_symbol + (index[-1] - last_symbol + 1) % self.num.fft_size
            self._index_maps[shift] = np.append(index, extra)
        return self._index_maps[shift]

    def _channel_response(self, paths: Paths, reference_delay: float, fraction: float) -> np.ndarray:
        """(U, K) per-subcarrier response, U = 1 (static frame), 20 (per slot) or 140 (per symbol)."""
        # femtosecond rounding: equal delays computed along different float paths stay equal
        relative, tap = np.unique(np.round(paths.delays_s - reference_delay, 15), return_inverse=True)
        key = relative.tobytes()
        if key in self._steering:
            self._steering.move_to_end(key)
        else:
            self._steering[key] = np.exp(-2j * np.pi * np.outer(relative, self.frequencies)).astype(np.complex64)
            if len(self._steering) > STEERING_CACHE:
                self._steering.popitem(last=False)
        order = np.argsort(tap, kind="stable")
        first_of_tap = np.searchsorted(tap[order], np.arange(len(relative)))
        doppler = paths.doppler_hz[order]
        fastest = float(np.max(np.abs(doppler)))
        if fastest * FRAME_SECONDS < STATIC_DOPPLER_CYCLES:
            times = np.zeros(1)
        elif fastest * FRAME_SECONDS / SLOTS_PER_FRAME < SLOT_DOPPLER_CYCLES:
            times = self.slot_times
        else:
            times = self.symbol_times
        rotation = np.exp(2j * np.pi * np.outer(times, doppler)) * paths.gains[order]  # (U, P)
        taps = np.add.reduceat(rotation, first_of_tap, axis=1).astype(np.complex64)  # (U, Q)
        ramp = np.exp(-2j * np.pi * self.frequencies * fraction / self.rate).astype(np.complex64)
        return (taps @ self._steering[key]) * ramp

    def render(self, k: int) -> Frame:
        """Received samples of frame k of every cell of the group, summed."""
        start, stop = self.bounds(k)
        arrival = self._arrival(k)
        whole = int(np.floor(arrival + ON_SAMPLE))
        fraction = arrival - whole
        reference_delay = min(p.first_delay_s for p in self.paths(k))

        # Each symbol's IFFT is referenced to its own start; this restores the phase of the
        # carrier's whole-bin offset from the cluster centre accumulated up to that start.
        n = self.num.fft_size
        at_symbol = (whole % n + self.useful_start) % n
        symbol_phase = np.exp(2j * np.pi * ((self.carrier_bin * at_symbol) % n) / n)

        content = np.zeros(self._symbols.shape[:1] + self.frequencies.shape, dtype=np.complex64)
        for generator, amplitude, paths in zip(self.generators, self.amplitudes, self.paths(k)):
            response = self._channel_response(paths, reference_delay, fraction) * np.float32(amplitude)
            grid = generator.grid(k)
            per_update = grid.reshape(len(response), -1, grid.shape[1])  # rows sharing a response
            content += (per_update * response[:, None, :]).reshape(grid.shape)
        content *= symbol_phase[:, None].astype(np.complex64)
        for bins, subcarriers in self._bin_runs:
            self._symbols[:, bins] = content[:, subcarriers]
        symbols = scipy.fft.ifft(self._symbols, axis=1, norm="forward")
        samples = symbols.reshape(-1)[self._index_map(start - whole)[: stop - start]]
        if self._rotation is not None:
            turns = (self.residual_hz * start / self.rate) % 1.0
            samples *= np.complex64(np.exp(2j * np.pi * turns)) * self._rotation[: stop - start]
        return Frame(start, samples)
