"""A source played as a stream, for the nodes that play one (``envelope_adc``, the pipeline).

The recording is played on, looped if asked, paced by the chunks' own stamps on a steady clock,
and watched: whether the source keeps up with that pace (the live simulator does not on one core).
A live receiver (:class:`~deepsync.sources.LiveSource`) is polled without waiting, published as it
arrives (never paced or looped), and its health events (stalled, closed, dropped samples) are
counted. What it says goes to ``/diagnostics`` as a :class:`~deepsync_ros.health.Report`; the
rclpy timer that drives it is ``node_base``'s player. No ROS is imported here.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter, deque
from collections.abc import Iterator
from dataclasses import dataclass

from deepsync.sources import LiveSource, Source
from deepsync.sources.base import stamp_at
from deepsync.sources.live import LiveStream
from deepsync.types import EnvelopeChunk, Health, HealthKind, Severity

from .health import Report

# Steady-clock seconds a paced chunk may be published late before the source counts as not
# keeping up: far above a timer's jitter (ms), well below what a consumer notices (a stack, 0.1 s,
# takes several).
MAX_LAG_S = 0.5
# Wall-clock span over which the real-time factor is measured.
RATE_WINDOW_S = 5.0


def chunk_end_ns(chunk: EnvelopeChunk) -> int:
    """Receiver time just after a chunk's last sample: when the ADC has finished it."""
    return stamp_at(chunk.stamp_ns, len(chunk.samples), chunk.sample_rate)


@dataclass(frozen=True)
class PlaybackConfig:
    """``realtime``: pace the chunks by their stamps (else as fast as they come); ``rate``: the
    speed of that pace; ``loop``: at the end, start over as one continuous stream."""

    realtime: bool = True
    rate: float = 1.0
    loop: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.rate, bool) or not isinstance(self.rate, (int, float)) or not (
                math.isfinite(self.rate) and self.rate > 0):
            raise ValueError(f"rate must be a positive number (1 = real time), got {self.rate!r}")


