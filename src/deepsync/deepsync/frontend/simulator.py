"""The envelope-detector receiver end to end: emitters + channel in, ADC chunks out.

Chain: per-cell OFDM frames -> propagation paths -> clusters of carriers summed in complex
baseband -> |.|^2 (square-law diode: every in-band intermodulation product between cells and
carriers, nothing else) -> analog video low-pass -> detector and RF noise -> sampling at the
receiver clock's instants -> AC coupling, gain -> ADC noise, rounding, clipping -> int16.

Approximations, and why they hold:

* Ideal square law v = R |x|^2: a zero-bias Schottky detector is square-law below about
  -20 dBm at the diode; above that it turns linear. ``SimulationStats.diode_power_dbm``
  reports the level there so a scenario that leaves the square-law region is visible.
* The detector is memoryless before the video filter, and the diode's own bandwidth
  (GHz) passes everything, so only the video filter shapes the envelope.
* Other approximations are documented where they are made: ``render`` (channel, frame-wise
  delays), ``square_law`` (RF noise added analytically, block-wise noise), ``adc`` (AC
  coupling applied after sampling, exact at 50 Hz vs 1.92 MHz).

The analog part is a pure function of the sample range, so long recordings can be cut into
chunks that run in parallel processes and still give bit-identical codes. The worker processes
never outlive the stream: an interrupt (Ctrl-C, SIGTERM) or any error terminates them at once,
and they die with their parent even if it is killed outright.
"""

from __future__ import annotations

import ctypes
import math
import multiprocessing
import multiprocessing.connection
import signal
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from deepsync.frontend.adc import AdcStage, ReceiverClock, cubic_sample
from deepsync.frontend.channel import ChannelProvider, Emitter
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.square_law import CHUNK_TICKS, Detector, DetectorNoise
from deepsync.lte.numerology import BASE_RATE_HZ
from deepsync.numeric import one_blas_thread
from deepsync.types import FRAME_SECONDS, EnvelopeChunk

WORK_UNIT_SECONDS = 1.0
MAX_UNIT_SAMPLES = 2**21  # ADC samples per work unit at most: bounds a worker's memory at any rate
WORKER_MEMORY_BYTES = 256 * 2**20  # measured peak of one worker on such a unit: 180-205 MB, 1.92-15.36 MHz


@dataclass
class SimulationStats:
    samples: int = 0
    clipped: int = 0
    gain_db: float = float("nan")
    diode_power_dbm: float = float("nan")
    clusters: list[str] = field(default_factory=list)


