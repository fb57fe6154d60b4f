"""deepsync_ros.playback: a source played as a stream, against a steady clock the test drives
(the bundled campus bag, 300 chunks of 10 ms)."""

from __future__ import annotations

from pathlib import Path

import pytest

from deepsync.sources import BagSource
from deepsync.types import EnvelopeChunk, Severity
from deepsync_ros.playback import MAX_LAG_S, Playback, PlaybackConfig, chunk_end_ns

REPO = Path(__file__).resolve().parents[1]
CAMPUS_BAG = REPO / "bags" / "campus"


@pytest.fixture(scope="module")
def campus_chunks() -> list[EnvelopeChunk]:
    return list(BagSource(CAMPUS_BAG).chunks())


def values(report) -> dict[str, str]:
    return dict(report.values)


def play(playback: Playback, source_speed: float) -> int:
    """Publish each chunk when it is both made and due, from a source that makes
    ``source_speed`` seconds of signal per steady second; the number of chunks published."""
    start_ns = None
    while (chunk := playback.next_chunk()) is not None:
        start_ns = chunk.stamp_ns if start_ns is None else start_ns
        made_s = (chunk_end_ns(chunk) - start_ns) * 1e-9 / source_speed
        playback.mark_published(chunk, made_s + max(0.0, playback.due_in(chunk, made_s)))
    return playback.published


def test_a_source_at_half_real_time_cannot_keep_up() -> None:
    playback = Playback(BagSource(CAMPUS_BAG), PlaybackConfig(realtime=True), max_lag_s=MAX_LAG_S)
    chunks = [playback.next_chunk() for _ in range(120)]  # 1.2 s of signal, made in 2.4 s
    for chunk in chunks:
        now = 2 * (chunk_end_ns(chunk) - chunks[0].stamp_ns) * 1e-9
        assert playback.due_in(chunk, now) <= 0  # overdue as soon as it is made
        playback.mark_published(chunk, now)
    report = playback.report()
    assert playback.behind
    assert report.level is Severity.WARN
    assert report.message.startswith("cannot keep up with real time")
    assert values(report)["real-time factor"] == "0.50"
    assert float(values(report)["lag (s)"]) > MAX_LAG_S


def test_a_source_that_keeps_up_is_paced_at_real_time() -> None:
    playback = Playback(BagSource(CAMPUS_BAG), PlaybackConfig(realtime=True, rate=2.0))
    published = play(playback, source_speed=10.0)
    report = playback.report()
    assert published == 300 and playback.ended
    assert report.level is Severity.OK and report.message.startswith("end of source: 300 chunks")
    assert values(report)["real-time factor"] == "2.00"  # paced by the stamps, at the rate asked
    assert playback.lag_s == 0.0


def test_a_loop_is_one_continuous_stream(campus_chunks: list[EnvelopeChunk]) -> None:
    playback = Playback(BagSource(CAMPUS_BAG), PlaybackConfig(loop=True))
    stream = [playback.next_chunk() for _ in range(2 * len(campus_chunks) + 1)]
    assert playback.loops == 2 and not playback.ended
    for before, after in zip(stream, stream[1:]):
        assert after.first_sample_index == before.end_sample_index
        assert after.stamp_ns == chunk_end_ns(before)
    second = stream[len(campus_chunks):]
    assert all((a.samples == b.samples).all() for a, b in zip(second, campus_chunks))


def test_without_a_loop_the_source_ends() -> None:
    playback = Playback(BagSource(CAMPUS_BAG), PlaybackConfig(realtime=False))
    assert sum(1 for _ in iter(playback.next_chunk, None)) == 300
    assert playback.ended and playback.next_chunk() is None


def test_a_rate_must_be_positive() -> None:
    with pytest.raises(ValueError, match="rate must be a positive number"):
        PlaybackConfig(rate=0.0)
