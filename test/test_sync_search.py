"""Frame stacking, envelope-domain cell search, windows and the sync stage."""

import re
from pathlib import Path

import numpy as np
import pytest
import scipy.fft
import yaml

from deepsync.bag import read_envelope
from deepsync.types import FRAME_SECONDS, EnvelopeChunk, HealthKind, Severity
from deepsync.frontend.channel import Emitter, FixedChannel, Paths
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.simulator import EnvelopeSimulator
from deepsync.frontend.templates import SyncTemplates, code_template, known_frame, sync_code_offset_seconds
from deepsync.frontend.video import VideoFilter
from deepsync.lte.cell import CellConfig
from deepsync.sources import BagSource, squared_iq_frontend
from deepsync.sync.correlation import correlate, correlate_every, template_spectra
from deepsync.sync.search import CellDetection, CellSearch, ExpectedCell, SearchConfig
from deepsync.sync.sites import SiteFit
from deepsync.sync.stacking import FrameStacker, StackConfig
from deepsync.sync.stage import SyncConfig, SyncStage
from deepsync.towers import load_tower_database, parse_tower_database
from deepsync.sync.windows import extract_windows, extract_windows_at
from deepsync.timing.estimators import estimate_ml_frame, frame_spectrum
from deepsync.configio import ConfigError

REPO = Path(__file__).resolve().parents[1]
FRAME = 19200
CONFIG = FrontendConfig()


@pytest.fixture(scope="module")
def templates():
    return SyncTemplates(CONFIG)


def coloured_noise(rng, shape):
    """Gaussian noise shaped like the detector's output (white through the video filter)."""
    white = rng.standard_normal(shape)
    frequencies = scipy.fft.rfftfreq(shape[-1], 1 / CONFIG.adc_rate_hz)
    response = np.abs(VideoFilter(CONFIG).response(frequencies))
    shaped = scipy.fft.irfft(scipy.fft.rfft(white, axis=-1) * response, n=shape[-1], axis=-1)
    return shaped / shaped.std()