class EnvelopeSimulator:
    """Simulates the ADC stream of an envelope-detector receiver."""

    def __init__(
        self,
        emitters: list[Emitter],
        channel: ChannelProvider,
        config: FrontendConfig,
        seed: int,
        epoch_ns: int = 0,
    ) -> None:
        if not emitters:
            raise ValueError("nothing to simulate: no emitters")
        self.emitters = list(emitters)
        self.channel = channel
        self.config = config
        self.seed = int(seed)
        self.epoch_ns = int(epoch_ns)
        self.clock = ReceiverClock(config.clock_offset_ppm, config.clock_drift_ppm_per_s)
        self.noise = DetectorNoise(config, self.seed)
        self._detector: Detector | None = None
        self._video: dict[int, np.ndarray] = {}  # video chunks at hand, by index
        self._last_block: tuple[int, np.ndarray] | None = None

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.update(_detector=None, _video={}, _last_block=None)
        return state

    @property
    def detector(self) -> Detector:
        if self._detector is None:
            self._detector = Detector(self.emitters, self.channel, self.config, self.seed)
        return self._detector

    def sample_index(self, true_time_s: np.ndarray | float) -> np.ndarray | float:
        """Fractional ADC sample index at which a true time falls (receiver clock applied)."""
        return self.clock.receiver_time(true_time_s) * self.config.adc_rate_hz

    def stamp_ns(self, sample_index: int) -> int:
        """Receiver-clock time of ADC sample ``sample_index`` (what the header stamp carries)."""
        return self.epoch_ns + round(sample_index * 1e9 / self.config.adc_rate_hz)

    # -- analog part: pure in (n0, n1) -------------------------------------------------------

    def analog(self, n0: int, n1: int) -> np.ndarray:
        """Diode-output volts at ADC samples n0..n1-1 (before AC coupling and gain), noise
        included; computed in whole 10 ms blocks of samples, each a pure function of its index."""
        per_block = self.noise.block
        first, last = n0 // per_block, -(-n1 // per_block)
        # The matrix products here are small; BLAS threads would spin against the worker
        # processes (which are the parallelism) and cost more than they save.
        with one_blas_thread():
            volts = np.concatenate([self._block(b) for b in range(first, last)])
        return volts[n0 - first * per_block : n1 - first * per_block]

    def _block(self, block: int) -> np.ndarray:
        """Volts at ADC samples [block, block + 1) x ``noise.block``."""
        if self._last_block is not None and self._last_block[0] == block:
            return self._last_block[1]
        signal = self._signal(block)
        diode_power = float(np.mean(signal)) / self.config.detector_responsivity_v_per_w  # H(0) = 1
        volts = signal + self.noise.samples(block, diode_power)
        self._last_block = (block, volts)
        return volts

    def _signal(self, block: int) -> np.ndarray:
        """The detector's noiseless output at the block's ADC samples."""
        detector, per_block = self.detector, self.noise.block
        per_tick = self.config.adc_rate_hz / BASE_RATE_HZ
        if self.clock.nominal and detector.aligned(per_tick) and per_block == round(CHUNK_TICKS * per_tick):
            return detector.output(block, per_tick)  # the ADC samples the tick grid: no interpolation
        positions = self.clock.true_time(np.arange(block * per_block, (block + 1) * per_block)
                                         / self.config.adc_rate_hz) * detector.video_rate
        per_chunk = CHUNK_TICKS * detector.video_multiplier
        needed = int(np.floor(positions[0])) - 1, int(np.floor(positions[-1])) + 2  # cubic_sample's reach
        chunks = range(needed[0] // per_chunk, needed[1] // per_chunk + 1)
        video = np.concatenate([self._video_chunk(c) for c in chunks])
        return cubic_sample(video, chunks[0] * per_chunk, positions)

    def _video_chunk(self, chunk: int) -> np.ndarray:
        if chunk not in self._video:
            if len(self._video) > 2:
                self._video.pop(min(self._video))
            self._video[chunk] = self.detector.output(chunk, self.detector.video_multiplier)
        return self._video[chunk]

    # -- whole stream ---------------------------------------------------------------------

    def stream(
        self,
        seconds: float,
        chunk_samples: int | None = None,
        workers: int = 1,
        stats: SimulationStats | None = None,
    ) -> Iterator[EnvelopeChunk]:
        """ADC chunks covering ``seconds`` of receiver time; ``workers`` > 1 runs in processes."""
        if not (math.isfinite(seconds) and seconds > 0):
            raise ValueError(f"seconds must be a positive number, got {seconds!r}")
        rate = self.config.adc_rate_hz
        total = int(round(seconds * rate))
        chunk = chunk_samples or max(1, round(rate * FRAME_SECONDS))
        unit = max(chunk, min(round(WORK_UNIT_SECONDS * rate), MAX_UNIT_SAMPLES) // chunk * chunk)
        ranges = [(n, min(n + unit, total)) for n in range(0, total, unit)]
        adc = AdcStage(self.config, self.seed)
        stats = stats if stats is not None else SimulationStats()
        stats.clusters = [
            f"{c.cluster.center_hz / 1e6:.3f} MHz x {c.cluster.sample_rate_hz / 1e6:.2f} MS/s "
            f"({len(c.cluster.emitter_indices)} cells)"
            for c in self.detector.clusters
        ]
        for (n0, _), volts in zip(ranges, self._analog_units(ranges, workers)):
            coupled = adc.couple(volts)
            if adc.gain is None:
                adc.set_gain_from(coupled[: adc.settling])
                stats.gain_db = adc.gain_db
            codes = adc.quantize(n0, coupled)
            if n0 == 0:  # the mean detector voltage is R times the power at the diode
                power = float(np.mean(volts[: adc.settling])) / self.config.detector_responsivity_v_per_w
                stats.diode_power_dbm = 10 * math.log10(power * 1e3) if power > 0 else float("-inf")
            for offset in range(0, len(codes), chunk):
                first = n0 + offset
                yield EnvelopeChunk(
                    stamp_ns=self.stamp_ns(first),
                    sample_rate=rate,
                    first_sample_index=first,
                    adc_bits=self.config.adc_bits,
                    volts_per_code=self.config.volts_per_code,
                    samples=codes[offset : offset + chunk],
                )
            stats.samples = ranges[-1][1] if n0 == ranges[-1][0] else n0 + len(codes)
            stats.clipped = adc.clipped
        stats.gain_db = adc.gain_db

    def _analog_units(self, ranges: list[tuple[int, int]], workers: int) -> Iterator[np.ndarray]:
        if workers <= 1 or len(ranges) == 1:
            for n0, n1 in ranges:
                yield self.analog(n0, n1)
            return
        workers = min(workers, len(ranges))  # more processes than work units would only idle
        check_memory(workers)
        team = _Workers(self, workers)
        try:
            yield from team.map(ranges)
        finally:  # done, interrupted or failed: no worker is left computing
            team.stop()


class _Workers:
    """Worker processes, each with its own pipe, fed round-robin and read in order.

    Not a ``multiprocessing.Pool``: its workers share one task queue behind a lock that an idle
    worker holds while it waits, and ``Pool.terminate`` takes that lock first, so an interrupt at
    the wrong moment hung the parent for good. A pipe per worker shares nothing.
    """

    AHEAD = 2  # units queued per worker: the next one is there when a result goes out

    def __init__(self, simulator: EnvelopeSimulator, count: int) -> None:
        context = multiprocessing.get_context()
        self.processes, self.pipes = [], []
        for _ in range(count):
            parent, child = context.Pipe()
            process = context.Process(target=_worker_loop, args=(simulator, child), daemon=True)
            process.start()
            child.close()
            self.processes.append(process)
            self.pipes.append(parent)

    def map(self, ranges: list[tuple[int, int]]) -> Iterator[np.ndarray]:
        """Each unit's analog samples, in order."""
        count = len(self.processes)
        queued = min(len(ranges), count * self.AHEAD)
        for k in range(queued):
            self.pipes[k % count].send(ranges[k])
        for k in range(len(ranges)):
            pipe = self.pipes[k % count]
            try:
                ok, value = pipe.recv()
            except EOFError:
                raise RuntimeError(f"simulation worker {k % count} died (out of memory?)") from None
            if not ok:
                raise value
            if queued < len(ranges):
                self.pipes[queued % count].send(ranges[queued])
                queued += 1
            yield value

    def stop(self) -> None:
        for process in self.processes:
            process.terminate()
        for process in self.processes:
            process.join(timeout=5)
            if process.is_alive():
                process.kill()
                process.join()
        for pipe in self.pipes:
            pipe.close()


def available_memory_bytes() -> int | None:
    """Memory the system can still hand out without swapping (Linux ``MemAvailable``), or None."""
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def check_memory(workers: int) -> None:
    """ValueError before ``workers`` processes are started that the machine cannot hold."""
    available = available_memory_bytes()
    if available is not None and workers * WORKER_MEMORY_BYTES > available:
        fits = max(1, available // WORKER_MEMORY_BYTES)
        raise ValueError(
            f"{workers} worker processes need about {workers * WORKER_MEMORY_BYTES / 2**30:.1f} GiB "
            f"({WORKER_MEMORY_BYTES // 2**20} MiB each) and {available / 2**30:.1f} GiB is available: "
            f"use at most {fits}"
        )


_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def _detach_worker() -> None:
    # The parent handles Ctrl-C (it reaches the whole process group) and SIGTERM, and then
    # terminates the workers; a worker must neither print its own KeyboardInterrupt nor outlive it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if sys.platform.startswith("linux"):  # die with the parent, however it ends (even SIGKILL)
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


def _worker_loop(simulator: EnvelopeSimulator, pipe: multiprocessing.connection.Connection) -> None:
    """Compute the units the parent sends until it closes the pipe; a failure goes back to it."""
    _detach_worker()
    while True:
        try:
            span = pipe.recv()
        except EOFError:
            return
        try:
            pipe.send((True, simulator.analog(*span)))
        except Exception as error:  # the parent raises it
            pipe.send((False, error))
