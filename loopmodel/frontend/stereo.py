"""Keyframe features.

Grid-bucketed Shi-Tomasi corners in the rectified left image, row search in the rectified right
image (normalised correlation, sub-pixel parabola, left-right consistency, vertical offset check)
and triangulation in the left camera frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.config import FrontendConfig
from loopmodel.frontend.beside import Beside

F64 = NDArray[np.float64]


def detect_corners(
    img: NDArray[np.uint8],
    max_features: int,
    grid: tuple[int, int],
    quality: float,
    min_distance_px: float,
    border_px: int,
    half_resolution: bool = False,
) -> F64:
    """(N, 2) corner pixels (u, v), spread over a ``grid`` = (cols, rows) of cells with an equal quota each.

    The Shi-Tomasi quality level is relative to each cell. With ``half_resolution`` the corners are
    found in the half-size image (4x less work) and scaled to full-resolution pixels.
    """
    if half_resolution:
        small = cv2.pyrDown(img)
        pts = detect_corners(small, max_features, grid, quality, max(1.0, min_distance_px / 2),
                             (border_px + 1) // 2)
        return 2.0 * pts
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
    """Matched features.

    Left pixel (u, v, rounded to integers), right u and v (sub-pixel), disparity (pixels), ZNCC
    score, the index of each match in the input corners, and each disparity's standard deviation
    (pixels; from the residual and the row gradient of the sub-pixel fit, see :func:`refine_row_gradient`).
    """

    uv_left: F64
    u_right: F64
    v_right: F64
    disparity: F64
    score: F64
    index: NDArray[np.int64]
    sigma_px: F64 = field(default_factory=lambda: np.zeros(0))  # disparity standard deviation (px)


def _parabola_offsets(a: F64, b: F64, c: F64) -> F64:
    """Sub-sample offsets of the maxima of parabolas through (-1, a), (0, b), (1, c)."""
    den = a - 2.0 * b + c
    off = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    return np.clip(off, -0.5, 0.5)


#: floor of a match's disparity standard deviation (px): interpolation and rectification errors
MIN_DISPARITY_SIGMA_PX = 0.05


def refine_row_gradient(
    src: NDArray[np.uint8],
    dst: NDArray[np.uint8],
    pad: int,
    u: NDArray[np.int64],
    v: NDArray[np.int64],
    x0: F64,
    v_dst: NDArray[np.int64],
    half: int,
    iterations: int = 4,
) -> tuple[F64, F64]:
    """Sub-pixel column of the ``src`` template at integer (u, v) in row ``v_dst`` of ``dst``, from ``x0``.

    Gauss-Newton on the column shift (one-dimensional Lucas-Kanade) with a gain and an offset
    (the template's zero-mean copy scaled to the window): the window is interpolated linearly at
    each step, so the estimate is not drawn towards whole pixels as a parabola through three
    correlation scores is. Images are padded by ``pad`` pixels. Returns the column (pixels) and
    its standard deviation (pixels): the fit's residual RMS over the root of the summed squared
    row gradient, at least :data:`MIN_DISPARITY_SIGMA_PX`. Compiled, in float32
    (:mod:`loopmodel.frontend._stereo_kernels`).

    A match off its row by a fraction of a pixel (a rectification from an imperfect calibration)
    is measured here at the nearest whole row: its column takes a bias of the row offset times the
    patch's shear (the gradients' product over the squared column gradient);
    :func:`refine_2d_gradient` refines the row too.
    """
    if u.size:  # every window (and its +-1 columns, moving by at most 0.5 px a step) inside the padded images
        reach = half + 3 + iterations
        hs, ws = src.shape[:2]
        hd, wd = dst.shape[:2]
        x0a = np.asarray(x0, dtype=float)
        ok = (v.min() + pad - half >= 0) and (v.max() + pad + half < hs) and (u.min() + pad - half >= 0)
        ok = ok and (u.max() + pad + half < ws) and (v_dst.min() + pad - half >= 0) and (v_dst.max() + pad + half < hd)
        ok = ok and bool(np.all(np.isfinite(x0a))) and (x0a.min() + pad - reach >= 0) and (x0a.max() + pad + reach < wd)
        if not ok:
            raise ValueError("stereo refinement: a window reaches beyond the padded image")
    from loopmodel.frontend._stereo_kernels import row_gradient  # numba: imported when first needed

    x, sigma = row_gradient(
        np.ascontiguousarray(src), np.ascontiguousarray(dst), pad, np.ascontiguousarray(u, dtype=np.int64),
        np.ascontiguousarray(v, dtype=np.int64), np.array(x0, dtype=float), np.ascontiguousarray(v_dst, dtype=np.int64),
        half, iterations, float(np.float32(MIN_DISPARITY_SIGMA_PX)),
    )
    return x, sigma


def refine_2d_gradient(
    src: NDArray[np.uint8],
    dst: NDArray[np.uint8],
    pad: int,
    u: NDArray[np.int64],
    v: NDArray[np.int64],
    x0: F64,
    y0: F64,
    half: int,
    iterations: int = 4,
) -> tuple[F64, F64, F64]:
    """Sub-pixel column and row of the ``src`` template at integer (u, v) in ``dst``, from ``(x0, y0)``.

    :func:`refine_row_gradient` in both directions: Gauss-Newton on the column and row shift with a
    gain and an offset, the window interpolated bilinearly. Returns the column, the row (pixels) and
    the column's standard deviation (pixels, at least :data:`MIN_DISPARITY_SIGMA_PX`). Compiled, in
    float32 (:func:`~loopmodel.frontend._stereo_kernels.gradient_2d`; the numpy form took 10 ms of a
    KITTI keyframe, the kernel 2 ms, the same columns to 1e-5 px).
    """
    if u.size:  # every window (and the rows / columns around it, moving by at most 0.5 px a step) inside
        reach = half + 3 + iterations
        hs, ws = src.shape[:2]
        hd, wd = dst.shape[:2]
        x0a, y0a = np.asarray(x0, dtype=float), np.asarray(y0, dtype=float)
        ok = (v.min() + pad - half >= 0) and (v.max() + pad + half < hs) and (u.min() + pad - half >= 0)
        ok = ok and (u.max() + pad + half < ws) and bool(np.all(np.isfinite(x0a)) and np.all(np.isfinite(y0a)))
        ok = ok and (x0a.min() + pad - reach >= 0) and (x0a.max() + pad + reach < wd)
        ok = ok and (y0a.min() + pad - reach >= 0) and (y0a.max() + pad + reach < hd)
        if not ok:
            raise ValueError("stereo refinement: a window reaches beyond the padded image")
    from loopmodel.frontend._stereo_kernels import gradient_2d  # numba: imported when first needed

    x, y, sigma = gradient_2d(
        np.ascontiguousarray(src), np.ascontiguousarray(dst), pad, np.ascontiguousarray(u, dtype=np.int64),
        np.ascontiguousarray(v, dtype=np.int64), np.array(x0, dtype=float), np.array(y0, dtype=float), half,
        iterations, MIN_DISPARITY_SIGMA_PX,
    )
    return x, y, sigma


def _zncc_scan(
    src: NDArray[np.uint8],
    dst: NDArray[np.uint8],
    pad: int,
    u: NDArray[np.int64],
    v: NDArray[np.int64],
    start: NDArray[np.int64],
    length: int,
    half: int,
    row_offsets: tuple[int, ...] = (0,),
) -> NDArray[np.float32]:
    """ZNCC of the (2*half+1)^2 template of ``src`` at integer (u, v) with windows of ``dst``.

    The windows of ``dst`` are centred at columns ``start + k`` (k < length) and rows ``v + r``.
    Images are padded by ``pad`` pixels. Returns (N, len(row_offsets), length). Compiled
    (:mod:`loopmodel.frontend._stereo_kernels`); every window must lie inside the padded images.
    """
    rows = np.asarray(row_offsets, dtype=np.int64)
    if u.size:
        hs, ws = src.shape[:2]
        hd, wd = dst.shape[:2]
        inside = (
            (v.min() + pad - half >= 0) and (v.max() + pad + half < hs) and (u.min() + pad - half >= 0)
            and (u.max() + pad + half < ws) and (v.min() + rows.min() + pad - half >= 0)
            and (v.max() + rows.max() + pad + half < hd) and (start.min() + pad - half >= 0)
            and (start.max() + length - 1 + pad + half < wd)
        )
        if not inside:
            raise ValueError("stereo scan: a window reaches beyond the padded image")
    from loopmodel.frontend._stereo_kernels import zncc_scan  # numba: imported when first needed

    def c64(a: NDArray[np.int64]) -> NDArray[np.int64]:
        return np.ascontiguousarray(a, dtype=np.int64)

    return zncc_scan(np.ascontiguousarray(src), np.ascontiguousarray(dst), pad, c64(u), c64(v), c64(start), length,
                     half, rows)


def _search_row(
    src_c: NDArray[np.uint8],
    dst_c: NDArray[np.uint8],
    src_f: NDArray[np.uint8],
    dst_f: NDArray[np.uint8],
    pad_c: int,
    pad_f: int,
    u: NDArray[np.int64],
    v: NDArray[np.int64],
    sign: int,
    dmax: int,
    half_f: int,
    width: int,
    rows: tuple[int, ...],
) -> tuple[NDArray[np.int64], NDArray[np.int64], F64, F64, F64, F64]:
    """Coarse-to-fine search over disparities 0..dmax along the row.

    Coarse (half resolution, 7x7) search in the direction ``sign`` (-1: right image, +1: left
    image), then a fine (full resolution) search of +-2 pixels and ``rows``. Returns integer column,
    row offset index, sub-pixel column and row offsets, the best score, and the coarse margin: the
    best coarse score minus the best coarse score more than 2 coarse columns (4 px) away from it
    (small where the row repeats: a fence, foliage).
    """
    half_c = 3
    uh, vh = (u + 1) // 2, (v + 1) // 2
    Dh = dmax // 2 + 2
    start_c = uh - Dh if sign < 0 else uh
    sc = _zncc_scan(src_c, dst_c, pad_c, uh, vh, start_c, Dh + 1, half_c)[:, 0]
    from loopmodel.frontend._stereo_kernels import row_peaks  # numba: imported when first needed

    # the best column inside the half-size image, and the best more than 2 columns from it
    k_c, margin = row_peaks(sc, np.ascontiguousarray(start_c, dtype=np.int64), half_c, width // 2 - 1 - half_c, 2)
    best_c = start_c + k_c
    start_f = 2 * best_c - 3
    L = 7
    # a fine row beyond the padding (no valid coarse column: every one of its columns is invalid
    # below, the match fails) is scanned at a column inside instead and scored -2 after
    wd = dst_f.shape[1]
    beyond = (start_f + pad_f - half_f < 0) | (start_f + L - 1 + pad_f + half_f >= wd)
    scan_f = np.where(beyond, half_f, start_f) if beyond.any() else start_f
    sf = _zncc_scan(src_f, dst_f, pad_f, u, v, scan_f, L, half_f, rows)
    col_f = start_f[:, None] + np.arange(L)
    bad_col = (col_f < half_f) | (col_f > width - 1 - half_f)
    bad_col |= (col_f - u[:, None]) * sign < 0  # wrong side of the source column
    bad_col |= beyond[:, None]
    sf[np.broadcast_to(bad_col[:, None, :], sf.shape)] = -2.0
    flat = np.argmax(sf.reshape(len(u), -1), axis=1)
    ri, k = np.divmod(flat, L)
    idx = np.arange(len(u))
    best = sf[idx, ri, k]
    kk = np.clip(k, 1, L - 2)
    du = _parabola_offsets(sf[idx, ri, kk - 1], sf[idx, ri, kk], sf[idx, ri, kk + 1])
    du = np.where((k == kk), du, 0.0)
    interior = (k > 0) & (k < L - 1)
    best = np.where(interior, best, -2.0)  # peak not bracketed: coarse search was off
    if len(rows) == 3:
        dv = _parabola_offsets(sf[idx, 0, k], sf[idx, 1, k], sf[idx, 2, k])
        dv = np.where(ri == 1, dv, np.asarray(rows)[ri].astype(float))
    else:
        dv = np.zeros(len(u))
    return start_f + k, ri, du, dv, best.astype(float), margin


def match_stereo(
    left: NDArray[np.uint8],
    right: NDArray[np.uint8],
    uv_left: F64,
    cfg: FrontendConfig,
    min_disparity_px: float | None = None,
) -> StereoMatches:
    """Find the left corners in the rectified right image along their row (+-1 row).

    Normalised cross-correlation, coarse to fine (half resolution over the whole disparity
    range, then full resolution), sub-pixel parabola fits in u and v, then (``stereo_subpixel:
    gradient``) the column refined by :func:`refine_row_gradient`. A match is kept when
    its ZNCC exceeds ``min_zncc``, its best coarse peak beats every other one along the row by
    ``stereo_uniqueness``, its vertical offset is within ``max_row_error_px`` (the
    reprojection check of a rectified pair), its disparity is within range, and searching
    the right patch back along the left row returns to the corner within
    ``lr_tolerance_px``. ``min_disparity_px`` replaces ``cfg.min_disparity_px`` (0: keep far
    points down to zero disparity).
    """
    h, w = left.shape[:2]
    half = cfg.patch_px // 2
    dmax = int(np.ceil(cfg.max_disparity_px))
    uv = np.rint(np.asarray(uv_left, dtype=float).reshape(-1, 2)).astype(np.int64)
    inside = (uv[:, 0] >= half) & (uv[:, 0] < w - half) & (uv[:, 1] >= half + 1)
    inside &= uv[:, 1] < h - half - 1
    uv = uv[inside]
    index = np.flatnonzero(inside)
    u, v = uv[:, 0], uv[:, 1]
    empty = StereoMatches(
        np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, np.int64), np.zeros(0)
    )
    if u.size == 0:
        return empty
    # the fine search and the sub-pixel refinement stay within a few pixels of valid columns (a row
    # whose coarse search found none is scored -2 in _search_row): a narrow border, not the whole
    # disparity range (issue 36: padding both full-size images by 178 px was 1 ms of a KITTI keyframe)
    pad_f = 2 * half + 8
    pad_c = dmax // 2 + 16
    lf = cv2.copyMakeBorder(left, pad_f, pad_f, pad_f, pad_f, cv2.BORDER_REPLICATE)
    rf = cv2.copyMakeBorder(right, pad_f, pad_f, pad_f, pad_f, cv2.BORDER_REPLICATE)
    lc = cv2.copyMakeBorder(cv2.pyrDown(left), pad_c, pad_c, pad_c, pad_c, cv2.BORDER_REPLICATE)
    rc = cv2.copyMakeBorder(cv2.pyrDown(right), pad_c, pad_c, pad_c, pad_c, cv2.BORDER_REPLICATE)
    col, ri, du, dv, score, margin = _search_row(lc, rc, lf, rf, pad_c, pad_f, u, v, -1, dmax, half, w,
                                         (-1, 0, 1))
    ur = col + du
    vr_int = v + np.asarray((-1, 0, 1))[ri]
    inside_r = (vr_int >= half + 1) & (vr_int < h - half - 1)
    sigma = np.full(u.shape[0], cfg.disparity_sigma_px)
    ok = (score >= cfg.min_zncc) & (np.abs(dv) <= cfg.max_row_error_px) & inside_r
    d_min = cfg.min_disparity_px if min_disparity_px is None else min_disparity_px
    ok &= (u - ur >= d_min - 1.0) & (u - ur <= cfg.max_disparity_px + 1.0)
    if cfg.stereo_subpixel == "gradient":  # only the candidates that passed the checks so far
        r = np.flatnonzero(ok)
        ur_g, sigma[r] = refine_row_gradient(lf, rf, pad_f, u[r], v[r], ur[r], vr_int[r], half, iterations=3)
        moved = np.abs(ur_g - ur[r]) <= 1.0  # a step beyond the bracketing pixels: no clear optimum
        ur[r] = np.where(moved, ur_g, ur[r])
        inside_r[r] &= moved
    elif cfg.stereo_subpixel == "gradient_2d":  # the row refined too: the column measured at its own row
        r = np.flatnonzero(ok)
        y0 = (v + dv)[r].astype(float)
        ur_g, vr_g, sigma[r] = refine_2d_gradient(lf, rf, pad_f, u[r], v[r], ur[r], y0, half, iterations=3)
        moved = (np.abs(ur_g - ur[r]) <= 1.0) & (np.abs(vr_g - y0) <= 1.0)
        ur[r] = np.where(moved, ur_g, ur[r])
        dv = dv.astype(float).copy()
        dv[r] = np.where(moved, vr_g - v[r], dv[r])
        inside_r[r] &= moved
        ok &= np.abs(dv) <= cfg.max_row_error_px
    disp = u - ur
    ok &= (disp >= d_min) & (disp <= cfg.max_disparity_px)
    if cfg.stereo_uniqueness > 0:  # best and second-best peaks along the row too close: ambiguous
        ok &= margin >= cfg.stereo_uniqueness
    # left-right consistency: the right patch (at its integer match) searched in the left row
    ok &= inside_r
    sel = np.flatnonzero(ok)
    if sel.size:
        bcol, _bri, bdu, _bdv, bscore, _bm = _search_row(
            rc, lc, rf, lf, pad_c, pad_f, col[sel], vr_int[sel], +1, dmax, half, w, (0,)
        )
        back_ok = (np.abs(bcol + bdu - u[sel]) <= cfg.lr_tolerance_px) & (bscore >= cfg.min_zncc)
        ok[sel] = back_ok
    return StereoMatches(
        uv[ok].astype(float), ur[ok], (v + dv)[ok], disp[ok], score[ok], index[ok], sigma[ok]
    )


def match_stereo_split(
    left: NDArray[np.uint8],
    right: NDArray[np.uint8],
    uv_left: F64,
    cfg: FrontendConfig,
    min_disparity_px: float | None = None,
    threads: int = 1,
) -> StereoMatches:
    """:func:`match_stereo` with the corners ``uv_left`` (N, 2) split over ``threads`` threads.

    Every corner is matched on its own, so the matches are the same; the numpy and OpenCV calls
    release the GIL on their large arrays, so the parts run on both cores (issue 33).
    """
    uv = np.asarray(uv_left, dtype=float).reshape(-1, 2)
    parts = [p for p in np.array_split(np.arange(uv.shape[0]), max(threads, 1)) if p.size]
    if len(parts) <= 1:
        return match_stereo(left, right, uv, cfg, min_disparity_px)
    beside = [Beside(True, match_stereo, left, right, uv[p], cfg, min_disparity_px) for p in parts[1:]]
    done = [match_stereo(left, right, uv[parts[0]], cfg, min_disparity_px)] + [b.result() for b in beside]
    return StereoMatches(
        np.vstack([m.uv_left for m in done]),
        np.concatenate([m.u_right for m in done]),
        np.concatenate([m.v_right for m in done]),
        np.concatenate([m.disparity for m in done]),
        np.concatenate([m.score for m in done]),
        np.concatenate([p[m.index] for p, m in zip(parts, done, strict=True)]),
        np.concatenate([m.sigma_px for m in done]),
    )


def spread_subset(
    uv: F64,
    score: F64,
    candidates: NDArray[np.bool_],
    count: int,
    grid: tuple[int, int],
    image_size: tuple[int, int],
) -> NDArray[np.bool_]:
    """Mask of at most ``count`` of the ``candidates``, spread over a (cols, rows) grid.

    Cells take turns, each giving its best-scoring remaining point.
    """
    cols, rows = grid
    w, h = image_size
    cx = np.clip((uv[:, 0] * cols / w).astype(int), 0, cols - 1)
    cy = np.clip((uv[:, 1] * rows / h).astype(int), 0, rows - 1)
    cell = cy * cols + cx
    idx = np.flatnonzero(candidates)
    # rank of each candidate inside its cell by score (0 = best)
    order = idx[np.lexsort((-score[idx], cell[idx]))]
    c_sorted = cell[order]
    starts = np.r_[0, np.flatnonzero(np.diff(c_sorted)) + 1]
    rank = np.arange(order.size) - np.repeat(starts, np.diff(np.r_[starts, order.size]))
    # take rank 0 of every cell, then rank 1, ...; ties in a round by score
    pick = order[np.lexsort((-score[order], rank))][:count]
    out = np.zeros(uv.shape[0], dtype=bool)
    out[pick] = True
    return out


def triangulate_rectified(uv_left: F64, disparity: F64, K: F64, baseline_m: float) -> F64:
    """(N, 3) points (metres) in the rectified left camera frame.

    From left pixels and disparities (pixels).
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Z = fx * baseline_m / disparity
    X = (uv_left[:, 0] - cx) * Z / fx
    Y = (uv_left[:, 1] - cy) * Z / fy
    return np.column_stack([X, Y, Z])


