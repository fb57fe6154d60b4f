"""A recorded route through the whole chain, every fix against the ground truth.

``replay_route`` runs the pipeline (sync, timing, fusion) over a bag that carries the true
receiver track (``/deepsync/truth/pose``) and keeps, per stack, what each method made of it:
the snapshot solver, the tracker, the RSSI baseline (fitted afterwards, see ``rssi_fixes``) and
the position Cramer-Rao bound of the sites heard (their timing bounds and the true geometry).
``summarize_route`` turns that into the numbers people compare: fix rate, horizontal error
median / p90 / p95, no-fix reasons, NEES, GDOP, sites heard per stack.

The truth is the receiver antenna's true position at the stack's stamp; stamps are receiver
clock time, which runs a few ppm off true time: at walking pace that is micrometres.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from deepsync.bag import TRUTH_POSE_TOPIC, BagReader, position_from_pose_msg
from deepsync.bag.convert import stamp_to_ns
from deepsync.eval.aiding import AidingPlan, recording_seed, true_heading
from deepsync.eval.cell_search import timing_error
from deepsync.eval.pulls import describe_pulls, site_pulls
from deepsync.eval.route_scores import CHI2_2DOF_95, METHODS, horizontal_error, nees
from deepsync.fusion.anchors import Anchors, SiteArrival
from deepsync.fusion.calibration import CalibrationObservation
from deepsync.fusion.rssi import RssiAverager, RssiConfig, fit_path_loss, solve_rssi
from deepsync.fusion.bias_map import BiasMap
from deepsync.fusion.snapshot import position_bound
from deepsync.fusion.stage import FusionConfig, FusionResult, FusionStage, answer_counts, sites_per_stack
from deepsync.pipeline import Pipeline, PipelineConfig, places_sites
from deepsync.sources import BagSource
from deepsync.towers import TowerDatabase
from deepsync.twin.scenario import RayTracingSettings, load_scenario
from deepsync.twin.world import twin_cells
from deepsync.types import (
    SPEED_OF_LIGHT_M_S,
    UNMEASURED_VARIANCE,
    Fix,
    GnssFix,
    HealthKind,
    NoFix,
    PositionPrior,
    StackArrivals,
)

HEADING_SPAN_NS = 500_000_000  # the truth's motion this far either side says which way it faces


@dataclass(frozen=True)
class TruthTrack:
    """The true receiver positions of a recording (``map`` ENU) at their stamps."""

    stamps_ns: np.ndarray  # (N,) int64, increasing
    positions: np.ndarray  # (N, 3)

    def at(self, stamp_ns: int | float) -> np.ndarray:
        """Position at ``stamp_ns``, linear between poses (ValueError outside the track)."""
        stamps = self.stamps_ns
        period = (stamps[-1] - stamps[0]) / (len(stamps) - 1)  # a stack may start in the last pose's period
        if not stamps[0] <= stamp_ns <= stamps[-1] + period:
            raise ValueError(f"stamp {stamp_ns} ns is outside the ground-truth track")
        offsets = (stamps - stamps[0]).astype(np.float64)
        t = float(stamp_ns - stamps[0])
        return np.array([np.interp(t, offsets, self.positions[:, k]) for k in range(3)])


def read_truth_track(bag: str | Path) -> TruthTrack:
    """The bag's ``/deepsync/truth/pose`` track; ValueError naming the bag if it has none."""
    with BagReader(bag) as reader:
        if TRUTH_POSE_TOPIC not in reader.topics:
            raise ValueError(f"{bag}: no ground truth ({TRUTH_POSE_TOPIC}); evaluating, calibrating or surveying a "
                             "route needs a simulated recording or one with surveyed positions")
        poses = [(stamp_to_ns(item.message.header.stamp), position_from_pose_msg(item.message))
                 for item in reader.messages([TRUTH_POSE_TOPIC])]
    if len(poses) < 2:
        raise ValueError(f"{bag}: {len(poses)} ground-truth pose(s), at least 2 are needed")
    broken = next((stamp for stamp, position in poses if not np.isfinite(position).all()), None)
    if broken is not None:  # a NaN error would pass every comparison that scores the route
        raise ValueError(f"{bag}: the ground-truth pose stamped {broken} ns holds NaN or inf")
    poses.sort(key=lambda pose: pose[0])
    return TruthTrack(np.array([p[0] for p in poses], dtype=np.int64), np.array([p[1] for p in poses]))


