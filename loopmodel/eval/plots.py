"""Evaluation pictures (matplotlib, Agg canvas, no pyplot state).

As evo draws them: the paths in a chosen plane (``xy``, ``xz``, ``yz``) or in 3-D (``xyz``) with
loop closures; x, y, z and roll, pitch, yaw over time; ATE and RPE over time; the path coloured by
its ATE. Lengths in the report's unit (mm or m, :class:`loopmodel.display.LengthUnit`). Each
function returns PNG bytes.
"""

from __future__ import annotations

import io
import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.display import LengthUnit, M

F64 = NDArray[np.float64]
AXIS_NAMES = ("x", "y", "z")
PLOT_MODES = ("xy", "xz", "yz", "xyz")


@dataclass
class PlotTrack:
    """One trajectory to draw: poses (N x 4 x 4, metres, ground-truth frame), times (s), ATE (m)."""

    label: str
    poses: F64
    times_s: F64
    errors_m: F64 | None = None
    style: str = "-"
    color: str = "C0"
    rpe_times_s: F64 | None = None
    rpe_m: F64 | None = None
    rpe_deg: F64 | None = None

    @property
    def positions_m(self) -> F64:
        """Positions (N x 3, metres)."""
        return self.poses[:, :3, 3]


@dataclass
class PlotClosure:
    """A loop closure to mark: time (s), query position and optional matched position (metres)."""

    time_s: float
    query_m: F64
    match_m: F64 | None = None


def resolve_plot_mode(mode: str, reference_poses: F64) -> str:
    """The plot plane of ``mode``; ``auto``: ``xz`` for camera-frame ground truth, else ``xy``.

    Camera-frame ground truth (KITTI poses, a run's own world) starts at the identity: y points
    down and z forward, so the ground plane is xz (evo's ``--plot_mode xz`` for KITTI). Other ground
    truth (EuRoC, TUM motion capture, simulated worlds) has z up: the ground plane is xy.
    """
    if mode != "auto":
        if mode not in PLOT_MODES:
            raise ValueError(f"plot mode must be auto or one of {', '.join(PLOT_MODES)}, got '{mode}'")
        return mode
    if len(reference_poses) and np.allclose(reference_poses[0], np.eye(4), atol=1e-6):
        return "xz"
    return "xy"


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


def _axes(mode: str) -> list[int]:
    return ["xyz".index(c) for c in mode]


def _path_axes(fig, mode: str, unit: LengthUnit):  # type: ignore[no-untyped-def]
    """A 2-D axes (x/y labels of the plane) or a 3-D one for ``xyz``."""
    idx = _axes(mode)
    if len(idx) == 3:
        from mpl_toolkits.mplot3d import Axes3D  # noqa: F401  (registers the 3-D projection)

        ax = fig.add_subplot(111, projection="3d")
        ax.set_zlabel(f"z [{unit.symbol}]")
    else:
        ax = fig.add_subplot(111)
        ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"{AXIS_NAMES[idx[0]]} [{unit.symbol}]")
    ax.set_ylabel(f"{AXIS_NAMES[idx[1]]} [{unit.symbol}]")
    return ax


def _coords(p: F64, mode: str, unit: LengthUnit) -> list[F64]:
    """The plotted coordinates of positions (N x 3 or 3, metres) in the display unit."""
    q = np.asarray(p, dtype=np.float64) * unit.per_m
    return [q[..., i] for i in _axes(mode)]


def plot_paths(
    reference_m: F64,
    tracks: list[PlotTrack],
    closures: list[PlotClosure],
    title: str,
    mode: str = "xy",
    unit: LengthUnit = M,
) -> bytes:
    """Ground truth and trajectories in the plane ``mode`` (or 3-D), loop closures marked."""
    fig = _figure()
    ax = _path_axes(fig, mode, unit)
    ax.plot(*_coords(reference_m, mode, unit), "-", color="k", lw=1.2, label="ground truth")
    for tr in tracks:
        ax.plot(*_coords(tr.positions_m, mode, unit), tr.style, color=tr.color, lw=1.0, label=tr.label)
    for k, c in enumerate(closures):
        if c.match_m is not None:
            pair = np.stack([c.query_m, c.match_m])
            ax.plot(*_coords(pair, mode, unit), "-", color="red", lw=0.8, alpha=0.7)
        q = [np.atleast_1d(v) for v in _coords(c.query_m, mode, unit)]
        ax.plot(*q, "*", color="red", ms=10, label="loop closure" if k == 0 else None)
    start = [np.atleast_1d(v) for v in _coords(reference_m[0], mode, unit)]
    ax.plot(*start, "o", color="g", ms=6, label="start")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _png(fig)


def plot_error_over_time(
    tracks: list[PlotTrack], closures: list[PlotClosure], title: str, unit: LengthUnit = M
) -> bytes:
    """Translational ATE of each trajectory over time, loop closures as vertical lines."""
    fig = _figure(8.0, 4.0)
    ax = fig.add_subplot(111)
    for tr in tracks:
        if tr.errors_m is not None:
            ax.plot(tr.times_s, tr.errors_m * unit.per_m, tr.style, color=tr.color, lw=1.0, label=tr.label)
    for k, c in enumerate(closures):
        ax.axvline(c.time_s, color="red", lw=0.8, alpha=0.6, label="loop closure" if k == 0 else None)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"ATE [{unit.symbol}]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _png(fig)


