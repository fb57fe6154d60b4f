"""The ``deepsync`` command: simulate recordings, inspect bags, run the demo."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from deepsync.bag import TRUTH_CELL_TIMING_TOPIC, BagError, BagReader, cell_timing_array_from_msg
from deepsync.bag.writer import PROVENANCE_KEY
from deepsync.configio import ConfigError

REPO = Path(__file__).resolve().parents[3]
DEMO_SCENARIO = REPO / "config" / "scenarios" / "campus.yaml"
DEMO_BAG = REPO / "bags" / "campus"


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be a positive number")
    return value


def _print_recording(summary) -> None:
    stats = summary.stats
    print(f"recorded {summary.seconds:.3f} s of ADC stream into {summary.out}")
    print(f"  scenario {summary.scenario} (seed {summary.seed})")
    print(f"  {summary.samples} samples in {summary.chunks} EnvelopeSamples chunks, {summary.truth_messages} truth messages")
    print(f"  bag size {summary.bag_bytes / 1e6:.2f} MB; simulated in {summary.wall_seconds:.1f} s "
          f"({summary.realtime_factor:.2f} x real time)")
    print(f"  carriers simulated together: {'; '.join(stats.clusters)}")
    print(f"  power at the diode {stats.diode_power_dbm:.1f} dBm, video gain {stats.gain_db:.1f} dB, "
          f"{stats.clipped} clipped samples")
    print("  cells (at t = 0):")
    for cell in summary.cells:
        print(f"    PCI {cell.pci:3d}  site {cell.site:<4} {cell.carrier_mhz:8.1f} MHz {cell.bandwidth_mhz:4g} MHz  "
              f"{cell.distance_m:6.0f} m  {'LOS ' if cell.los else 'NLOS'}  {cell.re_power_dbm:6.1f} dBm/RE")


def describe_bag(path: Path) -> None:
    """Print what a bag holds: topics, types, counts, duration, provenance, truth cells."""
    with BagReader(path) as bag:
        print(f"bag {path}: {bag.message_count} messages over {bag.duration_ns / 1e9:.3f} s")
        for topic, msgtype in sorted(bag.topics.items()):
            print(f"  {topic:<32} {msgtype:<38} {bag.message_counts[topic]:6d} messages")
        provenance = bag.custom_data.get(PROVENANCE_KEY)
        if provenance:
            try:
                info = json.loads(provenance)
                print(f"  made by {info.get('generator')} from {info.get('scenario')} (seed {info.get('seed')})")
            except json.JSONDecodeError:
                print(f"  provenance: {provenance}")
        if TRUTH_CELL_TIMING_TOPIC in bag.topics:
            codes: dict[int, int] = {}
            for item in bag.messages([TRUTH_CELL_TIMING_TOPIC]):
                for record in cell_timing_array_from_msg(item.message):
                    codes[record.pci] = codes.get(record.pci, 0) + 1
            print("  ground truth: " + ", ".join(f"PCI {pci} ({n} sync codes)" for pci, n in sorted(codes.items())))


def _cmd_simulate(args: argparse.Namespace) -> int:
    from deepsync.recording import record_scenario

    summary = record_scenario(
        args.scenario, args.seconds, args.out, seed=args.seed, workers=args.workers,
        overwrite=args.overwrite, progress=not args.quiet,
    )
    _print_recording(summary)
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    describe_bag(Path(args.bag))
    return 0


def _truth_phases(bag_path: Path) -> dict[int, float]:
    """PCI -> true subframe-0 code position modulo the frame, from a bag's ground truth."""
    phases: dict[int, float] = {}
    with BagReader(bag_path) as bag:
        if TRUTH_CELL_TIMING_TOPIC not in bag.topics:
            return phases
        for item in bag.messages([TRUTH_CELL_TIMING_TOPIC]):
            for record in cell_timing_array_from_msg(item.message):
                phases.setdefault(record.pci, record.toa)
    return phases


