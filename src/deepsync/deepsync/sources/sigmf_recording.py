"""SigMF recordings (https://sigmf.org): samples plus the metadata a raw file lacks.

Read with the ``sigmf`` package. From the metadata: the sample rate (``core:sample_rate``),
the sample format (``core:datatype``: one of :class:`SampleFormat`, one channel), the centre
frequency (``core:frequency`` of the first capture, optional) and the receiver time of sample 0
(``core:datetime`` of the first capture, optional; UTC, kept to the nanosecond). Samples are
read unscaled (``autoscale=False``) so the stored values and the rails are intact, and turned
into envelope codes by the same rule as raw files (:mod:`deepsync.sources.envelope`).

The captures say how the samples were taken, and every field of them that shifts, cuts or
re-times samples is honoured or refused, never ignored:

* a capture whose ``core:global_index`` or ``core:datetime`` says samples were lost before it
  (a dropout: the receiver's count or clock jumped further than the samples recorded between)
  starts a new :class:`~deepsync.sources.base.Segment`: the stream's sample index jumps by what
  was lost (the sync stage reports a ``gap``) and its stamps follow the capture's datetime;
* captures out of order, at a ``sample_start`` beyond the dataset or before ``core:offset``, a
  count or a clock that runs backwards (samples recorded twice?), ``core:global_index`` and
  ``core:datetime`` that disagree about a dropout, header bytes in any capture but an NCD's
  first (they would be read as samples), ``core:metadata_only``: refused;
* ``core:trailing_bytes`` and a Non-Conforming Dataset's first ``core:header_bytes`` are left
  out of the samples.

A recording the stream cannot represent honestly is refused too: several channels (which one is
the envelope?), a capture that retunes (another carrier is another envelope).

An archive (``.sigmf``: a tar, plain, gzip, xz or bzip2; ``.sigmf.zip``) is read here, not by
the ``sigmf`` package, which reads a compressed archive whole into memory (a 23 MB ``.sigmf.gz``
of zeros took 5.4 GB): its dataset streams from the archive, block by block, and its SHA-512,
when the metadata gives one, is checked in one pass over it.
"""

from __future__ import annotations

import calendar
import hashlib
import math
import os
import re
import tarfile
import warnings
import zipfile
from datetime import datetime
from typing import Any

import numpy as np

from .base import FileSource, Segment, check_rate
from .formats import SampleFormat, is_sigmf_path

_DATETIME = re.compile(r"^(\d{4})-(\d{2})-(\d{2})T(\d{2}):(\d{2}):(\d{2})(?:\.(\d+))?Z$")


def sigmf_datetime_ns(text: object, where: str) -> int:
    """A SigMF ``core:datetime`` (ISO 8601 UTC, ``...Z``) as ns since the Unix epoch, exact to
    the nanosecond (``datetime`` keeps only microseconds)."""
    match = _DATETIME.match(str(text).strip())
    if match is None:
        raise ValueError(f"{where}: core:datetime {text!r} is not an ISO 8601 UTC time (YYYY-MM-DDTHH:MM:SS[.f]Z)")
    year, month, day, hour, minute, second = (int(g) for g in match.groups()[:6])
    try:
        datetime(year, month, day, hour, minute, min(second, 59))  # leap second 60 passes
    except ValueError as error:
        raise ValueError(f"{where}: core:datetime {text!r}: {error}") from None
    fraction = (match.group(7) or "")[:9].ljust(9, "0")
    seconds = calendar.timegm((year, month, day, hour, minute, second, 0, 0, 0))
    return seconds * 10**9 + int(fraction)


MAX_META_BYTES = 16 * 2**20
"""Largest SigMF metadata read (ours are a kB; a metadata file is held in memory whole)."""
CLOCK_TOLERANCE = 100e-6
"""How far a receiver's sample clock may run from the clock that wrote its captures' datetimes
(an uncalibrated RTL-SDR crystal: up to ~100 ppm): datetimes closer than this, and than their
own written precision, to what the samples between them take are one unbroken stream."""
_BLOCK_BYTES = 1 << 22  # what one read of a streamed archive member or a checksum pass takes at most