def frame_with_codes(templates, cells, frame=FRAME):
    """One frame holding each (pci, subframe-0 code start, amplitude) cell's two codes, in
    units of the peak of its subframe-0 code (both codes are sent at the same power)."""
    out = np.zeros(frame)
    for pci, start, amplitude in cells:
        scale = amplitude / np.abs(templates.template(pci, 0)).max()
        for subframe, at in ((0, start), (5, start + frame // 2)):
            whole = int(np.floor(at))
            code = templates.template(pci, subframe, at - whole)
            out[(whole + np.arange(len(code))) % frame] += scale * code
    return out


def frame_with_cosited_pair(templates, pcis, start, amplitudes, phase, frame=FRAME):
    """One frame holding two co-sited sectors' coinciding codes: |x s_a + y s_b|^2 through the
    chain, |x| and |y| the amplitudes, arg(x y*) the phase; in units of the peak of a's
    subframe-0 code."""
    (x, y), mixed = amplitudes, amplitudes[0] * amplitudes[1] * np.exp(1j * phase)
    fit = SiteFit(pcis, (x**2, y**2, mixed.real, -mixed.imag))
    whole, fraction = int(np.floor(start)), start - np.floor(start)
    scale = 1 / np.abs(templates.template(pcis[0], 0)).max()
    out = np.zeros(frame)
    for subframe, at in ((0, whole), (5, whole + frame // 2)):
        code = fit.template(templates, subframe, fraction)
        out[(at + np.arange(len(code))) % frame] += scale * code
    return out


def stack_rows(templates, cells, noise, n_frames, rng):
    return frame_with_codes(templates, cells)[None, :] + noise * coloured_noise(rng, (n_frames, FRAME))


# -- stacking -----------------------------------------------------------------------------


def chunked(samples, sizes, first=0, rate=1.92e6):
    out, i = [], 0
    for size in sizes:
        part = samples[i : i + size]
        out.append(EnvelopeChunk(int(1e9 * (first + i) / rate), rate, first + i, 12, 1e-3, part))
        i += size
    return out


def test_stacks_do_not_depend_on_chunking():
    rng = np.random.default_rng(1)
    codes = rng.integers(-2000, 2000, size=3 * 10 * FRAME + 777).astype(np.int16)
    a, b = FrameStacker(1.92e6), FrameStacker(1.92e6)
    whole = [s for c in chunked(codes, [len(codes)]) for s in a.push(c)]
    sizes = rng.integers(1, 50_000, size=2000)
    sizes = sizes[np.cumsum(sizes) <= len(codes)]
    pieces = [s for c in chunked(codes, list(sizes) + [len(codes) - int(sizes.sum())]) for s in b.push(c)]
    assert len(whole) == len(pieces) == 3
    for x, y in zip(whole, pieces):
        np.testing.assert_array_equal(x.rows, y.rows)
        assert x.first_sample_index == y.first_sample_index and x.stamp_ns == y.stamp_ns
    np.testing.assert_allclose(whole[1].rows[0], codes[10 * FRAME : 11 * FRAME] * 1e-3, rtol=1e-6)
    assert not a.events


def test_gap_nan_backwards_restart_and_rate_mismatch_are_reported_not_stacked():
    stacker = FrameStacker(1.92e6, StackConfig(n_frames=2))
    rng = np.random.default_rng(2)
    good = rng.standard_normal(5 * FRAME)

    def push(samples, index, rate=1.92e6, stamp_index=None):  # stamps on one timeline, unless told
        stamp = round((index if stamp_index is None else stamp_index) * 1e9 / 1.92e6)
        return stacker.push_samples(samples, index, rate, stamp)

    assert [s.first_sample_index for s in push(good[: 3 * FRAME], 0)] == [0]
    # gap of 1000 samples: the half-filled second stack is dropped, stacking restarts after it
    stacks = push(good[: 2 * FRAME], 3 * FRAME + 1000)
    assert [e.kind for e in stacker.events] == [HealthKind.GAP]
    assert "gap of 1000 samples" in stacker.events[0].message
    assert [s.first_sample_index for s in stacks] == [3 * FRAME + 1000]
    # non-finite samples: frames spanning them are dropped
    bad = good.copy()
    bad[100:110] = np.nan
    bad[200] = np.inf
    start = 5 * FRAME + 1000
    stacks = push(bad, start)
    assert stacker.events[-1].kind is HealthKind.NOT_FINITE and stacker.events[-1].sample_index == start + 100
    assert all(np.all(np.isfinite(s.rows)) for s in stacks)
    assert [s.first_sample_index for s in stacks] == [start + 201, start + 201 + 2 * FRAME]
    # a late (repeated) chunk, a frame back on the same timeline, is dropped
    assert push(good[:10], start + 4 * FRAME) == []
    assert stacker.events[-1].kind is HealthKind.BACKWARDS
    # samples at another rate than the templates': dropped, said once for the whole run
    assert push(good[: FRAME + 5], start + 5 * FRAME) == []  # 2 frames minus 196 pending
    assert push(np.ones(4 * 10000), start + 6 * FRAME + 5, 1.0e6) == []
    assert push(np.ones(4 * 10000), start + 6 * FRAME + 40005, 1.0e6) == []
    mismatch = stacker.events[-1]
    assert mismatch.kind is HealthKind.RATE_MISMATCH and mismatch.severity is Severity.ERROR
    assert "1e+06 Hz" in mismatch.message and "1.92e+06 Hz" in mismatch.message
    assert f"{2 * FRAME - 196} pending samples" in mismatch.message
    assert sum(e.kind is HealthKind.RATE_MISMATCH for e in stacker.events) == 1
    # back at the right rate, stacking starts afresh there (no gap reported on top)
    events = len(stacker.events)
    assert [s.first_sample_index for s in push(good[: 2 * FRAME], 30 * FRAME)] == [30 * FRAME]
    assert len(stacker.events) == events
    # the index starts over (a driver restart) while time goes on: a fresh start, not a stall
    stacks = push(good[: 2 * FRAME], 0, stamp_index=40 * FRAME)
    assert stacker.events[-1].kind is HealthKind.RESTART and [s.first_sample_index for s in stacks] == [0]
    # the same stream played again (index and stamps back to the start): also a fresh start
    push(good[: 3 * FRAME], 2 * FRAME, stamp_index=42 * FRAME)
    stacks = push(good[: 2 * FRAME], 0, stamp_index=0)
    assert stacker.events[-1].kind is HealthKind.RESTART and [s.first_sample_index for s in stacks] == [0]


def test_codes_beyond_the_adc_range_are_corrupt_data_never_stacked():
    """One flipped byte in a bag garbles thousands of codes far beyond a 12-bit ADC's range:
    reported as corrupt (not as clipping), and no stack spans them."""
    stacker = FrameStacker(1.92e6, StackConfig(n_frames=1))
    codes = np.random.default_rng(3).integers(-1000, 1000, 3 * FRAME).astype(np.int16)
    codes[FRAME + 10 : FRAME + 20] = np.array([31000, -29000] * 5, dtype=np.int16)
    stacks = stacker.push(EnvelopeChunk(0, 1.92e6, 0, 12, 1e-3, codes))
    (event,) = stacker.events
    assert event.kind is HealthKind.CORRUPT and event.severity is Severity.ERROR
    assert event.sample_index == FRAME + 10 and "10 codes beyond the 12-bit" in event.message
    assert [s.first_sample_index for s in stacks] == [0, FRAME + 20]
    assert all(not s.flags for s in stacks)  # not mistaken for clipping


def test_flags_for_clipping_and_silence():
    stacker = FrameStacker(1.92e6, StackConfig(n_frames=1))
    codes = np.zeros(FRAME, dtype=np.int16)
    (silent,) = stacker.push(EnvelopeChunk(0, 1.92e6, 0, 12, 1e-3, codes))
    assert [(f.kind, f.severity) for f in silent.flags] == [(HealthKind.NO_SIGNAL, Severity.ERROR)]
    assert "100.0 %" in silent.flags[0].message
    codes = np.full(FRAME, 300, dtype=np.int16)
    codes[5000:5200] = np.random.default_rng(4).integers(-1000, 1000, 200)
    (stuck,) = stacker.push(EnvelopeChunk(0, 1.92e6, FRAME, 12, 1e-3, codes))
    assert [f.kind for f in stuck.flags] == [HealthKind.NO_SIGNAL] and "99.0 %" in str(stuck.flags[0])  # stuck ADC, a burst
    codes = np.random.default_rng(3).integers(-1000, 1000, FRAME).astype(np.int16)
    codes[:100] = 2047
    (clipped,) = stacker.push(EnvelopeChunk(0, 1.92e6, 2 * FRAME, 12, 1e-3, codes))
    assert [f.kind for f in clipped.flags] == [HealthKind.CLIPPED] and "0.52 %" in str(clipped.flags[0])


def test_sliding_stacks_start_every_hop_frames_and_share_the_rest():
    rng = np.random.default_rng(2)
    codes = rng.integers(-2000, 2000, size=12 * FRAME + 5).astype(np.int16)
    stacker = FrameStacker(1.92e6, StackConfig(n_frames=5, hop_frames=2))
    stacks = [s for c in chunked(codes, [3 * FRAME, 5000, 9 * FRAME - 5000 + 5]) for s in stacker.push(c)]
    assert [s.first_sample_index for s in stacks] == [0, 2 * FRAME, 4 * FRAME, 6 * FRAME]  # 12 frames: 4 stacks
    for earlier, later in zip(stacks, stacks[1:]):
        np.testing.assert_array_equal(later.rows[:3], earlier.rows[2:])  # 5 - 2 frames in common
    np.testing.assert_allclose(stacks[3].rows[-1], codes[10 * FRAME : 11 * FRAME] * 1e-3, rtol=1e-6)
    assert not stacker.events
    with pytest.raises(ValueError, match="hop_frames must be 1..n_frames"):
        StackConfig(n_frames=5, hop_frames=6)


def test_a_sliding_stacks_mean_summed_block_by_block_is_the_mean_of_its_rows():
    rng = np.random.default_rng(5)
    codes = rng.integers(-2000, 2000, size=40 * FRAME).astype(np.int16)
    stacker = FrameStacker(1.92e6, StackConfig(n_frames=20, hop_frames=4, track_clock=False))
    stacks = [s for c in chunked(codes, [7777] * (len(codes) // 7777 + 1)) for s in stacker.push(c)]
    assert len(stacks) == 6
    for stack in stacks:
        np.testing.assert_allclose(stack.stacked(), stack.rows.mean(axis=0), rtol=1e-5, atol=1e-7)
        np.testing.assert_array_equal(stack.rows, codes[stack.first_sample_index :][: 20 * FRAME].reshape(20, FRAME) * np.float32(1e-3))


def periodic_stream(frames: int, clock_ppm: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """ADC codes of a pattern that repeats every frame of a receiver clock ``clock_ppm`` fast
    (as every cell's codes and CRS do), in noise; and the pattern."""
    rng = np.random.default_rng(seed)
    spectrum = scipy.fft.rfft(rng.normal(size=FRAME))
    spectrum[FRAME // 8 :] = 0  # smooth enough to interpolate linearly
    pattern = scipy.fft.irfft(spectrum, FRAME)
    pattern /= pattern.std()
    n = np.arange(frames * FRAME)
    phase = n / (1 + clock_ppm * 1e-6) % FRAME
    signal = np.interp(phase, np.arange(FRAME + 1), np.r_[pattern, pattern[0]]) + 0.5 * rng.normal(size=n.size)
    return np.round(300 * signal).astype(np.int16), pattern


@pytest.mark.parametrize("n_frames, hop, chunk", [(10, None, FRAME // 4), (10, None, 0), (50, 10, FRAME // 4), (50, 10, 0)])
def test_the_receiver_clock_is_followed_and_stacks_line_up_once_it_is_known(n_frames, hop, chunk):
    """A 22 ppm receiver clock (the real recording's) moves the frames 0.42 samples each: the
    first stack measures it and says it is misaligned; every later one is cut by it, and a
    sliding stack's frames cut before it was known are placed by it again. Chunks of a quarter
    frame (a frame then often ends where the data does), or of any size (0)."""
    codes, pattern = periodic_stream(160, 22.0, seed=6)
    stacker = FrameStacker(1.92e6, StackConfig(n_frames=n_frames, hop_frames=hop))
    sizes = np.full(len(codes) // chunk, chunk) if chunk else np.random.default_rng(7).integers(1000, 30000, 250)
    sizes = sizes[: np.searchsorted(np.cumsum(sizes), len(codes)) + 1].tolist()
    stacks = [s for c in chunked(codes, sizes) for s in stacker.push(c)]
    assert not stacks[0].aligned and stacks[0].drift_ppm == pytest.approx(22.0, abs=0.5)
    assert len(stacks) >= 6 and all(s.aligned for s in stacks[1:])
    assert all(s.drift_ppm == pytest.approx(22.0, abs=0.2) for s in stacks[1:])
    for stack in stacks[1:]:  # the stacked pattern as sharp as one frame of it
        c = scipy.fft.irfft(scipy.fft.rfft(stack.stacked() - stack.stacked().mean()) * np.conj(scipy.fft.rfft(pattern)), FRAME)
        assert c.max() / (np.linalg.norm(stack.stacked() - stack.stacked().mean()) * np.linalg.norm(pattern)) > 0.95
    starts = np.diff([s.first_sample_index for s in stacks]) / ((hop or n_frames) * FRAME * (1 + 22e-6))
    assert np.all(np.abs(starts - 1) < 1e-4)  # a stack every hop frames of the receiver's clock, from the first on


def test_sliding_stacks_confirm_a_cell_at_the_hop_rate():
    """A 20-frame stack every 5 frames on the campus bag: a result every 50 ms, the cells found
    where they are, and confirmed after three stacks in a row, as with back-to-back stacks."""
    bag = REPO / "bags" / "campus"
    config = SyncConfig(stack=StackConfig(n_frames=20, hop_frames=5))
    stage = SyncStage(BagSource(bag).frontend, config, load_tower_database(CAMPUS_TOWERS))
    results = [r for chunk in read_envelope(bag) for r in stage.process(chunk)]
    assert len(results) == (300 - 20) // 5 + 1  # 3 s of frames
    assert np.all(np.diff([r.first_sample_index for r in results]) == 5 * FRAME)
    truth = {56: 1672.06, 301: 14938.01, 120: 6680.06, 121: 6680.06}
    assert not results[0].cells and not results[1].cells  # three stacks in a row confirm a cell
    complete = [{c.pci for c in r.cells} == set(truth) for r in results[2:]]
    assert np.mean(complete) >= 0.9  # PCI 301, at -6 dB, fades out of a few stacks
    for result in results:
        for cell in result.cells:
            assert abs((cell.code_position - truth[cell.pci] + FRAME / 2) % FRAME - FRAME / 2) <= 1.0
            assert cell.window.windows.shape == (20, 276 + 20)


def test_clock_offset_is_compensated_to_the_sub_sample(templates):
    """A receiver clock 37 ppm fast: compensated rows put the code at one place, exactly."""
    ppm, n = 37.0, 10
    period = FRAME * (1 + ppm * 1e-6)
    stream = np.zeros(int(period * (n + 1)))
    for f in range(n + 1):  # one code per frame at a drifting sub-sample position
        at = 5000.3 + f * period
        whole = int(np.floor(at))
        code = templates.template(120, 0, at - whole)
        stream[whole : whole + len(code)] += code
    (stack,) = FrameStacker(1.92e6, StackConfig(n_frames=n, clock_ppm=ppm)).push_samples(stream, 0, 1.92e6)
    assert stack.aligned
    windows = extract_windows(stack, 5000, templates.length, margin=10)
    expected = templates.template(120, 0, 10.3)[: windows.shape[1]]
    for row in windows:
        np.testing.assert_allclose(row[:276], expected[:276], atol=1e-2 * np.abs(expected).max())
    assert stack.drift_ppm == pytest.approx(ppm, abs=1.0)  # measured from the stream itself
    # several cells' windows cut at once are each cell's own, exactly (here and without a clock, whole samples)
    (exact,) = FrameStacker(1.92e6, StackConfig(n_frames=n)).push_samples(stream[: n * FRAME], 0, 1.92e6)
    for cut in (stack, exact):
        starts = [5000, 19190, 77, 5000]  # one near the frame's end: rows are cut circularly
        together = extract_windows_at(cut, starts, templates.length, margin=10)
        assert together.shape == (4, n, templates.length + 20) and together.dtype == np.float32
        for start, rows in zip(starts, together):
            np.testing.assert_array_equal(rows, extract_windows(cut, start, templates.length, margin=10))
    # without compensation the last frame's code has moved 7 samples: measured and flagged
    (drifted,) = FrameStacker(1.92e6, StackConfig(n_frames=n)).push_samples(stream, 0, 1.92e6)
    assert not drifted.aligned
    assert [f.message[:3] for f in drifted.flags if f.kind is HealthKind.MISALIGNED] == ["+37"]
    assert drifted.drift_ppm == pytest.approx(ppm, abs=1.0)


# -- detection ----------------------------------------------------------------------------


@pytest.mark.parametrize("known, noise", [(False, 0.45), (True, 0.6)])  # a DB's full codes: more reach
def test_cells_sharing_nid2_and_cells_close_in_time_are_separated(templates, known, noise):
    rng = np.random.default_rng(4)
    # 301 and 121 share N_ID2 = 1; 56 sits 4.9 samples from 121
    cells = [(301, 14938.4, 1.0), (121, 6680.7, 1.0), (56, 6685.6, 0.8)]
    rows = stack_rows(templates, cells, noise=noise, n_frames=10, rng=rng)
    allowed = [120, 121, 122, 301, 302, 56, 57, 405, 406] if known else None
    found = CellSearch(templates, allowed_pcis=allowed).search(rows.mean(axis=0))
    positions = {d.pci: d.frame_offset + d.fraction for d in found}
    if known:
        assert sorted(positions) == [56, 121, 301]
    for pci, start, _ in cells:
        timing = [p for p in (d.frame_offset + d.fraction for d in found) if abs(p - start) < 1.0]
        assert timing, f"no detection within 1 sample of {pci}'s code at {start}"
        if pci in positions:
            assert positions[pci] == pytest.approx(start, abs=0.5)
    assert len(found) == 3  # and nothing else


CAMPUS_TOWERS = REPO / "config" / "towers" / "campus.yaml"


@pytest.mark.parametrize("known", [False, True])  # with a database: single templates and site pairs
def test_noise_alone_gives_false_alarms_at_the_stated_rate(templates, known):
    rng = np.random.default_rng(5)
    db = load_tower_database(CAMPUS_TOWERS)
    search = CellSearch(templates, SearchConfig(false_alarm_rate=1e-2), *((db.pcis, db.cosited_pairs()) if known else ()))
    assert known == (search.sites is not None)
    false = sum(len(search.search(coloured_noise(rng, (FRAME,)))) > 0 for _ in range(100))
    assert false <= 4  # 1 expected at a 1 % per-stack rate


@pytest.mark.parametrize("n, step", [(19200, 32), (9600, 4), (1001, 7), (1000, 3), (500, 1)])
def test_correlations_at_every_step_th_lag_are_the_full_ones_sampled(n, step):
    rng = np.random.default_rng(n)
    spectrum = scipy.fft.rfft(rng.standard_normal(n))
    spectra = template_spectra(rng.standard_normal((2, 3, 50)), n)
    full = correlate(spectrum, spectra, n)
    sampled = correlate_every(spectrum, spectra, n, step)
    assert sampled.shape == full[..., ::step].shape
    np.testing.assert_allclose(sampled, full[..., ::step], atol=1e-5 * np.abs(full).max())


@pytest.mark.parametrize("amplitude", [0.4, 1.5])
def test_cosited_sectors_are_found_together(templates, amplitude):
    """Two sectors of one site at equal power, at several relative phases: the cross term of
    their codes dominates the envelope. Weak, single templates mostly miss them; strong, a
    sector's own template may peak first, and its partner is then recognised at once (not
    left in the residual to pass for other cells)."""
    rng = np.random.default_rng(7)
    db = load_tower_database(CAMPUS_TOWERS)
    with_sites = CellSearch(templates, allowed_pcis=db.pcis, cosited_pairs=db.cosited_pairs())
    singles = CellSearch(templates, allowed_pcis=db.pcis)
    start, singles_found_both = 6680.3, 0
    for phase in (0.3, 1.9, 3.5, 5.1):
        rows = frame_with_cosited_pair(templates, (120, 121), start, (1.0, 1.0), phase)[None, :] * amplitude \
            + coloured_noise(rng, (10, FRAME))
        stacked = rows.mean(axis=0)
        found = with_sites.search(stacked)
        assert sorted(d.pci for d in found) == [120, 121]
        for d in found:
            assert d.site is not None and d.site.pcis == (120, 121)
            assert d.frame_offset + d.fraction == pytest.approx(start, abs=0.3)
        singles_found_both += {120, 121} <= {d.pci for d in singles.search(stacked)}
    if amplitude < 1:
        assert singles_found_both <= 1


def test_a_second_site_is_found_and_pairs_of_found_sectors_are_not_searched(templates, monkeypatch):
    """Two sites' pairs in one stack: both are found. The pairs' statistic (the search's
    costliest pass) is computed only for pairs none of whose sectors is found yet: a pair
    with a found sector could not be added."""
    rng = np.random.default_rng(9)
    db = load_tower_database(CAMPUS_TOWERS)
    search = CellSearch(templates, allowed_pcis=db.pcis, cosited_pairs=db.cosited_pairs())
    searched = []
    correlations = type(search.sites).correlations
    def spy(self, spectrum, single, pairs, step=1, single_step=1):
        if step == 1:
            searched.append({pci for k in pairs for pci in self.pairs[k]})
        return correlations(self, spectrum, single, pairs, step, single_step)
    monkeypatch.setattr(type(search.sites), "correlations", spy)
    rows = (frame_with_cosited_pair(templates, (120, 121), 3100.4, (1.0, 1.0), 1.1) * 1.5
            + frame_with_cosited_pair(templates, (301, 302), 9900.7, (1.0, 0.8), 2.3) * 0.6)[None, :] \
        + coloured_noise(rng, (10, FRAME))
    found = search.search(rows.mean(axis=0))
    assert sorted(d.pci for d in found) == [120, 121, 301, 302]
    assert searched, "the pairs' statistic was never computed"
    for pcis in searched:  # the strong pair is found first, by its own templates
        assert not pcis & {120, 121}


def test_a_single_sector_is_not_taken_for_a_pair(templates):
    rng = np.random.default_rng(8)
    db = load_tower_database(CAMPUS_TOWERS)
    search = CellSearch(templates, allowed_pcis=db.pcis, cosited_pairs=db.cosited_pairs())
    for trial, amplitude in enumerate((2.0, 4.0, 8.0, 16.0)):  # from near detection to ~20 dB above
        start = 1000.0 + 2000 * trial + 0.25 * trial
        rows = frame_with_cosited_pair(templates, (120, 121), start, (1.0, 0.0), 0.0)[None, :] * amplitude \
            + coloured_noise(rng, (10, FRAME))
        (found,) = search.search(rows.mean(axis=0))
        assert found.pci == 120 and found.site is None
        assert found.frame_offset + found.fraction == pytest.approx(start, abs=0.3)


def test_blind_identity_is_a_ranked_candidate_list(templates):
    rng = np.random.default_rng(6)
    rows = stack_rows(templates, [(88, 1234.0, 1.0)], noise=0.2, n_frames=20, rng=rng)
    (found,) = CellSearch(templates).search(rows.mean(axis=0))
    assert found.frame_offset + found.fraction == pytest.approx(1234.0, abs=0.3)
    assert 88 in [c.pci for c in found.candidates[:3]]
    assert found.candidates[0].score >= found.candidates[-1].score


def test_bad_stacked_frames(templates):
    search = CellSearch(templates)
    with pytest.raises(ValueError, match="NaN"):
        search.search(np.full(FRAME, np.nan))
    assert search.search(np.full(FRAME, 3.0)) == []
    # a short burst on a stuck input: the correlations vanish at most lags, so no noise level
    # exists to measure; without this guard the burst passed for cells at 1e8 sigma
    burst = np.zeros(FRAME)
    burst[5000:5050] = np.random.default_rng(9).standard_normal(50)
    db = load_tower_database(CAMPUS_TOWERS)
    for stuck in (CellSearch(templates), CellSearch(templates, allowed_pcis=db.pcis, cosited_pairs=db.cosited_pairs())):
        assert stuck.search(burst) == []
    with pytest.raises(ValueError, match="allowed_pcis"):
        CellSearch(templates, allowed_pcis=[600])


def test_tower_database_validation(tmp_path):
    db = load_tower_database(CAMPUS_TOWERS)
    assert {120, 121, 301, 56} <= set(db.pcis) and len(db.sites) == 5
    assert db.cells_with_pci(301)[0].carrier_hz == pytest.approx(2115e6)
    pairs = db.cosited_pairs()
    assert {(120, 121), (120, 122), (121, 122), (56, 57)} <= set(pairs)
    assert (121, 301) not in pairs and (57, 120) not in pairs  # other sites
    mixed = parse_tower_database({"sites": [{"name": "A", "cells": [
        {"pci": 1, "earfcn": 2000}, {"pci": 2, "earfcn": 2300}, {"pci": 3, "earfcn": 2000}]}]})
    assert mixed.cosited_pairs() == [(1, 3)]  # sectors on another carrier do not mix
    reused = parse_tower_database({"sites": [
        {"name": "A", "cells": [{"pci": 1, "bandwidth_mhz": 10}, {"pci": 2, "bandwidth_mhz": 20}, {"pci": 3}]},
        {"name": "B", "cells": [{"pci": 1, "bandwidth_mhz": 10.0}, {"pci": 2, "bandwidth_mhz": 5}]}]})
    assert reused.bandwidths() == {1: 10.0}  # PCI 2's two cells disagree, PCI 3 gives none
    for broken, message in (
        ({"sites": []}, "lists no sites"),
        ({"sites": [{"name": "A", "cells": [{"pci": 999}]}]}, r"sites\[0\].cells\[0\]: PCI 999"),
        ({"sites": [{"name": "A", "latitude_deg": 91, "cells": [{"pci": 1}]}]}, "latitude_deg"),
        ({"sites": [{"name": "A", "cells": [{"pci": 1, "earfcn": 99999}]}]}, "99999"),
        ({"sites": [{"name": "A", "cells": [{"pci": 1}]}, {"name": "A", "cells": [{"pci": 2}]}]}, "unique"),
    ):
        with pytest.raises(ConfigError, match=message):
            parse_tower_database(broken)


# -- the stage on the bundled recording ---------------------------------------------------


def test_stage_on_the_campus_bag_finds_every_cell_and_no_others():
    bag = REPO / "bags" / "campus"
    stage = SyncStage(BagSource(bag).frontend, SyncConfig(), load_tower_database(CAMPUS_TOWERS))
    truth = {56: 1672.06, 301: 14938.01, 120: 6680.06, 121: 6680.06}  # code phase, from the bag's truth
    results = [r for chunk in read_envelope(bag) for r in stage.process(chunk)]
    assert len(results) == 30
    seen = dict.fromkeys(truth, 0)
    for result in results:
        assert result.aligned and not result.events
        assert {c.pci for c in result.cells} <= set(truth)  # never reports a cell that is not on the air
        for cell in result.cells + result.tentative:
            if cell.pci not in truth:
                continue  # a tentative false detection: what confirmation is for
            error = (cell.code_position - truth[cell.pci] + FRAME / 2) % FRAME - FRAME / 2
            assert abs(error) <= 1.0
            assert cell.window.windows.shape == (10, 276 + 20)
            # the co-sited sectors of site A (equal power, same timing) are found as a pair
            assert cell.window.cosited_pci == {120: 121, 121: 120}.get(cell.pci)
            seen[cell.pci] += 1
    assert min(seen.values()) >= 25, seen  # PCI 301, at -6 dB, is missed in a few stacks
    assert {c.pci for r in results[-5:] for c in r.cells} == set(truth)  # confirmed: three stacks in a row
    assert not results[0].cells and not results[1].cells  # nothing is confirmed before that
    assert abs(results[-1].clock_drift_ppm) < 1.0  # the simulated receiver clock is exact (measured to ~0.5 ppm)


# -- tracking the cells found ------------------------------------------------------------------


def fading_stream(templates, amplitudes, rng, pci=56, start=1672.3):
    """One frame per amplitude: the cell's codes at that amplitude (0: gone) in unit coloured noise."""
    return np.concatenate([frame_with_codes(templates, [(pci, start, a)]) + coloured_noise(rng, (FRAME,))
                           for a in amplitudes])


def test_a_confirmed_cell_is_held_through_a_fade_the_full_search_misses(templates):
    """Strong for 4 stacks, then at a level where the full search (6 sigmas over a frame of lags
    and 26 PCIs) finds it in a third of the stacks, while tracking tests 3 lags of one PCI (3.6
    sigmas); then gone: not reported, looked for in two more stacks, and each stack after a miss
    is searched in full."""
    db = load_tower_database(CAMPUS_TOWERS)
    stage = SyncStage(CONFIG, SyncConfig(search_every=5), db)
    stream = fading_stream(templates, [1.0] * 40 + [0.45] * 80 + [0.0] * 30, np.random.default_rng(21))
    results = stage.process_samples(stream, 0, 1.92e6)
    assert len(results) == 15
    weak, gone = results[4:12], results[12:]
    held = [r for r in weak if [c.pci for c in r.cells + r.tentative] == [56]]
    assert len(held) >= 7
    for result in held:
        (cell,) = result.cells + result.tentative
        assert abs(cell.code_position - result.first_sample_index - 1672.3) < 1.0
        # reported (timed) only where strong enough to time
        assert (result.cells != ()) == (cell.detection.peak_metric >= SyncConfig().report_z)
    assert sum(r.pcis == [56] for r in weak) >= 3
    # the same stacks searched afresh, as every stack was before tracking
    full = CellSearch(templates, allowed_pcis=db.pcis, cosited_pairs=db.cosited_pairs())
    stacks = stream.reshape(-1, 10, FRAME).mean(axis=1)[4:12]
    assert sum(any(d.pci == 56 for d in full.search(stack)) for stack in stacks) <= 4
    assert all(not r.cells and not r.tentative for r in gone)
    # a stack that missed the (confirmed) cell is followed by a full search
    missed = [56 not in [c.pci for c in r.cells + r.tentative] for r in results]
    assert all(later.searched for later, miss in zip(results[5:], missed[4:]) if miss)
    # between full searches, only the cells found are looked for
    assert [r.searched for r in results[:5]] == [True, False, False, False, False]


def test_full_searches_back_off_while_they_find_nothing_new_and_resume_when_a_cell_appears(templates):
    """Cell 56 from the start, cell 301 from stack 40 on: while the full searches find nothing
    new their gap doubles from search_every (5 stacks) up to max_search_interval_s (2 s: 20
    10-frame stacks); the one that finds 301 brings the gap back to 5."""
    db = load_tower_database(CAMPUS_TOWERS)
    rng = np.random.default_rng(5)
    one = frame_with_codes(templates, [(56, 1672.3, 1.0)])
    two = one + frame_with_codes(templates, [(301, 9021.6, 1.0)])
    stream = np.concatenate([(one if frame < 400 else two) + coloured_noise(rng, (FRAME,)) for frame in range(750)])
    searched = {}
    for limit in (2.0, 0.0):
        stage = SyncStage(CONFIG, SyncConfig(search_every=5, max_search_interval_s=limit), db)
        results = stage.process_samples(stream, 0, 1.92e6)
        assert len(results) == 75
        searched[limit] = [i for i, r in enumerate(results) if r.searched]
        first_301 = next(i for i, r in enumerate(results) if 301 in {c.pci for c in r.cells + r.tentative})
        assert first_301 == next(i for i in searched[limit] if i >= 40)  # the first full search after it appears
        assert all(301 in r.pcis for r in results[first_301 + 2 :])  # then tracked and confirmed
        assert all(56 in r.pcis for r in results[2:])
    assert searched[2.0] == [0, 5, 15, 35, 55, 60, 70]
    assert searched[0.0] == list(range(0, 75, 5))  # no backoff
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match=r"max_search_interval_s must be (within \[0, 3600\] s|a finite number)"):
            SyncConfig(max_search_interval_s=bad)


def test_tracking_confirms_and_times_the_campus_cells_as_a_search_every_stack_does():
    bag = REPO / "bags" / "campus"
    db = load_tower_database(CAMPUS_TOWERS)
    runs = {}
    for every in (1, 5):
        stage = SyncStage(BagSource(bag).frontend, SyncConfig(search_every=every, max_search_interval_s=0.0), db)
        runs[every] = [r for chunk in read_envelope(bag) for r in stage.process(chunk)]
    assert sum(r.searched for r in runs[1]) == 30 and sum(r.searched for r in runs[5]) <= 8
    for full, tracked in zip(runs[1], runs[5]):
        assert set(full.pcis) == set(tracked.pcis)
        positions = {c.pci: c.code_position for c in full.cells}
        for cell in tracked.cells:
            assert cell.code_position == pytest.approx(positions[cell.pci], abs=0.05)


def test_a_stack_that_only_tracks_times_its_cells_as_a_full_search_does(templates):
    """Tracking only, the statistic is the frame templates' dot products at the few tracked
    lags, over spreads measured at every 4th lag by a shorter transform; a full search takes it
    from every lag's FFT correlation. Same stack, same cells expected: same peaks, positions and
    scales, on the first pass and on the residual of a cancelled strong cell next to them."""
    rng = np.random.default_rng(12)
    cells = [(40, 5200.3, 9.0), (301, 5230.6, 1.2), (156, 12000.8, 1.5)]  # 301 overlaps the strong 40
    stacked = stack_rows(templates, cells, 1.0, 10, rng).mean(axis=0)
    expected = [ExpectedCell(pci, start, held=True) for pci, start, _ in cells]
    search = CellSearch(templates, allowed_pcis=[40, 156, 301, 302, 57])
    tracked = search.search(stacked, expected, discover=False)
    full = search.search(stacked, expected, discover=True)[: len(tracked)]
    assert [d.pci for d in tracked] == [40, 301, 156]
    for a, b in zip(tracked, full):
        assert (a.pci, a.frame_offset) == (b.pci, b.frame_offset)
        assert a.peak_metric == pytest.approx(b.peak_metric, rel=1e-5)
        assert a.fraction == pytest.approx(b.fraction, abs=1e-6) and a.amplitude == pytest.approx(b.amplitude, rel=1e-6)


def test_detect_command_reports_cells_and_refuses_ambiguous_input(capsys):
    from deepsync.cli import main

    bag = REPO / "bags" / "campus"
    towers = REPO / "config" / "towers" / "campus.yaml"
    assert main(["detect", "--bag", str(bag), "--towers", str(towers)]) == 0
    out = capsys.readouterr().out
    assert all(f"PCI {pci:3d}" in out for pci in (56, 120, 121, 301)) and "(ml_frame, bound" in out and "truth" in out
    assert "no such cell" not in out
    assert main(["detect", "--towers", str(towers)]) == 2
    assert "give one recording: --bag BAG or --input FILE" in capsys.readouterr().err


def test_detect_command_on_an_iq_recording_without_truth(tmp_path, capsys, templates):
    """An RTL-SDR file (8-bit I/Q) holding one cell's codes: found, summarised, no truth claimed."""
    from deepsync.cli import main

    rng = np.random.default_rng(11)
    frames = 40
    envelope = np.tile(frame_with_codes(templates, [(88, 4321.0, 1.0)]), frames) + 0.3 * rng.standard_normal(frames * FRAME)
    amplitude = np.sqrt(np.clip(envelope + 3.0, 0, None))  # |x|^2 = envelope + a pedestal
    iq = np.stack([amplitude, np.zeros_like(amplitude)], axis=1) * 30 + 127.5  # real-valued I/Q
    path = tmp_path / "cell88.bin"
    np.clip(np.round(iq), 0, 255).astype(np.uint8).tofile(path)
    assert main(["detect", "--input", str(path), "--format", "cu8", "--rate", "1.92e6"]) == 0
    out = capsys.readouterr().out
    assert "PCI  88  reported in" in out and "truth" not in out


def test_stage_survives_every_kind_of_bad_input_and_says_what_happened(templates):
    """NaN, a gap, going back in time, another sample rate, silence and clipping, in one stream."""
    stage = SyncStage(CONFIG, SyncConfig(stack=StackConfig(n_frames=2), confirm_stacks=1))
    rng = np.random.default_rng(9)
    code = frame_with_codes(templates, [(301, 5000.2, 1.0)])

    def frames(n, rate=1.92e6):
        length = round(rate * FRAME_SECONDS)
        return np.tile(code[:length] if length <= FRAME else np.resize(code, length), n) + 0.05 * rng.standard_normal(n * length)

    good = frames(2)
    nan = frames(2)
    nan[777] = np.nan
    def feed(samples, index, rate=1.92e6):
        return stage.process_samples(samples, index, rate, round(index * 1e9 / 1.92e6))

    results = []
    results += feed(good, 0)  # a stack with the cell
    results += feed(nan, 2 * FRAME)  # non-finite sample: stack dropped
    results += feed(frames(2), 5 * FRAME)  # after a one-frame gap
    results += feed(frames(1), 6 * FRAME)  # back in time, a late chunk: dropped
    results += feed(np.zeros(2 * FRAME), 7 * FRAME)  # silence
    results += feed(frames(2, 1.0e6), 9 * FRAME, 1.0e6)  # another sample rate
    chunk = EnvelopeChunk(round(10**7 / 1.92e-3), 1.92e6, 10**7, 12, 1e-3, np.full(2 * FRAME, 2047, dtype=np.int16))
    results += stage.process(chunk)  # clipped throughout (after another gap)
    events = [e.kind for r in results for e in r.events]
    flags = [f.kind for r in results for f in r.flags]
    assert {HealthKind.NOT_FINITE, HealthKind.GAP, HealthKind.BACKWARDS, HealthKind.RATE_MISMATCH} <= set(events)
    assert {HealthKind.NO_SIGNAL, HealthKind.CLIPPED} <= set(flags)
    assert results[0].pcis == [301]
    assert all(r.cells == () for r in results if any(f.kind is HealthKind.NO_SIGNAL for f in r.flags))


# -- a strong cell's CRS --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def strong_cell_frames():
    """100 frames of one strong, loaded 10 MHz cell (PCI 456, line of sight) through the default
    chain, and where its code sits: what long stacks near a tower look like."""
    cell = Emitter(CellConfig(pci=456, bandwidth_mhz=10, load=0.6), 2115e6, 2e-3, 0.0, 0.0, "S")
    sim = EnvelopeSimulator([cell], FixedChannel(Paths([1e-6], [3e-5], [0.0])), FrontendConfig(), seed=3)
    volts = np.concatenate([c.samples for c in sim.stream(1.0)]).astype(np.float64)
    code = float(sim.sample_index(sync_code_offset_seconds() + 1e-6)) % FRAME
    return volts[: 100 * FRAME].reshape(100, FRAME), code


def test_the_crs_template_is_what_the_simulator_sends(templates, strong_cell_frames):
    frames, code = strong_cell_frames
    stacked = frames.mean(axis=0)
    start = code - sync_code_offset_seconds() * templates.sample_rate  # where the cell's frame starts

    def correlation(pci: int) -> float:
        shape = templates.crs_envelope(pci, 10)
        shifted = np.fft.irfft(np.fft.rfft(shape) * np.exp(-2j * np.pi * np.fft.rfftfreq(FRAME) * start), FRAME)
        return float(np.corrcoef(shifted, stacked)[0, 1])

    assert correlation(456) > 0.5  # the CRS is a large part of everything in the stack (0.64)
    assert correlation(457) < 0.5 * correlation(456)  # another PCI's CRS comb sits on other subcarriers


def test_a_known_cells_full_frame_template_is_its_codes_and_crs_as_sent(templates, strong_cell_frames):
    """Codes + CRS: what the simulator sends, with 10x the codes' energy at 10 MHz, and the
    CRS comb's sidelobes one comb period (21.3 samples) out (``benchmarks/detection/full_frame_template.py``)."""
    frames, code = strong_cell_frames
    stacked = frames.mean(axis=0) - frames.mean()

    def correlation(pci: int) -> float:
        full = np.roll(templates.frame_template(pci, 10, [code % 1])[0], int(code))
        return float(np.corrcoef(full, stacked)[0, 1])

    start = code - sync_code_offset_seconds() * templates.sample_rate
    crs = scipy.fft.irfft(scipy.fft.rfft(templates.crs_envelope(456, 10)) * np.exp(-2j * np.pi * scipy.fft.rfftfreq(FRAME) * start), FRAME)
    assert correlation(456) > float(np.corrcoef(crs, stacked)[0, 1]) + 0.03  # 0.69 against 0.64: the codes are where they are sent
    assert correlation(457) < 0.5 * correlation(456)
    full = templates.frame_template(456, 10, [0.0])[0]
    codes = sum(np.sum((t - t.mean()) ** 2) for t in (templates.template(456, s, 0.0) for s in (0, 5)))
    assert 9.0 < 10 * np.log10(np.sum(full**2) / codes) < 11.5
    auto = scipy.fft.irfft(np.abs(scipy.fft.rfft(full)) ** 2, FRAME) / np.sum(full**2)
    comb = auto[18:25]
    assert 0.45 < comb.max() < 0.75 and 20 <= 18 + np.argmax(comb) <= 22 and auto[5:16].max() < comb.max()


def test_a_pairs_known_frame_is_its_fitted_codes_and_crs_with_their_cross_terms(templates):
    """What the timing stage fits for two co-sited sectors found together: the pair's code model
    of the sync stage in subframes 0 and 5, and their CRS with the same four coefficients (each
    sector's own, and the two cross terms of the square law)."""
    assert np.array_equal(known_frame(templates, 456, 10), templates.frame_template(456, 10, [0.0])[0])
    coefficients = (0.8, -0.1, 0.3, -0.2)
    pair = known_frame(templates, 121, 10, 120, coefficients)
    crs = (0.8 * templates.code_aligned_crs(120, 10) - 0.1 * templates.code_aligned_crs(121, 10)
           + np.array([0.3, -0.2]) @ templates.code_aligned_crs(120, 10, 121))
    half = len(pair) // 2
    for start, subframe in ((0, 0), (half, 5)):
        code = code_template(templates, 121, 120, coefficients, subframe)
        np.testing.assert_allclose(pair[start : start + code.size] - crs[start : start + code.size],
                                   code - code.mean(), atol=1e-9 * np.abs(code).max())
    between = slice(templates.length + 10, half - 10)
    np.testing.assert_allclose(pair[between], crs[between], atol=1e-9 * np.abs(crs).max())
    with pytest.raises(ValueError, match="4 site coefficients"):
        known_frame(templates, 121, 10, 120, None)


def test_the_cross_terms_of_two_sectors_crs_are_in_their_stacks():
    """Two co-sited sectors at equal power with another relative phase than 0 or pi: the square law
    mixes their CRS as it mixes their codes, and the pair's known frame with those cross terms
    (scaled by the sync stage's fit of the codes) explains more of the stack than without
    (8.5 % of its energy against 5.0 % when this was written), and times it within 0.03 samples."""
    sectors = [Emitter(CellConfig(pci=pci, bandwidth_mhz=10, load=0.5), 2115e6, 1.0, 0.0, 0.0, str(pci)) for pci in (120, 121)]
    gain = np.sqrt(10 ** ((-80 - 30) / 10))
    sim = EnvelopeSimulator(sectors, FixedChannel([Paths([1.3e-6], [gain], [phase]) for phase in (0.0, 2.0)]),
                            FrontendConfig(), seed=5)
    towers = parse_tower_database({"name": "pair", "sites": [{"name": "A", "cells": [
        {"pci": 120, "earfcn": 2000, "bandwidth_mhz": 10}, {"pci": 121, "earfcn": 2000, "bandwidth_mhz": 10}]}]})
    stage = SyncStage(FrontendConfig(), towers=towers)
    reported = [r for chunk in sim.stream(0.4) for r in stage.process(chunk) if r.cells]
    assert reported and all(c.window.cosited_pci is not None for r in reported for c in r.cells)
    code = float(sim.sample_index(sync_code_offset_seconds() + 1.3e-6)) % FRAME
    for result in reported:
        window = result.cells[0].window
        start = (window.coarse_index - result.first_sample_index) % FRAME
        _, _, real, imaginary = window.site_coefficients
        full = known_frame(stage.templates, window.pci, 10, window.cosited_pci, window.site_coefficients)
        own = full - np.array([real, imaginary]) @ stage.templates.code_aligned_crs(120, 10, 121)
        frame = result.frame - result.frame.mean()
        explained = {}
        for name, model in (("cross", full), ("own", own)):
            moved = np.roll(model, start)
            explained[name] = 1 - np.sum((frame - (frame @ moved) / (moved @ moved) * moved) ** 2) / np.sum(frame**2)
            timing = estimate_ml_frame(frame_spectrum(result.frame), model, start, 10).estimate
            explained[name + " error"] = abs((start + timing.offset - code + FRAME / 2) % FRAME - FRAME / 2)
        assert explained["cross"] > 1.3 * explained["own"]
        assert explained["cross error"] < 0.03


def test_a_tracked_cell_its_codes_miss_is_held_by_its_whole_frame(templates):
    """A loaded 10 MHz cell at -114 dBm per RE, 10-frame stacks: its codes pass the tracking
    threshold in about 1 stack of 6, its codes and CRS in all of them
    (``benchmarks/detection/full_frame_template.py``: Pd 0.18 against 1.0 there). Held within a sample
    of its code start; without the database's bandwidth the cell cannot be held so."""
    power_w, eirp_w, delay = 10 ** ((-114 - 30) / 10), 1.0, 1.3e-6
    cell = Emitter(CellConfig(pci=301, bandwidth_mhz=10, load=1.0), 2115e6, eirp_w, 0.0, 0.0, "weak")
    sim = EnvelopeSimulator([cell], FixedChannel([Paths([delay], [np.sqrt(power_w / eirp_w)], [0.0])]),
                            FrontendConfig(), seed=21)
    volts = np.concatenate([c.samples for c in sim.stream(0.6)]).astype(np.float64)
    stacks = volts[: 60 * FRAME].reshape(6, 10, FRAME).mean(axis=1)
    code = float(sim.sample_index(sync_code_offset_seconds() + delay)) % FRAME
    expected = [ExpectedCell(301, code, held=True)]
    searches = {name: CellSearch(templates, SearchConfig(hold_by_frame=hold), [301, 302, 40], None, bandwidths)
                for name, hold, bandwidths in (("frame", True, {301: 10.0}), ("codes", False, {301: 10.0}),
                                               ("no bandwidth", True, None))}
    found = {name: [] for name in searches}
    for stacked in stacks:
        for name, search in searches.items():
            found[name] += [d.frame_offset + d.fraction for d in search.search(stacked, expected, discover=False)]
    assert len(found["frame"]) == 6 and len(found["codes"]) <= 2 and len(found["no bandwidth"]) <= 2
    assert all(abs(start - code) < 1.0 for start in found["frame"])


def test_a_cells_bandwidth_is_learned_where_the_database_gives_none():
    """The campus database without its bandwidths: each confirmed cell's stacks vote for the LTE
    bandwidth whose known frame explains them best, and after 5 agreeing votes it is the cell's
    (10 MHz, as sent), so its windows carry it and the stack's frame goes along for ml_frame.
    A 5 MHz cell is learned as 5 MHz, not as the campus's 10. Switched off, nothing is learned."""
    text = (REPO / "config" / "towers" / "campus.yaml").read_text()
    towers = parse_tower_database(yaml.safe_load(re.sub(r",\s*bandwidth_mhz:\s*[0-9.]+", "", text)))
    assert towers.bandwidths() == {}
    source = BagSource(REPO / "bags" / "campus")
    stage = SyncStage(source.frontend, towers=towers)
    results = [r for chunk in source.chunks() for r in stage.process(chunk)]
    assert stage.search.bandwidths == {56: 10.0, 120: 10.0, 121: 10.0, 301: 10.0}
    assert all(w.bandwidth_mhz == 10.0 for w in results[-1].windows) and results[-1].frame is not None
    assert any(r.cells and r.frame is None for r in results)  # the first stacks, before the votes
    # a PCI the database gives two bandwidths (reused on two carriers) stays unknown, not learned
    reused = parse_tower_database({"name": "reused", "sites": [
        {"name": "A", "cells": [{"pci": 56, "earfcn": 2300, "bandwidth_mhz": 5}, {"pci": 301, "earfcn": 2000}]},
        {"name": "B", "cells": [{"pci": 56, "earfcn": 2000, "bandwidth_mhz": 20}]}]})
    assert reused.unsized_pcis() == {301} and reused.bandwidths() == {}
    careful = SyncStage(source.frontend, towers=reused)
    for chunk in source.chunks():
        careful.process(chunk)
    assert careful.search.bandwidths == {301: 10.0}
    off = SyncStage(source.frontend, SyncConfig(learn_bandwidths=False), towers)
    for chunk in source.chunks():
        off.process(chunk)
    assert off.search.bandwidths == {}

    cell = Emitter(CellConfig(pci=200, bandwidth_mhz=5, load=0.6), 2115e6, 1.0, 0.0, 0.0, "5 MHz")
    sim = EnvelopeSimulator([cell], FixedChannel([Paths([1e-6], [np.sqrt(10 ** ((-80 - 30) / 10))], [0.0])]),
                            FrontendConfig(), seed=8)
    narrow = SyncStage(FrontendConfig(), towers=parse_tower_database(
        {"name": "five", "sites": [{"name": "S", "cells": [{"pci": 200}, {"pci": 17}]}]}))
    for chunk in sim.stream(0.9, workers=2):
        narrow.process(chunk)
    assert narrow.search.bandwidths == {200: 5.0}


def test_an_iq_radios_passband_slices_a_cells_crs(templates):
    """An I/Q recording at 1.92 MS/s squared afterwards saw only the middle 1.92 MHz of a carrier:
    the CRS template there is the same for every carrier of 3 MHz or more (the CRS sequence is
    indexed from the carrier's centre), where the envelope detector's whole-carrier CRS differs."""
    iq = SyncTemplates(squared_iq_frontend(1.92e6))
    wide, wider = iq.crs_envelope(142, 10), iq.crs_envelope(142, 20)
    np.testing.assert_allclose(wide, wider, atol=1e-9 * np.abs(wide).max())
    assert np.corrcoef(templates.crs_envelope(142, 10), templates.crs_envelope(142, 20))[0, 1] < 0.9


def test_a_strong_cells_crs_is_modelled_at_the_bandwidth_the_database_gives(templates, strong_cell_frames):
    """Without one, the best-fitting of the six LTE bandwidths is the cell's (10 MHz); given
    one, the model is at that bandwidth only, even a wrong one (the database is believed)."""
    frames, code = strong_cell_frames
    stacked = frames[:50].mean(axis=0)
    stacked -= stacked.mean()
    found = CellDetection(int(code), code - int(code), 456, (), 40.0, 10.0, 1.0)

    def model(bandwidths):
        return CellSearch(templates, SearchConfig(), [456, 457], bandwidths=bandwidths)._crs_model(stacked, found)

    def shape(bandwidth):
        start = code - sync_code_offset_seconds() * templates.sample_rate
        return scipy.fft.irfft(scipy.fft.rfft(templates.crs_envelope(456, bandwidth))
                               * np.exp(-2j * np.pi * scipy.fft.rfftfreq(FRAME) * start), FRAME)

    for bandwidths, expected in ((None, 10), ({456: 10.0}, 10), ({456: 5.0}, 5), ({457: 5.0}, 10)):
        fitted = model(bandwidths)
        assert np.corrcoef(fitted, shape(expected))[0, 1] > 0.999, (bandwidths, expected)


def test_a_strong_cells_crs_does_not_pass_for_other_cells_over_long_stacks(templates, strong_cell_frames):
    """Stacking averages the data away but not the CRS: without its cancellation, database
    PCIs' codes match parts of it; with it, the one cell on the air is all that is found."""
    frames, code = strong_cell_frames
    rng = np.random.default_rng(4)
    database = [456, *rng.choice(np.setdiff1d(np.arange(504), [456]), 19, replace=False).tolist()]
    false = {}
    for z in (0.0, SearchConfig().crs_cancel_z):
        search = CellSearch(templates, SearchConfig(crs_cancel_z=z), database)
        found = [search.search(frames[k : k + 50].mean(axis=0)) for k in range(0, 51, 10)]
        assert all(any(d.pci == 456 and abs((d.frame_offset + d.fraction - code + FRAME / 2) % FRAME - FRAME / 2) <= 1
                       for d in cells) for cells in found)
        false[z] = sum(d.pci != 456 for cells in found for d in cells)
    assert false[0.0] >= 3 and false[SearchConfig().crs_cancel_z] == 0, false
