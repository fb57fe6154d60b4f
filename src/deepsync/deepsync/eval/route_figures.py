"""Figures of a route evaluation (PNG): error CDFs, the route on a map, the route over time."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from deepsync.eval.route_scores import CHI2_2DOF_95, METHODS, horizontal_error, nees  # noqa: E402
from deepsync.fusion.anchors import Anchors  # noqa: E402
from deepsync.types import Fix  # noqa: E402

if TYPE_CHECKING:  # deepsync.eval.route draws its figures with this module
    from deepsync.eval.route import RouteRun

COLOURS = {"snapshot": "tab:blue", "tracked": "tab:green", "rssi": "tab:orange", "bound": "black"}


def _errors(run: RouteRun, method: str) -> tuple[np.ndarray, np.ndarray]:
    """(seconds since the first stack, horizontal error) of a method's fixes."""
    pick = METHODS[method]
    start = run.epochs[0].stamp_ns
    pairs = [((e.stamp_ns - start) * 1e-9, horizontal_error(pick(e), e.truth_enu)) for e in run.epochs
             if isinstance(pick(e), Fix)]
    return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])


def plot_cdf(run: RouteRun, path: Path) -> None:
    _save(cdf_figure(run), path)


def cdf_figure(run: RouteRun) -> plt.Figure:
    fig, ax = plt.subplots(figsize=(6, 4))
    for method in METHODS:
        _, errors = _errors(run, method)
        if errors.size:
            ax.plot(np.sort(errors), np.arange(1, errors.size + 1) / len(run.epochs), color=COLOURS[method],
                    label=f"{method} ({errors.size} fixes)")
    bounds = np.sort([e.bound_m for e in run.epochs if np.isfinite(e.bound_m)])
    if bounds.size:
        ax.plot(bounds, np.arange(1, bounds.size + 1) / len(run.epochs), "--", color=COLOURS["bound"],
                label="position bound (DRMS)")
    ax.set_xscale("log")
    ax.set_xlabel("horizontal error (m)")
    ax.set_ylabel("fraction of stacks (no fix counts as never)")
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    what = "Horizontal error CDF" if ax.get_legend_handles_labels()[0] else "Horizontal error CDF: no fixes"
    ax.set_title(f"{what}\n{Path(run.bag).name}, {len(run.epochs)} stacks; {run.aiding}", fontsize=10)
    fig.tight_layout()
    return fig


def plot_map(run: RouteRun, anchors: Anchors, path: Path, buildings: Sequence[np.ndarray] = ()) -> None:
    _save(map_figure(run, anchors, buildings), path)


# where an inset may go, in axes fractions (x0, y0, width, height), with room left and below
# for its own ticks and labels
CORNERS = ((0.58, 0.1, 0.38, 0.38), (0.14, 0.1, 0.38, 0.38), (0.58, 0.56, 0.38, 0.38), (0.14, 0.56, 0.38, 0.38))


