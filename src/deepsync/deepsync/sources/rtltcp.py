"""A client of RTL-SDR's network server, ``rtl_tcp``: ``rtl_tcp://HOST:PORT?freq=1860e6&gain=30``.

The protocol (osmocom rtl-sdr, ``src/rtl_tcp.c``): on connection the server sends 12 bytes,
the magic ``RTL0``, the tuner type and the number of tuner gains (both unsigned 32-bit,
big-endian), then streams interleaved unsigned 8-bit I/Q (``cu8``, zero 127.5) for as long as
the connection lasts. The client steers it with 5-byte commands: one command byte and a 32-bit
big-endian argument. Those used here: 0x01 centre frequency (Hz), 0x02 sample rate (Hz),
0x03 tuner gain mode (0 automatic, 1 manual), 0x04 tuner gain (tenths of a dB), 0x05
frequency correction (ppm, signed), 0x08 the RTL2832's digital AGC (0 off, 1 on).

Settings, as options of the address: ``freq`` (Hz; unset: the server's ``-f`` stands),
``gain`` (dB, or ``auto``; unset: the server's), ``ppm`` (whole ppm; unset: the server's),
``agc`` (1/0; unset: the server's), ``settle`` (seconds of samples dropped after the commands,
default 0.25: the server streams from the moment it accepts, at its old tuning, until the
commands take effect). The sample rate is the stream's (``--rate`` / ``sample_rate``; 1.92 MS/s
unless given), always sent: it is the rate the envelope is stamped and searched at.
"""

from __future__ import annotations

import math
import struct
import time
from dataclasses import dataclass

from .connections import SocketConnection, connect_tcp

MAGIC = b"RTL0"
HEADER_BYTES = 12
HEADER_TIMEOUT_S = 5.0
SET_FREQUENCY = 0x01
SET_SAMPLE_RATE = 0x02
SET_GAIN_MODE = 0x03
SET_GAIN = 0x04
SET_FREQUENCY_CORRECTION = 0x05
SET_AGC = 0x08
TUNERS = {0: "unknown", 1: "E4000", 2: "FC0012", 3: "FC0013", 4: "FC2580", 5: "R820T", 6: "R828D"}
DEFAULT_SETTLE_S = 0.25


@dataclass(frozen=True)
class RtlTcpSettings:
    """What the client asks the server for; None leaves the server's own setting."""

    sample_rate: float
    center_hz: float | None = None
    gain_db: float | None = None  # None: the server's; math.nan: automatic gain
    ppm: int | None = None
    agc: bool | None = None
    settle_s: float = DEFAULT_SETTLE_S

    def commands(self) -> bytes:
        """The command bytes, in the order sent: rate, frequency, correction, gain, AGC."""
        out = [command(SET_SAMPLE_RATE, round(self.sample_rate))]
        if self.center_hz is not None:
            out.append(command(SET_FREQUENCY, round(self.center_hz)))
        if self.ppm is not None:
            out.append(command(SET_FREQUENCY_CORRECTION, self.ppm))
        if self.gain_db is not None:
            if math.isnan(self.gain_db):
                out.append(command(SET_GAIN_MODE, 0))
            else:
                out += [command(SET_GAIN_MODE, 1), command(SET_GAIN, round(self.gain_db * 10))]
        if self.agc is not None:
            out.append(command(SET_AGC, int(self.agc)))
        return b"".join(out)


def command(code: int, argument: int) -> bytes:
    """One 5-byte command; a negative argument (a ppm) goes as its 32-bit two's complement."""
    if not -(2**31) <= argument < 2**32:
        raise ValueError(f"rtl_tcp command 0x{code:02x}: argument {argument} does not fit in 32 bits")
    return struct.pack(">BI", code, argument & 0xFFFFFFFF)


def parse_gain(text: str) -> float:
    """An address's ``gain``: ``auto`` (NaN) or dB within 0..60."""
    if text.strip().lower() == "auto":
        return math.nan
    value = float(text)
    if not (math.isfinite(value) and 0 <= value <= 60):
        raise ValueError("must be auto or a gain in dB within 0..60")
    return value


class RtlTcpConnection(SocketConnection):
    """An rtl_tcp connection after its greeting and the commands: what ``read`` returns is I/Q."""

    tuner = "unknown"
    gains = 0

    def __init__(self, host: str, port: int, settings: RtlTcpSettings) -> None:
        plain = connect_tcp(host, port)
        super().__init__(plain.sock, f"rtl_tcp {host}:{port}")
        try:
            self._greeting()
            self.send(settings.commands())
        except (OSError, ValueError):
            self.close()
            raise
        self._skip = 2 * round(settings.settle_s * settings.sample_rate)

    def _greeting(self) -> None:
        header = b""
        deadline = time.monotonic() + HEADER_TIMEOUT_S
        while len(header) < HEADER_BYTES:
            left = deadline - time.monotonic()
            data = super().read(HEADER_BYTES - len(header), left) if left > 0 else None
            if data is None:
                raise OSError(f"{self.description}: no rtl_tcp greeting within {HEADER_TIMEOUT_S:g} s")
            if not data:
                raise OSError(f"{self.description}: closed before its 12-byte greeting ({len(header)} bytes came)")
            header += data
        magic, tuner, gains = struct.unpack(">4sII", header)
        if magic != MAGIC:
            raise ValueError(f"{self.description}: not an rtl_tcp server (greeting {header[:4]!r}, not {MAGIC!r})")
        self.tuner = TUNERS.get(tuner, f"type {tuner}")
        self.gains = gains
        self.description += f" ({self.tuner} tuner)"

    def read(self, max_bytes: int, timeout: float) -> bytes | None:
        """I/Q bytes, those of the first ``settle`` seconds dropped."""
        while self._skip:
            data = super().read(min(max_bytes, self._skip), timeout)
            if not data:
                return data
            self._skip -= len(data)
        return super().read(max_bytes, timeout)
