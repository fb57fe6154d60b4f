"""Bad input, recordings (raw files, SigMF): one file of the bad-input matrix (``test/test_bad_input_*.py``;
the module docstring of ``test_bad_input_streams.py`` explains its outcome classes).

Recording metadata that moves samples (a SigMF capture after a dropout, captures out of order or
beyond the data) is honoured or refused, never ignored; an archive streams, whatever its
compression and size.
"""

from __future__ import annotations

import io
import json
import subprocess
from dataclasses import replace
import sys
import tarfile
from pathlib import Path

import numpy as np
import pytest

from deepsync.sources import BagSource, SigmfSource, open_source
from deepsync.sync.stacking import SERVED_RATES_HZ
from deepsync.types import HealthKind

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "campus"
TOWERS = REPO / "config" / "towers" / "campus.yaml"
RATE = 1.92e6
FRAME = 19200
T0 = "2026-01-01T00:00:00.000000Z"
T0_NS = 1_767_225_600 * 10**9
# a child's own peak resident memory (kB): its VmHWM, which exec starts afresh (ru_maxrss keeps
# the forking parent's, here the test run's)
PEAK_KB = ("peak = next(int(line.split()[1]) for line in open('/proc/self/status') "
           "if line.startswith('VmHWM:'))")


def samples_and_peak_kb(source: str) -> tuple[int, int]:
    """A ``deepsync.sources`` source opened (and its length counted) in a fresh interpreter: its
    sample count and the process's peak resident memory in kB."""
    probe = f"from deepsync.sources import *; s = {source}; {PEAK_KB}; print(s.n_samples, peak)"
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    samples, peak_kb = map(int, run.stdout.split())
    return samples, peak_kb


def campus_codes(frames: int = 60) -> tuple[np.ndarray, int]:
    """The campus bag's first ``frames`` frames of ADC codes, and the stamp of its first sample."""
    chunks = [c for c, _ in zip(BagSource(BAG).chunks(), range(frames))]
    return np.concatenate([c.samples for c in chunks]), chunks[0].stamp_ns


def write_sigmf(path: Path, codes: np.ndarray, captures: list[dict], **global_info) -> Path:
    """``path``.sigmf-meta / -data: ``codes`` as an ri16_le envelope with these captures."""
    meta = {"global": {"core:datatype": "ri16_le", "core:sample_rate": RATE, "core:version": "1.0.0", **global_info},
            "captures": captures, "annotations": []}
    path.with_suffix(".sigmf-data").write_bytes(codes.astype("<i2").tobytes())
    path.with_suffix(".sigmf-meta").write_text(json.dumps(meta))
    return path.with_suffix(".sigmf-meta")


def iso(ns: int) -> str:
    seconds, fraction = divmod(ns, 10**9)
    from datetime import datetime, timezone

    return datetime.fromtimestamp(seconds, timezone.utc).strftime("%Y-%m-%dT%H:%M:%S") + f".{fraction:09d}Z"


@pytest.mark.parametrize("mark", ["datetime", "global_index", "both"])
def test_a_capture_after_a_dropout_moves_the_stream_on_by_what_was_lost(tmp_path, mark):
    """5000 samples lost after 20 frames, the second capture saying so: on main it was ignored
    (no gap, every later arrival and stamp 5000 samples early, exit 0). Now the stream jumps by
    the samples lost, stamps and all, exactly as the unbroken recording had them."""
    codes, stamp = campus_codes()
    cut, lost = 20 * FRAME, 5000
    kept = np.concatenate([codes[:cut], codes[cut + lost:]])
    second: dict = {"core:sample_start": cut}
    first: dict = {"core:sample_start": 0, "core:datetime": iso(stamp)}
    if mark in ("datetime", "both"):
        second["core:datetime"] = iso(stamp + round((cut + lost) * 1e9 / RATE))
    if mark in ("global_index", "both"):
        first["core:global_index"], second["core:global_index"] = 0, cut + lost
    source = SigmfSource(write_sigmf(tmp_path / "dropout", kept, [first, second]))
    assert "1 dropout(s) losing 5000 samples" in source.description
    chunks = list(source.chunks())
    assert sum(len(c.samples) for c in chunks) == len(kept)
    for chunk in chunks:  # every sample at its place in the unbroken stream, at its time
        end = chunk.first_sample_index + len(chunk.samples)
        assert not (cut <= chunk.first_sample_index < cut + lost)
        np.testing.assert_array_equal(chunk.samples, codes[chunk.first_sample_index:end])
        assert abs(chunk.stamp_ns - (stamp + chunk.first_sample_index * 1e9 / RATE)) < 1.0
    from deepsync.pipeline import Pipeline, PipelineConfig
    from deepsync.towers import load_tower_database

    pipeline = Pipeline(source.frontend, PipelineConfig().with_choices(10), load_tower_database(TOWERS))
    events = [h.kind for c in chunks for r in pipeline.process(c) for h in r.health]
    assert events.count(HealthKind.GAP) == 1


