"""Bad-input matrix: envelope streams, chunks and windows (one file of ``test/test_bad_input_*.py``).

Every row feeds one kind of bad or edge input to the stages and asserts its outcome class:

* ``error``: refused at the door with a ValueError naming the cause (a chunk that cannot exist);
* ``event``: the stream goes on, and a typed :class:`~deepsync.types.Health` says what happened
  (stream events and stack flags, each with the severity a node reports on /diagnostics);
* ``result``: the right answer despite the odd input.

A property-based fuzz (hypothesis) then throws random chunk sequences at the sync stage: it must
never raise, and never complete a stack from data that spans a bad chunk, a gap or a restart.

The other files of the matrix: ``test_bad_input_config.py`` (front end, scenario, tower
database), ``test_bad_input_bags.py`` (bags), ``test_bad_input_cli.py`` (the command line,
signals); recordings are in ``test_sources.py``, live receivers (stalls, closes, drops, partial
samples, bad addresses) in ``test_live_sources.py``. Whatever comes next (fusion, the timing network,
the ROS nodes, bag replay) adds its rows to this matrix, in these files or a new
``test_bad_input_<part>.py`` with the same outcome classes.
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from deepsync.bag import sync_window_array_from_msg, sync_window_array_to_msg
from deepsync.frontend.config import FrontendConfig
from deepsync.pipeline import Pipeline, PipelineConfig
from deepsync.sources import BagSource
from deepsync.sync.stacking import StackConfig
from deepsync.sync.stage import SyncConfig, SyncStage
from deepsync.timing.stage import TimingStage
from deepsync.towers import load_tower_database
from deepsync.types import EnvelopeChunk, HealthKind, Severity, StackWindows, SyncWindow

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "campus"
TOWERS = REPO / "config" / "towers" / "campus.yaml"
RATE = 1.92e6
FRAME = 19200
CAMPUS = [56, 120, 121, 301]


@lru_cache(maxsize=1)
def campus_chunks() -> tuple[EnvelopeChunk, ...]:
    return tuple(BagSource(BAG).chunks())


def campus_pipeline(confirm_stacks: int = 3) -> Pipeline:
    config = PipelineConfig(sync=SyncConfig(confirm_stacks=confirm_stacks))
    return Pipeline(BagSource(BAG).frontend, config, load_tower_database(TOWERS))


def run(pipeline: Pipeline, chunks) -> list:
    return [result for chunk in chunks for result in pipeline.process(chunk)]


def shifted(chunk: EnvelopeChunk, index: int, stamp_ns: int | None = None) -> EnvelopeChunk:
    """The chunk at another stream index (and stamp: on the same timeline unless given)."""
    stamp = chunk.stamp_ns + round((index - chunk.first_sample_index) * 1e9 / RATE) if stamp_ns is None else stamp_ns
    return dataclasses.replace(chunk, first_sample_index=index, stamp_ns=stamp)


def confirmed_at_the_end(results) -> list[int]:
    """The cells confirmed in the last 5 stacks: PCI 301 is at the campus bag's margin (-6 dB,
    missed in a few stacks of the 30), so "found again" is asked of the stream's end, not of one stack."""
    return sorted({pci for result in results[-5:] for pci in result.sync.pcis})


def kinds(results) -> list[HealthKind]:
    return [h.kind for r in results for h in r.health]


# -- chunks that cannot exist: refused at construction ----------------------------------------

GOOD = dict(stamp_ns=0, sample_rate=RATE, first_sample_index=0, adc_bits=12, volts_per_code=1e-3,
            samples=np.zeros(10, dtype=np.int16))


