"""Soak: minutes of envelope stream through the pipeline with faults injected, as a robot runs it.

The bundled campus bag (4 cells) is played in a loop with continuing sample indices and stamps,
through sync and timing (fusion joins when it exists). The loop is its first 1.8 s, where every
stack of the clean recording reports all four cells: later, the weaker site-A pair falls below
the threshold in a few stacks on its own, which would blur what a fault costs. Every few seconds of stream one
fault is injected, drawn at random:

* ``gap``: a few chunks lost;  * ``restart``: the index starts over at 0 while time goes on;
* ``nan``: a chunk of NaN samples (refused at the door by ``EnvelopeChunk``: the stage then
  sees the hole it leaves, a gap);  * ``corrupt``: codes beyond the ADC's 12 bits;
* ``rate``: chunks labelled 3.84 MHz;  * ``late``: an old chunk sent again;
* ``clipping``: a stretch driven into the ADC rails.

Checked: nothing raises; every fault shows as its event or flag; after each fault, detection is
back (a confirmed cell reported) within 3 stacks of the first clean stack (after a restart the
confirmation over 3 stacks is the floor), and the stacks until all four cells are back are
counted too (the site-A pair, at -5 dB per stack, misses a stack now and then on its own:
``all_four_fraction`` says how often); resident memory (RSS) must stay flat (measured after a warm-up loop, once templates and caches are built, and every minute).
Results: ``docs/results/soak.json``.

    .venv/bin/python benchmarks/speed/soak.py [--minutes 10] [--every 5] [--seed 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from deepsync.pipeline import Pipeline
from deepsync.sources import BagSource
from deepsync.towers import load_tower_database
from deepsync.types import FRAME_SECONDS, EnvelopeChunk, HealthKind

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "campus"
TOWERS = REPO / "config" / "towers" / "campus.yaml"
OUT = REPO / "docs" / "results" / "soak.json"
CELLS = {56, 120, 121, 301}
LOOP_FRAMES = 180
EXPECTED = {  # what each fault must show as
    "gap": HealthKind.GAP, "restart": HealthKind.RESTART, "nan": HealthKind.GAP, "corrupt": HealthKind.CORRUPT,
    "rate": HealthKind.RATE_MISMATCH, "late": HealthKind.BACKWARDS, "clipping": HealthKind.CLIPPED,
}


def rss_mb() -> float:
    """Resident memory now (MB), from /proc (Linux)."""
    with open("/proc/self/statm", encoding="ascii") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


class Stream:
    """The bag's chunks in a loop, on one continuing index and time line (restarts aside)."""

    def __init__(self, chunks: list[EnvelopeChunk]) -> None:
        self.chunks = chunks
        self.k = 0  # chunks emitted
        self.index = 0
        self.stamp = chunks[0].stamp_ns
        self.frame_ns = round(FRAME_SECONDS * 1e9)

    def next(self) -> EnvelopeChunk:
        chunk = self.chunks[self.k % len(self.chunks)]
        out = dataclasses.replace(chunk, first_sample_index=self.index, stamp_ns=self.stamp)
        self.k += 1
        self.index += len(chunk.samples)
        self.stamp += self.frame_ns
        return out

    def skip(self, n: int) -> None:
        for _ in range(n):
            self.next()