def plot_rpe_over_time(tracks: list[PlotTrack], closures: list[PlotClosure], title: str, unit: LengthUnit = M) -> bytes:
    """RPE between consecutive poses over time: translation (top) and rotation (bottom)."""
    fig = _figure(8.0, 5.0)
    ax_t = fig.add_subplot(211)
    ax_r = fig.add_subplot(212, sharex=ax_t)
    for tr in tracks:
        if tr.rpe_times_s is None or tr.rpe_m is None or tr.rpe_deg is None:
            continue
        ax_t.plot(tr.rpe_times_s, tr.rpe_m * unit.per_m, tr.style, color=tr.color, lw=1.0, label=tr.label)
        ax_r.plot(tr.rpe_times_s, tr.rpe_deg, tr.style, color=tr.color, lw=1.0)
    for k, c in enumerate(closures):
        for ax in (ax_t, ax_r):
            ax.axvline(
                c.time_s, color="red", lw=0.8, alpha=0.6, label="loop closure" if k == 0 and ax is ax_t else None
            )
    ax_t.set_ylabel(f"RPE translation [{unit.symbol}]")
    ax_r.set_ylabel("RPE rotation [°]")
    ax_r.set_xlabel("time [s]")
    for ax in (ax_t, ax_r):
        ax.grid(True, alpha=0.3)
    ax_t.legend(loc="best", fontsize=8)
    ax_t.set_title(title, fontsize=10)
    fig.tight_layout()
    return _png(fig)


def roll_pitch_yaw_deg(poses: F64) -> F64:
    """Roll, pitch, yaw (degrees, N x 3) of poses: static x-y-z Euler angles as evo's ``sxyz``, unwrapped."""
    from scipy.spatial.transform import Rotation

    if len(poses) == 0:
        return np.zeros((0, 3))
    with warnings.catch_warnings():  # at pitch +-90 deg yaw is set to 0, as evo does: no warning per report
        warnings.simplefilter("ignore", UserWarning)
        rpy = Rotation.from_matrix(poses[:, :3, :3]).as_euler("xyz")
    return np.degrees(np.unwrap(rpy, axis=0))


def plot_xyz_rpy(
    reference: PlotTrack, tracks: list[PlotTrack], closures: list[PlotClosure], title: str, unit: LengthUnit = M
) -> bytes:
    """x, y, z (left) and roll, pitch, yaw (right) of ground truth and trajectories over time."""
    fig = _figure(10.0, 7.0)
    rpy = {id(t): roll_pitch_yaw_deg(t.poses) for t in (reference, *tracks)}
    for row in range(3):
        ax_p = fig.add_subplot(3, 2, 2 * row + 1)
        ax_a = fig.add_subplot(3, 2, 2 * row + 2)
        for t in (reference, *tracks):
            style, color = ("-", "k") if t is reference else (t.style, t.color)
            ax_p.plot(t.times_s, t.positions_m[:, row] * unit.per_m, style, color=color, lw=1.0, label=t.label)
            ax_a.plot(t.times_s, rpy[id(t)][:, row], style, color=color, lw=1.0)
        for c in closures:
            for ax in (ax_p, ax_a):
                ax.axvline(c.time_s, color="red", lw=0.6, alpha=0.5)
        ax_p.set_ylabel(f"{AXIS_NAMES[row]} [{unit.symbol}]")
        ax_a.set_ylabel(f"{('roll', 'pitch', 'yaw')[row]} [°]")
        for ax in (ax_p, ax_a):
            ax.grid(True, alpha=0.3)
            if row == 2:
                ax.set_xlabel("time [s]")
        if row == 0:
            ax_p.legend(loc="best", fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _png(fig)


def plot_error_colored(reference_m: F64, track: PlotTrack, title: str, mode: str = "xy", unit: LengthUnit = M) -> bytes:
    """One trajectory in the plane ``mode`` (or 3-D), coloured by its translational ATE."""
    fig = _figure()
    ax = _path_axes(fig, mode, unit)
    ax.plot(*_coords(reference_m, mode, unit), "--", color="0.6", lw=0.8, label="ground truth")
    pts = np.stack(_coords(track.positions_m, mode, unit), axis=1)
    err = (track.errors_m if track.errors_m is not None else np.zeros(len(pts))) * unit.per_m
    if len(pts) >= 2:
        segs = np.stack([pts[:-1], pts[1:]], axis=1)
        if pts.shape[1] == 3:
            from mpl_toolkits.mplot3d.art3d import Line3DCollection

            lc = Line3DCollection(list(segs), cmap="jet", linewidths=2.0)
        else:
            from matplotlib.collections import LineCollection

            lc = LineCollection(list(segs), cmap="jet", linewidths=2.0)
        lc.set_array(0.5 * (err[:-1] + err[1:]))
        ax.add_collection(lc)
        cb = fig.colorbar(lc, ax=ax)
        cb.set_label(f"ATE [{unit.symbol}]")
    ax.autoscale_view()
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
