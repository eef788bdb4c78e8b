"""Compiled row scan of :func:`loopmodel.frontend.stereo.match_stereo` (numba, GIL released).

:func:`zncc_scan` scores a corner's template against windows along rows of the other (padded)
image: zero-mean normalised cross-correlation, computed in float32 as the numpy form it replaces
did (window sums of whole grey levels are exact in float32). The numpy form built (N, p, L + p - 1)
strips and spent a keyframe's 10-13 ms of CPU per scan on the KITTI clip in temporaries. Since fe8
the window sums come from sliding column sums (exact integers) and each row's pixels are converted
once, so the inner loop is the cross term alone: the same scores at about half the CPU.
:func:`row_peaks` takes a coarse scan's best window and its margin over the best one further away
(numpy's masks and maxima over the (N, 83) scores took 1.4 ms a scan). :func:`row_gradient` is the
sub-pixel column fit of :func:`~loopmodel.frontend.stereo.refine_row_gradient`, likewise in float32.
"""

from __future__ import annotations

import math

import numba
import numpy as np


def _template_py(src, r0, c0, out):  # type: ignore[no-untyped-def]
    """``out`` (p, p) = src's window at (r0, c0) less its mean, in float32; returns its sum of squares."""
    p = out.shape[0]
    s = np.float32(0.0)
    for a in range(p):
        for b in range(p):
            out[a, b] = np.float32(src[r0 + a, c0 + b])
            s += out[a, b]
    mean = np.float32(s / np.float32(p * p))
    ss = np.float32(0.0)
    for a in range(p):
        for b in range(p):
            out[a, b] = out[a, b] - mean
            ss += out[a, b] * out[a, b]
    return ss


_template = numba.njit(cache=True, nogil=True, inline="always")(_template_py)


def _cross_short_py(tz, band, p, length, cross):  # type: ignore[no-untyped-def]
    """``cross[k]`` = the template ``tz``'s cross term with the window at column k of ``band``, k < ``length`` <= 8.

    A short row (the fine search): eight windows in registers, each summed in the same order.
    """
    c0 = c1 = c2 = c3 = c4 = c5 = c6 = c7 = np.float32(0.0)
    for a in range(p):
        for b in range(p):
            t = tz[a, b]
            c0 += t * band[a, b]
            c1 += t * band[a, b + 1]
            c2 += t * band[a, b + 2]
            c3 += t * band[a, b + 3]
            c4 += t * band[a, b + 4]
            c5 += t * band[a, b + 5]
            c6 += t * band[a, b + 6]
            c7 += t * band[a, b + 7]
    block = (c0, c1, c2, c3, c4, c5, c6, c7)
    for k in range(length):
        cross[k] = block[k]


_cross_short = numba.njit(cache=True, nogil=True, inline="always")(_cross_short_py)


def _zncc_scan_py(src, dst, pad, u, v, start, length, half, row_offsets):  # type: ignore[no-untyped-def]
    n = u.shape[0]
    p = 2 * half + 1
    pp = np.float32(p * p)
    nr = row_offsets.shape[0]
    width = length + p - 1  # the columns the windows of one row cover
    out = np.empty((n, nr, length), np.float32)
    tz = np.empty((p, p), np.float32)
    band = np.zeros((p, max(width, p + 7)), np.float32)  # a short row's block of 8 windows reads up to p + 7
    cross = np.empty(length, np.float32)
    col1 = np.empty(width, np.int64)
    col2 = np.empty(width, np.int64)
    for i in range(n):
        ss = _template(src, v[i] + pad - half, u[i] + pad - half, tz)
        tn = np.float32(np.float32(math.sqrt(ss)) + np.float32(1e-6))
        for ri in range(nr):
            w0 = v[i] + row_offsets[ri] + pad - half
            x0 = start[i] + pad - half
            # the windows' pixels as float32 once, and their column sums (exact integers)
            col1[:] = 0
            col2[:] = 0
            for a in range(p):
                for c in range(width):
                    g = np.int64(dst[w0 + a, x0 + c])
                    band[a, c] = np.float32(g)
                    col1[c] += g
                    col2[c] += g * g
            if length > 8:  # over the template's pixels, every window at once (vectorised over k)
                cross[:] = 0.0
                for a in range(p):
                    for b in range(p):
                        t = tz[a, b]
                        for k in range(length):
                            cross[k] += t * band[a, b + k]
            else:
                _cross_short(tz, band, p, length, cross)
            s1 = np.int64(0)
            s2 = np.int64(0)
            for c in range(p):
                s1 += col1[c]
                s2 += col2[c]
            for k in range(length):
                if k > 0:  # the window slides one column
                    s1 += col1[k + p - 1] - col1[k - 1]
                    s2 += col2[k + p - 1] - col2[k - 1]
                f1 = np.float32(s1)
                var = max(np.float32(np.float32(s2) - f1 * f1 / pp), np.float32(1e-3))
                out[i, ri, k] = np.float32(cross[k] / np.float32(tn * np.float32(math.sqrt(var))))
    return out


