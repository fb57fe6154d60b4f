"""deepsync.sources: every recording a user may have, as envelope chunks under one stated rule."""

import io
import json
import math
import platform
import sys
from pathlib import Path

import numpy as np
import pytest
import sigmf

from deepsync.bag import ENVELOPE_TOPIC, PROVENANCE_KEY, TRUTH_CELL_TIMING_TOPIC, BagReader, BagWriter
from deepsync.bag import cell_timing_array_from_msg
from deepsync.frontend.config import FrontendConfig
from deepsync.sources import (
    BagSource,
    RawFileSource,
    SampleFormat,
    SigmfSource,
    SimulatorSource,
    Source,
    bag_frontend,
    envelope_codes,
    open_source,
    read_iq,
    squared_iq_frontend,
)
from deepsync.sync.stage import SyncConfig, SyncStage
from deepsync.towers import load_tower_database
from deepsync.types import EnvelopeChunk, HealthKind

FS = 1.92e6
FRAME = 19200
REPO = Path(__file__).resolve().parents[1]
REAL = REPO.parent / "shared" / "data" / "real_lte" / "f1860_s1.92_g0_1s_strong_rtlsdr.bin"
TOWERS = REPO / "config" / "towers" / "real_lte_1860.yaml"
CAMPUS = REPO / "bags" / "campus"

needs_real = pytest.mark.skipif(not REAL.is_file(), reason=f"real RTL-SDR recording not present at {REAL} (test data)")

EXTENSION = {"cu8": ".cu8", "ci8": ".cs8", "ci16_le": ".cs16", "cf32_le": ".cf32", "ri16_le": ".ri16", "rf32_le": ".f32"}
DTYPE = {"cu8": "u1", "ci8": "i1", "ci16_le": "<i2", "cf32_le": "<f4", "ri16_le": "<i2", "rf32_le": "<f4"}
RAILS = {"cu8": (0, 255), "ci8": (-128, 127), "ci16_le": (-32768, 32767), "ri16_le": (-32768, 32767)}