@pytest.mark.parametrize("captures, message", [
    ([{"core:sample_start": 0}, {"core:sample_start": 0}], "the capture at sample 0 follows the one at sample 0"),
    ([{"core:sample_start": 100}, {"core:sample_start": 50}], "the capture at sample 50 follows the one at sample 100"),
    ([{"core:sample_start": 0}, {"core:sample_start": 10**6}], "the capture at sample 1000000 lies beyond the dataset's"),
    ([{"core:sample_start": 0, "core:global_index": 500}, {"core:sample_start": 100, "core:global_index": 550}],
     "core:global_index 550 is 50 samples behind"),
    ([{"core:sample_start": 0, "core:datetime": T0}, {"core:sample_start": 19200, "core:datetime": T0}],
     "earlier than the samples recorded before it take: the clock goes back"),
    ([{"core:sample_start": 0, "core:datetime": T0, "core:global_index": 0},
      {"core:sample_start": 19200, "core:datetime": "2026-01-01T00:00:00.020000Z", "core:global_index": 19200}],
     "its core:datetime and core:global_index disagree by +19200 samples"),
    ([{"core:sample_start": 0, "core:header_bytes": 4}], "has header bytes inside the dataset"),
    ([{"core:sample_start": 5}], "lies before the dataset's first sample (core:offset 10)"),
    ([{"core:sample_start": -5}], "core:sample_start -5 is not a sample index"),
], ids=["twice", "unordered", "beyond-the-data", "count-goes-back", "clock-goes-back", "count-and-clock-disagree",
        "header-bytes-in-a-conforming-dataset", "before-core-offset", "negative"])
def test_captures_that_cannot_describe_the_samples_are_refused_naming_the_capture(tmp_path, captures, message):
    """On main unordered captures and a sample_start beyond the data were accepted."""
    extra = {"core:offset": 10} if "core:offset" in message else {}
    path = write_sigmf(tmp_path / "odd", np.zeros(50_000, np.int16), captures, **extra)
    with pytest.raises(ValueError) as error:
        SigmfSource(path)
    assert message in str(error.value) and str(path) in str(error.value)


def test_a_recording_distributed_without_its_samples_is_refused(tmp_path):
    path = write_sigmf(tmp_path / "empty", np.zeros(100, np.int16), [{"core:sample_start": 0}],
                       **{"core:metadata_only": True})
    with pytest.raises(ValueError, match="core:metadata_only"):
        SigmfSource(path)


def test_contiguous_captures_with_datetimes_keep_one_unbroken_stream(tmp_path):
    """Datetimes within their written precision and a receiver clock's 100 ppm of the samples
    between them are no dropout: the file is one segment, its stamps from the first datetime."""
    captures = [{"core:sample_start": 0, "core:datetime": "2026-01-01T00:00:00.000Z"},
                {"core:sample_start": 19200, "core:datetime": "2026-01-01T00:00:00.010Z"},
                {"core:sample_start": 38400, "core:datetime": "2026-01-01T00:00:00.021Z"}]  # 1 ms late: the precision
    source = SigmfSource(write_sigmf(tmp_path / "ok", np.zeros(60_000, np.int16), captures))
    assert len(source.segments) == 1 and source.segments[0].stamp_ns == T0_NS
    assert [c.first_sample_index for c in source.chunks()] == [0, 19200, 38400, 57600]


# -- archives stream --------------------------------------------------------------------------


class _Zeros(io.RawIOBase):
    def __init__(self, n: int) -> None:
        self.left = n

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        n = min(len(buffer), self.left)
        buffer[:n] = bytes(n)
        self.left -= n
        return n