@pytest.mark.parametrize("change, message", [
    (dict(samples=np.array([1.0, np.nan])), r"samples\[1\] is nan"),
    (dict(samples=np.array([np.inf])), r"samples\[0\] is inf"),
    (dict(samples=np.array([1.0, 2.5])), "whole numbers"),
    (dict(samples=np.array([40000])), "beyond int16"),  # cast to int16 it wrapped to -25536
    (dict(samples=np.array([-40000.0])), "beyond int16"),
    (dict(samples=np.zeros((2, 5), dtype=np.int16)), "1-D"),
    (dict(samples=np.array(["1", "2"])), "numbers"),
    (dict(sample_rate=0.0), "sample_rate"),
    (dict(sample_rate=float("nan")), "sample_rate"),
    (dict(adc_bits=0), "adc_bits"),
    (dict(adc_bits=17), "adc_bits"),
    (dict(first_sample_index=-1), "first_sample_index"),
    (dict(volts_per_code=0.0), "volts_per_code"),
    (dict(volts_per_code=float("inf")), "volts_per_code"),
], ids=["nan", "inf", "fraction", "above_int16", "below_int16", "2d", "strings", "rate_0", "rate_nan",
        "bits_0", "bits_17", "negative_index", "volts_0", "volts_inf"])
def test_error_a_chunk_that_cannot_exist_is_refused(change, message):
    with pytest.raises(ValueError, match=message):
        EnvelopeChunk(**{**GOOD, **change})


def test_result_whole_floats_and_wider_ints_within_int16_are_codes():
    for values in (np.array([1.0, -2.0, 2047.0]), np.array([1, -2, 2047], dtype=np.int64)):
        chunk = EnvelopeChunk(**{**GOOD, "samples": values})
        assert chunk.samples.dtype == np.dtype("<i2") and chunk.samples.tolist() == [1, -2, 2047]


# -- streams: events, and the stream goes on ----------------------------------------------------


def test_event_gap_then_detection_again():
    chunks = list(campus_chunks())
    results = run(campus_pipeline(), chunks[:100] + [shifted(c, c.first_sample_index + 777) for c in chunks[100:]])
    assert kinds(results).count(HealthKind.GAP) == 1
    assert confirmed_at_the_end(results) == CAMPUS


def test_event_driver_restart_index_back_to_zero_while_time_goes_on():
    """Today's main dropped every chunk after a reset as 'backwards' until the index passed
    the old maximum: a stall as long as the stream had run."""
    chunks = list(campus_chunks())
    later = chunks[-1].stamp_ns + 10_000_000
    restarted = [shifted(c, c.first_sample_index, later + c.stamp_ns - chunks[0].stamp_ns) for c in chunks[:100]]
    results = run(campus_pipeline(), chunks[:150] + restarted)
    (restart,) = [h for r in results for h in r.health if h.kind is HealthKind.RESTART]
    assert restart.sample_index == 0 and restart.severity is Severity.WARN
    after = [r for r in results if r.sync.events == (restart,) or r.stamp_ns >= later]
    assert len(after) == 10  # every stack of the restarted stream is searched: no stall
    assert confirmed_at_the_end(after) == CAMPUS  # and confirmed again


def test_event_bag_played_in_a_loop_index_and_stamps_back_to_the_start():
    chunks = list(campus_chunks())
    results = run(campus_pipeline(), chunks + chunks[:60])
    assert kinds(results) == [HealthKind.RESTART] and len(results) == 30 + 6
    assert confirmed_at_the_end(results) == CAMPUS


def test_result_stamps_that_drift_from_the_sample_count_are_no_restart():
    """A driver stamping chunks by another clock than the ADC's: 1 % apart (10 ms per second, far
    worse than two crystals) moves the stamps a frame off the sample count within a second; only
    a jump from one chunk to the next means the stream started over."""
    chunks = list(campus_chunks())
    start = chunks[0].stamp_ns
    drifting = [dataclasses.replace(c, stamp_ns=start + round((c.stamp_ns - start) * 1.01)) for c in chunks]
    results = run(campus_pipeline(), drifting)
    assert kinds(results) == [] and len(results) == 30 and confirmed_at_the_end(results) == CAMPUS