def map_figure(run: RouteRun, anchors: Anchors, buildings: Sequence[np.ndarray] = ()) -> plt.Figure:
    """The route, the sites (their names beside them), the snapshot's and the tracker's fixes,
    and where the sites shrink a short walk to a dot, an inset on it in a corner that hides no
    site; over ``buildings`` (outlines in the map frame: a ray-traced scene's) where given."""
    fig, ax = plt.subplots(figsize=(7, 7))
    truth = np.array([e.truth_enu for e in run.epochs])
    heard = {s.site for e in run.epochs for s in e.sites}
    sites = {name: anchor.position_enu[:2] for name, anchor in anchors.anchors.items()}
    for name, (x, y) in sites.items():
        ax.plot(x, y, "^", color="tab:red" if name in heard else "0.6", ms=9)
        ax.annotate(name, (x, y), textcoords="offset points", xytext=(5, 5), fontsize=8)
    drawn = _draw_route(ax, run, truth, markers=(6, 9))
    if drawn.tracked is not None:
        fig.colorbar(drawn.tracked, ax=ax, shrink=0.7, label="tracked fix's horizontal error (m)")
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(f"{Path(run.bag).name}: route, sites (red: heard) and fixes\n{run.aiding}", fontsize=10)
    fig.canvas.draw()  # the aspect's limits, where the corners are decided
    free = _free_corners(ax, np.array([*sites.values(), *truth[:, :2], *drawn.points]).reshape(-1, 2))
    inset = _zoom_on_route(ax, run, truth, drawn.points, free)
    for axes in (ax, inset):
        if axes is not None and len(buildings):  # beneath all, and not widening the view
            axes.add_collection(PolyCollection(list(buildings), facecolor="0.88", edgecolor="0.65", linewidth=0.3,
                                               zorder=0, label="buildings" if axes is ax else None), autolim=False)
    # along the figure's foot, where it hides nothing (not even the axis label)
    fig.legend(*ax.get_legend_handles_labels(), fontsize=8, loc="lower center", ncol=4, frameon=False)
    fig.tight_layout(rect=(0.0, 0.06, 1.0, 1.0))
    return fig


class _Drawn:
    """What ``_draw_route`` put on an axes: the tracked fixes' scatter and every fix's position."""

    def __init__(self, tracked, points: np.ndarray) -> None:
        self.tracked = tracked
        self.points = points


def _draw_route(ax: plt.Axes, run: RouteRun, truth: np.ndarray, markers: tuple[float, float],
                norm=None) -> _Drawn:
    """The true route, the snapshot's fixes (crosses), the tracker's (dots by their error) and
    the GNSS fixes given, on ``ax``; ``markers``: the dots' and crosses' sizes."""
    ax.plot(truth[:, 0], truth[:, 1], "k-", lw=1.5, label="true route")
    snapshot = np.array([e.snapshot.position_enu[:2] for e in run.epochs if isinstance(e.snapshot, Fix)])
    if snapshot.size:
        ax.plot(snapshot[:, 0], snapshot[:, 1], "x", color=COLOURS["snapshot"], ms=markers[1] / 2, mew=0.8,
                label="snapshot fixes")
    fixes = [(e.tracked, e.truth_enu) for e in run.epochs if isinstance(e.tracked, Fix)]
    scatter = None
    if fixes:
        points = np.array([f.position_enu[:2] for f, _ in fixes])
        errors = np.array([horizontal_error(f, t) for f, t in fixes])
        scatter = ax.scatter(points[:, 0], points[:, 1], c=errors, s=markers[0], cmap="viridis",
                             norm=norm, vmax=None if norm else np.percentile(errors, 95), label="tracked fixes")
    if run.anchors:
        given = np.array([enu[:2] for _, enu in run.anchors])
        ax.plot(given[:, 0], given[:, 1], "D", color="tab:purple", mfc="none", ms=7, label="GNSS fixes given")
    shown = [a.reshape(-1, 2) for a in (snapshot, points if fixes else np.empty((0, 2)))]
    return _Drawn(scatter, np.vstack(shown))


def _free_corners(ax: plt.Axes, points: np.ndarray) -> list[tuple]:
    """The corners (``CORNERS``) that hold none of ``points`` (data coordinates), with room for
    a site's name beside it; all of them, fewest points first, where none is free."""
    inside = ax.transAxes.inverted().transform(ax.transData.transform(points)) if len(points) else np.empty((0, 2))

    def count(corner: tuple) -> int:
        x0, y0, width, height = corner
        margin = 0.1  # a name is written up and to the right of its triangle; the inset's ticks left and below
        return int(np.sum((inside[:, 0] > x0 - margin) & (inside[:, 0] < x0 + width)
                          & (inside[:, 1] > y0 - margin) & (inside[:, 1] < y0 + height)))

    free = [corner for corner in CORNERS if count(corner) == 0]
    return free or sorted(CORNERS, key=count)


