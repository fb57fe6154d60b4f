"""Simulate a scenario into a rosbag2 MCAP bag: the ADC stream plus its ground truth.

Topics: ``/deepsync/envelope`` (EnvelopeSamples, 10 ms chunks), ``/deepsync/truth/pose``
(PoseStamped in ``map``, 10 Hz) and ``/deepsync/truth/cell_timing`` (CellTimingArray, one per
10 ms of stream, listing every cell whose subframe-0 sync code starts in that span; ``toa`` is
its fractional stream sample index on the receiver clock, from the line-of-sight delay and the
site's drifting frame clock). The provenance adds the scenario ``origin`` and the true
``sites`` (position, timing offset at the first sample, timing drift, oscillator error).
"""

from __future__ import annotations

import hashlib
import heapq
import json
import math
import os
import platform
import reprlib
import shutil
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

import deepsync
from deepsync.bag import BagWriter
from deepsync.configio import parse_yaml, read_config_bytes
from deepsync.frontend.channel import Emitter
from deepsync.frontend.portable import squared_magnitude
from deepsync.frontend.simulator import EnvelopeSimulator, SimulationStats
from deepsync.frontend.templates import sync_code_offset_seconds
from deepsync.jobs import JobRunner
from deepsync.sync.stacking import check_stack_rate
from deepsync.twin import Twin, build_twin
from deepsync.twin.scenario import SEED_RANGE, load_scenario, parse_scenario
from deepsync.types import FRAME_SECONDS, SPEED_OF_LIGHT_M_S, CellTiming, StackArrivals

EPOCH_NS = 1_767_225_600 * 10**9  # 2026-01-01T00:00:00Z: receiver clock at sample 0
POSE_PERIOD_SECONDS = 0.1
MAX_SECONDS = 86_400.0  # a day of signal (about 250 GB of bag at 1.92 MS/s), the scenario's longest route
TRUTH_ESTIMATOR = "truth"


@dataclass
class CellSummary:
    pci: int
    site: str
    carrier_mhz: float
    bandwidth_mhz: float
    distance_m: float
    los: bool
    re_power_dbm: float  # received power per resource element at the antenna, t = 0 (-inf: no path reaches it)


@dataclass
class RecordingSummary:
    out: str
    scenario: str
    seed: int
    seconds: float
    samples: int
    chunks: int
    truth_messages: int
    bag_bytes: int
    wall_seconds: float
    stats: SimulationStats
    cells: list[CellSummary] = field(default_factory=list)

    @property
    def realtime_factor(self) -> float:
        return self.seconds / self.wall_seconds if self.wall_seconds > 0 else math.inf


def cell_summaries(twin: Twin) -> list[CellSummary]:
    """What each cell looks like at the receiver at t = 0."""
    out = []
    for i, (cell, emitter) in enumerate(zip(twin.cells, twin.emitters)):
        paths = twin.channel.paths(i, 0.0)
        power_w = emitter.re_power_w * float(np.sum(squared_magnitude(paths.gains)))
        out.append(
            CellSummary(
                pci=cell.pci,
                site=cell.site,
                carrier_mhz=cell.carrier_hz / 1e6,
                bandwidth_mhz=cell.bandwidth_mhz,
                distance_m=twin.geometric_delay_s(i, 0.0) * SPEED_OF_LIGHT_M_S,
                los=twin.channel.los_at(i, 0.0),
                re_power_dbm=10 * math.log10(power_w * 1e3) if power_w > 0 else -math.inf,
            )
        )
    return out


