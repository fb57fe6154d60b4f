"""Reading DeepSync bags back: typed messages, or the ADC stream as core chunks.

Whatever goes wrong underneath (missing path, not a bag, truncated or corrupt MCAP, a message
definition that changed since the bag was written) surfaces as one :class:`BagError` that names
the bag (or its ``.mcap`` file) and the cause, instead of a KeyError or struct.error from deep
inside rosbags.

What a bag holds is what its MCAP file(s) say: topics, message counts, the time span and the
provenance come from the file (its summary statistics, which its summary CRC protects, and its
metadata records); ``metadata.yaml`` says where the files are and is otherwise a copy that may
be stale, hand-edited, missing or broken. Every way it disagrees with the file is kept, as
data, in :attr:`BagReader.inconsistencies`; a missing or unreadable ``metadata.yaml`` next to a
single ``.mcap`` file is one of them, not an error.

CRCs (see :mod:`deepsync.bag.mcapfile`): the summary CRC is checked when a bag is opened, each
chunk's CRC when the chunk is read, and :meth:`BagReader.verify` checks everything. A CRC of 0
means "not computed" (other writers, DeepSync bags written before the CRCs) and passes.

:class:`SalvageReader` is the exception to refusing: it reads a damaged bag (cut short, a
corrupt chunk or summary) from its start up to the damage, for bag replay, which processes what
was recorded before the damage and says where it stopped.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path, PurePath
from types import TracebackType
from typing import TYPE_CHECKING, Any, NamedTuple

import zstandard  # what the mcap library decompresses chunks with
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from rosbags.interfaces import Connection
from rosbags.rosbag2 import Reader, ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import TypesysError, get_types_from_msg
from rosbags.typesys.store import Typestore

from ..configio import ConfigError, load_yaml, parse_yaml
from ..types import EnvelopeChunk
from . import mcapfile
from .convert import ENVELOPE_SAMPLES, envelope_from_msg
from .errors import BagError
from .mcapfile import CrcStatus
from .msgdefs import PACKAGE, find_msg_dir, load_typestore, typestore
from .topics import ENVELOPE_TOPIC
from .writer import PROVENANCE_KEY

if TYPE_CHECKING:
    from typing import Self  # Python >= 3.11; only for type checkers

try:  # what rosbags decompresses MCAP chunks with (stdlib from Python 3.14 on)
    from compression import zstd  # type: ignore[import-not-found]
    from compression.zstd import ZstdError  # type: ignore[import-not-found]
except ImportError:  # pragma: no cover - depends on the Python version
    from backports import zstd  # type: ignore[import-not-found,no-redef]
    from backports.zstd import ZstdError  # type: ignore[import-not-found,no-redef]

# Everything rosbags (and the decompressors under it) raises on unreadable input; found by
# truncating and corrupting bags: an empty .mcap makes rosbags call ord(b"") (TypeError), a
# corrupt length field makes it read 2**63 bytes (OverflowError, MemoryError).
_READ_ERRORS: tuple[type[BaseException], ...] = (
    ReaderError,
    SerdeError,
    TypesysError,
    ZstdError,
    OSError,
    EOFError,
    struct.error,
    KeyError,
    IndexError,
    ValueError,
    UnicodeDecodeError,
    RuntimeError,
    TypeError,
    OverflowError,
    MemoryError,
    AssertionError,
)

_NOT_MCAP = (
    "DeepSync reads MCAP bags (ROS 2 Jazzy's default storage); convert it with "
    "`ros2 bag convert -i BAG -o convert.yaml`, convert.yaml holding "
    "`output_bags: [{uri: BAG_mcap, storage_id: mcap}]`"
)


class BagMessage(NamedTuple):
    """One deserialised message and where it sits in the bag."""

    topic: str
    msgtype: str
    log_time_ns: int
    message: Any


@dataclass(frozen=True)
class BagInconsistency:
    """One way ``metadata.yaml`` disagrees with the bag's MCAP file, or could not be used.

    ``metadata`` is what ``metadata.yaml`` says (None: nothing, e.g. it is missing), ``file``
    what the MCAP file says (None: nothing); ``used`` is the one the reader goes by. ``str()``
    gives one line for a report.
    """

    subject: str
    metadata: object
    file: object
    used: str = "file"  # "file" or "metadata.yaml"
    note: str = ""

    def __str__(self) -> str:
        if self.note:
            return f"{self.subject}: {self.note}"
        return (
            f"{self.subject}: metadata.yaml says {self.metadata!r}, the .mcap file "
            f"{self.file!r}; the {'file' if self.used == 'file' else 'metadata.yaml'}'s value is used"
        )


def _metadata_problem(info: Any) -> str | None:
    """Why a parsed ``metadata.yaml`` cannot describe a bag (None: it can)."""
    if not isinstance(info, dict) or not isinstance(info.get("rosbag2_bagfile_information"), dict):
        return "no rosbag2_bagfile_information mapping"
    meta = info["rosbag2_bagfile_information"]
    for key, kind in (
        ("version", int),
        ("storage_identifier", str),
        ("relative_file_paths", list),
        ("topics_with_message_count", list),
        ("message_count", int),
        ("duration", dict),
        ("starting_time", dict),
    ):
        if not isinstance(meta.get(key), kind):
            return f"{key} is missing or not a {kind.__name__}"
    if not isinstance(meta["duration"].get("nanoseconds"), int):
        return "duration.nanoseconds is missing"
    if not isinstance(meta["starting_time"].get("nanoseconds_since_epoch"), int):
        return "starting_time.nanoseconds_since_epoch is missing"
    if not all(isinstance(name, str) for name in meta["relative_file_paths"]):
        return "relative_file_paths holds something that is not a file name"
    for entry in meta["topics_with_message_count"]:
        topic = entry.get("topic_metadata") if isinstance(entry, dict) else None
        if not (
            isinstance(topic, dict)
            and isinstance(topic.get("name"), str)
            and isinstance(topic.get("type"), str)
            and isinstance(entry.get("message_count"), int)
        ):
            return "a topics_with_message_count entry lacks its name, type or message_count"
    custom = meta.get("custom_data")
    if custom is not None and not isinstance(custom, dict):
        return "custom_data is not a mapping"
    return None


def _load_metadata(path: Path) -> tuple[dict[str, Any] | None, str | None]:
    """(parsed metadata.yaml, None) or (None, why it is unusable), through the project's
    guarded YAML loader (no alias bombs, bounded nesting and size)."""
    try:
        info = load_yaml(path, path.name)
    except ConfigError as error:
        return None, f"unusable ({str(error).removeprefix(f'{path.name}: ')})"
    problem = _metadata_problem(info)
    return (info, None) if problem is None else (None, problem)


class BagReader:
    """Read a rosbag2 MCAP bag with the DeepSync typestore; use as a context manager.

    ``bag_dir`` is a bag directory or an ``.mcap`` file. After :meth:`open`:
    :attr:`topics`, :attr:`message_counts`, :attr:`message_count` and :attr:`duration_ns` are
    the MCAP file's; :attr:`inconsistencies` lists where ``metadata.yaml`` disagrees;
    :attr:`custom_data` holds the provenance even for an ``.mcap`` copied without its
    ``metadata.yaml``.

    A chunk whose CRC does not match its records (or that does not decompress) makes reading
    stop with a :class:`BagError` naming the ``.mcap`` file, the chunk (its number, byte offset
    and log-time span) and the cause, when the reading reaches it; messages before it have been
    delivered. The reader refuses rather than skipping the chunk: a bag is a file on disk, not a
    live stream, so refusing loses nothing (the error says which span to cut away, and
    ``mcap recover`` or ``ros2 bag convert`` with a time range salvages the rest), while a
    skipped chunk would reach the stages as a plain gap in the ADC stream, and every result
    after it would rest on a stream silently missing 1 MiB of records.
    """

    def __init__(self, bag_dir: str | Path, *, store: Typestore | None = None) -> None:
        self.path = Path(bag_dir)
        self._store = store
        self._older: dict[str, OlderDefinition] = {}  # our types the bag holds in an older definition
        self._reader: Reader | None = None
        self._storages: list[Any] = []
        self._connections: list[Connection] = []
        self._files: list[Path] = []
        self._message_compressed = False
        self._custom: dict[str, str] = {}
        self.inconsistencies: tuple[BagInconsistency, ...] = ()
        """Where ``metadata.yaml`` disagrees with the MCAP file, or was unusable (after open)."""

    def _fail(self, cause: str, error: BaseException | None = None) -> BagError:
        detail = f": {error}" if error is not None and str(error) else ""
        return BagError(f"{self.path}: {cause}{detail}")

    # -- opening ------------------------------------------------------------------------------

    def _locate(self, notes: list[BagInconsistency]) -> tuple[Path, dict[str, Any] | None]:
        """What to hand rosbags (the directory, or one .mcap file) and the usable metadata."""
        p = self.path
        if not p.exists():
            raise self._fail("no such bag (path does not exist)")
        if not p.is_dir():
            suffix = p.suffix.lower()
            if suffix == ".mcap":
                return p, None
            if suffix == ".db3":
                raise self._fail(f"a sqlite3 storage file (.db3): {_NOT_MCAP}")
            raise self._fail(
                f"not a rosbag2 bag: give the bag directory or its .mcap file, not a "
                f"{suffix or 'extension-less'} file"
            )
        meta = p / "metadata.yaml"
        problem = "missing"
        if meta.is_file():
            info, problem = _load_metadata(meta)
            if info is not None:
                storage = info["rosbag2_bagfile_information"]["storage_identifier"]
                if storage != "mcap":
                    raise self._fail(f"storage {storage!r} (metadata.yaml storage_identifier): {_NOT_MCAP}")
                return p, info
        mcaps = sorted(x for x in p.iterdir() if x.suffix.lower() == ".mcap" and x.is_file())
        if len(mcaps) == 1:
            notes.append(BagInconsistency(
                "metadata.yaml", None, None,
                note=f"{problem}; topics, counts and custom data come from {mcaps[0].name} alone",
            ))
            return mcaps[0], None
        if mcaps:
            raise self._fail(
                f"metadata.yaml is {problem} and there are {len(mcaps)} .mcap files, in an "
                "order it alone records; rebuild it with `ros2 bag reindex`"
            )
        if any(x.suffix.lower() == ".db3" for x in p.iterdir()):
            raise self._fail(f"a sqlite3 bag (.db3 files): {_NOT_MCAP}")
        if problem == "missing":
            raise self._fail("not a rosbag2 directory (no metadata.yaml, no .mcap file)")
        raise self._fail(f"not a readable rosbag2 directory: metadata.yaml is {problem}, and no .mcap file")

    def open(self) -> None:
        """Open the bag, check its summary CRC(s) and that our message definitions match it."""
        if self._reader is not None:
            return
        notes: list[BagInconsistency] = []
        target, info = self._locate(notes)
        if info is None:
            files = [target]
        else:
            names = info["rosbag2_bagfile_information"]["relative_file_paths"]
            files = [target / PurePath(name).name for name in names]
            files = list(dict.fromkeys(f for f in files if f.suffix.lower() == ".mcap" and f.is_file()))
        records: list[mcapfile.MetadataRecords] = []
        chunks: dict[Path, list[int]] = {}
        for f in files:  # footer, summary CRC, chunk sizes and metadata records, before rosbags parses them
            try:
                found = mcapfile.metadata_records(f)
                chunks[f] = mcapfile.checked_chunk_offsets(f)
            except OSError as error:
                raise BagError(f"{f}: cannot read: {error}") from error
            for name, offset, cause in found.unreadable:
                if name in (mcapfile.DEEPSYNC_RECORD, "?"):
                    raise BagError(f"{f}: the metadata record at byte {offset} (maybe DeepSync's "
                                   f"provenance) is unreadable: {cause}")
                notes.append(BagInconsistency(
                    f"{f.name}: metadata record {name!r}", None, None,
                    used="metadata.yaml" if info is not None else "file",
                    note=f"unreadable ({cause}) and left aside: it is only a copy",
                ))
            records.append(found)
        try:
            reader = Reader(target)
            reader.open()
        except FileNotFoundError as error:
            raise self._fail("cannot open bag", error) from error
        except _READ_ERRORS as error:
            raise self._diagnose(files, "cannot open bag", error) from error
        self._reader = reader
        self._files = files
        try:
            self._take_stock(reader, info, records, notes)
            self._check_chunk_index(chunks, notes)
            self.inconsistencies = tuple(notes)
            self._check_definitions()
        except BaseException:
            self.close()
            raise

    def _in_time_order(self, storages: list[Any], notes: list[BagInconsistency]) -> list[Any]:
        """A split bag's files, each once, in the order of their messages' times (what a
        recorder wrote them in), whatever order ``metadata.yaml`` lists them in; BagError for
        files whose times overlap (two recordings in one bag, not one split in parts)."""
        unique: dict[Path, Any] = {}
        for one in storages:
            unique.setdefault(Path(one.path).resolve(), one)
        if len(unique) < len(storages):
            notes.append(BagInconsistency("metadata.yaml relative_file_paths", None, None, used="file",
                                          note="lists a file more than once; each is read once"))
        ordered = sorted(unique.values(), key=lambda one: (one.metadata.message_count == 0, one.metadata.start_time))
        if [id(one) for one in ordered] != [id(one) for one in unique.values()]:
            notes.append(BagInconsistency("metadata.yaml relative_file_paths", None, None, used="file",
                                          note="lists the files out of the order of their times; they are read "
                                               f"in time order: {', '.join(Path(one.path).name for one in ordered)}"))
        filled = [one for one in ordered if one.metadata.message_count]
        for before, after in zip(filled, filled[1:]):
            if after.metadata.start_time < before.metadata.end_time:
                span = f"{before.metadata.start_time}..{before.metadata.end_time - 1}"
                raise self._fail(f"{Path(before.path).name} ({span} "
                                 f"ns) and {Path(after.path).name} (from {after.metadata.start_time} ns) overlap in "
                                 "time: two recordings in one bag, not one recording split in parts; open each alone")
        return ordered

    def _check_chunk_index(self, chunks: dict[Path, list[int]], notes: list[BagInconsistency]) -> None:
        """Where a file's chunk index (its summary) points elsewhere than at its chunks (zeroed or
        stale offsets: a file without a summary CRC cannot tell), read its chunks in file order
        instead, as a file without an index is read: they are intact, and every message is in them."""
        for storage in self._storages:
            found = chunks.get(Path(storage.path))
            indexed = sorted(chunk.chunk_start_offset for chunk in storage.chunks)
            if found is None or not indexed or indexed == sorted(found):
                continue
            notes.append(BagInconsistency(
                f"{Path(storage.path).name}: chunk index", None, None,
                note=f"{sum(1 for at in indexed if at not in found)} of its {len(indexed)} entries point where no "
                     f"chunk lies (the file has {len(found)} chunks): the messages are read from the chunks in "
                     "file order",
            ))
            storage.chunks.clear()

    def _diagnose(self, files: Iterable[Path], cause: str, error: BaseException) -> BagError:
        """The corrupt chunk behind ``error`` if there is one, else the error as it came."""
        for f in files:
            try:
                problems = mcapfile.chunk_problems(Path(f))
            except BagError as found:
                return found
            except OSError:
                continue
            if problems:
                return BagError(f"{f}: {problems[0]}")
        return self._fail(cause, error)

    def _take_stock(
        self,
        reader: Reader,
        info: dict[str, Any] | None,
        records: list[mcapfile.MetadataRecords],
        notes: list[BagInconsistency],
    ) -> None:
        """Topics, counts and custom data from the file; where metadata.yaml disagrees."""
        storage = reader.storage
        self._storages = self._in_time_order(list(getattr(storage, "storages", [storage])), notes)
        self._message_compressed = getattr(storage, "metadata", None) is not None and (
            storage.metadata.compression_mode == "message"
        )
        meta = info["rosbag2_bagfile_information"] if info is not None else None
        digests = {}
        if meta is not None:
            for entry in meta["topics_with_message_count"]:
                t = entry["topic_metadata"]
                digests[(t["name"], t["type"])] = t.get("type_description_hash") or ""
        self._connections = [
            conn._replace(digest=digests.get((conn.topic, conn.msgtype), conn.digest))
            for s in self._storages
            for conn in s.connections
        ]
        self._custom = self._custom_data(records, meta, notes)
        if meta is not None:
            self._compare(meta, notes)
        self.inconsistencies = tuple(notes)

    def _custom_data(
        self,
        records: list[mcapfile.MetadataRecords],
        meta: dict[str, Any] | None,
        notes: list[BagInconsistency],
    ) -> dict[str, str]:
        """Custom data: metadata.yaml's when usable, else the copy rosbag2/rosbags embed in the
        .mcap (its ``rosbag2`` record, no CRC of its own); the provenance in DeepSync's own
        CRC-protected ``deepsync`` record overrides both."""
        embedded: dict[str, str] = {}
        provenance: str | None = None
        for f, file_records in zip(self._files, records):
            found = file_records.records
            serialized = found.get(mcapfile.ROSBAG2_RECORD, {}).get("serialized_metadata")
            if serialized:
                try:
                    data = parse_yaml(serialized, f"{f}: its {mcapfile.ROSBAG2_RECORD} metadata record")
                except ConfigError as error:
                    notes.append(BagInconsistency(f"{f.name}: metadata record {mcapfile.ROSBAG2_RECORD!r}", None, None,
                                                  note=f"left aside: {error}"))
                    data = None
                custom = data.get("custom_data") if isinstance(data, dict) else None
                if isinstance(custom, dict):
                    for key, value in custom.items():
                        embedded.setdefault(str(key), str(value))
            if provenance is None:
                provenance = mcapfile.provenance_from(found.get(mcapfile.DEEPSYNC_RECORD, {}), f)
        result = dict(embedded)
        if meta is not None:
            listed = {str(k): str(v) for k, v in (meta.get("custom_data") or {}).items()}
            for key in sorted(set(listed) | set(embedded)):
                if key in listed and key in embedded and listed[key] == embedded[key]:
                    continue
                if key == PROVENANCE_KEY and provenance is not None:
                    continue  # judged against the CRC-protected copy below
                if key in listed and embedded:
                    notes.append(BagInconsistency(
                        f"custom_data {key}", listed[key], embedded.get(key), used="metadata.yaml",
                        note=f"metadata.yaml says {listed[key]!r}, the .mcap's rosbag2 record "
                             f"{embedded.get(key)!r}; metadata.yaml's value is used (the record has no CRC)",
                    ))
                elif key not in listed:
                    notes.append(BagInconsistency(f"custom_data {key}", None, embedded[key]))
            result.update(listed)
        if provenance is not None:
            said = result.get(PROVENANCE_KEY)
            if meta is not None and said != provenance:
                notes.append(BagInconsistency(f"custom_data {PROVENANCE_KEY}", said, provenance))
            result[PROVENANCE_KEY] = provenance
        return result

    def _compare(self, meta: dict[str, Any], notes: list[BagInconsistency]) -> None:
        listed: dict[str, int] = {}
        types: dict[str, str] = {}
        for entry in meta["topics_with_message_count"]:
            name = entry["topic_metadata"]["name"]
            listed[name] = listed.get(name, 0) + entry["message_count"]
            types[name] = entry["topic_metadata"]["type"]
        counts = self.message_counts
        for topic in sorted(set(listed) | set(counts)):
            if topic not in counts:
                notes.append(BagInconsistency(
                    f"topic {topic}", listed[topic], None,
                    note=f"listed in metadata.yaml ({listed[topic]} messages) but not in the .mcap file",
                ))
            elif topic not in listed:
                notes.append(BagInconsistency(
                    f"topic {topic}", None, counts[topic],
                    note=f"in the .mcap file ({counts[topic]} messages) but not in metadata.yaml",
                ))
            else:
                if listed[topic] != counts[topic]:
                    notes.append(BagInconsistency(f"message count of {topic}", listed[topic], counts[topic]))
                if types[topic] != self.topics[topic]:
                    notes.append(BagInconsistency(f"type of {topic}", types[topic], self.topics[topic]))
        if meta["message_count"] != self.message_count:
            notes.append(BagInconsistency("message count", meta["message_count"], self.message_count))
        if meta["duration"]["nanoseconds"] != self.duration_ns:
            notes.append(BagInconsistency("duration_ns", meta["duration"]["nanoseconds"], self.duration_ns))
        start = meta["starting_time"]["nanoseconds_since_epoch"]
        if self.message_count and start != self.start_ns:
            notes.append(BagInconsistency("starting time (ns)", start, self.start_ns))

    def _check_definitions(self) -> None:
        """Refuse bags whose deepsync_msgs types differ from ours (stale bag or stale source).

        The type hash decides when it matches; when it does not, the field layout embedded in
        the bag decides, so a bag recorded by ``ros2 bag record`` on a robot is not refused
        only because its hash was computed by another implementation than rosbags'.
        """
        store = self.store
        for conn in self._connections:
            if not conn.msgtype.startswith(f"{PACKAGE}/"):
                continue
            if conn.msgtype not in store.types:
                raise self._fail(f"{conn.topic}: unknown type {conn.msgtype}")
            if conn.digest and conn.digest == store.hash_rihs01(conn.msgtype):
                continue
            text = getattr(conn.msgdef, "data", "") or ""
            if _embedded_fields(text, conn.msgtype) == store.fielddefs[conn.msgtype]:
                continue
            older = OlderDefinition.of(store, conn.msgtype, text)
            if older is None:
                raise self._fail(
                    f"{conn.topic}: {conn.msgtype} in the bag differs from the current "
                    "definition; regenerate the bag or check out matching msgs"
                )
            self._older[conn.msgtype] = older

    def close(self) -> None:
        """Close the bag (idempotent)."""
        reader, self._reader = self._reader, None
        self._storages = []
        self._connections = []
        if reader is not None:
            try:
                reader.close()
            except _READ_ERRORS as error:
                raise self._fail("cannot close bag", error) from error

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> bool:
        self.close()
        return False

    # -- what the bag holds --------------------------------------------------------------------

    @property
    def store(self) -> Typestore:
        """Typestore used for deserialisation (the shared one unless given)."""
        return typestore() if self._store is None else self._store

    def _opened(self) -> Reader:
        if self._reader is None:
            raise BagError(f"{self.path}: bag is not open; use 'with BagReader(...)'")
        return self._reader

    @property
    def files(self) -> list[Path]:
        """The MCAP file(s) read."""
        self._opened()
        return list(self._files)

    @property
    def topics(self) -> dict[str, str]:
        """Topic name -> message type, as the MCAP file has them."""
        self._opened()
        return {c.topic: c.msgtype for c in self._connections}

    @property
    def message_counts(self) -> dict[str, int]:
        """Topic name -> number of messages, from the MCAP file (its summary statistics, or
        its chunk indexes, or counted); see :attr:`inconsistencies` for metadata.yaml's."""
        self._opened()
        counts: dict[str, int] = {}
        for c in self._connections:
            counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
        return counts

    @property
    def message_count(self) -> int:
        """Total number of messages in the MCAP file(s)."""
        self._opened()
        return sum(s.metadata.message_count for s in self._storages)

    @property
    def start_ns(self) -> int:
        """Log time of the first message (0 for an empty bag)."""
        self._opened()
        starts = [s.metadata.start_time for s in self._storages if s.metadata.message_count]
        return min(starts) if starts else 0

    @property
    def duration_ns(self) -> int:
        """Log time from the first message to the last (0 for an empty bag), from the file."""
        self._opened()
        spans = [s.metadata for s in self._storages if s.metadata.message_count]
        if not spans:
            return 0
        return max(m.end_time - 1 for m in spans) - min(m.start_time for m in spans)

    @property
    def custom_data(self) -> dict[str, str]:
        """``custom_data`` (e.g. the provenance string): metadata.yaml's, else the copy inside
        the .mcap; the provenance from the .mcap's CRC-protected ``deepsync`` record wins."""
        self._opened()
        return dict(self._custom)

    @property
    def provenance(self) -> str | None:
        """How the bag was made (``custom_data[PROVENANCE_KEY]``), or None."""
        return self.custom_data.get(PROVENANCE_KEY)

    @property
    def crc_status(self) -> CrcStatus:
        """How much of the MCAP data carries CRCs (summed over the files); 0 CRCs (bags from
        other writers, older DeepSync bags) mean corruption inside them cannot be detected."""
        self._opened()
        total = CrcStatus(0, 0, bool(self._files), bool(self._files))  # no file checked: no CRC
        for f in self._files:
            one = mcapfile.crc_status(f)
            total = CrcStatus(total.chunks + one.chunks, total.chunks_with_crc + one.chunks_with_crc,
                              total.summary_crc and one.summary_crc, total.data_crc and one.data_crc)
        return total

    def verify(self) -> CrcStatus:
        """Check every CRC of the bag's MCAP file(s): summary, data section and every chunk
        (reads and decompresses everything). BagError naming the file and the place."""
        self._opened()
        for f in self._files:
            mcapfile.verify(f)
        return self.crc_status

    # -- reading --------------------------------------------------------------------------------

    def _read_failure(self, storage: Any, error: BaseException) -> BagError:
        return self._diagnose([Path(storage.path)], "cannot read message", error)

    def messages(self, topics: Iterable[str] | None = None, *,
                 skipped: Callable[[str], None] | None = None) -> Iterator[BagMessage]:
        """Messages in log-time order (per file), optionally only those of ``topics`` (all must
        exist). A corrupt chunk stops the reading with a BagError (see the class docstring). A
        message that cannot be decoded, or takes more than ``MAX_MESSAGE_BYTES``, is a BagError
        too, or, with ``skipped``, said to it (one line: topic, time, cause) and passed over:
        the chunk around it is intact, and so is every message after it."""
        self._opened()
        connections = self._connections
        if topics is not None:
            wanted = set(topics)
            missing = wanted - {c.topic for c in connections}
            if missing:
                raise self._fail(
                    f"no topic {', '.join(sorted(missing))} "
                    f"(the bag has {', '.join(sorted(self.topics)) or 'no topics'})"
                )
            connections = [c for c in connections if c.topic in wanted]
        if not connections:
            return
        store = self.store
        for conn in connections:
            if conn.msgtype not in store.types:
                raise self._fail(f"{conn.topic}: type {conn.msgtype} is unknown to DeepSync's typestore; "
                                 "its messages cannot be decoded")
        for storage in self._storages:
            mine = [c for c in connections if c.owner is storage]
            if not mine:
                continue
            stream = storage.messages(mine)
            while True:
                try:
                    item = next(stream, None)
                    if item is None:
                        break
                    conn, log_time_ns, raw = item
                    if self._message_compressed:
                        raw = _decompress_message(raw)
                except _READ_ERRORS as error:
                    raise self._read_failure(storage, error) from error
                problem = _undecodable(store, raw, conn.msgtype, conn.topic, log_time_ns, self._older)
                if isinstance(problem, str):
                    if skipped is None:
                        raise self._fail(problem)
                    skipped(problem)
                    continue
                yield BagMessage(conn.topic, conn.msgtype, log_time_ns, problem)