@dataclass
class RouteEpoch:
    """One stack of a route: what was heard and what each method answered."""

    stamp_ns: int
    truth_enu: np.ndarray
    cells: int  # cells timed
    sites: tuple[SiteArrival, ...]  # anchored sites heard
    snapshot: Fix | NoFix
    tracked: Fix | NoFix | None
    bound_m: float  # horizontal DRMS of the position Cramer-Rao bound (NaN: fewer than 3 sites)
    site_truth: dict[str, np.ndarray] = field(default_factory=dict)  # truth at each site's arrival
    timing_errors: dict[str, tuple[float, float]] = field(default_factory=dict)  # site: (error, claimed sigma), samples
    rssi: Fix | NoFix | None = None
    events: tuple[str, ...] = ()  # what fusion refused of the aiding, in words


@dataclass
class RouteRun:
    bag: str
    epochs: list[RouteEpoch]
    reference_ns: int | None  # the fusion stage's time origin: ``SiteArrival.time_s`` counts from it
    interrupted: bool = False
    aiding: str = "no aiding"  # what the tracker was given besides the sites (AidingPlan.describes)
    anchors: tuple[tuple[int, np.ndarray], ...] = ()  # the GNSS fixes given: (stamp, map ENU)
    site_biases: dict[str, tuple[float, float]] = field(default_factory=dict)  # learned at the end: site: (m, sigma m)
    # the odometry frame as learned by the end, and how long into the route it was first aligned
    odometry_frame: dict | None = None

    def since_anchor_s(self, stamp_ns: int) -> float:
        """Seconds from the latest GNSS fix at or before ``stamp_ns`` (NaN before the first)."""
        before = [stamp for stamp, _ in self.anchors if stamp <= stamp_ns]
        return (stamp_ns - before[-1]) * 1e-9 if before else math.nan

    def observations(self, until_ns: int | None = None) -> list[CalibrationObservation]:
        """Every site heard (in stacks stamped up to ``until_ns``), with where the receiver truly
        was when its code arrived."""
        return [observation for epoch, stack in zip(self.epochs, self.observations_by_stack())
                if until_ns is None or epoch.stamp_ns <= until_ns for observation in stack]

    def observations_by_stack(self) -> list[list[CalibrationObservation]]:
        """Every stack's sites with where the receiver truly was when each code arrived: a
        survey (``fusion.bias_map.survey_bias_map``) compares sites within a stack."""
        return [[CalibrationObservation(site, epoch.site_truth[site.site]) for site in epoch.sites]
                for epoch in self.epochs]


@dataclass
class Replay:
    """The arrivals of every stack of a recording, as the timing stage made them: what fusion
    runs on. Fusion is cheap next to the cell search, so variants (another database, tracker
    settings) re-run on one replay."""

    source: BagSource
    arrivals: list[StackArrivals]
    truth: TruthTrack
    true_arrivals: dict[int, np.ndarray]
    interrupted: bool = False


def replay(source: BagSource, towers: TowerDatabase, config: PipelineConfig | None = None,
           progress: bool = True) -> Replay:
    """Run the chain's cell search and timing over ``source``. Ctrl-C stops early: what was
    replayed so far is kept, marked ``interrupted``. ValueError if the bag has no ground truth
    or the database places no site."""
    truth = read_truth_track(source.path)
    source.check_frame(towers)
    if not places_sites(towers):
        raise ValueError(f"tower database {towers.name!r} places no site (it needs an origin and sites with "
                         "position and timing offset)")
    pipeline = Pipeline(source.frontend, config, towers)
    arrivals = []
    interrupted = False
    bar = tqdm(total=source.n_chunks, unit="chunk", disable=not progress, desc="replay")
    try:
        for chunk in source.chunks():
            arrivals += [result.arrivals for result in pipeline.process(chunk)]
            bar.update(1)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        bar.close()
    return Replay(source, arrivals, truth, source.truth_arrivals(), interrupted)


