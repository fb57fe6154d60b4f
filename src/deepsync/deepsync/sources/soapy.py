"""Any SoapySDR receiver (RTL-SDR, HackRF, Airspy, SDRplay, USRP, LimeSDR, ...), optional:
``soapy://DRIVER?freq=1860e6&gain=30``.

SoapySDR's Python bindings do not come from PyPI: they come with the SoapySDR library
(``sudo apt install python3-soapysdr soapysdr-module-rtlsdr``, or conda-forge ``soapysdr``).
They are imported only when a ``soapy://`` source connects; without them the source says so.

Options of the address: ``freq`` (Hz, required), ``gain`` (dB, or ``auto``; default auto),
``antenna``, ``channel`` (default 0), ``device`` (more device arguments, ``key=value,key=value``,
e.g. ``serial=00000001``). The rate is the stream's (``--rate``; 1.92 MS/s unless given); samples are read as complex
float32 (``cf32_le``, components within +-1).
"""

from __future__ import annotations

import math

import numpy as np

from .connections import SamplesLost

INSTALL_HINT = ("SoapySDR's Python bindings (not on PyPI): sudo apt install python3-soapysdr plus the "
                "driver module (e.g. soapysdr-module-rtlsdr), or conda install -c conda-forge soapysdr; "
                "the interpreter running deepsync must see them (a venv made with --system-site-packages)")
SOAPY_TIMEOUT = -1  # SOAPY_SDR_TIMEOUT: nothing arrived within the timeout
SOAPY_OVERFLOW = -4  # SOAPY_SDR_OVERFLOW: the driver dropped samples; reading goes on


def import_soapy():
    """The ``SoapySDR`` module, or ImportError naming how to get it."""
    try:
        import SoapySDR  # noqa: N813 (the bindings' own name)
    except ImportError as error:
        raise ImportError(f"a soapy:// source needs {INSTALL_HINT} ({error})") from None
    return SoapySDR


def device_arguments(driver: str, extra: str | None) -> dict[str, str]:
    """SoapySDR device arguments: the driver and ``key=value,key=value`` more."""
    arguments = {"driver": driver} if driver else {}
    for item in filter(None, (extra or "").split(",")):
        key, equals, value = item.partition("=")
        if not equals or not key.strip():
            raise ValueError(f"device argument {item!r} is not key=value")
        arguments[key.strip()] = value.strip()
    return arguments


class SoapyConnection:
    """An open, streaming SoapySDR receiver; ``read`` gives complex float32 samples as bytes."""

    def __init__(self, arguments: dict[str, str], sample_rate: float, center_hz: float, gain_db: float,
                 antenna: str | None, channel: int) -> None:
        soapy = import_soapy()
        self.description = "SoapySDR " + ",".join(f"{k}={v}" for k, v in arguments.items())
        rx = soapy.SOAPY_SDR_RX
        try:
            self.device = soapy.Device(arguments)
            self.device.setSampleRate(rx, channel, sample_rate)
            self.device.setFrequency(rx, channel, center_hz)
            self.device.setGainMode(rx, channel, math.isnan(gain_db))
            if not math.isnan(gain_db):
                self.device.setGain(rx, channel, gain_db)
            if antenna:
                self.device.setAntenna(rx, channel, antenna)
            self.stream = self.device.setupStream(rx, soapy.SOAPY_SDR_CF32, [channel])
            self.device.activateStream(self.stream)
        except RuntimeError as error:  # what the bindings raise for a device that will not open or tune
            raise OSError(f"{self.description}: {error}") from None
        self.buffer = np.empty(1 << 15, dtype=np.complex64)

    def read(self, max_bytes: int, timeout: float) -> bytes | None:
        count = max(1, min(len(self.buffer), max_bytes // self.buffer.itemsize))
        result = self.device.readStream(self.stream, [self.buffer], count, timeoutUs=int(timeout * 1e6))
        if result.ret == SOAPY_TIMEOUT:
            return None
        if result.ret == SOAPY_OVERFLOW:
            raise SamplesLost(f"{self.description}: overflow, the driver dropped samples")
        if result.ret < 0:
            raise OSError(f"{self.description}: readStream error {result.ret}")
        return self.buffer[:result.ret].tobytes()

    def close(self) -> None:
        self.device.deactivateStream(self.stream)
        self.device.closeStream(self.stream)
