"""Figures of the calibrations: per-view reprojection errors and the image area the corners cover."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from loopmodel.calibration.stereo import StereoCalibrationResult
from loopmodel.io.atomic import save_figure_atomic


def plot_stereo_calibration(result: StereoCalibrationResult, path: str | Path) -> Path:
    """Per-view RMS bar chart and corner coverage over each image, written as PNG.

    Bar chart of the per-view RMS (pixels, left and right) and the corners of all views over each
    image (coverage).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    names = [Path(v.left_path).stem for v in result.views]
    x = np.arange(len(names))
    axes[0].bar(x - 0.2, [v.rms_left_px for v in result.views], 0.4, label="left")
    axes[0].bar(x + 0.2, [v.rms_right_px for v in result.views], 0.4, label="right")
    axes[0].axhline(result.rms_left_px, color="C0", ls="--", lw=0.8)
    axes[0].axhline(result.rms_right_px, color="C1", ls="--", lw=0.8)
    axes[0].set_xticks(x, names, rotation=60, fontsize=7)
    axes[0].set_ylabel("reprojection RMS (px)")
    axes[0].set_title(f"per view (stereo RMS {result.rms_stereo_px:.3f} px)")
    axes[0].legend()
    w, h = result.calibration.image_size
    for ax, corners, name in ((axes[1], result.corners_left, "left"), (axes[2], result.corners_right, "right")):
        for k, c in enumerate(corners):
            ax.plot(c[:, 0], c[:, 1], ".", ms=2, color=plt.cm.tab20(k % 20))
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: corner coverage ({len(corners)} views)")
    fig.tight_layout()
    return save_figure_atomic(path, fig)