@dataclass(frozen=True)
class InitialPose:
    """An operator's initial position, simulated: given before the first stack stamped at or
    after ``after_ns`` (None: the first stack), the truth there off by a draw of N(0, std_m^2)
    per horizontal axis (``seed``), and claiming ``std_m``; with ``heading_std_rad``, the way the
    receiver moves there too (RViz's drag), off by a draw of that sigma and claiming it."""

    std_m: float
    after_ns: int | None = None
    seed: int = 0
    heading_std_rad: float | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.std_m, (int, float)) and math.isfinite(self.std_m) and 0 < self.std_m <= 1e4):
            raise ValueError(f"std_m: {self.std_m!r} must be a positive number of metres (<= 1e4)")
        if self.heading_std_rad is not None and not (isinstance(self.heading_std_rad, (int, float))
                                                     and 0 < self.heading_std_rad <= math.pi):
            raise ValueError(f"heading_std_rad: {self.heading_std_rad!r} must be in (0, pi] rad")

    def for_recording(self, recording: str) -> InitialPose:
        """The pose with the draws of the recording named ``recording`` (``aiding.recording_seed``)."""
        return dataclasses.replace(self, seed=recording_seed(self.seed, recording))

    def prior(self, truth_enu: np.ndarray, heading_rad: float | None = None) -> PositionPrior:
        """The prior at a true position, and heading where one is asked for and known (None: the
        receiver stands)."""
        rng = np.random.default_rng(self.seed)
        offset = rng.normal(0.0, self.std_m, 2)
        covariance = np.diag([self.std_m**2, self.std_m**2, UNMEASURED_VARIANCE])
        position = (truth_enu[0] + offset[0], truth_enu[1] + offset[1], truth_enu[2])
        if self.heading_std_rad is None or heading_rad is None:
            return PositionPrior(position, covariance)
        return PositionPrior(position, covariance, heading_rad + rng.normal(0.0, self.heading_std_rad),
                             self.heading_std_rad)


def fuse_route(recorded: Replay, towers: TowerDatabase, config: FusionConfig | None = None,
               initial_pose: InitialPose | None = None, aiding: AidingPlan | None = None,
               bias_map: BiasMap | None = None) -> RouteRun:
    """Fusion over a replay's arrivals with ``towers`` (and ``bias_map``), every stack paired
    with the truth; the tracker started from ``initial_pose`` where one is given, and given the
    GNSS fixes and odometry ``aiding`` draws from the truth."""
    stage = FusionStage(towers, config, bias_map=bias_map)
    plan = aiding or AidingPlan()
    truth = recorded.truth
    stamps = [arrivals.stamp_ns for arrivals in recorded.arrivals]
    fixes, odometry = [], []
    if stamps:  # from the first stack on, as a receiver starting with its ADC would have them
        end = min(int(truth.stamps_ns[-1]), stamps[-1])
        fixes = plan.gnss_fixes(stamps[0], end, truth.at, stage.frame)
        odometry = plan.odometry(stamps[0], end, truth.stamps_ns, truth.positions)
    aids = sorted([*fixes, *odometry], key=lambda aid: aid.stamp_ns)
    fused, notes = [], []
    aligned_ns = None
    pending = initial_pose
    given = 0
    for k, arrivals in enumerate(recorded.arrivals):
        if pending is not None and (pending.after_ns is None or arrivals.stamp_ns >= pending.after_ns):
            stage.start_from(pending.prior(truth.at(arrivals.stamp_ns), _true_heading_at(truth, arrivals.stamp_ns)))
            pending = None
        # what a live receiver has queued by the time this stack is fused: everything up to the next stack
        due = stamps[k + 1] if k + 1 < len(stamps) else math.inf
        refused = []
        while given < len(aids) and aids[given].stamp_ns <= due:
            event = (stage.add_gnss if isinstance(aids[given], GnssFix) else stage.add_odometry)(aids[given])
            refused += [] if event is None else [event.message]
            given += 1
        fusion = stage.process(arrivals)
        if aligned_ns is None and stage.tracker is not None and stage.tracker.odometry_frame() is not None:
            aligned_ns = arrivals.stamp_ns
        notes.append(tuple(refused) + tuple(e.message for e in fusion.events if e.kind is HealthKind.AIDING_REFUSED))
        fused.append((arrivals, fusion, stage.reference_ns))
    run = score_stacks(str(recorded.source.path), fused, truth, recorded.true_arrivals, recorded.interrupted)
    for epoch, events in zip(run.epochs, notes):
        epoch.events = events
    run.aiding = plan.describes
    run.anchors = tuple((fix.stamp_ns, np.asarray(stage.frame.geodetic_to_enu(fix.latitude_deg, fix.longitude_deg,
                                                                              fix.height_m))) for fix in fixes)
    if stage.tracker is not None:
        run.site_biases = {name: (b.bias_m, b.std_m) for name, b in stage.tracker.site_biases().items()}
        if aligned_ns is not None:
            run.odometry_frame = {"aligned_after_s": (aligned_ns - stamps[0]) * 1e-9,
                                  **dataclasses.asdict(stage.tracker.odometry_frame())}
    return run


