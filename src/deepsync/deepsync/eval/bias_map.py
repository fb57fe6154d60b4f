"""A site bias map from a recording at known positions: ``deepsync survey-map``.

The route is replayed through the chain with the tower database the map will be used with
(snapshot only: a map is made of the sites' ranges, not of the tracker's fixes), each stack's
sites are paired with where the receiver truly was when their codes arrived, and
``fusion.bias_map.survey_bias_map`` maps every heard site's range bias over the ``map`` frame
at the database's origin. The database's site clocks are the rest of each site's bias, so the
map holds only with that database.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from deepsync.eval.route import RouteRun, replay_route
from deepsync.fusion.bias_map import BiasMap, SurveyConfig, survey_bias_map
from deepsync.pipeline import PipelineConfig
from deepsync.sources import BagSource
from deepsync.towers import TowerDatabase


@dataclass(frozen=True)
class MappedSite:
    """What a map knows of one site: how many grid nodes, and its bias range there (m; NaN
    where no node is known)."""

    site: str
    known_nodes: int
    low_m: float
    high_m: float


@dataclass(frozen=True)
class RouteSurvey:
    bias_map: BiasMap
    run: RouteRun
    sites: tuple[MappedSite, ...]
    stacks_used: int  # stacks that heard two sites or more: the only ones that say anything of a bias


def mapped_sites(bias_map: BiasMap) -> tuple[MappedSite, ...]:
    """Every site of ``bias_map`` with its known nodes and bias range, by name."""
    rows = []
    for name, grid in sorted(bias_map.sites.items()):
        known = grid.mean_m[np.isfinite(grid.mean_m)]
        low, high = (float(known.min()), float(known.max())) if known.size else (np.nan, np.nan)
        rows.append(MappedSite(name, int(known.size), low, high))
    return tuple(rows)


def survey_route(source: BagSource, towers: TowerDatabase, config: PipelineConfig | None = None,
                 survey: SurveyConfig | None = None, progress: bool = True) -> RouteSurvey:
    """The bias map of every site heard along a recorded route with ground truth (ValueError
    naming the bag if it has none). KeyboardInterrupt if the replay was interrupted: a map of
    part of a survey is not returned."""
    config = config or PipelineConfig()
    snapshot_only = dataclasses.replace(config, fusion=dataclasses.replace(config.fusion, track=False))
    run = replay_route(source, towers, snapshot_only, progress)
    if run.interrupted:
        raise KeyboardInterrupt
    stacks = run.observations_by_stack()
    origin = towers.origin  # replay_route refused a database without one
    try:
        bias_map = survey_bias_map(stacks, (origin.latitude_deg, origin.longitude_deg, origin.height_m), survey,
                                   made_by=f"survey of {source.path} with tower database {towers.name!r}")
    except ValueError as error:
        raise ValueError(f"{source.path}: {error}") from None
    used = sum(len({o.arrival.site for o in stack}) >= 2 for stack in stacks)
    return RouteSurvey(bias_map, run, mapped_sites(bias_map), used)
