"""Site bias maps: how late each site's arrivals read, where a survey went, known before the run.

In a city the envelope's peak lags a site's straight line by its NLOS pull (25-165 m on the
statistical walks, up to 300 m and for whole streets on the ray-traced one), changing over tens
of metres. The tracker learns each site's pull online (its bias states), but without an anchor a
pull is weakly observable: it trades against position. A map says it in advance: for each site,
on a regular grid over the ``map`` frame, the mean range bias (m) and its 1-sigma, known within
a kernel's width of where a survey went.

* **Where a map comes from**: a survey, a run at known positions (a receiver with GNSS, or a
  twin's truth: statistical or ray-traced) through :func:`survey_bias_map`.
* **Where it is read**: the pull changes by up to 100 m over 50 m of street, so a map read at a
  fix tens of metres off corrects wrongly. Each stack hearing three mapped sites or more reads
  it where its sites, each with its map taken off, agree best (:meth:`BiasMap.locate`, among
  the survey's own nodes); a stack hearing fewer reads it at the latest such place, widened by
  the speed the receiver may have walked since (the fusion stage does this).
* **How fusion uses it** (:meth:`BiasMap.correct`): the map's mean comes off each mapped site's
  range; the site's bias sigma stays the one it has without a map (``multipath_std_m``), or the
  map's where that is wider (averaged over where the receiver may be, its spread there added).
  A map is read where the stack says the receiver is, and that place can be wrong: a correction
  wrong by as much as the pull then leaves a bias no larger than the one the sigma already
  covers, where the map's own narrow sigma made such a track overconfident and worse than no
  map (the route set: NEES 6-11 on the ray-traced walk). The tracker's bias states carry what
  the map got wrong. An unmapped site, or one off the map, is left as it was: a map never stops
  a site being used.
* **Gauge**: TDOA sees a bias common to every site as the receiver clock, so a map holds each
  site's bias against the others; only differences count.
* **A wrong map** (its sigma floored at ``min_std_m``) pulls by what it claims: build a map
  against the tower database it will be used with, whose site clocks are the rest of each
  site's bias.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from deepsync.fusion.anchors import FRAME_RANGE_M, SiteArrival, unwrap_range
from deepsync.fusion.calibration import CalibrationObservation
from deepsync.fusion.snapshot import chi_square_limit
from deepsync.outputs import replacing
from deepsync.schema import check_settings, setting
from deepsync.towers import TowerDatabase

FORMAT = "deepsync-bias-map-1"
MAX_BIAS_M = 1000.0  # beyond any NLOS pull (6.7 samples at 1.92 MHz)
# 3 x 3 Gauss-Hermite points over a receiver's position uncertainty: nodes in sqrt(3) sigmas, weights
_HERMITE_EAST, _HERMITE_NORTH = (axis.ravel() for axis in np.meshgrid([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0]))
_HERMITE_WEIGHTS = np.outer([1 / 6, 2 / 3, 1 / 6], [1 / 6, 2 / 3, 1 / 6]).ravel()
CHI2_68_2DOF = 2.28  # chi-square with 2 degrees of freedom at 68 %
LOCATE_GATE_PROBABILITY = 1e-3
SURVEY_ROUNDS = 10  # turns of stack offsets and site maps: the maps move by centimetres after ten


@dataclass(frozen=True)
class BiasGrid:
    """One site's bias on a regular grid: node ``[i, j]`` at east ``x0_m + j * step_m``, north
    ``y0_m + i * step_m`` (m, map frame); NaN where the map knows nothing."""

    x0_m: float
    y0_m: float
    step_m: float
    mean_m: np.ndarray = field(compare=False)  # (ny, nx)
    std_m: np.ndarray = field(compare=False)  # (ny, nx)

    def __post_init__(self) -> None:
        mean, std = np.asarray(self.mean_m, dtype=np.float64), np.asarray(self.std_m, dtype=np.float64)
        if mean.ndim != 2 or mean.shape != std.shape or min(mean.shape) < 1:
            raise ValueError(f"a bias grid's mean and std must be 2-D arrays of one shape, got {mean.shape} "
                             f"and {std.shape}")
        if not (math.isfinite(self.x0_m) and math.isfinite(self.y0_m) and math.isfinite(self.step_m)
                and self.step_m > 0):
            raise ValueError(f"a bias grid needs a finite origin and a positive step, got ({self.x0_m!r}, "
                             f"{self.y0_m!r}) step {self.step_m!r}")
        known = np.isfinite(mean)
        if np.any(known != np.isfinite(std)) or np.any(std[known] < 0):
            raise ValueError("a bias grid's std must be a non-negative number exactly where its mean is known")
        object.__setattr__(self, "mean_m", mean)
        object.__setattr__(self, "std_m", std)

    def at(self, east_m: float, north_m: float) -> tuple[float, float] | None:
        """The bias (m) and its 1-sigma (m) at a point (:meth:`values`); None where unknown."""
        mean, std = self.values(np.array([east_m]), np.array([north_m]))
        return None if math.isnan(mean[0]) else (float(mean[0]), float(std[0]))

    def values(self, east_m: np.ndarray, north_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bias and 1-sigma (m) at each point, bilinear between the known nodes of its cell;
        NaN outside the grid or where no node of the cell is known."""
        ny, nx = self.mean_m.shape
        u, v = (np.asarray(east_m) - self.x0_m) / self.step_m, (np.asarray(north_m) - self.y0_m) / self.step_m
        inside = (u >= 0) & (u <= nx - 1) & (v >= 0) & (v <= ny - 1)
        j = np.clip(np.floor(u), 0, max(nx - 2, 0)).astype(np.intp)
        i = np.clip(np.floor(v), 0, max(ny - 2, 0)).astype(np.intp)
        fu, fv = np.clip(u - j, 0, 1), np.clip(v - i, 0, 1)
        total = mean = sigma = 0.0
        for di, dj, weight in ((0, 0, (1 - fu) * (1 - fv)), (0, 1, fu * (1 - fv)), (1, 0, (1 - fu) * fv), (1, 1, fu * fv)):
            rows, cols = np.minimum(i + di, ny - 1), np.minimum(j + dj, nx - 1)
            node_mean, node_std = self.mean_m[rows, cols], self.std_m[rows, cols]
            weight = np.where(np.isfinite(node_mean) & inside, weight, 0.0)
            total = total + weight
            mean = mean + weight * np.nan_to_num(node_mean)
            sigma = sigma + weight * np.nan_to_num(node_std)
        known = total > 0
        safe = np.where(known, total, 1.0)
        return np.where(known, mean / safe, np.nan), np.where(known, sigma / safe, np.nan)


