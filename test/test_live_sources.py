"""Live receivers as sources (deepsync.sources.live): byte streams over TCP, rtl_tcp, standard
input and a serial port, served here by local servers (threads, port 0) streaming the real
RTL-SDR recording; stalls, closes, reconnections, partial samples and a full queue said as
health events, never raised."""

from __future__ import annotations

import math
import os
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from deepsync.pipeline import Pipeline, PipelineConfig
from deepsync.sources import LiveOptions, LiveSource, RawFileSource, Source, open_live, open_source
from deepsync.sources.base import stamp_at
from deepsync.sources.connections import SamplesLost, connect_tcp
from deepsync.sources.envelope import envelope_codes, full_scale
from deepsync.sources.rtltcp import RtlTcpSettings
from deepsync.towers import load_tower_database
from deepsync.types import HealthKind

REPO = Path(__file__).resolve().parents[1]
RECORDING = REPO.parent / "shared" / "data" / "real_lte" / "f1860_s1.92_g0_1s_strong_rtlsdr.bin"
TOWERS = REPO / "config" / "towers" / "real_lte_1860.yaml"
FS = 1.92e6
FRAME = 19200
CU8_SCALE = full_scale("cu8")

needs_real = pytest.mark.skipif(not RECORDING.is_file(), reason=f"real RTL-SDR recording not present at {RECORDING}")


class Server:
    """A TCP server on a free local port; each connection is handed to the next of ``scripts``
    (``script(conn, server)``) in a thread; what clients send is recorded in ``received``."""

    def __init__(self, *scripts: Callable[[socket.socket, Server], None]) -> None:
        self.scripts = list(scripts)
        self.received = bytearray()
        self.connections = 0
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        self.listener.settimeout(0.1)
        while not self.stop.is_set() and self.scripts:
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            self.connections += 1
            script = self.scripts.pop(0)
            threading.Thread(target=self._run, args=(script, conn), daemon=True).start()
        self.listener.close()

    def _run(self, script, conn: socket.socket) -> None:
        with conn:
            try:
                script(conn, self)
            except OSError:  # the client went away: its test says what it expects
                pass

    def record(self, conn: socket.socket) -> threading.Thread:
        """Record what the client sends on ``conn`` (in a thread) until it closes."""

        def run() -> None:
            while True:
                try:
                    data = conn.recv(4096)
                except OSError:
                    return
                if not data:
                    return
                self.received += data

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        return thread

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)


def send(data: bytes, piece: int = 1 << 16, pause: float = 0.0) -> Callable[[socket.socket, Server], None]:
    """A script: send ``data`` in ``piece``-byte pieces (``pause`` s between), then close."""

    def script(conn: socket.socket, server: Server) -> None:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for start in range(0, len(data), piece):
            conn.sendall(data[start:start + piece])
            if pause:
                time.sleep(pause)

    return script


def rtl_tcp(data: bytes, magic: bytes = b"RTL0") -> Callable[[socket.socket, Server], None]:
    """A script speaking rtl_tcp: the 12-byte greeting (an R820T with 29 gains), the commands
    recorded, then ``data`` streamed."""

    def script(conn: socket.socket, server: Server) -> None:
        conn.sendall(magic + struct.pack(">II", 5, 29))
        recorder = server.record(conn)
        send(data)(conn, server)
        conn.shutdown(socket.SHUT_WR)
        recorder.join(timeout=5)

    return script


def drain(stream, until: Callable[[list], bool] = lambda chunks: False, timeout: float = 20.0) -> list:
    """Chunks of a LiveStream until it ends, ``until(chunks)`` holds, or ``timeout`` s pass."""
    chunks, deadline = [], time.monotonic() + timeout
    while not stream.ended and not until(chunks) and time.monotonic() < deadline:
        chunk = stream.next(0.1)
        if chunk is not None:
            chunks.append(chunk)
    return chunks


def codes_of(chunks) -> np.ndarray:
    return np.concatenate([c.samples for c in chunks]) if chunks else np.zeros(0, np.int16)


@pytest.fixture(scope="module")
def recording() -> bytes:
    if not RECORDING.is_file():
        pytest.skip(f"real RTL-SDR recording not present at {RECORDING}")
    return RECORDING.read_bytes()


@pytest.fixture(scope="module")
def file_codes() -> np.ndarray:
    """The recording's envelope codes read as a file, at a live stream's default scale."""
    return codes_of(RawFileSource(RECORDING, "cu8", FS, scale=CU8_SCALE).chunks())