def write_archive(path: Path, mode: str, data: bytes | int, **global_info) -> Path:
    """A SigMF archive (``mode``: tarfile's "w", "w:gz", "w:xz") of ri16_le ``data`` (bytes, or
    that many zero bytes streamed in)."""
    meta = json.dumps({"global": {"core:datatype": "ri16_le", "core:sample_rate": RATE, "core:version": "1.0.0",
                                  **global_info}, "captures": [{"core:sample_start": 0}], "annotations": []}).encode()
    with tarfile.open(path, mode) as tar:
        info = tarfile.TarInfo("rec/rec.sigmf-meta")
        info.size = len(meta)
        tar.addfile(info, io.BytesIO(meta))
        info = tarfile.TarInfo("rec/rec.sigmf-data")
        info.size = data if isinstance(data, int) else len(data)
        tar.addfile(info, io.BufferedReader(_Zeros(data), 1 << 20) if isinstance(data, int) else io.BytesIO(data))
    return path


@pytest.mark.parametrize("name, mode", [("plain.sigmf", "w"), ("gzip.sigmf.gz", "w:gz"), ("xz.sigmf.xz", "w:xz"),
                                        ("gzip-named-plain.sigmf", "w:gz")])
def test_an_archive_reads_like_its_files_whatever_its_compression(tmp_path, name, mode):
    import hashlib

    codes, _ = campus_codes(12)
    data = codes.astype("<i2").tobytes()
    files = write_sigmf(tmp_path / "files", codes, [{"core:sample_start": 0}])
    archive = write_archive(tmp_path / name, mode, data, **{"core:sha512": hashlib.sha512(data).hexdigest()})
    want = [(c.first_sample_index, c.samples.tobytes()) for c in SigmfSource(files).chunks()]
    assert [(c.first_sample_index, c.samples.tobytes()) for c in open_source(archive).chunks()] == want
    damaged = write_archive(tmp_path / f"damaged-{name}", mode, data[:-2] + b"\x01\x00",
                            **{"core:sha512": hashlib.sha512(data).hexdigest()})
    with pytest.raises(ValueError, match="SHA-512 does not match"):
        open_source(damaged)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads its peak memory from /proc")
def test_a_compressed_archive_streams_instead_of_being_read_into_memory(tmp_path):
    """A .sigmf.gz of 400 MB of zeros (about 2 MB of file): on main the sigmf package read the
    dataset into memory (5 GiB of zeros took 5.4 GB). Opening it here stays near the interpreter's
    own size: the dataset streams through a block at a time."""
    archive = write_archive(tmp_path / "zeros.sigmf.gz", "w:gz", 400 * 2**20)
    assert archive.stat().st_size < 5 * 2**20
    samples, peak_kb = samples_and_peak_kb(f"SigmfSource({str(archive)!r})")
    assert samples == 200 * 2**20
    assert peak_kb < 300 * 1024, f"{peak_kb / 1024:.0f} MB resident to open a 400 MB dataset"


@pytest.mark.parametrize("content, message", [
    (lambda p: p.write_bytes(b"not an archive at all"), "not a readable SigMF recording"),
    (lambda p: write_archive(p, "w:gz", 100)
     .write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]), "not a readable SigMF recording"),
], ids=["not-an-archive", "cut-short"])
def test_an_archive_that_is_none_or_cut_short_says_so(tmp_path, content, message):
    path = tmp_path / "odd.sigmf.gz"
    content(path)
    with pytest.raises(ValueError, match=message):
        list(open_source(path).chunks())


# -- sample rates: every rate accepted is served --------------------------------------------------

SCENARIO = REPO / "config" / "scenarios" / "campus.yaml"


def scenario_at(tmp_path: Path, rate: float) -> Path:
    text = SCENARIO.read_text()
    assert "\nfrontend: {rf_gain_db: 10.0}\n" in text
    path = tmp_path / f"campus_{rate:.0f}.yaml"
    path.write_text(text.replace("\nfrontend: {rf_gain_db: 10.0}\n",
                                 f"\nfrontend: {{rf_gain_db: 10.0, adc_rate_hz: {rate!r}}}\n"))
    return path