def _true_heading_at(truth: TruthTrack, stamp_ns: int) -> float | None:
    """The way the receiver moves at ``stamp_ns`` (its truth over +-``HEADING_SPAN_NS``); None
    where it stands."""
    low = max(int(truth.stamps_ns[0]), stamp_ns - HEADING_SPAN_NS)
    high = min(int(truth.stamps_ns[-1]), stamp_ns + HEADING_SPAN_NS)
    if high <= low:
        return None
    return true_heading((truth.at(high) - truth.at(low))[:2] / ((high - low) * 1e-9))


def score_stacks(bag: str, fused: Sequence[tuple[StackArrivals, FusionResult, int]], truth: TruthTrack,
                 true_arrivals: dict[int, np.ndarray], interrupted: bool = False) -> RouteRun:
    """Every stack's arrivals and fusion result, with the fusion stage's time origin after it
    (``FusionStage.reference_ns``), paired with the truth: what fusion did along a route."""
    epochs = [_epoch(arrivals, fusion, reference_ns, truth, true_arrivals) for arrivals, fusion, reference_ns in fused]
    return RouteRun(bag, epochs, fused[-1][2] if fused else None, interrupted)


def replay_route(source: BagSource, towers: TowerDatabase, config: PipelineConfig | None = None,
                 progress: bool = True, initial_pose: InitialPose | None = None,
                 aiding: AidingPlan | None = None, bias_map: BiasMap | None = None) -> RouteRun:
    """Replay and fuse in one go (a bias map made in another frame is refused before the replay)."""
    config = config or PipelineConfig()
    if bias_map is not None:
        bias_map.check_database(towers)
    return fuse_route(replay(source, towers, config, progress), towers, config.fusion, initial_pose, aiding, bias_map)


def _epoch(arrivals: StackArrivals, fusion: FusionResult, reference_ns: int, truth: TruthTrack,
           true_arrivals: dict[int, np.ndarray]) -> RouteEpoch:
    site_truth = {site.site: truth.at(reference_ns + site.time_s * 1e9) for site in fusion.sites}
    cells = {cell.pci: cell for cell in arrivals.cells}
    errors = {}
    for site in fusion.sites:
        cell = min((cells[pci] for pci in site.pcis), key=lambda c: c.toa_std)
        errors[site.site] = (timing_error(cell.toa, true_arrivals.get(cell.pci, np.empty(0))), cell.toa_std)
    here = truth.at(arrivals.stamp_ns)
    return RouteEpoch(arrivals.stamp_ns, here, len(arrivals.cells), fusion.sites, fusion.snapshot,
                      fusion.tracked, _bound(arrivals, fusion.sites, here), site_truth, errors)


