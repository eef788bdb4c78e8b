"""Compiled laser-line peak finder of :func:`loopmodel.mapping.extraction.extract_laser_peaks` (numba, GIL released).

For a uint8 image without a mask or width gate, with the centre-of-gravity method: the same peaks as
the numpy path, computed only where they can be (issue 33: 8-10 ms a 640x480 laser image in numpy,
most of it smoothing, transposing and sampling the whole image for one line).

Images are given as ``P`` (profiles, positions): one laser profile per row of ``P`` (an image row
for ``axis="rows"``, an image column for ``"columns"``), "along the line" is across the rows of ``P``.
"""

from __future__ import annotations

import math

import numba
import numpy as np


def _smoothed_py(P, taps, li, s):  # type: ignore[no-untyped-def]
    """The profile ``li``'s value at ``s`` smoothed across profiles by ``taps`` (reflected border, as OpenCV's)."""
    m = P.shape[0]
    h = taps.shape[0] // 2
    acc = 0.0
    for j in range(taps.shape[0]):
        r = li + j - h
        while r < 0 or r >= m:  # BORDER_REFLECT: fedcba|abcdefgh|hgfedcb
            r = -r - 1 if r < 0 else 2 * m - r - 1
        acc += taps[j] * P[r, s]
    return acc


_smoothed = numba.njit(cache=True, nogil=True, inline="always")(_smoothed_py)


def _median_u8_py(row, counts):  # type: ignore[no-untyped-def]
    """The median of a uint8 row (the mean of the two middle order statistics), by a histogram."""
    counts[:] = 0
    n = row.shape[0]
    for s in range(n):
        counts[row[s]] += 1
    want_lo, want_hi = (n - 1) // 2 + 1, n // 2 + 1
    lo = hi = -1
    c = 0
    for v in range(256):
        c += counts[v]
        if lo < 0 and c >= want_lo:
            lo = v
        if c >= want_hi:
            hi = v
            break
    return (lo + hi) / 2.0


_median_u8 = numba.njit(cache=True, nogil=True)(_median_u8_py)


def _best_position_py(P, bound, taps, li, top, slack):  # type: ignore[no-untyped-def]
    """Profile ``li``'s maximum of the smoothed values and its (first) position.

    ``top``: the position of the largest bound; only positions whose bound can reach the best value
    so far are smoothed.
    """
    n = P.shape[1]
    best = _smoothed(P, taps, li, top)
    k = top
    for s in range(n):
        if bound[li, s] * slack < best or s == top:
            continue
        v = _smoothed(P, taps, li, s)
        if v > best or (v == best and s < k):
            best, k = v, s
    return best, k


_best_position = numba.njit(cache=True, nogil=True, inline="always")(_best_position_py)


def _profile_peaks_py(P, bound, taps, min_contrast, window, local_background):  # type: ignore[no-untyped-def]
    """Per profile of ``P`` (uint8, profiles x positions): peak index, sub-pixel position, accepted, background.

    ``taps``: the Gaussian across profiles (length 1 = none); ``bound``: ``P``'s maximum over the
    profiles the taps reach (an upper bound of the smoothed value, for the taps' sum of 1), so only
    positions that can hold the maximum are smoothed. The background is the profile's median; the
    centre of gravity over ``window`` either side weighs the samples above it, or with
    ``local_background`` above the straight line through the two samples just outside the window.
    """
    m, n = P.shape
    k_out = np.zeros(m, np.int64)
    pos = np.zeros(m)
    ok = np.zeros(m, np.bool_)
    background = np.zeros(m)
    counts = np.zeros(256, np.int64)
    tsum = 0.0
    for j in range(taps.shape[0]):
        tsum += taps[j]
    slack = tsum * (1.0 + 1e-9)
    need = max(min_contrast, 1e-9)
    e = window + 1
    lo = hi = 0.0
    for li in range(m):
        bg = _median_u8(P[li], counts)
        background[li] = bg
        # the best position's smoothed value, a lower bound of the maximum
        top = 0
        for s in range(1, n):
            if bound[li, s] > bound[li, top]:
                top = s
        if bound[li, top] * slack - bg < need:
            continue  # no position can stand out enough
        best, k = _best_position(P, bound, taps, li, top, slack)
        k_out[li] = k
        if best - bg < need:
            continue
        if local_background:
            lo = _smoothed(P, taps, li, min(max(k - e, 0), n - 1))
            hi = _smoothed(P, taps, li, min(max(k + e, 0), n - 1))
        sw = 0.0
        swo = 0.0
        for o in range(-window, window + 1):
            idx = k + o
            if idx < 0 or idx >= n:
                continue
            base = lo + (hi - lo) * ((o + e) / (2.0 * e)) if local_background else bg
            w = _smoothed(P, taps, li, idx) - base
            if w > 0.0:
                sw += w
                swo += w * o
        if sw > 0.0:
            ok[li] = True
            pos[li] = k + swo / sw
    return k_out, pos, ok, background


profile_peaks = numba.njit(cache=True, nogil=True)(_profile_peaks_py)


def _bilinear_py(P, lc, sc):  # type: ignore[no-untyped-def]
    """``P`` at (profile ``lc``, position ``sc``), bilinear, edges extended (scipy's ``mode="nearest"``)."""
    m, n = P.shape
    lc = min(max(lc, 0.0), m - 1.0)
    sc = min(max(sc, 0.0), n - 1.0)
    l0 = int(math.floor(lc))
    s0 = int(math.floor(sc))
    fl, fs = lc - l0, sc - s0
    l1, s1 = min(l0 + 1, m - 1), min(s0 + 1, n - 1)
    return (1.0 - fl) * ((1.0 - fs) * P[l0, s0] + fs * P[l0, s1]) + fl * ((1.0 - fs) * P[l1, s0] + fs * P[l1, s1])


