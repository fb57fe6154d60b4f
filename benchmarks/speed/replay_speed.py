"""Replay speed, pose latency, the cost of split nodes, and memory over a long replay.

Everything on one core (BLAS limited to one thread), through ``deepsync.pipeline.Pipeline`` and
the message conversions of ``deepsync.bag`` that the nodes and ``deepsync replay`` use:

* **speed**: milliseconds of processing per second of ADC data, per stage (sync: stacking, cell
  search, windows; timing; fusion), on the bundled campus bag (static) and walk bag: the bag's
  chunks looped on one continuing stream (``soak.Stream``) for ``--seconds`` seconds after one
  loop of warm-up (templates are built at start-up, as a node builds them), median and p90 over
  the seconds. The target is 50 ms per second of data (20x real time). Also the whole
  ``replay_bag`` (reading, converting and writing the bag too) once over each bag, as a real-time
  factor; and the stages again with 20- and 50-frame stacks (a fix every 0.2 or 0.5 s: a
  tracker's choice).
  The campus is an easy case (a few strong cells); where the dense walk's bag has been made
  (``ROUTE``), its stages are timed too, 10, 20 and 50 frames, on ``--seconds`` of the walk after
  its first 10 s: more cells, weaker, in a larger tower database, as a city gives them.
* **latency**: from a stack's ``SyncWindowArray`` message (as the timing node receives it) to
  the ``PoseWithCovarianceStamped`` message (timing, fusion and every conversion between: what
  the timing and fusion nodes do, without DDS), and from a ``CellTimingArray`` (the fusion node
  alone); median and p90 over every stack of both bags. Target 10 ms.
* **split nodes**: what a DDS hop adds per second of data (ms per 1 s of ADC data), for each
  message the chain would send between separate nodes (EnvelopeSamples 100/s, SyncWindowArray
  10/s, CellTimingArray 10/s): core -> message and CDR serialisation (publisher),
  deserialisation and message -> core (subscriber), with rosbags' typestore (rclpy's C
  serialiser would be faster; DDS transport itself is not counted), against the in-process
  pipeline's processing of the same second. The EnvelopeSamples hop exists in one process too
  when the ADC driver is a node of its own.
* **memory**: resident memory over ``--minutes`` of stream (default 10) through one Pipeline,
  the campus bag looped with increasing indices and stamps: at the start, every minute of
  signal and at the end. Ctrl-C stops it early; what was measured is written.

Run:  .venv/bin/python benchmarks/speed/replay_speed.py [--seconds 20] [--minutes 10]
Writes docs/results/replay_speed.json.
"""

from __future__ import annotations

import argparse
import itertools
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from deepsync.bag import (
    cell_timing_array_from_msg,
    cell_timing_array_to_msg,
    envelope_from_msg,
    envelope_to_msg,
    fix_to_pose_msg,
    read_envelope,
    sync_window_array_from_msg,
    sync_window_array_to_msg,
    typestore,
)
from deepsync.bag.convert import CELL_TIMING_ARRAY, ENVELOPE_SAMPLES, SYNC_WINDOW_ARRAY
from deepsync.pipeline import Pipeline, PipelineConfig
from deepsync.replay import replay_bag
from deepsync.sources import bag_frontend
from deepsync.towers import load_tower_database
from deepsync.types import FRAME_SECONDS, Fix
from soak import Stream, rss_mb  # benchmarks/speed/soak.py: the looped stream and /proc's RSS

REPO = Path(__file__).resolve().parents[2]
TOWERS = REPO / "config" / "towers" / "campus.yaml"
BAGS = {"campus": REPO / "bags" / "campus", "campus_route": REPO / "bags" / "campus_route"}
# a realistic walk (six sites on two carriers 0.2-1 km away, mostly NLOS, 33 tower-database
# cells): made by `deepsync simulate --scenario config/scenarios/route_dense.yaml --seconds 96.4
# --out bags/generated/route_dense` (about 18 minutes), timed where it has been made
ROUTE = REPO / "bags" / "generated" / "route_dense"
ROUTE_TOWERS = REPO / "config" / "towers" / "route_dense.yaml"
ROUTE_WARMUP_S = 10  # the cells found and confirmed before the timed seconds, which follow on the route
OUT = REPO / "docs" / "results" / "replay_speed.json"
LONGER_STACKS = (20, 50)  # frames per stack timed beside the default
CHUNKS_PER_SECOND = round(1 / FRAME_SECONDS)


