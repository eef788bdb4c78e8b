"""Compiled inner loop of :func:`loopmodel.frontend.affine_klt.refine_affine` (numba, GIL released).

One feature at a time: its (2 h + 1)^2 template sampled from the reference image, then Gauss-Newton
over the position, a 2 x 2 affine warp and a brightness gain and offset in the current image, with
the image and its gradients sampled bilinearly (float32 coordinates and values, border replicated,
as ``cv2.remap`` with ``INTER_LINEAR`` / ``BORDER_REPLICATE`` samples them) and the 8 x 8 normal
equations solved by LU with partial pivoting. The numpy version it replaces converted both whole
images to float32 and built (n, 8, P) Jacobians every iteration (15 ms a call for 10-60 features on
the KITTI clip; 3.4 ms now).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def _solve8_py(H, g, dp):  # type: ignore[no-untyped-def]
    """dp = -H^-1 g by LU with partial pivoting (H, g overwritten); False when a pivot is zero."""
    n = 8
    for k in range(n):
        p = k
        best = abs(H[k, k])
        for i in range(k + 1, n):
            if abs(H[i, k]) > best:
                best = abs(H[i, k])
                p = i
        if H[p, k] == 0.0:
            return False
        if p != k:
            for j in range(n):
                t = H[k, j]
                H[k, j] = H[p, j]
                H[p, j] = t
            t = g[k]
            g[k] = g[p]
            g[p] = t
        for i in range(k + 1, n):
            f = H[i, k] / H[k, k]
            for j in range(k + 1, n):
                H[i, j] -= f * H[k, j]
            g[i] -= f * g[k]
    for i in range(n - 1, -1, -1):
        acc = g[i]
        for j in range(i + 1, n):
            acc -= H[i, j] * dp[j]
        dp[i] = acc / H[i, i]
    for i in range(n):
        dp[i] = -dp[i]
    return True


def _weights_py(h, w, x, y):  # type: ignore[no-untyped-def]
    """Bilinear corners and weights at float32 (x, y), border replicated: (xa, xb, ya, yb, ax, ay)."""
    xf = np.float32(x)
    yf = np.float32(y)
    if not (math.isfinite(xf) and math.isfinite(yf)):
        return 0, 0, 0, 0, np.float32(0.0), np.float32(0.0), False
    x0f = math.floor(xf)
    y0f = math.floor(yf)
    ax = np.float32(xf - np.float32(x0f))
    ay = np.float32(yf - np.float32(y0f))
    x0 = int(min(max(x0f, -1.0), float(w)))
    y0 = int(min(max(y0f, -1.0), float(h)))
    return (min(max(x0, 0), w - 1), min(max(x0 + 1, 0), w - 1), min(max(y0, 0), h - 1),
            min(max(y0 + 1, 0), h - 1), ax, ay, True)


def _at_py(img, xa, xb, ya, yb, ax, ay):  # type: ignore[no-untyped-def]
    one = np.float32(1.0)
    top = (one - ax) * np.float32(img[ya, xa]) + ax * np.float32(img[ya, xb])
    bot = (one - ax) * np.float32(img[yb, xa]) + ax * np.float32(img[yb, xb])
    return np.float64(np.float32((one - ay) * top + ay * bot))


def _inside_py(h, w, c0, c1, a00, a01, a10, a11, sx, sy):  # type: ignore[no-untyped-def]
    """Whether the warped patch (c, A) lies at least half a pixel inside an h x w image.

    The patch's extreme offsets are its first and last pixels (``sx``, ``sy`` row-major, square),
    so its four corners bound every sample; then no sample reaches the border and the clamping of
    :func:`_weights_py` changes nothing (:func:`_fast_weights_py` gives the same values).
    """
    P = sx.shape[0]
    side = int(math.sqrt(P) + 0.5)
    for k in (0, side - 1, P - side, P - 1):
        x = c0 + a00 * sx[k] + a01 * sy[k]
        y = c1 + a10 * sx[k] + a11 * sy[k]
        if not (x >= 0.5 and x <= w - 1.5 and y >= 0.5 and y <= h - 1.5):
            return False
    return True


def _fast_weights_py(x, y):  # type: ignore[no-untyped-def]
    """:func:`_weights_py` at a point known to lie inside (:func:`_inside_py`): (xa, xb, ya, yb, ax, ay)."""
    xf = np.float32(x)
    yf = np.float32(y)
    xa = int(xf)  # floor: xf >= 0.5
    ya = int(yf)
    return xa, xa + 1, ya, ya + 1, np.float32(xf - np.float32(xa)), np.float32(yf - np.float32(ya))


def _dot_py(a, b):  # type: ignore[no-untyped-def]
    s = 0.0
    for k in range(a.shape[0]):
        s += a[k] * b[k]
    return s


def _template_py(ref, u0, v0, sx, sy, T, Jm):  # type: ignore[no-untyped-def]
    """The reference template at (u0, v0) into ``T``; the gain and offset rows of ``Jm`` (-T, -1)."""
    hr, wr = ref.shape
    fast = _inside(hr, wr, u0, v0, 1.0, 0.0, 0.0, 1.0, sx, sy)
    for k in range(T.shape[0]):
        if fast:
            xa, xb, ya, yb, ax, ay = _fast_weights(u0 + sx[k], v0 + sy[k])
            T[k] = _at(ref, xa, xb, ya, yb, ax, ay)
        else:
            xa, xb, ya, yb, ax, ay, fin = _weights(hr, wr, u0 + sx[k], v0 + sy[k])
            T[k] = _at(ref, xa, xb, ya, yb, ax, ay) if fin else 0.0
        Jm[6, k] = -T[k]
        Jm[7, k] = -1.0


def _rows_py(cur, gx, gy, c0, c1, a00, a01, a10, a11, gain, offset, sx, sy, T, Jm):  # type: ignore[no-untyped-def]
    """Position and warp Jacobian rows (0-5) and the residual (row 8) of ``Jm`` at the warp (c, A)."""
    hc, wc = cur.shape
    fast = _inside(hc, wc, c0, c1, a00, a01, a10, a11, sx, sy)  # no clamping: 1.5x faster, the same values
    for k in range(T.shape[0]):
        x = c0 + a00 * sx[k] + a01 * sy[k]
        y = c1 + a10 * sx[k] + a11 * sy[k]
        ic, ggx, ggy = 0.0, 0.0, 0.0
        if fast:
            xa, xb, ya, yb, ax, ay = _fast_weights(x, y)
            fin = True
        else:
            xa, xb, ya, yb, ax, ay, fin = _weights(hc, wc, x, y)
        if fin:
            ic = _at(cur, xa, xb, ya, yb, ax, ay)
            ggx = _at(gx, xa, xb, ya, yb, ax, ay)
            ggy = _at(gy, xa, xb, ya, yb, ax, ay)
        Jm[8, k] = ic - (gain * T[k] + offset)
        Jm[0, k] = ggx
        Jm[1, k] = ggy
        Jm[2, k] = ggx * sx[k]
        Jm[3, k] = ggx * sy[k]
        Jm[4, k] = ggy * sx[k]
        Jm[5, k] = ggy * sy[k]


def _normal_py(Jm, H, g):  # type: ignore[no-untyped-def]
    """The damped normal equations of ``Jm``'s 8 rows against its residual row."""
    for i in range(8):
        g[i] = _dot(Jm[i], Jm[8])
        for j in range(i, 8):
            H[i, j] = _dot(Jm[i], Jm[j])
            H[j, i] = H[i, j]
    for i in range(8):
        H[i, i] += 1e-6 * (1.0 + H[i, i])