def named_cells(source, chunks) -> set[int]:
    """The cells the pipeline names in ``chunks`` (as the real-recording tests run it on the file)."""
    pipeline = Pipeline(source.frontend, PipelineConfig().with_choices(n_frames=10),
                        towers=load_tower_database(TOWERS))
    return {cell.pci for result in pipeline.run(chunks) for cell in result.sync.cells}


# --- the real recording through the streams ------------------------------------------------


@needs_real
def test_a_tcp_stream_of_the_recording_names_142_and_86(recording, file_codes) -> None:
    server = Server(send(recording))
    source = open_source(f"tcp://127.0.0.1:{server.port}", "cu8", FS)
    assert isinstance(source, Source) and source.frontend == RawFileSource(RECORDING, "cu8", FS).frontend
    try:
        chunks = list(source.chunks())
        assert np.array_equal(codes_of(chunks), file_codes)  # every byte, decoded as the file is
        assert [c.first_sample_index for c in chunks] == list(range(0, len(file_codes), FRAME))
        events = source.take_events()
        assert [e.kind for e in events] == [HealthKind.SOURCE_CLOSED]
        assert "end of stream" in events[0].message and "1920000 samples" in events[0].message
        assert named_cells(source, chunks) == {142, 86}
    finally:
        server.close()


@needs_real
def test_an_rtl_tcp_stream_names_142_and_86_and_the_server_gets_the_commands(recording, file_codes) -> None:
    server = Server(rtl_tcp(recording))
    address = f"rtl_tcp://127.0.0.1:{server.port}?freq=1860e6&gain=30&ppm=-3&agc=1&settle=0"
    source = open_source(address)  # cu8 at 1.92 MS/s: what an rtl_tcp client asks for unless told
    try:
        assert source.center_hz == 1860e6 and source.sample_rate == FS
        chunks = list(source.chunks())
        assert np.array_equal(codes_of(chunks), file_codes)
        # rate 1,920,000; frequency 1,860,000,000; ppm -3 (two's complement); manual gain 300 tenths; AGC on
        assert bytes(server.received) == bytes.fromhex("02001d4c00" "016edd5900" "05fffffffd" "0300000001"
                                                       "040000012c" "0800000001")
        assert named_cells(source, chunks) == {142, 86}
    finally:
        server.close()


@needs_real
def test_rtl_tcp_drops_the_settle_time_after_its_commands(recording, file_codes) -> None:
    server = Server(rtl_tcp(recording))
    source = open_source(f"rtl_tcp://127.0.0.1:{server.port}?gain=auto&settle=0.1")
    try:
        codes = codes_of(source.chunks())
        settle = round(0.1 * FS)
        assert np.array_equal(codes, file_codes[settle:])  # sample 0 of the stream: the first one kept
        assert bytes(server.received) == bytes.fromhex("02001d4c00" "0300000000")  # only what was asked
    finally:
        server.close()


def test_a_server_that_is_not_rtl_tcp_is_a_closed_source() -> None:
    server = Server(rtl_tcp(b"\x80" * 4000, magic=b"HTTP"))
    source = open_source(f"rtl_tcp://127.0.0.1:{server.port}")
    try:
        assert list(source.chunks()) == []
        (event,) = source.take_events()
        assert event.kind is HealthKind.SOURCE_CLOSED and "not an rtl_tcp server" in event.message
    finally:
        server.close()