@dataclass(frozen=True)
class BiasMap:
    """Every mapped site's :class:`BiasGrid`, the ``map`` frame's origin it was made in
    (latitude, longitude in degrees, height in m) and what made it, in words.

    ``min_std_m`` floors the sigma a map gives (a survey's few arrivals at a node can agree
    by chance)."""

    origin: tuple[float, float, float]
    sites: Mapping[str, BiasGrid]
    made_by: str = ""
    min_std_m: float = 10.0

    def __post_init__(self) -> None:
        if len(self.origin) != 3 or not all(math.isfinite(v) for v in self.origin):
            raise ValueError(f"a bias map's origin must be (latitude, longitude, height), got {self.origin!r}")
        if not (math.isfinite(self.min_std_m) and self.min_std_m > 0):
            raise ValueError(f"min_std_m: {self.min_std_m!r} must be a positive number of metres")

    def at(self, site: str, east_m: float, north_m: float, position_std_m: float = 0.0) -> tuple[float, float] | None:
        """A site's bias (m) and 1-sigma (m) for a receiver at a point known to ``position_std_m``
        (1-sigma per axis): the map averaged over that uncertainty, its spread there added to its
        own sigma (3 x 3 Gauss-Hermite points); None where the map cannot say (no grid for the
        site, or less than half the uncertainty's weight on known nodes)."""
        grid = self.sites.get(site)
        if grid is None or not math.isfinite(position_std_m):
            return None
        step = math.sqrt(3.0) * max(position_std_m, 0.0)
        means, sigmas = grid.values(east_m + step * _HERMITE_EAST, north_m + step * _HERMITE_NORTH)
        known = np.isfinite(means)
        if _HERMITE_WEIGHTS[known].sum() < 0.5:
            return None
        w = _HERMITE_WEIGHTS[known] / _HERMITE_WEIGHTS[known].sum()
        mean = float(w @ means[known])
        spread = float(w @ (means[known] - mean) ** 2)
        return mean, math.sqrt(float(w @ np.maximum(sigmas[known], self.min_std_m) ** 2) + spread)

    def correct(self, arrivals: Sequence[SiteArrival], position_enu: Sequence[float],
                position_std_m: float) -> tuple[SiteArrival, ...]:
        """The arrivals with each mapped site's bias for a receiver at ``position_enu`` (known
        to ``position_std_m``) taken off its range, its bias sigma the larger of its own and the
        map's; sites the map cannot say there as they were."""
        out = []
        for arrival in arrivals:
            value = self.at(arrival.site, float(position_enu[0]), float(position_enu[1]), position_std_m)
            if value is not None:
                mean, std = value
                arrival = dataclasses.replace(arrival, range_mod_m=(arrival.range_mod_m - mean) % FRAME_RANGE_M,
                                              bias_std_m=max(std, arrival.bias_std_m))
            out.append(arrival)
        return tuple(out)

    @functools.cached_property
    def _nodes(self) -> np.ndarray:
        """(N, 2) every node some site's map knows: where a survey went."""
        points = []
        for grid in self.sites.values():
            rows, cols = np.nonzero(np.isfinite(grid.mean_m))
            points.append(np.column_stack([grid.x0_m + cols * grid.step_m, grid.y0_m + rows * grid.step_m]))
        return np.unique(np.round(np.concatenate(points), 3), axis=0) if points else np.empty((0, 2))

    def locate(self, arrivals: Sequence[SiteArrival]) -> tuple[np.ndarray, float] | None:
        """The mapped point (a node some site's map knows: where the survey went) at which the
        stack's sites, each with its map taken off, agree best with one receiver clock, and the
        spread (m, 1-sigma) of the nodes that fit about as well; None with fewer than three
        mapped sites, or where even the best node fails the chi-square test (the receiver is off
        the map). Nodes, not the plane: off the survey the map says nothing, and a pull that
        changes over tens of metres fits somewhere by chance in a plane."""
        nodes = self._nodes
        mapped = [a for a in arrivals if a.site in self.sites]
        if len(mapped) < 3 or not len(nodes):
            return None
        east, north = nodes[:, 0], nodes[:, 1]
        reference = mapped[0].range_mod_m
        residual, weight = [], []
        for arrival in mapped:
            mean, std = self.sites[arrival.site].values(east, north)
            distance = np.hypot(east - arrival.position_enu[0], north - arrival.position_enu[1])
            noise = arrival.timing_std_m**2 + arrival.clock_std_m**2 + np.maximum(np.nan_to_num(std), self.min_std_m) ** 2
            residual.append(unwrap_range(arrival.range_mod_m - reference, 0.0) - distance - np.nan_to_num(mean))
            weight.append(np.where(np.isfinite(mean), 1.0 / noise, 0.0))
        residual, weight = np.array(residual), np.array(weight)
        counted = (weight > 0).sum(axis=0)
        clock = (weight * residual).sum(axis=0) / np.maximum(weight.sum(axis=0), 1e-300)
        cost = np.where(counted >= 3, (weight * (residual - clock) ** 2).sum(axis=0), np.inf)
        best = int(np.argmin(cost))
        if not cost[best] <= chi_square_limit(LOCATE_GATE_PROBABILITY, int(counted[best]) - 1):
            return None
        near = cost <= cost[best] + CHI2_68_2DOF
        spread = math.sqrt(np.mean((east[near] - east[best]) ** 2 + (north[near] - north[best]) ** 2) / 2)
        return nodes[best], spread

    def check_frame(self, origin: tuple[float, float, float], what: str) -> None:
        """ValueError unless the map was made in the frame with ``origin`` (within a metre)."""
        (lat0, lon0, h0), (lat1, lon1, h1) = self.origin, origin
        if abs(lat0 - lat1) > 1e-5 or abs(lon0 - lon1) > 1e-5 or abs(h0 - h1) > 1.0:
            raise ValueError(f"bias map ({self.made_by or 'no source'}) was made in the frame at {self.origin}, "
                             f"{what} is at {tuple(origin)}: use a map made with the same tower database's origin")

    def check_database(self, towers: TowerDatabase) -> None:
        """ValueError unless ``towers`` has an origin and the map was made in its ``map`` frame."""
        if towers.origin is None:
            raise ValueError(f"tower database {towers.name!r} has no origin: a bias map needs the map frame's")
        origin = towers.origin
        self.check_frame((origin.latitude_deg, origin.longitude_deg, origin.height_m), f"tower database {towers.name!r}")