@dataclass
class StereoSet:
    """A new keyframe's stereo feature set, in its rectified left camera frame (metres, pixels).

    ``points`` (M, 3) triangulated near points with ``stereo_px`` (M, 3) = (u_left, u_right, v) and
    each match's disparity standard deviation ``disparity_sigma_px`` (M,); far matches as bearings:
    ``far_rays`` (F, 3) = (x/z, y/z, 1), ``far_inv_depth`` (F,) 1/m (0 at zero disparity) and
    ``far_px`` (F, 2) left pixels; ``unmatched_px`` (U, 2) the corners without a stereo match;
    ``offset_px`` the disparity offset taken out of the matches (``frontend.disparity_offset``);
    ``right_rows_px`` (M,) the rectified row of each point's right match (the order of ``stereo_px``;
    the self-calibration measures it, issue 31).
    """

    points: F64
    stereo_px: F64
    disparity_sigma_px: F64
    far_rays: F64
    far_inv_depth: F64
    far_px: F64
    unmatched_px: F64
    offset_px: float
    right_rows_px: F64 = field(default_factory=lambda: np.zeros(0))


def far_match_mask(disparity_px: F64, cfg: FrontendConfig, fx_px: float, baseline_m: float) -> NDArray[np.bool_]:
    """Stereo matches that enter the pose as bearings (``frontend.far_points = "bearing"``).

    Those the disparity gate drops (below ``min_disparity_px`` or beyond ``max_depth_m``) and,
    with ``far_depth_baselines`` > 0, those beyond that many baselines (disparity below
    ``fx / far_depth_baselines``).
    """
    fb = fx_px * baseline_m
    far = (disparity_px < cfg.min_disparity_px) | (disparity_px * cfg.max_depth_m < fb)
    if cfg.far_depth_baselines > 0:
        far |= disparity_px * cfg.far_depth_baselines < fx_px
    return np.asarray(far)


