"""The depth observer on real image sequences.

KLT tracks on the left camera, two-view signals from the essential matrix, scale from one stereo
depth, and a comparison of every recovered depth with the stereo depth of the same feature.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import InputError
from loopmodel.imaging.klt import track_klt
from loopmodel.imaging.rectify import to_grey
from loopmodel.observers.depth_observer import DepthObserver, ObserverConfig, ViewMeasurement
from loopmodel.observers.homography import signals_from_essential
from loopmodel.types import StereoCalibration, StereoFrame

F64 = NDArray[np.float64]
KLT_WINDOW_PX, KLT_LEVELS = 21, 4


def klt_fb(
    prev: NDArray[np.uint8], cur: NDArray[np.uint8], pts: F64, fb_px: float = 0.5
) -> tuple[F64, NDArray[np.bool_]]:
    """Track points from ``prev`` to ``cur`` with the front end's pyramidal LK.

    With its forward-backward check (no motion prediction: the search starts at the same pixel).
    """
    tracked, ok, _fb = track_klt(prev, cur, pts, None, KLT_WINDOW_PX, KLT_LEVELS, fb_px, iterations=30)
    return tracked, ok


def stereo_depths(left: NDArray[np.uint8], right: NDArray[np.uint8], pts: F64, cal: StereoCalibration) -> F64:
    """Depth (m) of left-image points by LK search in the rectified right image.

    NaN where the match fails the row, disparity or forward-backward checks.
    """
    if not cal.rectified:
        raise InputError("stereo depth", "needs a rectified stereo pair")
    p1, ok = klt_fb(left, right, pts, fb_px=0.5)
    disp = pts[:, 0] - p1[:, 0]
    ok &= (np.abs(p1[:, 1] - pts[:, 1]) < 1.0) & (disp > 1.0)
    z = np.full(len(pts), np.nan)
    z[ok] = cal.fx_px * cal.baseline_m / disp[ok]
    return z


@dataclass
class WindowResult:
    """Depths of one reference frame's features: observer vs stereo."""

    start_index: int
    depth_observer_m: F64
    depth_stereo_m: F64
    excited: bool
    lambda_history: list[F64] = field(default_factory=list)

    @property
    def rel_err(self) -> F64:
        """Relative errors of the features with a valid stereo depth (excluding the scale feature)."""
        ok = np.isfinite(self.depth_stereo_m) & np.isfinite(self.depth_observer_m)
        ok[0] = False
        return np.abs(self.depth_observer_m[ok] - self.depth_stereo_m[ok]) / self.depth_stereo_m[ok]


def observe_window(
    frames: list[StereoFrame],
    cal: StereoCalibration,
    config: ObserverConfig | None = None,
    max_features: int = 400,
    max_depth_m: float = 40.0,
) -> WindowResult:
    """Run the observer over consecutive frames.

    The first is the reference view. Feature 0 (the one whose stereo depth gives the scale) is the
    best-matched near feature.
    """
    if len(frames) < 3:
        raise InputError("depth observer", "needs at least 3 frames in a window")
    ref_left = to_grey(frames[0].left)
    corners = cv2.goodFeaturesToTrack(ref_left, max_features, 0.005, 10, blockSize=7)
    if corners is None or len(corners) < 12:
        raise InputError("depth observer", "too few corners in the reference frame")
    pts = corners.reshape(-1, 2).astype(float)
    z_stereo = stereo_depths(ref_left, to_grey(frames[0].right), pts, cal)
    # track through the window, keep features seen in every frame
    tracks = [pts]
    alive = np.ones(len(pts), bool)
    prev = ref_left
    for f in frames[1:]:
        cur = to_grey(f.left)
        nxt, ok = klt_fb(prev, cur, tracks[-1])
        alive &= ok
        tracks.append(nxt)
        prev = cur
    cand = np.flatnonzero(alive & np.isfinite(z_stereo) & (z_stereo < max_depth_m))
    if cand.size < 12:
        raise InputError("depth observer", f"only {cand.size} features tracked through the window")
    A = cal.K_left
    # two-view signals per frame; features that are essential-matrix outliers in any frame
    # (independently moving objects, bad tracks) are dropped before the observer starts
    signals = [signals_from_essential(A, tracks[0][cand], tracks[k][cand]) for k in range(1, len(frames))]
    good = np.logical_and.reduce([sg.inliers for sg in signals])
    order = cand[good]
    if order.size < 12:
        raise InputError("depth observer", f"only {order.size} features consistent with rigid motion")
    centre = np.array([cal.K_left[0, 2], cal.K_left[1, 2]])
    score = np.linalg.norm(pts[order] - centre, axis=1) / 100.0 + z_stereo[order] / 10.0
    first_pos = int(np.argmin(score))  # scale feature: near the image centre and close (precise disparity)
    sel = np.concatenate([[first_pos], np.delete(np.arange(order.size), first_pos)])
    idx = order[sel]
    local = np.flatnonzero(good)[sel]  # positions of idx within cand (and the signals)
    obs = DepthObserver(A, tracks[0][idx], config)
    t0 = frames[0].timestamp_ns
    for k, f in enumerate(frames):
        if k == 0:
            R, alpha = np.eye(3), np.ones(len(idx))
        else:
            R, alpha = signals[k - 1].cur_from_ref_rot, np.clip(signals[k - 1].alpha[local], 1e-3, None)
        obs.feed(ViewMeasurement((f.timestamp_ns - t0) * 1e-9, tracks[k][idx], alpha, R))
    first = idx[0]
    depth = obs.points_from_reference_depth(float(z_stereo[first]))[:, 2]
    depth[~(obs.lambda_hat > 0)] = np.nan  # an estimate that left the physical range is no depth
    return WindowResult(int(frames[0].index), depth, z_stereo[idx], obs.excited, obs.history.lambda_hat)


def observe_sequence(
    frames: Iterable[StereoFrame],
    cal: StereoCalibration,
    window: int = 6,
    stride: int = 10,
    config: ObserverConfig | None = None,
) -> tuple[list[WindowResult], list[str]]:
    """Windows of ``window`` frames starting every ``stride`` frames.

    Stride >= window; frames stream, at most one window is held. Returns the results and the windows
    skipped, with why.
    """
    if stride < window:
        raise InputError("depth observer", f"stride ({stride}) must be >= window ({window})")
    results: list[WindowResult] = []
    skipped: list[str] = []
    buf: list[StereoFrame] = []
    for i, f in enumerate(frames):
        if i % stride == 0:
            buf = []
        if len(buf) < window:
            buf.append(f)
            if len(buf) == window:
                try:
                    results.append(observe_window(buf, cal, config))
                except InputError as exc:
                    skipped.append(f"frame {buf[0].index}: {exc.problem}")
    return results, skipped
