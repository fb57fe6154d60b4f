"""One entry point for every recording a user may have: :func:`open_source`."""

from __future__ import annotations

import math
import os

from .bagfile import BagSource, is_bag_path
from .base import Source
from .formats import SampleFormat, is_sigmf_path
from .rawfile import RawFileSource
from .sigmf_recording import SigmfSource
from .simulated import SimulatorSource, is_scenario_path


def _same_rate(given: float, known: float) -> bool:
    return math.isclose(float(given), known, rel_tol=1e-9)


def _coded(kind: type[BagSource] | type[SimulatorSource], name: str, why: str, rate_of: str,
           sample_format: SampleFormat | str | None, sample_rate: float | None, scale: float | None) -> Source:
    """A source that delivers ADC codes at its front end's rate: a format or a scale does not
    apply, and a rate given must be that one."""
    if sample_format is not None or scale is not None:
        raise ValueError(f"{name}: {why}; a sample format or a scale does not apply")
    source = kind(name)
    if sample_rate is not None and not _same_rate(sample_rate, source.frontend.adc_rate_hz):
        raise ValueError(f"{name}: sample rate {sample_rate:g} Hz given, but {rate_of} "
                         f"at {source.frontend.adc_rate_hz:g} Hz")
    return source


def open_source(
    path: str | os.PathLike,
    sample_format: SampleFormat | str | None = None,
    sample_rate: float | None = None,
    scale: float | None = None,
) -> Source:
    """The source for ``path``, by what it is.

    * a rosbag2 bag (a directory with ``metadata.yaml``, or an ``.mcap`` file):
      :class:`BagSource`; it carries ADC codes, so a format or a scale is an error, and a rate
      must agree with the bag's;
    * a scenario file (``.yaml``): :class:`SimulatorSource`, the live simulator; it makes ADC
      codes at the scenario's rate, so a format, a scale or another rate is an error;
    * a SigMF recording (``.sigmf-meta``, ``.sigmf-data``, ``.sigmf`` archive):
      :class:`SigmfSource`; a format or a rate given must agree with its metadata;
    * anything else: a raw file, :class:`RawFileSource`, in the format given or named by its
      extension, at the rate given (required).

    Raises ValueError naming the path and the cause.
    """
    name = os.fspath(path)
    if not os.path.exists(name):
        raise ValueError(f"{name}: no such file or directory")
    if is_bag_path(name):
        return _coded(BagSource, name, "a bag carries ADC codes already", "the bag was recorded", sample_format,
                      sample_rate, scale)
    if os.path.isdir(name):
        raise ValueError(f"{name}: a directory, but not a rosbag2 bag (no metadata.yaml)")
    if is_scenario_path(name):
        return _coded(SimulatorSource, name, "a scenario is simulated into ADC codes",
                      "the scenario's front end samples", sample_format, sample_rate, scale)
    if is_sigmf_path(name):
        sigmf = SigmfSource(name, scale=scale)
        if sample_format is not None and SampleFormat.parse(sample_format) is not sigmf.sample_format:
            raise ValueError(f"{name}: sample format {SampleFormat.parse(sample_format).value} given, but "
                             f"the metadata says {sigmf.sample_format.value}")
        if sample_rate is not None and not _same_rate(sample_rate, sigmf.sample_rate):
            raise ValueError(f"{name}: sample rate {sample_rate:g} Hz given, but the metadata says "
                             f"{sigmf.sample_rate:g} Hz (core:sample_rate)")
        return sigmf
    fmt = SampleFormat.from_extension(name) if sample_format is None else sample_format
    return RawFileSource(name, fmt, sample_rate, scale=scale)
