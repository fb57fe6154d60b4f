"""Site bias maps from a survey: what a map made on one run of a route does for another.

Pairs of route-set bags on the same sites, route and channel (``route_set.py`` makes them): the
statistical city walk's evening run (loads 0.1-0.2) surveys for its daytime run (0.35-0.6) of
the same seed, whose channel is the same draw; the ray-traced Munich walk's seed-2 run surveys
for seed 1 and seed 3 for seed 2 (a seed moves the site clocks and the noise, not the
buildings). The survey is the run's own arrivals at the simulator's true positions
(``survey_bias_map``; a receiver with GNSS would do the same), fused against the tower database
with the recording's true clocks. Per pair, with no anchor and with a GNSS fix a minute: the
published pose without a map, with the map, and with a wrong map (the survey's database had
its first site 50 m north of where it is). Writes docs/results/bias_maps.json.

    python benchmarks/fusion/bias_maps.py [--pairs city_walk_s1 munich_walk_s1 ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the route set's bags, configurations and summaries
import route_set as rs  # noqa: E402

from deepsync.eval.route import fuse_route  # noqa: E402
from deepsync.fusion.anchors import Anchors  # noqa: E402
from deepsync.fusion.bias_map import BiasMap, survey_bias_map  # noqa: E402
from deepsync.towers import TowerDatabase  # noqa: E402

PAIRS = {  # name: (route, survey bag, bag it is used on)
    **{f"city_walk_s{k}": ("city_walk", f"city_walk_evening_s{k}", f"city_walk_day_s{k}") for k in (1, 2, 3)},
    "munich_walk_s1": ("munich_walk", "munich_walk_day_s2", "munich_walk_day_s1"),
    "munich_walk_s2": ("munich_walk", "munich_walk_day_s3", "munich_walk_day_s2"),
}
CONFIGURATIONS = ("no anchor", "GNSS 60 s")
WRONG_BY_M = 50.0
METRES_PER_DEGREE_LATITUDE = 111_320.0
OUT = rs.RESULTS / "bias_maps.json"


def survey(run_replay, towers: TowerDatabase, config, made_by: str) -> BiasMap:
    """The survey's map: its stacks' fused sites at the true positions."""
    frame = Anchors(towers).frame
    return survey_bias_map(fuse_route(run_replay, towers, config).observations_by_stack(),
                           (frame.latitude_deg, frame.longitude_deg, frame.height_m), made_by=made_by)


def moved_first_site(towers: TowerDatabase) -> TowerDatabase:
    site = towers.sites[0]
    moved = dataclasses.replace(site, latitude_deg=site.latitude_deg + WRONG_BY_M / METRES_PER_DEGREE_LATITUDE)
    return dataclasses.replace(towers, sites=(moved, *towers.sites[1:]))


def measure(pair: str) -> dict:
    route, survey_bag, bag = PAIRS[pair]
    survey_replay, survey_towers, pipeline = rs.replayed(route, rs.BAGS / survey_bag)
    test_replay, towers, _ = rs.replayed(route, rs.BAGS / bag)
    config = pipeline.fusion
    maps = {"no map": None,
            "map": survey(survey_replay, survey_towers, config, survey_bag),
            "wrong map": survey(survey_replay, moved_first_site(survey_towers), config,
                                f"{survey_bag}, first site {WRONG_BY_M:g} m off")}
    row = {"survey": survey_bag, "bag": bag, "wrong_site": towers.sites[0].name, "configurations": {}}
    for name in CONFIGURATIONS:
        row["configurations"][name] = {
            label: rs.published_summary(fuse_route(test_replay, towers, config, aiding=rs.CONFIGURATIONS[name],
                                                   bias_map=bias_map), config.tracker.max_std_m)
            for label, bias_map in maps.items()}
    return row


def table(rows: dict[str, dict]) -> str:
    lines = [f"{'pair':16s} {'configuration':12s} {'no map':>16s} {'map':>16s} {'wrong map':>16s}   (median / p90 m, NEES)"]
    for pair, row in rows.items():
        for name, variants in row["configurations"].items():
            cells = [f"{_m(v['median_m'])}/{_m(v['p90_m'])} {_m(v['nees_mean'], '{:.1f}')}" for v in variants.values()]
            lines.append(f"{pair:16s} {name:12s} " + " ".join(f"{c:>16s}" for c in cells))
    return "\n".join(lines)


def _m(value: float | None, style: str = "{:.0f}") -> str:
    return "-" if value is None else style.format(value)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", nargs="+", choices=tuple(PAIRS), default=list(PAIRS))
    args = parser.parse_args()
    missing = sorted({bag for pair in args.pairs for bag in PAIRS[pair][1:] if not (rs.BAGS / bag).exists()})
    if missing:
        parser.exit(2, f"bias_maps: missing route-set bags {', '.join(missing)}: make them with "
                       "benchmarks/fusion/route_set.py --bags-only (--routes city_walk munich_walk, "
                       "--loads day evening)\n")
    rows = {}
    for pair in args.pairs:
        print(f"== {pair}", flush=True)
        rows[pair] = measure(pair)
    print(table(rows))
    OUT.write_text(json.dumps(rows, indent=1))
    print(f"written: {OUT}")


if __name__ == "__main__":
    main()