_bilinear = numba.njit(cache=True, nogil=True, inline="always")(_bilinear_py)


def _neighbour_run_py(pos, li, si, F, near):  # type: ignore[no-untyped-def]
    """``near[o + F]``: profile ``li + o``'s peak continues the line through ``si``; the run of them either side."""
    for o in range(-F, F + 1):
        nb = pos[li + F + o]
        near[o + F] = o == 0 or (np.isfinite(nb) and abs(nb - si) <= 2.0 * abs(o) + 1.0)
    right = 0
    while right < F and near[F + 1 + right]:
        right += 1
    left = 0
    while left < F and near[F - 1 - left]:
        left += 1
    return min(left, right)


_neighbour_run = numba.njit(cache=True, nogil=True, inline="always")(_neighbour_run_py)


def _line_slope_py(pos, near, li, si, F, lim):  # type: ignore[no-untyped-def]
    """The least-squares slope of the near peaks within ``lim`` profiles of ``li`` (0 with fewer than 3)."""
    cnt = 0
    sx = 0.0
    sy = 0.0
    for o in range(-lim, lim + 1):
        if near[o + F]:
            cnt += 1
            sx += o
            sy += pos[li + F + o] - si
    mx, my = sx / cnt, sy / cnt
    sxx = 0.0
    sxy = 0.0
    for o in range(-lim, lim + 1):
        if near[o + F]:
            sxx += (o - mx) ** 2
            sxy += (o - mx) * (pos[li + F + o] - si - my)
    return sxy / sxx if cnt >= 3 and sxx > 0 else 0.0


_line_slope = numba.njit(cache=True, nogil=True, inline="always")(_line_slope_py)


def _normal_profile_py(P, li, si, slope, run, reach, sig, e, wj, p):  # type: ignore[no-untyped-def]
    """``p[t + e]``: ``P`` along the normal at (li, si), t in -e..e, averaged along the line over ``run``.

    Returns the normal's direction (n_s, n_l).
    """
    norm = math.sqrt(1.0 + slope * slope)
    n_s, n_l = 1.0 / norm, -slope / norm
    d_s, d_l = slope / norm, 1.0 / norm
    wsum = 0.0
    for j in range(-reach, reach + 1):
        w = math.exp(-0.5 * j * j / (sig * sig)) if abs(j) <= run else 0.0
        wj[j + reach] = w
        wsum += w
    for t in range(-e, e + 1):
        acc = 0.0
        for j in range(-reach, reach + 1):
            if wj[j + reach] == 0.0:
                continue
            sc = si + t * n_s + j * d_s
            lc = li + t * n_l + j * d_l
            acc += _bilinear(P, lc, sc) * (wj[j + reach] / wsum)
        p[t + e] = acc
    return n_s, n_l


_normal_profile = numba.njit(cache=True, nogil=True, inline="always")(_normal_profile_py)


def _profile_cog_py(p, background, i, e):  # type: ignore[no-untyped-def]
    """Sums (w, w t) of the normal's samples above the background (the peak's, or the end samples' line)."""
    sw = 0.0
    swt = 0.0
    for t in range(-e + 1, e):
        base = background[i] if background.shape[0] else p[0] + (p[2 * e] - p[0]) * ((t + e) / (2.0 * e))
        w = p[t + e] - base
        if w > 0.0:
            sw += w
            swt += w * t
    return sw, swt


_profile_cog = numba.njit(cache=True, nogil=True, inline="always")(_profile_cog_py)


def _across_line_py(P, line, sub, window, smooth, background, fit_px, max_slope):  # type: ignore[no-untyped-def]
    """The peaks refined across the line: :func:`loopmodel.mapping.extraction._refine_across_line` on ``P``.

    ``line`` (int), ``sub``: the accepted profiles and their peaks; ``background`` per peak, or an
    empty array for the straight line through the two end samples of each normal's profile.
    """
    m = P.shape[0]
    reach = int(math.ceil(3.0 * smooth)) if smooth > 0 else 0
    F = max(fit_px, reach)
    pos = np.full(m + 2 * F, np.nan)
    for i in range(line.shape[0]):
        pos[line[i] + F] = sub[i]
    out = sub.copy()
    e = window + 1
    sig = max(smooth, 1e-9)
    near = np.zeros(2 * F + 1, np.bool_)
    wj = np.zeros(2 * reach + 1)
    p = np.zeros(2 * e + 1)
    for i in range(line.shape[0]):
        li, si = line[i], sub[i]
        run = _neighbour_run(pos, li, si, F, near)
        slope = _line_slope(pos, near, li, si, F, min(run, fit_px))
        n_s, n_l = _normal_profile(P, li, si, slope, run, reach, sig, e, wj, p)
        sw, swt = _profile_cog(p, background, i, e)
        if sw > 0.0:
            off = swt / sw
            if abs(off) <= window and run >= 1 and abs(slope) <= max_slope:
                out[i] = si + off * n_s - slope * (off * n_l)
    return out


across_line = numba.njit(cache=True, nogil=True)(_across_line_py)


def warm_up() -> None:
    """Load (or compile) the kernels: their first call's cost, up front."""
    P = np.zeros((4, 8), np.uint8)
    P[:, 4] = 200
    taps = np.full(3, 1.0 / 3.0)
    _k, pos, _ok, _bg = profile_peaks(P, P, taps, 20.0, 1, True)
    across_line(P, np.arange(4), pos, 1, 1.0, np.zeros(0), 3, 1.5)
