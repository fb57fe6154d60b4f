"""A site bias map traced from a scene, without a survey: ``deepsync trace-map``.

A map must hold what the timing stage reads late at each place, which is seldom the first
traced path's excess delay: behind a building the envelope's peak often lands on the strongest
path, a street or two later (100-500 m on the Munich walk where the first path is 1-100 m
late). So at every node of a street grid along the scenario's receiver (``street_grid``: within
``margin_m`` of its route or position, outside buildings), each site is simulated alone, its
traced channel to that node through the same front end, cell search and timing stage as a
recording, for a few stacks; its reported arrivals against the straight line's give its bias
there (the median over its sectors and stacks). One site at a time: the lock its own channel
gives, each site heard even where the others would bury it; the others' noise moves single
stacks, not where they centre. The nodes' biases are kernel-averaged onto the map's grid
(``fusion.bias_map.bias_map_from_points``), known within a kernel sigma of a node that heard
the site.

The map holds each site's whole bias (no receiver clock to take out: the simulator knows the
truth), so it fits any tower database whose site clocks are right; a database's clock errors
are not in it, unlike a survey's map.

The nodes run as jobs (``deepsync.jobs``: local processes or a Ray cluster), a group of nodes
each, written atomically into ``<map>.parts/<digest>/`` (the digest of the scenario file and the
settings, so another run's parts are never mixed in): an interrupted run resumes where it
stopped; the folder goes once the map is written.
"""

from __future__ import annotations

import hashlib
import math
import shutil
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from deepsync.configio import ConfigError
from deepsync.eval.bias_map import MappedSite, mapped_sites
from deepsync.eval.cell_search import timing_error
from deepsync.frontend.channel import Emitter, FixedChannel, Paths
from deepsync.frontend.config import FrontendConfig
from deepsync.frontend.simulator import EnvelopeSimulator
from deepsync.fusion.bias_map import SurveyConfig, bias_map_from_points, save_bias_map
from deepsync.jobs import JobRunner
from deepsync.outputs import replacing
from deepsync.pipeline import Pipeline, PipelineConfig
from deepsync.recording import EPOCH_NS, truth_timing
from deepsync.schema import check_settings, setting
from deepsync.twin.scenario import RayTracingSettings, Scenario, load_scenario
from deepsync.twin.seeding import transmit_chain_phase
from deepsync.twin.world import TwinCells, receiver_trajectory, twin_cells
from deepsync.types import FRAME_SECONDS, SPEED_OF_LIGHT_M_S

if TYPE_CHECKING:  # the ray-tracing extra is imported where it is used
    from deepsync.twin.raytrace.scenes import RayScene

NODES_PER_JOB = 8  # a job takes 15-30 s for six sites on this machine: enough to amortise a worker's start


@dataclass(frozen=True)
class TracedMapConfig:
    """Where a traced map's nodes lie, how long each site is listened to there, and how the
    nodes become the map."""

    margin_m: float = setting(30.0, help="How far from the receiver's route (or position) the map reaches: its nodes "
                              "lie within this distance of the route's polyline.",
                              unit="m", bounds=(0.0, 5000.0))
    node_step_m: float = setting(10.0, help="Spacing of the nodes at which each site is simulated; also the "
                                 "map's grid.", unit="m", bounds=(1.0, 1000.0))
    stack_frames: int = setting(20, help="Frames per stack of the cell search at a node.", bounds=(2, 1000))
    hop_frames: int = setting(5, help="Frames from one stack to the next at a node.", bounds=(1, 1000))
    stacks: int = setting(4, help="Stacks per site and node; the cell search reports a cell from its "
                          "confirm_stacks-th stack on (3 by default).", bounds=(1, 100))
    smoothing_m: float = setting(10.0, help="1-sigma of the Gaussian kernel that spreads the nodes' biases "
                                 "onto the map.", unit="m", bounds=(0.0, 1e4), open_low=True)

    def __post_init__(self) -> None:
        check_settings(self)

    @property
    def frames(self) -> int:
        """Frames simulated per site and node: its stacks, and one for the stacker to start on."""
        return self.stack_frames + (self.stacks - 1) * self.hop_frames + 2

    def survey(self) -> SurveyConfig:
        # every node's bias is an expectation, not one noisy arrival: a node is known from one
        # neighbour's worth of kernel weight (a street one node wide has ~2.5)
        return SurveyConfig(step_m=self.node_step_m, smoothing_m=self.smoothing_m, min_weight=1.0)

    def pipeline(self) -> PipelineConfig:
        """The chain a node's stream runs through: a static receiver's, with these stacks."""
        return PipelineConfig.for_motion("static").with_choices(n_frames=self.stack_frames,
                                                                 hop_frames=self.hop_frames)


