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
DEMO_TOWERS = REPO / "config" / "towers" / "campus.yaml"


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


def _frame_error(toa: float, truth: float, frame: int) -> float:
    return (toa - truth + frame / 2) % frame - frame / 2


def run_detection(chunks, frontend, towers_path: Path | None, frames: int, truth: dict[int, float], label: str,
                  verbose: bool = True) -> list[dict]:
    """Run the cell-search stage over a stream; print each stack's confirmed cells (if verbose) with
    their maximum-likelihood sub-sample arrival and the error against ground truth, if known.
    Returns one record per stack: its start time and its confirmed cells."""
    from deepsync.timing.estimators import estimate_ml, noise_psd
    from deepsync.sync.stacking import StackConfig
    from deepsync.sync.stage import SyncConfig, SyncStage
    from deepsync.towers import load_tower_database

    towers = None if towers_path is None else load_tower_database(towers_path)
    stage = SyncStage(frontend, SyncConfig(stack=StackConfig(n_frames=frames)), towers)
    mode = f"known PCIs from {towers_path} ({len(towers.pcis)} PCIs)" if towers else "blind (all 504 PCIs)"
    print(f"cell search over {label}: {frames}-frame stacks, {mode}; a cell is reported once found in "
          f"{stage.config.confirm_stacks} stacks in a row")
    stacks = []
    for chunk in chunks:
        frame = round(chunk.sample_rate * 0.01)
        for result in stage.process(chunk):
            cells = []
            for cell in result.cells:
                d = cell.detection
                fine = estimate_ml(cell.windows, stage.search.code_template(d), cell.margin, noise_psd(cell.windows))
                toa = cell.coarse_index + fine.offset
                error = _frame_error(toa, truth[d.pci], frame) if d.pci in truth else None
                cells.append({"pci": d.pci, "toa": toa, "std": fine.std, "snr_db": fine.snr_db,
                              "peak_sigma": d.peak_metric, "truth_error": error,
                              "runners_up": [c.pci for c in d.candidates[1:4]]})
            stacks.append({"time_s": result.first_sample_index / chunk.sample_rate,
                           "clock_drift_ppm": result.clock_drift_ppm, "flags": list(result.flags), "cells": cells})
            if verbose:
                _print_stack(result, stacks[-1], truth)
    return stacks


def _print_stack(result, record: dict, truth: dict[int, float]) -> None:
    clock = "" if result.clock_drift_ppm is None else f", receiver clock {result.clock_drift_ppm:+.1f} ppm"
    print(f"  stack at {record['time_s']:7.3f} s{clock}: {len(result.cells)} cell(s), {len(result.tentative)} "
          "tentative" + "".join(f"; {f}" for f in result.flags))
    for event in result.events:
        print(f"    input: {event.message}")
    for cell in record["cells"]:
        line = (f"    PCI {cell['pci']:3d}  code at {cell['toa']:12.2f} +- {cell['std']:.3f} samples (ML)  peak "
                f"{cell['peak_sigma']:5.1f} sigma  SNR {cell['snr_db']:5.1f} dB  runners-up "
                + ", ".join(map(str, cell["runners_up"])))
        if cell["truth_error"] is not None:
            line += f"  (truth {cell['truth_error']:+.3f} samples)"
        elif truth:
            line += "  (no such cell in the truth)"
        print(line)


def summarize_detection(stacks: list[dict], truth: dict[int, float]) -> dict:
    """Per cell: in how many stacks it was reported, its timing error against the truth, its claimed
    std; and the truth cells never reported."""
    by_pci: dict[int, list[dict]] = {}
    for stack in stacks:
        for cell in stack["cells"]:
            by_pci.setdefault(cell["pci"], []).append(cell)
    cells = {}
    for pci, found in sorted(by_pci.items()):
        errors = [c["truth_error"] for c in found if c["truth_error"] is not None]
        cells[pci] = {
            "stacks_reported": len(found),
            "in_truth": (pci in truth) if truth else None,  # None: no ground truth to compare with
            "median_snr_db": _median([c["snr_db"] for c in found]),
            "median_claimed_std": _median([c["std"] for c in found]),
            "rms_truth_error": math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else None,
        }
    return {"stacks": len(stacks), "cells": cells, "missed": sorted(set(truth) - set(by_pci))}


