"""Speed of frame stacking: incremental sliding stacks against forming each stack anew.

Pushes the bundled campus bag, looped as one stream of 10 ms chunks, through ``FrameStacker``
for back-to-back and sliding stacks, on one core. A stack's cost is the time of all the pushes
that complete it, from the one after the previous stack's on: checking and converting each
chunk (about 0.1 ms per 10 ms chunk, the same for any N), cutting the new frames once, summing
them into their block, adding the blocks, the clock measurement. It stays flat in N.

Beside it, what forming the same stack anew from its N frames costs (the work a stacker that
re-cuts every stack repeats, without its chunk handling): the frames copied into one array,
averaged, the clock measured from the halves; it grows with N. The stacker before it was
incremental (re-cutting every stack from a buffer of N frames, which it also re-joined) cost
1.4 / 1.3 / 3.0 / 3.5 ms per stack for the four configurations below, measured with this
script's first pass on the same machine. Median and 90th percentile over --stacks stacks.

Run:  .venv/bin/python benchmarks/speed/stacking_speed.py [--stacks 200]
Writes docs/results/stacking_speed.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from deepsync.bag import read_envelope
from deepsync.sync.stacking import FrameStacker, Stack, StackConfig, held_fraction, measure_drift
from soak import Stream  # benchmarks/speed/soak.py: the bag looped on one stream

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "campus"
CONFIGS = ((10, None), (20, 5), (50, 10), (100, 10))  # (N, hop): back to back, then sliding


def formed_anew(stack: Stack) -> float:
    """ms to form ``stack`` from its frames from scratch."""
    started = time.perf_counter()
    rows = np.stack(stack.frames)
    mean = rows.mean(axis=0)
    held_fraction(mean)
    half = len(rows) // 2
    if half:
        measure_drift(rows[:half].sum(axis=0), rows[half : 2 * half].sum(axis=0), half)
    return (time.perf_counter() - started) * 1e3


def time_config(chunks, n_frames: int, hop: int | None, stacks: int) -> dict:
    """Two passes over the same stream: the stacker's own cost per stack, then (apart, so one
    does not evict the other's memory) the cost of forming each of its stacks anew."""
    times: dict[str, list[float]] = {"incremental": [], "formed_anew": []}
    for name, timed in times.items():
        stacker = FrameStacker(chunks[0].sample_rate, StackConfig(n_frames=n_frames, hop_frames=hop))
        stream = Stream(chunks)
        for _ in range(n_frames + 10):  # the clock measured, the first stacks out
            stacker.push(stream.next())
        spent = 0.0
        while len(timed) < stacks:
            chunk = stream.next()
            started = time.perf_counter()
            done = stacker.push(chunk)
            spent += (time.perf_counter() - started) * 1e3
            if done:
                timed.append(spent if name == "incremental" else formed_anew(done[-1]))
                spent = 0.0
    return {"n_frames": n_frames, "hop_frames": hop or n_frames,
            **{name: {"median_ms": statistics.median(t), "p90_ms": sorted(t)[int(0.9 * (len(t) - 1))]}
               for name, t in times.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stacks", type=int, default=200)
    args = parser.parse_args()
    chunks = list(read_envelope(BAG))
    with threadpool_limits(1):
        rows = [time_config(chunks, n, hop, args.stacks) for n, hop in CONFIGS]
    print("stack (frames / hop)   incremental: median / p90    formed anew: median / p90   (ms per stack)")
    for r in rows:
        inc, anew = r["incremental"], r["formed_anew"]
        print(f"  {r['n_frames']:4d} / {r['hop_frames']:<4d}          {inc['median_ms']:6.2f} / {inc['p90_ms']:6.2f}"
              f"              {anew['median_ms']:6.2f} / {anew['p90_ms']:6.2f}")
    out = REPO / "docs" / "results" / "stacking_speed.json"
    out.write_text(json.dumps({"stacks": args.stacks, "configs": rows}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
