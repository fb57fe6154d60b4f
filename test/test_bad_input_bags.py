"""Bad-input matrix: rosbag2 / MCAP bags (one file of ``test/test_bad_input_*.py``).

Issue "Nothing silent, nothing lost": every bad bag a user can hand DeepSync has one row here
that asserts its outcome class (the matrix's ``error`` / ``event`` / ``result``), one of

* **refused** (error): a :class:`~deepsync.bag.BagError` naming the file and the cause;
* **reported** (event): the correct result from the MCAP file, plus the disagreement as data
  (:attr:`BagReader.inconsistencies <deepsync.bag.BagReader.inconsistencies>`);
* **correct** (result): the same result as from the intact bag.

Never a different result without a word. This file covers rosbag2 / MCAP bags (corrupt bytes,
truncation, ``metadata.yaml`` that lies or is gone, foreign storage and types); later work
(fusion, nodes, replay) adds rows of its own in files of its own.
"""

from __future__ import annotations

import json
import random
import shutil
import sqlite3
import struct
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import yaml
from deepsync.bag import (
    ENVELOPE_TOPIC,
    PROVENANCE_KEY,
    TRUTH_POSE_TOPIC,
    BagError,
    BagReader,
    BagWriter,
    envelope_to_msg,
    pose_to_msg,
    read_envelope,
    read_messages,
    typestore,
)
from deepsync.bag.convert import ENVELOPE_SAMPLES
from deepsync.bag.reader import SalvageReader
from deepsync.frontend.config import FrontendConfig
from deepsync.sources import BagSource, bag_frontend, open_source
from deepsync.types import EnvelopeChunk
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapLibWriter
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer

FS = 1.92e6
T0 = 1_767_225_600 * 10**9
N_CHUNKS = 6
SAMPLES = 200_000  # 400 kB a message: the bag spans three MCAP chunks (rosbags closes one at 1 MiB)
RECORDED = FrontendConfig(rf_gain_db=10.0)  # not the default chain: provenance must be what decides
PROVENANCE = json.dumps({"generator": "test_bad_input_bags", "frontend": asdict(RECORDED)}, sort_keys=True)
MAGIC = b"\x89MCAP0\r\n"


def make_chunks(n: int = N_CHUNKS, size: int = SAMPLES, seed: int = 3) -> list[EnvelopeChunk]:
    rng = np.random.default_rng(seed)
    return [
        EnvelopeChunk(T0 + round(k * size / FS * 1e9), FS, k * size, 12, 2 / 4096,
                      rng.integers(-2048, 2048, size=size, dtype=np.int16))
        for k in range(n)
    ]


CHUNKS = make_chunks()


def write_bag(out: Path, chunks: list[EnvelopeChunk] = CHUNKS, provenance: str | None = PROVENANCE) -> Path:
    with BagWriter(out, provenance=provenance) as bag:
        for k, chunk in enumerate(chunks):
            bag.write_envelope(chunk)
            bag.write_truth_pose(chunk.stamp_ns, float(k), 2.0, 1.5)
    return out


def write_plain_rosbags_bag(out: Path, chunks: list[EnvelopeChunk] = CHUNKS) -> Path:
    """A bag as rosbags alone writes it (and DeepSync did before the CRCs): every CRC 0, no
    ``deepsync`` metadata record, the provenance only in custom data."""
    store = typestore()
    writer = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.set_custom_data(PROVENANCE_KEY, PROVENANCE)
    with writer:
        conn = writer.add_connection(ENVELOPE_TOPIC, ENVELOPE_SAMPLES, typestore=store)
        for chunk in chunks:
            writer.write(conn, chunk.stamp_ns, store.serialize_cdr(envelope_to_msg(chunk), ENVELOPE_SAMPLES))
    return out


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_bag(tmp_path_factory.mktemp("bags") / "good")