@pytest.mark.parametrize("rate", SERVED_RATES_HZ, ids=lambda rate: f"{rate / 1e6:g}MSps")
def test_every_served_rate_finds_and_times_the_campus_cells(tmp_path, rate):
    """The whole accepted set, simulated and searched: on main 30.72 / 9 MS/s was accepted and
    died mid-stream in the search (shapes (17068,) and (17067,)), 30.72 / 7 MS/s found none of
    the four cells and exited 0."""
    from deepsync.pipeline import Pipeline, PipelineConfig
    from deepsync.recording import record_scenario
    from deepsync.towers import load_tower_database

    bag = tmp_path / "bag"
    record_scenario(scenario_at(tmp_path, rate), 0.2, bag, workers=1, progress=False)
    source = BagSource(bag)
    assert source.frontend.adc_rate_hz == rate
    truth = source.truth_arrivals()
    config = PipelineConfig().with_choices(10)  # 10-frame stacks: two in 0.2 s
    config = replace(config, sync=replace(config.sync, confirm_stacks=1))
    pipeline = Pipeline(source.frontend, config, load_tower_database(TOWERS))
    timed = {}
    for chunk in source.chunks():
        for result in pipeline.process(chunk):
            for cell in result.arrivals.cells:
                timed[cell.pci] = min(abs(truth[cell.pci] - cell.toa)) if cell.pci in truth else np.inf
    assert len(set(timed) & {56, 120, 121, 301}) >= 3, timed
    assert all(error < 0.5 for error in timed.values()), timed


@pytest.mark.parametrize("divisor", [7, 9, 24, 32])
def test_a_rate_the_templates_take_but_the_search_cannot_serve_is_refused_at_the_door(tmp_path, divisor, capsys):
    """Rates dividing 30.72 MHz that split a half frame (7, 9) or alias the PSS envelope (24, 32:
    1.28 and 0.96 MS/s): simulate, a raw recording and the stages refuse them before any work."""
    from deepsync.cli import main
    from deepsync.frontend.config import FrontendConfig
    from deepsync.sync.stage import SyncStage

    rate = 30.72e6 / divisor
    assert main(["simulate", "--scenario", str(scenario_at(tmp_path, rate)), "--seconds", "0.1", "--out",
                 str(tmp_path / "bag"), "--quiet"]) == 2
    assert "the cell search serves 1.92, 2.048" in capsys.readouterr().err and not (tmp_path / "bag").exists()
    raw = tmp_path / "noise.cu8"
    raw.write_bytes(bytes(range(256)) * 100)
    assert main(["detect", "--input", str(raw), "--rate", repr(rate)]) == 2
    assert f"{raw}: sample rate {rate:g} Hz: the cell search serves" in capsys.readouterr().err
    with pytest.raises(ValueError, match="the cell search serves"):
        SyncStage(FrontendConfig(adc_rate_hz=rate, video_cutoff_hz=min(0.9e6, rate / 3)))


# -- long raw recordings ----------------------------------------------------------------------------


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads its peak memory from /proc")
def test_a_long_raw_recording_streams_in_bounded_memory(tmp_path):
    """A sparse 20 GB cu8 file grew the process to its size on main (a memory map keeps the
    pages it touched); here a 600 MB one is read whole (the scale pass) a block at a time."""
    path = tmp_path / "long.cu8"
    with open(path, "wb") as handle:
        handle.truncate(600 * 2**20)  # sparse: no disk used, every byte 0 when read
    samples, peak_kb = samples_and_peak_kb(f"RawFileSource({str(path)!r}, 'cu8', 1.92e6)")
    assert samples == 300 * 2**20
    assert peak_kb < 350 * 1024, f"{peak_kb / 1024:.0f} MB resident to read a 600 MB recording"


def test_a_silent_recording_says_so_once_not_once_a_stack(tmp_path, capsys):
    """A silent ri16 file printed 56,000 identical no_signal lines on main."""
    from deepsync.cli import main

    path = tmp_path / "silent.ri16"
    np.zeros(FRAME * 300, np.int16).tofile(path)
    assert main(["detect", "--input", str(path), "--rate", "1.92e6"]) == 0
    out = capsys.readouterr().out
    assert out.count("the stacked frame holds one value") == 1 and "... 29 more stack(s) like it, to 2.900 s" in out
