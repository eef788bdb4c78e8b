"""Pyramidal Lucas-Kanade tracking with a forward-backward check and a predicted start."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
Pyramid = NDArray[np.uint8]


def build_pyramid(img: NDArray[np.uint8], window_px: int, levels: int) -> Pyramid:
    """What :func:`track_klt` takes for an image.

    OpenCV 5's Python binding of ``calcOpticalFlowPyrLK`` accepts no prebuilt pyramid, so this is
    the image itself (the pyramid is built inside each call).
    """
    del window_px, levels
    return img


def track_klt(
    prev: Pyramid,
    cur: Pyramid,
    pts_prev: F64,
    pts_guess: F64 | None,
    window_px: int,
    levels: int,
    fb_threshold_px: float,
    iterations: int = 20,
    image_size: tuple[int, int] | None = None,
) -> tuple[F64, NDArray[np.bool_], F64]:
    """Track ``pts_prev`` (N, 2 pixels) from ``prev`` to ``cur``.

    ``pts_guess`` (N, 2) is the predicted position in ``cur`` (e.g. from a motion model) and
    starts the search. Returns the tracked points, a validity mask (tracked both ways,
    forward-backward error below ``fb_threshold_px``, inside the image) and the
    forward-backward error (pixels; inf where the forward search failed).
    """
    n = pts_prev.shape[0]
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 0.01)
    p0 = pts_prev.astype(np.float32).reshape(-1, 1, 2)
    if pts_guess is not None:
        p1 = pts_guess.astype(np.float32).reshape(-1, 1, 2).copy()
    else:
        p1 = p0.copy()
    flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    win = (window_px, window_px)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(
        prev, cur, p0, p1, winSize=win, maxLevel=levels, criteria=criteria, flags=flags
    )
    # the backward search starts at the forward result itself (an independent search;
    # starting it from the prediction would bias the check towards success); only for the points
    # found forward (each point is searched on its own: the same values as searching all)
    found = np.flatnonzero(st1.ravel() == 1)
    fwd = p1.reshape(-1, 2).astype(float)
    fb = np.full(n, np.inf)
    ok = np.zeros(n, dtype=bool)
    if found.size:
        p1f = np.ascontiguousarray(p1[found])
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(
            cur,
            prev,
            p1f,
            p1f.copy(),
            winSize=win,
            maxLevel=levels,
            criteria=criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        fb[found] = np.linalg.norm(p0b.reshape(-1, 2) - pts_prev[found], axis=1)
        ok[found] = st2.ravel() == 1
    ok &= (fb < fb_threshold_px) & np.isfinite(fb)
    if image_size is not None:
        w, h = image_size
        ok &= (fwd[:, 0] >= 0) & (fwd[:, 0] <= w - 1) & (fwd[:, 1] >= 0) & (fwd[:, 1] <= h - 1)
    return fwd, ok, fb
