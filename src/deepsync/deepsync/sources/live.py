"""A live receiver's byte stream as envelope chunks: read in a background thread, never blocking
the consumer (a ROS executor), with every loss said as a health event.

**Threads and the queue.** A reader thread connects, reads bytes and queues whole samples; the
consumer (:meth:`LiveStream.next`, or :meth:`LiveSource.chunks`) decodes them into envelope codes
under the recordings' rule (:mod:`deepsync.sources.envelope`) and cuts one chunk per LTE frame.
The queue holds at most ``buffer`` seconds of samples. When it is full (the consumer fell
behind) the newest samples are dropped, counted, and reported as one ``GAP`` event per run of
drops; the stream's sample count goes on past them, so the sync stage sees the jump too.
A read that ends inside a sample keeps those bytes for the next read.

**Stamps.** Samples are stamped on the receiver's clock: sample ``i`` is at
``anchor + i / rate``. The host clock gives only the anchor: the host time at which the first
bytes arrived, less the duration of the samples they held (the time of sample 0 as well as the
host can tell; the link's latency is in it). So the stamps advance exactly with the receiver's
sample clock (its ppm error and all, which the sync stage measures), not with the host's.
After a reconnection, the count resumes where the host clock says the receiver is (the
samples of the outage are a gap); it never goes back.

**Health.** ``SOURCE_STALLED``: no bytes for ``stall`` seconds (once per stall); without
``reconnect`` the source keeps waiting, with it the connection is dropped and made again.
``SOURCE_CLOSED``: the peer closed the stream, the link failed, or a connection could not be
made; with ``reconnect`` the source tries again after 0.5 s, 1 s, 2 s, ... (at most 30 s; back to
0.5 s once a connection delivers), without it the stream ends cleanly. A receiver that says it
dropped samples itself (a SoapySDR overflow) is a ``GAP``, the host clock placing what follows.
A float sample that is NaN or inf drops its chunk with a ``NOT_FINITE`` event. Nothing here
raises on a bad stream.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from deepsync.frontend.config import FrontendConfig
from deepsync.types import EnvelopeChunk, Health, HealthKind
from .base import frame_samples, stamp_at, stream_frontend
from .connections import Connection, SamplesLost
from .envelope import NonFiniteSample, check_scale, envelope_codes, full_scale
from .formats import SampleFormat

READ_BYTES = 1 << 16  # bytes per read: 17 ms of cu8 at 1.92 MS/s
POLL_S = 0.05  # how often a waiting thread looks whether it was asked to stop
BACKOFF_S = (0.5, 30.0)  # first and longest wait before a reconnection


@dataclass(frozen=True)
class LiveOptions:
    """How a live stream is read (options of its address: ``?reconnect=1&stall=5&buffer=2``).

    ``reconnect``: after a close, a failed link or a stall, connect again (exponential backoff);
    ``stall_s``: seconds without a byte that make a stall; ``buffer_s``: seconds of samples the
    queue between the reader thread and the consumer holds."""

    reconnect: bool = False
    stall_s: float = 2.0
    buffer_s: float = 2.0

    def __post_init__(self) -> None:
        for name in ("stall_s", "buffer_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0 and value < float("inf")):
                raise ValueError(f"{name} must be a finite number of seconds > 0, got {value!r}")


class _SampleQueue:
    """Blocks of whole samples ``(first index, bytes, samples)`` from the reader thread to the
    consumer, at most ``capacity`` samples queued; ``put`` refuses (never waits) when full."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._blocks: deque[tuple[int, bytes, int]] = deque()
        self._queued = 0
        self._closed = False
        self._ready = threading.Condition()

    def put(self, index: int, data: bytes, samples: int) -> bool:
        with self._ready:
            if self._queued + samples > self.capacity:
                return False
            self._blocks.append((index, data, samples))
            self._queued += samples
            self._ready.notify()
            return True

    def close(self) -> None:
        with self._ready:
            self._closed = True
            self._ready.notify()

    def get(self, timeout: float) -> tuple[int, bytes, int] | None:
        """The oldest block; None when none came within ``timeout`` (or the queue is closed and empty)."""
        with self._ready:
            if not self._blocks and not self._closed and timeout > 0:
                self._ready.wait(timeout)
            if not self._blocks:
                return None
            block = self._blocks.popleft()
            self._queued -= block[2]
            return block

    @property
    def finished(self) -> bool:
        with self._ready:
            return self._closed and not self._blocks


