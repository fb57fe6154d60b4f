"""What a twin's channel gives each site along its route: the numbers that tell two channel
models apart (the statistical 3GPP one and a ray-traced one on the same sites and route).

Per site, at receiver positions spread evenly in time over the route, from the site's strongest
sector there (any provider of :class:`~deepsync.frontend.channel.Paths`):

* ``delay_spread_ns``: the power-weighted RMS delay spread;
* ``first_path_share``: the share of the power arriving within ``FIRST_PATH_WINDOW_S`` of the
  earliest path (what a timing estimator that locks to the energy's leading edge can use);
* ``first_path_excess_m``: the earliest path's delay beyond the straight line (0 where the
  direct path exists; a ray tracer's NLOS adds the detour);
* ``centroid_excess_m``: the power centroid's delay beyond the straight line: where an
  envelope's peak is pulled to when the paths are not resolved (1 sample = 156 m at 1.92 MHz);
* ``direct_first_share``: how often the earliest path arrives on the straight line (within a
  nanosecond): always in the statistical channel, whose first tap sits there by construction
  even in NLOS; a ray tracer's blocked sites arrive later;
* ``received_dbm``: the sector's total received power per resource element.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from deepsync.frontend.channel import Emitter, Paths
from deepsync.types import SPEED_OF_LIGHT_M_S

FIRST_PATH_WINDOW_S = 50e-9  # a tenth of a 1.92 MS/s sample: paths this close are one arrival
DIRECT_TOLERANCE_S = 1e-9


def path_statistics(paths: Paths, geometric_delay_s: float) -> dict[str, float]:
    """One sector's paths at one instant (see the module docstring); power in linear units."""
    power = np.abs(paths.gains) ** 2
    total = float(power.sum())
    delays = paths.delays_s
    first = float(delays.min())
    mean = float(power @ delays / total) if total > 0 else first
    spread = float(np.sqrt(max(power @ (delays - mean) ** 2 / total, 0.0))) if total > 0 else 0.0
    return {
        "power": total,
        "delay_spread_ns": spread * 1e9,
        "first_path_share": float(power[delays <= first + FIRST_PATH_WINDOW_S].sum() / total) if total > 0 else 0.0,
        "first_path_excess_m": (first - geometric_delay_s) * SPEED_OF_LIGHT_M_S,
        "centroid_excess_m": (mean - geometric_delay_s) * SPEED_OF_LIGHT_M_S,
        "direct_first": float(abs(first - geometric_delay_s) <= DIRECT_TOLERANCE_S),
    }


def channel_statistics(channel, emitters: Sequence[Emitter], times_s: Sequence[float]) -> dict[str, dict]:
    """Per site (by name): the median over ``times_s`` of its strongest sector's path statistics
    (``direct_first_share``: the mean of its flag), and how many instants it was evaluated at.
    ``channel`` needs ``paths(emitter_index, t)`` and ``geometric_delay_s(emitter_index, t)``."""
    table = {}
    for site, indices in _sectors(emitters).items():
        rows = [_strongest_sector(channel, emitters, indices, t) for t in times_s]
        table[site] = {key: float(np.median([row[key] for row in rows])) for key in rows[0] if key != "direct_first"}
        table[site]["direct_first_share"] = float(np.mean([row["direct_first"] for row in rows]))
        table[site]["instants"] = len(rows)
    return table


def direct_first(channel, emitters: Sequence[Emitter], site: str, t: float) -> bool:
    """Whether ``site``'s strongest sector's earliest path at ``t`` is the straight line (LOS)."""
    return bool(_strongest_sector(channel, emitters, _sectors(emitters)[site], t)["direct_first"])


def _sectors(emitters: Sequence[Emitter]) -> dict[str, list[int]]:
    """Each site's emitter indices, sites by name in order."""
    by_site: dict[str, list[int]] = {}
    for index, emitter in enumerate(emitters):
        by_site.setdefault(emitter.site, []).append(index)
    return dict(sorted(by_site.items()))


def _strongest_sector(channel, emitters: Sequence[Emitter], indices: Sequence[int], t: float) -> dict[str, float]:
    """The path statistics at ``t`` of the sector among ``indices`` that arrives strongest, its
    power turned into ``received_dbm`` per resource element."""
    stats = [(path_statistics(channel.paths(i, t), channel.geometric_delay_s(i, t)), i) for i in indices]
    best, index = max(stats, key=lambda pair: pair[0]["power"])
    best["received_dbm"] = 10 * np.log10(max(best.pop("power") * emitters[index].re_power_w, 1e-30)) + 30
    return best