def test_event_late_or_repeated_chunk_is_dropped_and_nothing_else_changes():
    chunks = list(campus_chunks())
    results = run(campus_pipeline(), chunks[:55] + [chunks[52]] + chunks[55:])
    assert kinds(results) == [HealthKind.BACKWARDS] and len(results) == 30


@pytest.mark.parametrize("rate", [3.84e6, RATE * (1 + 50e-6)], ids=["another_rate", "50ppm_off"])
def test_event_chunks_labelled_with_another_rate_are_never_stacked(rate):
    """50 ppm off passed silently on main and gave 0 cells."""
    chunks = [dataclasses.replace(c, sample_rate=rate) if 100 <= k < 110 else c
              for k, c in enumerate(campus_chunks())]
    results = run(campus_pipeline(), chunks)
    assert kinds(results) == [HealthKind.RATE_MISMATCH]
    assert all(r.sync.first_sample_index >= 110 * FRAME or r.sync.first_sample_index + 10 * FRAME <= 100 * FRAME
               for r in results)
    assert confirmed_at_the_end(results) == CAMPUS


def test_event_a_wholly_mislabelled_stream_says_so_once():
    chunks = [dataclasses.replace(c, sample_rate=3.84e6) for c in campus_chunks()]
    stage = SyncStage(FrontendConfig())
    results = [r for c in chunks for r in stage.process(c)]
    assert results == [] and [e.kind for e in stage.take_events()] == [HealthKind.RATE_MISMATCH]
    assert stage.take_events() == ()  # taken, said once


def test_event_codes_beyond_the_adc_range_are_corrupt_not_clipped():
    """A flipped byte in a bag chunk garbles thousands of codes: on main the stack was searched
    and flagged 'clipped'."""
    chunks = list(campus_chunks())
    codes = chunks[40].samples.copy()
    codes[5000:15000] = np.random.default_rng(1).integers(-32768, 32767, 10000)
    results = run(campus_pipeline(), chunks[:40] + [dataclasses.replace(chunks[40], samples=codes)] + chunks[41:])
    assert kinds(results) == [HealthKind.CORRUPT]
    assert all(not r.sync.flags for r in results)
    bad = (40 * FRAME + 5000, 40 * FRAME + 15000)
    assert all(r.sync.first_sample_index >= bad[1] or r.sync.first_sample_index + 10 * FRAME <= bad[0] for r in results)
    assert len(results) == 29 and confirmed_at_the_end(results) == CAMPUS


def test_event_not_finite_samples_from_a_float_source():
    stage = SyncStage(FrontendConfig(), SyncConfig(stack=StackConfig(n_frames=2)))
    samples = np.random.default_rng(2).standard_normal(5 * FRAME)
    samples[FRAME + 3] = np.nan
    results = stage.process_samples(samples, 0, RATE)
    assert [e.kind for r in results for e in r.events] == [HealthKind.NOT_FINITE]
    assert [r.first_sample_index for r in results] == [FRAME + 4]


@pytest.mark.parametrize("codes, flag", [
    (np.zeros(2 * FRAME, dtype=np.int16), HealthKind.NO_SIGNAL),  # silent
    (np.full(2 * FRAME, 317, dtype=np.int16), HealthKind.NO_SIGNAL),  # stuck
    (np.full(2 * FRAME, 2047, dtype=np.int16), HealthKind.NO_SIGNAL),  # stuck at the rail
], ids=["silent", "stuck", "stuck_at_rail"])
def test_event_dead_input_is_flagged_and_not_searched(codes, flag):
    stage = SyncStage(FrontendConfig(), SyncConfig(stack=StackConfig(n_frames=2), confirm_stacks=1))
    (result,) = stage.process(EnvelopeChunk(0, RATE, 0, 12, 1e-3, codes))
    assert flag in [f.kind for f in result.flags] and result.cells == () and result.tentative == ()