def _datetime_resolution_ns(text: object) -> int:
    """The precision a ``core:datetime`` is written to (ns): 1 s without a fraction, 1 ms
    with three fractional digits, ..."""
    match = _DATETIME.match(str(text).strip())
    digits = len(match.group(7) or "") if match else 0
    return 10 ** max(0, 9 - digits)


def _dataset_path(path: str) -> str | None:
    """The ``.sigmf-data`` file next to a metadata or dataset path, if there is one (None for
    archives, and for datasets named otherwise by ``core:dataset``)."""
    lower = path.lower()
    for suffix in (".sigmf-meta", ".sigmf-data"):
        if lower.endswith(suffix):
            data = path[: -len(suffix)] + ".sigmf-data"
            return data if os.path.isfile(data) else None
    return None


def _is_archive(path: str) -> bool:
    lower = path.lower()
    return not lower.endswith((".sigmf-meta", ".sigmf-data"))


def _metadata_file(path: str) -> str:
    lower = path.lower()
    return path[: -len(".sigmf-data")] + ".sigmf-meta" if lower.endswith(".sigmf-data") else path


def _open(path: str) -> tuple[Any, int, Any]:
    """(the metadata as a ``sigmf`` SigMFFile, samples in the dataset, ``read(start, stop)`` of
    the stored values) for ``path``, or ValueError naming it."""
    if _is_archive(path):
        archive = _Archive(path)
        return archive.handle, archive.n_samples, archive.read
    handle = _open_files(path)
    return handle, len(handle), None


def _metadata_handle(path: str, text: bytes) -> Any:
    """A ``sigmf`` SigMFFile of metadata ``text`` (checked against the SigMF schema)."""
    import sigmf

    try:
        handle = sigmf.SigMFFile(metadata=text, autoscale=False)
        handle.validate()
    except Exception as error:  # noqa: BLE001 - json, jsonschema and sigmf raise many kinds
        first = (str(error).strip().splitlines() or [type(error).__name__])[0].rstrip(":")
        raise ValueError(f"{path}: not a readable SigMF recording: {first}") from None
    return handle


