"""Keyframe features: grid-bucketed Shi-Tomasi corners in the rectified left image, row
search in the rectified right image (normalised correlation, sub-pixel parabola, left-right
consistency, vertical offset check) and triangulation in the left camera frame."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.config import FrontendConfig

F64 = NDArray[np.float64]


def detect_corners(
    img: NDArray[np.uint8],
    max_features: int,
    grid: tuple[int, int],
    quality: float,
    min_distance_px: float,
    border_px: int,
) -> F64:
    """(N, 2) corner pixels (u, v), spread over a ``grid`` = (cols, rows) of cells with an
    equal quota each; the Shi-Tomasi quality level is relative to each cell."""
    h, w = img.shape[:2]
    cols, rows = grid
    quota = max(1, int(np.ceil(max_features / (cols * rows))))
    xs = np.linspace(border_px, w - border_px, cols + 1).astype(int)
    ys = np.linspace(border_px, h - border_px, rows + 1).astype(int)
    out: list[F64] = []
    for r in range(rows):
        for c in range(cols):
            x0, x1, y0, y1 = xs[c], xs[c + 1], ys[r], ys[r + 1]
            if x1 - x0 < 4 or y1 - y0 < 4:
                continue
            pts = cv2.goodFeaturesToTrack(
                img[y0:y1, x0:x1], quota, quality, min_distance_px, blockSize=5
            )
            if pts is not None:
                p = pts.reshape(-1, 2).astype(float)
                p[:, 0] += x0
                p[:, 1] += y0
                out.append(p)
    if not out:
        return np.zeros((0, 2))
    return np.vstack(out)


@dataclass
class StereoMatches:
    """Matched features: left pixel (u, v), right u, disparity (pixels) and ZNCC score."""

    uv_left: F64
    u_right: F64
    v_right: F64
    disparity: F64
    score: F64


def _parabola_peak(a: float, b: float, c: float) -> float:
    den = a - 2.0 * b + c
    if den >= 0:  # not a maximum
        return 0.0
    return float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))


def match_stereo(
    left: NDArray[np.uint8], right: NDArray[np.uint8], uv_left: F64, cfg: FrontendConfig
) -> StereoMatches:
    """Find the left corners in the rectified right image along their row (±1 row).

    Keeps a match when its ZNCC exceeds ``min_zncc``, the best row is within
    ``max_row_error_px``, the disparity is within range and searching the right patch back
    along the left row returns to the corner within ``lr_tolerance_px``.
    """
    h, w = left.shape[:2]
    half = cfg.patch_px // 2
    dmax = int(np.ceil(cfg.max_disparity_px))
    keep_uv, keep_ur, keep_vr, keep_d, keep_s = [], [], [], [], []
    lf = left
    rf = right
    method = cv2.TM_CCOEFF_NORMED
    for u_f, v_f in uv_left:
        u, v = int(round(u_f)), int(round(v_f))
        if v - half - 1 < 0 or v + half + 2 > h or u - half < 0 or u + half + 1 > w:
            continue
        tpl = lf[v - half : v + half + 1, u - half : u + half + 1]
        x_lo = max(half, u - dmax)
        if u - x_lo < 1:
            continue
        strip = rf[v - half - 1 : v + half + 2, x_lo - half : u + half + 1]
        res = cv2.matchTemplate(strip, tpl, method)  # (3, u - x_lo + 1); column k <-> x_lo + k
        row, col = np.unravel_index(int(np.argmax(res)), res.shape)
        best = float(res[row, col])
        if best < cfg.min_zncc or not np.isfinite(best):
            continue
        # sub-pixel along the row and across rows
        line = res[row]
        du = (
            _parabola_peak(line[col - 1], line[col], line[col + 1])
            if 0 < col < line.size - 1
            else 0.0
        )
        dv = _parabola_peak(res[0, col], res[1, col], res[2, col]) if row == 1 else float(row - 1)
        if abs(dv) > cfg.max_row_error_px:
            continue
        ur = x_lo + col + du
        d = u - ur
        if d < cfg.min_disparity_px or d > cfg.max_disparity_px:
            continue
        # left-right consistency: the right patch searched along the left row
        xr = x_lo + col
        rtpl = rf[v + row - 1 - half : v + row - 1 + half + 2 - 1, xr - half : xr + half + 1]
        x_hi = min(w - half - 1, xr + dmax)
        lstrip = lf[v + row - 1 - half : v + row - 1 + half + 1, xr - half : x_hi + half + 1]
        if lstrip.shape[1] < rtpl.shape[1] or rtpl.shape != tpl.shape:
            continue
        back = cv2.matchTemplate(lstrip, rtpl, method).ravel()
        bcol = int(np.argmax(back))
        if abs((xr + bcol) - u) > cfg.lr_tolerance_px:
            continue
        keep_uv.append((u, v))
        keep_ur.append(ur)
        keep_vr.append(v + dv)
        keep_d.append(d)
        keep_s.append(best)
    n = len(keep_uv)
    return StereoMatches(
        np.asarray(keep_uv, dtype=float).reshape(n, 2),
        np.asarray(keep_ur, dtype=float),
        np.asarray(keep_vr, dtype=float),
        np.asarray(keep_d, dtype=float),
        np.asarray(keep_s, dtype=float),
    )


def triangulate_rectified(uv_left: F64, disparity: F64, K: F64, baseline_m: float) -> F64:
    """(N, 3) points (metres) in the rectified left camera frame from left pixels and
    disparities (pixels)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Z = fx * baseline_m / disparity
    X = (uv_left[:, 0] - cx) * Z / fx
    Y = (uv_left[:, 1] - cy) * Z / fy
    return np.column_stack([X, Y, Z])
