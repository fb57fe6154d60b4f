"""Reading DeepSync bags back: typed messages, or the ADC stream as core chunks.

Whatever goes wrong underneath (missing path, not a bag, truncated or corrupt MCAP, a message
definition that changed since the bag was written) surfaces as one :class:`BagError` that names
the bag and the cause, instead of a KeyError or struct.error from deep inside rosbags.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, NamedTuple

from rosbags.rosbag2 import Reader, ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import TypesysError, get_types_from_msg
from rosbags.typesys.store import Typestore

from ..types import EnvelopeChunk
from .convert import envelope_from_msg
from .errors import BagError
from .msgdefs import PACKAGE, typestore
from .topics import ENVELOPE_TOPIC

if TYPE_CHECKING:
    from typing import Self  # Python >= 3.11; only for type checkers

try:  # what rosbags decompresses MCAP chunks with (stdlib from Python 3.14 on)
    from compression.zstd import ZstdError  # type: ignore[import-not-found]
except ImportError:  # pragma: no cover - depends on the Python version
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
)


class BagMessage(NamedTuple):
    """One deserialised message and where it sits in the bag."""

    topic: str
    msgtype: str
    log_time_ns: int
    message: Any


class BagReader:
    """Read a rosbag2 bag with the DeepSync typestore; use as a context manager."""

    def __init__(self, bag_dir: str | Path, *, store: Typestore | None = None) -> None:
        self.path = Path(bag_dir)
        self._store = store
        self._reader: Reader | None = None

    def _fail(self, cause: str, error: BaseException | None = None) -> BagError:
        detail = f": {error}" if error is not None and str(error) else ""
        return BagError(f"{self.path}: {cause}{detail}")

    def open(self) -> None:
        """Open the bag and check that our message definitions still match it."""
        if self._reader is not None:
            return
        if not self.path.exists():
            raise self._fail("no such bag (path does not exist)")
        if self.path.is_dir() and not (self.path / "metadata.yaml").is_file():
            raise self._fail("not a rosbag2 directory (no metadata.yaml)")
        try:
            reader = Reader(self.path)
            reader.open()
        except _READ_ERRORS as error:
            raise self._fail("cannot open bag", error) from error
        self._reader = reader
        try:
            self._check_definitions()
        except BaseException:
            self.close()
            raise

    def _check_definitions(self) -> None:
        """Refuse bags whose deepsync_msgs types differ from ours (stale bag or stale source).

        The type hash decides when it matches; when it does not, the field layout embedded in
        the bag decides, so a bag recorded by ``ros2 bag record`` on a robot is not refused
        only because its hash was computed by another implementation than rosbags'.
        """
        assert self._reader is not None
        store = self.store
        for conn in self._reader.connections:
            if not conn.msgtype.startswith(f"{PACKAGE}/"):
                continue
            if conn.msgtype not in store.types:
                raise self._fail(f"{conn.topic}: unknown type {conn.msgtype}")
            if conn.digest and conn.digest == store.hash_rihs01(conn.msgtype):
                continue
            if self._embedded_fields(conn) != store.fielddefs[conn.msgtype]:
                raise self._fail(
                    f"{conn.topic}: {conn.msgtype} in the bag differs from the current "
                    "definition; regenerate the bag or check out matching msgs"
                )

    @staticmethod
    def _embedded_fields(conn: Any) -> Any:
        """Field layout of ``conn``'s type as recorded in the bag, or None if unreadable."""
        text = getattr(conn.msgdef, "data", "") or ""
        try:
            own = text.split("=" * 80)[0]  # the type itself precedes its dependencies
            return get_types_from_msg(own, conn.msgtype).get(conn.msgtype)
        except _READ_ERRORS:
            return None

    def close(self) -> None:
        """Close the bag (idempotent)."""
        reader, self._reader = self._reader, None
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

    @property
    def store(self) -> Typestore:
        """Typestore used for deserialisation (the shared one unless given)."""
        return typestore() if self._store is None else self._store

    def _opened(self) -> Reader:
        if self._reader is None:
            raise BagError(f"{self.path}: bag is not open; use 'with BagReader(...)'")
        return self._reader

    @property
    def topics(self) -> dict[str, str]:
        """Topic name -> message type."""
        return {c.topic: c.msgtype for c in self._opened().connections}

    @property
    def message_counts(self) -> dict[str, int]:
        """Topic name -> number of messages (from the bag metadata)."""
        counts: dict[str, int] = {}
        for c in self._opened().connections:
            counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
        return counts

    @property
    def message_count(self) -> int:
        """Total number of messages in the bag."""
        return self._opened().message_count

    @property
    def duration_ns(self) -> int:
        """Log time from the first message to the last (0 for an empty bag)."""
        reader = self._opened()
        return reader.duration if reader.message_count else 0

    @property
    def custom_data(self) -> dict[str, str]:
        """``custom_data`` of ``metadata.yaml`` (e.g. the provenance string)."""
        metadata = self._opened().storage.metadata
        return dict(metadata.custom or {})

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
        """Messages in log-time order, optionally only those of ``topics`` (all must exist)."""
        reader = self._opened()
        connections = reader.connections
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
        stream = reader.messages(connections=connections)
        while True:
            try:
                item = next(stream, None)
                if item is None:
                    return
                conn, log_time_ns, raw = item
                message = store.deserialize_cdr(raw, conn.msgtype)
            except _READ_ERRORS as error:
                raise self._fail("cannot read message", error) from error
            yield BagMessage(conn.topic, conn.msgtype, log_time_ns, message)


def read_messages(bag_dir: str | Path, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Yield ``(topic, msgtype, log_time_ns, message)`` from a bag, in log-time order."""
    with BagReader(bag_dir) as reader:
        yield from reader.messages(topics)


def read_envelope(bag_dir: str | Path, *, topic: str = ENVELOPE_TOPIC) -> Iterator[EnvelopeChunk]:
    """Yield the ADC stream of a bag as :class:`EnvelopeChunk` objects, in order."""
    with BagReader(bag_dir) as reader:
        for item in reader.messages([topic]):
            try:
                yield envelope_from_msg(item.message)
            except (AttributeError, ValueError) as error:
                raise BagError(
                    f"{bag_dir}: {topic} at {item.log_time_ns} ns is not a valid envelope chunk: "
                    f"{error}"
                ) from error