class _Archive:
    """A SigMF archive's metadata and its dataset, streamed from the archive: reads go forward
    through the member, and a read before the last one starts the member over, so memory holds
    one block whatever the archive's size and compression."""

    def __init__(self, path: str) -> None:
        self.path = path
        with open(path, "rb") as handle:
            head = handle.read(4)
        try:
            if head == b"PK\x03\x04":
                self._zip = zipfile.ZipFile(path)
                members = {info.filename: info.file_size for info in self._zip.infolist() if not info.is_dir()}
                self._member = lambda name: self._zip.open(name)
            else:
                self._tar = tarfile.open(path, "r:*")
                found = {m.name: m for m in self._tar.getmembers() if m.isfile()}
                members = {name: m.size for name, m in found.items()}
                self._member = lambda name: self._tar.extractfile(found[name])
        except (tarfile.TarError, zipfile.BadZipFile, OSError, EOFError, ValueError) as error:
            first = (str(error).strip().splitlines() or [type(error).__name__])[0].rstrip(":")
            raise ValueError(f"{path}: not a readable SigMF recording: {first} "
                             "(an archive is a tar or zip file)") from None
        metas = sorted(name for name in members if name.endswith(".sigmf-meta"))
        if len(metas) != 1:
            raise ValueError(f"{path}: the archive holds {len(metas)} SigMF metadata files"
                             + (f" ({', '.join(metas[:4])}): extract the recording to read" if metas else ""))
        if members[metas[0]] > MAX_META_BYTES:
            raise ValueError(f"{path}: its metadata {metas[0]} is {members[metas[0]]:,} bytes, more than the "
                             f"{MAX_META_BYTES // 2**20} MiB a SigMF metadata file may take")
        with self._member(metas[0]) as member:
            self.handle = _metadata_handle(path, member.read(MAX_META_BYTES + 1))
        glob = self.handle.get_global_info()
        named = glob.get("core:dataset")
        data = metas[0][: -len(".sigmf-meta")] + ".sigmf-data"
        datasets = [name for name in members if name.endswith(".sigmf-data")]
        if data not in members:
            data = next((name for name in members if isinstance(named, str) and name.endswith(named)),
                        datasets[0] if len(datasets) == 1 else None)
        if data is None:
            raise ValueError(f"{path}: no dataset for {metas[0]} in the archive")
        self._data = data
        captures = self.handle.get_captures()
        first = captures[0] if captures and isinstance(captures[0], dict) else {}
        self._header = int(first.get("core:header_bytes", 0) or 0) if named else 0
        trailing = int(glob.get("core:trailing_bytes", 0) or 0)
        fmt = SampleFormat.from_sigmf(glob.get("core:datatype"), path)
        self._dtype = fmt.component_dtype
        self._sample_bytes = fmt.bytes_per_sample
        sample_bytes = members[data] - self._header - trailing
        if sample_bytes < 0 or sample_bytes % self._sample_bytes:
            raise ValueError(f"{path}: the dataset ({members[data]} bytes) is not a whole number of samples: a "
                             "truncated recording?")
        self.n_samples = sample_bytes // self._sample_bytes
        self._stream: Any = None
        self._at = 0
        digest = glob.get("core:sha512")
        if digest is not None:
            self._check_digest(str(digest), members[data])

    def _check_digest(self, digest: str, size: int) -> None:
        """The dataset's SHA-512 (of the whole member, as the sigmf package computes it) against
        the metadata's, in one pass."""
        sha = hashlib.sha512()
        with self._member(self._data) as member:
            while block := member.read(_BLOCK_BYTES):
                sha.update(block)
        if sha.hexdigest() != digest.lower():
            raise ValueError(f"{self.path}: not a readable SigMF recording: the dataset's SHA-512 does not match its "
                             "metadata's core:sha512 (a damaged or altered recording)")

    def _bytes(self, offset: int, size: int) -> bytes:
        if self._stream is None or offset < self._at:
            if self._stream is not None:
                self._stream.close()
            self._stream, self._at = self._member(self._data), 0
        while self._at < offset:  # forward: read and drop (compressed members cannot seek cheaply)
            skipped = len(self._stream.read(min(_BLOCK_BYTES, offset - self._at)))
            if not skipped:
                break
            self._at += skipped
        data = self._stream.read(size)
        self._at += len(data)
        if len(data) != size:
            raise ValueError(f"{self.path}: the archive ends inside its dataset (at byte {self._at} of {self._data}): "
                             "a truncated archive?")
        return data

    def read(self, start: int, stop: int) -> np.ndarray:
        """The stored values of samples ``start:stop``, interleaved."""
        data = self._bytes(self._header + start * self._sample_bytes, (stop - start) * self._sample_bytes)
        return np.frombuffer(data, dtype=self._dtype)


def _open_files(path: str) -> Any:
    """The ``sigmf`` package's SigMFFile for a ``.sigmf-meta`` / ``.sigmf-data`` pair (unscaled,
    the dataset memory-mapped), or ValueError naming it."""
    import sigmf  # imported here: only SigMF users pay for jsonschema & co

    meta = _metadata_file(path)
    if os.path.isfile(meta) and os.path.getsize(meta) > MAX_META_BYTES:
        raise ValueError(f"{path}: its metadata is {os.path.getsize(meta):,} bytes, more than the "
                         f"{MAX_META_BYTES // 2**20} MiB a SigMF metadata file may take")
    data = _dataset_path(path)
    size = None if data is None else os.path.getsize(data)
    if size == 0:
        raise ValueError(f"{path}: the dataset {os.path.basename(data)} is empty (0 bytes): no samples to read")
    handle: Any = None
    failure: Exception | None = None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            handle = sigmf.fromfile(path, autoscale=False)
        except Exception as error:  # noqa: BLE001 - a malformed file makes sigmf's parsers raise many kinds
            failure = error
    for warning in caught:  # sigmf only warns of a partial sample, then may fail on it
        text = str(warning.message)
        if "integer number of samples" in text:
            count = "" if size is None else f" ({size} bytes)"
            raise ValueError(f"{path}: the dataset{count} is not a whole number of samples: a truncated recording?")
    if failure is not None:
        first = (str(failure).strip().splitlines() or [type(failure).__name__])[0].rstrip(":")
        raise ValueError(f"{path}: not a readable SigMF recording: {first}")
    for warning in caught:
        text = str(warning.message)
        if issubclass(warning.category, UserWarning) and "final annotation" not in text:
            warnings.warn(f"{path}: {text}", stacklevel=3)  # annotations are not our business
    if not isinstance(handle, sigmf.SigMFFile):
        raise ValueError(f"{path}: a SigMF collection, not one recording; open one of its recordings")
    if handle.data_file is None and getattr(handle, "data_buffer", None) is None:
        raise ValueError(f"{path}: no dataset: no .sigmf-data file beside the metadata")
    return handle