def _gauss_newton_py(cur, gx, gy, c, A, q, sx, sy, T, Jm, H, g, dp, iterations, limit):  # type: ignore[no-untyped-def]
    """Gauss-Newton of feature q's position ``c[q]``, warp ``A[q]``, gain and offset, in place.

    Stops when converged, singular, no longer finite or more than ``limit`` px from its guess.
    """
    g0 = c[q, 0]
    g1 = c[q, 1]
    gain = 1.0
    offset = 0.0
    for _ in range(iterations):
        _rows(cur, gx, gy, c[q, 0], c[q, 1], A[q, 0, 0], A[q, 0, 1], A[q, 1, 0], A[q, 1, 1], gain, offset, sx, sy,
              T, Jm)
        _normal(Jm, H, g)
        if not _solve8(H, g, dp):
            break  # a singular (flat) patch stays where it is
        c[q, 0] += dp[0]
        c[q, 1] += dp[1]
        A[q, 0, 0] += dp[2]
        A[q, 0, 1] += dp[3]
        A[q, 1, 0] += dp[4]
        A[q, 1, 1] += dp[5]
        gain += dp[6]
        offset += dp[7]
        e0 = c[q, 0] - g0
        e1 = c[q, 1] - g1
        if not (math.isfinite(c[q, 0]) and math.isfinite(c[q, 1])) or math.sqrt(e0 * e0 + e1 * e1) > limit:
            break
        if max(abs(dp[0]), abs(dp[1])) < 1e-3:
            break  # converged