def truth_timing(emitters: Sequence[Emitter], geometric_delay_s: Callable[[int, float], float],
                 simulator: EnvelopeSimulator, n_samples: int) -> Iterator[tuple[int, float, int]]:
    """(pci, toa, emitter index) of every subframe-0 sync code that starts inside the stream, in
    order of arrival (emitter order among equal arrivals), computed as they are consumed: an hour
    of four cells holds 1.4 million codes, and the first chunk should not wait for them all.
    ``geometric_delay_s(i, t)``: emitter i's straight-line delay to the receiver at true time t
    (the truth is the first path's arrival as if nothing stood in the way)."""
    rate = simulator.config.adc_rate_hz
    end_time = float(simulator.clock.true_time(n_samples / rate))

    def arrivals(i: int, emitter: Emitter) -> Iterator[tuple[float, int, int]]:
        first = emitter.frame_index_at(0.0) - 1
        last = emitter.frame_index_at(end_time) + 1
        for k in range(first, last + 1):  # a frame moves the arrival on by far more than the path changes
            sent = emitter.frame_start_s(k)  # the site's frame clock, drift and all
            toa = float(simulator.sample_index(sent + sync_code_offset_seconds() + geometric_delay_s(i, sent)))
            if 0 <= toa < n_samples:
                yield toa, i, emitter.cell.pci

    for toa, i, pci in heapq.merge(*(arrivals(i, emitter) for i, emitter in enumerate(emitters))):
        yield pci, toa, i


def check_output(out_dir: Path, n_samples: int) -> None:
    """ValueError before a run whose bag cannot be written where asked, or would not fit there:
    int16 codes compress to about 3/4 with zstd (the bundled bag: 0.73)."""
    existing = next(p for p in (out_dir, *out_dir.parents) if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"{out_dir}: cannot write a bag there ({existing} is not a writable directory)")
    needed = n_samples * 2 * 0.75
    free = shutil.disk_usage(existing).free
    if needed > 0.95 * free:
        raise ValueError(f"{out_dir}: the bag would take about {_size(needed)} and {_size(free)} is free there; "
                         "record less, or elsewhere")


def _size(n_bytes: float) -> str:
    return f"{n_bytes / 1e9:.1f} GB" if n_bytes >= 1e9 else f"{n_bytes / 1e6:.1f} MB"


def _provenance(scenario_path: Path, scenario_bytes: bytes, seed: int, seconds: float, twin: Twin) -> str:
    return json.dumps(
        {
            "generator": f"deepsync {deepsync.__version__} simulate",
            "scenario": str(scenario_path),
            "scenario_sha256": hashlib.sha256(scenario_bytes).hexdigest(),
            "seed": seed,
            "seconds": seconds,
            "frontend": asdict(twin.frontend),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "origin": asdict(twin.scenario.origin),
            "sites": truth_sites(twin),
        },
        sort_keys=True,
    )


def truth_sites(twin: Twin) -> list[dict]:
    """What a perfect tower database would say about each site of the twin, for the bag's
    provenance: position (``height_m`` above ground), the frame timing offset at the first
    sample and how fast it changes (the frame clock's drift), and the oscillator error."""
    out = []
    for site in twin.sites:
        clock = next(e for e in twin.emitters if e.site == site.name)  # its cells share one clock
        out.append({
            "name": site.name,
            "latitude_deg": site.latitude_deg,
            "longitude_deg": site.longitude_deg,
            "height_m": site.height_m,
            "timing_offset_us": clock.timing_offset_at(0.0) * 1e6,
            "timing_drift_ns_per_s": clock.timing_drift_s_per_s * 1e9,
            "frequency_error_ppb": site.frequency_error_ppb,
        })
    return out


