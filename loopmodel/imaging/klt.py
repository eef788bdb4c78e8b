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


def shared_tracks(pts_prev: F64, pts_guess: F64, radius_px: float, motion_px: float) -> NDArray[np.int64]:
    """For each point (N, 2 pixels, predicted at ``pts_guess``) the point whose KLT it takes: itself or a twin.

    Two points share a track when their positions differ by at most ``radius_px`` and their
    predicted displacements by at most ``motion_px`` in each coordinate (the same patch, moving alike:
    one search from either start finds the same place): the first of them is
    tracked, each later one moves with the first it is near (:func:`track_klt` ``share``).
    ``radius_px`` 0: every point its own.
    """
    n = pts_prev.shape[0]
    if radius_px <= 0 or n < 2:
        return np.arange(n, dtype=np.int64)
    from loopmodel.imaging._klt_kernels import share_tracks

    x = np.ascontiguousarray(np.column_stack([pts_prev, pts_guess - pts_prev]), dtype=np.float64)
    fin = np.flatnonzero(np.isfinite(x).all(axis=1))
    order = fin[np.argsort(x[fin, 0], kind="stable")]
    return np.asarray(share_tracks(x, order, float(radius_px), float(motion_px)), dtype=np.int64)


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
    share: NDArray[np.int64] | None = None,
) -> tuple[F64, NDArray[np.bool_], F64]:
    """Track ``pts_prev`` (N, 2 pixels) from ``prev`` to ``cur``.

    ``pts_guess`` (N, 2) is the predicted position in ``cur`` (e.g. from a motion model) and
    starts the search. Returns the tracked points, a validity mask (tracked both ways,
    forward-backward error below ``fb_threshold_px``, inside the image) and the
    forward-backward error (pixels; inf where the forward search failed). ``share``
    (:func:`shared_tracks`): point i moves as point ``share[i]``, searched once.
    """
    if share is not None and pts_guess is not None and share.shape[0] and (share != np.arange(share.shape[0])).any():
        own = np.flatnonzero(share == np.arange(share.shape[0]))
        uv, ok, fb = track_klt(
            prev, cur, pts_prev[own], pts_guess[own], window_px, levels, fb_threshold_px, iterations, None
        )
        at = np.empty(share.shape[0], dtype=np.int64)
        at[own] = np.arange(own.size)
        j = at[share]
        fwd = uv[j] + (pts_prev - pts_prev[share])
        return fwd, _inside(fwd, ok[j], image_size), fb[j]
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
    return fwd, _inside(fwd, ok, image_size), fb


def _inside(uv: F64, ok: NDArray[np.bool_], image_size: tuple[int, int] | None) -> NDArray[np.bool_]:
    """``ok`` and ``uv`` (N, 2 pixels) inside an image of ``image_size`` (width, height; None: any)."""
    if image_size is None:
        return ok
    w, h = image_size
    return ok & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
