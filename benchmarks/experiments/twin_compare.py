"""The statistical and the ray-traced twin side by side on the same sites and route.

The Munich walk (config/scenarios/munich_walk.yaml: 250 m, six three-sector rooftop sites,
buildings from Sionna RT's Munich scene) with its ray-traced channel, and with the statistical
channel in its place (38.901 UMa, LOS by distance, TDL-A/TDL-D, spatially consistent:
``route_set.py``'s ``munich_statistical``). Per site, from each channel at 60 instants along the
route (``deepsync.eval.channel_stats``): delay spread, the first path's power share, how often
the first path is the straight line, the first path's and the power centroid's excess over the
straight line; from the route set's measured rows (docs/results/route_set/munich_*_day_s*.json,
written by ``route_set.py --routes munich_walk munich_statistical --loads day``): the timing
stage's median lag per site (a seed whose median is beyond a kilometre locked that site falsely
and is left out), the sites heard, and the published position with no anchor and
with a GNSS fix a minute. The ray-traced channel has no random draw, so its seeds differ only in
site clocks and noise; the statistical one's draw its channel too. Writes
docs/results/twin_compare.json and twin_compare.png.

    python benchmarks/experiments/twin_compare.py
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "fusion"))  # the route set's routes and rows
import route_set as rs  # noqa: E402

from deepsync.eval.channel_stats import channel_statistics  # noqa: E402
from deepsync.twin import build_twin  # noqa: E402
from deepsync.twin.scenario import parse_scenario  # noqa: E402
from deepsync.types import SPEED_OF_LIGHT_M_S  # noqa: E402

TWINS = {"ray-traced": "munich_walk", "statistical": "munich_statistical"}
SEEDS = (1, 2, 3)
INSTANTS = 60
MAX_LAG_M = 1000.0
CONFIGURATIONS = ("no anchor", "GNSS 60 s")
OUT = rs.RESULTS / "twin_compare.json"
FIGURE = rs.RESULTS / "twin_compare.png"


def channel_rows(route: str, seed: int) -> tuple[dict[str, dict], float]:
    """Per site, the channel's statistics along the route; and the ADC's metres per sample."""
    twin = build_twin(parse_scenario(rs.scenario_for(route, "day", seed)))
    times = np.linspace(0.0, rs.ROUTES[route][2], INSTANTS)
    return channel_statistics(twin.channel, twin.emitters, times), SPEED_OF_LIGHT_M_S / twin.frontend.adc_rate_hz


def measured_rows(route: str) -> list[dict]:
    rows = []
    for seed in SEEDS:
        path = rs.RESULTS / "route_set" / f"{route}_day_s{seed}.json"
        if not path.exists():
            raise SystemExit(f"twin_compare: {path} is missing: run benchmarks/fusion/route_set.py --routes "
                             f"{route} --loads day --seeds {' '.join(map(str, SEEDS))}")
        rows.append(json.loads(path.read_text()))
    return rows


def summary() -> dict:
    out = {}
    for label, route in TWINS.items():
        channels, scales = zip(*(channel_rows(route, seed) for seed in SEEDS))
        measured = measured_rows(route)
        metres_per_sample = scales[0]
        sites = sorted(channels[0])
        per_site = {}
        for site in sites:
            keys = channels[0][site].keys() - {"instants"}
            lags = [row["site_bias_samples"].get(site) for row in measured]
            # a median a kilometre off is a site locked falsely most of the run, not a pull
            lags = [lag * metres_per_sample for lag in lags if lag is not None and abs(lag * metres_per_sample) <= MAX_LAG_M]
            per_site[site] = {key: float(np.median([c[site][key] for c in channels])) for key in keys} | {
                "timing_lag_m": float(np.median(lags)) if lags else None}
        out[label] = {
            "sites": per_site,
            "heard_per_stack": [row["heard"]["mean"] for row in measured],
            "bound_median_m": [row["bound"]["median_m"] for row in measured],
            "positions": {name: [row["configurations"][name] for row in measured] for name in CONFIGURATIONS},
        }
    return out


def table(result: dict) -> str:
    lines = [f"{'site':5s} {'twin':11s} {'DS ns':>6s} {'1st share':>9s} {'1st direct':>10s} {'1st excess':>10s} "
             f"{'centroid':>9s} {'lag':>6s} {'dBm/RE':>7s}"]
    for site in sorted(result["ray-traced"]["sites"]):
        for label in TWINS:
            row = result[label]["sites"][site]
            lag = "-" if row["timing_lag_m"] is None else f"{row['timing_lag_m']:.0f}"
            lines.append(f"{site:5s} {label:11s} {row['delay_spread_ns']:6.0f} {row['first_path_share']:9.2f} "
                         f"{row['direct_first_share']:10.2f} {row['first_path_excess_m']:8.0f} m "
                         f"{row['centroid_excess_m']:7.0f} m {lag:>4s} m {row['received_dbm']:7.1f}")
    for label in TWINS:
        heard = ", ".join(f"{h:.1f}" for h in result[label]["heard_per_stack"])
        lines.append(f"{label}: sites per stack {heard}")
        for name in CONFIGURATIONS:
            cells = [f"{_m(p['median_m'])}/{_m(p['p90_m'])} m NEES {_m(p['nees_mean'], '{:.1f}')}"
                     for p in result[label]["positions"][name]]
            lines.append(f"  {name:10s} " + " | ".join(cells))
    return "\n".join(lines)


def _m(value: float | None, style: str = "{:.0f}") -> str:
    return "-" if value is None else style.format(value)


def plot(result: dict) -> None:
    sites = sorted(result["ray-traced"]["sites"])
    x = np.arange(len(sites))
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    for k, (key, title) in enumerate((("centroid_excess_m", "power centroid beyond the straight line (m)"),
                                      ("timing_lag_m", "timing stage's median lag (m)"))):
        for j, label in enumerate(TWINS):
            values = [result[label]["sites"][s][key] or 0.0 for s in sites]
            axes[k].bar(x + (j - 0.5) * 0.4, values, 0.4, label=label)
        axes[k].set_xticks(x, sites)
        axes[k].set_title(title, fontsize=10)
        axes[k].legend(fontsize=8)
    for label in TWINS:
        for name, style in zip(CONFIGURATIONS, ("-o", "--s")):
            medians = [p["median_m"] or np.nan for p in result[label]["positions"][name]]
            axes[2].plot(SEEDS, medians, style, label=f"{label}, {name}")
    axes[2].set_xticks(SEEDS)
    axes[2].set_xlabel("seed")
    axes[2].set_ylabel("published median error (m)")
    axes[2].set_title("Munich walk: position by twin", fontsize=10)
    axes[2].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(FIGURE, dpi=120)
    plt.close(fig)


def main() -> None:
    result = summary()
    print(table(result))
    OUT.write_text(json.dumps(result, indent=1))
    plot(result)
    print(f"written: {OUT}, {FIGURE}")


if __name__ == "__main__":
    main()