def _handle_reader(handle: Any, fmt: SampleFormat) -> Any:
    """``read(start, stop)`` of the stored values, interleaved, through the sigmf package's map."""
    if fmt.is_complex:
        # Complex samples come back as complex64 (integers: converted exactly, not scaled);
        # a float32 view of them is the stored values, interleaved.
        return lambda a, b: np.ascontiguousarray(handle[a:b], dtype=np.complex64).view(np.float32)
    return lambda a, b: np.asarray(handle[a:b])


def _index(value: object, what: str, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{where}: {what} {value!r} is not a sample index (a whole number >= 0)")
    return value


def capture_segments(captures: list[dict], offset: object, n_samples: int, sample_rate: float,
                     where: str) -> tuple[Segment, ...]:
    """The runs of samples a recording's captures describe (module docstring): a new segment
    where a capture's ``core:global_index`` or ``core:datetime`` says samples were lost before
    it. ValueError naming the capture for captures out of order or beyond the dataset, a count
    or a clock that goes back, and the two disagreeing about a dropout."""
    offset = _index(offset if offset is not None else 0, "core:offset", where)
    captures = list(captures) or [{"core:sample_start": offset}]
    starts: list[tuple[int, int]] = []  # (file sample, stream index) where a segment starts
    times: list[tuple[int, int, int]] = []  # (stream index, ns, resolution ns) of every capture's datetime
    previous: tuple[int, int, int] | None = None  # file sample, stream index and global index of the last capture
    for k, capture in enumerate(captures):
        raw = _index(capture.get("core:sample_start"), "core:sample_start", f"{where}: captures[{k}]")
        start, at = raw - offset, f"{where}: the capture at sample {raw}"
        if start < 0:
            raise ValueError(f"{at} lies before the dataset's first sample (core:offset {offset})")
        if start >= n_samples:
            raise ValueError(f"{at} lies beyond the dataset's {n_samples} samples")
        if previous is not None and start <= previous[0]:
            raise ValueError(f"{at} follows the one at sample {previous[0] + offset}: captures must be in order of "
                             "core:sample_start, each once")
        counted = capture.get("core:global_index")
        counted = raw if counted is None else _index(counted, "core:global_index", at)
        when = capture.get("core:datetime")
        stamp = None if when is None else sigmf_datetime_ns(when, at)
        if previous is None:
            index = start
        else:
            recorded = start - previous[0]
            lost = counted - previous[2] - recorded  # what the receiver's sample count says went missing
            if lost < 0:
                raise ValueError(f"{at}: core:global_index {counted} is {-lost} samples behind the samples recorded "
                                 "before it: the receiver's count goes back")
            if stamp is not None and times:
                last_index, last_ns, last_resolution = times[-1]
                expected = previous[1] + recorded + lost - last_index  # samples since the last datetime
                missing = (stamp - last_ns) * sample_rate / 1e9 - expected
                tolerance = (max(0.5, (last_resolution + _datetime_resolution_ns(when)) * sample_rate / 1e9)
                             + CLOCK_TOLERANCE * expected)
                if abs(missing) > tolerance and "core:global_index" in capture:
                    raise ValueError(f"{at}: its core:datetime and core:global_index disagree by {missing:+.0f} "
                                     "samples about what was lost before it")
                if missing < -tolerance:
                    raise ValueError(f"{at}: core:datetime {when!r} is {-missing / sample_rate * 1e3:.3f} ms earlier "
                                     "than the samples recorded before it take: the clock goes back")
                if missing > tolerance:
                    lost += round(missing)
            index = previous[1] + recorded + lost
            if lost:
                starts.append((start, index))
        if previous is None:
            starts.append((start, index))
        if stamp is not None:
            times.append((index, stamp, _datetime_resolution_ns(when)))
        previous = (start, index, counted)
    # samples before the first capture belong to its segment (it describes the recording from its start)
    starts[0] = (0, starts[0][1] - starts[0][0])
    stops = [start for start, _ in starts[1:]] + [n_samples]
    return tuple(Segment(start, stop, index, _stamp_at(index, times, sample_rate))
                 for (start, index), stop in zip(starts, stops))


def _stamp_at(index: int, times: list[tuple[int, int, int]], sample_rate: float) -> int:
    """Receiver time of stream sample ``index`` from the captures' datetimes: the last one at or
    before it, else the first (counted back); 0 without any (as a raw file)."""
    if not times:
        return 0
    at, ns, _ = next((t for t in reversed(times) if t[0] <= index), times[0])
    return ns + round((index - at) * 1e9 / sample_rate)


class SigmfSource(FileSource):
    """A SigMF recording: ``path`` is its ``.sigmf-meta``, its ``.sigmf-data`` or its archive
    (``.sigmf``, ``.sigmf.gz``, ...). ``scale`` overrides the default taken from the recording.

    The front end is that of :class:`~deepsync.sources.RawFileSource` for the same format and
    rate; ``center_hz`` and the stamp of sample 0 come from the metadata (None and 0 without).
    """

    def __init__(self, path: str | os.PathLike, *, scale: float | None = None) -> None:
        name = os.fspath(path)
        if not os.path.exists(name):
            raise ValueError(f"{name}: no such file")
        if not is_sigmf_path(name):
            raise ValueError(f"{name}: not a SigMF file name (.sigmf-meta, .sigmf-data or .sigmf archive)")
        handle, n, read = _open(name)
        try:
            self._read_metadata(name, handle, n, read, scale)
        except (AttributeError, TypeError, KeyError, IndexError) as error:  # a field of another shape than SigMF's
            raise ValueError(f"{name}: malformed SigMF metadata ({type(error).__name__}: {error})") from None

    def _read_metadata(self, name: str, handle: Any, n: int, read: Any, scale: float | None) -> None:
        glob = handle.get_global_info()
        fmt = SampleFormat.from_sigmf(glob.get("core:datatype"), name)
        channels = glob.get("core:num_channels", 1)
        if channels != 1:
            raise ValueError(f"{name}: {channels} channels (core:num_channels); only one-channel recordings are read")
        rate = glob.get("core:sample_rate")
        if rate is None:
            raise ValueError(f"{name}: the metadata has no core:sample_rate")
        rate = check_rate(rate, name)
        if glob.get("core:metadata_only"):
            raise ValueError(f"{name}: core:metadata_only: a recording distributed without its samples")
        captures = handle.get_captures()
        first = captures[0] if captures else {}
        center = first.get("core:frequency")
        if center is not None and not (isinstance(center, (int, float)) and math.isfinite(center)):
            raise ValueError(f"{name}: core:frequency {center!r} is not a number")
        for k, capture in enumerate(captures):
            if k and capture.get("core:frequency", center) != center:
                raise ValueError(
                    f"{name}: the capture at sample {capture.get('core:sample_start')} retunes to "
                    f"{capture.get('core:frequency')!r} Hz from {center!r} Hz: one envelope stream is one carrier"
                )
            if capture.get("core:header_bytes", 0) and (k or not glob.get("core:dataset")):
                raise ValueError(
                    f"{name}: the capture at sample {capture.get('core:sample_start')} has header bytes "
                    "inside the dataset; they would be read as samples"
                )
        if n == 0:
            raise ValueError(f"{name}: the dataset is empty: no samples to read")
        segments = capture_segments(captures, glob.get("core:offset", 0), n, rate, name)
        self._handle = handle
        self._setup(name, fmt, rate, n, read or _handle_reader(handle, fmt), scale, segments[0].stamp_ns,
                    None if center is None else float(center), segments)

    @property
    def description(self) -> str:
        return self._describe("SigMF recording")
