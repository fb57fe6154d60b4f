"""Received complex baseband of co-located cells, one 10 ms frame at a time.

A *group* is the cells of one site on one carrier (its sectors): same position, frame timing
and oscillator, hence the same propagation delays. Their grids are weighted by their own
channels, summed, and sent through a single IFFT per OFDM symbol. The group is rendered at
its own carrier (its subcarriers around DC); the cluster turns it to its offset from the
cluster's centre (``ClusterDetector``), a rotation that only matters against other groups.

What is exact and what is approximated:

* The bulk delay (frame timing + first-path delay) is applied exactly, sub-sample part
  included: each symbol's waveform is evaluated at the true sample instants through a phase
  ramp on its subcarriers, and every symbol boundary falls on the first sample at or after
  its true instant. The ground-truth arrival time is therefore the waveform's.
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

Every product of complex numbers here goes through ``deepsync.frontend.portable``: the frame
is the same, bit for bit, on every CPU.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft

from deepsync.frontend.channel import ChannelProvider, Emitter, Paths
from deepsync.frontend.plan import Cluster
from deepsync.frontend.portable import ExactProduct, multiply, multiply_double, phasor
from deepsync.lte.frame import FrameGenerator
from deepsync.lte.numerology import SLOTS_PER_FRAME, SUBCARRIER_SPACING_HZ, SYMBOLS_PER_SLOT, Numerology
from deepsync.types import FRAME_SECONDS

STATIC_DOPPLER_CYCLES = 1e-4  # below this many cycles per frame, gains are held constant
SLOT_DOPPLER_CYCLES = 0.01  # below this many cycles per slot (20 Hz), gains change per slot
ON_SAMPLE = 1e-9  # arrivals this close to a sample instant are on it (float noise, not physics)
CACHE_SIZE = 64  # path sets whose layout and rotations are kept (a static scene needs one per cell)


def _first_sample(arrival: float) -> int:
    """First sample at or after a (fractional) arrival instant."""
    return int(np.ceil(arrival - ON_SAMPLE))


def emitter_seed(seed: int, emitter_index: int) -> int:
    """Seed of one cell's random content, independent of how cells are grouped."""
    return int(np.random.SeedSequence([seed, 0x5EED, emitter_index]).generate_state(1)[0])


class _TapLayout:
    """Paths grouped by delay (taps), and every tap's phase across the subcarriers."""

    def __init__(self, relative_delays: np.ndarray, frequencies: np.ndarray) -> None:
        delays, tap = np.unique(relative_delays, return_inverse=True)
        self.order = np.argsort(tap, kind="stable")
        self.first = np.searchsorted(tap[self.order], np.arange(len(delays)))  # each tap's first path
        self.steering = ExactProduct(phasor(-2 * np.pi * np.outer(delays, frequencies)))


def _cached(cache: dict, key: bytes, make):
    if key not in cache:
        if len(cache) >= CACHE_SIZE:
            cache.pop(next(iter(cache)))
        cache[key] = make()
    return cache[key]


@dataclass(frozen=True)
class Frame:
    """Samples ``start .. start + len(samples)`` of a group's complex baseband."""

    start: int
    samples: np.ndarray

    @property
    def stop(self) -> int:
        return self.start + len(self.samples)


