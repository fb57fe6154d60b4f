"""The demo: the bundled walk (or a fresh recording of its scenario) replayed through sync,
timing and fusion as the nodes would, into a bag of what they publish, scored against the
walk's truth (``deepsync demo`` prints it).

The tower database and the scenario ship inside the package (``deepsync/data``, read through
``importlib.resources``); the 15 MB recording does not: it is looked for in the source checkout
the package runs from and under the working directory, and a missing one is an error that says
how to get one.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from importlib.resources import as_file, files
from pathlib import Path

import numpy as np

from deepsync.eval.route import (method_summary, read_truth_track, score_stacks, summarize_route,
                                 write_route_report)
from deepsync.eval.route_scores import METHODS, horizontal_error
from deepsync.fusion.anchors import Anchors
from deepsync.pipeline import Pipeline
from deepsync.recording import RecordingSummary, record_scenario
from deepsync.replay import ReplaySummary, replay_bag
from deepsync.sources import BagSource
from deepsync.towers import load_tower_database
from deepsync.types import Fix, NoFix

TOWERS = "data/towers/campus.yaml"  # inside the package
SCENARIO = "data/scenarios/campus_route.yaml"  # inside the package: what bags/campus_route was made from
BAG = Path("bags") / "campus_route"  # in a checkout, beside src/
SHOWN_METHODS = ("tracked", "snapshot")  # besides the published answer


@contextlib.contextmanager
def packaged(name: str) -> Iterator[Path]:
    """A file shipped inside the package (``TOWERS``, ``SCENARIO``) as a path on disk for the
    ``with`` block (a temporary copy where the package is not a folder of files)."""
    with as_file(files("deepsync").joinpath(name)) as path:
        yield path


def _checkout() -> Path | None:
    """The source checkout this package runs from (an editable install, PYTHONPATH), told by the
    core package's setup.py beside it; None for an installed package."""
    project = Path(__file__).resolve().parents[2]  # src/deepsync in a checkout
    return project.parents[1] if (project / "setup.py").is_file() and (project / "package.xml").is_file() else None


def bag_places() -> list[Path]:
    """Where the demo looks for its recording, in order."""
    checkout = _checkout()
    places = [] if checkout is None else [checkout / BAG]
    here = Path.cwd() / BAG
    return places + ([here] if here not in places else [])


def find_bag(bag: str | Path | None = None) -> Path:
    """The recording to replay: ``bag`` if given, else the bundled walk where ``bag_places``
    finds it. Raises ValueError saying where it looked and how to get one."""
    if bag is not None:
        return Path(bag)
    for place in bag_places():
        if place.is_dir():
            return place
    raise ValueError(f"the demo's recording {BAG} is not here (looked in {', '.join(map(str, bag_places()))}): it "
                     "comes with the source checkout, not with an installed package. Run the demo from the "
                     "checkout's root, give a recording of the walk with --bag BAG, or make a fresh one with "
                     "--simulate SECONDS (e.g. deepsync demo --simulate 6)")


def simulate(seconds: float, out: Path, workers: int, progress: bool) -> RecordingSummary:
    """A fresh recording of the demo's scenario into the bag ``out`` (replaced)."""
    with packaged(SCENARIO) as scenario:
        return record_scenario(scenario, seconds, out, workers=workers, overwrite=True, progress=progress)


@dataclass(frozen=True)
class DemoEpoch:
    """One stack of the demo: what it heard and what the methods of ``SHOWN_METHODS`` answered."""

    seconds: float  # since the first stack
    cells: int
    sites: tuple[str, ...]
    answers: dict[str, float | NoFix | None]  # method -> horizontal error (m), its no-fix, or None (no answer)


@dataclass(frozen=True)
class DemoResult:
    replayed: ReplaySummary  # the bag of what the nodes publish, the speed, the health events
    report: list[Path]  # route.json and the figures
    walked_m: float  # along the true track
    pcis: list[int]  # every cell timed
    sites_heard: list[str]
    sites_per_stack: dict[str, int]  # sites heard: stacks
    methods: dict[str, dict]  # published, then SHOWN_METHODS: ``method_summary``s
    bound: dict  # the position Cramer-Rao bound: stacks, median_m, p90_m
    epochs: list[DemoEpoch]


def run_demo(bag: Path, out: Path, progress: bool = True, say: Callable[[str], None] | None = None) -> DemoResult:
    """Replay ``bag`` (the walk, with its truth) with the bundled tower database into
    ``out``/replay, write the route report into ``out`` and score every stack. Raises ValueError
    when no stack was completed."""
    with packaged(TOWERS) as path:
        towers = load_tower_database(path)
    truth = read_truth_track(bag)
    true_arrivals = BagSource(bag).truth_arrivals()
    fused = []

    def keep(timed, pipeline: Pipeline) -> None:
        fused.append((timed.arrivals, timed.fusion, pipeline.fusion.reference_ns))

    replayed = replay_bag(bag, out / "replay", towers, overwrite=True, progress=progress, say=say, on_stack=keep)
    if not fused:
        raise ValueError(f"no stack of {bag} was completed: nothing to show")
    run = score_stacks(str(bag), fused, truth, true_arrivals, interrupted=replayed.damage is not None)
    summary = summarize_route(run)
    report = write_route_report(run, summary, Anchors(towers), out)
    truths = [epoch.truth_enu for epoch in run.epochs]
    published = method_summary([fusion.published for _, fusion, _ in fused], truths)
    start_ns = run.epochs[0].stamp_ns
    epochs = [DemoEpoch((epoch.stamp_ns - start_ns) * 1e-9, epoch.cells, tuple(site.site for site in epoch.sites),
                        {name: _scored(METHODS[name](epoch), epoch.truth_enu) for name in SHOWN_METHODS})
              for epoch in run.epochs]
    return DemoResult(
        replayed=replayed,
        report=report,
        walked_m=float(np.sum(np.linalg.norm(np.diff(truth.positions[:, :2], axis=0), axis=1))),
        pcis=sorted({cell.pci for arrivals, _, _ in fused for cell in arrivals.cells}),
        sites_heard=summary["sites_heard"],
        sites_per_stack=summary["sites_heard_per_stack"],
        methods={"published": published} | {name: summary["methods"][name] for name in SHOWN_METHODS},
        bound=summary["position_bound"],
        epochs=epochs,
    )


def _scored(answer: Fix | NoFix | None, truth_enu: np.ndarray) -> float | NoFix | None:
    return horizontal_error(answer, truth_enu) if isinstance(answer, Fix) else answer