@pytest.fixture(scope="module")
def plain(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_plain_rosbags_bag(tmp_path_factory.mktemp("bags") / "plain")


def copy_bag(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for f in src.iterdir():
        (dst / f.name.replace(src.name, dst.name)).write_bytes(f.read_bytes())
    meta = dst / "metadata.yaml"
    if meta.exists():
        meta.write_text(meta.read_text().replace(f"{src.name}.mcap", f"{dst.name}.mcap"))
    return dst


def mcap_of(bag: Path) -> Path:
    return bag / f"{bag.name}.mcap"


def flip(path: Path, offset: int, mask: int = 0xFF) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= mask
    path.write_bytes(bytes(data))


def snapshot(bag: Path) -> tuple:
    """What a user gets from a bag: counts, provenance, the ADC stream and the truth."""
    with BagReader(bag) as reader:
        counts = reader.message_counts
        provenance = reader.provenance
        messages = [(m.topic, m.log_time_ns) for m in reader.messages()]
    samples = [(c.first_sample_index, c.samples.tobytes()) for c in read_envelope(bag)]
    return counts, provenance, messages, samples


def chunk_indexes(mcap: Path) -> list:
    with mcap.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)


def compressed_span(index) -> tuple[int, int]:
    """[start, end) of a chunk's compressed records in the file (after its 40-byte header)."""
    start = index.chunk_start_offset + 9 + 8 + 8 + 8 + 4 + 4 + len(index.compression) + 8
    return start, start + index.compressed_size


def footer(mcap: Path) -> tuple[int, int, int, int]:
    """(footer offset, summary_start, summary_offset_start, summary_crc)."""
    data = mcap.read_bytes()
    at = len(data) - 8 - 29
    return (at, *struct.unpack_from("<QQI", data, at + 9))


def summary_records(mcap: Path) -> list[tuple[int, int, int]]:
    """(offset, opcode, body length) of the summary section's records (offsets included)."""
    data = mcap.read_bytes()
    end, start, _, _ = footer(mcap)
    records, at = [], start
    while at < end:
        op, length = data[at], struct.unpack_from("<Q", data, at + 1)[0]
        records.append((at, op, length))
        at += 9 + length
    return records


def edit_metadata(bag: Path, edit) -> None:
    meta = bag / "metadata.yaml"
    info = yaml.safe_load(meta.read_text())
    edit(info["rosbag2_bagfile_information"])
    meta.write_text(yaml.safe_dump(info))


# -- corrupt bytes: refused, naming the file and the place -----------------------------------


@pytest.mark.parametrize(
    ("chunk", "where"),
    [(0, "crc"), (0, "first"), (0, "middle"), (1, "middle"), (1, "last"), (1, "quarter")],
    ids=["chunk1-crc-field", "chunk1-first-data-byte", "chunk1-middle", "chunk2-middle",
         "chunk2-last-byte", "chunk2-quarter"],
)
def test_a_flipped_byte_inside_a_chunk_is_refused_naming_the_file_and_the_chunk(tmp_path, good, chunk, where):
    bag = copy_bag(good, tmp_path / "flipped")
    mcap = mcap_of(bag)
    indexes = chunk_indexes(mcap)
    assert len(indexes) == 3  # two with envelope messages, a last one with the last pose
    start, end = compressed_span(indexes[chunk])
    offset = {
        "crc": indexes[chunk].chunk_start_offset + 9 + 24,
        "first": start,
        "quarter": start + (end - start) // 4,
        "middle": (start + end) // 2,
        "last": end - 1,
    }[where]
    flip(mcap, offset, 0x01)
    with pytest.raises(BagError, match=rf"chunk {chunk + 1} of 3 \(record at byte {indexes[chunk].chunk_start_offset}") as info:
        list(read_envelope(bag))
    assert str(info.value).startswith(f"{mcap}: ")
    with BagReader(bag) as reader, pytest.raises(BagError, match=f"chunk {chunk + 1} of 3"):
        reader.verify()


@pytest.mark.parametrize(
    "target",
    ["schema", "channel", "chunk index", "metadata index", "statistics", "summary offset",
     "footer summary_start", "footer summary_crc"],
)
def test_a_flipped_byte_in_the_summary_is_refused_when_the_bag_is_opened(tmp_path, good, target):
    bag = copy_bag(good, tmp_path / "flipped")
    mcap = mcap_of(bag)
    opcodes = {"schema": 0x03, "channel": 0x04, "chunk index": 0x08, "metadata index": 0x0D,
               "statistics": 0x0B, "summary offset": 0x0E}
    footer_at = footer(mcap)[0]
    if target in opcodes:
        at, _, length = next(r for r in summary_records(mcap) if r[1] == opcodes[target])
        offset = at + 9 + length // 2
    else:
        offset = footer_at + 9 + (0 if target == "footer summary_start" else 16)
    flip(mcap, offset, 0x04)
    with pytest.raises(BagError) as info:
        BagReader(bag).open()
    assert str(info.value).startswith(f"{mcap}: ")
    assert "summary section" in str(info.value) or "footer is corrupt" in str(info.value)


def test_a_flipped_byte_in_the_summary_of_a_bag_without_crcs_is_reported(tmp_path, plain):
    """No summary CRC to catch it: metadata.yaml, the copy, is what says the file is wrong."""
    bag = copy_bag(plain, tmp_path / "flipped")
    mcap = mcap_of(bag)
    at, _, length = next(r for r in summary_records(mcap) if r[1] == 0x0B)
    flip(mcap, at + 9 + length - 8, 0x01)  # low byte of the envelope channel's message count
    with BagReader(bag) as reader:
        assert reader.message_counts == {ENVELOPE_TOPIC: N_CHUNKS ^ 1}
        assert [str(i) for i in reader.inconsistencies] == [
            f"message count of {ENVELOPE_TOPIC}: metadata.yaml says {N_CHUNKS}, the .mcap file "
            f"{N_CHUNKS ^ 1}; the file's value is used"
        ]


def test_a_corrupt_provenance_record_is_refused(tmp_path, good):
    bag = copy_bag(good, tmp_path / "flipped")
    mcap = mcap_of(bag)
    with mcap.open("rb") as f:
        (index,) = [m for m in make_reader(f).get_summary().metadata_indexes if m.name == "deepsync"]
    offset = mcap.read_bytes().index(b'"rf_gain_db": 10.0', index.offset) + len(b'"rf_gain_db": 1')
    flip(mcap, offset, ord("0") ^ ord("1"))  # 10 dB -> 11 dB: valid JSON, another front end
    with pytest.raises(BagError, match=r"provenance in its 'deepsync' metadata record is corrupt") as info:
        bag_frontend(bag)
    assert str(info.value).startswith(f"{mcap}: ")


def test_a_flipped_byte_outside_the_chunks_records_reads_correctly_and_verify_finds_it(tmp_path, good):
    """A message index (not read: rosbags decompresses whole chunks) is covered by the data
    section CRC only, which :meth:`BagReader.verify` checks."""
    want = snapshot(good)
    bag = copy_bag(good, tmp_path / "flipped")
    mcap = mcap_of(bag)
    first = chunk_indexes(mcap)[0]
    index_at = min(first.message_index_offsets.values())
    flip(mcap, index_at + 9 + 2 + 4 + 3)  # inside the first (log time, offset) pair
    assert snapshot(bag) == want
    with BagReader(bag) as reader, pytest.raises(BagError, match="the data section .* is corrupt outside the chunks' records") as info:
        reader.verify()
    assert str(info.value).startswith(f"{mcap}: ")


def test_an_unreadable_rosbag2_metadata_record_is_reported_and_left_aside(tmp_path, good):
    want = snapshot(good)
    bag = copy_bag(good, tmp_path / "flipped")
    mcap = mcap_of(bag)
    with mcap.open("rb") as f:
        (index,) = [m for m in make_reader(f).get_summary().metadata_indexes if m.name == "rosbag2"]
    flip(mcap, index.offset + 9 + 4 + len("rosbag2") + 3, 0x10)  # its map now "runs" 256 MiB
    assert snapshot(bag) == want
    with BagReader(bag) as reader:
        (issue,) = reader.inconsistencies
    assert issue.subject == "flipped.mcap: metadata record 'rosbag2'" and "left aside" in str(issue)
    alone = tmp_path / "alone.mcap"
    alone.write_bytes(mcap.read_bytes())
    assert bag_frontend(alone) == RECORDED  # the deepsync record still says it


def test_random_flipped_bytes_are_refused_or_change_nothing(tmp_path, good):
    """Any single flipped byte: a BagError naming the bag, or exactly the intact result."""
    want = snapshot(good)
    size = mcap_of(good).stat().st_size
    data_spans = [compressed_span(i) for i in chunk_indexes(mcap_of(good))]
    structure = [o for o in range(size) if not any(a <= o < b for a, b in data_spans)]
    rng = random.Random(11)
    offsets = rng.sample(range(size), 8) + rng.sample(structure, 32)
    outcomes = {"refused": 0, "correct": 0}
    for k, offset in enumerate(offsets):
        bag = copy_bag(good, tmp_path / f"fuzz{k}")
        flip(bag / f"fuzz{k}.mcap", offset, rng.randrange(1, 256))
        try:
            got = snapshot(bag)
        except BagError as error:
            assert str(bag) in str(error), (offset, error)
            outcomes["refused"] += 1
            continue
        assert got == want, f"a flip at byte {offset} changed the result without a word"
        outcomes["correct"] += 1
    assert outcomes["refused"] >= 8  # at least every flip inside the compressed data


# -- truncated -------------------------------------------------------------------------------


@pytest.mark.parametrize("cut", ["empty", "magic", "header", "half", "before-footer", "last-byte"])
def test_a_truncated_mcap_is_refused_naming_the_file(tmp_path, good, cut):
    bag = copy_bag(good, tmp_path / "cut")
    mcap = mcap_of(bag)
    data = mcap.read_bytes()
    keep = {"empty": 0, "magic": 5, "header": 20, "half": len(data) // 2,
            "before-footer": footer(mcap)[0], "last-byte": len(data) - 1}[cut]
    mcap.write_bytes(data[:keep])
    with pytest.raises(BagError, match="is empty|does not start with the MCAP magic|cut short") as info:
        list(read_envelope(bag))
    assert str(info.value).startswith(f"{mcap}: ")


# -- metadata.yaml that lies, is gone, or is not YAML: the file's truth, reported ------------


def test_wrong_counts_in_metadata_yaml_are_reported_and_the_files_counts_used(tmp_path, good):
    bag = copy_bag(good, tmp_path / "lying")

    def lie(meta):
        for entry in meta["topics_with_message_count"]:
            if entry["topic_metadata"]["name"] == ENVELOPE_TOPIC:
                entry["message_count"] = 7
        meta["message_count"] = 99
        meta["duration"]["nanoseconds"] += 5
        meta["starting_time"]["nanoseconds_since_epoch"] -= 1

    edit_metadata(bag, lie)
    with BagReader(bag) as reader:
        assert reader.message_counts == {ENVELOPE_TOPIC: N_CHUNKS, TRUTH_POSE_TOPIC: N_CHUNKS}
        assert reader.message_count == 2 * N_CHUNKS
        assert reader.start_ns == T0
        assert reader.duration_ns == CHUNKS[-1].stamp_ns - T0
        found = {i.subject: (i.metadata, i.file, i.used) for i in reader.inconsistencies}
    assert found == {
        f"message count of {ENVELOPE_TOPIC}": (7, N_CHUNKS, "file"),
        "message count": (99, 2 * N_CHUNKS, "file"),
        "duration_ns": (CHUNKS[-1].stamp_ns - T0 + 5, CHUNKS[-1].stamp_ns - T0, "file"),
        "starting time (ns)": (T0 - 1, T0, "file"),
    }
    source = BagSource(bag)
    assert source.n_chunks == N_CHUNKS and len(source.inconsistencies) == 4
    assert "metadata.yaml and the .mcap disagree in 4 point(s)" in source.description


def test_topics_metadata_yaml_lists_wrongly_are_reported(tmp_path, good):
    bag = copy_bag(good, tmp_path / "lying")

    def swap(meta):
        pose = next(e for e in meta["topics_with_message_count"] if e["topic_metadata"]["name"] == TRUTH_POSE_TOPIC)
        pose["topic_metadata"]["name"] = "/ghost"

    edit_metadata(bag, swap)
    with BagReader(bag) as reader:
        assert set(reader.topics) == {ENVELOPE_TOPIC, TRUTH_POSE_TOPIC}  # the file's topics
        assert len(list(reader.messages([TRUTH_POSE_TOPIC]))) == N_CHUNKS  # still readable
        assert sorted(str(i) for i in reader.inconsistencies) == [
            f"topic {TRUTH_POSE_TOPIC}: in the .mcap file ({N_CHUNKS} messages) but not in metadata.yaml",
            f"topic /ghost: listed in metadata.yaml ({N_CHUNKS} messages) but not in the .mcap file",
        ]


@pytest.mark.parametrize(
    ("content", "why"),
    [(None, "missing"), ("rosbag2_bagfile_information: [unclosed\n", "unusable (invalid YAML"),
     ("hello: world\n", "no rosbag2_bagfile_information mapping"),
     ("rosbag2_bagfile_information: {version: 9}\n", "storage_identifier is missing"),
     (b"\xff\xfe binary", "unusable (not UTF-8 text"),
     # what the guarded loader refuses in our own configs, refused here too (on main: a message
     # hundreds of MB long from the alias bomb, a TypeError from the key, a RecursionError)
     ("rosbag2_bagfile_information: {custom_data: " + "[" * 5000 + "]" * 5000 + "}\n",
      "unusable (nested too deeply to read"),
     ("rosbag2_bagfile_information: {1: 2}\n", "unusable (metadata.yaml.rosbag2_bagfile_information: key 1 is not a string"),
     ("a0: &a0 [x, x, x, x, x, x, x, x, x]\n"
      + "".join(f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]\n" for i in range(1, 9))
      + "rosbag2_bagfile_information: {custom_data: {provenance: *a8}}\n", "unusable (metadata.yaml.a6: expands to more than")],
    ids=["missing", "not-yaml", "not-rosbag2", "keys-missing", "not-text", "deep", "int-key", "alias-bomb"],
)
def test_unusable_metadata_yaml_is_reported_and_the_mcap_read(tmp_path, good, content, why):
    want = snapshot(good)
    bag = copy_bag(good, tmp_path / "nometa")
    if content is None:
        (bag / "metadata.yaml").unlink()
    elif isinstance(content, bytes):
        (bag / "metadata.yaml").write_bytes(content)
    else:
        (bag / "metadata.yaml").write_text(content)
    assert snapshot(bag) == want
    with BagReader(bag) as reader:
        (issue,) = reader.inconsistencies
    assert issue.subject == "metadata.yaml"
    assert str(issue).startswith(f"metadata.yaml: {why}") and str(issue).endswith("come from nometa.mcap alone")
    source = open_source(bag)  # a directory with an .mcap is a bag, metadata.yaml or not
    assert isinstance(source, BagSource) and source.frontend == RECORDED


# -- provenance travels inside the .mcap -----------------------------------------------------


def test_an_mcap_copied_alone_keeps_its_recorded_front_end(tmp_path, good):
    alone = tmp_path / "elsewhere" / "copied.mcap"
    alone.parent.mkdir()
    alone.write_bytes(mcap_of(good).read_bytes())
    assert bag_frontend(alone) == RECORDED != FrontendConfig()
    source = BagSource(alone)
    assert source.frontend == RECORDED and "recorded front end" in source.description
    with BagReader(alone) as reader:
        assert reader.provenance == PROVENANCE and reader.inconsistencies == ()
        assert reader.message_counts == {ENVELOPE_TOPIC: N_CHUNKS, TRUTH_POSE_TOPIC: N_CHUNKS}
    with mcap_of(good).open("rb") as f:
        records = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert records["deepsync"]["provenance"] == PROVENANCE  # for Foxglove / `mcap info` too


def test_an_older_mcap_copied_alone_keeps_its_front_end_from_the_rosbag2_record(tmp_path, plain):
    alone = tmp_path / "old.mcap"
    alone.write_bytes(mcap_of(plain).read_bytes())
    assert bag_frontend(alone) == RECORDED


# -- CRCs: written, checked, and 0 still read --------------------------------------------------


def test_the_written_crcs_satisfy_the_mcap_library_and_rosbags(good):
    mcap = mcap_of(good)
    with mcap.open("rb") as f:  # chunk and data-section CRCs, validated by the mcap library
        records = list(StreamReader(f, validate_crcs=True, emit_chunks=True).records)
    assert all(r.uncompressed_crc for r in records if type(r).__name__ == "Chunk")
    assert next(r for r in records if type(r).__name__ == "DataEnd").data_section_crc
    assert footer(mcap)[3]
    with mcap.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_summary().statistics.metadata_count == 2  # rosbag2 + deepsync
        assert len(list(reader.iter_messages())) == 2 * N_CHUNKS
    with Reader(good) as rosbags_reader:  # what `ros2 bag`-side tooling in Python uses
        assert rosbags_reader.message_count == 2 * N_CHUNKS
    with BagReader(good) as bag:
        status = bag.verify()
        assert status.complete and status.chunks == 3


def test_the_summary_crc_agrees_with_the_mcap_librarys_writer(tmp_path):
    """An MCAP written by the mcap library itself (its own CRC code) reads and verifies; a
    flipped byte in its summary is refused: both sides compute the same summary CRC."""
    path = tmp_path / "other_writer.mcap"
    store = typestore()
    with path.open("wb") as stream:
        writer = McapLibWriter(stream, compression=CompressionType.ZSTD, enable_data_crcs=True)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(ENVELOPE_SAMPLES, "ros2msg",
                                        store.generate_msgdef(ENVELOPE_SAMPLES, ros_version=2)[0].encode())
        channel = writer.register_channel(ENVELOPE_TOPIC, "cdr", schema)
        for chunk in CHUNKS[:2]:
            data = store.serialize_cdr(envelope_to_msg(chunk), ENVELOPE_SAMPLES)
            writer.add_message(channel, chunk.stamp_ns, bytes(data), chunk.stamp_ns)
        writer.finish()
    with BagReader(path) as reader:
        assert reader.verify().complete
    assert [c.samples.tobytes() for c in read_envelope(path)] == [c.samples.tobytes() for c in CHUNKS[:2]]
    flip(path, footer(path)[1] + 3)
    with pytest.raises(BagError, match="summary section .* is corrupt"):
        BagReader(path).open()


def test_a_bag_written_without_crcs_still_reads(tmp_path, plain):
    with BagReader(plain) as reader:
        status = reader.crc_status
        assert (status.chunks_with_crc, status.summary_crc, status.data_crc) == (0, False, False)
        assert not status.complete and reader.verify() == status  # nothing to check, nothing wrong
        assert reader.provenance == PROVENANCE and reader.inconsistencies == ()
    assert [c.samples.tobytes() for c in read_envelope(plain)] == [c.samples.tobytes() for c in CHUNKS]


def test_a_bag_whose_crcs_were_zeroed_reads_the_same(tmp_path, good):
    want = snapshot(good)
    bag = copy_bag(good, tmp_path / "zeroed")
    mcap = mcap_of(bag)
    data = bytearray(mcap.read_bytes())
    for index in chunk_indexes(mcap):
        data[index.chunk_start_offset + 33 : index.chunk_start_offset + 37] = bytes(4)
    footer_at, summary_start, _, _ = footer(mcap)
    data[summary_start - 4 : summary_start] = bytes(4)  # data end record, just before the summary
    data[footer_at + 25 : footer_at + 29] = bytes(4)
    mcap.write_bytes(bytes(data))
    assert snapshot(bag) == want
    with BagReader(bag) as reader:
        assert reader.crc_status.chunks_with_crc == 0 and not reader.crc_status.summary_crc


# -- not a bag, or not one of ours ---------------------------------------------------------------


def test_an_empty_directory_is_refused(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(BagError, match=r"empty: not a rosbag2 directory \(no metadata.yaml, no .mcap file\)"):
        list(read_envelope(empty))


def test_a_directory_that_is_not_a_bag_is_refused(tmp_path):
    other = tmp_path / "notes"
    other.mkdir()
    (other / "readme.txt").write_text("not a bag")
    (other / "capture.cu8").write_bytes(bytes(64))
    with pytest.raises(BagError, match="notes: not a rosbag2 directory"):
        BagReader(other).open()


def test_a_bag_with_no_messages_reads_as_empty(tmp_path):
    bag = tmp_path / "nothing"
    with BagWriter(bag, provenance=PROVENANCE):
        pass
    with BagReader(bag) as reader:
        assert (reader.message_counts, reader.message_count, reader.duration_ns) == ({}, 0, 0)
        assert reader.inconsistencies == () and reader.provenance == PROVENANCE
    with pytest.raises(BagError, match=f"no topic {ENVELOPE_TOPIC} \\(the bag has no topics\\)"):
        list(read_envelope(bag))


def test_a_missing_mcap_and_mcaps_without_order_are_refused(tmp_path, good):
    gone = copy_bag(good, tmp_path / "gone")
    mcap_of(gone).unlink()
    with pytest.raises(BagError, match="gone: cannot open bag: .*missing"):
        BagReader(gone).open()
    two = copy_bag(good, tmp_path / "two")
    (two / "metadata.yaml").unlink()
    (two / "two_1.mcap").write_bytes(mcap_of(two).read_bytes())
    with pytest.raises(BagError, match="metadata.yaml is missing and there are 2 .mcap files.*ros2 bag reindex"):
        BagReader(two).open()


def test_another_kind_of_message_on_the_envelope_topic_is_refused(tmp_path):
    bag = tmp_path / "poses"
    with BagWriter(bag) as writer:
        writer.write(ENVELOPE_TOPIC, pose_to_msg(T0, 1.0, 2.0, 3.0))
    with pytest.raises(BagError, match=f"{ENVELOPE_TOPIC} carries geometry_msgs/msg/PoseStamped, not {ENVELOPE_SAMPLES}"):
        list(read_envelope(bag))


def test_an_unknown_message_type_on_the_envelope_topic_is_refused(tmp_path):
    bag = tmp_path / "foreign"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(ENVELOPE_TOPIC, "acme_msgs/msg/Envelope", msgdef="int16[] codes",
                                     rihs01="RIHS01_" + "00" * 32)
        writer.write(conn, T0, b"\x00\x01\x00\x00" + bytes(8))
    with pytest.raises(BagError, match=f"{ENVELOPE_TOPIC} carries acme_msgs/msg/Envelope, not {ENVELOPE_SAMPLES}"):
        list(read_envelope(bag))
    with pytest.raises(BagError, match="acme_msgs/msg/Envelope is unknown to DeepSync's typestore"):
        list(read_messages(bag))


def test_a_bag_without_the_envelope_topic_is_refused(tmp_path):
    bag = tmp_path / "truth_only"
    with BagWriter(bag) as writer:
        writer.write_truth_pose(T0, 1.0, 2.0, 3.0)
    with pytest.raises(BagError, match=f"truth_only: no topic {ENVELOPE_TOPIC} \\(the bag has {TRUTH_POSE_TOPIC}\\)"):
        list(read_envelope(bag))
    with pytest.raises(BagError, match=f"truth_only: no topic {ENVELOPE_TOPIC}"):
        BagSource(bag)  # no provenance, and no envelope message to take the rate from


def test_a_sqlite3_bag_is_refused_with_how_to_convert_it(tmp_path):
    bag = tmp_path / "old_db3"
    store = typestore()
    with Writer(bag, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        conn = writer.add_connection(ENVELOPE_TOPIC, ENVELOPE_SAMPLES, typestore=store)
        writer.write(conn, T0, store.serialize_cdr(envelope_to_msg(CHUNKS[0]), ENVELOPE_SAMPLES))
    db3 = next(bag.glob("*.db3"))
    assert sqlite3.connect(db3).execute("select count(*) from messages").fetchone() == (1,)
    for path in (bag, db3):
        with pytest.raises(BagError, match="sqlite3.*DeepSync reads MCAP bags.*ros2 bag convert") as info:
            BagReader(path).open()
        assert str(info.value).startswith(f"{path}: ")
    (bag / "metadata.yaml").unlink()
    with pytest.raises(BagError, match=r"a sqlite3 bag \(.db3 files\)"):
        BagReader(bag).open()


def test_a_ros1_bag_or_other_file_is_refused(tmp_path):
    ros1 = tmp_path / "drive.bag"
    ros1.write_bytes(b"#ROSBAG V2.0\n" + bytes(100))
    with pytest.raises(BagError, match=r"drive.bag: not a rosbag2 bag: give the bag directory or its .mcap file"):
        BagReader(ros1).open()
    fake = tmp_path / "fake.mcap"
    fake.write_bytes(b"#ROSBAG V2.0\n" + bytes(100))
    with pytest.raises(BagError, match="fake.mcap: not an MCAP file"):
        BagReader(fake).open()


# -- what the reader leaves to the stages ------------------------------------------------------


def test_codes_outside_adc_bits_are_read_as_recorded(tmp_path):
    """Codes a 12-bit ADC cannot produce (what corruption gives): the stream stage's to judge."""
    wild = EnvelopeChunk(T0, FS, 0, 12, 2 / 4096, np.array([-32768, -2049, 2048, 32767, 0], np.int16))
    bag = write_bag(tmp_path / "wild", [wild])
    (back,) = list(read_envelope(bag))
    assert back.adc_bits == 12 and back.samples.tolist() == [-32768, -2049, 2048, 32767, 0]


def test_a_bag_at_3_84_mhz_opened_by_its_mcap_alone_is_searched_at_its_own_rate(tmp_path):
    """On main this bag, opened by its .mcap, was searched with 1.92 MS/s templates and gave
    0 cells with no flag (exit 0)."""
    from deepsync.pipeline import Pipeline, PipelineConfig
    from deepsync.recording import record_scenario
    from deepsync.sources import BagSource
    from deepsync.towers import load_tower_database

    repo = Path(__file__).resolve().parents[1]
    scenario = tmp_path / "fast.yaml"
    text = (repo / "config" / "scenarios" / "campus.yaml").read_text()
    scenario.write_text(text.replace("frontend: {rf_gain_db: 10.0}", "frontend: {rf_gain_db: 10.0, adc_rate_hz: 3.84e6}"))
    record_scenario(scenario, 0.4, tmp_path / "fast", workers=1, progress=False)
    alone = tmp_path / "elsewhere"
    alone.mkdir()
    shutil.copy(tmp_path / "fast" / "fast.mcap", alone / "fast.mcap")
    source = BagSource(alone / "fast.mcap")
    assert source.frontend.adc_rate_hz == 3.84e6 and source.frontend.rf_gain_db == 10.0
    pipeline = Pipeline(source.frontend, PipelineConfig().with_choices(n_frames=10),
                        towers=load_tower_database(repo / "config" / "towers" / "campus.yaml"))
    results = list(pipeline.run(source.chunks()))
    assert len(results) == 4 and not any(r.health for r in results)
    assert {56, 301} <= set(results[-1].sync.pcis)


# -- sizes bounded before anything is allocated --------------------------------------------------


def test_a_chunk_that_would_decompress_beyond_its_bound_is_refused_before_it_is_read(tmp_path, monkeypatch):
    """A 2.8 MB bag whose one zstd chunk held a 200-million-sample message took 5.35 GB on main
    and was replayed as "105 s of signal". The chunk's size is judged from its header, against
    ``MAX_CHUNK_BYTES`` (here lowered to 1 MiB, so that the test writes no 400 MB message)."""
    from deepsync.bag import mcapfile

    bag = write_bag(tmp_path / "big", make_chunks(2, 300_000))  # 600 kB messages: a chunk of 1.2 MB
    monkeypatch.setattr(mcapfile, "MAX_CHUNK_BYTES", 2**20)
    with pytest.raises(BagError, match=r"big.mcap: chunk 1 of 2 .* decompresses to 1,2\d\d,\d\d\d bytes, beyond "
                                       r"the 1 MiB a chunk may take in memory; not read"):
        BagReader(bag).open()
    salvage = SalvageReader(bag)  # what replay falls back on reads up to it, and no further
    assert not list(salvage.messages()) and "beyond the 1 MiB a chunk may take" in salvage.damage


def test_an_envelope_chunk_beyond_its_bound_cannot_exist():
    from deepsync.types import MAX_CHUNK_SAMPLES

    with pytest.raises(ValueError, match=f"EnvelopeChunk of {MAX_CHUNK_SAMPLES + 1:,} samples: at most"):
        EnvelopeChunk(T0, FS, 0, 12, 2 / 4096, np.zeros(MAX_CHUNK_SAMPLES + 1, np.int16))


def write_with_a_raw_message(out: Path, raw: bytes, at: int = 3) -> Path:
    """The test chunks with one envelope message of ``raw`` bytes (not a valid CDR: empty, or
    too long) written before chunk ``at``."""
    with BagWriter(out, provenance=PROVENANCE) as bag:
        for k, chunk in enumerate(CHUNKS):
            if k == at:
                bag._writer.write(bag._connection(ENVELOPE_TOPIC, ENVELOPE_SAMPLES, None), chunk.stamp_ns - 1, raw)
            bag.write_envelope(chunk)
    return out


@pytest.mark.parametrize("raw, cause", [(b"", "cannot decode"), (b"\0\1\0\0" + bytes(600_000), "beyond the 0.5 MiB")],
                         ids=["zero_length", "beyond_the_message_bound"])
def test_a_message_that_cannot_be_had_is_skipped_by_replay_and_the_rest_kept(tmp_path, monkeypatch, capsys, raw, cause):
    """On main one zero-length envelope message stopped a replay ("the input is damaged") and
    everything after it was lost, though the chunk around it was intact."""
    from deepsync.bag import mcapfile
    from deepsync.cli import main

    if "beyond" in cause:
        monkeypatch.setattr(mcapfile, "MAX_MESSAGE_BYTES", 2**19)
    bag = write_with_a_raw_message(tmp_path / "odd", raw)
    with BagReader(bag) as reader:  # plain reading still refuses: a bag is a file, not a stream
        with pytest.raises(BagError, match=cause):
            list(reader.messages([ENVELOPE_TOPIC]))
        skipped: list[str] = []
        assert len(list(reader.messages([ENVELOPE_TOPIC], skipped=skipped.append))) == N_CHUNKS
    assert len(skipped) == 1 and cause in skipped[0] and f"at {T0 + round(3 * SAMPLES / FS * 1e9) - 1} ns" in skipped[0]
    out = tmp_path / "out"
    assert main(["replay", "--in", str(bag), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert f"{N_CHUNKS} input messages" in printed and "skipped a message no stage can take" in printed


def test_a_chunk_index_that_points_nowhere_reads_the_chunks_in_file_order(tmp_path, plain):
    """Zeroed chunk-index offsets in a bag without a summary CRC: on main every message was lost
    ("Unknown frame descriptor") though the chunks were intact."""
    want = snapshot(plain)
    bag = copy_bag(plain, tmp_path / "zeroed")
    data = bytearray(mcap_of(bag).read_bytes())
    for at, op, _ in summary_records(mcap_of(bag)):
        if op == 0x08:  # a chunk index: message start and end time, then chunk_start_offset
            struct.pack_into("<Q", data, at + 9 + 16, 0)
    mcap_of(bag).write_bytes(bytes(data))
    assert snapshot(bag) == want
    with BagReader(bag) as reader:
        assert any("chunk index: 2 of its 2 entries point where no chunk lies (the file has 2 chunks)" in str(note)
                   for note in reader.inconsistencies)


# -- a bag of several files ----------------------------------------------------------------------


def split_bag(tmp_path: Path, listing: list[str], second: list[EnvelopeChunk] = CHUNKS[3:]) -> Path:
    """A bag of two files, ``a.mcap`` (the test chunks' first half) and ``b.mcap`` (``second``),
    its metadata.yaml listing ``listing``."""
    for name, chunks in (("a", CHUNKS[:3]), ("b", second)):
        write_bag(tmp_path / name, chunks)
    bag = tmp_path / "split"
    bag.mkdir()
    for name in ("a", "b"):
        shutil.copy(tmp_path / name / f"{name}.mcap", bag / f"{name}.mcap")
    info = yaml.safe_load((tmp_path / "a" / "metadata.yaml").read_text())
    info["rosbag2_bagfile_information"]["relative_file_paths"] = listing
    (bag / "metadata.yaml").write_text(yaml.safe_dump(info))
    return bag


@pytest.mark.parametrize("listing, note", [
    (["a.mcap", "a.mcap", "b.mcap"], "lists a file more than once; each is read once"),
    (["b.mcap", "a.mcap"], "lists the files out of the order of their times; they are read in time order: a.mcap, b.mcap"),
], ids=["a-file-twice", "split-in-reverse"])
def test_a_split_bag_listed_twice_or_in_reverse_is_read_once_in_time_order(tmp_path, listing, note):
    """On main the file listed twice was read twice ("2.0 s of signal" for a 1.0 s bag), and a
    split bag listed in reverse was read backwards (a fix rate of 70 % instead of 85 %)."""
    bag = split_bag(tmp_path, listing)
    with BagReader(bag) as reader:
        assert reader.message_counts[ENVELOPE_TOPIC] == N_CHUNKS
        assert any(note in str(n) for n in reader.inconsistencies), reader.inconsistencies
    assert [c.first_sample_index for c in read_envelope(bag)] == [c.first_sample_index for c in CHUNKS]


def test_two_recordings_in_one_bag_are_refused(tmp_path):
    bag = split_bag(tmp_path, ["a.mcap", "b.mcap"], second=CHUNKS[1:4])  # b's times overlap a's
    with pytest.raises(BagError, match=r"a.mcap \(\d+..\d+ ns\) and b.mcap \(from \d+ ns\) overlap in time: two "
                                       "recordings in one bag"):
        BagReader(bag).open()


@pytest.mark.parametrize("provenance, why", [
    ("[]", "a JSON list, not a mapping"), ("null", "a JSON NoneType, not a mapping"),
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"), ('{"a": ' * 70 + "1" + "}" * 70, "nested more than 64 levels deep"),
], ids=["list", "null", "deeper-than-python", "deeper-than-the-loader"])
def test_a_provenance_that_is_no_mapping_is_said_in_one_line(tmp_path, capsys, provenance, why):
    """Found by the fuzzing pass: `info` raised AttributeError on a provenance of another shape,
    and every command a RecursionError on a deeply nested one."""
    from deepsync.cli import main

    bag = write_bag(tmp_path / "odd", CHUNKS[:2], provenance=provenance)
    assert main(["info", "--bag", str(bag)]) == 0
    out = capsys.readouterr().out
    assert f"  provenance: {bag}: " in out and why in out
    assert main(["detect", "--bag", str(bag)]) == 2
    err = capsys.readouterr().err
    assert why in err and "Traceback" not in err and len(err.splitlines()) == 1


def test_a_chunk_whose_compressed_bytes_are_damaged_stops_salvage_where_it_lies(tmp_path, good):
    """Found by the fuzzing pass: bytes inserted into a chunk made the mcap library's zstandard
    raise an error replay did not know, a traceback instead of "replayed up to the damage"."""
    from deepsync.cli import main

    bag = copy_bag(good, tmp_path / "inserted")
    data = bytearray(mcap_of(bag).read_bytes())
    start, end = compressed_span(chunk_indexes(mcap_of(good))[1])
    data[(start + end) // 2:(start + end) // 2] = b"\x13" * 7
    mcap_of(bag).write_bytes(bytes(data))
    salvage = SalvageReader(bag)
    assert len(list(salvage.messages([ENVELOPE_TOPIC]))) >= 1 and "damaged" in salvage.damage
    assert main(["replay", "--in", str(bag), "--out", str(tmp_path / "out"), "--quiet"]) == 1