def _median(values: list[float]) -> float:
    ordered = sorted(values)
    middle = len(ordered) // 2
    return ordered[middle] if len(ordered) % 2 else (ordered[middle - 1] + ordered[middle]) / 2


def _print_summary(summary: dict) -> None:
    print(f"  {summary['stacks']} stacks:")
    for pci, cell in summary["cells"].items():
        if cell["in_truth"] is None:
            truth = ""
        elif not cell["in_truth"]:
            truth = "  not in the truth"
        else:
            truth = f"  RMS error vs truth {cell['rms_truth_error']:.3f} samples"
        print(f"    PCI {pci:3d}  reported in {cell['stacks_reported']:3d} stacks  SNR {cell['median_snr_db']:5.1f} dB  "
              f"claimed std {cell['median_claimed_std']:.3f} samples{truth}")
    if summary["missed"]:
        print("    never reported: " + ", ".join(f"PCI {pci}" for pci in summary["missed"]))


def _cmd_detect(args: argparse.Namespace) -> int:
    towers = None if args.towers is None else Path(args.towers)
    if (args.bag is None) == (args.iq is None):
        raise ValueError("give either --bag or --iq")
    if args.bag is not None:
        from deepsync.bag import read_envelope
        from deepsync.recording import recorded_frontend

        bag = Path(args.bag)
        truth = _truth_phases(bag)
        stacks = run_detection(read_envelope(bag), recorded_frontend(bag), towers, args.frames, truth, str(bag))
    else:
        from deepsync.sources.iq import envelope_chunks, load_rtlsdr_u8, recording_frontend

        iq = load_rtlsdr_u8(args.iq)
        chunks = envelope_chunks(iq, args.iq_rate, volts_per_code=0.5)
        truth = {}
        stacks = run_detection(chunks, recording_frontend(args.iq_rate), towers, args.frames, truth, f"|x|^2 of {args.iq}")
    _print_summary(summarize_detection(stacks, truth))
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from deepsync.bag import read_envelope
    from deepsync.recording import recorded_frontend

    out = Path(args.out)
    print(f"== the bundled recording {DEMO_BAG.relative_to(REPO)}")
    describe_bag(DEMO_BAG)
    print("\n== cell search and classical sub-sample timing")
    truth = _truth_phases(DEMO_BAG)
    stacks = run_detection(read_envelope(DEMO_BAG), recorded_frontend(DEMO_BAG), DEMO_TOWERS, 10, truth,
                           str(DEMO_BAG.relative_to(REPO)), verbose=args.verbose)
    summary = summarize_detection(stacks, truth)
    _print_summary(summary)
    out.mkdir(parents=True, exist_ok=True)
    report = out / "cell_search.json"
    report.write_text(json.dumps({"bag": str(DEMO_BAG.relative_to(REPO)), "summary": summary, "stacks": stacks},
                                 indent=1))
    print(f"  per-stack results in {report}")
    if args.simulate:
        from deepsync.recording import record_scenario

        bag = out / "recording"
        print(f"\n== simulating {args.simulate:g} s of {DEMO_SCENARIO.relative_to(REPO)} into {bag}")
        _print_recording(record_scenario(DEMO_SCENARIO, args.simulate, bag, workers=args.workers, overwrite=True,
                                         progress=not args.quiet))
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
    demo.add_argument("--verbose", action="store_true", help="print every stack's cells")
    demo.add_argument("--simulate", type=_positive_float, metavar="SECONDS",
                      help="also simulate a fresh recording of the demo scenario this long")
    demo.add_argument("--workers", type=int, default=workers)
    demo.add_argument("--quiet", action="store_true", help="no progress bar")
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
