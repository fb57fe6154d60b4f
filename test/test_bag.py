"""deepsync.bag: rosbag2 v9 MCAP bags written atomically and read back bit-exactly.

Checked from three sides: our own reader, rosbags' reader (what the replay tools use) and the
independent ``mcap`` library (what Foxglove and ``ros2 bag``'s MCAP plugin build on).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from deepsync.bag import (
    ENVELOPE_TOPIC,
    PROVENANCE_KEY,
    TRUTH_CELL_TIMING_TOPIC,
    TRUTH_POSE_TOPIC,
    BagError,
    BagExistsError,
    BagReader,
    BagWriter,
    MsgDefsNotFoundError,
    cell_timing_array_from_msg,
    envelope_from_msg,
    envelope_to_msg,
    find_msg_dir,
    load_typestore,
    ns_to_stamp,
    position_from_pose_msg,
    read_envelope,
    read_messages,
    stamp_to_ns,
)
from deepsync.types import CellTiming, EnvelopeChunk, StackArrivals
from mcap.reader import make_reader
from rosbags.interfaces import QosDurability, QosHistory, QosReliability
from rosbags.rosbag2 import Reader

import deepsync

REPO = Path(__file__).resolve().parents[1]
MSG_DIR = REPO / "src" / "deepsync_msgs" / "msg"
T0 = 1_700_000_000_123_456_789  # ns; odd nanoseconds catch any float rounding of stamps
FS = 1.92e6


def make_chunks(seed: int = 7) -> list[EnvelopeChunk]:
    """Contiguous chunks of varying length (one > 1 MiB, one of 1 sample) incl. int16 extremes."""
    rng = np.random.default_rng(seed)
    lengths = [4800, 1, 640_000, 12_345, 0, 3]
    chunks, index = [], 0
    for k, n in enumerate(lengths):
        samples = rng.integers(-32768, 32768, size=n, dtype=np.int16)
        if n >= 2:
            samples[0], samples[-1] = -32768, 32767
        stamp = T0 + round(index / FS * 1e9) + k  # + k: distinct, non-round stamps
        chunks.append(EnvelopeChunk(stamp, FS, index, 12, 1.0 / 2048, samples))
        index += n
    return chunks


TRUTH_CELLS = [
    CellTiming(pci=142, toa=1234.5678901234, toa_std=0.0, snr_db=-3.25, estimator="truth"),
    CellTiming(pci=86, toa=98765.4321, toa_std=0.0, snr_db=7.5, estimator="truth", earfcn=2000, amplitude=0.125),
]


def write_example(out_dir: Path, chunks: list[EnvelopeChunk], **kwargs) -> None:
    with BagWriter(out_dir, provenance="deepsync simulate --seed 7", **kwargs) as bag:
        for k, chunk in enumerate(chunks):
            bag.write_envelope(chunk)
            bag.write_truth_pose(chunk.stamp_ns, 10.0 + k, -20.5, 1.25)
        bag.write_truth_cell_timing(StackArrivals(chunks[0].stamp_ns, chunks[0].first_sample_index,
                                                   chunks[0].sample_rate, tuple(TRUTH_CELLS), 21.75))


@pytest.fixture(scope="module")
def chunks() -> list[EnvelopeChunk]:
    return make_chunks()


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory, chunks: list[EnvelopeChunk]) -> Path:
    out = tmp_path_factory.mktemp("bags") / "example"
    write_example(out, chunks)
    return out


# -- round trip ---------------------------------------------------------------------------------


def test_envelope_round_trip_is_bit_exact(bag: Path, chunks: list[EnvelopeChunk]) -> None:
    back = list(read_envelope(bag))
    assert len(back) == len(chunks)
    for got, want in zip(back, chunks, strict=False):
        assert got.samples.dtype == np.dtype("<i2")
        assert np.array_equal(got.samples, want.samples)
        assert got.samples.tobytes() == want.samples.tobytes()
        assert got.stamp_ns == want.stamp_ns
        assert got.first_sample_index == want.first_sample_index
        assert got.sample_rate == want.sample_rate
        assert got.adc_bits == want.adc_bits
        assert got.volts_per_code == want.volts_per_code
    # contiguity survives: each chunk starts where the previous ended
    for prev, nxt in itertools.pairwise(back):
        assert nxt.first_sample_index == prev.end_sample_index


def test_truth_round_trip(bag: Path, chunks: list[EnvelopeChunk]) -> None:
    poses = list(read_messages(bag, [TRUTH_POSE_TOPIC]))
    assert [position_from_pose_msg(m.message) for m in poses] == [
        (10.0 + k, -20.5, 1.25) for k in range(len(chunks))
    ]
    for m in poses:
        assert m.message.header.frame_id == "map"
        q = m.message.pose.orientation
        assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)
    (timing,) = list(read_messages(bag, [TRUTH_CELL_TIMING_TOPIC]))
    assert timing.msgtype == "deepsync_msgs/msg/CellTimingArray"
    arrivals = cell_timing_array_from_msg(timing.message)
    # snr_db and amplitude are float32 on the wire: chosen values are exact in float32
    assert dataclasses.replace(arrivals.cells[0], amplitude=math.nan) == TRUTH_CELLS[0]  # NaN: not measured
    assert math.isnan(arrivals.cells[0].amplitude) and arrivals.cells[0].earfcn is None
    assert arrivals.cells[1] == TRUTH_CELLS[1]
    assert (arrivals.stamp_ns, arrivals.first_sample_index, arrivals.sample_rate, arrivals.clock_drift_ppm) == (
        chunks[0].stamp_ns, chunks[0].first_sample_index, chunks[0].sample_rate, 21.75)


def test_log_time_is_header_stamp(bag: Path) -> None:
    items = list(read_messages(bag))
    assert len(items) == 2 * len(make_chunks()) + 1
    for item in items:
        assert item.log_time_ns == stamp_to_ns(item.message.header.stamp)
    times = [item.log_time_ns for item in items]
    assert times == sorted(times)


def test_envelope_header(bag: Path) -> None:
    first = next(read_messages(bag, [ENVELOPE_TOPIC]))
    assert first.message.header.frame_id == "envelope_adc"
    assert first.message.samples.dtype == np.dtype("<i2")


# -- seen by other tools -----------------------------------------------------------------------


def test_metadata_yaml(bag: Path) -> None:
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 9
    assert info["storage_identifier"] == "mcap"
    assert info["relative_file_paths"] == ["example.mcap"]
    assert info["custom_data"] == {PROVENANCE_KEY: "deepsync simulate --seed 7"}
    assert info["starting_time"]["nanoseconds_since_epoch"] == make_chunks()[0].stamp_ns
    assert sorted(os_entry.name for os_entry in bag.iterdir()) == ["example.mcap", "metadata.yaml"]


def test_mcap_library_sees_topics_schemas_and_zstd(bag: Path) -> None:
    with (bag / "example.mcap").open("rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == {ENVELOPE_TOPIC, TRUTH_POSE_TOPIC, TRUTH_CELL_TIMING_TOPIC}
        schemas = {topic: summary.schemas[channel.schema_id] for topic, channel in channels.items()}
        assert schemas[ENVELOPE_TOPIC].name == "deepsync_msgs/msg/EnvelopeSamples"
        assert schemas[TRUTH_POSE_TOPIC].name == "geometry_msgs/msg/PoseStamped"
        assert schemas[TRUTH_CELL_TIMING_TOPIC].name == "deepsync_msgs/msg/CellTimingArray"
        for topic, schema in schemas.items():
            assert schema.encoding == "ros2msg", topic
            assert channels[topic].message_encoding == "cdr"
        envelope_def = schemas[ENVELOPE_TOPIC].data.decode()
        for line in (
            "std_msgs/Header header",
            "float64 sample_rate",
            "uint64 first_sample_index",
            "uint8 adc_bits",
            "float64 volts_per_code",
            "int16[] samples",
        ):
            assert line in envelope_def
        timing_def = schemas[TRUTH_CELL_TIMING_TOPIC].data.decode()
        assert "MSG: deepsync_msgs/CellTiming" in timing_def
        assert "float64 toa_std" in timing_def
        assert "string estimator" in timing_def
        assert summary.chunk_indexes
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        assert sum(c.compressed_size for c in summary.chunk_indexes) < sum(
            c.uncompressed_size for c in summary.chunk_indexes
        )
        log_times = [m.log_time for _, _, m in reader.iter_messages(log_time_order=True)]
        assert len(log_times) == summary.statistics.message_count == 2 * len(make_chunks()) + 1


def test_rosbags_reader_connections_and_qos(bag: Path) -> None:
    with Reader(bag) as reader:
        conns = {c.topic: c for c in reader.connections}
        assert {t: c.msgtype for t, c in conns.items()} == {
            ENVELOPE_TOPIC: "deepsync_msgs/msg/EnvelopeSamples",
            TRUTH_POSE_TOPIC: "geometry_msgs/msg/PoseStamped",
            TRUTH_CELL_TIMING_TOPIC: "deepsync_msgs/msg/CellTimingArray",
        }
        (sensor,) = conns[ENVELOPE_TOPIC].ext.offered_qos_profiles
        assert sensor.reliability == QosReliability.BEST_EFFORT
        assert sensor.history == QosHistory.KEEP_LAST
        assert sensor.depth == 10
        assert sensor.durability == QosDurability.VOLATILE
        for topic in (TRUTH_POSE_TOPIC, TRUTH_CELL_TIMING_TOPIC):
            (qos,) = conns[topic].ext.offered_qos_profiles
            assert qos.reliability == QosReliability.RELIABLE
            assert qos.durability == QosDurability.VOLATILE
        assert all(c.digest.startswith("RIHS01_") for c in conns.values())


def test_bag_reader_api(bag: Path) -> None:
    with BagReader(bag) as reader:
        assert reader.topics[ENVELOPE_TOPIC] == "deepsync_msgs/msg/EnvelopeSamples"
        assert reader.message_counts == {
            ENVELOPE_TOPIC: len(make_chunks()),
            TRUTH_POSE_TOPIC: len(make_chunks()),
            TRUTH_CELL_TIMING_TOPIC: 1,
        }
        assert reader.custom_data[PROVENANCE_KEY] == "deepsync simulate --seed 7"
        with pytest.raises(BagError, match="no topic /nope"):
            list(reader.messages(["/nope"]))


# -- atomic writing ----------------------------------------------------------------------------


class Boom(RuntimeError):
    pass


def test_exception_inside_with_leaves_nothing(tmp_path: Path, chunks: list[EnvelopeChunk]) -> None:
    out = tmp_path / "out" / "bag"
    with pytest.raises(Boom), BagWriter(out) as writer:
        writer.write_envelope(chunks[0])
        raise Boom("simulation failed half way")
    assert not out.exists()
    assert list(out.parent.iterdir()) == []  # no temporary sibling left behind


def test_keyboard_interrupt_leaves_nothing(tmp_path: Path, chunks: list[EnvelopeChunk]) -> None:
    out = tmp_path / "bag"
    with pytest.raises(KeyboardInterrupt), BagWriter(out) as writer:
        writer.write_envelope(chunks[0])
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_existing_out_dir_is_refused(tmp_path: Path, chunks: list[EnvelopeChunk]) -> None:
    out = tmp_path / "bag"
    out.mkdir()
    (out / "keep.txt").write_text("precious")
    with pytest.raises(BagExistsError, match="exists already"):
        BagWriter(out)
    with pytest.raises(FileExistsError):  # BagExistsError is also a FileExistsError
        BagWriter(out)
    # overwrite=True still refuses something that is not a bag
    with pytest.raises(BagExistsError, match="not a rosbag2 directory"):
        BagWriter(out, overwrite=True)
    assert (out / "keep.txt").read_text() == "precious"


def test_overwrite_replaces_only_after_success(tmp_path: Path) -> None:
    out = tmp_path / "bag"
    old = make_chunks(seed=1)[:2]
    new = make_chunks(seed=2)[:3]
    write_example(out, old)
    with pytest.raises(BagExistsError):
        write_example(out, new)
    # a failed overwrite keeps the old bag intact
    with pytest.raises(Boom), BagWriter(out, overwrite=True) as writer:
        writer.write_envelope(new[0])
        raise Boom
    assert [c.samples.tobytes() for c in read_envelope(out)] == [c.samples.tobytes() for c in old]
    write_example(out, new, overwrite=True)
    assert [c.samples.tobytes() for c in read_envelope(out)] == [c.samples.tobytes() for c in new]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]


def test_custom_data_and_single_use(tmp_path: Path, chunks: list[EnvelopeChunk]) -> None:
    out = tmp_path / "bag"
    writer = BagWriter(out, custom_data={"scenario": "config/scenarios/x.yaml"})
    with writer:
        writer.set_provenance("deepsync simulate --seed 3")
        writer.write_envelope(chunks[0])
    with BagReader(out) as reader:
        assert reader.custom_data == {
            "scenario": "config/scenarios/x.yaml",
            PROVENANCE_KEY: "deepsync simulate --seed 3",
        }
    with pytest.raises(BagError, match="one bag"), writer:
        pass
    with pytest.raises(TypeError):
        BagWriter(tmp_path / "other", custom_data={"seed": 3})  # type: ignore[dict-item]


def test_topic_type_is_fixed_on_first_use(tmp_path: Path, chunks: list[EnvelopeChunk]) -> None:
    mismatch = "carries deepsync_msgs/msg/EnvelopeSamples"
    with pytest.raises(BagError, match=mismatch), BagWriter(tmp_path / "bag") as writer:
        writer.write_envelope(chunks[0])
        writer.write_truth_pose(chunks[0].stamp_ns, 0, 0, 0, topic=ENVELOPE_TOPIC)
    assert list(tmp_path.iterdir()) == []


# -- unreadable bags -------------------------------------------------------------------------


def copy_bag(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for f in src.iterdir():
        (dst / f.name).write_bytes(f.read_bytes())
    return dst


@pytest.mark.parametrize("keep", [0.0, 0.001, 0.3, 0.5, 0.9, 0.999])
def test_truncated_mcap_raises_bag_error(tmp_path: Path, bag: Path, keep: float) -> None:
    broken = copy_bag(bag, tmp_path / "broken")
    mcap = broken / "example.mcap"
    data = mcap.read_bytes()
    mcap.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(BagError) as info:
        list(read_messages(broken))
    assert str(broken) in str(info.value)


def test_corrupt_mcap_raises_bag_error(tmp_path: Path, bag: Path) -> None:
    broken = copy_bag(bag, tmp_path / "broken")
    mcap = broken / "example.mcap"
    data = bytearray(mcap.read_bytes())
    data[len(data) // 3 : len(data) // 3 + 4096] = b"\xff" * 4096
    data[-200:] = b"\x00" * 200  # summary and footer gone
    mcap.write_bytes(bytes(data))
    with pytest.raises(BagError) as info:
        list(read_envelope(broken))
    assert str(broken) in str(info.value)


def test_garbage_metadata_is_reported_and_the_mcap_read(tmp_path: Path, bag: Path) -> None:
    broken = copy_bag(bag, tmp_path / "broken")
    (broken / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    with BagReader(broken) as reader:  # the .mcap is the truth; metadata.yaml only a copy
        (issue,) = reader.inconsistencies
        assert str(issue).startswith("metadata.yaml: unusable (invalid YAML") and "example.mcap alone" in str(issue)
    assert len(list(read_messages(broken))) == len(list(read_messages(bag)))


def test_non_bag_and_missing_paths(tmp_path: Path) -> None:
    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / "notes.txt").write_text("not a bag")
    with pytest.raises(BagError, match="not a rosbag2 directory") as info:
        list(read_messages(plain))
    assert str(plain) in str(info.value)
    missing = tmp_path / "missing"
    with pytest.raises(BagError, match="does not exist") as info:
        list(read_envelope(missing))
    assert str(missing) in str(info.value)


def test_missing_envelope_topic(tmp_path: Path) -> None:
    out = tmp_path / "truth_only"
    with BagWriter(out) as writer:
        writer.write_truth_pose(T0, 1.0, 2.0, 3.0)
    with pytest.raises(BagError, match="no topic /deepsync/envelope"):
        list(read_envelope(out))


def test_changed_message_definition_is_detected(tmp_path: Path, chunks) -> None:
    """A bag written with an older EnvelopeSamples must not be decoded with the new one."""
    old_msgs = tmp_path / "old_msgs"
    old_msgs.mkdir()
    for f in MSG_DIR.glob("*.msg"):
        text = f.read_text()
        if f.stem == "EnvelopeSamples":
            text = text.replace("uint8 adc_bits", "uint16 adc_bits")
        (old_msgs / f.name).write_text(text)
    old_store = load_typestore(old_msgs)
    out = tmp_path / "old_bag"
    with BagWriter(out, store=old_store) as writer:
        writer.write_envelope(chunks[0])
    with pytest.raises(BagError, match="differs from the current definition"):
        list(read_envelope(out))
    # with the matching definitions it reads fine
    with BagReader(out, store=old_store) as reader:
        (item,) = list(reader.messages())
        assert envelope_from_msg(item.message).samples.tobytes() == chunks[0].samples.tobytes()


def test_foreign_type_hash_with_same_fields_is_accepted(tmp_path: Path, chunks, monkeypatch) -> None:
    """A bag recorded by another RIHS01 implementation (ros2 bag record) still reads."""
    store = load_typestore(MSG_DIR)
    monkeypatch.setattr(store, "hash_rihs01", lambda msgtype: "RIHS01_" + "ab" * 32)
    out = tmp_path / "recorded_elsewhere"
    with BagWriter(out, store=store) as writer:
        writer.write_envelope(chunks[0])
    (chunk,) = list(read_envelope(out))
    assert chunk.samples.tobytes() == chunks[0].samples.tobytes()


# -- message definitions and conversions ------------------------------------------------------


def test_find_msg_dir_search_order(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DEEPSYNC_MSGS_DIR", raising=False)
    monkeypatch.delenv("AMENT_PREFIX_PATH", raising=False)
    if Path(deepsync.__file__).resolve().is_relative_to(REPO):  # running from this checkout
        assert find_msg_dir().resolve() == MSG_DIR.resolve()  # the shipped copy: a link to the source tree
    prefix = tmp_path / "install" / "deepsync_msgs"
    installed = prefix / "share" / "deepsync_msgs" / "msg"
    installed.mkdir(parents=True)
    for f in MSG_DIR.glob("*.msg"):
        (installed / f.name).write_text(f.read_text())
    monkeypatch.setenv("AMENT_PREFIX_PATH", f"{tmp_path / 'nothing'}:{prefix}")
    assert find_msg_dir() == installed
    monkeypatch.setenv("DEEPSYNC_MSGS_DIR", str(MSG_DIR))
    assert find_msg_dir() == MSG_DIR
    monkeypatch.setenv("DEEPSYNC_MSGS_DIR", str(tmp_path / "wrong"))
    with pytest.raises(MsgDefsNotFoundError, match="DEEPSYNC_MSGS_DIR"):
        find_msg_dir()


def test_stamp_conversion() -> None:
    assert stamp_to_ns(ns_to_stamp(T0)) == T0
    assert (ns_to_stamp(T0).sec, ns_to_stamp(T0).nanosec) == (1_700_000_000, 123_456_789)
    with pytest.raises(ValueError, match="outside"):
        ns_to_stamp(-1)
    with pytest.raises(ValueError, match="outside"):
        ns_to_stamp(2**31 * 10**9)


def test_envelope_to_msg_dtype_and_values(chunks: list[EnvelopeChunk]) -> None:
    msg = envelope_to_msg(chunks[0])
    assert msg.samples.dtype == np.dtype("<i2")
    assert msg.samples.flags.c_contiguous
    assert type(msg.sample_rate) is float
    assert type(msg.volts_per_code) is float
    assert msg.first_sample_index == chunks[0].first_sample_index
    assert envelope_from_msg(msg).samples.tobytes() == chunks[0].samples.tobytes()


def test_cell_timing_record_validation() -> None:
    with pytest.raises(ValueError, match="pci"):
        CellTiming(pci=504, toa=1.0, toa_std=0.1, snr_db=0.0, estimator="x")
    with pytest.raises(ValueError, match="toa_std"):
        CellTiming(pci=1, toa=1.0, toa_std=-0.1, snr_db=0.0, estimator="x")
    with pytest.raises(ValueError, match="toa"):
        CellTiming(pci=1, toa=float("nan"), toa_std=0.1, snr_db=0.0, estimator="x")