def _bound(arrivals: StackArrivals, sites: Sequence[SiteArrival], truth_enu: np.ndarray) -> float:
    """Horizontal DRMS of the snapshot position bound from the heard sites' timing bounds."""
    if len(sites) < 3:
        return math.nan
    metres_per_sample = SPEED_OF_LIGHT_M_S / arrivals.sample_rate
    crlb = {cell.pci: cell.crlb_std for cell in arrivals.cells}
    sigmas = np.array([min(crlb.get(pci, math.nan) for pci in site.pcis) * metres_per_sample for site in sites])
    if not np.all(np.isfinite(sigmas) & (sigmas > 0)):
        return math.nan
    covariance = position_bound(np.array([s.position_enu for s in sites]), sigmas, truth_enu)
    trace = float(np.trace(covariance))
    # sites that do not place the receiver (co-located, in a line with it) leave an information
    # matrix whose inverse rounding can drive negative: no bound there
    return math.sqrt(trace) if math.isfinite(trace) and trace >= 0 else math.nan


def add_rssi_fixes(run: RouteRun, config: RssiConfig) -> dict:
    """The RSSI baseline's answer for every stack, and its path-loss model (or why there is none).

    The model (a power intercept per site, one exponent) is fitted on this same route's powers
    at the true positions: an oracle fit, as generous to the baseline as a site survey of the
    route itself would be."""
    try:
        model = fit_path_loss(run.observations())
    except ValueError as error:
        return {"fitted": False, "why": str(error)}  # no answer from the baseline: its fix rate says 0
    averager = RssiAverager(config)
    for epoch in run.epochs:
        epoch.rssi = solve_rssi(averager.add(epoch.sites), model, config, epoch.stamp_ns)
    return {"fitted": True, "exponent": model.exponent, "exponent_std": model.exponent_std,
            "shadowing_db": model.shadowing_db, "observations": model.n_observations}


# -- numbers ------------------------------------------------------------------------------------


def method_summary(answers: Sequence[Fix | NoFix | None], truths: Sequence[np.ndarray]) -> dict:
    """Fix rate, error percentiles, NEES and no-fix reasons of one method along a route."""
    paired = list(zip(answers, truths))  # an answer without its truth is not scored
    counts = answer_counts([answer for answer, _ in paired])
    fixes = [(a, t) for a, t in paired if isinstance(a, Fix)]
    errors = np.array([horizontal_error(a, t) for a, t in fixes])
    scores = np.array([nees(a, t) for a, t in fixes])

    def percentile(q: float) -> float | None:
        return float(np.percentile(errors, q)) if errors.size else None

    return {
        "epochs": counts["epochs"],
        "fixes": counts["fixes"],
        "fix_rate": counts["fix_rate"],
        "median_m": percentile(50),
        "p90_m": percentile(90),
        "p95_m": percentile(95),
        "rms_m": float(np.sqrt(np.mean(errors**2))) if errors.size else None,
        "nees_mean": float(np.mean(scores)) if scores.size else None,
        "nees_within_95": float(np.mean(scores <= CHI2_2DOF_95)) if scores.size else None,
        "median_gdop": float(np.nanmedian([a.gdop for a, _ in fixes])) if fixes and any(
            math.isfinite(a.gdop) for a, _ in fixes) else None,
        "no_fix_reasons": counts["no_fix_reasons"],
    }