def _finite_or_reset_py(c, A, q, g0, g1):  # type: ignore[no-untyped-def]
    """Whether feature q's solution is finite; if not, put it back at its guess with an identity warp."""
    finite = math.isfinite(c[q, 0]) and math.isfinite(c[q, 1])
    for i in range(2):
        for j in range(2):
            finite = finite and math.isfinite(A[q, i, j])
    if not finite:
        c[q, 0] = g0
        c[q, 1] = g1
        A[q, 0, 0] = 1.0
        A[q, 0, 1] = 0.0
        A[q, 1, 0] = 0.0
        A[q, 1, 1] = 1.0
    return finite


def _ncc_py(cur, c, A, q, sx, sy, T, Ic):  # type: ignore[no-untyped-def]
    """NCC of the template ``T`` with the current image under feature q's warp."""
    hc, wc = cur.shape
    P = T.shape[0]
    mt = 0.0
    mi = 0.0
    fast = _inside(hc, wc, c[q, 0], c[q, 1], A[q, 0, 0], A[q, 0, 1], A[q, 1, 0], A[q, 1, 1], sx, sy)
    for k in range(P):
        x = c[q, 0] + A[q, 0, 0] * sx[k] + A[q, 0, 1] * sy[k]
        y = c[q, 1] + A[q, 1, 0] * sx[k] + A[q, 1, 1] * sy[k]
        if fast:
            xa, xb, ya, yb, ax, ay = _fast_weights(x, y)
            Ic[k] = _at(cur, xa, xb, ya, yb, ax, ay)
        else:
            xa, xb, ya, yb, ax, ay, fin = _weights(hc, wc, x, y)
            Ic[k] = _at(cur, xa, xb, ya, yb, ax, ay) if fin else 0.0
        mt += T[k]
        mi += Ic[k]
    mt /= P
    mi /= P
    stt = 0.0
    sii = 0.0
    sti = 0.0
    for k in range(P):
        tc = T[k] - mt
        icc = Ic[k] - mi
        stt += tc * tc
        sii += icc * icc
        sti += tc * icc
    return sti / math.sqrt(stt * sii + 1e-9)


def _refine_py(ref, cur, gx, gy, uv_ref, c, A, half, iterations, max_shift_px):  # type: ignore[no-untyped-def]
    """Refine positions ``c`` (n, 2) and warps ``A`` (n, 2, 2) in place; returns the NCC and finite flag per feature.

    A feature whose solution is not finite is put back at its guess with an identity warp.
    """
    n = uv_ref.shape[0]
    side = 2 * half + 1
    P = side * side
    sx = np.empty(P)
    sy = np.empty(P)
    for i in range(side):
        for j in range(side):
            sx[i * side + j] = j - half
            sy[i * side + j] = i - half
    T = np.empty(P)
    Ic = np.empty(P)
    Jm = np.empty((9, P))  # the 8 Jacobian rows and the residual, per pixel
    H = np.empty((8, 8))
    g = np.empty(8)
    dp = np.empty(8)
    ncc = np.empty(n)
    ok = np.ones(n, np.bool_)
    limit = 2.0 * max_shift_px + 1.0
    for q in range(n):
        _template(ref, uv_ref[q, 0], uv_ref[q, 1], sx, sy, T, Jm)
        g0 = c[q, 0]
        g1 = c[q, 1]
        _gauss_newton(cur, gx, gy, c, A, q, sx, sy, T, Jm, H, g, dp, iterations, limit)
        ok[q] = _finite_or_reset(c, A, q, g0, g1)
        ncc[q] = _ncc(cur, c, A, q, sx, sy, T, Ic)
    return ncc, ok


_jit = numba.njit(cache=True, nogil=True)
_weights = numba.njit(cache=True, nogil=True, inline="always")(_weights_py)
_at = numba.njit(cache=True, nogil=True, inline="always")(_at_py)
_inside = numba.njit(cache=True, nogil=True, inline="always")(_inside_py)
_fast_weights = numba.njit(cache=True, nogil=True, inline="always")(_fast_weights_py)
# a sum in any order (vectorised); no assumption about NaN or infinity
_dot = numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract", "nsz", "arcp"})(_dot_py)
_solve8 = _jit(_solve8_py)
_inline = numba.njit(cache=True, nogil=True, inline="always")
_template = _inline(_template_py)
_rows = _inline(_rows_py)
_normal = _inline(_normal_py)
_gauss_newton = _inline(_gauss_newton_py)
_finite_or_reset = _inline(_finite_or_reset_py)
_ncc = _inline(_ncc_py)
refine_features = _jit(_refine_py)


def warm_up() -> None:
    """Load (or compile) the kernel for uint8 images and float32 gradients: the first call's cost, up front."""
    img = np.zeros((8, 8), np.uint8)
    grad = np.zeros((8, 8), np.float32)
    refine_features(img, img, grad, grad, np.full((1, 2), 4.0), np.full((1, 2), 4.0),
                    np.eye(2)[None].copy(), 1, 1, 2.0)
