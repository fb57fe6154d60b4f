"""Figures of a route evaluation (PNG): error CDFs, the route on a map, the route over time."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from deepsync.eval.route import CHI2_2DOF_95, METHODS, RouteRun, horizontal_error, nees  # noqa: E402
from deepsync.fusion.anchors import Anchors  # noqa: E402
from deepsync.types import Fix  # noqa: E402

COLOURS = {"snapshot": "tab:blue", "tracked": "tab:green", "rssi": "tab:orange", "bound": "black"}


def _errors(run: RouteRun, method: str) -> tuple[np.ndarray, np.ndarray]:
    """(seconds since the first stack, horizontal error) of a method's fixes."""
    pick = METHODS[method]
    start = run.epochs[0].stamp_ns
    pairs = [((e.stamp_ns - start) * 1e-9, horizontal_error(pick(e), e.truth_enu)) for e in run.epochs
             if isinstance(pick(e), Fix)]
    return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])


def plot_cdf(run: RouteRun, path: Path) -> None:
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
    ax.set_title("Horizontal error CDF" if ax.get_legend_handles_labels()[0] else "Horizontal error CDF: no fixes")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_map(run: RouteRun, anchors: Anchors, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(7, 7))
    truth = np.array([e.truth_enu for e in run.epochs])
    ax.plot(truth[:, 0], truth[:, 1], "k-", lw=1.5, label="true route")
    heard = {s.site for e in run.epochs for s in e.sites}
    for name, anchor in anchors.anchors.items():
        x, y = anchor.position_enu[:2]
        ax.plot(x, y, "^", color="tab:red" if name in heard else "0.6", ms=9)
        ax.annotate(name, (x, y), textcoords="offset points", xytext=(5, 5), fontsize=8)
    fixes = [(e.tracked, e.truth_enu) for e in run.epochs if isinstance(e.tracked, Fix)]
    if fixes:
        points = np.array([f.position_enu[:2] for f, _ in fixes])
        errors = np.array([horizontal_error(f, t) for f, t in fixes])
        scatter = ax.scatter(points[:, 0], points[:, 1], c=errors, s=6, cmap="viridis",
                             vmax=np.percentile(errors, 95), label="tracked fixes")
        fig.colorbar(scatter, ax=ax, shrink=0.7, label="horizontal error (m)")
    if run.anchors:
        given = np.array([enu[:2] for _, enu in run.anchors])
        ax.plot(given[:, 0], given[:, 1], "D", color="tab:purple", mfc="none", ms=7, label="GNSS fixes given")
    ax.set_aspect("equal")
    _zoom_on_route(ax, truth, points if fixes else np.empty((0, 2)))
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(f"Route, sites (red: heard) and tracked fixes; {run.aiding}")
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _zoom_on_route(ax: plt.Axes, truth: np.ndarray, fixes: np.ndarray) -> None:
    """An inset on the route and its fixes when the sites, kilometres apart, shrink them to a dot
    (a short walk): the fixes' scatter around the truth is what the map is for."""
    near = np.vstack([truth[:, :2], fixes]) if fixes.size else truth[:, :2]
    centre = np.median(near, axis=0)
    near = near[np.linalg.norm(near - centre, axis=1) < 200]  # fixes far off stay on the main map only
    span = float(np.ptp(near, axis=0).max()) if len(near) else 0.0
    x0, x1 = ax.get_xlim()
    if span > 0.1 * (x1 - x0):
        return
    half = max(span, 10.0) * 0.6
    inset = ax.inset_axes((0.58, 0.04, 0.38, 0.38))
    for line in ax.get_lines()[:1]:  # the true route
        inset.plot(*line.get_data(), "k-", lw=1.5)
    for line in ax.get_lines()[1:]:  # the GNSS fixes given (the sites are far off the inset)
        if line.get_label() == "GNSS fixes given":
            inset.plot(*line.get_data(), "D", color="tab:purple", mfc="none", ms=6)
    for collection in ax.collections:  # the fixes
        inset.scatter(*collection.get_offsets().T, c=collection.get_array(), s=10, cmap=collection.get_cmap(),
                      norm=collection.norm)
    inset.set_xlim(centre[0] - half, centre[0] + half)
    inset.set_ylim(centre[1] - half, centre[1] + half)
    inset.set_aspect("equal")
    inset.tick_params(labelsize=7)
    inset.set_title(f"zoom: {2 * half:.0f} m across", fontsize=8)
    ax.indicate_inset_zoom(inset, edgecolor="0.4")


def plot_timeline(run: RouteRun, path: Path) -> None:
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
    tracked = [(s, nees(e.tracked, e.truth_enu)) for s, e in zip(t, run.epochs) if isinstance(e.tracked, Fix)]
    if tracked:
        axes[2].semilogy([s for s, _ in tracked], [v for _, v in tracked], ".", ms=3, color=COLOURS["tracked"])
        axes[2].axhline(CHI2_2DOF_95, color="k", ls="--", lw=1, label="95 % of chi-square(2)")
        axes[2].legend(fontsize=8)
    axes[2].set_ylabel("tracked NEES")
    axes[2].set_xlabel("time (s)")
    for k, (stamp, _) in enumerate(run.anchors):
        for ax in axes:
            ax.axvline((stamp - start) * 1e-9, color="tab:purple", lw=0.8, alpha=0.6,
                       label="GNSS fix given" if k == 0 and ax is axes[0] else None)
    if run.anchors:
        axes[0].legend(fontsize=8)
    axes[0].set_title(f"{Path(run.bag).name}: {run.aiding}")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