def percentiles(values: list[float]) -> dict:
    return {"median": round(float(np.median(values)), 2), "p90": round(float(np.percentile(values, 90)), 2),
            "n": len(values)}


def stage_speed(bag: Path, seconds: int, config: PipelineConfig | None = None, towers: Path = TOWERS,
                warmup_seconds: float | None = None) -> dict:
    """ms of each stage per second of ADC data, the bag looped on one stream, after a warm-up
    of one loop (or of its first ``warmup_seconds``: a route then goes on where it was, timed
    on the ``seconds`` after, never jumping back to its start)."""
    if warmup_seconds is None:
        chunks = list(read_envelope(bag))
        warmup = len(chunks)
    else:
        warmup = round(warmup_seconds * CHUNKS_PER_SECOND)
        chunks = list(itertools.islice(read_envelope(bag), warmup + seconds * CHUNKS_PER_SECOND))
    pipeline = Pipeline(bag_frontend(bag), config, towers=load_tower_database(towers))
    stream = Stream(chunks)
    for _ in range(warmup):  # warm-up: templates, caches and the cells found, as at a node's start
        pipeline.process(stream.next())
    per_second = {"sync": [], "timing": [], "fusion": [], "total": []}
    for _ in tqdm(range(seconds), desc=f"speed {bag.name}", unit="s of data"):
        spent = dict.fromkeys(("sync", "timing", "fusion"), 0.0)
        for _ in range(CHUNKS_PER_SECOND):
            chunk = stream.next()
            started = time.perf_counter()
            syncs = pipeline.sync.process(chunk)
            spent["sync"] += time.perf_counter() - started
            for sync in syncs:
                windows = sync.stack_windows
                started = time.perf_counter()
                timing = pipeline.timing.process(windows)
                arrivals = windows.arrivals(timing.cells)
                timed = time.perf_counter()
                pipeline.fuse_arrivals(arrivals)
                spent["timing"] += timed - started
                spent["fusion"] += time.perf_counter() - timed
        for name, value in spent.items():
            per_second[name].append(value * 1e3)
        per_second["total"].append(sum(spent.values()) * 1e3)
    return {name: percentiles(values) for name, values in per_second.items()}


def whole_replay(bag: Path) -> dict:
    """``replay_bag`` over the bag once: reading, the stages, conversions and writing."""
    with tempfile.TemporaryDirectory() as tmp:
        summary = replay_bag(bag, Path(tmp) / "out", load_tower_database(TOWERS), progress=False)
    return {"signal_s": round(summary.signal_seconds, 2), "wall_s": round(summary.wall_seconds, 2),
            "realtime_factor": round(summary.realtime_factor, 2),
            "ms_per_second_of_data": round(1e3 * summary.wall_seconds / summary.signal_seconds, 1),
            "note": "includes reading and decompressing the bag, building templates (start-up) and writing the output"}


def stack_windows(bag: Path) -> list:
    """Every stack of the bag as the sync stage gives it to the timing stage (StackWindows)."""
    pipeline = Pipeline(bag_frontend(bag), towers=load_tower_database(TOWERS))
    return [result.sync.stack_windows for chunk in read_envelope(bag) for result in pipeline.process(chunk)]