def detect_in_bag(bag_path: Path, towers_path: Path | None, frames: int, quiet: bool = False) -> list:
    """Run the cell-search stage over a bag; print each stack's cells (and errors vs truth)."""
    from deepsync.bag import read_envelope
    from deepsync.recording import recorded_frontend
    from deepsync.sync.stacking import StackConfig
    from deepsync.sync.stage import SyncConfig, SyncStage
    from deepsync.sync.towers import load_tower_database

    towers = None if towers_path is None else load_tower_database(towers_path)
    stage = SyncStage(recorded_frontend(bag_path), SyncConfig(stack=StackConfig(n_frames=frames)), towers)
    truth = _truth_phases(bag_path)
    mode = f"known PCIs from {towers_path} ({len(towers.pcis)} PCIs)" if towers else "blind (all 504 PCIs)"
    print(f"cell search over {bag_path}: {frames}-frame stacks, {mode}")
    results = []
    for chunk in read_envelope(bag_path):
        for result in stage.process(chunk):
            results.append(result)
            if quiet:
                continue
            t = (result.first_sample_index) / chunk.sample_rate
            note = "" if result.aligned else " (misaligned)"
            print(f"  stack at {t:7.3f} s{note}: {len(result.cells)} cell(s)" + "".join(f"; {f}" for f in result.flags))
            for event in result.events:
                print(f"    input: {event.message}")
            for cell in result.cells:
                d = cell.detection
                position = cell.coarse_index + d.fraction
                line = (f"    PCI {d.pci:3d}  code at {position:12.2f}  peak {d.peak_metric:5.1f} sigma  "
                        f"SNR {d.snr_db:5.1f} dB  margin {d.score_margin:.3f}  runners-up "
                        + ", ".join(str(c.pci) for c in d.candidates[1:4]))
                if d.pci in truth:
                    frame = round(chunk.sample_rate * 0.01)
                    error = (position - truth[d.pci] + frame / 2) % frame - frame / 2
                    line += f"  (truth {error:+.2f} samples)"
                elif truth:
                    line += "  (no such cell in the truth)"
                print(line)
    return results


def _cmd_detect(args: argparse.Namespace) -> int:
    detect_in_bag(Path(args.bag), None if args.towers is None else Path(args.towers), args.frames)
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from deepsync.recording import record_scenario

    print(f"== the bundled recording {DEMO_BAG.relative_to(REPO)}")
    describe_bag(DEMO_BAG)
    out = Path(args.out)
    print(f"\n== simulating {args.seconds:g} s of {DEMO_SCENARIO.relative_to(REPO)} into {out}")
    summary = record_scenario(DEMO_SCENARIO, args.seconds, out, workers=args.workers, overwrite=True,
                              progress=not args.quiet)
    _print_recording(summary)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="deepsync", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    workers = max(1, min(os.cpu_count() or 1, 8))

    sim = commands.add_parser("simulate", help="simulate a scenario into an MCAP bag")
    sim.add_argument("--scenario", required=True, help="scenario YAML (see config/scenarios)")
    sim.add_argument("--seconds", required=True, type=_positive_float, help="length of the recording")
    sim.add_argument("--out", required=True, help="bag directory to create")
    sim.add_argument("--seed", type=int, help="override the scenario's seed")
    sim.add_argument("--workers", type=int, default=workers, help=f"processes (default {workers})")
    sim.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    sim.add_argument("--quiet", action="store_true", help="no progress bar")
    sim.set_defaults(run=_cmd_simulate)

    detect = commands.add_parser("detect", help="cell search over a bag's envelope stream")
    detect.add_argument("--bag", required=True)
    detect.add_argument("--towers", help="tower database YAML (known-PCI mode); blind without")
    detect.add_argument("--frames", type=int, default=10, help="frames per stack (default 10)")
    detect.set_defaults(run=_cmd_detect)

    info = commands.add_parser("info", help="describe a bag")
    info.add_argument("--bag", required=True)
    info.set_defaults(run=_cmd_info)

    demo = commands.add_parser("demo", help="the main job on the bundled data (no ROS needed)")
    demo.add_argument("--out", default=str(REPO / "out" / "demo_campus"), help="where the demo writes")
    demo.add_argument("--seconds", type=_positive_float, default=1.0)
    demo.add_argument("--workers", type=int, default=workers)
    demo.add_argument("--quiet", action="store_true")
    demo.set_defaults(run=_cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (ConfigError, BagError, ValueError, FileNotFoundError) as error:
        print(f"deepsync {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"deepsync {args.command}: interrupted; nothing was written", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