def _undecodable(store: Typestore, raw: bytes, msgtype: str, topic: str, log_time_ns: int,
                 older: dict[str, OlderDefinition]) -> Any:
    """The message ``raw`` holds (in the current definition: see :class:`OlderDefinition`), or
    why it cannot be had (a string): more bytes than ``MAX_MESSAGE_BYTES``, or bytes that do
    not decode as ``msgtype``."""
    where = f"the {msgtype} message on {topic} at {log_time_ns} ns"
    if len(raw) > mcapfile.MAX_MESSAGE_BYTES:
        return (f"{where} takes {len(raw):,} bytes, beyond the {mcapfile.MAX_MESSAGE_BYTES / 2**20:g} MiB a message "
                "may take; not decoded")
    try:
        if msgtype in older:
            return older[msgtype].upgraded(raw)
        return store.deserialize_cdr(raw, msgtype)
    except _READ_ERRORS as error:
        return f"cannot decode {where}: {error}"


@dataclass(frozen=True)
class OlderDefinition:
    """One of our types as a bag recorded it before numbers were appended to it (every bag's
    ground truth holds a ``CellTimingArray``): its messages decode with the bag's definition
    and come out in the current one, the appended numbers 0, which every appended field
    documents as "not said". Any other difference is refused (:meth:`of` gives None)."""

    decoder: Typestore  # the current types, ``msgtype`` as the bag has it
    current: type
    msgtype: str

    @classmethod
    def of(cls, store: Typestore, msgtype: str, text: str) -> OlderDefinition | None:
        embedded = _embedded_fields(text, msgtype)
        if embedded is None:
            return None
        (old_consts, old_fields), (consts, fields) = embedded, store.fielddefs[msgtype]
        appended = fields[len(old_fields):]
        if old_consts != consts or fields[:len(old_fields)] != old_fields or not appended or any(
                kind[0].name != "BASE" or kind[1][0] in ("string", "bool") for _, kind in appended):
            return None
        decoder = load_typestore(find_msg_dir(), {msgtype: text.split("=" * 80)[0]})
        return cls(decoder, store.types[msgtype], msgtype)

    def upgraded(self, raw: bytes) -> Any:
        message = self.decoder.deserialize_cdr(raw, self.msgtype)
        return self.current(**{name: getattr(message, name, 0) for name in self.current.__dataclass_fields__})