def pose_latency(bags: dict[str, Path], repeats: int) -> dict:
    """Per stack, ms from the SyncWindowArray message (what the timing node receives) to the
    PoseWithCovarianceStamped message (timing, fusion and the conversions between, as the
    timing and fusion nodes do them), and from the CellTimingArray message (the fusion node's
    share). Stacks without a fix publish no pose: they are timed to fusion's answer all the same."""
    from_windows, from_timing, poses = [], [], 0
    for bag in bags.values():
        messages = [sync_window_array_to_msg(windows) for windows in stack_windows(bag)]
        frontend = bag_frontend(bag)
        for _ in range(repeats):
            pipeline = Pipeline(frontend, towers=load_tower_database(TOWERS))  # fusion state from scratch
            pipeline.timing.process(sync_window_array_from_msg(messages[0]))  # templates, as at start-up
            for message in messages:
                started = time.perf_counter()
                windows = sync_window_array_from_msg(message)  # the timing node
                timing = pipeline.timing.process(windows)
                timing_message = cell_timing_array_to_msg(windows.arrivals(timing.cells))
                received = time.perf_counter()
                fix = pipeline.fuse_arrivals(cell_timing_array_from_msg(timing_message)).published  # the fusion node
                if isinstance(fix, Fix):
                    fix_to_pose_msg(fix)
                    poses += 1
                done = time.perf_counter()
                from_windows.append((done - started) * 1e3)
                from_timing.append((done - received) * 1e3)
    return {"sync_windows_to_pose_ms": percentiles(from_windows), "cell_timing_to_pose_ms": percentiles(from_timing),
            "stacks_with_a_pose": poses}


