"""How samples are stored in a recording: the six formats a source reads, named as SigMF names them.

A complex baseband (I/Q) recording stores each sample as two numbers, I then Q; a real envelope
recording stores one number per sample (the output of an envelope detector's ADC). The names are
SigMF ``core:datatype`` strings (``c``/``r`` complex or real, ``u``/``i``/``f`` unsigned, signed
or float, the bits per component, ``_le`` little-endian):

===========  ==================================================  ==========  ===============
format       typical producer                                    zero        rails
===========  ==================================================  ==========  ===============
``cu8``      RTL-SDR (``rtl_sdr``): unsigned 8-bit I/Q           127.5       0, 255
``ci8``      HackRF (``hackrf_transfer``): signed 8-bit I/Q      0           -128, 127
``ci16_le``  USRP, bladeRF, LimeSDR, SDRplay: signed 16-bit I/Q  0           -32768, 32767
``cf32_le``  GNU Radio file sink, SDR++, numpy: float32 I/Q      0           none
``ri16_le``  an envelope detector's ADC codes, int16             0           -32768, 32767
``rf32_le``  an envelope in float32 (volts or arbitrary units)   0           none
===========  ==================================================  ==========  ===============

The *zero* is the value a component takes with no signal: an RTL-SDR's ADC is unsigned, so its
zero sits between codes 127 and 128. The *rails* are the values an integer ADC is pinned at when
driven past full scale: a sample with a component at a rail was clipped in the recording, and
what the signal really was there is unknown. Float formats have no rails.
"""

from __future__ import annotations

import enum
import os
from pathlib import Path

import numpy as np

# File name endings whose format is unambiguous (lower case). ``.bin``, ``.raw``, ``.iq`` and
# ``.dat`` are not here: RTL-SDR and HackRF tools (and many others) all write them.
_EXTENSIONS: dict[str, str] = {
    ".cu8": "cu8",
    ".cs8": "ci8",
    ".ci8": "ci8",
    ".cs16": "ci16_le",
    ".ci16": "ci16_le",
    ".cf32": "cf32_le",
    ".cfile": "cf32_le",
    ".fc32": "cf32_le",
    ".ri16": "ri16_le",
    ".rf32": "rf32_le",
    ".f32": "rf32_le",
}

SIGMF_SUFFIXES = (".sigmf-meta", ".sigmf-data", ".sigmf", ".sigmf.gz", ".sigmf.xz", ".sigmf.zip")
"""File name endings of a SigMF recording: metadata, dataset, or (compressed) archive."""


def is_sigmf_path(path: str | os.PathLike) -> bool:
    """Whether ``path`` names a SigMF recording (its metadata, dataset or archive) by its name."""
    return os.fspath(path).lower().endswith(SIGMF_SUFFIXES)


class SampleFormat(enum.Enum):
    """How one sample is stored; the value is the SigMF ``core:datatype`` name."""

    CU8 = "cu8"
    CI8 = "ci8"
    CI16_LE = "ci16_le"
    CF32_LE = "cf32_le"
    RI16_LE = "ri16_le"
    RF32_LE = "rf32_le"

    @classmethod
    def names(cls) -> str:
        """The format names, for messages: ``cu8, ci8, ...``."""
        return ", ".join(f.value for f in cls)

    @classmethod
    def parse(cls, name: str | SampleFormat) -> SampleFormat:
        """The format called ``name`` (case-insensitive), or ValueError listing the names."""
        if isinstance(name, SampleFormat):
            return name
        try:
            return cls(str(name).strip().lower())
        except ValueError:
            raise ValueError(f"unknown sample format {name!r}; give one of {cls.names()}") from None

    @classmethod
    def from_sigmf(cls, datatype: object, where: str) -> SampleFormat:
        """The format of a SigMF ``core:datatype``, or ValueError naming ``where`` and why not."""
        text = str(datatype).strip().lower()
        try:
            return cls(text)
        except ValueError:
            pass
        if text.endswith("_be"):
            cause = "big-endian samples are not supported"
        else:
            cause = "not one of the supported datatypes"
        raise ValueError(f"{where}: core:datatype {datatype!r}: {cause}; supported: {cls.names()}")

    @classmethod
    def from_extension(cls, path: str | os.PathLike) -> SampleFormat:
        """The format a raw file's extension names, or ValueError when it does not tell.

        SigMF recordings say their format in their metadata, not in their name: open those with
        :class:`~deepsync.sources.SigmfSource` (or ``open_source``).
        """
        name = Path(path).name
        if is_sigmf_path(name):
            raise ValueError(
                f"{os.fspath(path)} is a SigMF recording: its sample format is in its metadata "
                "(open it with SigmfSource or open_source)"
            )
        found = _EXTENSIONS.get(Path(name).suffix.lower())
        if found is None:
            raise ValueError(
                f"cannot tell the sample format of {os.fspath(path)} from its extension; give one of "
                f"{cls.names()} (extensions read without one: {', '.join(sorted(_EXTENSIONS))})"
            )
        return cls(found)

    @property
    def is_complex(self) -> bool:
        """Two components (I, Q) per sample, or one (a real envelope)."""
        return self.value.startswith("c")

    @property
    def components(self) -> int:
        return 2 if self.is_complex else 1

    @property
    def component_dtype(self) -> np.dtype:
        """The numpy dtype of one stored component (little-endian where it matters)."""
        return np.dtype(_DTYPES[self])

    @property
    def bytes_per_sample(self) -> int:
        return self.components * self.component_dtype.itemsize

    @property
    def zero(self) -> float:
        """The component value with no signal (127.5 for the unsigned RTL-SDR codes)."""
        return 127.5 if self is SampleFormat.CU8 else 0.0

    @property
    def rails(self) -> tuple[float, float] | None:
        """The lowest and highest component value (an integer ADC's rails), None for floats."""
        dtype = self.component_dtype
        if dtype.kind == "f":
            return None
        info = np.iinfo(dtype)
        return float(info.min), float(info.max)


_DTYPES = {
    SampleFormat.CU8: "u1",
    SampleFormat.CI8: "i1",
    SampleFormat.CI16_LE: "<i2",
    SampleFormat.CF32_LE: "<f4",
    SampleFormat.RI16_LE: "<i2",
    SampleFormat.RF32_LE: "<f4",
}