def summarize_route(run: RouteRun) -> dict:
    """The route's table: per method, and what was heard."""
    truths = [epoch.truth_enu for epoch in run.epochs]
    bounds = np.array([epoch.bound_m for epoch in run.epochs])
    finite = bounds[np.isfinite(bounds)]
    return {
        "bag": run.bag,
        "interrupted": run.interrupted,
        "stacks": len(run.epochs),
        "seconds": (run.epochs[-1].stamp_ns - run.epochs[0].stamp_ns) * 1e-9 if run.epochs else 0.0,
        "sites_heard_per_stack": sites_per_stack(len(epoch.sites) for epoch in run.epochs),
        "sites_heard": sorted({site.site for epoch in run.epochs for site in epoch.sites}),
        "methods": {name: method_summary([pick(epoch) for epoch in run.epochs], truths)
                    for name, pick in METHODS.items()},
        "sites": _site_timing(run),
        "position_bound": {
            "stacks": int(finite.size),
            "median_m": float(np.median(finite)) if finite.size else None,
            "p90_m": float(np.percentile(finite, 90)) if finite.size else None,
        },
        "aiding": run.aiding,
        "anchors": len(run.anchors),
        "aiding_refused": sum(len(epoch.events) for epoch in run.epochs),
        "tracked_by_time_since_anchor": _by_time_since_anchor(run),
        "learned_site_biases_m": {site: {"bias_m": bias, "std_m": std} for site, (bias, std) in
                                  sorted(run.site_biases.items())},
        "odometry_frame": run.odometry_frame,
    }


SINCE_ANCHOR_BINS_S = (0.0, 10.0, 30.0, 60.0, 120.0, 300.0, math.inf)


def _by_time_since_anchor(run: RouteRun) -> list[dict]:
    """The tracked fixes' horizontal error by time since the latest GNSS fix (bins of
    :data:`SINCE_ANCHOR_BINS_S`): how long an anchor keeps helping."""
    if not run.anchors:
        return []
    rows = []
    pairs = [(run.since_anchor_s(e.stamp_ns), horizontal_error(e.tracked, e.truth_enu)) for e in run.epochs
             if isinstance(e.tracked, Fix)]
    for low, high in zip(SINCE_ANCHOR_BINS_S, SINCE_ANCHOR_BINS_S[1:]):
        errors = np.array([error for since, error in pairs if low <= since < high])
        if errors.size:
            rows.append({"from_s": low, "to_s": high if math.isfinite(high) else None, "fixes": int(errors.size),
                         "median_m": float(np.median(errors)), "p90_m": float(np.percentile(errors, 90))})
    return rows


def _site_timing(run: RouteRun) -> dict:
    """Per heard site: how often, and its arrivals against the truth (samples): the median error
    (a bias: NLOS, the channel's pull), the RMS, the share beyond 1 sample (false locks), and the
    median sigma the timing stage claimed."""
    errors: dict[str, list[tuple[float, float]]] = {}
    for epoch in run.epochs:
        for site, pair in epoch.timing_errors.items():
            errors.setdefault(site, []).append(pair)
    table = {}
    for site, pairs in sorted(errors.items()):
        error = np.array([e for e, _ in pairs if math.isfinite(e)])
        table[site] = {
            "stacks": len(pairs),
            "median_error_samples": float(np.median(error)) if error.size else None,
            "rms_error_samples": float(np.sqrt(np.mean(error**2))) if error.size else None,
            "beyond_1_sample": float(np.mean(np.abs(error) > 1)) if error.size else None,
            "median_claimed_std_samples": float(np.median([s for _, s in pairs])),
        }
    return table


def write_route_report(run: RouteRun, summary: dict, anchors: Anchors, out_dir: Path,
                       buildings: Sequence[np.ndarray] = ()) -> list[Path]:
    """``route.json`` (the summary and every stack) and the three figures, in ``out_dir``; the
    route map over ``buildings`` (outlines in the map frame) where given."""
    from deepsync.eval import route_figures  # matplotlib: only where figures are drawn

    out_dir.mkdir(parents=True, exist_ok=True)
    report = out_dir / "route.json"
    document = {"summary": summary,
                "anchors": [{"stamp_ns": stamp, "enu": [float(v) for v in enu]} for stamp, enu in run.anchors],
                "stacks": [_epoch_record(e, run) for e in run.epochs]}
    report.write_text(json.dumps(_strict_json(document), indent=1))
    paths = [report, out_dir / "route_cdf.png", out_dir / "route_map.png", out_dir / "route_timeline.png"]
    if run.epochs:
        route_figures.plot_cdf(run, paths[1])
        route_figures.plot_map(run, anchors, paths[2], buildings)
        route_figures.plot_timeline(run, paths[3])
    return paths if run.epochs else paths[:1]