def faulty(stream: Stream, fault: str, rng: np.random.Generator, history: list[EnvelopeChunk]) -> list:
    """The chunks (or the refusals) one fault puts into the stream."""
    if fault == "gap":
        stream.skip(int(rng.integers(1, 4)))
        return []
    if fault == "restart":
        stream.index, stream.stamp = 0, stream.stamp + 20 * stream.frame_ns  # a driver restarts
        return []
    if fault == "nan":
        chunk = stream.next()
        try:  # a driver delivering NaN: the chunk cannot be made, the stage sees the hole
            EnvelopeChunk(chunk.stamp_ns, chunk.sample_rate, chunk.first_sample_index, chunk.adc_bits,
                          chunk.volts_per_code, np.where(rng.random(len(chunk.samples)) < 0.1, np.nan, chunk.samples))
        except ValueError as error:
            return [error]
        raise AssertionError("a chunk with NaN samples was accepted")
    if fault == "corrupt":
        chunk = stream.next()
        codes = chunk.samples.copy()
        start = int(rng.integers(0, len(codes) - 5000))
        codes[start : start + 5000] = rng.integers(-32768, 32767, 5000)
        return [dataclasses.replace(chunk, samples=codes)]
    if fault == "rate":
        return [dataclasses.replace(stream.next(), sample_rate=3.84e6) for _ in range(int(rng.integers(1, 4)))]
    if fault == "late":
        return [history[-3]]
    loud = []  # clipping: a stack's worth driven into the rails
    for _ in range(10):
        chunk = stream.next()
        loud.append(dataclasses.replace(chunk, samples=np.clip(chunk.samples.astype(int) * 4, -2048, 2047)))
    return loud


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="minutes of stream")
    parser.add_argument("--every", type=float, default=5.0, help="seconds of stream between faults")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    source = BagSource(BAG)
    pipeline = Pipeline(source.frontend, towers=load_tower_database(TOWERS))
    stream = Stream(list(source.chunks())[:LOOP_FRAMES])
    total = round(args.minutes * 60 / FRAME_SECONDS)
    every = round(args.every / FRAME_SECONDS)
    faults: list[dict] = []
    history: list[EnvelopeChunk] = []
    started, rss = time.perf_counter(), []
    stacks, counts = 0, {"clean": 0, "all_four": 0}
    bar = tqdm(total=total, unit="frame", desc="soak")
    try:
        while stream.k < total:
            pending = [stream.next()]
            if stream.k % every == 0:
                fault = str(rng.choice(list(EXPECTED)))
                pending = faulty(stream, fault, rng, history) + [stream.next()]
                faults.append({"fault": fault, "at_chunk": stream.k, "seen": False, "refused": False,
                               "stacks_to_detection": None, "stacks_to_all_four": None})
            for item in pending:
                if isinstance(item, ValueError):
                    faults[-1]["refused"] = True
                    continue
                history = (history + [item])[-5:]
                for result in pipeline.process(item):
                    stacks += 1
                    observe(faults, result, counts)
            if stream.k % (60 * 100) == LOOP_FRAMES:  # after the warm-up loop, then every minute
                rss.append(round(rss_mb(), 1))
            bar.update(stream.k - bar.n)
    except KeyboardInterrupt:
        print("interrupted: the results so far", file=sys.stderr)
    bar.close()
    wall = time.perf_counter() - started
    report = summarize(faults, stacks, counts, stream.k * FRAME_SECONDS, wall, rss + [round(rss_mb(), 1)])
    OUT.write_text(json.dumps(report, indent=1))
    print(json.dumps({k: v for k, v in report.items() if k != "faults"}, indent=1))
    print(f"-> {OUT.relative_to(REPO)}")
    return 0 if report["all_seen"] and report["detection_back_within_3"] else 1


def observe(faults: list[dict], result, counts: dict) -> None:
    """Mark the latest fault seen when its event or flag comes, and count the clean stacks after
    it until a cell is reported again, and until all four are."""
    clean = not result.sync.flags and not result.health
    if clean:
        counts["clean"] += 1
        counts["all_four"] += CELLS <= set(result.sync.pcis)
    if not faults:
        return
    fault = faults[-1]
    if EXPECTED[fault["fault"]] in {h.kind for h in result.health}:
        fault["seen"] = True
        return
    if fault["seen"] and clean and fault["stacks_to_all_four"] is None:
        fault["clean"] = fault.get("clean", 0) + 1
        if fault["stacks_to_detection"] is None and result.sync.pcis:
            fault["stacks_to_detection"] = fault["clean"]
        if CELLS <= set(result.sync.pcis):
            fault["stacks_to_all_four"] = fault.pop("clean")


def summarize(faults: list[dict], stacks: int, counts: dict, seconds: float, wall: float, rss: list[float]) -> dict:
    judged = faults[:-1]  # the last fault may come too close to the end of the stream
    detection = [f["stacks_to_detection"] for f in judged]
    all_four = [f["stacks_to_all_four"] for f in judged if f["stacks_to_all_four"] is not None]
    return {
        "stream_seconds": round(seconds, 2),
        "wall_seconds": round(wall, 1),
        "stacks": stacks,
        "faults": faults,
        "faults_by_kind": {kind: sum(f["fault"] == kind for f in faults) for kind in EXPECTED},
        "all_seen": all(f["seen"] for f in judged),
        "detection_back_within_3": all(d is not None and d <= 3 for d in detection),
        "stacks_to_detection_max": max(detection, default=None),
        "stacks_to_all_four_mean": round(float(np.mean(all_four)), 2) if all_four else None,
        "stacks_to_all_four_max": max(all_four, default=None),
        "all_four_fraction": round(counts["all_four"] / max(counts["clean"], 1), 3),
        "rss_mb_start": rss[0],
        "rss_mb_end": rss[-1],
        "rss_mb_every_minute": rss,
    }


if __name__ == "__main__":
    sys.exit(main())