def test_event_clipping_is_flagged_and_the_stack_still_searched():
    chunks = list(campus_chunks())[:30]
    loud = [dataclasses.replace(c, samples=np.clip(c.samples.astype(int) * 4, -2048, 2047)) for c in chunks]
    results = run(campus_pipeline(confirm_stacks=1), loud)
    assert len(results) == 3 and all([f.kind for f in r.sync.flags] == [HealthKind.CLIPPED] for r in results)
    assert {56, 301} <= set(results[-1].sync.pcis)


def test_result_empty_and_one_sample_chunks():
    chunks = list(campus_chunks())[:30]
    empty = [EnvelopeChunk(c.stamp_ns, RATE, c.first_sample_index, 12, c.volts_per_code, c.samples[:0]) for c in chunks]
    pieces = []
    for c in chunks[:20]:
        pieces += [shifted(dataclasses.replace(c, samples=c.samples[i : i + 1]), c.first_sample_index + i)
                   for i in range(0, len(c.samples), 997)]  # every 997th sample, as a one-sample chunk
    assert run(campus_pipeline(), empty) == []  # nothing to stack, nothing raised
    whole = [shifted(dataclasses.replace(c, samples=c.samples[i : i + 997]), c.first_sample_index + i)
             for c in chunks for i in range(0, len(c.samples), 997)]
    assert [r.sync.pcis for r in run(campus_pipeline(), whole)] == [r.sync.pcis for r in run(campus_pipeline(), chunks)]
    sparse = campus_pipeline()
    assert run(sparse, pieces) == []  # never a whole stack of contiguous samples
    assert {e.kind for e in sparse.sync.take_events()} == {HealthKind.GAP}


def test_event_a_huge_index_jump_is_a_gap():
    chunks = list(campus_chunks())
    results = run(campus_pipeline(), chunks[:50] + [shifted(c, c.first_sample_index + 10**12) for c in chunks[50:]])
    assert kinds(results) == [HealthKind.GAP] and confirmed_at_the_end(results) == CAMPUS


# -- windows for the timing stage ------------------------------------------------------------


@pytest.fixture(scope="module")
def campus_window() -> SyncWindow:
    results = run(campus_pipeline(), campus_chunks()[:40])
    return next(w for w in results[-1].sync.windows if w.cosited_pci is None)


@pytest.mark.parametrize("broken, message", [
    (lambda w: np.ones_like(w), "constant"),
    (lambda w: w[:, :-1], "margin"),
    (lambda w: w[:, 40:-40], "margin"),
    (lambda w: w[:1], "at least 2 frames"),
], ids=["constant", "odd_length", "too_short", "one_frame"])
def test_event_windows_that_cannot_be_timed(campus_window, broken, message):
    stage = TimingStage(BagSource(BAG).frontend)
    result = stage.process([dataclasses.replace(campus_window, windows=broken(campus_window.windows))])
    assert result.cells == () and [e.kind for e in result.events] == [HealthKind.UNTIMEABLE]
    assert message in result.events[0].message


