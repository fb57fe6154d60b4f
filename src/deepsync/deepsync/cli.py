"""The ``deepsync`` command: simulate recordings, inspect bags, detect cells, evaluate a route,
calibrate site clocks, survey site bias maps, run the demo.

Argument parsing and printing only: the work is done by the pipeline (``deepsync.pipeline``)
over a source (``deepsync.sources``), and reported by ``deepsync.eval``."""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import reprlib
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from deepsync.bag import POSE_TOPIC, BagError, BagInfo, bag_info
from deepsync.configio import ConfigError
from deepsync.eval.cell_search import CellSearch, SearchedStack
from deepsync.eval.compare import DEFAULT_TOLERANCE_M, compare_poses
from deepsync.fusion.bias_map import BiasMap, SurveyConfig, load_bias_map
from deepsync.jobs import JobRunner
from deepsync.motion import DEFAULT_MOTION, MOTION
from deepsync.numeric import one_blas_thread
from deepsync.pipeline import PipelineConfig, StackResult, setting_paths
from deepsync.schema import Setting, add_flag, settings
from deepsync.sources import BagSource, SampleFormat, open_source
from deepsync.sync.stacking import StackConfig
from deepsync.timing import network_install_hint
from deepsync.towers import load_tower_database
from deepsync.types import HealthKind, NoFix

MAX_WORKERS = 64
INITIAL_STD_RANGE_M = (0.01, 1e4)  # evaluate-route --initial-pose-std