class LiveSource:
    """A receiver's live stream of samples in a :class:`SampleFormat`, from whatever ``connect``
    opens (a socket, a pipe, a serial port, an rtl_tcp server, an SDR driver).

    ``connect()`` makes a new :class:`~deepsync.sources.connections.Connection` (raising OSError
    or ValueError when it cannot); it is called in the reader thread, once per (re)connection.
    ``scale`` defaults to the format's full scale (:func:`~deepsync.sources.envelope.full_scale`):
    a stream has no recording to take a peak from. ``center_hz``: the tuning, when the source
    sets it. Health events gather in the source until :meth:`take_events`.
    """

    def __init__(self, name: str, connect: Callable[[], Connection], sample_format: SampleFormat | str,
                 sample_rate: float, options: LiveOptions | None = None, *, scale: float | None = None,
                 center_hz: float | None = None, clock: Callable[[], int] = time.time_ns) -> None:
        """``clock``: the host clock (ns since the epoch) the first sample's stamp is taken from."""
        self.name = name
        self.connect = connect
        try:
            self.sample_format = SampleFormat.parse(sample_format)
            given = check_scale(scale)
        except ValueError as error:
            raise ValueError(f"{name}: {error}") from None
        self.sample_rate = float(sample_rate)
        self.options = options or LiveOptions()
        self.scale = full_scale(self.sample_format) if given is None else given
        self.center_hz = center_hz
        self.frontend: FrontendConfig = stream_frontend(self.sample_format, self.sample_rate, name)
        self.clock = clock
        self.dropped_samples = 0
        self.connections = 0
        self._events: deque[Health] = deque()

    @property
    def description(self) -> str:
        fmt = self.sample_format
        what = "I/Q, envelope |x - zero|^2" if fmt.is_complex else "envelope"
        centre = "" if self.center_hz is None else f" at {self.center_hz / 1e6:g} MHz"
        again = "reconnects" if self.options.reconnect else "ends when it closes"
        return (f"live stream {self.name}: {fmt.value} {what} at {self.sample_rate / 1e6:g} MS/s{centre}, "
                f"scale {self.scale:.6g} per code; stall after {self.options.stall_s:g} s, "
                f"{self.options.buffer_s:g} s buffer, {again}")

    def report(self, kind: HealthKind, message: str, index: int | None = None) -> None:
        """A health event (thread-safe: deque appends are atomic)."""
        self._events.append(Health(kind, f"{self.name}: {message}", index))

    def take_events(self) -> list[Health]:
        """The health events since the last call, oldest first."""
        events = []
        while self._events:
            events.append(self._events.popleft())
        return events

    def open_stream(self) -> LiveStream:
        """Start reading (a reader thread connects); close the stream to stop."""
        return LiveStream(self)

    def chunks(self) -> Iterator[EnvelopeChunk]:
        """The stream, one chunk per LTE frame, until it ends (blocking: for the CLI; a node polls
        :meth:`open_stream`'s ``next(0)``). Each call connects afresh."""
        stream = self.open_stream()
        try:
            while True:
                chunk = stream.next(POLL_S * 10)
                if chunk is not None:
                    yield chunk
                elif stream.ended:
                    return
        finally:
            stream.close()


