"""Speed of the cell-search and timing stages: one 10-frame stack (192,000 samples at 1.92 MHz).

Times ``SyncStage.process`` on real stacks of the bundled campus bag (4 cells on the air):
stacking (10 chunks of 10 ms), the search (blind: 504 PCIs; known: the campus tower database,
timed by the PSS or by the PCIs' whole codes, with or without its co-sited sector pairs, the
default) and window extraction, on one core (BLAS limited to one thread). Templates are built
once, before timing, as a running node builds them at start-up. A fresh stage per stack: the
full search, with nothing tracked yet. Then the running stage: the bag looped as one stream,
each stack either a full search (with the cells found before tracked first) or, between full
searches (``SyncConfig.search_every``, the gap doubling up to ``max_search_interval_s`` while
they find nothing new), only the tracked cells; their medians and the mean per
stack; the same on the dense walk where its bag has been made (--repeats seconds of it after
its first 10: six sites 0.2-1 km away, 33 tower-database cells; ``replay_speed.ROUTE``). Then
``TimingStage.process`` on the confirmed cells of each stack (4 cells, one co-sited pair), per
classical estimator. Prints the median of --repeats runs.

Run:  .venv/bin/python benchmarks/speed/sync_speed.py [--repeats 30]
Writes docs/results/sync_speed.json.
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import time
from pathlib import Path

from threadpoolctl import threadpool_limits

from deepsync.bag import read_envelope
from deepsync.sources import bag_frontend
from deepsync.sync.search import SearchConfig
from deepsync.sync.stage import SyncConfig, SyncStage
from deepsync.timing.registry import ESTIMATORS, Estimator
from deepsync.timing.stage import TimingConfig, TimingStage
from deepsync.towers import load_tower_database
from replay_speed import CHUNKS_PER_SECOND, ROUTE, ROUTE_TOWERS, ROUTE_WARMUP_S  # the dense walk, where made
from soak import Stream  # benchmarks/speed/soak.py: the bag looped on one stream

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "bags" / "campus"
TOWERS = REPO / "config" / "towers" / "campus.yaml"


def time_mode(chunks, towers, repeats: int, config: SyncConfig) -> tuple[float, float]:
    """Median and 90th percentile (ms) of processing one 10-frame stack."""
    frontend = bag_frontend(BAG)
    warm = SyncStage(frontend, config, towers)
    for chunk in chunks[:30]:
        warm.process(chunk)  # builds and caches templates, CRS ones of the cells found too (not per stack)
    times = []
    for r in range(repeats):
        stage = SyncStage(frontend, config, towers)
        stage.templates, stage.search = warm.templates, warm.search
        first = 10 * (r % (len(chunks) // 10))
        started = time.perf_counter()
        results = [res for chunk in chunks[first : first + 10] for res in stage.process(chunk)]
        times.append((time.perf_counter() - started) * 1e3)
        assert len(results) == 1
    times.sort()
    return statistics.median(times), times[int(0.9 * (len(times) - 1))]


def time_stream(chunks, towers, stacks: int, config: SyncConfig, bag: Path = BAG, warmup: int | None = None) -> dict:
    """ms per stack of one running stage over the bag looped: median, p90 and mean over all its
    stacks, and full searches and tracked-only stacks apart (median, p90). Warmed up by one loop,
    or by its first ``warmup`` chunks (a route then goes on from there)."""
    stage = SyncStage(bag_frontend(bag), config, towers)
    stream = Stream(chunks)
    for _ in range(len(chunks) if warmup is None else warmup):  # templates, CRS templates of the cells found, the tracks
        stage.process(stream.next())
    times: dict[bool, list[float]] = {True: [], False: []}
    while len(times[True]) + len(times[False]) < stacks:
        chunk = stream.next()
        started = time.perf_counter()
        results = stage.process(chunk)
        spent = (time.perf_counter() - started) * 1e3
        if results:  # the chunk that completes a stack (stacking the others costs ~0.1 ms each)
            times[results[0].searched].append(spent)
    every = sorted(times[True] + times[False])
    row = {"mean_ms": statistics.fmean(every), "median_ms": statistics.median(every),
           "p90_ms": every[int(0.9 * (len(every) - 1))], "full_search_stacks": len(times[True]),
           "tracked_only_stacks": len(times[False])}
    for searched, name in ((True, "full_search"), (False, "tracked_only")):
        if times[searched]:
            ordered = sorted(times[searched])
            row[name] = {"median_ms": statistics.median(ordered), "p90_ms": ordered[int(0.9 * (len(ordered) - 1))]}
    return row


def print_stream(label: str, row: dict) -> None:
    # either kind may be absent from a short run: the full searches back off to one per 2 s
    full, tracked = (row.get(kind, {}).get("median_ms", float("nan")) for kind in ("full_search", "tracked_only"))
    print(f"{'running stage, ' + label:40s}: {row['median_ms']:6.1f} ms median, {row['p90_ms']:.1f} p90, "
          f"{row['mean_ms']:.1f} mean per stack; full search {full:.1f} ms median ({row['full_search_stacks']} "
          f"stacks), tracked only {tracked:.1f} ms ({row['tracked_only_stacks']} stacks)")


def time_timing(chunks, towers, repeats: int, estimator: Estimator) -> tuple[float, float]:
    """Median and 90th percentile (ms) of timing one stack's confirmed cells."""
    frontend = bag_frontend(BAG)
    sync = SyncStage(frontend, SyncConfig(), towers)
    results = [r for chunk in chunks for r in sync.process(chunk) if r.cells]
    stage = TimingStage(frontend, TimingConfig(estimator=estimator))
    stage.process(results[0].stack_windows)  # templates, as at start-up
    times = []
    for r in range(repeats):
        started = time.perf_counter()
        stage.process(results[r % len(results)].stack_windows)
        times.append((time.perf_counter() - started) * 1e3)
    times.sort()
    return statistics.median(times), times[int(0.9 * (len(times) - 1))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    chunks = list(read_envelope(BAG))
    out = {}
    with threadpool_limits(limits=1):
        database = load_tower_database(TOWERS)
        fast = SyncConfig(search=SearchConfig(full_code_timing=False))
        no_sites = SyncConfig(search=SearchConfig(site_hypotheses=False))
        pairs = len(database.cosited_pairs())
        for mode, towers, config, label in (
            ("blind", None, SyncConfig(), "blind (504 PCIs)"),
            ("known_fast", database, fast, f"known, PSS timing ({len(database.pcis)} PCIs)"),
            ("known_no_sites", database, no_sites, f"known, full-code timing ({len(database.pcis)} PCIs)"),
            ("known", database, SyncConfig(), f"known, full codes + {pairs} co-sited pairs"),
        ):
            median, p90 = time_mode(chunks, towers, args.repeats, config)
            out[mode] = {"median_ms": median, "p90_ms": p90}
            print(f"{label:40s}: {median:6.1f} ms median, {p90:6.1f} ms p90 per 10-frame stack "
                  f"(192,000 samples), one core")
        for mode, towers, label in (("blind_stream", None, "blind"), ("known_stream", database, "known, default")):
            out[mode] = time_stream(chunks, towers, 10 * args.repeats, SyncConfig())
            print_stream(label, out[mode])
        if ROUTE.exists():  # a city's load: more cells, weaker, in a larger database
            warmup, stacks = ROUTE_WARMUP_S * CHUNKS_PER_SECOND, 10 * args.repeats
            # one 10 ms chunk per frame: the walk is read as far as the timed stacks reach, never looped
            needed = warmup + stacks * SyncConfig().stack.n_frames
            out["known_stream_dense_walk"] = time_stream(list(itertools.islice(read_envelope(ROUTE), needed)),
                                                         load_tower_database(ROUTE_TOWERS), stacks, SyncConfig(),
                                                         ROUTE, warmup)
            print_stream("known, dense walk", out["known_stream_dense_walk"])
        else:
            print(f"{ROUTE.relative_to(REPO)} not made: the dense walk is not timed")
        for estimator in ESTIMATORS.values():
            median, p90 = time_timing(chunks, database, args.repeats, estimator)
            out[f"timing_{estimator.name}"] = {"median_ms": median, "p90_ms": p90}
            print(f"{'timing, ' + estimator.name:40s}: {median:6.1f} ms median, {p90:6.1f} ms p90 per stack "
                  "(4 cells), one core")
    path = REPO / "docs" / "results" / "sync_speed.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"stack": "10 frames x 19200 samples, campus bag", "repeats": args.repeats, **out}, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
