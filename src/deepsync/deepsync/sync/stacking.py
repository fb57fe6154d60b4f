"""Frame stacking: cut the ADC stream into consecutive 10 ms frames and group N of them.

Every cell repeats its sync codes every 10 ms, so adding N frames makes them add up N times in
amplitude while data averages out. The stacker knows nothing of the network's frame timing: a
"frame" is just 10 ms of stream, and a cell's code sits at its own offset inside it.

A stack starts every ``hop_frames`` frames: back to back by default (hop = N), or **sliding**
(hop < N): a 50-frame stack every 10 frames hears as far as 50 frames do and still answers at
10 Hz. Successive sliding stacks share N - hop frames, so their errors are correlated; and an
arrival moves by v/c over a stack (a car at 15 m/s: 0.1 sample per second), which the stack
averages: what it measures is the arrival at the stack's middle.

Stacking is incremental: each frame is cut from the stream once, when its samples are in, and
kept while a stack still needs it. Frames are summed in blocks of g = gcd(N, hop, N/2), each
block once, and a stack's mean is the sum of its N/g blocks, each moved by the whole samples
that line it up with the stack's first block (see the clock below). A sliding stack therefore
costs its new frames and a few block additions, not N frames again; and the buffer of raw
samples never holds much more than a frame.

The stream arrives in chunks of any size. The stacker checks what a driver or bag can get
wrong and reports it as a :class:`~deepsync.types.Health` event instead of stacking garbage:

* a gap (``first_sample_index`` jumps), samples that are not finite, or ADC codes beyond the
  range of ``adc_bits`` (no ADC makes them: the data is corrupt): the frames that would span
  them are dropped and stacking restarts after them; stacks before are unaffected;
* a chunk a little before what was already received (a late or repeated chunk, at most a
  stack back, on the same timeline): dropped;
* a stream that starts over (its index goes back further than a stack, or goes back while its
  time goes on: a driver restart, a bag played in a loop): stacking starts afresh from it;
* a chunk at another sample rate than the stacker's (the rate the templates were built for:
  one source of the rate): dropped with everything pending, and so is every chunk after it
  until the rate is right again, when stacking restarts;
* clipped frames, and silent or stuck ones (most of the stack holding one value): stacked,
  but the stack carries a flag.

Receiver clock offset: each frame starts ``frame * (1 + clock_ppm)`` samples after the one
before (the clock as known when it is cut). A block's first frame starts at that position
rounded, and its other frames at whole frames-and-samples from it (rounded relative to it, so
a block's rows line up within half a sample); the sub-sample remainder of each row is kept in
``Stack.row_shifts`` so windows can be aligned exactly. The clock needs no cell to be
known: everything deterministic in the envelope (every cell's sync codes and CRS, the symbol
power profile) repeats each frame and moves only with the receiver clock, so each stack
measures its own residual drift by cross-correlating the mean of its first and second halves
of frames. With ``track_clock`` the smoothed measurement becomes the compensation: the frames
cut after it are cut by it, and the frames a sliding stack keeps are placed by it again (their
exact starts, whole frame periods of the new clock apart; their samples stay where they were
cut). A stack whose residual drift across its rows exceeds ``max_drift_samples`` is marked
``aligned = False``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from functools import cached_property, lru_cache

import numpy as np
import scipy.fft

from deepsync.frontend.templates import check_template_rate
from deepsync.lte.numerology import BASE_RATE_HZ
from deepsync.numeric import mad_spread, parabolic_peak
from deepsync.schema import check_settings, setting
from deepsync.types import FRAME_SECONDS, HALF_FRAME_SECONDS, EnvelopeChunk, Health, HealthKind

MAX_CLOCK_PPM = 200.0  # a receiver crystal further off than this is not believed

MIN_STACK_RATE_HZ = 1.92e6
"""The slowest ADC the cell search serves: a PSS occupies 62 subcarriers (0.93 MHz), so its
envelope reaches 0.93 MHz and a slower ADC aliases it (measured on the campus scenario: every
cell found from 30.72 down to 1.536 MS/s, one missed at 1.28, three at 1.024)."""


def _serves(rate: float) -> bool:
    half = rate * HALF_FRAME_SECONDS
    return rate >= MIN_STACK_RATE_HZ and abs(half - round(half)) < 1e-6 * half


SERVED_RATES_HZ = tuple(rate for rate in (16 * BASE_RATE_HZ / k for k in range(1, 65)) if _serves(rate))
"""Every sample rate the sync stage serves, fastest first: 30.72 MS/s (1 / Ts, LTE's basic time
unit: 16 x 1.92 MS/s) divided by a whole factor
(the templates' rule) that leaves a whole number of samples in a half frame (the PSS repeats
every half frame, and frames are stacked on whole samples: 30.72 / 9 MS/s put 17066.7 samples
in one, and the search broke on it) and is at least :data:`MIN_STACK_RATE_HZ`."""


def check_stack_rate(sample_rate: float) -> float:
    """``sample_rate`` (Hz) if the sync stage serves it (:data:`SERVED_RATES_HZ`), else
    ValueError listing the rates it does: refused at the door, not mid-stream."""
    rate = check_template_rate(sample_rate)
    if not _serves(rate):
        listed = ", ".join(f"{r / 1e6:g}" for r in sorted(SERVED_RATES_HZ))
        raise ValueError(f"sample rate {rate:g} Hz: the cell search serves {listed} MS/s (a rate dividing 30.72 MHz "
                         f"with a whole number of samples per 5 ms half frame, at least "
                         f"{MIN_STACK_RATE_HZ / 1e6:g} MS/s for the PSS envelope's 0.93 MHz)")
    return rate
HELD_FRACTION = 0.5  # a stacked frame holding one value over more of it than this has no noise to measure
DRIFT_SMOOTHING = 0.3  # weight of each stack's drift measurement in the running estimate
CLOCK_REACH = 16  # samples kept before the next frame's start: how far a new clock estimate moves it back


@dataclass(frozen=True)
class StackConfig:
    n_frames: int = setting(10, help="LTE frames (10 ms) stacked per search: longer stacks hear weaker sites (3 dB "
                            "per doubling); the timing stage needs 2 to measure the noise.", unit="frames",
                            bounds=(1, 1000))
    clock_ppm: float = setting(0.0, help="Initial receiver clock error, compensated.", unit="ppm",
                               bounds=(-1000.0, 1000.0))
    track_clock: bool = setting(True, help="Follow the receiver clock drift measured on each stack.")
    max_drift_samples: float = setting(0.5, help="Largest drift across a stack still stacked as it is.",
                                       unit="samples", bounds=(0.0, 1000.0), open_low=True)
    clip_fraction: float = setting(1e-3, help="Flag a stack with more clipped samples than this fraction.",
                                   bounds=(0.0, 1.0))
    hop_frames: int | None = setting(None, help="Frames from one stack's start to the next; fewer than n_frames "
                                     "gives sliding stacks: n_frames 100, hop_frames 20 hears as 100 "
                                     "frames do and answers at 5 Hz.", unit="frames", bounds=(1, 1000))

    def __post_init__(self) -> None:
        check_settings(self)
        if self.hop_frames is not None and self.hop_frames > self.n_frames:
            raise ValueError(f"hop_frames must be 1..n_frames ({self.n_frames}), got {self.hop_frames!r}")

    @property
    def hop(self) -> int:
        """Frames from one stack's start to the next."""
        return self.n_frames if self.hop_frames is None else self.hop_frames


