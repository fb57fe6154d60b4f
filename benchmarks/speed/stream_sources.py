"""Throughput of the live sources: how many MS/s a ``tcp://`` and an ``rtl_tcp://`` source turn
into envelope chunks on one core, against the 1.92 MS/s an LTE envelope stream needs.

A server process (on another core where there is one) streams the real RTL-SDR recording
(cu8, looped) as fast as the socket takes it, over the loopback; the measured process, pinned
to one core with BLAS on one thread, runs the source as ``deepsync detect`` and the
``envelope_adc`` node do: the reader thread (socket reads, whole samples, the bounded queue)
and the consumer (decoding, |x - zero|^2, int16 codes, one chunk per 10 ms frame). The rate is
the samples delivered in chunks per wall second over --seconds of signal, from the connection
to the last chunk. The queue is made to hold the whole run (the server sends far faster than
a receiver would), so nothing is dropped and the rate is what the source can turn into chunks.

Run:  .venv/bin/python benchmarks/speed/stream_sources.py [--seconds 20]
Writes docs/results/stream_sources.json.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import socket
import struct
import time
from pathlib import Path

from threadpoolctl import threadpool_limits

from deepsync.sources import open_source

REPO = Path(__file__).resolve().parents[2]
RECORDING = REPO.parent / "shared" / "data" / "real_lte" / "f1860_s1.92_g0_1s_strong_rtlsdr.bin"
NEEDED_MSPS = 1.92
OUT = REPO / "docs" / "results" / "stream_sources.json"


def serve(listener: socket.socket, data: bytes, total: int, greeting: bytes, core: int | None) -> None:
    """Accept one client, send ``greeting`` then ``total`` bytes of ``data`` looped, close."""
    if core is not None:
        os.sched_setaffinity(0, {core})
    conn, _ = listener.accept()
    with conn:
        conn.sendall(greeting)
        sent = 0
        while sent < total:
            piece = data[: min(len(data), total - sent)]
            conn.sendall(piece)
            sent += len(piece)
        conn.shutdown(socket.SHUT_WR)
        try:
            while conn.recv(4096):  # an rtl_tcp client's commands, until it closes
                pass
        except OSError:
            pass


def measure(kind: str, seconds: float, data: bytes, cores: list[int]) -> dict:
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    total = 2 * round(seconds * NEEDED_MSPS * 1e6)  # cu8: two bytes a sample
    greeting = b"RTL0" + struct.pack(">II", 5, 29) if kind == "rtl_tcp" else b""
    server_core = cores[1] if len(cores) > 1 else None
    server = multiprocessing.Process(target=serve, args=(listener, data, total, greeting, server_core))
    server.start()
    listener.close()
    # a queue that holds it all: the server sends far faster than real time, and what is measured
    # is how fast the source turns bytes into chunks, not how much a short queue drops
    buffer = f"buffer={2 * seconds:g}"
    address = (f"rtl_tcp://127.0.0.1:{port}?settle=0&{buffer}" if kind == "rtl_tcp"
               else f"tcp://127.0.0.1:{port}?{buffer}")
    source = open_source(address, "cu8", NEEDED_MSPS * 1e6)
    samples, started = 0, time.perf_counter()
    for chunk in source.chunks():
        samples += len(chunk.samples)
    wall = time.perf_counter() - started
    server.join()
    msps = samples / wall / 1e6
    return {"source": kind, "samples": samples, "wall_s": round(wall, 3), "msps": round(msps, 2),
            "x_needed": round(msps / NEEDED_MSPS, 1), "dropped": source.dropped_samples,
            "events": [str(e) for e in source.take_events()]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="seconds of signal per source (default 20)")
    args = parser.parse_args()
    data = RECORDING.read_bytes()
    cores = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cores[0]})  # the measured process: one core, the server's elsewhere
    results = []
    with threadpool_limits(1):
        for kind in ("tcp", "rtl_tcp"):
            result = measure(kind, args.seconds, data, cores)
            results.append(result)
            print(f"{kind:8s} {result['msps']:6.2f} MS/s on one core ({result['x_needed']}x the "
                  f"{NEEDED_MSPS} MS/s needed), {result['samples']} samples in {result['wall_s']} s, "
                  f"{result['dropped']} dropped")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps({"machine": platform.processor() or platform.machine(), "cores_seen": len(cores),
                               "needed_msps": NEEDED_MSPS, "results": results}, indent=2) + "\n")
    print(f"written {OUT.relative_to(REPO)}")


if __name__ == "__main__":
    main()
