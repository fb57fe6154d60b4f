"""MCAP integrity for DeepSync bags: CRCs added when a bag is written, checked when it is read.

rosbags (0.11) writes 0 into every CRC field of an MCAP file, and 0 means "not computed", so
one flipped bit in a zstd chunk decodes into ~10,000 different samples and nothing notices.
:func:`seal` runs on the finished file inside :class:`~deepsync.bag.BagWriter`'s hidden
``.NAME.*.partial`` directory, before the bag is renamed into place, and changes nothing that
a reader relies on except what the MCAP specification says is there:

* each Chunk record's ``uncompressed_crc`` (CRC-32 of the decompressed records) is filled in
  in place, the file's size and every offset unchanged;
* extra Metadata records (the ``deepsync`` record with the provenance) are appended to the end
  of the data section, after rosbags' ``rosbag2`` record, with their Metadata Index records,
  and the Statistics record's ``metadata_count`` is raised to match;
* the Data End record gets ``data_section_crc`` (CRC-32 of every byte before it) and the
  Footer ``summary_crc`` (CRC-32 of the summary section through the footer's
  ``summary_offset_start``); the summary is written anew (same records, same order, Summary
  Offset records recomputed) after the grown data section.

So the file stays a plain rosbag2 MCAP file (profile ``ros2``, the same schemas, channels,
chunks, indexes and ``rosbag2`` metadata record): ``ros2 bag play``'s MCAP plugin, Foxglove and
``mcap info`` read it as before and those that check CRCs now can. The checks here accept 0 in
any CRC field (a file from another writer or an older DeepSync) as "not computed".

Every problem found is a :class:`~deepsync.bag.BagError` that names the file and the place.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

try:  # what rosbags decompresses chunks with (stdlib from Python 3.14 on)
    from compression import zstd  # type: ignore[import-not-found]
except ImportError:  # pragma: no cover - depends on the Python version
    from backports import zstd  # type: ignore[import-not-found,no-redef]

import lz4.frame  # type: ignore[import-untyped]

from .errors import BagError

MAGIC = b"\x89MCAP0\r\n"

OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_CHUNK = 0x06
OP_STATISTICS = 0x0B
OP_METADATA = 0x0C
OP_METADATA_INDEX = 0x0D
OP_SUMMARY_OFFSET = 0x0E
OP_DATA_END = 0x0F

_FOOTER_LEN = 1 + 8 + 8 + 8 + 4  # opcode, record length, summary_start, summary_offset_start, crc
_FOOTER_CRC_SPAN = 1 + 8 + 8 + 8  # what the summary CRC covers of the footer itself
_DATA_END_LEN = 1 + 8 + 4
_CHUNK_CRC_AT = 8 + 8 + 8  # in a Chunk body: message_start_time, message_end_time, uncompressed_size
_STATS_METADATA_COUNT_AT = 8 + 2 + 4 + 4  # message, schema, channel, attachment counts precede it
_BLOCK = 1 << 20

MAX_CHUNK_BYTES = 128 * 2**20
"""What one MCAP chunk may hold once decompressed: a reader holds a whole chunk in memory, so a
small file whose chunk inflates to gigabytes would take them before its first message is seen
(rosbag2 and rosbags write chunks of about 1 MiB; 128 MiB is far beyond any recorder's)."""
MAX_MESSAGE_BYTES = 64 * 2**20
"""What one serialised message may take: 8 times the largest envelope chunk (``types.MAX_CHUNK_SAMPLES``
int16 codes), far beyond any window or arrival array."""

DEEPSYNC_RECORD = "deepsync"
"""Name of the MCAP metadata record DeepSync writes (key ``provenance``, ``provenance_crc32``)."""
ROSBAG2_RECORD = "rosbag2"
"""Name of the metadata record rosbag2 (and rosbags) write: key ``serialized_metadata``."""

_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_CHUNK_HEAD = struct.Struct("<QQQI")

_DECOMPRESS = {
    "": lambda data: data,
    "zstd": zstd.decompress,
    "lz4": lz4.frame.decompress,
}


@dataclass(frozen=True)
class Footer:
    """Where an MCAP file's summary lies (offsets in bytes) and its summary CRC (0: none)."""

    offset: int  # of the footer record
    summary_start: int  # 0: no summary section
    summary_offset_start: int  # 0: no summary offset records
    summary_crc: int

    @property
    def summary_begin(self) -> int:
        """Where the data section ends: the summary, or the footer when there is none."""
        return self.summary_start or self.offset

    @property
    def summary_end(self) -> int:
        """Where the summary records (before any summary offsets) end."""
        return self.summary_offset_start or self.offset


@dataclass(frozen=True)
class ChunkProblem:
    """A chunk whose records cannot be trusted: decompression failed or the CRC disagrees."""

    index: int  # 0-based, in file order
    count: int  # chunks in the file
    offset: int  # of the chunk record
    start_ns: int
    end_ns: int
    cause: str

    def __str__(self) -> str:
        return (
            f"chunk {self.index + 1} of {self.count} (record at byte {self.offset}, messages "
            f"logged {self.start_ns}..{self.end_ns} ns) is corrupt: {self.cause}"
        )


@dataclass(frozen=True)
class CrcStatus:
    """How much of a bag's MCAP data carries CRCs (0 in a CRC field: not computed)."""

    chunks: int
    chunks_with_crc: int
    summary_crc: bool
    data_crc: bool

    @property
    def complete(self) -> bool:
        """Every chunk, the summary and the data section are protected."""
        return self.chunks == self.chunks_with_crc and self.summary_crc and self.data_crc


# -- low-level reading ------------------------------------------------------------------------


def _size(f: BinaryIO) -> int:
    return f.seek(0, 2)


def _read(f: BinaryIO, offset: int, size: int, path: Path, what: str) -> bytes:
    """Exactly ``size`` bytes at ``offset`` (checked against the file's size before reading,
    so that a corrupt length field never asks for 2**60 bytes)."""
    if offset < 0 or offset + size > _size(f):
        raise BagError(f"{path}: {what} at byte {offset} runs past the end of the file")
    f.seek(offset)
    data = f.read(size)
    if len(data) != size:
        raise BagError(f"{path}: {what} at byte {offset} runs past the end of the file")
    return data


def _string(body: bytes, at: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(body, at)
    end = at + 4 + n
    if end > len(body):
        raise ValueError("string runs past its record")
    return body[at + 4 : end].decode(errors="replace"), end


def _pack_string(text: str) -> bytes:
    data = text.encode()
    return _U32.pack(len(data)) + data


def _record(op: int, body: bytes) -> bytes:
    return bytes([op]) + _U64.pack(len(body)) + body


def read_footer(f: BinaryIO, path: Path) -> Footer:
    """The footer of an MCAP file, or a BagError saying why the file is not a whole MCAP file."""
    size = _size(f)
    if size == 0:
        raise BagError(f"{path}: the file is empty")
    f.seek(0)
    if f.read(len(MAGIC)) != MAGIC:
        raise BagError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
    tail = len(MAGIC) + _FOOTER_LEN
    if size < 2 * len(MAGIC) + _FOOTER_LEN:
        raise BagError(f"{path}: cut short ({size} bytes, no MCAP footer); "
                       "`mcap recover` can salvage what it holds")
    f.seek(size - tail)
    data = f.read(tail)
    if data[-len(MAGIC):] != MAGIC or data[0] != OP_FOOTER or _U64.unpack_from(data, 1)[0] != 20:
        raise BagError(
            f"{path}: the file ends without its MCAP footer: it was cut short (a recording "
            "that did not finish, or an incomplete copy); `mcap recover` can salvage its messages"
        )
    summary_start, summary_offset_start = struct.unpack_from("<QQ", data, 9)
    (crc,) = _U32.unpack_from(data, 25)
    footer = Footer(size - tail, summary_start, summary_offset_start, crc)
    for name, value in (("summary_start", summary_start), ("summary_offset_start", summary_offset_start)):
        if value and not len(MAGIC) < value <= footer.offset:
            raise BagError(f"{path}: the MCAP footer is corrupt ({name} {value} lies outside the file)")
    if summary_start and summary_offset_start and summary_offset_start < summary_start:
        raise BagError(f"{path}: the MCAP footer is corrupt (summary offsets before the summary)")
    return footer


def _crc_of(f: BinaryIO, start: int, end: int, crc: int = 0) -> int:
    f.seek(start)
    left = end - start
    while left > 0:
        block = f.read(min(_BLOCK, left))
        if not block:
            break
        crc = zlib.crc32(block, crc)
        left -= len(block)
    return crc


def _summary_crc(f: BinaryIO, footer: Footer) -> int:
    return _crc_of(f, footer.summary_begin, footer.offset + _FOOTER_CRC_SPAN)


def check_summary(f: BinaryIO, path: Path, footer: Footer) -> None:
    """BagError if the summary CRC is set and does not match (0: nothing to check)."""
    if not footer.summary_crc:
        return
    computed = _summary_crc(f, footer)
    if computed != footer.summary_crc:
        raise BagError(
            f"{path}: the summary section (bytes {footer.summary_begin}..{footer.offset + _FOOTER_LEN}: "
            f"indexes, statistics, footer) is corrupt: CRC 0x{computed:08x}, the file says "
            f"0x{footer.summary_crc:08x}; `mcap recover` rebuilds it from the data"
        )


def _records(f: BinaryIO, path: Path, start: int, end: int) -> Iterator[tuple[int, int, int]]:
    """(offset, opcode, body length) of the top-level records in [start, end), bodies unread."""
    at = start
    while at < end:
        head = _read(f, at, 9, path, "a record header")
        op = head[0]
        (length,) = _U64.unpack_from(head, 1)
        if at + 9 + length > end:
            raise BagError(f"{path}: the record at byte {at} (opcode 0x{op:02x}, {length} bytes) "
                           f"runs past its section (ends at byte {end})")
        yield at, op, length
        at += 9 + length


def _data_start(f: BinaryIO, path: Path) -> int:
    """Offset of the first record after the Header record."""
    head = _read(f, len(MAGIC), 9, path, "the header record")
    if head[0] != OP_HEADER:
        raise BagError(f"{path}: the MCAP header record is missing")
    return len(MAGIC) + 9 + _U64.unpack_from(head, 1)[0]


def _data_end(f: BinaryIO, path: Path, footer: Footer) -> tuple[int, int | None]:
    """(end of the data records, data_section_crc or None when there is no Data End record)."""
    at = footer.summary_begin - _DATA_END_LEN
    if at < len(MAGIC):
        return footer.summary_begin, None
    head = _read(f, at, _DATA_END_LEN, path, "the data end record")
    if head[0] == OP_DATA_END and _U64.unpack_from(head, 1)[0] == 4:
        return at, _U32.unpack_from(head, 9)[0]
    return footer.summary_begin, None


def _parse_chunk(body: bytes) -> tuple[int, int, int, int, str, bytes]:
    start_ns, end_ns, size, crc = _CHUNK_HEAD.unpack_from(body, 0)
    compression, at = _string(body, _CHUNK_HEAD.size)
    (compressed_size,) = _U64.unpack_from(body, at)
    data = body[at + 8 : at + 8 + compressed_size]
    if len(data) != compressed_size:
        raise ValueError("compressed data runs past the chunk record")
    return start_ns, end_ns, size, crc, compression, data


def _decompressed(compression: str, data: bytes, size: int) -> bytes:
    """The chunk's records, or ValueError with the cause."""
    decompress = _DECOMPRESS.get(compression)
    if decompress is None:
        raise ValueError(f"unknown chunk compression {compression!r}")
    try:
        raw = decompress(data)
    except Exception as error:  # noqa: BLE001 - each decompressor has its own error types
        raise ValueError(f"{compression} decompression failed ({error})") from None
    if len(raw) != size:
        raise ValueError(f"decompresses to {len(raw)} bytes, the chunk says {size}")
    return raw


def _chunk_offsets(f: BinaryIO, path: Path, footer: Footer) -> list[int]:
    start = _data_start(f, path)
    end, _ = _data_end(f, path, footer)
    return [at for at, op, _ in _records(f, path, start, end) if op == OP_CHUNK]


def checked_chunk_offsets(path: Path) -> list[int]:
    """Where the chunk records of ``path`` lie (byte offsets, found by walking the data section,
    not from its index); BagError naming the chunk when one would decompress to more than
    :data:`MAX_CHUNK_BYTES`, by what its record says and, for zstd, what its frame header says
    (the decompressor goes by the frame): judged from the headers alone, before anything is
    decompressed. Chunks too malformed to tell are left to the reading, which names them."""
    with path.open("rb") as f:
        footer = read_footer(f, path)
        offsets = _chunk_offsets(f, path, footer)
        for index, at in enumerate(offsets):
            (length,) = _U64.unpack(_read(f, at + 1, 8, path, "a chunk"))
            head = _read(f, at + 9, min(length, _CHUNK_HEAD.size + 4 + 64 + 8 + 18), path, "a chunk")
            try:
                start_ns, end_ns, size, _ = _CHUNK_HEAD.unpack_from(head, 0)
                compression, data_at = _string(head, _CHUNK_HEAD.size)
                frame = head[data_at + 8 :]
            except (ValueError, struct.error):
                continue
            declared = size
            if compression == "zstd":
                try:
                    declared = max(declared, zstd.get_frame_info(frame).decompressed_size or 0)
                except (zstd.ZstdError, ValueError, TypeError):
                    pass
            if declared > MAX_CHUNK_BYTES:
                raise BagError(f"{path}: chunk {index + 1} of {len(offsets)} (record at byte {at}, messages logged "
                               f"{start_ns}..{end_ns} ns) decompresses to {declared:,} bytes, beyond the "
                               f"{MAX_CHUNK_BYTES / 2**20:g} MiB a chunk may take in memory; not read")
    return offsets


def chunk_problems(path: Path, *, first_only: bool = True) -> list[ChunkProblem]:
    """Chunks of ``path`` that fail to decompress or whose set CRC disagrees (scans the file)."""
    problems: list[ChunkProblem] = []
    with path.open("rb") as f:
        footer = read_footer(f, path)
        offsets = _chunk_offsets(f, path, footer)
        for index, at in enumerate(offsets):
            (length,) = _U64.unpack(_read(f, at + 1, 8, path, "a chunk"))
            body = _read(f, at + 9, length, path, "a chunk")
            start_ns = end_ns = 0
            try:
                start_ns, end_ns, size, crc, compression, data = _parse_chunk(body)
                raw = _decompressed(compression, data, size)
                if crc and zlib.crc32(raw) != crc:
                    raise ValueError(
                        f"CRC 0x{zlib.crc32(raw):08x} of its records, the chunk says 0x{crc:08x}"
                    )
            except (ValueError, struct.error) as error:
                problems.append(ChunkProblem(index, len(offsets), at, start_ns, end_ns, str(error)))
                if first_only:
                    break
    return problems


def crc_status(path: Path) -> CrcStatus:
    """Which CRCs ``path`` carries (reads the chunk headers, not the chunks)."""
    with path.open("rb") as f:
        footer = read_footer(f, path)
        offsets = _chunk_offsets(f, path, footer)
        with_crc = sum(
            1 for at in offsets if _U32.unpack(_read(f, at + 9 + _CHUNK_CRC_AT, 4, path, "a chunk"))[0]
        )
        _, data_crc = _data_end(f, path, footer)
        return CrcStatus(len(offsets), with_crc, bool(footer.summary_crc), bool(data_crc))


def verify(path: Path) -> CrcStatus:
    """Check every CRC ``path`` carries (summary, data section, every chunk): reads the whole
    file and decompresses every chunk. BagError naming the file and the place at the first
    mismatch; what was checked otherwise."""
    with path.open("rb") as f:
        footer = read_footer(f, path)
        check_summary(f, path, footer)
    problems = chunk_problems(path)  # first: says which chunk, where the data CRC cannot
    if problems:
        raise BagError(f"{path}: {problems[0]}")
    with path.open("rb") as f:
        end, data_crc = _data_end(f, path, footer)
        if data_crc:
            computed = _crc_of(f, 0, end)
            if computed != data_crc:
                raise BagError(
                    f"{path}: the data section (bytes 0..{end}) is corrupt outside the chunks' "
                    f"records (in a record header, a message index or a metadata record): CRC "
                    f"0x{computed:08x}, the file says 0x{data_crc:08x}"
                )
    return crc_status(path)


# -- metadata records -------------------------------------------------------------------------


def _parse_metadata(body: bytes) -> tuple[str, dict[str, str]]:
    name, at = _string(body, 0)
    (size,) = _U32.unpack_from(body, at)
    at += 4
    end = at + size
    if end > len(body):
        raise ValueError("metadata map runs past its record")
    entries: dict[str, str] = {}
    while at < end:
        key, at = _string(body, at)
        value, at = _string(body, at)
        entries[key] = value
    return name, entries


def _pack_metadata(name: str, entries: Mapping[str, str]) -> bytes:
    pairs = b"".join(_pack_string(k) + _pack_string(v) for k, v in sorted(entries.items()))
    return _pack_string(name) + _U32.pack(len(pairs)) + pairs


@dataclass(frozen=True)
class MetadataRecords:
    """The Metadata records of an MCAP file: name -> key/value map, and those that do not
    parse (name as the CRC-protected index gives it, or ``"?"``; byte offset; cause)."""

    records: dict[str, dict[str, str]]
    unreadable: tuple[tuple[str, int, str], ...] = ()


def metadata_records(path: Path) -> MetadataRecords:
    """The file's Metadata records (via the summary's Metadata Index records, else by walking
    the data section; metadata never sits inside chunks). Checks the footer and the summary
    CRC first: a file that is cut short or has a corrupt summary is a BagError."""
    found: dict[str, dict[str, str]] = {}
    unreadable: list[tuple[str, int, str]] = []
    with path.open("rb") as f:
        footer = read_footer(f, path)
        check_summary(f, path, footer)
        places: list[tuple[int, str]] = []
        if footer.summary_start:
            for at, op, length in _records(f, path, footer.summary_start, footer.summary_end):
                if op == OP_METADATA_INDEX:
                    body = _read(f, at + 9, length, path, "a metadata index")
                    try:
                        places.append((_U64.unpack_from(body, 0)[0], _string(body, 16)[0]))
                    except (ValueError, struct.error) as error:
                        raise BagError(f"{path}: the metadata index at byte {at} is corrupt ({error})") from None
        if not places:  # no summary, or a writer without metadata indexes: walk the data section
            end, _ = _data_end(f, path, footer)
            places = [(at, "?") for at, op, _ in _records(f, path, _data_start(f, path), end) if op == OP_METADATA]
        for at, name in places:
            try:
                head = _read(f, at, 9, path, "a metadata record")
                if head[0] != OP_METADATA:
                    raise ValueError("no metadata record there")
                body = _read(f, at + 9, _U64.unpack_from(head, 1)[0], path, "a metadata record")
                recorded, entries = _parse_metadata(body)
                if name not in ("?", recorded):
                    raise ValueError(f"it is named {recorded!r}, its index says {name!r}")
            except (ValueError, struct.error) as error:  # BagError is a ValueError too
                cause = str(error).removeprefix(f"{path}: ")
                unreadable.append((name, at, cause))
                continue
            found.setdefault(recorded, {}).update(entries)
    return MetadataRecords(found, tuple(unreadable))


def provenance_entries(provenance: str) -> dict[str, str]:
    """The ``deepsync`` record's entries for ``provenance`` (with its own CRC: metadata records
    have none in MCAP, and a flipped digit must not pass for another front end)."""
    return {"provenance": provenance, "provenance_crc32": f"{zlib.crc32(provenance.encode()):08x}"}


def provenance_from(entries: Mapping[str, str], path: Path) -> str | None:
    """The provenance of a ``deepsync`` record, or BagError when its CRC disagrees."""
    text = entries.get("provenance")
    if text is None:
        return None
    stored = entries.get("provenance_crc32")
    if stored is not None and stored != f"{zlib.crc32(text.encode()):08x}":
        raise BagError(f"{path}: the provenance in its '{DEEPSYNC_RECORD}' metadata record is corrupt "
                       f"(CRC mismatch): the front end it names cannot be trusted")
    return text


# -- sealing (writer side) --------------------------------------------------------------------


def seal(path: Path, extra_metadata: Mapping[str, Mapping[str, str]] | None = None) -> None:
    """Fill in the CRCs of the finished MCAP file ``path`` and append ``extra_metadata``
    records (name -> key/value map), in place: run it on a file nobody else sees yet (the
    writer's partial directory). Chunk CRCs already set are checked, not trusted."""
    extra = dict(extra_metadata or {})
    with path.open("r+b") as f:
        footer = read_footer(f, path)
        end, data_crc = _data_end(f, path, footer)
        if data_crc is None or not footer.summary_start:
            raise BagError(f"{path}: cannot add CRCs: no data end record or no summary section")
        # 1. chunk CRCs, in place
        for index, (at, op, length) in enumerate(_records(f, path, _data_start(f, path), end)):
            if op != OP_CHUNK:
                continue
            body = _read(f, at + 9, length, path, "a chunk")
            try:
                _, _, size, crc, compression, data = _parse_chunk(body)
                computed = zlib.crc32(_decompressed(compression, data, size))
            except (ValueError, struct.error) as error:
                raise BagError(f"{path}: record {index} (chunk at byte {at}) is unreadable: {error}") from None
            if crc == 0:
                f.seek(at + 9 + _CHUNK_CRC_AT)
                f.write(_U32.pack(computed))
            elif crc != computed:
                raise BagError(f"{path}: the chunk at byte {at} does not match its own CRC")
        # 2. the summary as written, to be written again after the new metadata
        summary = [
            (op, _read(f, at + 9, length, path, "a summary record"))
            for at, op, length in _records(f, path, footer.summary_start, footer.summary_end)
            if op != OP_SUMMARY_OFFSET
        ]
        # 3. new metadata records at the end of the data section, then Data End with its CRC
        f.seek(end)
        f.truncate()
        indexes = []
        for name, entries in extra.items():
            at = f.tell()
            record = _record(OP_METADATA, _pack_metadata(name, entries))
            f.write(record)
            indexes.append(_record(OP_METADATA_INDEX, _U64.pack(at) + _U64.pack(len(record)) + _pack_string(name)))
        data_end = f.tell()
        f.write(_record(OP_DATA_END, _U32.pack(_crc_of(f, 0, data_end))))
        # 4. the summary: the same records, metadata indexes added, statistics counting them
        records: list[tuple[int, bytes]] = []
        for op, body in summary:
            if op == OP_STATISTICS and extra:
                (count,) = _U32.unpack_from(body, _STATS_METADATA_COUNT_AT)
                body = bytearray(body)
                _U32.pack_into(body, _STATS_METADATA_COUNT_AT, count + len(extra))
                body = bytes(body)
            records.append((op, body))
        last_index = max((i for i, (op, _) in enumerate(records) if op == OP_METADATA_INDEX), default=len(records) - 1)
        for k, index_record in enumerate(indexes):
            records.insert(last_index + 1 + k, (OP_METADATA_INDEX, index_record[9:]))
        summary_start = data_end + _DATA_END_LEN
        f.seek(summary_start)
        groups: list[tuple[int, int, int]] = []  # (opcode, start, length) of each run of one opcode
        for op, body in records:
            at = f.tell()
            f.write(_record(op, body))
            if groups and groups[-1][0] == op:
                groups[-1] = (op, groups[-1][1], f.tell() - groups[-1][1])
            else:
                groups.append((op, at, f.tell() - at))
        summary_offset_start = f.tell()
        for op, start, length in groups:
            f.write(_record(OP_SUMMARY_OFFSET, bytes([op]) + _U64.pack(start) + _U64.pack(length)))
        footer_at = f.tell()
        f.write(bytes([OP_FOOTER]) + _U64.pack(20) + _U64.pack(summary_start) + _U64.pack(summary_offset_start))
        f.flush()
        crc = _crc_of(f, summary_start, footer_at + _FOOTER_CRC_SPAN)
        f.seek(footer_at + _FOOTER_CRC_SPAN)
        f.write(_U32.pack(crc) + MAGIC)
        f.truncate()