@dataclass(frozen=True)
class TracedMap:
    path: Path                    # the map written
    nodes: int                    # street nodes simulated
    heard: dict[str, int]         # site: nodes at which it was heard
    sites: tuple[MappedSite, ...]


def ray_traced(scenario: Scenario, where: str) -> RayTracingSettings:
    """The scenario's ray-tracing settings; ConfigError for a statistical one (its bias at a
    place is a random draw, not the place's: a survey of a recording maps that)."""
    if not isinstance(scenario.channel, RayTracingSettings):
        raise ConfigError(f"{where}: channel model is statistical: a traced map needs `channel: {{model: raytraced}}` "
                          "(a statistical channel's pull is a draw that knows no street; map a recording of it "
                          "with survey-map)")
    return scenario.channel


def map_nodes(scenario: Scenario, cells: TwinCells, scene: RayScene, config: TracedMapConfig) -> np.ndarray:
    """(N, 3) street nodes (map frame) of ``scene`` within ``config.margin_m`` of the receiver's
    route (a looping one's closing leg included), or of its position."""
    from deepsync.twin.raytrace.sites import street_grid  # noqa: PLC0415 (shapely)

    waypoints = receiver_trajectory(scenario.receiver, cells.frame).waypoints_enu
    return street_grid(scene, waypoints, config.margin_m, scenario.receiver.height_m, config.node_step_m)


def site_biases_at(scenario_path: str, nodes: np.ndarray, indices: tuple[int, ...], config: TracedMapConfig,
                   out: str) -> int:
    """A job: every site's bias (m) at nodes ``indices`` of ``nodes``, written to ``out``
    (``node``, ``site``, ``bias_m``: one row per site heard at a node). Returns the nodes done."""
    from deepsync.twin.raytrace.build import scenario_scene, trace_sites  # noqa: PLC0415
    from deepsync.twin.raytrace.channel import static_paths  # noqa: PLC0415

    scenario = load_scenario(scenario_path)
    cells = twin_cells(scenario)
    settings = ray_traced(scenario, str(scenario_path))
    traces = trace_sites(settings, scenario_scene(settings, cells.frame), cells.transmitters, nodes)  # the cache's
    pipeline = config.pipeline()
    frontend = scenario.frontend
    rows = []
    for node in indices:
        for site in cells.sites:
            mine = [k for k, tx in enumerate(cells.transmitters) if tx.site == site.name]
            paths = [static_paths(traces[tx.site, tx.carrier_hz], node, tx.antenna,
                                  transmit_chain_phase(scenario.seed, tx.site, tx.pci))
                     for tx in (cells.transmitters[k] for k in mine)]
            emitters = [cells.emitters[k] for k in mine]
            distance_s = float(np.linalg.norm(nodes[node] - site.position_enu)) / SPEED_OF_LIGHT_M_S
            bias = _lock_bias_m(emitters, paths, distance_s, frontend, pipeline, config.frames, scenario.seed)
            if math.isfinite(bias):
                rows.append((node, site.name, bias))
    with replacing(out) as temporary, temporary.open("wb") as f:
        np.savez(f, node=np.array([r[0] for r in rows], dtype=np.int64), site=np.array([r[1] for r in rows], dtype=str),
                 bias_m=np.array([r[2] for r in rows], dtype=np.float64))
    return len(indices)