def _zoom_on_route(ax: plt.Axes, run: RouteRun, truth: np.ndarray, fixes: np.ndarray,
                   corners: list[tuple]) -> plt.Axes | None:
    """An inset on the route and its fixes, in the first of ``corners``, when the sites,
    kilometres apart, shrink them to a dot (a short walk): the fixes' scatter around the truth
    is what the map is for. Returns the inset (None: none was needed)."""
    near = np.vstack([truth[:, :2], fixes]) if fixes.size else truth[:, :2]
    centre = np.median(near, axis=0)
    near = near[np.linalg.norm(near - centre, axis=1) < 200]  # fixes far off stay on the main map only
    span = float(np.ptp(near, axis=0).max()) if len(near) else 0.0
    x0, x1 = ax.get_xlim()
    if span > 0.1 * (x1 - x0) or not corners:
        return None
    half = max(span, 10.0) * 0.6
    inset = ax.inset_axes(corners[0])
    scatter = next(iter(ax.collections), None)
    _draw_route(inset, run, truth, markers=(10, 8), norm=None if scatter is None else scatter.norm)
    inset.set_xlim(centre[0] - half, centre[0] + half)
    inset.set_ylim(centre[1] - half, centre[1] + half)
    inset.set_aspect("equal")
    inset.tick_params(labelsize=7)
    inset.set_xlabel("east (m)", fontsize=7, labelpad=1)
    inset.set_ylabel("north (m)", fontsize=7, labelpad=1)
    inset.set_title(f"zoom: {2 * half:.0f} m across", fontsize=8)
    ax.indicate_inset_zoom(inset, edgecolor="0.4")
    return inset


def plot_timeline(run: RouteRun, path: Path) -> None:
    _save(timeline_figure(run), path)


def timeline_figure(run: RouteRun) -> plt.Figure:
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    start = run.epochs[0].stamp_ns
    t = np.array([(e.stamp_ns - start) * 1e-9 for e in run.epochs])
    for method in METHODS:
        seconds, errors = _errors(run, method)
        if errors.size:
            axes[0].semilogy(seconds, errors, ".", ms=3, color=COLOURS[method], label=method)
    axes[0].set_ylabel("horizontal error (m)")
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=8)
    axes[1].step(t, [len(e.sites) for e in run.epochs], where="post", color="tab:red")
    axes[1].set_ylabel("sites heard")
    axes[1].yaxis.set_major_locator(MaxNLocator(integer=True))  # a count: no half steps
    tracked = [(s, nees(e.tracked, e.truth_enu)) for s, e in zip(t, run.epochs) if isinstance(e.tracked, Fix)]
    if tracked:
        axes[2].semilogy([s for s, _ in tracked], [v for _, v in tracked], ".", ms=3, color=COLOURS["tracked"])
        axes[2].axhline(2.0, color="0.4", ls=":", lw=1, label="2: its mean where the covariance is honest")
        axes[2].axhline(CHI2_2DOF_95, color="k", ls="--", lw=1, label="95 % of chi-square(2)")
        axes[2].legend(fontsize=8)
    # NEES: the squared horizontal error in units of the fix's own covariance
    axes[2].set_ylabel("tracked NEES\n(error$^2$ / covariance)")
    axes[2].set_xlabel("time since the first stack (s)")
    for k, (stamp, _) in enumerate(run.anchors):
        for ax in axes:
            ax.axvline((stamp - start) * 1e-9, color="tab:purple", lw=0.8, alpha=0.6,
                       label="GNSS fix given" if k == 0 and ax is axes[0] else None)
    if run.anchors:
        axes[0].legend(fontsize=8)
    axes[0].set_title(f"{Path(run.bag).name} over time: horizontal error, sites heard, tracked NEES; {run.aiding}",
                      fontsize=10)
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


def _save(fig: plt.Figure, path: Path) -> None:
    fig.savefig(path, dpi=120)
    plt.close(fig)
