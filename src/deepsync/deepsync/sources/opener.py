"""One entry point for every recording or live stream a user may have: :func:`open_source`.

The live streams' schemes are registered here, in :data:`LIVE_SCHEMES`, and nowhere else.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable

from .address import (STDIN, StreamAddress, flag, is_live_address, parse_address, positive, take_options, whole,
                      within)
from .bagfile import BagSource, is_bag_path
from .base import Source, check_rate
from .connections import connect_tcp, open_serial, open_stdin
from .formats import SampleFormat, is_sigmf_path
from .live import LiveOptions, LiveSource
from .rawfile import RawFileSource
from .rtltcp import DEFAULT_SETTLE_S, RtlTcpConnection, RtlTcpSettings, parse_gain
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

    A live stream (:func:`open_live`) is named by an address instead of a path: ``-``,
    ``tcp://``, ``rtl_tcp://``, ``serial://`` or ``soapy://``, or a serial device path.

    Raises ValueError naming the path and the cause.
    """
    name = os.fspath(path)
    if is_live_address(name):
        return open_live(name, sample_format, sample_rate, scale)
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


# --- live streams ---------------------------------------------------------------------------

LIVE_OPTIONS: dict[str, Callable[[str], object]] = {"reconnect": flag, "stall": positive, "buffer": positive}
"""Options every live address takes: ``reconnect`` (1/0), ``stall`` and ``buffer`` (seconds)."""

LiveOpener = Callable[[StreamAddress, SampleFormat | None, float | None, float | None], LiveSource]
TUNED_RATE_HZ = 1.92e6  # what a client that sets the receiver's rate asks for unless told: LTE's 1.4 MHz rate


def _rate(address: StreamAddress, rate: float | None, default: float | None = None) -> float:
    """The stream's rate: the one given, else ``default`` (a receiver the client tunes), else an error."""
    if rate is None:
        if default is None:
            raise ValueError(f"{address.text}: give the sample rate (--rate / sample_rate), e.g. 1.92e6: a byte "
                             "stream does not say it")
        rate = default
    return check_rate(rate, address.text)


def _options(address: StreamAddress, own: dict[str, Callable[[str], object]]) -> tuple[LiveOptions, dict]:
    """(the live options, the scheme's own options) of ``address``."""
    values = take_options(address, {**LIVE_OPTIONS, **own})
    fields = {"reconnect": "reconnect", "stall": "stall_s", "buffer": "buffer_s"}
    live = LiveOptions(**{field: values.pop(name) for name, field in fields.items() if name in values})
    return live, values


def _format(address: StreamAddress, sample_format: SampleFormat | None, fixed: SampleFormat | None = None
            ) -> SampleFormat:
    """The stream's format: the one its protocol fixes (a given one must agree), else the one given."""
    if fixed is not None:
        if sample_format is not None and sample_format is not fixed:
            raise ValueError(f"{address.text}: {address.scheme} streams {fixed.value}, not {sample_format.value}")
        return fixed
    if sample_format is None:
        raise ValueError(f"{address.text}: give the sample format (--format / sample_format): {SampleFormat.names()}; "
                         "a byte stream does not say it")
    return sample_format


def _raw(connect: Callable[[StreamAddress, dict], Callable], own: dict[str, Callable[[str], object]]) -> LiveOpener:
    """An opener of a plain byte stream in the format the user gives."""

    def opener(address: StreamAddress, sample_format: SampleFormat | None, rate: float | None,
               scale: float | None) -> LiveSource:
        options, values = _options(address, own)
        return LiveSource(address.text, connect(address, values), _format(address, sample_format),
                          _rate(address, rate), options, scale=scale)

    return opener


def _tcp(address: StreamAddress, values: dict) -> Callable:
    host, port = address.endpoint()
    return lambda: connect_tcp(host, port)


def _serial(address: StreamAddress, values: dict) -> Callable:
    path = address.path
    if not path:
        raise ValueError(f"{address.text}: no device (write serial:///dev/ttyUSB0)")
    baud = values.get("baud")
    return lambda: open_serial(path, baud)


def _stdin(address: StreamAddress, values: dict) -> Callable:
    return open_stdin


def _rtl_tcp(address: StreamAddress, sample_format: SampleFormat | None, rate: float | None,
             scale: float | None) -> LiveSource:
    host, port = address.endpoint()
    rate = _rate(address, rate, TUNED_RATE_HZ)
    options, values = _options(address, {"freq": positive, "gain": parse_gain, "ppm": whole(-1000, 1000),
                                         "agc": flag, "settle": within(0.0, 10.0)})
    settings = RtlTcpSettings(rate, values.get("freq"), values.get("gain"), values.get("ppm"), values.get("agc"),
                              values.get("settle", DEFAULT_SETTLE_S))
    fmt = _format(address, sample_format, SampleFormat.CU8)
    return LiveSource(address.text, lambda: RtlTcpConnection(host, port, settings), fmt, rate, options,
                      scale=scale, center_hz=settings.center_hz)


def _soapy(address: StreamAddress, sample_format: SampleFormat | None, rate: float | None,
           scale: float | None) -> LiveSource:
    from .soapy import SoapyConnection, device_arguments

    rate = _rate(address, rate, TUNED_RATE_HZ)
    options, values = _options(address, {"freq": positive, "gain": parse_gain, "antenna": str,
                                         "channel": whole(0, 64), "device": str})
    if "freq" not in values:
        raise ValueError(f"{address.text}: give the centre frequency, e.g. ?freq=1860e6")
    arguments = device_arguments(address.host or "", values.get("device"))
    fmt = _format(address, sample_format, SampleFormat.CF32_LE)
    gain = values.get("gain", math.nan)
    return LiveSource(address.text, lambda: SoapyConnection(arguments, rate, values["freq"], gain,
                                                            values.get("antenna"), values.get("channel", 0)),
                      fmt, rate, options, scale=scale, center_hz=values["freq"])


LIVE_SCHEMES: dict[str, LiveOpener] = {
    "tcp": _raw(_tcp, {}),
    "rtl_tcp": _rtl_tcp,
    "serial": _raw(_serial, {"baud": whole(50, 20_000_000)}),
    "stdin": _raw(_stdin, {}),
    "soapy": _soapy,
}
"""Scheme -> opener. ``stdin`` is written ``-``; a bare serial device path is ``serial``."""


def open_live(text: str, sample_format: SampleFormat | str | None = None, sample_rate: float | None = None,
              scale: float | None = None) -> LiveSource:
    """The live source an address names (see :mod:`deepsync.sources.address`); nothing connects
    until it is read. The rate: ``sample_rate`` (required for byte streams; ``rtl_tcp`` and
    ``soapy`` set the receiver to it, 1.92 MS/s unless given). ValueError naming the address and
    the fault: an unknown scheme, no host or port, a port out of range, an unknown option or
    format, a missing or unusable rate."""
    address = parse_address(text)
    opener = LIVE_SCHEMES.get(address.scheme)
    if opener is None:
        schemes = ", ".join(f"{s}://" for s in LIVE_SCHEMES if s != "stdin")
        raise ValueError(f"{text}: unknown scheme {address.scheme!r}; live streams are {schemes}, "
                         f"{STDIN} (standard input) or a serial device path")
    try:
        fmt = None if sample_format is None else SampleFormat.parse(sample_format)
    except ValueError as error:
        raise ValueError(f"{text}: {error}") from None
    return opener(address, fmt, sample_rate, scale)
