"""Site clocks from a recording at known positions: ``deepsync calibrate``.

The route is replayed through the chain with the tower database as it stands (snapshot only:
the tracker is not needed), every heard site's range is paired with the true receiver position
at its arrival, and ``fusion.calibration`` fits each site's frame timing offset and drift. The
calibrated database holds them at the replay's time origin.

``oracle_database`` is the other end of the comparison: the database with the simulated
sites' true timing (from the bag's provenance), what no calibration can beat.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass

from deepsync.eval.route import RouteRun, replay_route
from deepsync.fusion.calibration import CalibrationObservation, CalibrationResult, calibrate_sites, calibrated_database
from deepsync.pipeline import PipelineConfig
from deepsync.sources import BagSource
from deepsync.towers import TowerDatabase, parse_tower_database, tower_database_to_dict


MIN_ARRIVALS = 5  # a site heard fewer times is left out: a stray detection, or too little to fit a drift


@dataclass(frozen=True)
class RouteCalibration:
    result: CalibrationResult
    database: TowerDatabase  # the input database with the calibrated sites' timing
    run: RouteRun
    skipped: tuple[str, ...] = ()  # sites heard fewer than MIN_ARRIVALS times: not calibrated


def calibratable(observations: list[CalibrationObservation]) -> tuple[list[CalibrationObservation], tuple[str, ...]]:
    """The observations of sites heard at least :data:`MIN_ARRIVALS` times, and the others' names."""
    counts = Counter(o.arrival.site for o in observations)
    skipped = tuple(sorted(site for site, n in counts.items() if n < MIN_ARRIVALS))
    return [o for o in observations if o.arrival.site not in skipped], skipped


def calibrate_route(source: BagSource, towers: TowerDatabase, config: PipelineConfig | None = None,
                    progress: bool = True) -> RouteCalibration:
    """Calibrate the clocks of every site heard along a recorded route with ground truth.
    KeyboardInterrupt if the replay was interrupted (nothing half-calibrated is returned)."""
    config = config or PipelineConfig()
    snapshot_only = dataclasses.replace(config, fusion=dataclasses.replace(config.fusion, track=False))
    run = replay_route(source, towers, snapshot_only, progress)
    if run.interrupted:
        raise KeyboardInterrupt
    observations, skipped = calibratable(run.observations())
    if not observations:
        raise ValueError(f"no site of tower database {towers.name!r} was heard {MIN_ARRIVALS} times in "
                         f"{source.description}: nothing to calibrate")
    result = calibrate_sites(observations)
    return RouteCalibration(result, calibrated_database(towers, result.sites, run.reference_ns), run, skipped)


def oracle_database(towers: TowerDatabase, source: BagSource) -> TowerDatabase:
    """``towers`` with every simulated site's true timing offset and drift (sigma 0), held at the
    recording's first sample; sites the simulation did not have keep theirs."""
    truth = {site.name: site for site in source.truth_sites()}
    epoch_ns = next(iter(source.chunks())).stamp_ns
    sites = []
    for site in towers.sites:
        true = truth.get(site.name)
        if true is not None:
            site = dataclasses.replace(site, timing_offset_us=true.timing_offset_us, timing_offset_std_us=0.0,
                                       timing_drift_ns_per_s=true.timing_drift_ns_per_s, timing_drift_std_ns_per_s=0.0)
        sites.append(site)
    database = dataclasses.replace(towers, name=f"{towers.name} (true clocks)", sites=tuple(sites), timing_epoch_ns=epoch_ns)
    return parse_tower_database(tower_database_to_dict(database), database.name)