@dataclass(frozen=True)
class Stack:
    """N consecutive frames of the stream, one row per frame (float, volts). The frames are
    the stacker's own, shared with the other stacks that hold them, not copied per stack."""

    frames: tuple[np.ndarray, ...]  # n_frames x (frame_samples,) float32
    row_starts: np.ndarray  # (n_frames,) stream index of each row's first sample
    row_shifts: np.ndarray  # (n_frames,) exact start minus row_starts (clock remainder), samples
    sample_rate: float
    stamp_ns: int  # receiver time of the first sample of row 0
    mean: np.ndarray  # (frame_samples,) the rows averaged, summed incrementally by the stacker
    aligned: bool = True
    flags: tuple[Health, ...] = field(default=())
    drift_ppm: float | None = None  # receiver clock error measured on this stack (None: too weak)
    # samples by which what repeats sits later in ``mean`` than in row 0: the rows' clock
    # remainders averaged (a stack of N frames at c ppm: 0.0192 c (N - 1) / 2 samples)
    mean_delay: float = 0.0

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    @property
    def frame_samples(self) -> int:
        return len(self.frames[0])

    @cached_property
    def rows(self) -> np.ndarray:
        """(n_frames, frame_samples) the frames as one array (a copy)."""
        return np.stack(self.frames)

    def columns(self, index: np.ndarray) -> np.ndarray:
        """(n_frames, L) the samples at ``index`` of every frame (without copying them all):
        (L,) the same for every frame, or (n_frames, L) one row per frame."""
        index = np.broadcast_to(index, (self.n_frames, np.shape(index)[-1]))
        return np.stack([frame[row] for frame, row in zip(self.frames, index)])

    @property
    def first_sample_index(self) -> int:
        return int(self.row_starts[0])

    def stacked(self) -> np.ndarray:
        """The frames averaged: what the cell search looks at."""
        return self.mean