def synthetic(name: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """Stored values (interleaved for I/Q) of a noisy recording in format ``name``, with a few
    samples at the rails for integer formats."""
    complex_ = name.startswith("c")
    values = rng.standard_normal(n * (2 if complex_ else 1))
    if name == "cu8":
        stored = np.clip(np.rint(127.5 + 30 * values), 0, 255)
    elif name == "ci8":
        stored = np.clip(np.rint(30 * values), -128, 127)
    elif name in ("ci16_le", "ri16_le"):
        stored = np.clip(np.rint(6000 * values), -32768, 32767)
    else:
        stored = 0.25 * values
    stored = stored.astype(DTYPE[name])
    if name in RAILS:
        low, high = RAILS[name]
        stored[7] = high  # a few samples clipped in the recording, at either rail
        stored[1001] = low
    return stored


def expected_codes(name: str, stored: np.ndarray) -> tuple[np.ndarray, float]:
    """The documented rule, written out independently of the package: (codes, scale)."""
    x = stored.astype(np.float64)
    if name.startswith("c"):
        x = x.reshape(-1, 2) - (127.5 if name == "cu8" else 0.0)
        envelope = x[:, 0] ** 2 + x[:, 1] ** 2
        comps = stored.reshape(-1, 2)
    else:
        envelope = x
        comps = stored.reshape(-1, 1)
    clipped = np.zeros(len(envelope), bool)
    if name in RAILS:
        clipped = np.any((comps == RAILS[name][0]) | (comps == RAILS[name][1]), axis=1)
    if name == "ri16_le":
        scale = 1.0
    else:
        scale = np.max(np.abs(envelope[~clipped])) / 32766
    codes = np.rint(envelope / scale)
    if name.startswith("c"):
        codes[clipped] = 32767
    return codes.astype(np.int16), scale


def check_stream(chunks: list[EnvelopeChunk], rate: float, n: int, stamp_ns: int = 0) -> np.ndarray:
    """Contiguous indices from 0, stamps at the rate, one frame per chunk; the codes."""
    frame = round(rate * 10e-3)
    assert [c.first_sample_index for c in chunks] == list(range(0, n, frame))
    assert [len(c.samples) for c in chunks[:-1]] == [frame] * (len(chunks) - 1)
    assert chunks[-1].end_sample_index == n
    for c in chunks:
        assert c.stamp_ns == stamp_ns + round(c.first_sample_index * 1e9 / rate)
        assert c.sample_rate == rate and c.adc_bits == 16 and c.samples.dtype == np.int16
    return np.concatenate([c.samples for c in chunks])


# --------------------------------------------------------------------------- formats


@pytest.mark.parametrize("name", [f.value for f in SampleFormat])
def test_each_format_gives_the_stated_codes(tmp_path, name):
    n = 2 * FRAME + 777  # the last chunk is short
    stored = synthetic(name, n, np.random.default_rng(len(name)))
    path = tmp_path / f"rec{EXTENSION[name]}"
    stored.tofile(path)

    source = open_source(path, sample_rate=FS)  # the format from the extension

    assert isinstance(source, RawFileSource) and isinstance(source, Source)
    assert source.sample_format is SampleFormat(name) and source.n_samples == n
    codes, scale = expected_codes(name, stored)
    assert source.scale == pytest.approx(scale, rel=1e-12)
    chunks = list(source.chunks())
    got = check_stream(chunks, FS, n)
    np.testing.assert_array_equal(got, codes)
    assert all(c.volts_per_code == source.scale for c in chunks)
    if name != "ri16_le":  # the peak unclipped sample sits at 32766, clipped ones at the rail
        clipped = got == 32767
        assert np.max(np.abs(got[~clipped])) == 32766
    if name.startswith("c") and name in RAILS:
        assert got[7 // 2] == got[1001 // 2] == 32767  # the samples whose I or Q was set to a rail
    if name == "ri16_le":  # ADC codes pass unchanged, rails included
        np.testing.assert_array_equal(got, stored)
    expected_frontend = squared_iq_frontend(FS) if name.startswith("c") else FrontendConfig(adc_rate_hz=FS)
    assert source.frontend == expected_frontend
    assert source.center_hz is None
    # chunks() starts over on every call
    assert [c.first_sample_index for c in source.chunks()] == [c.first_sample_index for c in chunks]


def test_other_rates_keep_one_frame_per_chunk_and_exact_stamps(tmp_path):
    rate, n = 3.84e6, 3 * 38400 + 5
    stored = synthetic("ci16_le", n, np.random.default_rng(3))
    path = tmp_path / "usrp.bin"
    stored.tofile(path)
    start = 1_767_225_600 * 10**9 + 123
    source = RawFileSource(path, "ci16_le", rate, stamp_ns=start)
    chunks = list(source.chunks())
    check_stream(chunks, rate, n, stamp_ns=start)
    assert len(chunks[0].samples) == 38400 and chunks[1].stamp_ns == start + 10_000_000
    assert source.frontend.adc_rate_hz == rate


def test_a_given_scale_overrides_and_saturates_at_the_rail(tmp_path):
    stored = np.array([127, 128, 137, 118, 255, 128, 227, 27], np.uint8)  # |x|^2: 0.5, 180.5, clipped, 20000.5
    path = tmp_path / "x.cu8"
    stored.tofile(path)
    (chunk,) = RawFileSource(path, "cu8", FS, scale=0.5).chunks()
    np.testing.assert_array_equal(chunk.samples, [1, 361, 32767, 32767])  # 40001 saturates
    assert chunk.volts_per_code == 0.5
    (chunk,) = RawFileSource(path, "cu8", FS).chunks()
    assert chunk.volts_per_code == 20000.5 / 32766
    assert chunk.samples.tolist() == [1, round(180.5 / 20000.5 * 32766), 32767, 32766]  # 0.82 -> 1


def test_a_recording_using_the_full_8bit_range_fits(tmp_path):
    """|x|^2 of 8-bit I/Q reaches 2 * 127.5^2; a fixed scale of 0.5 overflowed int16 there."""
    grid = np.arange(256, dtype=np.uint8)
    stored = np.stack(np.meshgrid(grid, grid), axis=-1).reshape(-1)  # every (I, Q) pair
    path = tmp_path / "full.cu8"
    stored.tofile(path)
    source = RawFileSource(path, "cu8", FS)
    assert source.scale == pytest.approx(2 * 126.5**2 / 32766)  # (1, 1) and (254, 254): the largest unclipped
    codes = np.concatenate([c.samples for c in source.chunks()])
    comps = stored.reshape(-1, 2)
    rail = (comps == 0) | (comps == 255)
    assert np.all(codes[rail.any(axis=1)] == 32767)
    assert codes[~rail.any(axis=1)].max() == 32766
    assert codes.min() == 1  # (127, 128) and the like: |x|^2 = 0.5, just over half a code


def test_the_envelope_is_blind_to_carrier_frequency_offset(tmp_path):
    """The LO's offset and phase multiply x by a unit phasor: |x|^2 does not see them."""
    rng = np.random.default_rng(8)
    x = (rng.standard_normal(FRAME) + 1j * rng.standard_normal(FRAME)) * 20
    rotated = x * np.exp(2j * np.pi * (41_777.0 * np.arange(FRAME) / FS + 1.0))
    assert np.max(np.abs(rotated.real - x.real)) > 20  # the samples themselves differ a lot
    paths = []
    for name, y in (("plain", x), ("cfo", rotated)):
        paths.append(tmp_path / f"{name}.cf32")
        y.astype(np.complex64).tofile(paths[-1])
    a, b = (np.concatenate([c.samples for c in RawFileSource(p, "cf32_le", FS, scale=0.1).chunks()]) for p in paths)
    assert np.max(np.abs(a.astype(int) - b)) <= 1  # float32 storage: at most one code at a rounding edge
    assert np.mean(a == b) > 0.99


def test_envelope_codes_is_the_rule_on_stored_values():
    stored = np.array([0, 255, 127, 128, 200, 10], np.uint8)
    np.testing.assert_array_equal(envelope_codes(stored, "cu8", 2.0), [32767, 0, round((72.5**2 + 117.5**2) / 2)])
    np.testing.assert_array_equal(envelope_codes(np.array([-128, 5, 3, 4], np.int8), "ci8", 1.0), [32767, 25])
    np.testing.assert_array_equal(envelope_codes(np.array([-2.4, 7.0], np.float32), "rf32_le", 2.0), [-1, 4])


# --------------------------------------------------------------------------- format names


def test_format_names_and_extensions():
    assert SampleFormat.parse("CU8") is SampleFormat.CU8 and SampleFormat.parse("cf32_le") is SampleFormat.CF32_LE
    for ext, name in [(".cu8", "cu8"), (".cs8", "ci8"), (".ci8", "ci8"), (".cs16", "ci16_le"), (".ci16", "ci16_le"),
                      (".cf32", "cf32_le"), (".cfile", "cf32_le"), (".fc32", "cf32_le"), (".ri16", "ri16_le"),
                      (".rf32", "rf32_le"), (".F32", "rf32_le")]:
        assert SampleFormat.from_extension(f"/data/rec{ext}") is SampleFormat(name)
    for ambiguous in ("capture.bin", "capture.raw", "capture"):
        with pytest.raises(ValueError, match=f"cannot tell the sample format of {ambiguous} from its extension; "
                                             "give one of cu8, ci8, ci16_le, cf32_le, ri16_le, rf32_le"):
            SampleFormat.from_extension(ambiguous)
    with pytest.raises(ValueError, match="unknown sample format 'cs8'; give one of cu8, ci8, ci16_le"):
        SampleFormat.parse("cs8")
    assert SampleFormat.CU8.rails == (0, 255) and SampleFormat.CI8.rails == (-128, 127)
    assert SampleFormat.CF32_LE.rails is None and SampleFormat.CU8.zero == 127.5 and SampleFormat.CI8.zero == 0


# --------------------------------------------------------------------------- read_iq


def test_read_iq_reads_interleaved_samples_centred(tmp_path):
    path = tmp_path / "capture.bin"
    path.write_bytes(bytes([0, 255, 127, 128, 200, 10]))
    x = read_iq(path, "cu8")
    assert x.dtype == np.complex64
    np.testing.assert_array_equal(x, [-127.5 + 127.5j, -0.5 + 0.5j, 72.5 - 117.5j])
    np.testing.assert_array_equal(read_iq(path, "ci8"), [0 - 1j, 127 - 128j, -56 + 10j])  # the same bytes, signed
    cs16 = tmp_path / "x.cs16"
    np.array([1, -2, 300, 4], "<i2").tofile(cs16)
    np.testing.assert_array_equal(read_iq(cs16), [1 - 2j, 300 + 4j])


def test_read_iq_refuses_odd_length_missing_and_real_files(tmp_path):
    odd = tmp_path / "odd.bin"
    odd.write_bytes(bytes(7))
    with pytest.raises(ValueError, match="odd.bin: 7 bytes is not a whole number of cu8 samples"):
        read_iq(odd, "cu8")
    with pytest.raises(ValueError, match="nothere.bin: no such file"):
        read_iq(tmp_path / "nothere.bin", "cu8")
    env = tmp_path / "env.ri16"
    np.zeros(4, "<i2").tofile(env)
    with pytest.raises(ValueError, match="ri16_le is a real envelope format"):
        read_iq(env)


# --------------------------------------------------------------------------- the real recording


def _named_cells(source: Source) -> set[int]:
    stage = SyncStage(source.frontend, SyncConfig(), load_tower_database(TOWERS))
    return {cell.pci for chunk in source.chunks() for result in stage.process(chunk) for cell in result.cells}


@pytest.fixture(scope="module")
def real_cells():
    if not REAL.is_file():
        pytest.skip(f"real RTL-SDR recording not present at {REAL} (test data)")
    return _named_cells(RawFileSource(REAL, "cu8", FS))


@needs_real
def test_real_recording_names_its_two_cells(real_cells):
    assert real_cells == {142, 86}  # the recording author's own cell-search result


@needs_real
def test_real_recording_scaled_to_the_full_8bit_range_names_the_same_cells(tmp_path, real_cells):
    raw = np.fromfile(REAL, np.uint8).astype(np.float64)
    loud = np.clip(np.rint(127.5 + 16 * (raw - 127.5)), 0, 255).astype(np.uint8)
    assert loud.min() < 10 and loud.max() > 245  # nearly the whole 8-bit range
    path = tmp_path / "loud.cu8"
    loud.tofile(path)
    source = open_source(path, sample_rate=FS)
    assert source.frontend == squared_iq_frontend(FS)
    assert _named_cells(source) == real_cells == {142, 86}


@needs_real
def test_real_recording_as_sigmf_names_the_same_cells(tmp_path, real_cells):
    meta = sigmf.SigMFFile(global_info={"core:datatype": "cu8", "core:sample_rate": 1.92e6,
                                        "core:description": "RTL-SDR, band 3"})
    meta.set_data_file(data_buffer=io.BytesIO(REAL.read_bytes()))
    meta.add_capture(0, metadata={"core:frequency": 1860e6, "core:datetime": "2026-01-01T00:00:01.000000250Z"})
    meta.tofile(tmp_path / "real")  # real.sigmf-meta + real.sigmf-data, by the sigmf package

    source = open_source(tmp_path / "real.sigmf-meta")

    assert isinstance(source, SigmfSource) and source.sample_format is SampleFormat.CU8
    assert source.frontend.adc_rate_hz == 1.92e6 and source.center_hz == 1860e6
    assert source.stamp_ns == 1_767_225_601 * 10**9 + 250
    first = next(source.chunks())
    assert first.stamp_ns == source.stamp_ns and len(first.samples) == FRAME
    assert _named_cells(source) == real_cells


# --------------------------------------------------------------------------- clipping


def test_clipped_samples_sit_at_the_rail_and_the_stage_flags_them(tmp_path):
    rng = np.random.default_rng(5)
    n = 10 * FRAME
    stored = np.clip(np.rint(127.5 + 20 * rng.standard_normal(2 * n)), 1, 254).astype(np.uint8)
    comps = stored.reshape(-1, 2)
    clipped = np.zeros(n, bool)
    clipped[::3] = True  # a third of the samples: one component at a rail, either one
    comps[0::6, 0] = 255
    comps[3::6, 1] = 0
    path = tmp_path / "hot.cu8"
    stored.tofile(path)

    source = RawFileSource(path, "cu8", FS)
    stage = SyncStage(source.frontend, SyncConfig(), load_tower_database(TOWERS))
    results, codes = [], []
    for chunk in source.chunks():
        codes.append(chunk.samples)
        results += stage.process(chunk)
    codes = np.concatenate(codes)

    assert np.all(codes[clipped] == 32767)
    assert codes[~clipped].max() == 32766  # nothing unclipped reaches the rail
    assert len(results) == 1
    assert HealthKind.CLIPPED in [f.kind for f in results[0].flags], results[0].flags


# --------------------------------------------------------------------------- SigMF


def _write_sigmf(tmp_path: Path, name: str, stored: np.ndarray, datatype: str, rate: float = FS,
                 channels: int | None = None, **capture) -> sigmf.SigMFFile:
    info = {"core:datatype": datatype, "core:sample_rate": rate}
    if channels is not None:
        info["core:num_channels"] = channels
    meta = sigmf.SigMFFile(global_info=info)
    meta.set_data_file(data_buffer=io.BytesIO(stored.tobytes()))
    meta.add_capture(0, metadata=capture or None)
    meta.tofile(tmp_path / name, skip_validate=True)
    return meta


@pytest.mark.parametrize("name", ["ci8", "cf32_le", "rf32_le"])
def test_sigmf_meta_data_and_archive_read_like_the_raw_file(tmp_path, name):
    n = FRAME + 100
    stored = synthetic(name, n, np.random.default_rng(9))
    raw = tmp_path / f"rec{EXTENSION[name]}"
    stored.tofile(raw)
    expected = [c.samples for c in RawFileSource(raw, name, 3.84e6).chunks()]
    _write_sigmf(tmp_path, "rec", stored, name, rate=3.84e6)
    _write_sigmf(tmp_path, "arc.sigmf", stored, name, rate=3.84e6)
    for path in ("rec.sigmf-meta", "rec.sigmf-data", "arc.sigmf"):
        source = open_source(tmp_path / path)
        assert isinstance(source, SigmfSource)
        assert source.sample_rate == 3.84e6 and source.center_hz is None and source.stamp_ns == 0
        got = list(source.chunks())
        check_stream(got, 3.84e6, n)
        for a, b in zip(got, expected, strict=True):
            np.testing.assert_array_equal(a.samples, b)


def test_sigmf_refuses_what_it_cannot_stream(tmp_path):
    stored = np.arange(64, dtype="<i4")
    _write_sigmf(tmp_path, "wide", stored, "ci32_le")
    with pytest.raises(ValueError, match=r"wide.sigmf-meta: core:datatype 'ci32_le': not one of the supported.*cu8, ci8"):
        SigmfSource(tmp_path / "wide.sigmf-meta")
    _write_sigmf(tmp_path, "big", stored.astype(">i2"), "ci16_be")
    with pytest.raises(ValueError, match="big-endian"):
        SigmfSource(tmp_path / "big.sigmf-meta")
    _write_sigmf(tmp_path, "two", np.zeros(64, np.int8), "ci8", channels=2)
    with pytest.raises(ValueError, match=r"two.sigmf-meta: 2 channels \(core:num_channels\)"):
        SigmfSource(tmp_path / "two.sigmf-meta")
    _write_sigmf(tmp_path, "ok", np.zeros(64, np.int8), "ci8", rate=1.92e6)
    with pytest.raises(ValueError, match=r"ok.sigmf-meta: sample rate 3.84e\+06 Hz given, but the metadata says 1.92e\+06"):
        open_source(tmp_path / "ok.sigmf-meta", sample_rate=3.84e6)
    assert open_source(tmp_path / "ok.sigmf-meta", sample_rate=1.92e6).sample_rate == 1.92e6
    _write_sigmf(tmp_path, "fast", np.zeros(64, np.int8), "ci8", rate=2.4e6)
    with pytest.raises(ValueError, match=r"fast.sigmf-meta: sample rate 2.4e\+06 Hz"):
        SigmfSource(tmp_path / "fast.sigmf-meta")
    with pytest.raises(ValueError, match="gone.sigmf-meta: no such file"):
        SigmfSource(tmp_path / "gone.sigmf-meta")
    _write_sigmf(tmp_path, "empty", np.zeros(0, np.int8), "ci8")
    with pytest.raises(ValueError, match="empty.sigmf-meta: the dataset empty.sigmf-data is empty"):
        SigmfSource(tmp_path / "empty.sigmf-meta")
    _write_sigmf(tmp_path, "cut", np.zeros(64, np.int8), "ci8")
    meta = json.loads((tmp_path / "cut.sigmf-meta").read_text())
    del meta["global"]["core:sha512"]  # so that the truncation, not the checksum, is what is found
    (tmp_path / "cut.sigmf-meta").write_text(json.dumps(meta))
    (tmp_path / "cut.sigmf-data").write_bytes(bytes(63))
    with pytest.raises(ValueError, match=r"cut.sigmf-meta: the dataset \(63 bytes\) is not a whole number of samples"):
        SigmfSource(tmp_path / "cut.sigmf-meta")
    _write_sigmf(tmp_path, "tampered", np.zeros(64, np.int8), "ci8")
    (tmp_path / "tampered.sigmf-data").write_bytes(bytes(63) + b"\x01")
    with pytest.raises(ValueError, match="tampered.sigmf-meta: not a readable SigMF recording: .*hash"):
        SigmfSource(tmp_path / "tampered.sigmf-meta")
    _write_sigmf(tmp_path, "when", np.zeros(64, np.int8), "ci8", **{"core:datetime": "yesterday"})
    with pytest.raises(ValueError, match="when.sigmf-meta: the capture at sample 0: core:datetime 'yesterday' is not an ISO 8601"):
        SigmfSource(tmp_path / "when.sigmf-meta")
    retuned = _write_sigmf(tmp_path, "retune", np.zeros(64, np.int8), "ci8", **{"core:frequency": 1860e6})
    retuned.add_capture(16, metadata={"core:frequency": 2140e6})
    retuned.tofile(tmp_path / "retune", skip_validate=True, overwrite=True)
    with pytest.raises(ValueError, match="retune.sigmf-meta: the capture at sample 16 retunes"):
        SigmfSource(tmp_path / "retune.sigmf-meta")


# --------------------------------------------------------------------------- bags


@pytest.mark.parametrize("path", [CAMPUS, CAMPUS / "campus.mcap"], ids=["directory", "mcap"])
def test_bag_source_streams_the_recorded_envelope(path):
    source = open_source(path)
    assert isinstance(source, BagSource) and isinstance(source, Source)
    with BagReader(CAMPUS) as bag:
        recorded = FrontendConfig(**json.loads(bag.custom_data[PROVENANCE_KEY])["frontend"])
        count = bag.message_counts[ENVELOPE_TOPIC]
        every_toa: dict[int, list[float]] = {}
        for item in bag.messages([TRUTH_CELL_TIMING_TOPIC]):
            for record in cell_timing_array_from_msg(item.message).cells:
                every_toa.setdefault(record.pci, []).append(record.toa)
    assert source.frontend == recorded and recorded != FrontendConfig()  # the bag's own chain (10 dB LNA)
    indices = [c.first_sample_index for c in source.chunks()]
    assert len(indices) == count == 300 and indices == list(range(0, 300 * FRAME, FRAME))
    truth = source.truth_arrivals()
    assert set(truth) == {56, 120, 121, 301}
    assert all(truth[pci].tolist() == sorted(toas) for pci, toas in every_toa.items())
    assert all(0 <= toas[0] < FRAME and len(toas) == 300 for toas in truth.values())  # one a frame, from the first
    assert source.center_hz is None and "campus" in source.description


def test_a_bag_without_provenance_gets_the_default_chain_at_its_own_rate(tmp_path):
    out = tmp_path / "elsewhere"
    with BagWriter(out) as bag:
        for k in range(2):
            bag.write_envelope(EnvelopeChunk(stamp_ns=k * 10_000_000, sample_rate=3.84e6, first_sample_index=38400 * k,
                                             adc_bits=12, volts_per_code=2 / 4096, samples=np.zeros(38400, np.int16)))
    assert bag_frontend(out) == FrontendConfig(adc_rate_hz=3.84e6)
    source = BagSource(out)
    assert source.truth_arrivals() == {} and len(list(source.chunks())) == 2
    with pytest.raises(ValueError, match="sample rate 1.92e\\+06 Hz given, but the bag was recorded at 3.84e\\+06"):
        open_source(out, sample_rate=1.92e6)
    with pytest.raises(ValueError, match="a bag carries ADC codes"):
        open_source(out, sample_format="cu8")


# --------------------------------------------------------------------------- bad input


def test_bad_input_is_refused_with_the_file_and_the_cause(tmp_path):
    with pytest.raises(ValueError, match="missing.cu8: no such file"):
        open_source(tmp_path / "missing.cu8", sample_rate=FS)
    with pytest.raises(ValueError, match="missing.cu8: no such file"):
        RawFileSource(tmp_path / "missing.cu8", "cu8", FS)
    odd = tmp_path / "odd.cf32"
    odd.write_bytes(bytes(12))
    with pytest.raises(ValueError, match="odd.cf32: 12 bytes is not a whole number of cf32_le samples \\(8 bytes each\\)"):
        open_source(odd, sample_rate=FS)
    good = tmp_path / "capture.bin"
    good.write_bytes(bytes(range(200)))
    with pytest.raises(ValueError, match="unknown sample format 'rtlsdr'; give one of cu8"):
        open_source(good, "rtlsdr", FS)
    with pytest.raises(ValueError, match="cannot tell the sample format of .*capture.bin from its extension; give one of"):
        open_source(good, sample_rate=FS)
    with pytest.raises(ValueError, match="capture.bin: the sample rate must be given"):
        open_source(good, "cu8")
    with pytest.raises(ValueError, match=r"capture.bin: sample rate 2.4e\+06 Hz: sync templates need a rate that divides"):
        RawFileSource(good, "cu8", 2.4e6)
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="capture.bin: scale .* must be finite and > 0"):
            RawFileSource(good, "cu8", FS, scale=bad)
    empty = tmp_path / "empty.cs8"
    empty.write_bytes(b"")
    with pytest.raises(ValueError, match="empty.cs8: the file is empty"):
        open_source(empty, sample_rate=FS)
    with pytest.raises(ValueError, match="not a rosbag2 bag"):
        open_source(tmp_path)


@pytest.mark.parametrize("name", ["cf32_le", "rf32_le"])
def test_non_finite_samples_are_an_error_naming_the_file_and_the_sample(tmp_path, name):
    stored = synthetic(name, 2 * FRAME, np.random.default_rng(1))
    stored[(FRAME + 17) * (2 if name == "cf32_le" else 1)] = np.nan
    path = tmp_path / f"broken{EXTENSION[name]}"
    stored.tofile(path)
    with pytest.raises(ValueError, match=f"broken{EXTENSION[name]}: sample {FRAME + 17} is not finite"):
        RawFileSource(path, name, FS)  # the scale pass meets it before streaming
    source = RawFileSource(path, name, FS, scale=1e-3)  # no pass: the chunk that holds it says so
    chunks = source.chunks()
    assert next(chunks).end_sample_index == FRAME
    with pytest.raises(ValueError, match=f"sample {FRAME + 17} is not finite"):
        next(chunks)


def bag_reproduced_bit_for_bit() -> bool:
    """Where the bundled bags are reproduced bit for bit (README, docs/design/simulator.md): Linux on
    x86-64 with AVX2 and FMA, whose C math library (glibc's FMA variants) made them; numpy's and
    OpenBLAS's kernels do not matter (test_simulator_physics)."""
    from numpy.core._multiarray_umath import __cpu_features__

    return (sys.platform.startswith("linux") and platform.machine() == "x86_64"
            and bool(__cpu_features__.get("AVX2")) and bool(__cpu_features__.get("FMA3")))


def test_the_live_simulator_streams_what_the_recorded_bag_holds():
    """A scenario opened as a source is the simulator run live: its first frames are the campus
    bag's samples, stamps and indices exactly (same twin, seed and receiver clock epoch); on
    another CPU family or C library, a code at most one off now and then, where a sample sits
    on a rounding boundary."""
    live = open_source(REPO / "config" / "scenarios" / "campus.yaml")
    recorded = BagSource(REPO / "bags" / "campus")
    assert isinstance(live, SimulatorSource)
    assert live.frontend == recorded.frontend
    assert "campus" in live.description
    for got, want, _ in zip(live.chunks(), recorded.chunks(), range(3)):
        assert (got.stamp_ns, got.first_sample_index, got.sample_rate) == (
            want.stamp_ns, want.first_sample_index, want.sample_rate)
        if bag_reproduced_bit_for_bit():
            np.testing.assert_array_equal(got.samples, want.samples)
        else:
            off = np.abs(got.samples.astype(int) - want.samples)
            assert off.max() <= 1 and np.count_nonzero(off) <= 1e-3 * len(off)


@pytest.mark.parametrize("kwargs, message", [
    (dict(sample_format="cu8"), "does not apply"),
    (dict(sample_rate=2.4e6), "1.92e\\+06 Hz"),
])
def test_a_scenario_source_refuses_what_it_decides_itself(kwargs, message):
    with pytest.raises(ValueError, match=message):
        open_source(REPO / "config" / "scenarios" / "campus.yaml", **kwargs)


@pytest.mark.parametrize("edit, message", [
    (lambda meta: meta["global"].update({"core:datatype": 5}), "not a readable SigMF recording"),
    (lambda meta: meta.update({"global": [1]}), "not a readable SigMF recording"),
    (lambda meta: meta.update({"captures": "x"}), "not a readable SigMF recording"),
    ("no-data", "no dataset: no .sigmf-data file beside the metadata"),
    ("not-a-tar", "not a readable SigMF recording: file could not be opened successfully"),
], ids=["datatype-number", "global-list", "captures-text", "no-dataset", "archive-not-tar"])
def test_sigmf_metadata_of_another_shape_is_refused_in_one_line(tmp_path, edit, message):
    """Metadata whose fields have the wrong shape, a missing dataset, an archive that is none:
    ValueError naming the file (the sigmf package itself raises AttributeError and the like)."""
    _write_sigmf(tmp_path, "odd", np.zeros(64, np.int8), "ci8")
    path = tmp_path / "odd.sigmf-meta"
    if edit == "no-data":
        (tmp_path / "odd.sigmf-data").unlink()
    elif edit == "not-a-tar":
        path = tmp_path / "odd.sigmf"
        path.write_text("not a tar archive\n")
    else:
        meta = json.loads(path.read_text())
        meta["global"].pop("core:sha512", None)
        edit(meta)
        path.write_text(json.dumps(meta))
    with pytest.raises(ValueError) as error:
        SigmfSource(path)
    assert f"{path.name}: " in str(error.value) and message in str(error.value)
    assert "\n" not in str(error.value)