class GroupRenderer:
    """Renders the frames of one site's cells on one carrier at a cluster's sample rate."""

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
        # the carrier's offset from the cluster's centre: whole subcarriers and the rest
        self.offset_hz = cluster.carrier_bins[position] * SUBCARRIER_SPACING_HZ + cluster.residual_hz[position]
        self.timing_offset_s = first.timing_offset_s
        self.num = Numerology.for_bandwidth(first.cell.bandwidth_mhz, fft_size=cluster.fft_size)
        self.rate = self.num.sample_rate_hz
        self.frame_length = self.num.samples_per_frame
        self.generators = [FrameGenerator(emitters[i].cell, emitter_seed(seed, i)) for i in members]
        self.amplitudes = [math.sqrt(emitters[i].re_power_w) for i in members]

        offsets = self.num.subcarrier_offsets()
        self.frequencies = offsets * SUBCARRIER_SPACING_HZ
        half = len(offsets) // 2  # subcarriers below DC go to the top of the IFFT
        n = self.num.fft_size
        self._runs = ((slice(n - half, n), slice(0, half)), (slice(1, half + 1), slice(half, None)))
        self.useful_start = self.num.symbol_starts + self.num.cp_lengths
        self.symbol_times = (self.useful_start + self.num.fft_size / 2) / self.rate
        self.slot_times = self.symbol_times.reshape(SLOTS_PER_FRAME, -1).mean(axis=1)
        self._spectrum = np.zeros((len(self.useful_start), n), dtype=np.complex64)
        self._content = np.empty((len(self.useful_start), len(offsets)), dtype=np.complex64)
        self._layouts: dict[bytes, _TapLayout] = {}  # by relative delays
        self._rotations: dict[bytes, np.ndarray] = {}  # path gains' rotation over the frame, by delays and Doppler
        self._turns_per_sample = 0.0
        self._rotation = None
        self._paths: dict[int, list[Paths]] = {}
        cp = self.num.cp_lengths
        if not (np.all(cp[::SYMBOLS_PER_SLOT] == cp[0]) and np.all(np.delete(cp, np.s_[::SYMBOLS_PER_SLOT]) == cp[1])):
            raise AssertionError("every slot starts with the long cyclic prefix")
        self._cp_first, self._cp_other = int(cp[0]), int(cp[1])

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

    def _response(self, member: int, k: int, reference_delay: float, ramp: np.ndarray) -> np.ndarray:
        """(U, K) per-subcarrier response of one cell in frame k, U = 1 (static frame), 20 (per
        slot) or 140 (per symbol)."""
        paths = self.paths(k)[member]
        # femtosecond rounding: equal delays computed along different float paths stay equal
        relative = np.round(paths.delays_s - reference_delay, 15)
        layout = _cached(self._layouts, relative.tobytes(), lambda: _TapLayout(relative, self.frequencies))
        doppler = paths.doppler_hz[layout.order]
        # a static scene's paths rotate the same way in every frame
        rotation = _cached(self._rotations, relative.tobytes() + doppler.tobytes(), lambda: self._rotation_over(doppler))
        gains = paths.gains[layout.order] * self.amplitudes[member]
        per_tap = np.add.reduceat(multiply_double(rotation, gains), layout.first, axis=1)  # (U, Q)
        response = layout.steering(per_tap)
        return multiply(response, ramp, out=response)

    def _rotation_over(self, doppler: np.ndarray) -> np.ndarray:
        """exp(j 2 pi f t) of every path (P Doppler shifts) at the update instants: (U, P)."""
        return phasor(2 * np.pi * np.outer(self.update_times(doppler), doppler))

    def update_times(self, doppler: np.ndarray) -> np.ndarray:
        """Instants (s from the frame start) at which path gains are evaluated: the whole
        frame, each slot's or each symbol's middle, by the fastest Doppler."""
        fastest = float(np.max(np.abs(doppler)))
        if fastest * FRAME_SECONDS < STATIC_DOPPLER_CYCLES:
            return np.zeros(1)
        if fastest * FRAME_SECONDS / SLOTS_PER_FRAME < SLOT_DOPPLER_CYCLES:
            return self.slot_times
        return self.symbol_times

    def render(self, k: int) -> Frame:
        """Received samples of frame k of every cell of the group, summed, and turned by
        ``turns_per_sample`` (the cluster's rotation of this group against its first one)."""
        start, stop = self.bounds(k)
        reference_delay = min(p.first_delay_s for p in self.paths(k))
        # each symbol read from the first sample at or after its true start: a delay of
        # ``arrival - start`` (in (-1, 0]) samples on every subcarrier; and the rotation's phase
        # at the frame's first sample
        lead = self._arrival(k) - start
        turned = (self.turns_per_sample * start) % 1.0
        ramp = phasor(2 * np.pi * (turned - self.frequencies * (lead / self.rate))).astype(np.complex64)

        for m, generator in enumerate(self.generators):
            response = self._response(m, k, reference_delay, ramp)  # (U, K)
            shared = len(response)  # rows of the grid that share one response
            grid = generator.grid(k).reshape(shared, -1, response.shape[1])
            if m == 0:  # rounded to single precision once, the sum of the cells too
                content = multiply(grid, response[:, None, :], out=self._content.reshape(grid.shape))
            else:
                content = multiply(grid, response[:, None, :])
            content = content.reshape(len(self._spectrum), -1)
            for bins, subcarriers in self._runs:
                if m == 0:
                    self._spectrum[:, bins] = content[:, subcarriers]
                else:
                    self._spectrum[:, bins] += content[:, subcarriers]
        symbols = scipy.fft.ifft(self._spectrum, axis=1, norm="forward", workers=1)
        return Frame(start, self._with_prefixes(symbols, stop - start))

    @property
    def turns_per_sample(self) -> float:
        """The rotation the cluster gives this group (cycles per sample)."""
        return self._turns_per_sample

    @turns_per_sample.setter
    def turns_per_sample(self, turns: float) -> None:
        self._turns_per_sample = float(turns)
        self._rotation = phasor(2 * np.pi * self._turns_per_sample * np.arange(self.frame_length + 1)).astype(np.complex64)

    def _with_prefixes(self, symbols: np.ndarray, length: int) -> np.ndarray:
        """The frame's first ``length`` samples: each symbol after its cyclic prefix (its own
        tail), then the last symbol continued (a frame that ends late: by a sample as the
        arrival slides, by more where the earliest path vanishes from one frame to the next, as
        a ray-traced channel's may; the next frame then starts from its own later arrival);
        turned by the group's rotation on the way where it has one."""
        n, first, other = self.num.fft_size, self._cp_first, self._cp_other
        if length > self.frame_length + 1:
            head = self._with_prefixes(symbols, self.frame_length + 1)
            beyond = np.arange(1, length - self.frame_length)
            tail = symbols[-1, beyond % n].astype(np.complex64)
            if self.turns_per_sample:
                turn = phasor(2 * np.pi * self._turns_per_sample * (self.frame_length + beyond)).astype(np.complex64)
                multiply(tail, turn, out=tail)
            return np.concatenate([head, tail])
        out = np.empty(self.frame_length + 1, dtype=np.complex64)
        by_slot = symbols.reshape(SLOTS_PER_FRAME, SYMBOLS_PER_SLOT, n)
        slots = out[:-1].reshape(SLOTS_PER_FRAME, -1)
        rest = slots[:, first + n :].reshape(SLOTS_PER_FRAME, SYMBOLS_PER_SLOT - 1, other + n)
        pieces = ((slots[:, :first], by_slot[:, 0, n - first:]), (slots[:, first : first + n], by_slot[:, 0]),
                  (rest[:, :, :other], by_slot[:, 1:, n - other:]), (rest[:, :, other:], by_slot[:, 1:]))
        if not self.turns_per_sample:
            for into, source in pieces:
                into[...] = source
            out[-1] = symbols[-1, 0]
            return out[:length]
        turn = self._rotation
        turn_slots = turn[:-1].reshape(SLOTS_PER_FRAME, -1)
        turn_rest = turn_slots[:, first + n :].reshape(SLOTS_PER_FRAME, SYMBOLS_PER_SLOT - 1, other + n)
        turns = (turn_slots[:, :first], turn_slots[:, first : first + n], turn_rest[:, :, :other], turn_rest[:, :, other:])
        for (into, source), by in zip(pieces, turns):
            multiply(source, by, out=into)
        multiply(symbols[-1, :1], turn[-1:], out=out[-1:])
        return out[:length]