def save_bias_map(bias_map: BiasMap, path: str | Path) -> Path:
    """Write ``bias_map`` as one ``.npz`` file (no pickles)."""
    path = Path(path)
    arrays: dict[str, np.ndarray] = {
        "format": np.array(FORMAT), "origin": np.array(bias_map.origin, dtype=np.float64),
        "made_by": np.array(bias_map.made_by), "sites": np.array(sorted(bias_map.sites)),
        "min_std_m": np.array(bias_map.min_std_m),
    }
    for k, name in enumerate(sorted(bias_map.sites)):
        grid = bias_map.sites[name]
        arrays[f"grid{k}"] = np.array([grid.x0_m, grid.y0_m, grid.step_m])
        arrays[f"mean{k}"], arrays[f"std{k}"] = grid.mean_m, grid.std_m
    path.parent.mkdir(parents=True, exist_ok=True)
    with replacing(path) as temporary, temporary.open("wb") as f:  # whole or not at all; any name kept as given
        np.savez_compressed(f, **arrays)
    return path


def load_bias_map(path: str | Path) -> BiasMap:
    """Read a map written by :func:`save_bias_map`; ValueError naming the file and what is wrong."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"bias map {str(path)!r} does not exist")
    try:
        if not zipfile.is_zipfile(path):  # numpy would try it as a pickle, and say so
            raise ValueError(f"not a DeepSync bias map (an .npz archive, {FORMAT})")
        with np.load(path, allow_pickle=False) as data:
            if "format" not in data or str(data["format"]) != FORMAT:
                raise ValueError(f"not a DeepSync bias map ({FORMAT})")
            names = [str(n) for n in data["sites"]]
            sites = {}
            for k, name in enumerate(names):
                x0, y0, step = (float(v) for v in data[f"grid{k}"])
                sites[name] = BiasGrid(x0, y0, step, data[f"mean{k}"], data[f"std{k}"])
            return BiasMap(tuple(float(v) for v in data["origin"]), sites, str(data["made_by"]),
                           float(data["min_std_m"]))
    except (OSError, KeyError, ValueError, TypeError) as error:
        raise ValueError(f"bias map {str(path)!r} cannot be read: {error}") from None


@dataclass(frozen=True)
class SurveyConfig:
    """How a survey becomes a map (:func:`survey_bias_map`)."""

    step_m: float = setting(10.0, help="Spacing of the bias map's grid.", unit="m", bounds=(0.0, 1e4), open_low=True)
    smoothing_m: float = setting(15.0, help="1-sigma of the Gaussian kernel over which a survey's arrivals are "
                                 "averaged into a node: shorter than the pull's 40 m decorrelation, longer than "
                                 "a stack's walk.", unit="m", bounds=(0.0, 1e4), open_low=True)
    min_weight: float = setting(3.0, help="Arrivals' worth of kernel weight a node needs to be known.",
                                bounds=(0.0, 1e4), open_low=True)
    def __post_init__(self) -> None:
        check_settings(self)


def survey_bias_map(stacks: Sequence[Sequence[CalibrationObservation]], origin: tuple[float, float, float],
                    config: SurveyConfig | None = None, made_by: str = "survey") -> BiasMap:
    """A bias map from arrivals heard at known positions (a survey), grouped by the stack that
    heard them.

    Within one stack every site reads the same receiver clock, so what two sites read beyond
    their true distances differs by their biases alone (their arrivals lie within a frame, 10 ms,
    over which a receiver clock a few ppm off moves by metres); what is common to a stack is its
    own offset. Offsets and per-site maps are then fitted in turns (each map a
    Gaussian-kernel average of its site's biases, Huber-trimmed: a false lock a sample off is not
    a pull); their gauge: the maps average zero over the survey's arrivals. Stacks hearing one
    site say nothing of any bias and are left out."""
    config = config or SurveyConfig()
    stacks = [stack for stack in stacks if len({o.arrival.site for o in stack}) >= 2]
    flat = [o for stack in stacks for o in stack]
    if not flat:
        raise ValueError("a survey needs stacks that heard two or more sites at known positions, got none")
    stack, read = _stack_read(stacks)
    # what reads a kilometre off its stack's other sites is no pull (a false lock, a wrong clock):
    # left out, and stacks left with one site with it
    kept = np.abs(read - _stack_medians(stack, read)[stack]) <= MAX_BIAS_M
    stacks = [[o for o, k in zip(s, kept[stack == i]) if k] for i, s in enumerate(stacks)]
    stacks = [s for s in stacks if len({o.arrival.site for o in s}) >= 2]
    flat = [o for s in stacks for o in s]
    if not flat:
        raise ValueError(f"no two sites of one stack read within {MAX_BIAS_M:g} m of each other beyond their true "
                         "distances: the survey's positions or the tower database are wrong")
    stack, read = _stack_read(stacks)
    truth = np.array([o.truth_enu for o in flat], dtype=np.float64)[:, :2]
    names = np.array([o.arrival.site for o in flat])
    mine = {str(name): names == name for name in sorted(set(names))}
    mapped = np.zeros(len(flat))
    counts = np.bincount(stack)
    for _ in range(SURVEY_ROUNDS):
        offset = np.bincount(stack, read - mapped) / counts
        bias = read - offset[stack]
        for where in mine.values():
            mapped[where] = _kernel_average(truth[where], bias[where], truth[where], config)[0]
        # where a site's own arrivals are too few to map, its bias counts as none (and it is unmapped there)
        mapped = np.nan_to_num(mapped - np.nanmean(mapped) if np.any(np.isfinite(mapped)) else mapped)
    offset = np.bincount(stack, read - mapped) / counts
    bias = read - offset[stack]
    return bias_map_from_points({name: (truth[where], bias[where]) for name, where in mine.items()}, origin, config,
                                made_by)


def bias_map_from_points(biases: Mapping[str, tuple[np.ndarray, np.ndarray]], origin: tuple[float, float, float],
                         config: SurveyConfig | None = None, made_by: str = "") -> BiasMap:
    """A map from each site's range biases (m) measured at points ((N, 2) or (N, 3), map
    frame): ``{site: (points, biases)}``. Each node of a grid over the points (two kernel
    widths beyond them) holds the Gaussian-kernel mean and spread of the biases near it
    (:class:`SurveyConfig`); a site with no point is left out."""
    config = config or SurveyConfig()
    biases = {name: (np.asarray(points, dtype=np.float64)[:, :2], np.asarray(values, dtype=np.float64))
              for name, (points, values) in biases.items() if len(values)}
    if not biases:
        raise ValueError("a bias map needs at least one site's bias at one point, got none")
    everywhere = np.concatenate([points for points, _ in biases.values()])
    lo = everywhere.min(axis=0) - 2 * config.smoothing_m
    hi = everywhere.max(axis=0) + 2 * config.smoothing_m
    east = lo[0] + config.step_m * np.arange(int(math.ceil((hi[0] - lo[0]) / config.step_m)) + 1)
    north = lo[1] + config.step_m * np.arange(int(math.ceil((hi[1] - lo[1]) / config.step_m)) + 1)
    nodes = np.stack(np.meshgrid(east, north), axis=-1).reshape(-1, 2)
    grids = {}
    for name, (points, values) in biases.items():
        mean, std = _kernel_average(points, values, nodes, config)
        grids[name] = BiasGrid(float(east[0]), float(north[0]), config.step_m, mean.reshape(len(north), len(east)),
                               std.reshape(len(north), len(east)))
    return BiasMap(origin, grids, made_by)


def _stack_read(stacks: Sequence[Sequence[CalibrationObservation]]) -> tuple[np.ndarray, np.ndarray]:
    """Each arrival's stack index and what it reads beyond its true distance (m), against its
    stack's first arrival (the frame's ambiguity taken out)."""
    flat = [o for stack in stacks for o in stack]
    stack = np.repeat(np.arange(len(stacks)), [len(s) for s in stacks])
    truth = np.array([o.truth_enu for o in flat], dtype=np.float64)
    sites = np.array([o.arrival.position_enu for o in flat], dtype=np.float64)
    y_mod = np.array([o.arrival.range_mod_m for o in flat]) - np.linalg.norm(truth - sites, axis=1)
    first = np.searchsorted(stack, np.arange(len(stacks)))
    return stack, unwrap_range(y_mod - y_mod[first][stack], 0.0)


def _stack_medians(stack: np.ndarray, values: np.ndarray) -> np.ndarray:
    order = np.argsort(stack, kind="stable")
    starts = np.flatnonzero(np.diff(stack[order], prepend=-1))
    return np.array([np.median(part) for part in np.split(values[order], starts[1:])])


def _kernel_average(points: np.ndarray, values: np.ndarray, queries: np.ndarray,
                    config: SurveyConfig) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian-kernel mean and spread of ``values`` at each query point (NaN where less than
    ``min_weight`` of weight lies within four kernel sigmas), twice: the second pass leaves out
    what sits beyond 3 sigmas of the first."""
    pairs = cKDTree(queries).sparse_distance_matrix(cKDTree(points), 4 * config.smoothing_m, output_type="ndarray")
    query, point = pairs["i"], pairs["j"]
    weight = np.exp(-0.5 * (pairs["v"] / config.smoothing_m) ** 2)
    n = len(queries)
    # the sigma is what a new run's arrival meets there: the survey's own spread about the mean,
    # not the mean's standard error (tighter sigmas made the route set's tracks follow a map read
    # a node off, and lose 20 m on two of three walks)
    mean = std = np.zeros(n)
    for round_ in range(2):
        if round_:
            weight = np.where(np.abs(values[point] - mean[query]) <= 3 * np.maximum(std[query], 1.0), weight, 0.0)
        total = np.bincount(query, weight, n)
        safe = np.maximum(total, 1e-300)
        mean = np.bincount(query, weight * values[point], n) / safe
        std = np.sqrt(np.maximum(np.bincount(query, weight * values[point] ** 2, n) / safe - mean**2, 0.0))
    # a survey knows the pull where it went, not beside it: a node further than a kernel sigma
    # from every arrival is unknown (the pull changes over tens of metres across the street too)
    nearest = cKDTree(points).query(queries, distance_upper_bound=config.smoothing_m)[0]
    unknown = (total < config.min_weight) | ~np.isfinite(nearest)
    mean[unknown], std[unknown] = np.nan, np.nan
    return mean, std
