"""Evaluation pictures (matplotlib, Agg canvas, no pyplot state).

Top view of ground truth, online and final trajectories with loop closures; error over time before
and after closing; error-coloured trajectory. Each function returns PNG bytes.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
AXIS_NAMES = ("x", "y", "z")


@dataclass
class PlotTrack:
    """One trajectory to draw: positions (N x 3, metres, ground-truth frame), times (s)."""

    label: str
    positions_m: F64
    times_s: F64
    errors_m: F64 | None = None
    style: str = "-"
    color: str = "C0"


@dataclass
class PlotClosure:
    """A loop closure to mark: time (s), query position and optional matched position."""

    time_s: float
    query_m: F64
    match_m: F64 | None = None


def _figure(width_in: float = 7.0, height_in: float = 5.5):  # type: ignore[no-untyped-def]
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _png(fig) -> bytes:  # type: ignore[no-untyped-def]
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def top_view_axes(positions_m: F64) -> tuple[int, int]:
    """The two world axes spanning the largest extent of a path (the plane seen from above)."""
    spread = np.ptp(positions_m, axis=0) if len(positions_m) else np.ones(3)
    keep = sorted(np.argsort(spread)[1:].tolist())
    return int(keep[0]), int(keep[1])


def plot_top_view(reference_m: F64, tracks: list[PlotTrack], closures: list[PlotClosure], title: str) -> bytes:
    """Ground truth and trajectories seen from above, loop closures marked."""
    a, b = top_view_axes(reference_m)
    fig = _figure()
    ax = fig.add_subplot(111)
    ax.plot(reference_m[:, a], reference_m[:, b], "-", color="k", lw=1.2, label="ground truth")
    for tr in tracks:
        ax.plot(
            tr.positions_m[:, a],
            tr.positions_m[:, b],
            tr.style,
            color=tr.color,
            lw=1.0,
            label=tr.label,
        )
    for k, c in enumerate(closures):
        if c.match_m is not None:
            ax.plot(
                [c.query_m[a], c.match_m[a]],
                [c.query_m[b], c.match_m[b]],
                "-",
                color="red",
                lw=0.8,
                alpha=0.7,
            )
        ax.plot(
            [c.query_m[a]],
            [c.query_m[b]],
            "*",
            color="red",
            ms=10,
            label="loop closure" if k == 0 else None,
        )
    ax.plot([reference_m[0, a]], [reference_m[0, b]], "o", color="g", ms=6, label="start")
    ax.set_xlabel(f"{AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{AXIS_NAMES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _png(fig)


def plot_error_over_time(tracks: list[PlotTrack], closures: list[PlotClosure], title: str) -> bytes:
    """Translational ATE of each trajectory over time, loop closures as vertical lines."""
    fig = _figure(8.0, 4.0)
    ax = fig.add_subplot(111)
    for tr in tracks:
        if tr.errors_m is not None:
            ax.plot(tr.times_s, tr.errors_m, tr.style, color=tr.color, lw=1.0, label=tr.label)
    for k, c in enumerate(closures):
        ax.axvline(c.time_s, color="red", lw=0.8, alpha=0.6, label="loop closure" if k == 0 else None)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("ATE [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _png(fig)


def plot_error_colored(reference_m: F64, track: PlotTrack, title: str) -> bytes:
    """One trajectory seen from above, coloured by its translational ATE."""
    from matplotlib.collections import LineCollection

    a, b = top_view_axes(reference_m)
    fig = _figure()
    ax = fig.add_subplot(111)
    ax.plot(reference_m[:, a], reference_m[:, b], "--", color="0.6", lw=0.8, label="ground truth")
    xy = track.positions_m[:, [a, b]]
    err = track.errors_m if track.errors_m is not None else np.zeros(len(xy))
    if len(xy) >= 2:
        segs = np.stack([xy[:-1], xy[1:]], axis=1)
        lc = LineCollection(list(segs), cmap="jet", linewidths=2.0)
        lc.set_array(0.5 * (err[:-1] + err[1:]))
        ax.add_collection(lc)
        cb = fig.colorbar(lc, ax=ax)
        cb.set_label("ATE [m]")
    ax.autoscale_view()
    ax.set_xlabel(f"{AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{AXIS_NAMES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _png(fig)


# --------------------------------------------------------------------------- many runs


def plot_metric_by_group(values: dict[str, dict[str, float]], metric: str, title: str, log: bool = False) -> bytes:
    """One metric of many runs.

    A marker per (series, category), e.g. series = configuration variants and categories = sequences
    (``values[series][category]``; missing ones left out).
    """
    fig = _figure(8.0, 4.8)
    ax = fig.add_subplot(111)
    cats = sorted({c for v in values.values() for c in v})
    xs = np.arange(len(cats), dtype=float)
    n = max(len(values), 1)
    for k, (series, vals) in enumerate(values.items()):
        off = (k - (n - 1) / 2) * 0.6 / n
        pts = [(xs[i] + off, vals[c]) for i, c in enumerate(cats) if c in vals and np.isfinite(vals[c])]
        if pts:
            a = np.array(pts)
            ax.plot(a[:, 0], a[:, 1], "o", color=f"C{k % 10}", label=series)
    ax.set_xticks(xs, cats, rotation=20, ha="right")
    ax.set_ylabel(metric)
    if log:
        ax.set_yscale("log")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small")
    fig.tight_layout()
    return _png(fig)


def plot_boxes(panels: dict[str, dict[str, list[float]]], title: str) -> bytes:
    """Box plots, one panel per metric (``panels[metric][series]`` = values across runs)."""
    n = max(len(panels), 1)
    cols = min(n, 2)
    rows = (n + cols - 1) // cols
    fig = _figure(5.0 * cols, 3.8 * rows)
    for k, (metric, groups) in enumerate(panels.items()):
        ax = fig.add_subplot(rows, cols, k + 1)
        names = [g for g, v in groups.items() if len(v)]
        if names:
            ax.boxplot([groups[g] for g in names], tick_labels=names)
        ax.set_title(metric, fontsize="medium")
        ax.tick_params(axis="x", labelrotation=20)
        ax.grid(True, alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    return _png(fig)