def _strict_json(value: object) -> object:
    """NaN and infinities become null: JSON has no such numbers."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: _strict_json(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict_json(item) for item in value]
    return value


def _answer_record(answer: Fix | NoFix | None, truth_enu: np.ndarray) -> dict | None:
    if answer is None:
        return None
    if isinstance(answer, NoFix):
        return {"fix": False, "reason": answer.reason.value, "message": answer.message, "rejected": list(answer.rejected)}
    return {"fix": True, "enu": list(answer.position_enu), "error_m": horizontal_error(answer, truth_enu),
            "std_m": answer.horizontal_std_m, "nees": nees(answer, truth_enu), "gdop": answer.gdop,
            "sites": list(answer.sites), "rejected": list(answer.rejected)}


def _epoch_record(epoch: RouteEpoch, run: RouteRun) -> dict:
    return {
        "stamp_ns": epoch.stamp_ns,
        "truth_enu": [float(v) for v in epoch.truth_enu],
        "cells": epoch.cells,
        "sites": [site.site for site in epoch.sites],
        "timing_errors_samples": {site: error for site, (error, _) in epoch.timing_errors.items()},
        "bound_m": epoch.bound_m,
        "since_anchor_s": run.since_anchor_s(epoch.stamp_ns),
        "aiding_refused": list(epoch.events),
        **{name: _answer_record(pick(epoch), epoch.truth_enu) for name, pick in METHODS.items()},
    }


def evaluate_route(source: BagSource, towers: TowerDatabase, out_dir: Path, config: PipelineConfig | None = None,
                   progress: bool = True, initial_pose: InitialPose | None = None,
                   aiding: AidingPlan | None = None, bias_map: BiasMap | None = None) -> tuple[dict, list[Path]]:
    """Replay, score and report a route (its fusion corrected by ``bias_map``): the summary and
    the files written. What ``initial_pose`` and ``aiding`` draw is the bag's own (by its name:
    ``AidingPlan.for_recording``), so two bags evaluated alike do not err alike."""
    name = Path(source.path).resolve().name
    initial_pose = None if initial_pose is None else initial_pose.for_recording(name)
    aiding = None if aiding is None else aiding.for_recording(name)
    run = replay_route(source, towers, config, progress, initial_pose, aiding, bias_map)
    if not run.epochs:
        raise ValueError(f"no stack of {source.description} was completed: nothing to evaluate")
    fusion = (config or PipelineConfig()).fusion
    model = add_rssi_fixes(run, RssiConfig(receiver_height_m=fusion.snapshot.receiver_height_m))
    pulls = describe_pulls(site_pulls(run, source.frontend.adc_rate_hz))
    pulls["assumed"] = {"multipath_std_m": fusion.multipath_std_m,
                        "bias_decorrelation_m": fusion.tracker.bias_decorrelation_m}
    summary = {**summarize_route(run), "rssi_model": model, "pulls": pulls}
    return summary, write_route_report(run, summary, Anchors(towers), out_dir, recorded_buildings(source))


def recorded_buildings(source: BagSource) -> list[np.ndarray]:
    """The building outlines (map frame, (N, 2) each) of the ray-traced scene a simulated bag
    was recorded in, for its route map; none for a statistical or real recording, or where the
    scenario file or the ray-tracing extra is not there to read them from."""
    from deepsync.twin.raytrace.backend import missing  # noqa: PLC0415

    try:
        scenario = load_scenario(source.scenario_path())
    except (ValueError, OSError):
        return []
    if not isinstance(scenario.channel, RayTracingSettings) or missing() is not None:
        return []
    from deepsync.twin.raytrace.build import scenario_footprints  # noqa: PLC0415 (Sionna's scene files)

    return scenario_footprints(scenario.channel, twin_cells(scenario).frame)