def _lock_bias_m(emitters: Sequence[Emitter], paths: Sequence[Paths], distance_s: float, frontend: FrontendConfig,
                 pipeline: PipelineConfig, frames: int, seed: int) -> float:
    """Median over stacks and sectors of what the chain reports beyond the straight line (m);
    NaN where it reports none of the site's cells."""
    simulator = EnvelopeSimulator(emitters, FixedChannel(paths), frontend, seed, epoch_ns=EPOCH_NS)
    rate = frontend.adc_rate_hz
    n_samples = int(round(frames * FRAME_SECONDS * rate))
    truth: dict[int, list[float]] = {}
    for pci, toa, _ in truth_timing(emitters, lambda i, t: distance_s, simulator, n_samples):
        truth.setdefault(pci, []).append(toa)
    chain = Pipeline(frontend, pipeline)
    errors = [timing_error(cell.toa, np.asarray(truth[cell.pci]))
              for chunk in simulator.stream(frames * FRAME_SECONDS) for result in chain.process(chunk)
              for cell in result.arrivals.cells if cell.pci in truth]
    errors = [e for e in errors if math.isfinite(e)]
    return float(np.median(errors)) * SPEED_OF_LIGHT_M_S / rate if errors else math.nan


def traced_bias_map(scenario_path: str | Path, out: str | Path, config: TracedMapConfig | None = None,
                    runner: JobRunner | None = None, progress: bool = True) -> TracedMap:
    """Trace, simulate and map every site of a ray-traced scenario around its receiver (module
    docstring) and write the map to ``out``. ConfigError for a statistical scenario; ValueError
    where no site is heard at any node."""
    config = config or TracedMapConfig()
    runner = runner or JobRunner()
    scenario_path, out = Path(scenario_path), Path(out)
    from deepsync.twin.raytrace.build import scenario_scene, trace_sites  # noqa: PLC0415 (Sionna's scene files)

    scenario = load_scenario(scenario_path)
    settings = ray_traced(scenario, str(scenario_path))
    cells = twin_cells(scenario)
    scene = scenario_scene(settings, cells.frame)
    nodes = map_nodes(scenario, cells, scene, config)
    if not len(nodes):
        raise ValueError(f"{scenario_path}: no street node within {config.margin_m:g} m of the receiver: every one "
                         "lies inside a building")
    trace_sites(settings, scene, cells.transmitters, nodes)  # here, with its progress; the jobs load the cache
    digest = hashlib.sha256(scenario_path.read_bytes() + repr(sorted(asdict(config).items())).encode())
    parts = out.parent / f"{out.name}.parts" / digest.hexdigest()[:16]
    parts.mkdir(parents=True, exist_ok=True)
    groups = [tuple(range(k, min(k + NODES_PER_JOB, len(nodes)))) for k in range(0, len(nodes), NODES_PER_JOB)]
    files = [parts / f"nodes_{group[0]:05d}.npz" for group in groups]
    jobs = [(str(scenario_path), nodes, group, config, str(file)) for group, file in zip(groups, files)
            if not file.is_file()]
    with tqdm(total=len(nodes), initial=len(nodes) - sum(len(job[2]) for job in jobs), unit="node",
              desc="site biases", disable=not progress) as bar:
        for done in runner.map(site_biases_at, jobs):
            bar.update(done)
    node, site, bias = [], [], []
    for file in files:
        with np.load(file, allow_pickle=False) as data:
            node.append(data["node"])
            site.append(data["site"])
            bias.append(data["bias_m"])
    node, site, bias = np.concatenate(node), np.concatenate(site), np.concatenate(bias)
    heard = {s.name: int(np.count_nonzero(site == s.name)) for s in cells.sites}
    if not len(bias):
        raise ValueError(f"{scenario_path}: no site was heard at any of the {len(nodes)} nodes")
    origin = scenario.origin
    bias_map = bias_map_from_points(
        {name: (nodes[node[site == name]], bias[site == name]) for name in heard if heard[name]},
        (origin.latitude_deg, origin.longitude_deg, origin.height_m), config.survey(),
        made_by=f"traced from {scenario_path.name} ({len(nodes)} street nodes every {config.node_step_m:g} m)")
    save_bias_map(bias_map, out)
    shutil.rmtree(out.parent / f"{out.name}.parts", ignore_errors=True)
    return TracedMap(out, len(nodes), heard, mapped_sites(bias_map))