@needs_real
def test_standard_input_through_a_pipe(recording, file_codes, tmp_path) -> None:
    out = tmp_path / "codes.npy"
    program = ("import sys, numpy as np; from deepsync.sources import open_source\n"
               "s = open_source('-', 'cu8', 1.92e6)\n"
               "np.save(sys.argv[1], np.concatenate([c.samples for c in s.chunks()]))\n"
               "print([str(e) for e in s.take_events()])")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    with open(RECORDING, "rb") as stdin:
        done = subprocess.run([sys.executable, "-c", program, str(out)], stdin=stdin, capture_output=True,
                              text=True, env=env, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert np.array_equal(np.load(out), file_codes)
    assert "source_closed" in done.stdout and "standard input" in done.stdout


# --- what goes wrong on a stream -------------------------------------------------------------


def noise_cu8(samples: int, seed: int = 1) -> bytes:
    rng = np.random.default_rng(seed)
    return np.clip(np.rint(127.5 + 20 * rng.standard_normal(2 * samples)), 0, 255).astype(np.uint8).tobytes()


def test_a_stall_is_reported_and_the_stream_goes_on() -> None:
    data = noise_cu8(3 * FRAME)
    half = len(data) // 2

    def stalling(conn: socket.socket, server: Server) -> None:
        conn.sendall(data[:half])
        time.sleep(0.8)
        conn.sendall(data[half:])

    server = Server(stalling)
    source = open_source(f"tcp://127.0.0.1:{server.port}?stall=0.3", "cu8", FS)
    try:
        chunks = list(source.chunks())
        kinds = [e.kind for e in source.take_events()]
        assert kinds == [HealthKind.SOURCE_STALLED, HealthKind.SOURCE_CLOSED]
        assert np.array_equal(codes_of(chunks), envelope_codes(np.frombuffer(data, np.uint8), "cu8", CU8_SCALE))
        assert [c.first_sample_index for c in chunks] == [0, FRAME, 2 * FRAME]  # nothing lost in the stall
    finally:
        server.close()


def test_a_disconnect_ends_the_stream_cleanly_without_reconnect() -> None:
    data = noise_cu8(FRAME + 5000)
    server = Server(send(data[:-1]), send(data))  # the last sample is cut in half: that byte is said lost
    source = open_source(f"tcp://127.0.0.1:{server.port}", "cu8", FS)
    try:
        chunks = list(source.chunks())
        assert [len(c.samples) for c in chunks] == [FRAME, 4999]
        (event,) = source.take_events()
        assert event.kind is HealthKind.SOURCE_CLOSED and "1 bytes of a last, partial sample" in event.message
        assert server.connections == 1
    finally:
        server.close()


def test_with_reconnect_it_reconnects_and_the_outage_is_a_gap() -> None:
    first, second = noise_cu8(2 * FRAME, seed=1), noise_cu8(2 * FRAME, seed=2)
    server = Server(send(first), send(second))
    source = open_source(f"tcp://127.0.0.1:{server.port}?reconnect=1", "cu8", FS)
    stream = source.open_stream()
    try:
        chunks = drain(stream, until=lambda got: sum(len(c.samples) for c in got) >= 4 * FRAME)
    finally:
        stream.close()
    assert server.connections == 2
    assert sum(len(c.samples) for c in chunks) == 4 * FRAME
    indices = [c.first_sample_index for c in chunks]
    assert indices[:2] == [0, FRAME]
    # the backoff (0.5 s) passed on the host clock: the second connection resumes that far on
    assert indices[2] >= 2 * FRAME + round(0.4 * FS)
    assert indices[3] == indices[2] + FRAME
    assert np.array_equal(codes_of(chunks[2:]), envelope_codes(np.frombuffer(second, np.uint8), "cu8", CU8_SCALE))
    closed = [e for e in source.take_events() if e.kind is HealthKind.SOURCE_CLOSED]
    assert closed and "reconnecting in 0.5 s" in closed[0].message


def test_with_reconnect_a_stalled_connection_is_dropped_and_made_again() -> None:
    first, second = noise_cu8(FRAME, seed=1), noise_cu8(FRAME, seed=2)

    def then_silent(conn: socket.socket, server: Server) -> None:
        conn.sendall(first)
        time.sleep(3.0)  # open, but silent: a dead link the peer never closed

    server = Server(then_silent, send(second))
    source = open_source(f"tcp://127.0.0.1:{server.port}?reconnect=1&stall=0.3", "cu8", FS)
    stream = source.open_stream()
    try:
        chunks = drain(stream, until=lambda got: len(got) >= 2, timeout=10)
    finally:
        stream.close()
        server.close()
    assert server.connections == 2 and len(chunks) == 2
    assert np.array_equal(chunks[1].samples, envelope_codes(np.frombuffer(second, np.uint8), "cu8", CU8_SCALE))
    events = source.take_events()
    assert [e.kind for e in events[:2]] == [HealthKind.SOURCE_STALLED, HealthKind.SOURCE_CLOSED]
    assert events[1].message.startswith(f"tcp://127.0.0.1:{server.port}?reconnect=1&stall=0.3: stalled after 19200")


def test_a_refused_connection_is_a_closed_source_not_an_exception() -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    listener.close()  # nothing listens there now
    source = open_source(f"tcp://127.0.0.1:{port}", "ci16_le", FS)
    assert list(source.chunks()) == []
    (event,) = source.take_events()
    assert event.kind is HealthKind.SOURCE_CLOSED and "cannot connect" in event.message


class Pieces:
    """A connection that delivers ``data`` in the given piece sizes, then ends."""

    description = "pieces"

    def __init__(self, data: bytes, sizes: list[int]) -> None:
        self.pieces, start = [], 0
        for size in sizes:
            self.pieces.append(data[start:start + size])
            start += size
        assert start == len(data)

    def read(self, max_bytes: int, timeout: float) -> bytes | None:
        return self.pieces.pop(0) if self.pieces else b""

    def close(self) -> None:
        pass


def test_a_partial_sample_is_kept_for_the_next_read() -> None:
    rng = np.random.default_rng(3)
    values = np.clip(np.rint(3000 * rng.standard_normal(2 * 30000)), -32768, 32767).astype("<i2")
    data = values.tobytes()  # 4 bytes a sample; pieces of 7 bytes (and a tail) split samples everywhere
    sizes = [7] * (len(data) // 7) + ([len(data) % 7] if len(data) % 7 else [])
    source = LiveSource("pieces", lambda: Pieces(data, sizes), "ci16_le", FS)
    codes = codes_of(source.chunks())
    assert np.array_equal(codes, envelope_codes(values, "ci16_le", full_scale("ci16_le")))


def test_the_stamps_are_the_receiver_clock_from_the_first_samples_host_time() -> None:
    data = noise_cu8(3 * FRAME)
    arrival_ns = 1_700_000_000_000_000_000
    first_read = 4096  # bytes: the first read holds 2048 samples
    sizes = [first_read] + [len(data) - first_read]
    source = LiveSource("clocked", lambda: Pieces(data, sizes), "cu8", FS, clock=lambda: arrival_ns)
    chunks = list(source.chunks())
    anchor = arrival_ns - round(2048 / FS * 1e9)  # the first read arrived when its last sample did
    assert [c.stamp_ns for c in chunks] == [stamp_at(anchor, i * FRAME, FS) for i in range(3)]


def test_a_full_queue_drops_counts_and_reports_the_samples() -> None:
    burst, after = noise_cu8(20 * FRAME, seed=1), noise_cu8(2 * FRAME, seed=2)

    def bursty(conn: socket.socket, server: Server) -> None:
        conn.sendall(burst)  # while the consumer sleeps: far more than the queue holds
        time.sleep(1.0)
        conn.sendall(after)  # while it reads again: kept

    server = Server(bursty)
    source = open_source(f"tcp://127.0.0.1:{server.port}?buffer=0.02", "cu8", FS)  # 38,400 samples
    stream = source.open_stream()
    try:
        time.sleep(0.5)
        chunks = drain(stream)
    finally:
        stream.close()
        server.close()
    received = sum(len(c.samples) for c in chunks)
    assert source.dropped_samples > 0 and received + source.dropped_samples == 22 * FRAME
    gaps = [e for e in source.take_events() if e.kind is HealthKind.GAP]
    assert gaps and sum(int(e.message.split(": ")[1].split()[0]) for e in gaps) == source.dropped_samples
    # the kept samples sit where they were sent: the indices jump over the dropped ones
    assert chunks[-1].end_sample_index == 22 * FRAME
    assert np.array_equal(codes_of(chunks)[-2 * FRAME:],
                          envelope_codes(np.frombuffer(after, np.uint8), "cu8", CU8_SCALE))
    assert any(b.first_sample_index > a.end_sample_index for a, b in zip(chunks, chunks[1:]))


class Overflowing(Pieces):
    """Pieces with a driver overflow (SamplesLost) between the first and the second."""

    reads = 0

    def read(self, max_bytes: int, timeout: float) -> bytes | None:
        self.reads += 1
        if self.reads == 2:
            raise SamplesLost("overflow, the driver dropped samples")
        return super().read(max_bytes, timeout)


def test_samples_the_receiver_lost_are_a_gap_placed_by_the_host_clock() -> None:
    data = noise_cu8(2 * FRAME)
    now = [1_000_000_000_000]

    def clock() -> int:
        now[0] += 200_000_000  # every block arrives 0.2 s after the one before, on the host clock
        return now[0]

    source = LiveSource("overflowing", lambda: Overflowing(data, [2 * FRAME, 2 * FRAME]), "cu8", FS,
                        clock=clock)
    chunks = list(source.chunks())
    assert [c.first_sample_index for c in chunks] == [0, round(0.2 * FS)]  # 0.2 s on: the loss, not hidden
    assert chunks[1].stamp_ns - chunks[0].stamp_ns == 200_000_000
    gap, closed = source.take_events()
    assert gap.kind is HealthKind.GAP and "driver dropped samples after sample 19200" in gap.message
    assert closed.kind is HealthKind.SOURCE_CLOSED


def test_a_nan_in_a_float_stream_drops_its_chunk_with_an_event() -> None:
    values = np.full(2 * 2 * FRAME, 0.1, dtype="<f4")
    values[2 * FRAME + 10] = np.nan  # in the second frame
    data = values.tobytes()
    source = LiveSource("floats", lambda: Pieces(data, [len(data)]), "cf32_le", FS)
    chunks = list(source.chunks())
    assert [c.first_sample_index for c in chunks] == [0]
    kinds = [e.kind for e in source.take_events()]
    assert sorted(kinds, key=str) == sorted([HealthKind.NOT_FINITE, HealthKind.SOURCE_CLOSED], key=str)


@pytest.mark.parametrize("configured_by", ["termios", "pyserial"])
def test_a_serial_device_is_read_raw(configured_by: str, monkeypatch) -> None:
    if configured_by == "pyserial":
        pytest.importorskip("serial", reason="pyserial not installed (pip install 'deepsync[serial]')")
    else:
        monkeypatch.setitem(sys.modules, "serial", None)  # as if pyserial were not installed
    primary, secondary = os.openpty()
    device = os.ttyname(secondary)
    data = noise_cu8(FRAME - 256) + bytes(range(256)) * 2  # every byte value: ^C, ^S, CR, ... too
    source = open_source(device, "cu8", FS)  # a bare device path is a serial port
    opened, connect = [], source.connect
    source.connect = lambda: opened.append(connect()) or opened[-1]
    stream = source.open_stream()
    try:
        deadline = time.monotonic() + 10
        while not source.connections:  # the port is open, and raw, once it counts as a connection
            assert time.monotonic() < deadline
            time.sleep(0.01)
        for start in range(0, len(data), 4096):  # the pty's buffer is small: write as it is read
            os.write(primary, data[start:start + 4096])
            time.sleep(0.002)
        chunks = drain(stream, until=lambda got: sum(len(c.samples) for c in got) >= FRAME, timeout=10)
    finally:
        stream.close()
        os.close(primary)
        os.close(secondary)
    assert f"at 921600 baud ({configured_by}" in opened[0].description
    # raw mode: control bytes (0x03, 0x0d, 0x11, 0x13, ...) arrive as they were sent
    assert np.array_equal(codes_of(chunks), envelope_codes(np.frombuffer(data, np.uint8), "cu8", CU8_SCALE))


def test_the_stream_thread_never_blocks_a_poll() -> None:
    server = Server(lambda conn, s: time.sleep(1.0))  # connects, sends nothing
    source = open_source(f"tcp://127.0.0.1:{server.port}", "cu8", FS)
    stream = source.open_stream()
    try:
        start = time.monotonic()
        assert stream.next(0.0) is None and not stream.ended
        assert time.monotonic() - start < 0.05
    finally:
        stream.close()
        server.close()


# --- addresses -------------------------------------------------------------------------------


@pytest.mark.parametrize("address,fmt,rate,message", [
    ("ftp://host:21", "cu8", FS, r"unknown scheme 'ftp'; live streams are tcp://, rtl_tcp://"),
    ("tcp://localhost", "cu8", FS, r"no port \(write tcp://localhost:PORT\)"),
    ("tcp://:5000", "cu8", FS, r"no host"),
    ("tcp://localhost:70000", "cu8", FS, r"bad port .*out of range.*1\.\.65535"),
    ("tcp://localhost:http", "cu8", FS, r"bad port"),
    ("tcp://localhost:0", "cu8", FS, r"port 0 is not a port"),
    ("tcp://localhost:5000", "cu9", FS, r"unknown sample format 'cu9'"),
    ("tcp://localhost:5000", None, FS, r"give the sample format"),
    ("tcp://localhost:5000", "cu8", None, r"give the sample rate"),
    ("tcp://localhost:5000", "cu8", 1e6, r"sample rate 1e\+06 Hz"),
    ("tcp://localhost:5000?stal=3", "cu8", FS, r"unknown option\(s\) stal; tcp takes: buffer, reconnect, stall"),
    ("tcp://localhost:5000?stall=-1", "cu8", FS, r"option stall='-1': must be a finite number > 0"),
    ("tcp://localhost:5000?reconnect=maybe", "cu8", FS, r"option reconnect='maybe': not a yes/no"),
    ("rtl_tcp://localhost:1234", "ci16_le", None, r"rtl_tcp streams cu8, not ci16_le"),
    ("rtl_tcp://localhost:1234?gain=70", None, None, r"option gain='70': must be auto or a gain in dB"),
    ("rtl_tcp://localhost:1234?freq=1860e6&freq=1860e6", None, None, r"option 'freq' given twice"),
    ("soapy://rtlsdr", None, None, r"give the centre frequency"),
])
def test_bad_addresses_are_refused_with_the_cause(address: str, fmt, rate, message: str) -> None:
    with pytest.raises(ValueError, match=message) as error:
        open_live(address, fmt, rate)
    assert address in str(error.value)


def test_rtl_tcp_commands_are_big_endian_with_a_signed_ppm() -> None:
    settings = RtlTcpSettings(2.048e6, center_hz=751e6, gain_db=math.nan, ppm=42)
    assert settings.commands() == bytes.fromhex("02001f4000" "012cc359c0" "050000002a" "0300000000")


def test_soapy_without_its_bindings_names_how_to_get_them() -> None:
    try:
        import SoapySDR  # noqa: F401
    except ImportError:
        pass
    else:
        pytest.skip("SoapySDR's bindings are installed: the missing-module message cannot be seen here")
    source = open_source("soapy://rtlsdr?freq=1860e6")  # opening says nothing: connecting does
    assert list(source.chunks()) == []
    (event,) = source.take_events()
    assert event.kind is HealthKind.SOURCE_CLOSED and "python3-soapysdr" in event.message


def test_live_options_refuse_nonsense() -> None:
    with pytest.raises(ValueError, match="stall_s"):
        LiveOptions(stall_s=0)


def test_connect_tcp_refused_is_an_oserror() -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    listener.close()
    with pytest.raises(OSError):
        connect_tcp("127.0.0.1", port)


# --- the envelope_adc node's player, without ROS ------------------------------------------------


class Gated(Pieces):
    """Pieces that wait for ``gate`` before the first one: a receiver that has sent nothing yet."""

    def __init__(self, data: bytes, sizes: list[int], gate: threading.Event) -> None:
        super().__init__(data, sizes)
        self.gate = gate

    def read(self, max_bytes: int, timeout: float) -> bytes | None:
        if not self.gate.wait(timeout):
            return None
        return super().read(max_bytes, timeout)


def test_the_player_polls_a_live_source_without_waiting_pacing_or_looping() -> None:
    from deepsync_ros.playback import Playback, PlaybackConfig

    data = noise_cu8(2 * FRAME)
    gate = threading.Event()
    source = LiveSource("gated", lambda: Gated(data, [len(data)], gate), "cu8", FS)
    playback = Playback(source, PlaybackConfig(realtime=True, loop=True))
    try:
        start = time.monotonic()
        assert playback.next_chunk() is None and not playback.ended  # nothing yet: the timer looks again
        assert time.monotonic() - start < 0.05
        gate.set()
        chunks, deadline = [], time.monotonic() + 10
        while not playback.ended and time.monotonic() < deadline:
            chunk = playback.next_chunk()
            if chunk is not None:
                assert playback.due_in(chunk, time.monotonic()) == 0.0  # a live chunk goes out as it comes
                playback.mark_published(chunk, time.monotonic())
                chunks.append(chunk)
    finally:
        playback.close()
    assert [c.first_sample_index for c in chunks] == [0, FRAME] and playback.loops == 0  # never looped
    assert playback.source_events[HealthKind.SOURCE_CLOSED] == 1
    report = playback.report()
    assert report.level.name == "ERROR" and "source_closed" in report.message  # nothing came after the close
    assert ("source events: source_closed", "1") in report.values


@needs_real
def test_detect_reads_a_tcp_stream_and_prints_its_events(recording, capsys) -> None:
    from deepsync.cli import main

    server = Server(send(recording))
    try:
        assert main(["detect", "--input", f"tcp://127.0.0.1:{server.port}", "--format", "cu8", "--rate", "1.92e6",
                     "--towers", str(TOWERS), "--frames", "10"]) == 0
    finally:
        server.close()
    out = capsys.readouterr().out
    assert {int(line.split()[1]) for line in out.splitlines() if "reported in" in line} == {142, 86}
    assert "source: source_closed: tcp://127.0.0.1" in out and "end of stream" in out