class _Reader(threading.Thread):
    """Connects, reads and queues whole samples until stopped or the stream ends for good."""

    def __init__(self, source: LiveSource, queue: _SampleQueue) -> None:
        super().__init__(name=f"deepsync live source {source.name}", daemon=True)
        self.source = source
        self.queue = queue
        self.stop = threading.Event()
        self.anchor_ns: int | None = None  # host time of sample 0
        self.index = 0  # stream index of the next sample
        self._dropped = 0  # samples dropped in the current run of a full queue
        self._lost_at: int | None = None

    def run(self) -> None:
        try:
            self._run()
        finally:
            self._said_drops()
            self.queue.close()

    def _run(self) -> None:
        source, options = self.source, self.source.options
        wait = BACKOFF_S[0]
        while not self.stop.is_set():
            try:
                connection = source.connect()
            except (OSError, ValueError, ImportError) as error:  # ImportError: an optional driver's bindings
                why = f"cannot connect ({error})"
            else:
                source.connections += 1
                try:
                    delivered, why = self._pump(connection)
                except OSError as error:
                    delivered, why = True, f"the link failed ({error})"
                finally:
                    connection.close()
                if delivered:
                    wait = BACKOFF_S[0]
            if self.stop.is_set():
                return
            if not options.reconnect:
                source.report(HealthKind.SOURCE_CLOSED, f"{why} after {self.index} samples: end of stream", self.index)
                return
            source.report(HealthKind.SOURCE_CLOSED, f"{why} after {self.index} samples; reconnecting in {wait:g} s",
                          self.index)
            if self.stop.wait(wait):
                return
            wait = min(2 * wait, BACKOFF_S[1])

    def _pump(self, connection: Connection) -> tuple[bool, str]:
        """Read until the stream ends, fails or (with reconnect) stalls: (any sample arrived, why)."""
        source = self.source
        size = source.sample_format.bytes_per_sample
        stall_s = source.options.stall_s
        partial = b""
        delivered = False
        resync = True  # the next samples are placed by the host clock (a new connection, a loss)
        last_bytes = time.monotonic()
        stalled = False
        while not self.stop.is_set():
            try:
                data = connection.read(READ_BYTES, POLL_S)
            except SamplesLost as error:
                source.report(HealthKind.GAP, f"{error} after sample {self.index}", self.index)
                partial, resync = b"", True
                continue
            if data is None:
                quiet = time.monotonic() - last_bytes
                if quiet >= stall_s and not stalled:
                    stalled = True
                    source.report(HealthKind.SOURCE_STALLED, f"no bytes for {quiet:.1f} s after sample {self.index}",
                                  self.index)
                    if source.options.reconnect:
                        return delivered, "stalled"
                continue
            if not data:
                lost = f" ({len(partial)} bytes of a last, partial sample dropped)" if partial else ""
                return delivered, f"closed by {connection.description}{lost}"
            last_bytes = time.monotonic()
            stalled = False
            data = partial + data if partial else data
            whole = len(data) - len(data) % size
            partial = data[whole:]
            if whole:
                self._queue(data[:whole] if partial else data, whole // size, resync)
                delivered, resync = True, False
        return delivered, "stopped"

    def _queue(self, data: bytes, samples: int, resync: bool) -> None:
        rate = self.source.sample_rate
        now = self.source.clock()
        duration_ns = round(samples * 1e9 / rate)
        if self.anchor_ns is None:
            self.anchor_ns = now - duration_ns
        elif resync:  # resume where the receiver's clock is now: the outage is a gap
            self.index = max(self.index, round((now - duration_ns - self.anchor_ns) * rate / 1e9))
        if self.queue.put(self.index, data, samples):
            self._said_drops()
        else:
            if not self._dropped:
                self._lost_at = self.index
            self._dropped += samples
            self.source.dropped_samples += samples
        self.index += samples

    def _said_drops(self) -> None:
        if self._dropped:
            self.source.report(HealthKind.GAP, f"{self._dropped} samples dropped from sample {self._lost_at}: the "
                               f"consumer fell behind and the {self.source.options.buffer_s:g} s buffer was full",
                               self._lost_at)
            self._dropped = 0


class LiveStream:
    """One reading of a :class:`LiveSource`: ``next(timeout)`` returns the next chunk, or None
    when none is ready within ``timeout`` seconds (0: never waits) or the stream has ``ended``."""

    def __init__(self, source: LiveSource) -> None:
        self.source = source
        capacity = max(1, round(source.options.buffer_s * source.sample_rate))
        self._queue = _SampleQueue(capacity)
        self._reader = _Reader(source, self._queue)
        self._frame = frame_samples(source.sample_rate)
        self._size = source.sample_format.bytes_per_sample
        self._pending = bytearray()  # whole samples not yet in a chunk
        self._pending_index = 0
        self._ready: deque[EnvelopeChunk] = deque()
        self.ended = False
        self._reader.start()

    def next(self, timeout: float = 0.0) -> EnvelopeChunk | None:
        deadline = time.monotonic() + timeout
        while not self._ready and not self.ended:
            block = self._queue.get(max(0.0, deadline - time.monotonic()))
            if block is not None:
                self._take(*block)
            elif self._queue.finished:
                self._cut(len(self._pending) // self._size)
                self.ended = True
            elif time.monotonic() >= deadline:
                break
        return self._ready.popleft() if self._ready else None

    def close(self) -> None:
        """Stop the reader thread (it closes its connection) and wait for it."""
        self._reader.stop.set()
        self._reader.join()
        self.ended = True

    def _take(self, index: int, data: bytes, samples: int) -> None:
        held = len(self._pending) // self._size
        if held and index != self._pending_index + held:  # samples were lost between: no chunk across
            self._cut(held)
        if not self._pending:
            self._pending_index = index
        self._pending += data
        while len(self._pending) // self._size >= self._frame:
            self._cut(self._frame)

    def _cut(self, samples: int) -> None:
        """The first ``samples`` pending samples as a chunk (dropped with an event if not finite)."""
        if samples <= 0:
            return
        nbytes = samples * self._size
        values = np.frombuffer(bytes(self._pending[:nbytes]), dtype=self.source.sample_format.component_dtype)
        index = self._pending_index
        del self._pending[:nbytes]
        self._pending_index += samples
        source = self.source
        try:
            codes = envelope_codes(values, source.sample_format, source.scale)
        except NonFiniteSample as error:
            source.report(HealthKind.NOT_FINITE, f"sample {index + error.index} is not finite ({error.value}): "
                                                 f"its chunk of {samples} samples is dropped", index + error.index)
            return
        anchor = self._reader.anchor_ns or 0
        self._ready.append(EnvelopeChunk(stamp_ns=stamp_at(anchor, index, source.sample_rate),
                                         sample_rate=source.sample_rate, first_sample_index=index, adc_bits=16,
                                         volts_per_code=source.scale, samples=codes))
