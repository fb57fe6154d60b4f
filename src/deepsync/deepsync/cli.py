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


def run_detection(chunks, frontend, towers_path: Path | None, frames: int, truth: dict[int, float], label: str) -> list:
    """Run the cell-search stage over a stream; print each stack's confirmed cells with their
    maximum-likelihood sub-sample arrival (and the error against ground truth, if known)."""
    from deepsync.sync.estimators import estimate_ml, noise_psd
    from deepsync.sync.stacking import StackConfig
    from deepsync.sync.stage import SyncConfig, SyncStage
    from deepsync.sync.towers import load_tower_database

    towers = None if towers_path is None else load_tower_database(towers_path)
    stage = SyncStage(frontend, SyncConfig(stack=StackConfig(n_frames=frames)), towers)
    mode = f"known PCIs from {towers_path} ({len(towers.pcis)} PCIs)" if towers else "blind (all 504 PCIs)"
    print(f"cell search over {label}: {frames}-frame stacks, {mode}; a cell is reported once found in "
          f"{stage.config.confirm_stacks} stacks in a row")
    results = []
    for chunk in chunks:
        for result in stage.process(chunk):
            results.append(result)
            clock = "" if result.clock_drift_ppm is None else f", receiver clock {result.clock_drift_ppm:+.1f} ppm"
            print(f"  stack at {result.first_sample_index / chunk.sample_rate:7.3f} s{clock}: {len(result.cells)} "
                  f"cell(s), {len(result.tentative)} tentative" + "".join(f"; {f}" for f in result.flags))
            for event in result.events:
                print(f"    input: {event.message}")
            for cell in result.cells:
                d = cell.detection
                fine = estimate_ml(cell.windows, stage.templates.template(d.pci, 0), cell.margin, noise_psd(cell.windows))
                toa = cell.coarse_index + fine.offset
                line = (f"    PCI {d.pci:3d}  code at {toa:12.2f} +- {fine.std:.3f} samples (ML)  peak {d.peak_metric:5.1f} "
                        f"sigma  SNR {fine.snr_db:5.1f} dB  runners-up " + ", ".join(str(c.pci) for c in d.candidates[1:4]))
                if d.pci in truth:
                    frame = round(chunk.sample_rate * 0.01)
                    error = (toa - truth[d.pci] + frame / 2) % frame - frame / 2
                    line += f"  (truth {error:+.3f} samples)"
                elif truth:
                    line += "  (no such cell in the truth)"
                print(line)
    return results


def _cmd_detect(args: argparse.Namespace) -> int:
    towers = None if args.towers is None else Path(args.towers)
    if (args.bag is None) == (args.iq is None):
        raise ValueError("give either --bag or --iq")
    if args.bag is not None:
        from deepsync.bag import read_envelope
        from deepsync.recording import recorded_frontend

        bag = Path(args.bag)
        run_detection(read_envelope(bag), recorded_frontend(bag), towers, args.frames, _truth_phases(bag), str(bag))
    else:
        from deepsync.sync.iq import envelope_chunks, load_rtlsdr_u8, recording_frontend

        iq = load_rtlsdr_u8(args.iq)
        chunks = envelope_chunks(iq, args.iq_rate, volts_per_code=0.5)
        run_detection(chunks, recording_frontend(args.iq_rate), towers, args.frames, {}, f"|x|^2 of {args.iq}")
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

    detect = commands.add_parser("detect", help="cell search over an envelope stream (bag or I/Q recording)")
    detect.add_argument("--bag", help="rosbag2 bag with /deepsync/envelope")
    detect.add_argument("--iq", help="RTL-SDR recording (8-bit I/Q): its |x|^2 is the envelope")
    detect.add_argument("--iq-rate", type=_positive_float, default=1.92e6, help="sample rate of --iq (Hz)")
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