def record_scenario(
    scenario_path: str | Path,
    seconds: float,
    out_dir: str | Path,
    *,
    seed: int | None = None,
    workers: int = 1,
    overwrite: bool = False,
    progress: bool = True,
) -> RecordingSummary:
    """Simulate ``seconds`` of a scenario into the bag ``out_dir`` (written atomically)."""
    if not (math.isfinite(seconds) and FRAME_SECONDS <= seconds <= MAX_SECONDS):
        raise ValueError(f"--seconds must be at least one 10 ms frame and at most a day ({MAX_SECONDS:g} s), "
                         f"got {seconds!r}")
    scenario_path = Path(scenario_path)
    scenario_bytes = read_config_bytes(scenario_path)  # once: a FIFO cannot be read again for the hash
    scenario = parse_scenario(parse_yaml(scenario_bytes, str(scenario_path)))
    seed = scenario.seed if seed is None else int(seed)
    if not SEED_RANGE[0] <= seed <= SEED_RANGE[1]:
        raise ValueError(f"--seed must be in [{SEED_RANGE[0]}, {SEED_RANGE[1]}] (bag provenance and ROS "
                         f"parameters hold it as int64), got {reprlib.repr(seed)}")
    twin = build_twin(scenario)
    try:  # a bag the cell search can read, or none
        check_stack_rate(twin.frontend.adc_rate_hz)
    except ValueError as error:
        raise ValueError(f"{scenario_path}: frontend.adc_rate_hz: {error}") from None
    simulator = EnvelopeSimulator(twin.emitters, twin.channel, twin.frontend, seed, epoch_ns=EPOCH_NS)
    rate = twin.frontend.adc_rate_hz
    n_samples = int(round(seconds * rate))
    chunk = max(1, round(FRAME_SECONDS * rate))
    check_output(Path(out_dir), n_samples)

    codes = truth_timing(twin.emitters, twin.geometric_delay_s, simulator, n_samples)
    code = next(codes, None)
    pose_every = max(1, round(POSE_PERIOD_SECONDS * rate))
    stats = SimulationStats()
    started = time.perf_counter()
    chunks = truth_messages = 0
    provenance = _provenance(scenario_path, scenario_bytes, seed, seconds, twin)
    with BagWriter(out_dir, overwrite=overwrite, provenance=provenance) as bag:
        bar = tqdm(total=n_samples, unit="S", unit_scale=True, disable=not progress, desc="simulate")
        for envelope in simulator.stream(seconds, chunk_samples=chunk, workers=workers, stats=stats):
            first, end = envelope.first_sample_index, envelope.end_sample_index
            for n in range(-(-first // pose_every) * pose_every, end, pose_every):
                x, y, z = twin.receiver_enu(float(simulator.clock.true_time(n / rate)))
                bag.write_truth_pose(simulator.stamp_ns(n), float(x), float(y), float(z))
                truth_messages += 1
            records = []
            while code is not None and code[1] < end:
                pci, toa, _ = code
                records.append(CellTiming(pci, toa, 0.0, float("nan"), TRUTH_ESTIMATOR))
                code = next(codes, None)
            if records:
                bag.write_truth_cell_timing(StackArrivals(envelope.stamp_ns, first, rate, tuple(records)))
                truth_messages += 1
            bag.write_envelope(envelope)
            chunks += 1
            bar.update(len(envelope.samples))
        bar.close()
    wall = time.perf_counter() - started
    out_dir = Path(out_dir)
    size = sum(p.stat().st_size for p in out_dir.rglob("*") if p.is_file())
    return RecordingSummary(
        out=str(out_dir),
        scenario=str(scenario_path),
        seed=seed,
        seconds=n_samples / rate,
        samples=stats.samples,
        chunks=chunks,
        truth_messages=truth_messages,
        bag_bytes=size,
        wall_seconds=wall,
        stats=stats,
        cells=cell_summaries(twin),
    )


def route_set_bag(out_dir: str | Path, scenario_path: str | Path, seed: int) -> Path:
    """Where a route set keeps the bag of one scenario and seed: ``<out>/<scenario>_seed<seed>``."""
    return Path(out_dir) / f"{Path(scenario_path).stem}_seed{seed}"


def record_route_set(
    scenarios: list[str | Path],
    seeds: list[int],
    seconds: float,
    out_dir: str | Path,
    runner: JobRunner,
    *,
    overwrite: bool = False,
) -> Iterator[RecordingSummary]:
    """A bag for every scenario and seed (``route_set_bag``), one job each, on ``runner``'s
    processes or Ray cluster; bags already there are kept (a rerun makes the missing ones)
    unless ``overwrite``. Summaries come as their bags are finished."""
    jobs = []
    for scenario in scenarios:
        if Path(scenario).exists() and not Path(scenario).is_file():  # every seed's job reads it: a pipe gives one
            raise ValueError(f"{scenario}: a route set reads its scenario once per seed: give a file, not a pipe")
        load_scenario(scenario)  # a bad file fails here, before any job starts
        for seed in seeds:
            out = route_set_bag(out_dir, scenario, seed)
            if overwrite or not out.exists():
                jobs.append((str(scenario), seconds, str(out), seed, overwrite))
    return runner.map(_record_one, jobs)


def _record_one(scenario: str, seconds: float, out: str, seed: int, overwrite: bool) -> RecordingSummary:
    return record_scenario(scenario, seconds, out, seed=seed, overwrite=overwrite, progress=False)