def _row_gradient_py(src, dst, pad, u, v, x0, v_dst, half, iterations, min_sigma):  # type: ignore[no-untyped-def]
    n = u.shape[0]
    p = 2 * half + 1
    pp = np.float32(p * p)
    x = x0.copy()
    sigma = np.full(n, np.inf)
    t = np.empty((p, p), np.float32)
    W = np.empty((p, p), np.float32)
    G = np.empty((p, p), np.float32)
    half32 = np.float32(0.5)
    one = np.float32(1.0)
    for i in range(n):
        tt = np.float32(_template(src, v[i] + pad - half, u[i] + pad - half, t) + np.float32(1e-9))
        rd = v_dst[i] + pad - half
        for _ in range(iterations):
            xf = math.floor(x[i])
            xi = int(xf)
            al = np.float32(x[i] - xf)
            base = xi + pad - half
            mw = np.float32(0.0)
            mg = np.float32(0.0)
            for a in range(p):
                for b in range(p):
                    c = base + b
                    s_m1 = np.float32(dst[rd + a, c - 1])
                    s_0 = np.float32(dst[rd + a, c])
                    s_1 = np.float32(dst[rd + a, c + 1])
                    s_2 = np.float32(dst[rd + a, c + 2])
                    w = (one - al) * s_0 + al * s_1
                    wp = (one - al) * s_1 + al * s_2
                    wm = (one - al) * s_m1 + al * s_0
                    W[a, b] = w
                    G[a, b] = half32 * (wp - wm)
                    mw += w
                    mg += G[a, b]
            mw = np.float32(mw / pp)
            mg = np.float32(mg / pp)
            wt = np.float32(0.0)
            for a in range(p):
                for b in range(p):
                    W[a, b] = W[a, b] - mw
                    G[a, b] = G[a, b] - mg
                    wt += W[a, b] * t[a, b]
            gain = np.float32(wt / tt)
            gg = np.float32(0.0)
            gr = np.float32(0.0)
            rr = np.float32(0.0)
            for a in range(p):
                for b in range(p):
                    r = W[a, b] - gain * t[a, b]
                    gg += G[a, b] * G[a, b]
                    gr += G[a, b] * r
                    rr += r * r
            gg = np.float32(gg + np.float32(1e-9))
            step = np.float32(-gr / gg)
            x[i] += np.float64(min(max(step, np.float32(-0.5)), np.float32(0.5)))
            per_px = np.float32(rr / np.float32(max(p * p - 3, 1)))
            sigma[i] = np.float64(np.float32(math.sqrt(np.float32(per_px / gg))))
        sigma[i] = max(sigma[i], min_sigma)
    return x, sigma


def _interpolate_py(dst, r0, c0, ax, ay, S, L, H):  # type: ignore[no-untyped-def]
    """``H``: ``dst`` from (r0, c0) interpolated at the fractional offsets (ax, ay): rows (L), then columns."""
    one = np.float32(1.0)
    q = S.shape[0]
    m = H.shape[0]
    for a in range(q):
        for b in range(q):
            S[a, b] = np.float32(dst[r0 + a, c0 + b])
    for j in range(m):
        for b in range(q):
            L[j, b] = (one - ay) * S[j, b] + ay * S[j + 1, b]
    for j in range(m):
        for c in range(m):
            H[j, c] = (one - ax) * L[j, c] + ax * L[j, c + 1]


_interpolate = numba.njit(cache=True, nogil=True)(_interpolate_py)


def _centred_window_py(H, t, pp, W, GX, GY):  # type: ignore[no-untyped-def]
    """The window ``W`` (H's inner p x p) and its gradients ``GX``, ``GY``, each less its mean; returns W . t."""
    p = W.shape[0]
    half32 = np.float32(0.5)
    mw = np.float32(0.0)
    mx = np.float32(0.0)
    my = np.float32(0.0)
    for a in range(p):
        for b in range(p):
            w = H[a + 1, b + 1]
            W[a, b] = w
            GX[a, b] = half32 * (H[a + 1, b + 2] - H[a + 1, b])
            GY[a, b] = half32 * (H[a + 2, b + 1] - H[a, b + 1])
            mw += w
            mx += GX[a, b]
            my += GY[a, b]
    mw = np.float32(mw / pp)
    mx = np.float32(mx / pp)
    my = np.float32(my / pp)
    wt = np.float32(0.0)
    for a in range(p):
        for b in range(p):
            W[a, b] = W[a, b] - mw
            GX[a, b] = GX[a, b] - mx
            GY[a, b] = GY[a, b] - my
            wt += W[a, b] * t[a, b]
    return wt


_centred_window = numba.njit(cache=True, nogil=True)(_centred_window_py)


