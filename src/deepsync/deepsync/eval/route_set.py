"""A set of recorded routes scored in one go: ``evaluate_route`` on every bag, one job each, on
local processes or a Ray cluster (``deepsync.jobs``), and a table of them all.

Each bag's report (``route.json`` and its figures) goes to ``<out>/<bag name>/``, written to a
temporary directory and renamed into place, so a lost or interrupted job leaves no partial
report and a rerun scores only the bags without one. ``<out>/route_set.json`` then lists every
report's headline numbers.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from deepsync.eval.aiding import AidingPlan
from deepsync.eval.route import evaluate_route
from deepsync.fusion.bias_map import load_bias_map
from deepsync.jobs import JobRunner
from deepsync.pipeline import PipelineConfig
from deepsync.sources import BagSource
from deepsync.towers import load_tower_database

REPORT = "route.json"
TABLE = "route_set.json"


def report_dir(out_dir: str | Path, bag: str | Path) -> Path:
    """Where the report of ``bag`` goes: ``<out>/<bag name>``."""
    return Path(out_dir) / Path(bag).resolve().name


def evaluate_route_set(bags: list[str | Path], towers: str | Path, out_dir: str | Path, runner: JobRunner,
                       config: PipelineConfig | None = None, aiding: AidingPlan | None = None,
                       bias_map: str | Path | None = None) -> Iterator[tuple[str, dict]]:
    """(bag, summary) of every bag as its report is finished, the tracker given what ``aiding``
    draws from each bag's truth and fusion corrected by the bias map file ``bias_map``; bags
    with a report are skipped."""
    database = load_tower_database(towers)  # a bad database or map fails here, before any job starts
    if bias_map is not None:
        load_bias_map(bias_map).check_database(database)
    names = [report_dir(out_dir, bag).name for bag in bags]
    if len(set(names)) < len(names):
        raise ValueError("two bags of the set have the same name: their reports would collide")
    jobs = [(str(bag), str(towers), str(out_dir), config, aiding, None if bias_map is None else str(bias_map))
            for bag in bags if not (report_dir(out_dir, bag) / REPORT).exists()]
    return runner.map(_evaluate_one, jobs)


def _evaluate_one(bag: str, towers: str, out_dir: str, config: PipelineConfig | None,
                  aiding: AidingPlan | None, bias_map: str | None) -> tuple[str, dict]:
    final = report_dir(out_dir, bag)
    final.parent.mkdir(parents=True, exist_ok=True)
    partial = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{final.name}."))
    try:
        summary, _ = evaluate_route(BagSource(bag), load_tower_database(towers), partial, config, progress=False,
                                    aiding=aiding, bias_map=None if bias_map is None else load_bias_map(bias_map))
        if final.exists():
            shutil.rmtree(final)
        os.replace(partial, final)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return bag, summary


def write_table(out_dir: str | Path, bags: list[str | Path]) -> Path:
    """``route_set.json``: the summary of every bag's report, under the bag's path."""
    table = {str(bag): json.loads((report_dir(out_dir, bag) / REPORT).read_text())["summary"]
             for bag in bags if (report_dir(out_dir, bag) / REPORT).exists()}
    path = Path(out_dir) / TABLE
    with tempfile.NamedTemporaryFile("w", dir=out_dir, suffix=".tmp", delete=False) as handle:
        json.dump(table, handle, indent=1)
    os.replace(handle.name, path)
    return path
