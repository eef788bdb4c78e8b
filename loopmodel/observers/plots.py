"""Figures of the depth observer (matplotlib, Agg).

Convergence of the depth ratios and of the depth errors (seed 003 Fig. 2-3), and observer-vs-stereo
depths on real tracks.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from loopmodel.observers.real_tracks import WindowResult  # noqa: E402
from loopmodel.observers.simulation import SimulationResult  # noqa: E402


def convergence_figures(res: SimulationResult) -> tuple[Figure, Figure]:
    """(lambda_hat over time with the true values dashed, depth error over time)."""
    f1, ax = plt.subplots(figsize=(7, 4))
    for i in range(res.lambda_hat.shape[1]):
        (line,) = ax.plot(res.t_s, res.lambda_hat[:, i], lw=1)
        ax.axhline(res.lambda_true[i], color=line.get_color(), ls="--", lw=0.6)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("depth ratio estimate  z*_1 / z*_i")
    ax.set_title("Convergence of the depth-ratio estimates (dashed: true)")
    f1.tight_layout()
    f2, ax2 = plt.subplots(figsize=(7, 4))
    z1 = res.points_ref_m[0, 2]
    depth_err = z1 / res.lambda_hat - res.points_ref_m[:, 2][None, :]
    ax2.plot(res.t_s, depth_err, lw=1)
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("depth error (m)")
    ax2.set_title("Depth error with z*_1 known")
    f2.tight_layout()
    return f1, f2


def stereo_comparison_figure(results: list[WindowResult]) -> Figure:
    """Observer depth against stereo depth for every compared feature."""
    fig, ax = plt.subplots(figsize=(5, 5))
    for r in results:
        ok = np.isfinite(r.depth_stereo_m) & np.isfinite(r.depth_observer_m)
        ax.scatter(r.depth_stereo_m[ok], r.depth_observer_m[ok], s=8, label=f"ref frame {r.start_index}")
    lim = [0, max(40.0, float(np.nanmax([np.nanmax(r.depth_stereo_m) for r in results])) if results else 40.0)]
    ax.plot(lim, lim, "k--", lw=0.8)
    ax.set_xlim(lim[0], lim[1])
    ax.set_ylim(lim[0], lim[1])
    ax.set_xlabel("stereo depth (m)")
    ax.set_ylabel("observer depth (m)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig
