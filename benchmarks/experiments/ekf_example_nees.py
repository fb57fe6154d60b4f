"""Is the robot_localization example honest? The NEES of a filter fed what it feeds its map EKF.

robot_localization's map filter (src/deepsync_ros/config/robot_localization_dual_ekf.yaml) fuses
wheel odometry and DeepSync's poses. Whether its covariance can be believed depends on what
DeepSync's poses are: the tracker's poses carry all the stacks before them and sliding stacks
share frames, so taking each as an independent measurement makes the filter overconfident.
This script replays a bag with ground truth through the chain exactly as the nodes would be
configured (the node parameters of deepsync_ros.params), feeds a 2-D filter built like
robot_localization's EKF (x, y, vx, vy; process noise per second from the example YAML, added
times dt; the pose gate pose0_rejection_threshold on the squared Mahalanobis distance;
odometry velocities drawn from the truth with --odometry-std of noise, at --odometry-rate), and
prints for each way of feeding it the mean NEES of the filter's horizontal position at every
pose (2 for an honest 2-D covariance; above 2 overconfident), its RMS error and the RMS 1-sigma
(DRMS) it claims.

Run:  .venv/bin/python benchmarks/experiments/ekf_example_nees.py [--bag bags/campus_route]
          [--towers config/towers/campus.yaml] [--odometry-std 0.05] [--odometry-rate 20]
A longer walk gives a firmer answer (bags/generated: scripts/route_bags.sh, with its towers).
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"  # before numpy loads: its BLAS reads these once

import argparse  # noqa: E402
import ast  # noqa: E402
import math  # noqa: E402
from dataclasses import dataclass, replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import yaml  # noqa: E402

from deepsync.eval.route import fuse_route, read_truth_track, replay  # noqa: E402
from deepsync.sources import BagSource  # noqa: E402
from deepsync.towers import load_tower_database  # noqa: E402
from deepsync.types import Fix  # noqa: E402
from deepsync_ros import params  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "src" / "deepsync_ros" / "config" / "robot_localization_dual_ekf.yaml"
MAP_FILTER = "/**/ekf_filter_node_map"
# robot_localization's state order: x, y at 0, 1; vx, vy at 6, 7
STATE = (0, 1, 6, 7)


@dataclass(frozen=True)
class Feed:
    """One way of feeding the map filter: the node parameters of the chain, which answer, at
    most one pose per ``every_s`` of stream time, its covariance times ``inflate``."""

    name: str
    node_parameters: tuple[tuple[str, object], ...]  # deepsync_ros.params names and values
    tracked: bool  # the tracker's pose (tracking: true), else the stack's snapshot fix
    every_s: float = 0.0
    inflate: float = 1.0


DEFAULTS = ()
SNAPSHOTS = (("tracking", False),)
BACK_TO_BACK = (("tracking", False), ("hop_frames", 100))
EXAMPLE_OVERLAY = REPO / "src" / "deepsync_ros" / "config" / "deepsync_ekf_poses.yaml"
EXAMPLE_LAUNCH = REPO / "src" / "deepsync_ros" / "launch" / "dual_ekf.launch.py"


def launch_constant(name: str) -> object:
    """A module-level constant of the example launch file, read without launch installed."""
    tree = ast.parse(EXAMPLE_LAUNCH.read_text())
    (value,) = [node.value for node in tree.body if isinstance(node, ast.Assign)
                and any(getattr(target, "id", None) == name for target in node.targets)]
    return ast.literal_eval(value)


def overlay_parameters(path: Path) -> tuple[tuple[str, object], ...]:
    """What the example's overlay (dual_ekf.launch.py's extra_params_file) sets, as one set of
    node parameters (cell_sync's and tdoa_fusion's names do not clash)."""
    document = yaml.safe_load(path.read_text())
    merged = {name: value for entry in document.values() for name, value in entry["ros__parameters"].items()}
    return tuple(sorted(merged.items()))


FEEDS = (
    Feed("every tracked pose (the nodes' defaults)", DEFAULTS, True),
    Feed("a tracked pose every 30 s", DEFAULTS, True, every_s=30.0),
    Feed("every snapshot fix (tracking: false)", SNAPSHOTS, False),
    Feed("snapshot fixes of back-to-back stacks (tracking: false, hop_frames: 100)", BACK_TO_BACK, False),
    Feed("the same, covariance x 4", BACK_TO_BACK, False, inflate=4.0),
    Feed(f"the example: {EXAMPLE_OVERLAY.name}, throttled to {launch_constant('EKF_POSES_PER_S'):g} per s",
         overlay_parameters(EXAMPLE_OVERLAY), False, every_s=1.0 / launch_constant("EKF_POSES_PER_S")),
)


def map_filter_settings(path: Path) -> dict:
    document = yaml.safe_load(path.read_text())
    return document[MAP_FILTER]["ros__parameters"]


class PlaneEkf:
    """x, y, vx, vy as robot_localization's EKF runs them in two_d_mode with yaw known: constant
    velocity, process noise ``q`` per second added times dt, Joseph-form updates."""

    def __init__(self, q: np.ndarray, p0: np.ndarray, gate_sigmas: float) -> None:
        self.q = np.diag(q)
        self.p = np.diag(p0)
        self.x: np.ndarray | None = None
        self.t_ns: int | None = None
        self.gate = gate_sigmas ** 2
        self.rejected = 0

    def predict(self, t_ns: int) -> None:
        dt = (t_ns - self.t_ns) * 1e-9
        if dt <= 0:
            return
        f = np.eye(4)
        f[0, 2] = f[1, 3] = dt
        self.x = f @ self.x
        self.p = f @ self.p @ f.T + self.q * dt
        self.t_ns = t_ns

    def update(self, t_ns: int, h: np.ndarray, z: np.ndarray, r: np.ndarray, gated: bool) -> None:
        if self.x is None:  # robot_localization starts from its first measurement's values
            self.x = np.zeros(4)
            self.x[np.argmax(h, axis=1)] = z
            self.t_ns = t_ns
        self.predict(t_ns)
        innovation = z - h @ self.x
        s = h @ self.p @ h.T + r
        if gated and innovation @ np.linalg.solve(s, innovation) >= self.gate:
            self.rejected += 1
            return
        k = self.p @ h.T @ np.linalg.inv(s)
        self.x = self.x + k @ innovation
        joseph = np.eye(4) - k @ h
        self.p = joseph @ self.p @ joseph.T + k @ r @ k.T


POSITION = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
VELOCITY = np.array([[0, 0, 1.0, 0], [0, 0, 0, 1.0]])


def fused_route(node_parameters: tuple, bag: str, towers_path: str, cache: dict):
    """The route fused as the nodes would with these parameters (one replay per parameter set)."""
    if node_parameters not in cache:
        values = {spec.name: spec.default for spec in params.DEEPSYNC_PIPELINE}
        values.update(towers=towers_path, source=bag, **dict(node_parameters))
        config = params.pipeline_config(values)
        towers = load_tower_database(towers_path)
        cache[node_parameters] = fuse_route(replay(BagSource(bag), towers, config, progress=False), towers,
                                            config.fusion)
    return cache[node_parameters]


def fed_poses(run, feed: Feed) -> list[tuple[int, Fix]]:
    poses, last_ns = [], None
    for epoch in run.epochs:
        answer = epoch.tracked if feed.tracked else epoch.snapshot
        if not isinstance(answer, Fix) or (last_ns is not None and (epoch.stamp_ns - last_ns) * 1e-9 < feed.every_s):
            continue
        poses.append((epoch.stamp_ns, replace(answer, covariance=answer.covariance * feed.inflate)))
        last_ns = epoch.stamp_ns
    return poses


def true_velocity(truth, stamp_ns: int, half_ns: int = 50_000_000) -> np.ndarray:
    """Horizontal velocity of the true track at ``stamp_ns`` (central difference, inside the track)."""
    before = max(stamp_ns - half_ns, int(truth.stamps_ns[0]))
    after = min(stamp_ns + half_ns, int(truth.stamps_ns[-1]))
    return (truth.at(after)[:2] - truth.at(before)[:2]) / ((after - before) * 1e-9)


def run_feed(feed: Feed, bag: str, towers_path: str, settings: dict, odometry_std: float, odometry_rate: float,
             seed: int, cache: dict) -> dict:
    poses = fed_poses(fused_route(feed.node_parameters, bag, towers_path, cache), feed)
    truth = read_truth_track(bag)
    q = np.asarray(settings["process_noise_covariance"], dtype=float)[list(STATE)]
    p0 = np.asarray(settings["initial_estimate_covariance"], dtype=float)[list(STATE)]
    ekf = PlaneEkf(q, p0, float(settings["pose0_rejection_threshold"]))
    rng = np.random.default_rng(seed)
    events = [(stamp, "pose", fix) for stamp, fix in poses]
    if odometry_std > 0 and poses:
        step_ns = int(1e9 / odometry_rate)
        for stamp in range(poses[0][0], poses[-1][0] + 1, step_ns):
            events.append((stamp, "odometry", None))
    events.sort(key=lambda event: (event[0], event[1] == "pose"))
    nees, errors, claimed = [], [], []
    for stamp, kind, fix in events:
        if kind == "odometry":
            if ekf.x is None:
                continue  # the position starts the filter
            measured = true_velocity(truth, stamp) + rng.normal(0.0, odometry_std, 2)
            ekf.update(stamp, VELOCITY, measured, np.eye(2) * odometry_std ** 2, gated=False)
            continue
        ekf.update(stamp, POSITION, np.asarray(fix.position_enu[:2], dtype=float), fix.covariance[:2, :2], gated=True)
        error = ekf.x[:2] - truth.at(stamp)[:2]
        covariance = ekf.p[:2, :2]
        nees.append(float(error @ np.linalg.solve(covariance, error)))
        errors.append(float(error @ error))
        claimed.append(float(np.trace(covariance)))
    given = [fix for _, fix in poses]
    return {
        "feed": feed.name,
        "poses": len(poses),
        "rejected": ekf.rejected,
        "nees": float(np.mean(nees)) if nees else math.nan,
        "rms_error_m": math.sqrt(np.mean(errors)) if errors else math.nan,
        "claimed_drms_m": math.sqrt(np.mean(claimed)) if claimed else math.nan,
        "input_drms_m": math.sqrt(np.mean([np.trace(f.covariance[:2, :2]) for f in given])) if given else math.nan,
        "input_rms_error_m": math.sqrt(np.mean([np.sum((np.asarray(f.position_enu[:2]) - truth.at(s)[:2]) ** 2)
                                                for s, f in poses])) if poses else math.nan,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bag", default=str(REPO / "bags" / "campus_route"))
    parser.add_argument("--towers", default=str(REPO / "config" / "towers" / "campus.yaml"))
    parser.add_argument("--example", default=str(EXAMPLE), help="the dual-EKF YAML whose map filter is mimicked")
    parser.add_argument("--odometry-std", type=float, default=0.05, help="odometry velocity noise [m/s], 0: none")
    parser.add_argument("--odometry-rate", type=float, default=20.0, help="odometry messages per second")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    settings = map_filter_settings(Path(args.example))
    print(f"{args.bag}: map filter of {Path(args.example).name}, odometry {args.odometry_std:g} m/s at "
          f"{args.odometry_rate:g} Hz; NEES 2 = honest (2-D)")
    cache: dict = {}
    for feed in FEEDS:
        result = run_feed(feed, args.bag, args.towers, settings, args.odometry_std, args.odometry_rate, args.seed,
                          cache)
        print(f"  {result['feed']}: {result['poses']} poses ({result['rejected']} gated out), input RMS error "
              f"{result['input_rms_error_m']:.1f} m vs claimed {result['input_drms_m']:.1f} m; filter NEES "
              f"{result['nees']:.2f}, RMS error {result['rms_error_m']:.1f} m, claimed DRMS "
              f"{result['claimed_drms_m']:.1f} m")


if __name__ == "__main__":
    main()