@pytest.mark.parametrize("change, message", [
    (lambda w: dict(pci=504), "pci"),
    (lambda w: dict(cosited_pci=121), "together"),
    (lambda w: dict(cosited_pci=w.pci, site_coefficients=(1.0, 2.0, 3.0, 4.0)), "another PCI"),
    (lambda w: dict(windows=np.zeros((0, 10))), "n_frames"),
], ids=["pci_504", "cosited_without_coefficients", "cosited_with_itself", "no_rows"])
def test_error_a_window_that_cannot_exist(campus_window, change, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(campus_window, **change(campus_window))


def test_error_a_sync_window_message_with_the_wrong_number_of_values(campus_window):
    msg = sync_window_array_to_msg(StackWindows(0, 0, 1.92e6, (campus_window,)))
    msg.cells[0].windows = msg.cells[0].windows[:-1]
    with pytest.raises(ValueError, match="n_frames x window_length"):
        sync_window_array_from_msg(msg)


def test_error_stacks_of_one_frame_cannot_be_timed():
    with pytest.raises(ValueError, match="at least 2 frames"):
        PipelineConfig(sync=SyncConfig(stack=StackConfig(n_frames=1)))


# -- fuzz: random chunk sequences -------------------------------------------------------------

KINDS = ("good",) * 6 + ("gap", "late", "restart", "nan", "corrupt", "wrong_rate", "silent", "clipped")
UNSET = np.nan  # an index whose sample no clean chunk of the current stream carried


def code(stream: int, index: np.ndarray) -> np.ndarray:
    """What a clean chunk of stream (epoch) ``stream`` carries at ``index``: a pattern that names
    both, so a stack holding anything else (another stream, a shifted copy) is caught."""
    return ((index * 7 + stream * 131) % 997 - 498).astype(np.int16)


@st.composite
def streams(draw):
    """A sequence of (kind, length) pieces, mostly clean and long enough to complete stacks
    between the faults; lengths from a sample to a frame and a half."""
    lengths = st.one_of(st.integers(FRAME // 2, 3 * FRAME // 2), st.integers(1, FRAME))
    return draw(st.lists(st.tuples(st.sampled_from(KINDS), lengths), min_size=1, max_size=20))


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(pieces=streams())
def test_fuzz_the_stage_never_raises_and_never_stacks_across_bad_data(pieces):
    """Random gaps, late chunks, restarts, NaN, corrupt codes, wrong rates, silence and clipping:
    the stage never raises, and every stack it searches holds exactly the samples of one clean,
    contiguous run of one stream (row by row), so no cell can come from mixed data."""
    stage = SyncStage(FrontendConfig(), SyncConfig(stack=StackConfig(n_frames=2, track_clock=False), confirm_stacks=1))
    stacks = []
    push = stage.stacker.push_samples

    def spy(*args, **kwargs):
        done = push(*args, **kwargs)
        stacks.extend(done)
        return done

    stage.stacker.push_samples = spy
    expected = np.full(sum(n for _, n in pieces) * 2 + 1, UNSET)  # the current stream's clean samples
    index = stamp = stream = 0
    last_clean = None  # (start, codes, stamp) of the last clean chunk delivered: what "late" sends again
    for kind, length in pieces:
        before = len(stacks)
        if kind == "gap":
            index, stamp = index + length, stamp + round(length * 1e9 / RATE)
            continue
        if kind == "late":  # a repeat of an old chunk, exactly as it was
            if last_clean is None:
                continue
            start, values, chunk_stamp = last_clean
            results = stage.process(EnvelopeChunk(chunk_stamp, RATE, start, 12, 1e-3, values))
        else:
            if kind == "restart":  # the index starts over; time goes on, by more than a frame (a driver restarts)
                stream, index, stamp = stream + 1, 0, stamp + 2 * round(FRAME * 1e9 / RATE)
                expected[:] = UNSET  # (an old stream's chunk, sent late after this, must not mix in either)
            at = index + np.arange(length)
            values, rate = code(stream, at), RATE
            if kind == "corrupt":
                values[:] = 4000  # beyond a 12-bit ADC
            elif kind == "silent":
                values[:] = 0
            elif kind == "clipped":
                values[::2] = 2047
            elif kind == "wrong_rate":
                rate = 3.84e6
            if kind == "nan":
                results = stage.process_samples(np.full(length, np.nan), index, rate, stamp)
            else:
                results = stage.process(EnvelopeChunk(stamp, rate, index, 12, 1e-3, values))
            clean = kind in ("good", "restart", "silent", "clipped")
            expected[at] = values if clean else UNSET
            last_clean = (index, values, stamp) if clean else last_clean
            index, stamp = index + length, stamp + round(length * 1e9 / RATE)
        assert len(results) == len(stacks) - before
        for stack in stacks[before:]:
            rows = np.round(stack.rows.astype(np.float64) * 1e3)  # back to codes
            span = stack.row_starts[:, None] + np.arange(FRAME)[None, :]
            assert np.array_equal(rows, expected[span]), f"a stack at {stack.first_sample_index} after a {kind} chunk"