def split_cost(bag: Path, repeats: int) -> dict:
    """ms per second of data that one DDS hop adds, per message type: core -> message and CDR
    serialisation (publisher), deserialisation and message -> core (subscriber)."""
    store = typestore()
    chunks = list(read_envelope(bag))[:CHUNKS_PER_SECOND]
    stacks = stack_windows(bag)
    pipeline = Pipeline(bag_frontend(bag), towers=load_tower_database(TOWERS))
    arrivals = [pipeline.time_stack(windows).arrivals for windows in stacks]
    stacks_per_second = round(1 / (10 * FRAME_SECONDS))

    def hop(to_msg, from_msg, msgtype: str, items: list) -> dict:
        times, size = [], 0
        for _ in range(repeats):
            started = time.perf_counter()
            for item in items:
                raw = store.serialize_cdr(to_msg(item, store=store), msgtype)
                from_msg(store.deserialize_cdr(raw, msgtype))
                size += len(raw)
            times.append((time.perf_counter() - started) * 1e3)
        return {**percentiles(times), "messages_per_second": len(items), "bytes_per_second": size // repeats}

    return {
        "envelope_samples": hop(envelope_to_msg, envelope_from_msg, ENVELOPE_SAMPLES, chunks),
        "sync_window_array": hop(sync_window_array_to_msg, sync_window_array_from_msg, SYNC_WINDOW_ARRAY,
                                 stacks[:stacks_per_second]),
        "cell_timing_array": hop(cell_timing_array_to_msg, cell_timing_array_from_msg, CELL_TIMING_ARRAY,
                                 arrivals[:stacks_per_second]),
    }


def memory(minutes: float) -> dict:
    """RSS (MB) over ``minutes`` of the campus bag looped through one Pipeline."""
    bag = BAGS["campus"]
    pipeline = Pipeline(bag_frontend(bag), towers=load_tower_database(TOWERS))
    stream = Stream(list(read_envelope(bag)))
    total = round(minutes * 60 * CHUNKS_PER_SECOND)
    rss = [{"signal_s": 0, "rss_mb": round(rss_mb(), 1)}]
    print(f"RSS at the start: {rss[0]['rss_mb']} MB")
    stacks, interrupted = 0, False
    started = time.perf_counter()
    bar = tqdm(total=total, desc="memory", unit="chunk")
    try:
        while stream.k < total:
            stacks += len(pipeline.process(stream.next()))
            bar.update(1)
            if stream.k % (60 * CHUNKS_PER_SECOND) == 0:
                rss.append({"signal_s": round(stream.k * FRAME_SECONDS), "rss_mb": round(rss_mb(), 1)})
                tqdm.write(f"RSS after {rss[-1]['signal_s']} s of signal: {rss[-1]['rss_mb']} MB")
    except KeyboardInterrupt:
        interrupted = True
        print("interrupted: the memory figures so far", file=sys.stderr)
    bar.close()
    wall = time.perf_counter() - started
    end = {"signal_s": round(stream.k * FRAME_SECONDS, 1), "rss_mb": round(rss_mb(), 1)}
    if rss[-1]["signal_s"] != end["signal_s"]:
        rss.append(end)
    print(f"RSS at the end: {end['rss_mb']} MB after {end['signal_s']} s of signal ({wall:.0f} s of wall time)")
    after_warmup = [r["rss_mb"] for r in rss if r["signal_s"] >= 60]
    return {"minutes_of_signal": round(stream.k * FRAME_SECONDS / 60, 2), "stacks": stacks, "wall_s": round(wall, 1),
            "interrupted": interrupted, "rss_mb_start": rss[0]["rss_mb"], "rss_mb_end": end["rss_mb"],
            "rss_mb_growth_after_first_minute": round(max(after_warmup) - min(after_warmup), 1) if after_warmup else None,
            "rss": rss}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=int, default=20, help="seconds of data timed per bag (after a warm-up loop)")
    parser.add_argument("--repeats", type=int, default=5, help="repeats of the latency and split-node timings")
    parser.add_argument("--minutes", type=float, default=10.0, help="minutes of signal for the memory run (0: skip)")
    args = parser.parse_args()
    report: dict = {"machine": f"{platform.machine()}, {platform.python_implementation()} {platform.python_version()}",
                    "threads": 1, "target_ms_per_second_of_data": 50, "target_pose_latency_ms": 10}
    with threadpool_limits(limits=1):
        report["speed"] = {}
        for name, bag in BAGS.items():
            report["speed"][name] = {"stages_ms_per_second_of_data": stage_speed(bag, args.seconds),
                                     "replay_bag": whole_replay(bag)}
            print(name, json.dumps(report["speed"][name], indent=1))
        # a tracker's choices: a fix every 0.2 s or 0.5 s from 20 or 50 frames (docs/design/fusion.md: both
        # track the dense walk better than 10), the per-stack work done a half or a fifth as often
        for frames in LONGER_STACKS:
            report[f"speed_{frames}_frames"] = {name: {"stages_ms_per_second_of_data": stage_speed(
                bag, args.seconds, PipelineConfig().with_choices(n_frames=frames))} for name, bag in BAGS.items()}
            print(f"{frames}-frame stacks", json.dumps(report[f"speed_{frames}_frames"], indent=1))
        report["latency"] = pose_latency(BAGS, args.repeats)
        print("latency", json.dumps(report["latency"], indent=1))
        report["split_nodes"] = {name: split_cost(bag, args.repeats) for name, bag in BAGS.items()}
        for name, cost in report["split_nodes"].items():
            processing = report["speed"][name]["stages_ms_per_second_of_data"]["total"]["median"]
            extra = sum(hop["median"] for hop in cost.values())
            cost["all_hops_ms_per_second_of_data"] = round(extra, 2)
            cost["in_process_pipeline_ms_per_second_of_data"] = processing
            cost["extra_over_in_process"] = round(extra / processing, 4)
        print("split nodes", json.dumps(report["split_nodes"], indent=1))
        OUT.write_text(json.dumps(report, indent=1))  # what is measured so far, before the long part
        if args.minutes > 0:
            report["memory"] = memory(args.minutes)
        # last: its chunks (a few hundred MB) would be part of the memory run's resident size
        if ROUTE.exists():
            report["speed_route_dense"] = {f"{frames}_frames": stage_speed(
                ROUTE, args.seconds, PipelineConfig().with_choices(n_frames=frames), ROUTE_TOWERS, ROUTE_WARMUP_S)
                for frames in (PipelineConfig().sync.stack.n_frames, *LONGER_STACKS)}
            print("dense walk", json.dumps(report["speed_route_dense"], indent=1))
        else:
            print(f"{ROUTE.relative_to(REPO)} not made: the dense walk is not timed", file=sys.stderr)
    OUT.write_text(json.dumps(report, indent=1))
    print(f"-> {OUT.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