@dataclass
class KeyframeMatches:
    """A keyframe's corners ``corners`` (N, 2, pixels) and their stereo ``matches``: what reads no tracker state.

    :func:`keyframe_matches`; :func:`keyframe_stereo_set` applies the disparity offset and the moving
    gate to them.
    """

    corners: F64
    matches: StereoMatches


def keyframe_matches(
    left: NDArray[np.uint8],
    right: NDArray[np.uint8] | Callable[[], NDArray[np.uint8]],
    cfg: FrontendConfig,
    threads: int = 1,
) -> KeyframeMatches:
    """Corners (:func:`detect_corners`) of the rectified ``left`` image and their row matches in ``right``.

    :func:`match_stereo_split` over ``threads`` threads; far matches kept down to zero disparity when
    they enter as bearings (``far_points``). ``right`` may be a function giving the rectified right
    image, called after the corner detection (it may be being decoded meanwhile).
    """
    corners = detect_corners(
        left, cfg.max_features, (cfg.grid_cols, cfg.grid_rows), cfg.gftt_quality, cfg.min_distance_px,
        cfg.border_px, cfg.detect_half_resolution,
    )
    if callable(right):
        right = right()
    bearing = cfg.far_points == "bearing"
    return KeyframeMatches(corners, match_stereo_split(left, right, corners, cfg, 0.0 if bearing else None, threads))


