"""Where a live stream comes from, as the user writes it: ``tcp://HOST:PORT``,
``rtl_tcp://HOST:PORT?freq=...``, ``serial:///dev/ttyUSB0?baud=...``, ``soapy://DRIVER?...``,
``-`` (standard input), or a serial device path.

A stream's own settings are query parameters of its address (``?reconnect=1&stall=5``), so one
string (a CLI ``--input``, a node's ``source`` parameter, a launch argument) says everything
about the connection; the sample format, rate and scale are given as for recordings
(``--format``, ``--rate``, ``--scale``; ``sample_format``, ``sample_rate``).
"""

from __future__ import annotations

import math
import os
import stat
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from urllib.parse import parse_qsl, urlsplit

STDIN = "-"


@dataclass(frozen=True)
class StreamAddress:
    """A parsed live-stream address: ``scheme://host:port/path?options``."""

    text: str
    scheme: str
    host: str | None
    port: int | None
    path: str
    options: Mapping[str, str]

    def endpoint(self) -> tuple[str, int]:
        """(host, port), or ValueError when either is missing."""
        if not self.host:
            raise ValueError(f"{self.text}: no host (write {self.scheme}://HOST:PORT)")
        if self.port is None:
            raise ValueError(f"{self.text}: no port (write {self.scheme}://{self.host}:PORT)")
        return self.host, self.port


def is_live_address(text: str) -> bool:
    """Whether ``text`` names a live stream rather than a file: ``-``, ``scheme://...``, or an
    existing character device (a serial port)."""
    if text == STDIN or "://" in text:
        return True
    try:
        return stat.S_ISCHR(os.stat(text).st_mode)
    except OSError:
        return False


def parse_address(text: str) -> StreamAddress:
    """``text`` (see :func:`is_live_address`) as a :class:`StreamAddress`; ValueError naming
    the address and the fault (a port that is not a number or out of 1..65535, an option twice)."""
    if text == STDIN:
        return StreamAddress(text, "stdin", None, None, "", {})
    if "://" not in text:
        return StreamAddress(text, "serial", None, None, text, {})
    scheme, _, rest = text.partition("://")
    parts = urlsplit("//" + rest)  # split by hand: a URL scheme may not hold "_" (rtl_tcp)
    try:
        port = parts.port
    except ValueError as error:  # "Port out of range 0-65535", "Port could not be cast to integer ..."
        raise ValueError(f"{text}: bad port ({error}); give a number in 1..65535") from None
    if port == 0:
        raise ValueError(f"{text}: port 0 is not a port to connect to; give a number in 1..65535")
    options: dict[str, str] = {}
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key in options:
            raise ValueError(f"{text}: option {key!r} given twice")
        options[key] = value
    return StreamAddress(text, scheme.lower(), parts.hostname, port, parts.path, options)


def take_options(address: StreamAddress, parsers: Mapping[str, Callable[[str], object]]) -> dict[str, object]:
    """The address's options parsed by ``parsers`` (name -> parser of the text); ValueError
    naming the option for an unknown name or a value its parser refuses."""
    unknown = sorted(set(address.options) - set(parsers))
    if unknown:
        known = ", ".join(sorted(parsers)) or "none"
        raise ValueError(f"{address.text}: unknown option(s) {', '.join(unknown)}; {address.scheme} takes: {known}")
    values = {}
    for name, text in address.options.items():
        try:
            values[name] = parsers[name](text)
        except ValueError as error:
            raise ValueError(f"{address.text}: option {name}={text!r}: {error}") from None
    return values


def flag(text: str) -> bool:
    """An option's yes/no: 1/0, true/false, yes/no, on/off."""
    value = text.strip().lower()
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise ValueError("not a yes/no (1/0, true/false, yes/no, on/off)")


def positive(text: str) -> float:
    """An option's positive finite number (``1.92e6`` is fine)."""
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise ValueError("must be a finite number > 0")
    return value


def within(low: float, high: float) -> Callable[[str], float]:
    """A parser of numbers in ``low..high``."""

    def parse(text: str) -> float:
        value = float(text)
        if not (math.isfinite(value) and low <= value <= high):
            raise ValueError(f"must be a number within {low:g}..{high:g}")
        return value

    return parse


def whole(low: int, high: int) -> Callable[[str], int]:
    """A parser of whole numbers in ``low..high``."""

    def parse(text: str) -> int:
        value = float(text)
        if not (math.isfinite(value) and value == int(value) and low <= value <= high):
            raise ValueError(f"must be a whole number in {low}..{high}")
        return int(value)

    return parse
