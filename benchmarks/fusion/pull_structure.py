"""How the route set's pulls change along each route, against the bias model the tracker assumes.

Per route (its bags pooled: loads and seeds), every heard site's pull along the path, replayed
as the route set does (the motion model's stacks, the tower database holding the true clocks):
the semivariogram's root at path lags of 1.5-192 m, the exponential fitted to it (stationary
sigma, decorrelation), and the spread of the sites' mean pulls (``deepsync.eval.pulls``). The
tracker assumes, per site, a level of ``persistent_bias_fraction`` (25 %) of
``multipath_std_m``'s variance plus a fading part of the rest over ``bias_decorrelation_m``
(40 m): for a walker 50 m and 87 m, for a car or a static asset 30 m and 52 m. Then, on the
city walk and the ray-traced walk, the published pose with the motion model's
``multipath_std_m`` and with the route's fitted sigma (the two parts together, rounded to 5
m), no anchor and a GNSS fix a minute. Writes docs/results/pull_structure.json and .png.

    python benchmarks/fusion/pull_structure.py [--routes city_walk munich_walk] [--seeds 1 2 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the route set's bags, configurations and summaries
import route_set as rs  # noqa: E402

from deepsync.eval.pulls import LAG_EDGES_M, SitePulls, describe_pulls, site_pulls  # noqa: E402
from deepsync.eval.route import fuse_route  # noqa: E402
from deepsync.fusion.tracker import TrackerConfig  # noqa: E402
from deepsync.motion import MOTION_MODELS  # noqa: E402
from deepsync.pipeline import PipelineConfig  # noqa: E402

COMPARED = ("city_walk", "munich_walk")  # the statistical and the ray-traced walk
CONFIGURATIONS = ("no anchor", "GNSS 60 s")
OUT = rs.RESULTS / "pull_structure.json"


def bags(route: str, seeds: list[int]) -> list[Path]:
    loads = ("day", "evening") if route in ("city_walk", "city_drive", "city_static") else ("day",)
    return [rs.bag_for(route, load, seed, workers=2) for load in loads for seed in seeds]


def measure(route: str, seeds: list[int]) -> dict:
    """The route's pulls pooled over its bags, fitted; the published pose with the model's and
    the fitted sigma where the route is compared."""
    pulls: list[SitePulls] = []
    replays = []
    for bag in bags(route, seeds):
        recorded, towers, config = rs.replayed(route, bag)
        run = fuse_route(recorded, towers, config.fusion)
        pulls += site_pulls(run, recorded.arrivals[0].sample_rate)
        if route in COMPARED:
            replays.append((bag.name, recorded, towers, config))
        print(f"  {bag.name}: {sum(len(p.pull_m) for p in pulls)} arrivals so far", flush=True)
    row = describe_pulls(pulls)
    if row["fit"] is None:  # a receiver that stands: no path for its pulls to change over
        row["static_std_m"] = float(np.median([p.pull_m.std() for p in pulls])) if pulls else None
        return row
    if replays:
        fit = row["fit"]
        fitted = 5.0 * round(math.hypot(fit["sigma_m"], fit["level_std_m"] or 0.0) / 5.0)
        row["fitted_multipath_std_m"] = fitted
        row["published"] = {name: _compare(recorded, towers, config, fitted)
                            for name, recorded, towers, config in replays}
    return row


def _compare(recorded, towers, config: PipelineConfig, fitted: float) -> dict:
    out = {}
    for sigma in (config.fusion.multipath_std_m, fitted):
        fusion = dataclasses.replace(config.fusion, multipath_std_m=sigma)
        for name in CONFIGURATIONS:
            run = fuse_route(recorded, towers, fusion, aiding=rs.CONFIGURATIONS[name])
            out[f"{name}, {sigma:g} m"] = rs.published_summary(run, fusion.tracker.max_std_m)
    return out


def table(rows: dict[str, dict]) -> str:
    edges = LAG_EDGES_M
    head = " | ".join(f"{a:g}-{b:g} m" for a, b in zip(edges[:-1], edges[1:]))
    lines = [f"| route | {head} | fitted sigma / decorrelation | sites' levels |",
             "|---|" + "---|" * (len(edges) - 1) + "---|---|"]
    for route, row in rows.items():
        roots = " | ".join("-" if b["root_m"] is None else f"{b['root_m']:.0f}" for b in row["semivariogram"])
        fit = row["fit"]
        if fit is None:
            lines.append(f"| {route} | {roots} | - (stands; pulls vary {row['static_std_m']:.0f} m) | - |")
        else:
            lines.append(f"| {route} | {roots} | {fit['sigma_m']:.0f} / {fit['decorrelation_m']:.0f} m | "
                         f"{fit['level_std_m']:.0f} m |")
    return "\n".join(lines)


def comparison(rows: dict[str, dict]) -> str:
    lines = ["| bag | configuration | model's sigma | fitted sigma |", "|---|---|---|---|"]
    for route, row in rows.items():
        for bag, results in row.get("published", {}).items():
            keys = list(results)
            for name in CONFIGURATIONS:
                ours, theirs = (results[k] for k in keys if k.startswith(name + ","))
                lines.append(f"| {bag} | {name} | {_cell(ours)} | {_cell(theirs)} |")
        if "fitted_multipath_std_m" in row:
            model = MOTION_MODELS[rs.ROUTES[route][3]].multipath_std_m
            lines.append(f"| ({route}: {model:g} m against {row['fitted_multipath_std_m']:g} m) | | | |")
    return "\n".join(lines)


def _cell(summary: dict) -> str:
    def m(value: float | None, style: str = "{:.0f}") -> str:
        return "-" if value is None else style.format(value)
    return (f"{m(summary['median_m'])} / {m(summary['p90_m'])} (NEES {m(summary['nees_mean'], '{:.1f}')}, "
            f"{m(summary['fix_rate_after_first'], '{:.0%}')} after the first)")


def plot(rows: dict[str, dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    figure, axis = plt.subplots(figsize=(7, 4.5))
    lags = np.geomspace(1.0, 200.0, 100)
    for route, row in rows.items():
        points = [(b["lag_m"], b["root_m"]) for b in row["semivariogram"] if b["root_m"] is not None]
        if row["fit"] is None or not points:
            continue
        line, = axis.plot(*zip(*points), "o", label=route)
        fit = row["fit"]
        axis.plot(lags, fit["sigma_m"] * np.sqrt(-np.expm1(-lags / fit["decorrelation_m"])), "-", color=line.get_color())
    tracker = TrackerConfig()
    for name, style in (("pedestrian", "k--"), ("vehicle", "k:")):
        fading = MOTION_MODELS[name].multipath_std_m * math.sqrt(1 - tracker.persistent_bias_fraction)
        axis.plot(lags, fading * np.sqrt(-np.expm1(-lags / tracker.bias_decorrelation_m)), style,
                  label=f"tracker, {name} ({fading:.0f} m over {tracker.bias_decorrelation_m:g} m)")
    axis.set_xscale("log")
    axis.set_xlabel("path between two arrivals of one site (m)")
    axis.set_ylabel("root semivariance of the pull (m)")
    axis.legend(fontsize=7)
    axis.grid(True, alpha=0.3)
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--routes", nargs="+", default=list(rs.ROUTES), choices=rs.ROUTES)
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3])
    args = parser.parse_args()
    rows = {}
    for route in args.routes:
        print(f"{route}:", flush=True)
        rows[route] = measure(route, args.seeds)
    print(table(rows))
    print()
    print(comparison(rows))
    OUT.write_text(json.dumps(rows, indent=1))
    plot(rows, OUT.with_suffix(".png"))
    print(f"written: {OUT}, {OUT.with_suffix('.png')}")


if __name__ == "__main__":
    main()