def keyframe_stereo_set(
    left: NDArray[np.uint8],
    right: NDArray[np.uint8] | Callable[[], NDArray[np.uint8]],
    K_left: F64,
    baseline_m: float,
    cfg: FrontendConfig,
    offset_px: float = 0.0,
    avoid_px: F64 | None = None,
    threads: int = 1,
    matched: KeyframeMatches | None = None,
) -> StereoSet | None:
    """Detect, match and triangulate a keyframe's features in a rectified pair (``K_left``, ``baseline_m``).

    Corners and their row matches (:func:`keyframe_matches`, or ``matched``: made already, e.g.
    while the frame was tracked) with the disparity offset ``offset_px`` taken out, points nearer
    than ``max_depth_m`` (at most ``max_keyframe_points``, spread over the grid), far matches as
    bearings (``far_points``); with ``moving_gate``, no point within ``moving_radius_px`` of
    ``avoid_px`` (N, 2) (where tracks were just dropped as moving). None when fewer than
    ``min_stereo_points`` points. Reads no tracker state: it runs beside the tracking thread
    (:class:`~loopmodel.frontend.FrontEnd`); ``threads`` > 1 splits the matching
    (:func:`match_stereo_split`).
    """
    km = matched if matched is not None else keyframe_matches(left, right, cfg, threads)
    corners, m = km.corners, km.matches
    bearing = cfg.far_points == "bearing"
    u_right, disparity = m.u_right, m.disparity
    if offset_px != 0.0:
        u_right = u_right - offset_px
        disparity = disparity + offset_px
    with np.errstate(divide="ignore", invalid="ignore"):  # zero disparity: at infinity
        pts = triangulate_rectified(m.uv_left, disparity, K_left, baseline_m)
    far = far_match_mask(disparity, cfg, K_left[0, 0], baseline_m) if bearing else np.zeros(len(disparity), bool)
    keep = (pts[:, 2] < cfg.max_depth_m) & ~far
    if cfg.moving_gate > 0 and avoid_px is not None and avoid_px.shape[0]:
        d2 = np.sum((m.uv_left[:, None, :] - avoid_px[None, :, :]) ** 2, axis=2)
        near_moving = np.min(d2, axis=1) < cfg.moving_radius_px**2
        keep &= ~near_moving
        far &= ~near_moving
    h, w = left.shape[:2]
    grid = (cfg.grid_cols, cfg.grid_rows)
    if cfg.max_keyframe_points and int(keep.sum()) > cfg.max_keyframe_points:
        keep &= spread_subset(m.uv_left, m.score, keep, cfg.max_keyframe_points, grid, (w, h))
    if int(keep.sum()) < cfg.min_stereo_points:
        return None
    if cfg.far_max_points and int(far.sum()) > cfg.far_max_points:
        far &= spread_subset(m.uv_left, m.score, far, cfg.far_max_points, grid, (w, h))
    elif not cfg.far_max_points:
        far[:] = False
    far_px = m.uv_left[far]
    far_rays = np.column_stack(
        [(far_px[:, 0] - K_left[0, 2]) / K_left[0, 0], (far_px[:, 1] - K_left[1, 2]) / K_left[1, 1],
         np.ones(len(far_px))]
    )
    unmatched = np.ones(len(corners), bool)
    unmatched[m.index] = False
    return StereoSet(
        points=pts[keep],
        stereo_px=np.column_stack([m.uv_left[keep, 0], u_right[keep], m.uv_left[keep, 1]]),
        disparity_sigma_px=m.sigma_px[keep],
        far_rays=far_rays,
        far_inv_depth=np.maximum(disparity[far], 0.0) / (K_left[0, 0] * baseline_m),
        far_px=far_px,
        unmatched_px=corners[unmatched],
        offset_px=offset_px,
        right_rows_px=m.v_right[keep],
    )
