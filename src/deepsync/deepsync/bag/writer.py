"""Atomic rosbag2 (version 9, MCAP, zstd chunks) writer for DeepSync streams and ground truth.

A bag is written into a hidden temporary sibling of ``out_dir`` and renamed into place only when
the ``with`` block finishes cleanly, so a crash, a Ctrl-C or a failed simulation never leaves a
half-written bag that looks valid (``ros2 bag play`` would happily play the first half).

Before the rename, :func:`~deepsync.bag.mcapfile.seal` fills in the MCAP CRCs that rosbags
leaves at 0 (every chunk, the data section, the summary) and adds the provenance as an MCAP
metadata record (``deepsync``: ``provenance``), so that corruption is detected when the bag is
read and the ``.mcap`` file copied on its own still says how it was made.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import tempfile
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

from rosbags.interfaces import Connection, Qos
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys.store import Typestore

from ..configio import ConfigError, check_tree
from ..outputs import partial_prefix, remove_abandoned
from ..types import EnvelopeChunk, StackArrivals
from .convert import (
    cell_timing_array_to_msg,
    envelope_to_msg,
    pose_to_msg,
    stamp_to_ns,
)
from .errors import BagError, BagExistsError
from .mcapfile import DEEPSYNC_RECORD, provenance_entries, seal
from .msgdefs import typestore
from .topics import (
    ENVELOPE_TOPIC,
    RELIABLE_QOS,
    TOPIC_QOS,
    TRUTH_CELL_TIMING_TOPIC,
    TRUTH_POSE_TOPIC,
)

if TYPE_CHECKING:
    from typing import Self  # Python >= 3.11; only for type checkers

PROVENANCE_KEY = "deepsync.provenance"
"""``custom_data`` key of the provenance string (command line, scenario, seed); the ``.mcap``
carries it too, in its ``deepsync`` metadata record (key ``provenance``)."""
ROSBAG2_VERSION = 9


def provenance_document(text: str | None, where: object) -> dict:
    """A bag's provenance as the JSON mapping DeepSync writes (empty for none), or BagError
    naming the bag: not JSON, not a mapping, or nested past what the project's guarded loader
    allows (:func:`deepsync.configio.check_tree`; a JSON of a hundred thousand brackets raised
    RecursionError)."""
    if not text:
        return {}
    try:
        document = json.loads(text)
    except (ValueError, RecursionError) as error:
        reason = "nested too deeply" if isinstance(error, RecursionError) else f"not JSON: {error}"
        raise BagError(f"{where}: unreadable provenance ({reason})") from None
    if not isinstance(document, dict):
        raise BagError(f"{where}: unreadable provenance (a JSON {type(document).__name__}, not a mapping)")
    try:
        check_tree(document, f"{where}: provenance")
    except ConfigError as error:
        raise BagError(str(error)) from None
    return document


def _is_bag_dir(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


class BagWriter:
    """Write a rosbag2 MCAP bag atomically; use as a context manager.

    Topics are created on first use with the QoS of :data:`~deepsync.bag.topics.TOPIC_QOS`
    (reliable for unknown topics). The log time of every message is its header stamp, so
    replay timing follows the ADC clock, not the wall clock of the simulation.

    ``out_dir`` must not exist, unless ``overwrite=True`` and it is a rosbag2 directory; it is
    then replaced only after the new bag is complete.
    """

    def __init__(
        self,
        out_dir: str | Path,
        *,
        overwrite: bool = False,
        provenance: str | None = None,
        custom_data: Mapping[str, str] | None = None,
        store: Typestore | None = None,
    ) -> None:
        self.path = Path(out_dir)
        self.overwrite = overwrite
        self._store = store
        self._custom: dict[str, str] = {}
        for key, value in (custom_data or {}).items():
            self.set_custom_data(key, value)
        if provenance is not None:
            self.set_custom_data(PROVENANCE_KEY, provenance)
        self._check_target()
        self._tmp: Path | None = None
        self._writer: Writer | None = None
        self._connections: dict[str, Connection] = {}
        self._used = False

    # -- target handling ------------------------------------------------------------------

    def _check_target(self) -> None:
        if not self.path.exists() and not self.path.is_symlink():
            return
        if not self.overwrite:
            raise BagExistsError(f"{self.path}: exists already; pass overwrite=True to replace it")
        if not _is_bag_dir(self.path):
            raise BagExistsError(
                f"{self.path}: exists and is not a rosbag2 directory (no metadata.yaml); "
                "refusing to replace it even with overwrite=True"
            )

    def _commit(self, built: Path) -> None:
        """Move the finished bag to ``self.path`` (replacing an old bag only now)."""
        assert self._tmp is not None
        self._check_target()
        if self.path.exists():
            old = self._tmp / "replaced"
            self.path.rename(old)  # same filesystem: atomic; the old bag is deleted below
        built.rename(self.path)

    def _cleanup(self) -> None:
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None

    def _seal(self, built: Path) -> None:
        """Add the CRCs rosbags leaves at 0, and the provenance as an MCAP metadata record, to
        the finished file (still in the partial directory, so a failure leaves no bag)."""
        extra = {}
        provenance = self._custom.get(PROVENANCE_KEY)
        if provenance is not None:
            extra[DEEPSYNC_RECORD] = provenance_entries(provenance)
        seal(built / f"{built.name}.mcap", extra)

    # -- context manager --------------------------------------------------------------------

    def __enter__(self) -> Self:
        if self._used:
            raise BagError(f"{self.path}: a BagWriter writes one bag; create a new one")
        self._used = True
        self._check_target()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            remove_abandoned(self.path)  # what a killed writer of this bag left
            self._tmp = Path(tempfile.mkdtemp(prefix=partial_prefix(self.path), suffix=".partial",
                                              dir=self.path.parent))
        except OSError as error:
            raise BagError(f"{self.path}: cannot write a bag there ({error.strerror})") from None
        try:
            # rosbags names the storage file after its directory: <name>/<name>.mcap
            writer = Writer(
                self._tmp / self.path.name,
                version=ROSBAG2_VERSION,
                storage_plugin=StoragePlugin.MCAP,
            )
            writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            writer.open()
        except BaseException:
            self._cleanup()
            raise
        self._writer = writer
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> bool:
        writer, self._writer = self._writer, None
        if writer is None:
            return False
        try:
            if exc_type is not None:
                with contextlib.suppress(Exception):  # the original exception is what matters
                    writer.abort()
                return False
            for key, value in self._custom.items():
                writer.set_custom_data(key, value)
            try:
                writer.close()
                self._seal(writer.path)
            except Exception as error:
                raise BagError(f"{self.path}: could not finish the bag: {error}") from error
            self._commit(writer.path)
            return False
        finally:
            self._cleanup()

    # -- writing ------------------------------------------------------------------------------

    @property
    def store(self) -> Typestore:
        """Typestore used for serialisation (the shared one unless given)."""
        return typestore() if self._store is None else self._store

    def set_custom_data(self, key: str, value: str) -> None:
        """Record a key/value string in ``metadata.yaml`` ``custom_data`` (written on close)."""
        if not isinstance(key, str) or not isinstance(value, str):
            raise TypeError(f"custom data must be str -> str, got {key!r}: {value!r}")
        self._custom[key] = value

    def set_provenance(self, text: str) -> None:
        """Record how this bag was made (command line, scenario, seed) under ``PROVENANCE_KEY``."""
        self.set_custom_data(PROVENANCE_KEY, text)

    def _connection(self, topic: str, msgtype: str, qos: Qos | None) -> Connection:
        assert self._writer is not None
        conn = self._connections.get(topic)
        if conn is None:
            offered = qos or TOPIC_QOS.get(topic, RELIABLE_QOS)
            conn = self._writer.add_connection(
                topic, msgtype, typestore=self.store, offered_qos_profiles=[offered]
            )
            self._connections[topic] = conn
        elif conn.msgtype != msgtype:
            raise BagError(
                f"{self.path}: topic {topic} carries {conn.msgtype}, cannot also write {msgtype}"
            )
        return conn

    def write(self, topic: str, message: Any, *, qos: Qos | None = None) -> None:
        """Write one rosbags message object; its ``header.stamp`` becomes the log time.

        ``qos`` is the offered profile used if this is the topic's first message.
        """
        if self._writer is None:
            raise BagError(f"{self.path}: write() outside the 'with BagWriter(...)' block")
        msgtype = getattr(message, "__msgtype__", None)
        header = getattr(message, "header", None)
        if msgtype is None or header is None:
            raise TypeError(
                f"expected a rosbags message with a std_msgs/Header, got {type(message).__name__}"
            )
        log_time_ns = stamp_to_ns(header.stamp)
        conn = self._connection(topic, msgtype, qos)
        try:
            data = self.store.serialize_cdr(message, msgtype)
        except Exception as error:
            raise BagError(
                f"{self.path}: cannot serialise {msgtype} for {topic}: {error}"
            ) from error
        try:
            self._writer.write(conn, log_time_ns, data)
        except OSError as error:  # a full disk: the bag the user named, not rosbags' file inside the partial one
            raise OSError(error.errno, error.strerror or str(error), str(self.path)) from None

    def write_envelope(self, chunk: EnvelopeChunk, *, topic: str = ENVELOPE_TOPIC) -> None:
        """Write one ADC chunk as ``deepsync_msgs/msg/EnvelopeSamples``."""
        self.write(topic, envelope_to_msg(chunk, store=self.store))

    def write_truth_pose(
        self, stamp_ns: int, x: float, y: float, z: float, *, topic: str = TRUTH_POSE_TOPIC
    ) -> None:
        """Write the true receiver position (ENU metres in ``map``) as ``PoseStamped``."""
        self.write(topic, pose_to_msg(stamp_ns, x, y, z, store=self.store))

    def write_truth_cell_timing(self, arrivals: StackArrivals, *, topic: str = TRUTH_CELL_TIMING_TOPIC) -> None:
        """Write true per-cell times of arrival as ``deepsync_msgs/msg/CellTimingArray``."""
        self.write(topic, cell_timing_array_to_msg(arrivals, store=self.store))
