"""SigMF recordings (https://sigmf.org): samples plus the metadata a raw file lacks.

Read with the ``sigmf`` package. From the metadata: the sample rate (``core:sample_rate``),
the sample format (``core:datatype``: one of :class:`SampleFormat`, one channel), the centre
frequency (``core:frequency`` of the first capture, optional) and the receiver time of sample 0
(``core:datetime`` of the first capture, optional; UTC, kept to the nanosecond). Samples are
read unscaled (``autoscale=False``) so the stored values and the rails are intact, and turned
into envelope codes by the same rule as raw files (:mod:`deepsync.sources.envelope`).

A recording the stream cannot represent honestly is refused: several channels (which one is the
envelope?), a capture that retunes (another carrier is another envelope), header bytes inside
the dataset after the first capture (they would be read as samples).
"""

from __future__ import annotations

import calendar
import math
import os
import re
import warnings
from datetime import datetime
from typing import Any

import numpy as np

from .base import FileSource, check_rate
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


def _dataset_path(path: str) -> str | None:
    """The ``.sigmf-data`` file next to a metadata or dataset path, if there is one (None for
    archives, and for datasets named otherwise by ``core:dataset``)."""
    lower = path.lower()
    for suffix in (".sigmf-meta", ".sigmf-data"):
        if lower.endswith(suffix):
            data = path[: -len(suffix)] + ".sigmf-data"
            return data if os.path.isfile(data) else None
    return None


def _open(path: str) -> Any:
    """The ``sigmf`` package's SigMFFile for ``path`` (unscaled), or ValueError naming it."""
    import sigmf  # imported here: only SigMF users pay for jsonschema & co

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
        handle = _open(name)
        try:
            self._read_metadata(name, handle, scale)
        except (AttributeError, TypeError, KeyError, IndexError) as error:  # a field of another shape than SigMF's
            raise ValueError(f"{name}: malformed SigMF metadata ({type(error).__name__}: {error})") from None

    def _read_metadata(self, name: str, handle: Any, scale: float | None) -> None:
        glob = handle.get_global_info()
        fmt = SampleFormat.from_sigmf(glob.get("core:datatype"), name)
        channels = glob.get("core:num_channels", 1)
        if channels != 1:
            raise ValueError(f"{name}: {channels} channels (core:num_channels); only one-channel recordings are read")
        rate = glob.get("core:sample_rate")
        if rate is None:
            raise ValueError(f"{name}: the metadata has no core:sample_rate")
        rate = check_rate(rate, name)
        captures = handle.get_captures()
        first = captures[0] if captures else {}
        center = first.get("core:frequency")
        if center is not None and not (isinstance(center, (int, float)) and math.isfinite(center)):
            raise ValueError(f"{name}: core:frequency {center!r} is not a number")
        for capture in captures[1:]:
            if capture.get("core:frequency", center) != center:
                raise ValueError(
                    f"{name}: the capture at sample {capture.get('core:sample_start')} retunes to "
                    f"{capture.get('core:frequency')!r} Hz from {center!r} Hz: one envelope stream is one carrier"
                )
            if capture.get("core:header_bytes", 0):
                raise ValueError(
                    f"{name}: the capture at sample {capture.get('core:sample_start')} has header bytes "
                    "inside the dataset; they would be read as samples"
                )
        stamp = 0 if first.get("core:datetime") is None else sigmf_datetime_ns(first["core:datetime"], name)
        n = len(handle)
        if n == 0:
            raise ValueError(f"{name}: the dataset is empty: no samples to read")
        self._handle = handle
        if fmt.is_complex:
            # Complex samples come back as complex64 (integers: converted exactly, not scaled);
            # a float32 view of them is the stored values, interleaved.
            def read(a: int, b: int) -> np.ndarray:
                return np.ascontiguousarray(handle[a:b], dtype=np.complex64).view(np.float32)
        else:
            def read(a: int, b: int) -> np.ndarray:
                return np.asarray(handle[a:b])
        self._setup(name, fmt, rate, n, read, scale, stamp, None if center is None else float(center))

    @property
    def description(self) -> str:
        return self._describe("SigMF recording")