def _decompress_message(raw: bytes) -> bytes:
    """A message-compressed bag's message, decompressed to at most one byte more than
    :data:`~deepsync.bag.mcapfile.MAX_MESSAGE_BYTES` (what is more is refused by size anyway)."""
    return zstd.ZstdDecompressor().decompress(raw, max_length=mcapfile.MAX_MESSAGE_BYTES + 1)


def _embedded_fields(text: str, msgtype: str) -> Any:
    """Field layout of ``msgtype`` from a definition embedded in a bag, or None if unreadable."""
    try:
        own = text.split("=" * 80)[0]  # the type itself precedes its dependencies
        return get_types_from_msg(own, msgtype).get(msgtype)
    except _READ_ERRORS:
        return None


class SalvageReader:
    """What can still be read of a damaged MCAP bag, for replay: its records in file order, from
    the start up to the damage (a file cut short, a chunk whose CRC or compression fails, junk
    where a record should be). Summary, index and footer are not needed, so a bag that
    :class:`BagReader` refuses at the door (truncated, corrupt summary) still gives the chunks
    written before the damage.

    ``bag_dir`` is a bag directory holding one ``.mcap`` file, or the file. :attr:`topics` and
    :attr:`custom_data` are what the readable part says (custom data from ``metadata.yaml``
    when it is usable: the copy inside the ``.mcap`` sits at its end, lost when it is cut).
    :meth:`messages` stops at the damage instead of raising, and :attr:`damage` then says where
    and why. Messages come in file order, which for a bag recorded live is log-time order.
    """

    def __init__(self, bag_dir: str | Path, *, store: Typestore | None = None) -> None:
        self.path = Path(bag_dir)
        self._store = store
        self._older: dict[str, OlderDefinition] = {}  # our types the bag holds in an older definition
        self.file = self._locate()
        self.custom_data: dict[str, str] = {}
        meta = self.path / "metadata.yaml"
        if self.path.is_dir() and meta.is_file():
            info, _ = _load_metadata(meta)
            if info is not None:
                custom = info["rosbag2_bagfile_information"].get("custom_data") or {}
                self.custom_data = {str(k): str(v) for k, v in custom.items()}
        self.damage: str | None = None
        self._types: dict[int, str] = {}  # schema id -> message type
        self._definitions: dict[str, str] = {}  # message type -> definition embedded in the bag
        self.topics: dict[str, str] = {}
        """Topic name -> message type, of the channels in the readable part of the file."""
        for record in self._records():
            if isinstance(record, Channel) and record.topic not in self.topics:
                self.topics[record.topic] = self._types.get(record.schema_id, "")
        self.damage = None  # found again, in order, by messages()
        self._check_definitions()

    @property
    def store(self) -> Typestore:
        return typestore() if self._store is None else self._store

    @property
    def provenance(self) -> str | None:
        return self.custom_data.get(PROVENANCE_KEY)

    def _locate(self) -> Path:
        p = self.path
        if p.is_file() and p.suffix.lower() == ".mcap":
            return p
        if p.is_dir():
            mcaps = sorted(x for x in p.iterdir() if x.suffix.lower() == ".mcap" and x.is_file())
            if len(mcaps) == 1:
                return mcaps[0]
            raise BagError(f"{p}: {len(mcaps)} .mcap files; a damaged bag is salvaged from a single one")
        raise BagError(f"{p}: not an MCAP bag to salvage")

    def _records(self) -> Iterator[Any]:
        """Records in file order, up to the damage (then :attr:`damage` says what it was); the
        schemas are noted on the way (their type names and embedded definitions)."""
        try:
            f = self.file.open("rb")
        except OSError as error:
            raise BagError(f"{self.file}: cannot read: {error}") from error
        with f:
            if f.read(len(mcapfile.MAGIC)) != mcapfile.MAGIC:
                raise BagError(f"{self.file}: does not start with the MCAP magic: nothing to salvage")
            f.seek(0)
            reader = StreamReader(f, validate_crcs=True, emit_chunks=True)
            try:
                for outer in reader.records:
                    if isinstance(outer, Chunk):  # decompressed here, once its size is judged
                        if outer.uncompressed_size > mcapfile.MAX_CHUNK_BYTES:
                            self.damage = (f"{self.file}: the chunk ending at byte {f.tell()} decompresses to "
                                           f"{outer.uncompressed_size:,} bytes, beyond the "
                                           f"{mcapfile.MAX_CHUNK_BYTES / 2**20:g} MiB a chunk may take in memory; "
                                           "read up to the chunk before it")
                            return
                        inner = breakup_chunk(outer, validate_crc=True)
                    else:
                        inner = [outer]
                    for record in inner:
                        if isinstance(record, Schema):
                            self._types[record.id] = record.name
                            self._definitions[record.name] = record.data.decode("utf-8", "replace")
                        yield record
            except (McapError, zstandard.ZstdError, *_READ_ERRORS) as error:
                # the stream reader's EndOfFile, or a struct.error on a partial record: the file
                # ends inside a record; anything else is bytes that do not make the record they should
                cut = isinstance(error, (EndOfFile, struct.error))
                why = "cut short" if cut else f"damaged ({type(error).__name__}: {error})"
                self.damage = f"{self.file}: {why} at byte {f.tell()}; read up to the last whole chunk before it"

    def _check_definitions(self) -> None:
        """As :meth:`BagReader._check_definitions`, from the schemas of the readable part."""
        store = self.store
        for topic, msgtype in self.topics.items():
            if not msgtype.startswith(f"{PACKAGE}/"):
                continue
            if msgtype not in store.types:
                raise BagError(f"{self.file}: {topic}: unknown type {msgtype}")
            text = self._definitions.get(msgtype, "")
            if _embedded_fields(text, msgtype) == store.fielddefs[msgtype]:
                continue
            older = OlderDefinition.of(store, msgtype, text)
            if older is None:
                raise BagError(f"{self.file}: {topic}: {msgtype} in the bag differs from the current definition; "
                               "regenerate the bag or check out matching msgs")
            self._older[msgtype] = older

    def messages(self, topics: Iterable[str] | None = None, *,
                 skipped: Callable[[str], None] | None = None) -> Iterator[BagMessage]:
        """Messages (of ``topics``, all of them if None) in file order, up to the damage; a
        message that cannot be decoded is damage too, or, with ``skipped``, said to it and
        passed over (as :meth:`BagReader.messages`)."""
        wanted = None if topics is None else set(topics)
        store = self.store
        channels: dict[int, tuple[str, str]] = {}
        for record in self._records():
            if isinstance(record, Channel):
                channels[record.id] = (record.topic, self._types.get(record.schema_id, ""))
            elif isinstance(record, Message) and record.channel_id in channels:
                topic, msgtype = channels[record.channel_id]
                if wanted is not None and topic not in wanted:
                    continue
                message = _undecodable(store, record.data, msgtype, topic, record.log_time, self._older)
                if isinstance(message, str):
                    if skipped is None:
                        self.damage = f"{self.file}: {message}"
                        return
                    skipped(message)
                    continue
                yield BagMessage(topic, msgtype, record.log_time, message)


def read_messages(bag_dir: str | Path, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Yield ``(topic, msgtype, log_time_ns, message)`` from a bag, in log-time order."""
    with BagReader(bag_dir) as reader:
        yield from reader.messages(topics)


def read_envelope(bag_dir: str | Path, *, topic: str = ENVELOPE_TOPIC) -> Iterator[EnvelopeChunk]:
    """Yield the ADC stream of a bag as :class:`EnvelopeChunk` objects, in order.

    Codes are passed on as recorded, also those outside ``adc_bits`` (what corruption or a
    misconfigured ADC produces): judging them is the stream stage's job, not the reader's.
    """
    with BagReader(bag_dir) as reader:
        carried = reader.topics.get(topic)
        if carried is not None and carried != ENVELOPE_SAMPLES:
            raise BagError(f"{bag_dir}: {topic} carries {carried}, not {ENVELOPE_SAMPLES}")
        for item in reader.messages([topic]):
            try:
                yield envelope_from_msg(item.message)
            except (AttributeError, ValueError) as error:
                raise BagError(
                    f"{bag_dir}: {topic} at {item.log_time_ns} ns is not a valid envelope chunk: "
                    f"{error}"
                ) from error