def _workers(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not 1 <= value <= MAX_WORKERS:
        raise argparse.ArgumentTypeError(f"{value} workers: give 1..{MAX_WORKERS} processes")
    return value


def _bounded_float(text: str, *, positive: bool) -> float:
    what = "a positive number" if positive else "a number >= 0"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{reprlib.repr(text)} is not a number") from None
    if not (math.isfinite(value) and (value > 0 if positive else value >= 0)):
        raise argparse.ArgumentTypeError(f"{reprlib.repr(text)} must be {what}")
    return value


def _positive_float(text: str) -> float:
    return _bounded_float(text, positive=True)


def _non_negative_float(text: str) -> float:
    return _bounded_float(text, positive=False)


MAX_SEEDS = 10_000  # bags a route set makes (a range of 10^12 seeds was built as a list)


def _seeds(text: str) -> list[int]:
    """``1-12`` or ``3,5,9`` (or both, comma-separated) as a list of seeds: each an int64 (as a
    bag's provenance holds it), at most ``MAX_SEEDS`` of them, counted before any list is made."""
    from deepsync.twin.scenario import SEED_RANGE

    ranges = []
    try:
        for part in text.split(","):
            low, _, high = part.partition("-")
            ranges.append((int(low), int(high or low)))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{reprlib.repr(text)}: give seeds as 1-12 or 3,5,9") from None
    if any(not SEED_RANGE[0] <= value <= SEED_RANGE[1] for pair in ranges for value in pair):
        raise argparse.ArgumentTypeError(f"{reprlib.repr(text)}: seeds must be in [{SEED_RANGE[0]}, {SEED_RANGE[1]}]")
    count = sum(max(0, high - low + 1) for low, high in ranges)
    if not 1 <= count <= MAX_SEEDS:
        raise argparse.ArgumentTypeError(f"{reprlib.repr(text)}: {count} seeds; give 1..{MAX_SEEDS}")
    return [seed for low, high in ranges for seed in range(low, high + 1)]


def _aiding_arguments(command: argparse.ArgumentParser) -> None:
    """What a route evaluation may give the tracker besides the sites, drawn from the truth."""
    command.add_argument("--gnss-interval", type=_non_negative_float, metavar="S",
                         help="give the tracker a GNSS fix drawn from the truth every S seconds (0: only at the "
                         "start), as a receiver that runs its GNSS now and then")
    command.add_argument("--gnss-std", type=_positive_float, default=5.0, metavar="M",
                         help="the GNSS fixes' error and claimed 1-sigma per horizontal axis (default %(default)g m)")
    command.add_argument("--odometry-std", type=_positive_float, metavar="F",
                         help="give the tracker odometry at 10 Hz: the true velocity in an odometry frame of unknown "
                         "yaw, with a fractional error F (a scale error and noise) and a slow yaw drift")
    command.add_argument("--odometry-in-map", action="store_true",
                         help="give that odometry turned into map by its frame's first yaw (a heading known from the "
                         "start; the yaw's drift and the scale error stay): only its scale is left to estimate")


def _aiding_plan(args: argparse.Namespace):
    from deepsync.eval.aiding import AidingPlan

    if args.odometry_in_map and args.odometry_std is None:
        raise ValueError("--odometry-in-map turns the odometry --odometry-std gives: give --odometry-std F too")
    return AidingPlan(args.gnss_interval, args.gnss_std, args.odometry_std, odometry_in_map=args.odometry_in_map)


def _bias_map_argument(command: argparse.ArgumentParser) -> None:
    command.add_argument("--bias-map", metavar="MAP.npz",
                         help="site bias map (deepsync survey-map) made with the same tower database: each mapped "
                         "site's range bias where the survey went comes off its ranges before fusion")


def _bias_map(args: argparse.Namespace) -> BiasMap | None:
    return None if args.bias_map is None else load_bias_map(args.bias_map)


def _bias_map_text(bias_map: BiasMap | None) -> str:
    return "" if bias_map is None else f"; bias map of {len(bias_map.sites)} site(s) ({bias_map.made_by})"


def _job_arguments(command: argparse.ArgumentParser, workers: int) -> None:
    command.add_argument("--workers", type=_workers, default=workers, help=f"local processes (default {workers})")
    command.add_argument("--ray", metavar="ADDRESS", help="run the jobs on a Ray cluster instead: auto (the cluster "
                         "this machine belongs to), local, or ray://HOST:10001 (needs deepsync[ray])")


def _heading_std(text: str) -> float:
    """A heading's sigma: above 0, at most pi rad."""
    value = _positive_float(text)
    if not value <= math.pi:
        raise argparse.ArgumentTypeError(f"{reprlib.repr(text)} rad: give more than 0, at most pi")
    return value


def _initial_std(text: str) -> float:
    """An initial pose's sigma: from a centimetre (a variance that does not vanish) to 10 km."""
    value = _positive_float(text)
    if not INITIAL_STD_RANGE_M[0] <= value <= INITIAL_STD_RANGE_M[1]:
        raise argparse.ArgumentTypeError(f"{reprlib.repr(text)} m: give {INITIAL_STD_RANGE_M[0]:g}..."
                                         f"{INITIAL_STD_RANGE_M[1]:g} m")
    return value


def _seconds(text: str) -> float:
    """A length of signal to simulate: positive, and at most a day (a bag that large already
    takes 250 GB; 1e308 s overflowed)."""
    from deepsync.recording import MAX_SECONDS

    value = _positive_float(text)
    if value > MAX_SECONDS:
        raise argparse.ArgumentTypeError(f"{text!r} s is more than a day ({MAX_SECONDS:g} s): record less")
    return value


def _seed(text: str) -> int:
    """A seed for the simulator's draws: an int64, as bag provenance and ROS parameters hold it."""
    from deepsync.twin.scenario import SEED_RANGE

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{reprlib.repr(text)} is not a whole number") from None
    if not SEED_RANGE[0] <= value <= SEED_RANGE[1]:
        raise argparse.ArgumentTypeError(f"must be in [{SEED_RANGE[0]}, {SEED_RANGE[1]}], got {reprlib.repr(value)}")
    return value


def _output_file(text: str) -> str:
    """A file (or folder of files) to write at the end of a long run: where it goes is tried at
    the door."""
    from deepsync.outputs import check_writable

    try:
        check_writable(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text


def _frame_counts(text: str) -> tuple[int, ...]:
    """Comma-separated frame counts (``5,10,12``), each a stack's ``n_frames``."""
    return tuple(_setting("n_frames").parse(part) for part in text.split(","))


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
              f"{cell.distance_m:6.0f} m  {'LOS ' if cell.los else 'NLOS'}  "
              + (f"{cell.re_power_dbm:6.1f} dBm/RE" if math.isfinite(cell.re_power_dbm) else "no path at t = 0"))


def _print_bag_info(info: BagInfo) -> None:
    print(f"bag {info.path}: {info.message_count} messages over {info.duration_s:.3f} s")
    for topic, msgtype, count in info.topics:
        print(f"  {topic:<32} {msgtype:<38} {count:6d} messages")
    crc = info.crc
    if crc.complete:
        print(f"  integrity: CRCs on all {crc.chunks} chunks and the summary (checked as they are read)")
    else:
        print(f"  integrity: CRCs on {crc.chunks_with_crc} of {crc.chunks} chunks"
              f"{'' if crc.summary_crc else ', none on the summary'}: corruption there cannot be detected")
    for note in info.notes:
        print(f"  note: {note}")
    if info.provenance_error is not None:
        print(f"  provenance: {_one_line(info.provenance_error)}")
    elif info.provenance is not None:
        made = info.provenance
        print(f"  made by {made.get('generator')} from {made.get('scenario')} (seed {made.get('seed')})")
    if info.truth_codes is not None:
        print("  ground truth: " + ", ".join(f"PCI {pci} ({n} sync codes)" for pci, n in info.truth_codes.items()))


def _cmd_simulate(args: argparse.Namespace) -> int:
    from deepsync.recording import record_scenario

    summary = record_scenario(
        args.scenario, args.seconds, args.out, seed=args.seed, workers=args.workers,
        overwrite=args.overwrite, progress=not args.quiet,
    )
    _print_recording(summary)
    return 0


def _cmd_simulate_set(args: argparse.Namespace) -> int:
    from deepsync.recording import record_route_set

    runner = JobRunner(args.workers, args.ray)
    print(f"route set: {len(args.scenario)} scenario(s) x {len(args.seeds)} seed(s) of {args.seconds:g} s into "
          f"{args.out}, on {runner.description}")
    for summary in record_route_set(args.scenario, args.seeds, args.seconds, args.out, runner, overwrite=args.overwrite):
        print(f"  {summary.out}: {summary.seconds:.1f} s simulated in {summary.wall_seconds:.1f} s")
    return 0


def _cmd_make_dataset(args: argparse.Namespace) -> int:
    try:
        from deepsync.training.train import kept_shards, load_run_config
    except ModuleNotFoundError as error:
        raise ValueError(f"the run config needs {error.name}: {network_install_hint(error.name)}") from None
    from deepsync.training.dataset import generate

    run = load_run_config(args.config)
    cfg = run.training
    runner = JobRunner(args.workers, args.ray)
    print(f"timing examples of {args.config} into {cfg.data_dir}, on {runner.description}")
    try:
        made = generate(Path(cfg.data_dir), {"train": cfg.train_shards, "val": cfg.val_shards,
                                             "test": cfg.test_shards}, run.dataset, workers=args.workers, ray=args.ray)
    except KeyboardInterrupt:
        print(f"deepsync make-dataset: interrupted\n  {kept_shards(cfg)}\n  the same command makes the rest",
              file=sys.stderr)
        return 130
    print(f"  {made} examples made; `deepsync train --config {args.config}` uses them")
    return 0


def _cmd_evaluate_routes(args: argparse.Namespace) -> int:
    from deepsync.eval.route_set import evaluate_route_set, write_table

    runner = JobRunner(args.workers, args.ray)
    aiding = _aiding_plan(args)
    print(f"route evaluation of {len(args.bag)} bag(s) with {args.towers}, on {runner.description}; {aiding.describes}"
          + ("" if args.bias_map is None else f"; bias map {args.bias_map}"))
    for bag, summary in evaluate_route_set(args.bag, args.towers, args.out, runner, _pipeline_config(args), aiding,
                                           args.bias_map):
        print(f"  {bag}: {summary['stacks']} stacks, heard {', '.join(summary['sites_heard']) or 'no site'}")
    print(f"  written: {write_table(args.out, args.bag)}")
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    _print_bag_info(bag_info(args.bag))
    return 0


def _print_cell_search(search: CellSearch, towers_path: str | None, verbose: bool = True) -> None:
    """Each stack's confirmed cells (if verbose) with their arrival and the error against the
    ground truth, if known; a run of stacks like the last one printed, with nothing in them, as
    one line."""
    config = search.config
    mode = f"known PCIs from {towers_path} ({len(search.towers.pcis)} PCIs)" if search.towers else "blind (all 504 PCIs)"
    print(f"cell search over {search.source.description}\n  {config.sync.stack.n_frames}-frame stacks, {mode}; a cell "
          f"is reported once found in {config.sync.confirm_stacks} stacks in a row; timing: "
          f"{config.timing.estimator.name}")
    if verbose:
        print(f"  tentative: found, not yet in {config.sync.confirm_stacks} stacks in a row; runners-up: the PCIs "
              "that scored next for the same code (the envelope keeps little of a cell's identity); "
              f"{HealthKind.MISALIGNED.value}: the receiver clock's drift smeared the stack's frames; "
              f"{HealthKind.CLIPPED.value}: samples at the ADC's rails; {HealthKind.NO_SIGNAL.value}: nothing to "
              "search")
    alike: list[dict] = []  # stacks not printed: like the last printed one, with no cell and no event
    printed: list | None = None  # the flags of the last stack printed
    for item in search.run():
        if not isinstance(item, SearchedStack):
            print(f"  source: {item}")
            continue
        if not verbose:
            continue
        kinds = [flag.kind for flag in item.result.sync.flags]
        if item.quiet and kinds == printed:
            alike.append(item.record)  # a silent file's 56,000 identical lines, said once
            continue
        _print_alike(alike)
        _print_stack(item.result, item.record, search.truth)
        printed = kinds if item.quiet else None
    _print_alike(alike)


def _print_alike(alike: list[dict]) -> None:
    """One line for the run of stacks like the last one printed (and the run emptied)."""
    if alike:
        print(f"  ... {len(alike)} more stack(s) like it, to {alike[-1]['time_s']:.3f} s")
        alike.clear()


def _print_stack(result: StackResult, record: dict, truth: dict[int, np.ndarray]) -> None:
    sync = result.sync
    clock = "" if sync.clock_drift_ppm is None else f", receiver clock {sync.clock_drift_ppm:+.1f} ppm"
    print(f"  stack at {record['time_s']:7.3f} s{clock}: {len(sync.cells)} cell(s), {len(sync.tentative)} "
          "tentative" + "".join(f"; {flag}" for flag in record["flags"]))
    for event in record["events"]:
        print(f"    input: {event}")
    for cell in record["cells"]:
        line = (f"    PCI {cell['pci']:3d}  code at {cell['toa']:12.2f} +- {cell['std']:.3f} samples "
                f"({cell['estimator']}, bound {cell['crlb_std']:.3f})  peak {cell['peak_sigma']:5.1f} sigma  "
                f"SNR {cell['snr_db']:5.1f} dB  runners-up " + ", ".join(map(str, cell["runners_up"])))
        if cell["truth_error"] is not None:
            line += f"  (truth {cell['truth_error']:+.3f} samples)"
        elif truth:
            line += "  (no such cell in the truth)"
        print(line)


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
    if (args.bag is None) == (args.input is None):
        raise ValueError("give one recording: --bag BAG or --input FILE")
    if args.bag is not None:
        source = BagSource(args.bag)
    else:
        source = open_source(args.input, args.format, args.rate, args.scale)
    towers = None if args.towers is None else load_tower_database(args.towers)
    search = CellSearch(source, towers, args.frames)
    _print_cell_search(search, args.towers)
    _print_summary(search.summary())
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from deepsync.eval import demo

    out = Path(args.out)
    if args.simulate:
        bag = out / "recording"
        with demo.packaged(demo.SCENARIO) as scenario:
            print(f"== simulating {args.simulate:g} s of {_shown(scenario)} into {bag}")
        _print_recording(demo.simulate(args.simulate, bag, args.workers, progress=not args.quiet))
    else:
        bag = demo.find_bag(args.bag)
    with demo.packaged(demo.TOWERS) as towers:
        print(f"== {_shown(bag)} through sync, timing and fusion (tower database {_shown(towers)})")
    result = demo.run_demo(bag, out, progress=not args.quiet, say=_say)
    replayed = result.replayed
    if args.verbose:
        for epoch in result.epochs:
            print(f"  {epoch.seconds:5.2f} s  {epoch.cells} cells  sites {','.join(epoch.sites) or '-':6s}  "
                  + "  ".join(f"{name} {_answer(answer)}" for name, answer in epoch.answers.items()))
    print(f"\n  recording   {replayed.signal_seconds:.1f} s of ADC stream, {result.walked_m:.1f} m walked (ground truth "
          "included)")
    heard = (f"{len(result.pcis)} cells (PCI {', '.join(map(str, result.pcis))}) on {len(result.sites_heard)} sites "
             f"({', '.join(result.sites_heard) or 'none placed by the tower database'})" if result.pcis else "no cell")
    print(f"  heard       {heard}; sites per stack: {_per_stack_text(result.sites_per_stack)}")
    print(f"  {'':11s} {'fix rate':>8s} {'median':>7s} {'p90':>7s}   horizontal error against the truth, m")
    for name, method in result.methods.items():
        print(f"  {name:11s} {method['fix_rate']:8.0%} {_metres(method['median_m'])} {_metres(method['p90_m'])}")
    print(f"  {'bound':11s} {'':8s} {_metres(result.bound['median_m'])} {_metres(result.bound['p90_m'])}   "
          "(position Cramer-Rao bound, stacks with >= 3 sites)")
    print(f"  speed       {replayed.signal_seconds:.1f} s of signal in {replayed.wall_seconds:.1f} s: "
          f"{replayed.realtime_factor:.1f}x real time (one process: read, sync, timing, fusion, write)")
    _print_health(replayed.health)
    print(f"  written     {replayed.out} (MCAP: {', '.join(f'{t} {n}' for t, n in replayed.written.items())}; "
          "opens in Foxglove, plays with ros2 bag play)")
    print("              " + ", ".join(str(p) for p in result.report))
    if replayed.damage:
        print(f"  the recording is damaged: {replayed.damage}", file=sys.stderr)
        return 1
    return 0


def _shown(path: Path) -> str:
    """A path under the working directory relative to it, others as given."""
    return str(path.relative_to(Path.cwd())) if path.is_absolute() and path.is_relative_to(Path.cwd()) else str(path)


def _answer(answer: float | NoFix | None) -> str:
    """A stack's answer as the demo scores it: the horizontal error (m) of a fix, or why none."""
    if answer is None:
        return "no fix"
    return f"no fix ({answer.reason.value})" if isinstance(answer, NoFix) else f"{answer:6.1f} m"


def _say(text: str) -> None:
    from tqdm import tqdm

    tqdm.write(f"  note: {text}")


def _per_stack_text(heard: dict[str, int]) -> str:
    """``sites_per_stack`` as printed: "0: 2, 3: 21" (sites heard: stacks)."""
    return ", ".join(f"{k}: {n}" for k, n in heard.items())


def _reasons_text(reasons: dict[str, int]) -> str:
    """No-fix reasons with their counts, the most frequent first."""
    return ", ".join(f"{reason} {n}" for reason, n in reasons.items())


def _print_fixes(fixes: dict, heard: dict[str, int]) -> None:
    """A replay's published answers: how many stacks gave a pose, why the others did not, and
    how many sites the stacks heard (a fix needs three, or a tracker that has started)."""
    if not fixes:
        return
    missing = fixes["epochs"] - fixes["fixes"]
    print(f"  fixes       {fixes['fixes']} of {fixes['epochs']} stacks gave a pose ({fixes['fix_rate']:.0%})"
          + (f"; no fix: {_reasons_text(fixes['no_fix_reasons'])}" if missing else ""))
    print(f"  sites       heard per stack (sites: stacks) {_per_stack_text(heard)}")


def _print_health(health: dict[str, int]) -> None:
    if health:
        print("  health      " + ", ".join(f"{kind} {n}" for kind, n in health.items())
              + "  (stream and stage events, see docs/guide.md: What happens when input is bad)")
    else:
        print("  health      no stage reported a problem")


def _pipeline_config(args: argparse.Namespace) -> PipelineConfig:
    """The pipeline a replaying command asked for (``_replay_arguments``)."""
    return PipelineConfig().with_choices(n_frames=args.frames, hop_frames=args.hop, motion=args.motion,
                                         search_every=args.search_every, estimator=args.estimator,
                                         multipath_std_m=args.multipath_std_m)


def _setting(name: str) -> Setting:
    """A stage config's setting, for its flag (``deepsync.schema.add_flag``)."""
    return setting_paths()[name][1]


def _stacks_text(config: PipelineConfig, motion: str) -> str:
    stack = config.sync.stack
    every = "back to back" if stack.hop == stack.n_frames else f"one every {stack.hop} frames"
    return f"{stack.n_frames}-frame stacks {every}, motion model {motion}"


def _cmd_evaluate_route(args: argparse.Namespace) -> int:
    from deepsync.eval.calibrate import oracle_database
    from deepsync.eval.route import InitialPose, evaluate_route

    source = BagSource(args.bag)
    towers = load_tower_database(args.towers)
    if args.true_clocks:
        towers = oracle_database(towers, source)
    bias_map = _bias_map(args)
    config = _pipeline_config(args)
    aiding = _aiding_plan(args)
    clocks = " with the recording's true site clocks" if args.true_clocks else ""
    print(f"route evaluation of {source.description}\n  tower database {args.towers}{clocks}, "
          f"{_stacks_text(config, args.motion)}; {aiding.describes}{_bias_map_text(bias_map)}")
    if args.initial_heading_std is not None and args.initial_pose_std is None:
        raise ValueError("--initial-heading-std goes with the initial pose: give --initial-pose-std M too")
    initial_pose = None if args.initial_pose_std is None else InitialPose(
        args.initial_pose_std, heading_std_rad=args.initial_heading_std)
    if initial_pose is not None:
        print(f"  the tracker starts from the true start position off by N(0, {args.initial_pose_std:g} m) per axis"
              + ("" if args.initial_heading_std is None else
                 f", facing the way it moves off by N(0, {args.initial_heading_std:g} rad)"))
    summary, paths = evaluate_route(source, towers, Path(args.out), config, progress=not args.quiet,
                                    initial_pose=initial_pose, aiding=aiding, bias_map=bias_map)
    _print_route(summary)
    print("  written: " + ", ".join(str(p) for p in paths))
    return 130 if summary["interrupted"] else 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from deepsync.eval.calibrate import MIN_ARRIVALS, calibrate_route
    from deepsync.towers import write_tower_database

    source = BagSource(args.bag)
    towers = load_tower_database(args.towers)
    config = _pipeline_config(args)
    print(f"site clock calibration from {source.description}\n  tower database {args.towers}, "
          f"{_stacks_text(config, args.motion)}")
    calibration = calibrate_route(source, towers, config, progress=not args.quiet)
    result = calibration.result
    print(f"  {len(result.sites)} sites heard; offsets relative to site {result.reference_site} (the most heard); "
          f"range residual RMS {result.residual_rms_before_m:.1f} m before, {result.residual_rms_after_m:.1f} m after "
          f"(stated sigmas scaled by {result.sigma_scale:.2f})")
    if calibration.skipped:
        print(f"  not calibrated (heard fewer than {MIN_ARRIVALS} times): {', '.join(calibration.skipped)}")
    for site in result.sites:
        print(f"    site {site.site}: offset {site.offset_correction_s * 1e9:+9.1f} +- {site.offset_std_s * 1e9:5.1f} ns, "
              f"drift {site.drift_correction * 1e9:+7.2f} +- {site.drift_std * 1e9:5.2f} ns/s  "
              f"({site.n_arrivals} arrivals, residual RMS {site.residual_rms_m:.1f} m)")
    kept = write_tower_database(calibration.database, Path(args.out), like=args.towers)
    print(f"  written: {args.out}" + ("" if kept else f" (without the comments of {args.towers}: merged into its text, "
                                       "the values would not read back exactly)"))
    return 0


def _cmd_survey_map(args: argparse.Namespace) -> int:
    from deepsync.eval.bias_map import survey_route
    from deepsync.fusion.bias_map import save_bias_map

    source = BagSource(args.bag)
    towers = load_tower_database(args.towers)
    config = _pipeline_config(args)
    survey = SurveyConfig(step_m=args.step_m, smoothing_m=args.smoothing_m)
    print(f"site bias map from {source.description}\n  tower database {args.towers}, "
          f"{_stacks_text(config, args.motion)}; grid every {survey.step_m:g} m, kernel {survey.smoothing_m:g} m")
    surveyed = survey_route(source, towers, config, survey, progress=not args.quiet)
    print(f"  {surveyed.stacks_used} of {len(surveyed.run.epochs)} stacks heard two sites or more; biases relative "
          "to the other sites (a bias common to all is the receiver clock)")
    for site in surveyed.sites:
        known = (f"{site.known_nodes} nodes known, bias {site.low_m:+.0f} to {site.high_m:+.0f} m" if site.known_nodes
                 else "no node known (heard too seldom)")
        print(f"    site {site.site}: {known}")
    print(f"  written: {save_bias_map(surveyed.bias_map, args.out)}")
    return 0


def _cmd_trace_map(args: argparse.Namespace) -> int:
    from deepsync.eval.traced_map import TracedMapConfig, traced_bias_map

    config = TracedMapConfig(margin_m=args.margin_m, node_step_m=args.step_m, smoothing_m=args.smoothing_m)
    runner = JobRunner(args.workers, args.ray)
    print(f"site bias map traced from {args.scenario}: street nodes every {config.node_step_m:g} m within "
          f"{config.margin_m:g} m of the receiver's route, each site simulated alone for {config.stacks} stacks of "
          f"{config.stack_frames} frames there, on {runner.description}")
    traced = traced_bias_map(args.scenario, args.out, config, runner, progress=not args.quiet)
    print(f"  {traced.nodes} street nodes; whole biases (the simulator knows the receiver clock)")
    for site in traced.sites:
        known = (f"heard at {traced.heard[site.site]} nodes, {site.known_nodes} map nodes known, bias "
                 f"{site.low_m:+.0f} to {site.high_m:+.0f} m" if site.known_nodes else "no map node known")
        print(f"    site {site.site}: {known}")
    unheard = sorted(name for name, count in traced.heard.items() if not count)
    if unheard:
        print(f"  never heard, not mapped: {', '.join(unheard)}")
    print(f"  written: {traced.path}")
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from deepsync.replay import parse_stages, replay_bag

    stages = parse_stages(args.stages)
    towers = None if args.towers is None else load_tower_database(args.towers)
    bias_map = _bias_map(args)
    config = _pipeline_config(args)
    print(f"replay of {args.bag} through {', '.join(stages)}; "
          + (f"tower database {args.towers}" if towers else "no tower database") + f", {_stacks_text(config, args.motion)}"
          + _bias_map_text(bias_map))
    summary = replay_bag(args.bag, args.out, towers, config, stages=stages, copy_inputs=args.copy_inputs,
                         overwrite=args.overwrite, progress=not args.quiet, say=_say, bias_map=bias_map)
    print(f"  {summary.inputs} input messages, {summary.stacks} stacks, {summary.signal_seconds:.1f} s of signal in "
          f"{summary.wall_seconds:.1f} s ({summary.realtime_factor:.1f}x real time)")
    print(f"  written to {summary.out}: " + (", ".join(f"{t} {n}" for t, n in summary.written.items()) or "nothing"))
    _print_fixes(summary.fixes, summary.sites_heard_per_stack)
    _print_health(summary.health)
    if summary.damage:
        print(f"deepsync replay: the input is damaged, replayed up to the damage: {summary.damage}; "
              f"{summary.out} holds everything produced before it", file=sys.stderr)
        return 1
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    try:
        from deepsync.training.train import destination, final_metrics, kept_after_interrupt, load_run_config, train
    except ModuleNotFoundError as error:
        raise ValueError(f"training needs {error.name}: {network_install_hint(error.name)} (scripts/setup.sh "
                         "installs everything)") from None

    run = load_run_config(args.config)
    shipping = destination(run.training, args.replace_shipped)
    print(f"training the timing network from {args.config}: {run.training.steps} steps of "
          f"{run.training.batch_size}, run directory {run.training.run_dir}; the network goes to "
          f"{shipping or Path(run.training.run_dir) / 'best.pt'}")
    try:
        path = train(run, args.config, args.replace_shipped)
    except KeyboardInterrupt:
        print("deepsync train: interrupted", file=sys.stderr)
        for line in kept_after_interrupt(run, args.config, args.replace_shipped):
            print(f"  {line}", file=sys.stderr)
        return 130
    for line in final_metrics(run.training.run_dir):
        print(f"  {line}")
    print(f"  trained network: {path}")
    return 0


def _cmd_evaluate_timing(args: argparse.Namespace) -> int:
    from deepsync.eval.timing import evaluate_timing, headline_table, stats_table

    frames = args.frames
    if args.bag:
        from deepsync.eval.timing import evaluate_timing_bag, side_by_side

        source = BagSource(args.bag)
        towers = None if args.towers is None else load_tower_database(args.towers)
        summary = evaluate_timing_bag(source, towers, args.out, args.checkpoint, frames[0], progress=not args.quiet)
        print(f"timing side by side on {source.description}, {frames[0]} frames: {summary['cells_timed']} cells timed, "
              f"{summary['fallbacks_to_ml']} of them by ML instead of the network; errors against the true "
              "arrival, samples (one is 156 m)")
        for line in stats_table({name: summary[name] for name in side_by_side()}):
            print(f"  {line}")
        print(f"  written: {Path(args.out) / 'timing_bag.json'}")
        return 0
    print(f"timing side by side on {args.data}/{args.split}, {', '.join(map(str, frames))} frames; "
          f"network {args.checkpoint or 'shipped'}")
    summary = evaluate_timing(args.data, args.out, args.checkpoint, frames, args.split, progress=not args.quiet)
    for count, result in summary["frames"].items():
        print(f"  {count} frames, errors against the true first path, samples (one is 156 m); median CRLB "
              f"{result['all']['crlb_median']:.3f}")
        rows = {name: stats for name, stats in result["all"].items() if isinstance(stats, dict)}
        for line in stats_table(rows):
            print(f"    {line}")
    for line in headline_table(summary["headline"]):
        print(f"  {line}")
    print(f"  written: {Path(args.out) / 'timing.json'}, {Path(args.out) / 'timing.png'}")
    return 0


def _cmd_export_onnx(args: argparse.Namespace) -> int:
    from deepsync.timing.checkpoint import load_checkpoint
    from deepsync.timing.export import check_onnx, export_onnx
    from deepsync.timing.network import DEFAULT_CHECKPOINT

    checkpoint = load_checkpoint(args.checkpoint or DEFAULT_CHECKPOINT)
    with _ticking("exporting: torch's exporter traces the network (about a minute and a half on 2 cores)"):
        path = export_onnx(checkpoint, args.out)
    print(f"  written {path} (one self-contained file; its inputs and outputs: docs/design/timing_network.md)")
    with _ticking("checking it in onnxruntime against torch on random inputs"):
        difference = check_onnx(path, checkpoint)
    print(f"  largest |onnxruntime - torch| {difference:.2e}")
    return 0


@contextlib.contextmanager
def _ticking(step: str) -> Iterator[None]:
    """Says what a long step does before it starts and how long it took; on a terminal, the
    seconds count up meanwhile."""
    print(f"  {step} ...", flush=True)
    started = time.monotonic()
    done = threading.Event()

    def tick() -> None:
        while not done.wait(1.0):
            print(f"\r    {time.monotonic() - started:4.0f} s", end="", file=sys.stderr, flush=True)

    ticker = threading.Thread(target=tick, daemon=True) if sys.stderr.isatty() else None
    if ticker is not None:
        ticker.start()
    try:
        yield
    finally:
        done.set()
        if ticker is not None:
            ticker.join()
            print("\r", end="", file=sys.stderr, flush=True)
    print(f"    done in {time.monotonic() - started:.0f} s", flush=True)


def _cmd_compare_poses(args: argparse.Namespace) -> int:

    result = compare_poses(args.reference, args.other, args.topic)
    print(f"{args.topic}: {result.matched} poses at the same stamps, {result.only_reference} only in "
          f"{args.reference}, {result.only_other} only in {args.other}")
    if result.not_finite:
        print(f"  {result.not_finite} of them hold NaN or inf (position, orientation or covariance) on either side")
    if result.matched > result.not_finite:
        print(f"  position difference: median {result.median_difference_m:.3g} m, largest "
              f"{result.max_difference_m:.3g} m; horizontal sigmas within a factor {result.max_sigma_ratio:.4g}")
    same = result.same(args.tolerance)
    print("  the same poses" if same else f"  NOT the same poses (tolerance {args.tolerance:g} m)")
    return 0 if same else 1


def _metres(value: float | None) -> str:
    return "    -" if value is None else f"{value:7.1f}"


def _print_route(summary: dict) -> None:
    if summary["interrupted"]:
        print("  interrupted: the numbers cover what was replayed")
    heard = _per_stack_text(summary["sites_heard_per_stack"])
    print(f"  {summary['stacks']} stacks over {summary['seconds']:.1f} s; sites heard per stack ({heard}); "
          f"heard at all: {', '.join(summary['sites_heard']) or 'none'}")
    print(f"  {'method':10s} {'fix rate':>8s} {'median':>7s} {'p90':>7s} {'p95':>7s} {'NEES':>6s}  "
          "(horizontal error in m; NEES 2 if the covariance is honest)  no-fix reasons")
    for name, method in summary["methods"].items():
        if name == "rssi" and not summary["rssi_model"]["fitted"]:
            print(f"  {name:10s} no path-loss model: {summary['rssi_model']['why']}")
            continue
        nees = "     -" if method["nees_mean"] is None else f"{method['nees_mean']:6.1f}"
        reasons = _reasons_text(method["no_fix_reasons"])
        print(f"  {name:10s} {method['fix_rate']:8.0%} {_metres(method['median_m'])} {_metres(method['p90_m'])} "
              f"{_metres(method['p95_m'])} {nees}  {reasons}")
    bound = summary["position_bound"]
    print(f"  {'bound':10s} {bound['stacks']:8d} {_metres(bound['median_m'])} {_metres(bound['p90_m'])}   "
          "(position Cramer-Rao bound where >= 3 sites were heard)")
    learned = summary["learned_site_biases_m"]
    for site, row in summary["sites"].items():
        median = row["median_error_samples"]
        text = "no truth" if median is None else (f"timing error median {median:+.2f}, RMS {row['rms_error_samples']:.2f} "
                                                  f"samples, {row['beyond_1_sample']:.0%} beyond 1 sample")
        bias = "" if site not in learned else (f"; the tracker's bias at the end {learned[site]['bias_m']:+.0f} +- "
                                               f"{learned[site]['std_m']:.0f} m")
        print(f"    site {site}: {row['stacks']} stacks, {text}; claimed sigma "
              f"{row['median_claimed_std_samples']:.2f}{bias}")
    if summary["anchors"]:
        since = ", ".join(f"{row['from_s']:g}-{'' if row['to_s'] is None else format(row['to_s'], 'g')} s: "
                          f"{row['median_m']:.1f} m" for row in summary["tracked_by_time_since_anchor"])
        print(f"  {summary['anchors']} GNSS fixes given; tracked median by time since the last: {since}")
    if summary["aiding_refused"]:
        print(f"  aiding refused {summary['aiding_refused']} times (route.json: aiding_refused per stack)")
    pulls = summary.get("pulls")
    if pulls and pulls["fit"]:
        fit, assumed = pulls["fit"], pulls["assumed"]
        levels = "" if fit["level_std_m"] is None else f", their levels {fit['level_std_m']:.0f} m apart"
        print(f"  the sites' pulls along the path: {fit['sigma_m']:.0f} m changing over {fit['decorrelation_m']:.0f} m"
              f"{levels}; the tracker assumes {assumed['multipath_std_m']:g} m (multipath_std_m) over "
              f"{assumed['bias_decorrelation_m']:g} m (docs/design/fusion.md)")


def _replay_arguments(command: argparse.ArgumentParser, bag_help: str, towers_help: str, *,
                      bag_options: Sequence[str] = ("--bag",), towers_required: bool = True,
                      many_bags: bool = False) -> None:
    """What every command that replays a bag through the whole chain takes."""
    defaults = PipelineConfig()
    many = {"action": "extend", "nargs": "+"} if many_bags else {}
    command.add_argument(*bag_options, dest="bag", required=True, help=bag_help, **many)
    command.add_argument("--towers", required=towers_required, help=towers_help)
    add_flag(command, MOTION, "--motion", default=DEFAULT_MOTION, metavar="MODEL")
    add_flag(command, _setting("n_frames"), "--frames", unset="the motion model's")
    add_flag(command, _setting("hop_frames"), "--hop", unset="the motion model's; with --frames alone, back to back; "
             "e.g. --frames 50 --hop 10 for 50-frame stacks at 10 Hz")
    add_flag(command, _setting("search_every"), "--search-every", default=defaults.sync.search_every)
    add_flag(command, _setting("estimator"), "--estimator", default=defaults.timing.estimator)
    add_flag(command, _setting("multipath_std_m"), "--multipath-std-m", metavar="M",
             unset="the motion model's; evaluate-route measures a simulated route's pulls against it")
    command.add_argument("--quiet", action="store_true", help="no progress bar")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="deepsync", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    workers = max(1, min(os.cpu_count() or 1, 8))

    sim = commands.add_parser("simulate", help="simulate a scenario into an MCAP bag")
    sim.add_argument("--scenario", required=True, help="scenario YAML (see config/scenarios)")
    sim.add_argument("--seconds", required=True, type=_seconds, help="length of the recording")
    sim.add_argument("--out", required=True, help="bag directory to create")
    sim.add_argument("--seed", type=_seed, help="override the scenario's seed")
    sim.add_argument("--workers", type=_workers, default=workers, help=f"processes (default {workers})")
    sim.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    sim.add_argument("--quiet", action="store_true", help="no progress bar")
    sim.set_defaults(run=_cmd_simulate)

    route_set = commands.add_parser("simulate-set", help="a bag for every scenario and seed (a route set), in "
                                    "local processes or on a Ray cluster")
    route_set.add_argument("--scenario", required=True, action="append", help="scenario YAML (repeat for more)")
    route_set.add_argument("--seeds", required=True, type=_seeds, help="seeds, e.g. 1-12 or 3,5,9")
    route_set.add_argument("--seconds", required=True, type=_seconds, help="length of each recording")
    route_set.add_argument("--out", required=True, help="directory of the bags (<scenario>_seed<seed>)")
    route_set.add_argument("--overwrite", action="store_true", help="replace bags already there (default: keep them)")
    _job_arguments(route_set, workers)
    route_set.set_defaults(run=_cmd_simulate_set)

    detect = commands.add_parser("detect", help="cell search and timing over a recording (bag, I/Q or envelope file)")
    detect.add_argument("--bag", help="rosbag2 bag (directory or .mcap) with /deepsync/envelope")
    detect.add_argument("--input", metavar="FILE|URL",
                        help="a recording: raw I/Q or envelope file, SigMF (.sigmf-meta/-data, .sigmf) or a bag; "
                             "or a live receiver: rtl_tcp://HOST:PORT?freq=1860e6, tcp://HOST:PORT, - (standard "
                             "input), a serial device, soapy://DRIVER?freq=... (docs/live_receivers.md); "
                             "complex I/Q becomes the envelope |x|^2")
    detect.add_argument("--format", choices=[f.value for f in SampleFormat],
                        help="sample format of a raw --input or a byte stream (SigMF datatype names: cu8 RTL-SDR, "
                             "ci8 HackRF, ...); guessed from a file's extension where it is unambiguous")
    detect.add_argument("--rate", type=_positive_float,
                        help="sample rate of a raw --input or a live stream (Hz), e.g. 1.92e6 (rtl_tcp: the default)")
    detect.add_argument("--scale", type=_positive_float,
                        help="envelope units per ADC code for --input (default: a recording's peak, a live "
                             "stream's full scale, maps to 32766)")
    detect.add_argument("--towers", help="tower database YAML (known-PCI mode); blind without")
    # a cell search shows each stack: short ones, back to back
    add_flag(detect, _setting("n_frames"), "--frames", default=StackConfig().n_frames)
    detect.set_defaults(run=_cmd_detect)

    route = commands.add_parser("evaluate-route", help="fixes along a recorded route against its ground truth "
                                "(snapshot, tracked, RSSI, the position bound): table, JSON and figures")
    _replay_arguments(route, "bag with /deepsync/envelope and /deepsync/truth/pose",
                      "tower database YAML with origin, positions and timing")
    route.add_argument("--out", default=str(Path("out") / "route"), type=_output_file,
                       help="where route.json and the PNGs go")
    route.add_argument("--initial-pose-std", type=_initial_std, metavar="M",
                       help="start the tracker from an initial position: the true start, off by a draw of "
                       "N(0, M^2) per axis and claiming M (what an operator's /initialpose gives where too few "
                       "sites are heard to start)")
    route.add_argument("--initial-heading-std", type=_heading_std, metavar="R",
                       help="with --initial-pose-std: the initial pose also faces the way the receiver moves, off by "
                       "a draw of N(0, R^2) rad and claiming R (RViz's drag), which aligns --odometry-std's frame "
                       "at once")
    route.add_argument("--true-clocks", action="store_true",
                       help="a simulated bag: each site's timing offset and drift from the recording's truth, as a "
                       "synchronised network or a calibrated database gives them (a database without timing "
                       "offsets, like config/towers/munich_walk.yaml, places no site otherwise)")
    _aiding_arguments(route)
    _bias_map_argument(route)
    route.set_defaults(run=_cmd_evaluate_route)

    routes = commands.add_parser("evaluate-routes", help="evaluate-route on many bags, in local processes or on a "
                                 "Ray cluster: a report per bag and route_set.json")
    _replay_arguments(routes, "bags with /deepsync/envelope and /deepsync/truth/pose (e.g. --bag bags/set/*)",
                      "tower database YAML with origin, positions and timing", many_bags=True)
    routes.add_argument("--out", required=True, type=_output_file, help="where the reports (one directory per bag) go")
    _aiding_arguments(routes)
    _bias_map_argument(routes)
    _job_arguments(routes, workers)
    routes.set_defaults(run=_cmd_evaluate_routes)

    replay = commands.add_parser("replay", help="run the chain's stages over a bag and write what the nodes publish "
                                 "(sync windows, cell timing, pose with covariance, NavSatFix) into a new bag")
    _replay_arguments(replay, "bag (directory or .mcap) with the first stage's input topic (--bag: the old spelling)",
                      "tower database YAML (origin, positions and timing for fusion); without it the cell search "
                      "runs blind and fusion is skipped", bag_options=("--in", "--bag"), towers_required=False)
    replay.add_argument("--out", required=True, help="bag directory to create")
    replay.add_argument("--stages", default="sync,timing,fusion",
                        help="a contiguous part of sync,timing,fusion (default all); timing starts from "
                             "/deepsync/sync_windows, fusion from /deepsync/cell_timing")
    replay.add_argument("--copy-inputs", action="store_true",
                        help="also copy every input topic (the envelope too); the truth is always copied")
    replay.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    _bias_map_argument(replay)
    replay.set_defaults(run=_cmd_replay)

    survey_map = commands.add_parser("survey-map", help="a site bias map from a recording with ground truth: each "
                                     "heard site's range bias where the recording went, for --bias-map")
    _replay_arguments(survey_map, "bag with /deepsync/envelope and /deepsync/truth/pose (a simulated walk, or one "
                      "at surveyed positions)", "tower database YAML the map will be used with (origin, positions "
                      "and timing: its site clocks are the rest of each site's bias)")
    survey_map.add_argument("--out", required=True, type=_output_file, help="the bias map (.npz) to write")
    surveying = settings(SurveyConfig)
    add_flag(survey_map, surveying["step_m"], "--step-m", default=SurveyConfig().step_m)
    add_flag(survey_map, surveying["smoothing_m"], "--smoothing-m", default=SurveyConfig().smoothing_m)
    survey_map.set_defaults(run=_cmd_survey_map)

    trace_map = commands.add_parser("trace-map", help="a site bias map from a ray-traced scenario alone (no "
                                    "recording): each site's bias on the streets around its receiver, for --bias-map")
    trace_map.add_argument("scenario", help="ray-traced scenario YAML (channel: {model: raytraced}); its receiver's "
                           "route or position says where to map")
    trace_map.add_argument("--out", required=True, type=_output_file, help="the bias map (.npz) to write")
    from deepsync.eval.traced_map import TracedMapConfig

    tracing = settings(TracedMapConfig)
    for name in ("margin_m", "smoothing_m"):
        add_flag(trace_map, tracing[name], f"--{name.replace('_', '-')}", default=getattr(TracedMapConfig(), name))
    add_flag(trace_map, tracing["node_step_m"], "--step-m", default=TracedMapConfig().node_step_m)
    _job_arguments(trace_map, 1)
    trace_map.add_argument("--quiet", action="store_true", help="no progress bars")
    trace_map.set_defaults(run=_cmd_trace_map)

    calibrate = commands.add_parser("calibrate", help="estimate each heard site's frame timing offset and drift "
                                    "from a recording with ground truth; write the updated tower database")
    _replay_arguments(calibrate, "bag with /deepsync/envelope and /deepsync/truth/pose",
                      "tower database YAML to start from")
    calibrate.add_argument("--out", required=True, type=_output_file, help="calibrated tower database YAML to write")
    calibrate.set_defaults(run=_cmd_calibrate)

    compare = commands.add_parser("compare-poses", help="do two bags hold the same poses (matched by stamp)? "
                                  "E.g. a live run recorded with ros2 bag record against deepsync replay")
    compare.add_argument("--reference", required=True, help="bag with the expected poses (deepsync replay's)")
    compare.add_argument("--other", required=True, help="bag to check (e.g. recorded from the nodes)")
    compare.add_argument("--topic", default=POSE_TOPIC, help="PoseWithCovarianceStamped topic (default %(default)s)")
    compare.add_argument("--tolerance", type=_positive_float, default=DEFAULT_TOLERANCE_M, metavar="METRES",
                         help="largest position difference still the same (default %(default)s m)")
    compare.set_defaults(run=_cmd_compare_poses)

    training = commands.add_parser("train", help="train the timing network (makes its simulated examples first "
                                   "if missing; resumes an interrupted run)")
    training.add_argument("--config", required=True, help="run YAML (config/timing/timing_net.yaml)")
    training.add_argument("--replace-shipped", action="store_true",
                          help="when the run ends, replace the network shipped with deepsync by its best checkpoint "
                          "(otherwise it stays <run_dir>/best.pt, or goes to the config's training.model_path)")
    training.set_defaults(run=_cmd_train)

    dataset = commands.add_parser("make-dataset", help="make a run config's missing timing examples, in local "
                                  "processes or on a Ray cluster (deepsync train then uses them)")
    dataset.add_argument("--config", required=True, help="run YAML (config/timing/timing_net.yaml)")
    _job_arguments(dataset, workers)
    dataset.set_defaults(run=_cmd_make_dataset)

    evaluate = commands.add_parser("evaluate-timing", help="every timing estimator (network, ML, FFT-upsampled, ...) side "
                                   "by side against the true first path and the CRLB: JSON and a figure")
    evaluate.add_argument("--data", default="data/timing", help="timing data directory (default %(default)s; "
                          "`deepsync make-dataset` makes it, about 20 minutes on 2 cores; `deepsync train` too)")
    evaluate.add_argument("--split", default="test", choices=("train", "val", "test"),
                          help="which examples to score (default %(default)s: those nobody trained or chose on)")
    add_flag(evaluate, _setting("checkpoint"), "--checkpoint", unset="the shipped one")
    evaluate.add_argument("--frames", type=_frame_counts, default="5,10,12",
                          help="stacked frames to evaluate, comma-separated "
                          "(with --bag: the first)")
    evaluate.add_argument("--bag", help="instead of the test set: a simulated bag with ground truth")
    evaluate.add_argument("--towers", help="with --bag: tower database YAML (known-PCI cell search)")
    evaluate.add_argument("--out", default=str(Path("out") / "timing"), type=_output_file,
                          help="where timing.json and timing.png go (with --bag: timing_bag.json)")
    evaluate.add_argument("--quiet", action="store_true", help="no progress bar")
    evaluate.set_defaults(run=_cmd_evaluate_timing)

    onnx = commands.add_parser("export-onnx", help="write the timing network as ONNX and check it against torch")
    onnx.add_argument("--checkpoint", help="network checkpoint (default: the shipped one)")
    onnx.add_argument("--out", required=True, type=_output_file, help="the .onnx file to write")
    onnx.set_defaults(run=_cmd_export_onnx)

    info = commands.add_parser("info", help="describe a bag")
    info.add_argument("--bag", required=True, help="bag directory or .mcap file: its topics and message counts, "
                      "length, integrity, what made it and the ground truth it holds")
    info.set_defaults(run=_cmd_info)

    demo = commands.add_parser("demo", help="the main job on the bundled walk (no ROS needed): replay it through "
                               "every stage into an MCAP bag, a route map, an error CDF and a table")
    demo.add_argument("--out", default=str(Path("out") / "demo"), help="where the demo writes (default %(default)s)")
    demo.add_argument("--verbose", action="store_true", help="print every stack: cells, sites, fix errors")
    recording = demo.add_mutually_exclusive_group()
    recording.add_argument("--bag", help="a recording of the demo's walk to replay instead of the bundled "
                           "bags/campus_route (which comes with the source checkout, not with an installed package)")
    recording.add_argument("--simulate", type=_seconds, metavar="SECONDS",
                           help="simulate a fresh recording of the demo's scenario this long and use it instead")
    demo.add_argument("--workers", type=_workers, default=workers,
                      help=f"processes simulating a --simulate recording (default {workers})")
    demo.add_argument("--quiet", action="store_true", help="no progress bar")
    demo.set_defaults(run=_cmd_demo)
    return parser


MAX_ERROR_CHARACTERS = 1000


def _one_line(error: object) -> str:
    """An error as the one line the command promises: whitespace runs (a library's multi-line
    message) made single spaces, and a message past ``MAX_ERROR_CHARACTERS`` (a value quoted
    whole) cut with how much was left out."""
    text = " ".join(str(error).split())
    if len(text) > MAX_ERROR_CHARACTERS:
        text = f"{text[:MAX_ERROR_CHARACTERS]}... ({len(text) - MAX_ERROR_CHARACTERS} characters more)"
    return text


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt  # SIGTERM takes Ctrl-C's path: what was being written is removed


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _interrupt) if in_main_thread else None
    try:
        with one_blas_thread():
            return args.run(args)
    except (ConfigError, BagError, ValueError) as error:
        print(f"deepsync {args.command}: error: {_one_line(error)}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader went away (`deepsync info | head`): stop quietly, and keep Python from
        # complaining again when it flushes stdout at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        print(f"deepsync {args.command}: output closed early (broken pipe); stopped", file=sys.stderr)
        return 1
    except OSError as error:
        where = f"{error.filename}: " if error.filename else ""
        print(f"deepsync {args.command}: error: {_one_line(f'{where}{error.strerror or error}')}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"deepsync {args.command}: interrupted; nothing was written", file=sys.stderr)
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