class Playback:
    """A source played as a stream: looped, paced, and watched (see the module docstring).

    Steady-clock times (``now_s``, e.g. ``time.monotonic()``) are passed in, never read here, so
    the pacing follows no ROS clock (a player that publishes ``/clock`` cannot wait on it).
    A loop keeps ``first_sample_index`` and the stamps going on by the recording's length, so a
    consumer sees one stream; what the recording's end joins to its start is its business.
    """

    def __init__(self, source: Source, config: PlaybackConfig | None = None, *, max_lag_s: float = MAX_LAG_S,
                 window_s: float = RATE_WINDOW_S) -> None:
        self.source = source
        self.config = config or PlaybackConfig()
        self.max_lag_s = max_lag_s
        self.window_s = window_s
        self.published = 0
        self.unpublishable = 0
        self.last_unpublishable: str | None = None
        self.loops = 0
        self.ended = False
        self.error: str | None = None
        self.lag_s = 0.0
        self._chunks: Iterator[EnvelopeChunk] | None = None
        self._pass: tuple[EnvelopeChunk, EnvelopeChunk] | None = None  # first and last chunk of this pass
        self._shift = (0, 0)  # (samples, ns) added to this pass
        self._anchor: tuple[float, int] | None = None  # (steady s, stamp ns) the pace is counted from
        self._history: deque[tuple[float, int]] = deque()  # (steady s, stream ns) of recent chunks
        self._stream: LiveStream | None = None
        self.source_events: Counter[HealthKind] = Counter()
        self.last_source_event: Health | None = None
        self.new_source_events: list[Health] = []  # for the node's log; it empties the list
        self._published_at_event = 0

    def reconfigure(self, config: PlaybackConfig) -> None:
        """New settings at runtime; the pace starts again from the next chunk."""
        self.config = config
        self._anchor = None
        self._history.clear()

    @property
    def live(self) -> bool:
        """The source is a live receiver: polled, never paced nor looped."""
        return isinstance(self.source, LiveSource)

    def next_chunk(self) -> EnvelopeChunk | None:
        """The next chunk of the stream; None at its end (``ended``; ``error`` if the source failed),
        or, from a live source, when none has arrived yet (never waits for one)."""
        if self.live:
            return self._next_live()
        while not self.ended:
            if self._chunks is None:
                self._chunks = iter(self.source.chunks())
            try:
                chunk = next(self._chunks, None)
            except (ValueError, OSError) as error:  # a recording unreadable beyond some point
                self.error = f"{type(error).__name__}: {error}"
                self.ended = True
                return None
            if chunk is not None:
                self._pass = (chunk if self._pass is None else self._pass[0], chunk)
                samples, ns = self._shift
                if samples or ns:
                    chunk = dataclasses.replace(chunk, first_sample_index=chunk.first_sample_index + samples,
                                                stamp_ns=chunk.stamp_ns + ns)
                return chunk
            if not self.config.loop or self._pass is None:
                self.ended = True
                return None
            first, last = self._pass
            samples, ns = self._shift
            self._shift = (samples + last.end_sample_index - first.first_sample_index,
                           ns + chunk_end_ns(last) - first.stamp_ns)
            self._chunks = None
            self._pass = None
            self.loops += 1
        return None

    def _next_live(self) -> EnvelopeChunk | None:
        if self.ended:
            return None
        if self._stream is None:
            self._stream = self.source.open_stream()  # type: ignore[attr-defined]
        chunk = self._stream.next(0.0)
        for event in self.source.take_events():  # type: ignore[attr-defined]
            self.source_events[event.kind] += 1
            self.last_source_event = event
            self.new_source_events.append(event)
            self._published_at_event = self.published
        if chunk is None and self._stream.ended:
            self.ended = True
        return chunk

    def close(self) -> None:
        """Stop a live source's reading (its thread and connection)."""
        if self._stream is not None:
            self._stream.close()

    def due_in(self, chunk: EnvelopeChunk, now_s: float) -> float:
        """Seconds until ``chunk`` is due (<= 0: publish now); the first chunk is due at once,
        a live source's chunks as they arrive."""
        if not self.config.realtime or self.live:
            return 0.0
        if self._anchor is None:
            self._anchor = (now_s, chunk.stamp_ns)
        start_s, start_ns = self._anchor
        return start_s + (chunk.stamp_ns - start_ns) * 1e-9 / self.config.rate - now_s

    def mark_published(self, chunk: EnvelopeChunk, now_s: float) -> None:
        """``chunk`` went out at ``now_s``."""
        self.published += 1
        self.lag_s = max(0.0, -self.due_in(chunk, now_s))
        self._history.append((now_s, chunk_end_ns(chunk)))
        while self._history and self._history[0][0] < now_s - self.window_s:
            self._history.popleft()

    def mark_unpublishable(self, chunk: EnvelopeChunk, error: Exception) -> None:
        """``chunk`` could not become a message (a stamp beyond what a ROS time holds, ...)."""
        self.unpublishable += 1
        self.last_unpublishable = f"chunk at sample {chunk.first_sample_index}: {error}"

    def realtime_factor(self) -> float | None:
        """Seconds of signal published per steady second over the last ``window_s``."""
        if len(self._history) < 2:
            return None
        (first_s, first_ns), (last_s, last_ns) = self._history[0], self._history[-1]
        return (last_ns - first_ns) * 1e-9 / (last_s - first_s) if last_s > first_s else None

    @property
    def behind(self) -> bool:
        """Chunks fall due faster than the source makes them."""
        return self.config.realtime and not self.live and not self.ended and self.lag_s > self.max_lag_s

    def report(self) -> Report:
        factor = self.realtime_factor()
        values = [
            ("source", self.source.description),
            ("chunks published", str(self.published)),
            ("loops", str(self.loops)),
            ("paced", "no: a live source, published as it arrives" if self.live
             else f"{self.config.realtime} (rate {self.config.rate:g})"),
            ("real-time factor", "n/a" if factor is None else f"{factor:.2f}"),
            ("lag (s)", f"{self.lag_s:.3f}"),
            ("end of source", str(self.ended)),
            ("unpublishable chunks", str(self.unpublishable)),
        ]
        if self.last_unpublishable is not None:
            values.append(("last unpublishable chunk", self.last_unpublishable))
        for kind, count in self.source_events.items():
            values.append((f"source events: {kind.value}", str(count)))
        if self.last_source_event is not None:
            values.append(("last source event", str(self.last_source_event)))
            if self.ended or self.published == self._published_at_event:  # it still holds: nothing came since
                return Report(self.last_source_event.severity, str(self.last_source_event), values)
        if self.error is not None:
            return Report(Severity.ERROR, f"source failed after {self.published} chunks: {self.error}", values)
        if self.behind:
            made = "" if factor is None else f" (it makes {factor:.2f} s of signal per second)"
            return Report(Severity.WARN, f"cannot keep up with real time x {self.config.rate:g}: the source is "
                                         f"{self.lag_s:.1f} s late{made}", values)
        if self.unpublishable:
            return Report(Severity.WARN, f"{self.unpublishable} chunks could not be published", values)
        if self.ended:
            return Report(Severity.OK, f"end of source: {self.published} chunks published", values)
        if not self.published:
            return Report(Severity.OK, "waiting for the first chunk", values)
        speed = "" if factor is None else f" at {factor:.2f} x real time"
        return Report(Severity.OK, f"publishing{speed}", values)
