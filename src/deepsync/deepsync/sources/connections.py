"""Byte connections a live source reads: a TCP socket, standard input, a serial port.

Each is a :class:`Connection`: ``read(max_bytes, timeout)`` gives the bytes that arrived (at most
``max_bytes``), None when none came within ``timeout`` seconds, ``b""`` when the stream ended;
it raises OSError when the link failed, :class:`SamplesLost` when the receiver says it dropped
samples (a driver overflow) and reading goes on. Connecting is the caller's (a live source's reader
thread), and so is what a timeout means (a stall).
"""

from __future__ import annotations

import os
import select
import socket
import sys
from typing import Protocol

DEFAULT_BAUD = 921600
CONNECT_TIMEOUT_S = 5.0


class SamplesLost(Exception):
    """The receiver dropped samples (how many, it may not say); the stream goes on."""


class Connection(Protocol):
    description: str

    def read(self, max_bytes: int, timeout: float) -> bytes | None:
        """Up to ``max_bytes`` bytes; None: nothing within ``timeout`` s; ``b""``: the end."""
        ...

    def close(self) -> None: ...


class SocketConnection:
    """A connected TCP socket."""

    def __init__(self, sock: socket.socket, description: str) -> None:
        self.sock = sock
        self.description = description

    def read(self, max_bytes: int, timeout: float) -> bytes | None:
        self.sock.settimeout(timeout)
        try:
            return self.sock.recv(max_bytes)
        except TimeoutError:  # socket.timeout is TimeoutError since Python 3.10
            return None

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def close(self) -> None:
        self.sock.close()


def connect_tcp(host: str, port: int, timeout: float = CONNECT_TIMEOUT_S) -> SocketConnection:
    """A TCP connection to ``host:port`` (OSError when refused or unreachable)."""
    sock = socket.create_connection((host, port), timeout=timeout)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)  # a second of cu8 at 1.92 MS/s, give or take
    return SocketConnection(sock, f"tcp {host}:{port}")


class FileConnection:
    """A readable file descriptor: a pipe (standard input), a tty (a serial port)."""

    def __init__(self, fd: int, description: str, owned: object | None = None) -> None:
        """``owned``: what to close with the connection (an open port), if anything."""
        self.fd = fd
        self.description = description
        self._owned = owned

    def read(self, max_bytes: int, timeout: float) -> bytes | None:
        ready, _, _ = select.select([self.fd], [], [], timeout)
        if not ready:
            return None
        return os.read(self.fd, max_bytes)

    def close(self) -> None:
        if self._owned is not None:
            self._owned.close()  # type: ignore[attr-defined]


def open_stdin() -> FileConnection:
    """Standard input, as raw bytes (it stays open: the process owns it)."""
    return FileConnection(sys.stdin.fileno(), "standard input")


def open_serial(path: str, baud: int | None) -> FileConnection:
    """The serial port at ``path``, raw (no echo, no line editing), at ``baud`` (default
    :data:`DEFAULT_BAUD`; a USB CDC device ignores it).

    With pyserial (``pip install 'deepsync[serial]'``) the port is configured by it, any baud
    rate the driver takes. Without it the device is opened as a file and put in raw mode with
    the standard library's termios, at a baud rate termios names (``termios.B921600``, ...).
    """
    rate = DEFAULT_BAUD if baud is None else baud
    try:
        import serial  # pyserial, optional
    except ImportError:
        return _open_tty(path, rate)
    try:
        port = serial.Serial(path, baudrate=rate, timeout=0)
    except (serial.SerialException, ValueError) as error:
        raise OSError(f"{path}: {error}") from None
    return FileConnection(port.fileno(), f"serial port {path} at {rate} baud (pyserial)", owned=port)


def _open_tty(path: str, baud: int) -> FileConnection:
    import termios
    import tty

    speed = getattr(termios, f"B{baud}", None)
    if speed is None:
        raise ValueError(f"{path}: baud {baud} is not one termios names; install pyserial "
                         "(pip install 'deepsync[serial]') for any rate the driver takes")
    fd = os.open(path, os.O_RDONLY | os.O_NOCTTY)
    handle = os.fdopen(fd, "rb", buffering=0)
    if os.isatty(fd):
        tty.setraw(fd)
        attributes = termios.tcgetattr(fd)
        attributes[4] = attributes[5] = speed  # input and output speed
        termios.tcsetattr(fd, termios.TCSANOW, attributes)
    return FileConnection(fd, f"serial port {path} at {baud} baud (termios; pyserial not installed)", owned=handle)