@dataclass(frozen=True)
class _Frame:
    """One frame cut from the stream, kept while a stack still needs it."""

    start: int  # stream index of its first sample
    shift: float  # exact start minus ``start`` (clock remainder; whole samples too, once placed again)
    samples: np.ndarray  # (frame_samples,) float32, volts
    clipped: int  # samples at the ADC rails


@dataclass(frozen=True)
class _Block:
    """The sum of a block's frames, and where their content sits in it: what repeats at time u
    of a frame is at sample u + ``placement`` of the sum (the frames' mean clock remainder, and
    any whole samples each was moved by to be summed)."""

    total: np.ndarray  # (frame_samples,) float64
    moves: tuple[int, ...]  # whole samples each frame was moved by to be summed
    placement: float


class FrameStacker:
    """Turns a chunked stream into :class:`Stack` objects (see the module docstring)."""

    def __init__(self, sample_rate: float, config: StackConfig | None = None) -> None:
        self.sample_rate = check_stack_rate(sample_rate)
        self.config = config or StackConfig()
        self.clock_ppm = self.config.clock_ppm
        self.measured_drift_ppm: float | None = None  # smoothed over stacks
        self.events: list[Health] = []
        self._expected: int | None = None  # next stream index expected; None: (re)start at the next chunk
        self._wrong_rate = False  # in a run of chunks at another sample rate
        self._origin = (0, 0)  # (stream index, stamp ns) the stamps are counted from
        self._latest = (0, 0)  # (stream index, stamp ns) of the latest chunk: the timeline a chunk must keep
        self._buffer = np.empty(0, dtype=np.float32)  # samples from the next frame's start on
        self._clipped = np.empty(0, dtype=bool)
        self._parts: list[tuple[np.ndarray, np.ndarray]] = []  # chunks after the buffer, joined once a frame is complete
        self._buffer_start = 0
        self._next_start = 0.0  # exact stream position of the next frame to cut
        self._block_origin = (0.0, 0)  # exact and integer start of the block being cut
        self._frames: deque[_Frame] = deque()  # cut, for the next stack; the first starts a block
        self._blocks: deque[_Block] = deque()  # sums of the frames, ``_block`` at a time
        n, hop = self.config.n_frames, self.config.hop
        self._block = math.gcd(n, hop, max(n // 2, 1))  # frames per block: stacks start and halve on block edges

    @property
    def frame_samples(self) -> int:
        return int(round(self.sample_rate * FRAME_SECONDS))

    @property
    def _held(self) -> int:
        """Samples received and not yet behind the last stack: its cut frames, the buffer and the parts."""
        first = self._frames[0].start if self._frames else self._buffer_start
        return self._buffer_start - first + len(self._buffer) + sum(len(part) for part, _ in self._parts)

    def push(self, chunk: EnvelopeChunk) -> list[Stack]:
        """Add a chunk of ADC codes; return the stacks it completes."""
        volts = chunk.samples.astype(np.float32) * np.float32(chunk.volts_per_code)
        low, high = -(2 ** (chunk.adc_bits - 1)), 2 ** (chunk.adc_bits - 1) - 1
        clipped = (chunk.samples == low) | (chunk.samples == high)
        corrupt = None  # codes beyond the ADC's range: only a wider dtype can hold them
        if not _fits_in(chunk.samples.dtype, low, high):
            beyond = (chunk.samples < low) | (chunk.samples > high)
            corrupt = beyond if beyond.any() else None
        return self.push_samples(volts, chunk.first_sample_index, chunk.sample_rate, chunk.stamp_ns, clipped,
                                 corrupt, chunk.adc_bits)

    def push_samples(
        self,
        samples: np.ndarray,
        first_sample_index: int,
        sample_rate: float,
        stamp_ns: int = 0,
        clipped: np.ndarray | None = None,
        corrupt: np.ndarray | None = None,
        adc_bits: int | None = None,
    ) -> list[Stack]:
        """Add float samples from any source (ADC volts, a recorded |x|^2, ...), sampled at
        ``sample_rate`` (Hz): at any other rate than the stacker's they are dropped (an event).
        ``clipped`` marks samples at the ADC rails, ``corrupt`` codes beyond ``adc_bits``."""
        samples = np.asarray(samples, dtype=np.float32)
        clipped = np.zeros(len(samples), dtype=bool) if clipped is None else np.asarray(clipped, dtype=bool)
        if not math.isclose(sample_rate, self.sample_rate, rel_tol=1e-9):
            if not self._wrong_rate:  # the first chunk of a run at the wrong rate says so
                self.events.append(Health(
                    HealthKind.RATE_MISMATCH,
                    f"chunk at sample {first_sample_index} comes at {sample_rate:g} Hz, but the templates are built "
                    f"for {self.sample_rate:g} Hz: dropped with {self._held} pending samples (an unfinished "
                    "stack), as is every chunk until the rate is right again",
                    first_sample_index,
                ))
                self._wrong_rate = True
                self._expected = None
                self._restart(first_sample_index, stamp_ns)
            return []
        self._wrong_rate = False
        if self._expected is None:
            self._restart(first_sample_index, stamp_ns)
        elif self._starts_over(first_sample_index, stamp_ns):
            self.events.append(Health(
                HealthKind.RESTART,
                f"the stream starts over at sample {first_sample_index} after sample {self._expected - 1} "
                f"(a driver restart, a bag played again?): {self._held} pending samples (an unfinished "
                "stack) dropped; stacking starts afresh",
                first_sample_index,
            ))
            self._restart(first_sample_index, stamp_ns)
        elif first_sample_index < self._expected:
            self.events.append(Health(
                HealthKind.BACKWARDS,
                f"chunk starts at sample {first_sample_index}, before {self._expected} already received; dropped",
                first_sample_index,
            ))
            return []
        elif first_sample_index > self._expected:
            self._event(HealthKind.GAP, self._expected, f"gap of {first_sample_index - self._expected} samples")
            self._restart(first_sample_index, stamp_ns)
        self._expected = first_sample_index + len(samples)
        self._latest = (first_sample_index, stamp_ns)

        not_finite = ~np.isfinite(samples)
        bad = not_finite if corrupt is None else not_finite | corrupt
        if not bad.any():
            return self._append(samples, clipped)
        first, last = int(np.argmax(bad)), len(bad) - 1 - int(np.argmax(bad[::-1]))
        stacks = self._append(samples[:first], clipped[:first])
        if corrupt is not None and corrupt.any():
            self._event(HealthKind.CORRUPT, first_sample_index + first,
                        f"{int(corrupt.sum())} codes beyond the {adc_bits}-bit ADC's range (corrupt data?) up to "
                        f"sample {first_sample_index + last}")
        else:
            self._event(HealthKind.NOT_FINITE, first_sample_index + first,
                        f"{int(bad.sum())} non-finite samples up to sample {first_sample_index + last}")
        after = first_sample_index + last + 1
        self._restart(after, stamp_ns + round((last + 1) * 1e9 / sample_rate))
        return stacks + self._append(samples[last + 1 :], clipped[last + 1 :])

    def _event(self, kind: HealthKind, index: int, what: str) -> None:
        self.events.append(Health(
            kind, f"{what} at sample {index}: {self._held} pending samples (an unfinished "
            "stack) dropped; stacking restarts after it", index,
        ))

    def _starts_over(self, index: int, stamp_ns: int) -> bool:
        """Whether a chunk begins a new stream rather than continuing, repeating or skipping
        ahead in this one: its stamp is off the stream's timeline (the time of the previous
        chunk, moved on by the samples in between) by more than a frame, so index and time no
        longer agree; or it goes back further than a stack could span (a bag played again)."""
        stack = self.config.n_frames * self.frame_samples
        latest_index, latest_stamp = self._latest  # not the origin: a slow drift of the stamps never adds up
        moved_on = latest_stamp + (index - latest_index) * 1e9 / self.sample_rate
        return abs(stamp_ns - moved_on) > FRAME_SECONDS * 1e9 or self._expected - index > stack

    def _restart(self, index: int, stamp_ns: int) -> None:
        self._buffer = np.empty(0, dtype=np.float32)
        self._clipped = np.empty(0, dtype=bool)
        self._parts.clear()
        self._buffer_start = index
        self._next_start = float(index)
        self._frames.clear()
        self._blocks.clear()
        self._origin = (index, stamp_ns)

    def _stamp(self, index: int) -> int:
        origin_index, origin_stamp = self._origin
        return origin_stamp + round((index - origin_index) * 1e9 / self.sample_rate)

    def _append(self, samples: np.ndarray, clipped: np.ndarray) -> list[Stack]:
        self._parts.append((samples, clipped))
        frame = self.frame_samples
        stacks = []
        while self._held_from_next() >= frame:
            if self._parts:  # joined once per frame, not per chunk
                self._buffer = np.concatenate([self._buffer, *(part for part, _ in self._parts)])
                self._clipped = np.concatenate([self._clipped, *(part for _, part in self._parts)])
                self._parts.clear()
            start = self._next_frame_start()
            if len(self._frames) % self._block == 0:
                self._block_origin = (self._next_start, start)
            at = start - self._buffer_start
            samples = self._buffer[at : at + frame].copy()
            samples.flags.writeable = False  # shared by every stack that holds the frame
            self._frames.append(_Frame(start, self._next_start - start, samples,
                                       int(np.count_nonzero(self._clipped[at : at + frame]))))
            self._next_start += frame * (1 + self.clock_ppm * 1e-6)
            # no frame needs the samples before the next one's start (which may be beyond what is
            # in), but a new clock estimate may move that start back by a few
            behind = max(0, min(self._next_frame_start() - CLOCK_REACH - self._buffer_start, len(self._buffer)))
            self._buffer, self._clipped = self._buffer[behind:], self._clipped[behind:]
            self._buffer_start += behind
            if len(self._frames) == self.config.n_frames:
                stacks.append(self._stack())
        return stacks

    def _next_frame_start(self) -> int:
        """Stream index of the next frame's first sample: its exact start rounded if it begins
        a block, else rounded relative to the block's first frame."""
        if len(self._frames) % self._block == 0:
            return round(self._next_start)
        exact, first = self._block_origin
        return first + round(self._next_start - exact)

    def _held_from_next(self) -> int:
        """Samples received from the next frame's start on."""
        return self._buffer_start - self._next_frame_start() + len(self._buffer) + sum(len(p) for p, _ in self._parts)

    def _stack(self) -> Stack:
        """The stack of the frames cut, then the first ``hop`` of them let go."""
        n, block, frame = self.config.n_frames, self._block, self.frame_samples
        frames = list(self._frames)
        for k in range(len(self._blocks) * block, n, block):  # each block summed once, by the first stack to hold it
            self._blocks.append(_sum_block(frames[k : k + block], frame))
        # each block moved by the whole samples that line it up with the first (a frame's
        # content repeats, so a circular move is exact for everything that repeats); half a
        # sample of misalignment stays, as within a block
        moves = [round(self._blocks[0].placement - b.placement) for b in self._blocks]
        moved = [np.roll(b.total, m) if m else b.total for b, m in zip(self._blocks, moves)]
        half = len(moved) // 2
        first, second = np.sum(moved[:half], axis=0), np.sum(moved[len(moved) - half :], axis=0)
        total = first + second if 2 * half == len(moved) else np.sum(moved, axis=0)
        mean = (total / n).astype(np.float32)
        flags = []
        clipped_fraction = sum(f.clipped for f in frames) / (n * frame)
        if clipped_fraction > self.config.clip_fraction:
            flags.append(Health(HealthKind.CLIPPED, f"{100 * clipped_fraction:.2f} % of samples at the ADC rails"))
        held = held_fraction(mean)
        if held > HELD_FRACTION:
            flags.append(Health(HealthKind.NO_SIGNAL, f"{100 * held:.1f} % of the stacked frame holds one "
                                "value (silent or stuck input)"))
        starts = np.array([f.start for f in frames], dtype=np.int64)
        shifts = np.array([f.shift for f in frames])
        residual = None
        placed = np.array([b.placement + m for b, m in zip(self._blocks, moves)])  # each block's content
        if half:  # where the halves' contents sit relative to each other, from the alignment alone
            offset = placed[len(moved) - half :].mean() - placed[:half].mean()
            residual = measure_drift(first, second, (len(moved) - half) * block, offset)
        exact = starts + shifts
        compensated = ((exact[-1] - exact[0]) / ((n - 1) * frame) - 1) * 1e6 if n > 1 else self.clock_ppm
        drift = None if residual is None else compensated + residual
        aligned = residual is None or abs(residual) * 1e-6 * frame * (n - 1) <= self.config.max_drift_samples
        if not aligned:
            flags.append(Health(HealthKind.MISALIGNED, f"{residual:+.1f} ppm of clock drift was not compensated"))
        stack = Stack(tuple(f.samples for f in frames), starts, shifts, self.sample_rate,
                      self._stamp(int(starts[0])), mean, aligned, tuple(flags), drift,
                      float(placed.mean() - shifts[0]))
        for _ in range(self.config.hop):
            self._frames.popleft()
        for _ in range(self.config.hop // block):
            self._blocks.popleft()
        if drift is not None:
            previous = self.measured_drift_ppm
            self.measured_drift_ppm = drift if previous is None else previous + DRIFT_SMOOTHING * (drift - previous)
            if self.config.track_clock and self.measured_drift_ppm != self.clock_ppm:
                self._replace(self.measured_drift_ppm)
        return stack

    def _replace(self, clock_ppm: float) -> None:
        """Follow a new clock estimate: the frames kept are placed by it, each a whole number of
        its frame periods before the newest (which the next frame follows), so the next stacks
        line them up by it; where that moves a block's frames against each other by more than
        a tenth of a sample, the block is summed again, each frame moved by its whole samples."""
        frame = self.frame_samples
        old, new = frame * (1 + self.clock_ppm * 1e-6), frame * (1 + clock_ppm * 1e-6)
        self.clock_ppm = clock_ppm
        newest = self._next_start - old
        self._next_start = newest + new
        kept = len(self._frames)
        self._frames = deque(_Frame(f.start, newest - (kept - 1 - i) * new - f.start, f.samples, f.clipped)
                             for i, f in enumerate(self._frames))
        block, frames = self._block, list(self._frames)
        if abs(new - old) * (block - 1) > 0.1:  # a block's frames moved against each other
            self._blocks = deque(_sum_block(frames[k : k + block], frame) for k in range(0, len(self._blocks) * block, block))
        else:
            self._blocks = deque(_Block(b.total, b.moves, float(np.mean(
                [f.shift + move for f, move in zip(frames[k * block : (k + 1) * block], b.moves)])))
                for k, b in enumerate(self._blocks))


@lru_cache(maxsize=16)
def _fits_in(dtype: np.dtype, low: int, high: int) -> bool:
    """Whether every value of an integer ``dtype`` lies in [low, high] (no code can be corrupt).
    Cached: numpy's type queries cost several microseconds, and every chunk asks."""
    if not np.issubdtype(dtype, np.integer):
        return False
    info = np.iinfo(dtype)
    return low <= info.min and info.max <= high


def _sum_block(frames: list[_Frame], frame: int) -> _Block:
    """A block of frames summed, each moved by the whole samples that line it up with the first."""
    total = np.zeros(frame)
    moves = tuple(round(frames[0].shift - f.shift) for f in frames)
    for f, move in zip(frames, moves):
        total += np.roll(f.samples, move) if move else f.samples
    return _Block(total, moves, float(np.mean([f.shift + move for f, move in zip(frames, moves)])))


HELD_STRIDE = 8  # every how many samples the held value is looked for among


def held_fraction(frame: np.ndarray) -> float:
    """Share of a frame's samples equal to the (upper) median of every ``HELD_STRIDE``-th one:
    1 for silent or stuck input, a little above 0 for anything with noise in it. Where most
    of a frame holds one value, correlations are exactly zero at most lags and no noise level
    can be measured from them. A value on more than half the samples is their median, and that
    of every 8th sample too unless where it is held lines up with the stride (a pattern of
    period 8, which no stuck or silent input makes); the selection's data-dependent branches
    cost about 10 ns a sample, so an eighth of them saves 0.2 ms per stacked frame, twice per
    stack (the stacker's flag, the search's check)."""
    sample = frame[::HELD_STRIDE]
    middle = len(sample) // 2
    return float(np.mean(frame == np.partition(sample, middle)[middle]))


def measure_drift(first: np.ndarray, second: np.ndarray, apart_frames: int, offset: float = 0.0,
                  max_ppm: float = MAX_CLOCK_PPM, min_z: float = 5.0) -> float | None:
    """Residual receiver clock drift (ppm) between two sums of a stack's frames (its first and
    its second half) whose middles are ``apart_frames`` frames apart, or None if it cannot be
    told; ``offset`` is how much later the second's content sits by the way the rows were cut.

    The second half is the first shifted by (apart x frame x drift) + offset: the peak of
    their circular cross-correlation, refined by a parabola, gives it. The peak must stand
    ``min_z`` robust sigmas out of the correlation, or there is nothing deterministic enough
    in the stream to time it by.
    """
    frame = len(first)
    first, second = first - first.mean(), second - second.mean()
    c = scipy.fft.irfft(scipy.fft.rfft(second) * np.conj(scipy.fft.rfft(first)), n=frame)
    reach = int(np.ceil(max_ppm * 1e-6 * frame * apart_frames + abs(offset))) + 1
    lags = np.arange(-reach, reach + 1)
    lag = int(lags[np.argmax(c[lags % frame])])
    spread = mad_spread(c, centre=0.0)  # zero-mean frames: the correlation sums to zero
    if spread <= 0 or c[lag % frame] / spread < min_z:
        return None
    return (lag + parabolic_peak(c, lag % frame) - offset) / (apart_frames * frame) * 1e6