def _step_2d_py(W, GX, GY, t, gain, dof):  # type: ignore[no-untyped-def]
    """The Gauss-Newton step (sx, sy) of the gain-fitted residual W - gain t, and its x standard deviation."""
    p = W.shape[0]
    one = np.float32(1.0)
    tiny = np.float32(1e-9)
    hxx = np.float32(0.0)
    hyy = np.float32(0.0)
    hxy = np.float32(0.0)
    bx = np.float32(0.0)
    by = np.float32(0.0)
    rr = np.float32(0.0)
    for a in range(p):
        for b in range(p):
            r = W[a, b] - gain * t[a, b]
            hxx += GX[a, b] * GX[a, b]
            hyy += GY[a, b] * GY[a, b]
            hxy += GX[a, b] * GY[a, b]
            bx -= GX[a, b] * r
            by -= GY[a, b] * r
            rr += r * r
    hxx = np.float32(hxx + tiny)
    hyy = np.float32(hyy + tiny)
    det = np.float32(hxx * hyy - hxy * hxy)
    if det > np.float32(1e-6) * hxx * hyy:
        sx = np.float32((hyy * bx - hxy * by) / det)
        sy = np.float32((hxx * by - hxy * bx) / det)
        var_x = np.float32(hyy / det)
    else:
        sx = np.float32(bx / hxx)
        sy = np.float32(0.0)
        var_x = np.float32(one / hxx)
    return sx, sy, np.float32(math.sqrt(np.float32(np.float32(rr / dof) * var_x)))


_step_2d = numba.njit(cache=True, nogil=True)(_step_2d_py)


def _grad2d_py(src, dst, pad, u, v, x0, y0, half, iterations, min_sigma):  # type: ignore[no-untyped-def]
    n = u.shape[0]
    p = 2 * half + 1
    pp = np.float32(p * p)
    q = p + 3  # the window's rows / columns around floor(y) / floor(x), one more each side for the gradients
    x = x0.copy()
    y = y0.copy()
    sigma = np.full(n, np.inf)
    t = np.empty((p, p), np.float32)
    S = np.empty((q, q), np.float32)
    # S interpolated at row y + j - 1 (L), then at column x + c - 1 (H), j, c < p + 2: the window is H[1:p+1,
    # 1:p+1], its column neighbours H[1:p+1, 0:p] and [2:p+2], its row neighbours H[0:p, 1:p+1] and [2:p+2]
    # (each value the same products as interpolating every shifted window on its own)
    L = np.empty((p + 2, q), np.float32)
    H = np.empty((p + 2, p + 2), np.float32)
    W = np.empty((p, p), np.float32)
    GX = np.empty((p, p), np.float32)
    GY = np.empty((p, p), np.float32)
    tiny = np.float32(1e-9)
    dof = np.float32(max(p * p - 4, 1))
    for i in range(n):
        tt = np.float32(_template(src, v[i] + pad - half, u[i] + pad - half, t) + tiny)
        for _ in range(iterations):
            xf = math.floor(x[i])
            yf = math.floor(y[i])
            ax = np.float32(x[i] - xf)
            ay = np.float32(y[i] - yf)
            _interpolate(dst, int(yf) + pad - half - 1, int(xf) + pad - half - 1, ax, ay, S, L, H)
            gain = np.float32(_centred_window(H, t, pp, W, GX, GY) / tt)
            sx, sy, sd = _step_2d(W, GX, GY, t, gain, dof)
            x[i] += np.float64(min(max(sx, np.float32(-0.5)), np.float32(0.5)))
            y[i] += np.float64(min(max(sy, np.float32(-0.5)), np.float32(0.5)))
            sigma[i] = np.float64(sd)
        sigma[i] = max(sigma[i], min_sigma)
    return x, y, sigma


def _row_peaks_py(scores, start, lo, hi, apart):  # type: ignore[no-untyped-def]
    n, length = scores.shape
    best_k = np.zeros(n, np.int64)
    margin = np.empty(n, np.float64)
    minus2 = np.float32(-2.0)
    for i in range(n):
        best = minus2
        k_best = 0
        first = True
        for k in range(length):
            c = start[i] + k
            s = scores[i, k] if lo <= c <= hi else minus2
            if first or s > best:  # the first maximum (numpy's argmax)
                best, k_best, first = s, k, False
        second = minus2
        for k in range(length):
            c = start[i] + k
            if abs(k - k_best) > apart and lo <= c <= hi and scores[i, k] > second:
                second = scores[i, k]
        best_k[i] = k_best
        margin[i] = np.float64(np.float32(best - second))
    return best_k, margin


zncc_scan = numba.njit(cache=True, nogil=True)(_zncc_scan_py)
row_peaks = numba.njit(cache=True, nogil=True)(_row_peaks_py)
row_gradient = numba.njit(cache=True, nogil=True)(_row_gradient_py)
gradient_2d = numba.njit(cache=True, nogil=True)(_grad2d_py)


def warm_up() -> None:
    """Load (or compile) the kernels for uint8 images and int64 pixels: the first call's cost, up front."""
    img = np.zeros((12, 12), np.uint8)
    one = np.full(1, 5, np.int64)
    scores = zncc_scan(img, img, 3, one, one, one, 2, 1, np.zeros(1, np.int64))
    row_peaks(scores[:, 0], one, 0, 9, 2)
    row_gradient(img, img, 3, one, one, np.full(1, 5.0), one, 1, 1, 0.05)
    gradient_2d(img, img, 3, one, one, np.full(1, 5.0), np.full(1, 5.0), 1, 1, 0.05)
