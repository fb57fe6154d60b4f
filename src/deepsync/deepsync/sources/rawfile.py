"""Raw headerless sample files (``rtl_sdr`` output, ``hackrf_transfer -r``, a GNU Radio file sink,
an envelope ADC dump): samples and nothing else, so the format and the rate come from the user.
"""

from __future__ import annotations

import os

import numpy as np

from .base import FileSource, centred_iq, check_rate
from .formats import SampleFormat, is_sigmf_path
from .sigmf_recording import SigmfSource


def _open_raw(path: str | os.PathLike, sample_format: SampleFormat) -> tuple[str, int]:
    """(path, samples in it), or ValueError naming the file and the cause."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise ValueError(f"{path}: no such file")
    if not os.path.isfile(path):
        raise ValueError(f"{path}: not a file")
    size = os.path.getsize(path)
    if size == 0:
        raise ValueError(f"{path}: the file is empty (0 bytes): no samples to read")
    if size % sample_format.bytes_per_sample:
        raise ValueError(
            f"{path}: {size} bytes is not a whole number of {sample_format.value} samples "
            f"({sample_format.bytes_per_sample} bytes each): a truncated recording, or another format?"
        )
    return path, size // sample_format.bytes_per_sample


def _block_reader(path: str, sample_format: SampleFormat):
    """``read(start, stop)``: the stored values of samples ``start:stop``, read from the file.
    Memory holds the block alone: a memory map keeps the pages it has touched resident, and
    streaming a 20 GB file through one grew the process to 20 GB."""
    dtype, k = sample_format.component_dtype, sample_format.components

    def read(start: int, stop: int) -> np.ndarray:
        with open(path, "rb") as handle:
            handle.seek(start * k * dtype.itemsize)
            return np.fromfile(handle, dtype=dtype, count=(stop - start) * k)

    return read


class RawFileSource(FileSource):
    """A raw headerless recording in one of the :class:`SampleFormat` s.

    ``sample_rate`` (Hz) must be given (a raw file does not say it) and be one that sync
    templates can be built for. ``scale`` overrides the default taken from the recording (see
    :mod:`deepsync.sources.envelope`); ``stamp_ns`` is the receiver time of sample 0. The
    front end is :func:`~deepsync.sources.squared_iq_frontend` for I/Q formats, the default
    envelope-detector chain at ``sample_rate`` for real envelope formats. ``center_hz`` is None:
    the file does not say it.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        sample_format: SampleFormat | str,
        sample_rate: float | None,
        *,
        scale: float | None = None,
        stamp_ns: int = 0,
    ) -> None:
        name = os.fspath(path)
        try:
            fmt = SampleFormat.parse(sample_format)
        except ValueError as error:
            raise ValueError(f"{name}: {error}") from None
        name, n_samples = _open_raw(name, fmt)
        rate = check_rate(sample_rate, name)
        self._setup(name, fmt, rate, n_samples, _block_reader(name, fmt), scale, stamp_ns, None)

    @property
    def description(self) -> str:
        return self._describe("raw file")


def read_iq(path: str | os.PathLike, sample_format: SampleFormat | str | None = None) -> np.ndarray:
    """All samples of a complex I/Q recording as complex64 ``(I - zero) + j (Q - zero)``.

    ``path`` is a raw file (format given, or guessed from the extension) or a SigMF recording
    (format from its metadata; a given one must agree). The zero is 127.5 for ``cu8`` (the
    RTL-SDR's unsigned codes), 0 otherwise, so the samples are centred; no other scaling. What
    the coherent (complex-domain) search in :mod:`deepsync.testing.coherent` reads.
    """
    name = os.fspath(path)
    if is_sigmf_path(name):
        source = SigmfSource(name, scale=1.0)  # the scale is not used: skip the pass over the file
        if sample_format is not None and SampleFormat.parse(sample_format) is not source.sample_format:
            raise ValueError(
                f"{name}: its metadata says {source.sample_format.value}, not {SampleFormat.parse(sample_format).value}"
            )
        return source.read_iq()
    fmt = SampleFormat.from_extension(name) if sample_format is None else SampleFormat.parse(sample_format)
    if not fmt.is_complex:
        raise ValueError(f"{name}: {fmt.value} is a real envelope format, not complex I/Q")
    name, _ = _open_raw(name, fmt)
    return centred_iq(np.fromfile(name, dtype=fmt.component_dtype), fmt)
