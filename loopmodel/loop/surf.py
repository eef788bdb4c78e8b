"""SURF (Bay, Ess, Tuytelaars, Van Gool 2006/2008), written here from the papers.

Detection ("Fast-Hessian"): the determinant of the Hessian is approximated with box
filters on an integral image, ``det = Dxx Dyy - (0.9 Dxy)^2`` (each response divided by
the filter area), at filter sizes 9, 15, 21, 27 in the first octave, doubling the size
step (and the sampling step) in each further octave. Local maxima over 3x3x3 neighbours
in (x, y, scale) above a threshold are interpolated to sub-pixel and sub-scale positions
with a quadratic fit; the scale of a keypoint is ``s = 1.2 L / 9`` for filter size L.
The sign of the Laplacian (``Dxx + Dyy``) is kept for matching (only features of the
same sign are compared).

Orientation: Haar wavelet responses of side 4s at the sample points (step s) within a
radius of 6s, weighted with a Gaussian of sigma 2s; a window of 60 degrees slides around
the circle and the longest sum of the responses in a window gives the orientation
(U-SURF, ``upright=True``, skips this: orientation 0).

Descriptor: a square of side 20s, aligned with the orientation, split into 4x4
sub-regions of 5x5 samples; Haar responses of side 2s (in image axes, rotated into the
keypoint frame) are weighted with a Gaussian of sigma 3.3s (by default the sub-regions
overlap instead: 9x9 samples each over a 24s square, see :class:`Surf`); each sub-region contributes
``(sum dx, sum dy, sum |dx|, sum |dy|)`` (64 values), or with ``extended=True`` the sums of
dx and |dx| split by the sign of dy and those of dy and |dy| split by the sign of dx
(128 values). The vector is normalised to unit length.

Pixel coordinates: the centre of the top-left pixel is (0, 0), x to the right, y down;
orientations are radians from +x towards +y (image axes).
Kernels are compiled with numba (per-row or per-keypoint parallel loops).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np
from numpy.typing import NDArray

from loopmodel.config import SurfConfig

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

_DEFAULTS = SurfConfig()

#: Weight of the Dxy box response in the Hessian determinant (Bay et al. 2008, eq. 4).
HESSIAN_DXY_WEIGHT = 0.9


@dataclass
class SurfKeypoints:
    """Keypoints: positions, scales, angles, Hessian responses and Laplacian signs.

    ``xy`` (N, 2) pixels, ``scale`` (N,) s in pixels (1.2 for the 9x9 filter), ``angle`` (N,)
    radians, ``response`` (N,) Hessian determinant, ``sign`` (N,) int8 sign of the Laplacian
    (+1 / -1).
    """

    xy: F64
    scale: F64
    angle: F64
    response: F64
    sign: NDArray[np.int8]

    def __len__(self) -> int:
        return int(self.xy.shape[0])

    def subset(self, idx: NDArray[np.int64]) -> SurfKeypoints:
        """The keypoints at ``idx``."""
        return SurfKeypoints(self.xy[idx], self.scale[idx], self.angle[idx], self.response[idx], self.sign[idx])


def integral_image(image: NDArray[np.generic], sigma_px: float = 0.0) -> F64:
    """(h+1, w+1) integral image of a grey image scaled to [0, 1] (uint8) or as given.

    Optionally smoothed first with a Gaussian of ``sigma_px``.
    """
    img = np.asarray(image)
    f = img.astype(np.float32) / 255.0 if img.dtype == np.uint8 else img.astype(np.float32)
    if sigma_px > 0:
        f = cv2.GaussianBlur(f, (0, 0), sigma_px)
    return np.asarray(cv2.integral(np.ascontiguousarray(f, dtype=np.float32), sdepth=cv2.CV_64F), dtype=np.float64)


@nb.njit(cache=True)
def _box(ii: F64, r0: int, c0: int, r1: int, c1: int) -> float:
    """Sum over rows [r0, r1) and columns [c0, c1), clipped to the image."""
    h = ii.shape[0] - 1
    w = ii.shape[1] - 1
    r0 = min(max(r0, 0), h)
    r1 = min(max(r1, 0), h)
    c0 = min(max(c0, 0), w)
    c1 = min(max(c1, 0), w)
    return ii[r1, c1] - ii[r0, c1] - ii[r1, c0] + ii[r0, c0]


@nb.njit(cache=True)
def _box_in(ii: F64, r0: int, c0: int, r1: int, c1: int) -> float:
    """Sum over rows [r0, r1) and columns [c0, c1) lying inside the image (no clipping)."""
    return ii[r1, c1] - ii[r0, c1] - ii[r1, c0] + ii[r0, c0]


@nb.njit(cache=True)
def _hessian_at(ii: F64, r: int, c: int, b: int, lobe: int, hl: int, clip: bool) -> tuple[float, float, float]:
    """Box-filter (Dxx, Dyy, Dxy) of lobe ``lobe`` at pixel (r, c), unnormalised."""
    if clip:
        dyy = _box(ii, r - b, c - lobe + 1, r + b + 1, c + lobe) - 3.0 * _box(
            ii, r - hl, c - lobe + 1, r + hl + 1, c + lobe
        )
        dxx = _box(ii, r - lobe + 1, c - b, r + lobe, c + b + 1) - 3.0 * _box(
            ii, r - lobe + 1, c - hl, r + lobe, c + hl + 1
        )
        dxy = (
            _box(ii, r - lobe, c - lobe, r, c)
            + _box(ii, r + 1, c + 1, r + lobe + 1, c + lobe + 1)
            - _box(ii, r - lobe, c + 1, r, c + lobe + 1)
            - _box(ii, r + 1, c - lobe, r + lobe + 1, c)
        )
    else:
        dyy = _box_in(ii, r - b, c - lobe + 1, r + b + 1, c + lobe) - 3.0 * _box_in(
            ii, r - hl, c - lobe + 1, r + hl + 1, c + lobe
        )
        dxx = _box_in(ii, r - lobe + 1, c - b, r + lobe, c + b + 1) - 3.0 * _box_in(
            ii, r - lobe + 1, c - hl, r + lobe, c + hl + 1
        )
        dxy = (
            _box_in(ii, r - lobe, c - lobe, r, c)
            + _box_in(ii, r + 1, c + 1, r + lobe + 1, c + lobe + 1)
            - _box_in(ii, r - lobe, c + 1, r, c + lobe + 1)
            - _box_in(ii, r + 1, c - lobe, r + lobe + 1, c)
        )
    return dxx, dyy, dxy


@nb.njit(cache=True, parallel=True)
def _hessian_octave(ii: F64, sizes: NDArray[np.int64], step: int, det: F32, lap: F32) -> None:
    """Determinants of the box-filter Hessian for every filter side in ``sizes``.

    At pixels (i * step, j * step) -> ``det`` (layers, rows, cols); its trace -> ``lap`` (both
    normalised by the filter area). Filters reaching past the border are clipped.
    """
    n_layers, rows, cols = det.shape
    h = ii.shape[0] - 1
    w = ii.shape[1] - 1
    w2 = HESSIAN_DXY_WEIGHT * HESSIAN_DXY_WEIGHT
    for i in nb.prange(rows):
        r = i * step
        for k in range(n_layers):
            size = sizes[k]
            lobe = size // 3
            b = (size - 1) // 2
            hl = (lobe - 1) // 2
            inv_area = 1.0 / float(size * size)
            row_in = r - b - 1 >= 0 and r + b + 1 <= h
            j_lo = (b + 1 + step - 1) // step  # first column with c - b - 1 >= 0
            j_hi = (w - b - 1) // step  # last column with c + b + 1 <= w
            for j in range(cols):
                c = j * step
                clip = not (row_in and j_lo <= j <= j_hi)
                dxx, dyy, dxy = _hessian_at(ii, r, c, b, lobe, hl, clip)
                dxx *= inv_area
                dyy *= inv_area
                dxy *= inv_area
                det[k, i, j] = dxx * dyy - w2 * dxy * dxy
                lap[k, i, j] = dxx + dyy


@nb.njit(cache=True)
def _extrema(
    stack: F32,
    laps: F32,
    sizes: NDArray[np.int64],
    step: int,
    threshold: float,
    edge_ratio: float,
    height: int,
    width: int,
    out: F64,
    count: int,
) -> int:
    """3x3x3 maxima of one octave's determinant stack (layers, rows, cols) above ``threshold``.

    Interpolated in (x, y, size); rows of ``out``: x, y, size, response, sign. Returns the new
    count.
    """
    n_layers, rows, cols = stack.shape
    for k in range(1, n_layers - 1):
        # the largest filter involved must lie inside the image
        margin = (sizes[k + 1] - 1) // 2 + 1
        for i in range(1, rows - 1):
            r = i * step
            if r - margin < 0 or r + margin > height - 1:
                continue
            for j in range(1, cols - 1):
                c = j * step
                if c - margin < 0 or c + margin > width - 1:
                    continue
                v = stack[k, i, j]
                if v <= threshold:
                    continue
                tr = laps[k, i, j]
                if edge_ratio > 0 and tr * tr * edge_ratio >= (edge_ratio + 1.0) ** 2 * v:
                    continue
                is_max = True
                for dk in range(-1, 2):
                    for di in range(-1, 2):
                        for dj in range(-1, 2):
                            if dk == 0 and di == 0 and dj == 0:
                                continue
                            if stack[k + dk, i + di, j + dj] >= v:
                                is_max = False
                                break
                        if not is_max:
                            break
                    if not is_max:
                        break
                if not is_max:
                    continue
                # quadratic fit: gradient and Hessian by central differences (x, y, layer)
                gx = 0.5 * (stack[k, i, j + 1] - stack[k, i, j - 1])
                gy = 0.5 * (stack[k, i + 1, j] - stack[k, i - 1, j])
                gs = 0.5 * (stack[k + 1, i, j] - stack[k - 1, i, j])
                hxx = stack[k, i, j + 1] + stack[k, i, j - 1] - 2.0 * v
                hyy = stack[k, i + 1, j] + stack[k, i - 1, j] - 2.0 * v
                hss = stack[k + 1, i, j] + stack[k - 1, i, j] - 2.0 * v
                hxy = 0.25 * (
                    stack[k, i + 1, j + 1] - stack[k, i + 1, j - 1] - stack[k, i - 1, j + 1] + stack[k, i - 1, j - 1]
                )
                hxs = 0.25 * (
                    stack[k + 1, i, j + 1] - stack[k + 1, i, j - 1] - stack[k - 1, i, j + 1] + stack[k - 1, i, j - 1]
                )
                hys = 0.25 * (
                    stack[k + 1, i + 1, j] - stack[k + 1, i - 1, j] - stack[k - 1, i + 1, j] + stack[k - 1, i - 1, j]
                )
                # solve H o = -g (Cramer's rule)
                a00, a01, a02 = hxx, hxy, hxs
                a11, a12, a22 = hyy, hys, hss
                c00 = a11 * a22 - a12 * a12
                c01 = a02 * a12 - a01 * a22
                c02 = a01 * a12 - a02 * a11
                dt = a00 * c00 + a01 * c01 + a02 * c02
                if dt == 0.0:
                    continue
                c11 = a00 * a22 - a02 * a02
                c12 = a01 * a02 - a00 * a12
                c22 = a00 * a11 - a01 * a01
                ox = -(c00 * gx + c01 * gy + c02 * gs) / dt
                oy = -(c01 * gx + c11 * gy + c12 * gs) / dt
                os_ = -(c02 * gx + c12 * gy + c22 * gs) / dt
                if abs(ox) > 1.0 or abs(oy) > 1.0 or abs(os_) > 1.0:
                    continue
                if count >= out.shape[0]:
                    return count
                out[count, 0] = (j + ox) * step
                out[count, 1] = (i + oy) * step
                out[count, 2] = sizes[k] + os_ * (sizes[k + 1] - sizes[k])
                out[count, 3] = v + 0.5 * (gx * ox + gy * oy + gs * os_)
                out[count, 4] = 1.0 if tr >= 0 else -1.0
                count += 1
    return count


@nb.njit(cache=True)
def _haar(ii: F64, x: int, y: int, half: int) -> tuple[float, float]:
    """Haar wavelet responses (x, y) of side 2*half centred on the corner between two pixels.

    The corner between pixels (x - 1, y - 1) and (x, y), i.e. at (x - 0.5, y - 0.5) (callers add 0.5
    before rounding).
    """
    dx = _box(ii, y - half, x, y + half, x + half) - _box(ii, y - half, x - half, y + half, x)
    dy = _box(ii, y, x - half, y + half, x + half) - _box(ii, y - half, x - half, y, x + half)
    return dx, dy


@nb.njit(cache=True)
def _ii_at(ii: F64, y: float, x: float) -> float:
    """The integral image at a real pixel-boundary position (x, y), bilinear and clipped to the image.

    The image is constant over each pixel, so its integral is bilinear within each pixel and
    the interpolation is exact: box sums with real-valued sides.
    """
    h = ii.shape[0] - 1
    w = ii.shape[1] - 1
    r = min(max(y + 0.5, 0.0), float(h))
    c = min(max(x + 0.5, 0.0), float(w))
    r0 = min(int(r), h - 1)
    c0 = min(int(c), w - 1)
    fr = r - r0
    fc = c - c0
    top = ii[r0, c0] + fc * (ii[r0, c0 + 1] - ii[r0, c0])
    bot = ii[r0 + 1, c0] + fc * (ii[r0 + 1, c0 + 1] - ii[r0 + 1, c0])
    return top + fr * (bot - top)


@nb.njit(cache=True)
def _cell(v: float, n: int) -> tuple[int, float]:
    """Integral-image index and fraction of a real pixel-boundary coordinate, clipped to [0, n]."""
    t = min(max(v + 0.5, 0.0), float(n))
    i = min(int(t), n - 1)
    return i, t - i


@nb.njit(cache=True)
def _bilinear(ii: F64, r: int, fr: float, c: int, fc: float) -> float:
    top = ii[r, c] + fc * (ii[r, c + 1] - ii[r, c])
    bot = ii[r + 1, c] + fc * (ii[r + 1, c + 1] - ii[r + 1, c])
    return top + fr * (bot - top)


@nb.njit(cache=True)
def _haar_f(ii: F64, x: float, y: float, half: float) -> tuple[float, float]:
    """Haar wavelet responses (x, y) of side ``2 half`` (real) centred on the real position (x, y).

    Neither the centre nor the side is rounded to whole pixels, so the responses of a rotated
    sampling grid do not depend on where it falls on the pixel grid. Box sums come from the
    integral image interpolated bilinearly (:func:`_ii_at`), which is exact for an image
    constant over each pixel; the four boxes share eight corners of a 3 x 3 grid.
    """
    h = ii.shape[0] - 1
    w = ii.shape[1] - 1
    r0, f0 = _cell(y - half, h)
    r1, f1 = _cell(y, h)
    r2, f2 = _cell(y + half, h)
    c0, g0 = _cell(x - half, w)
    c1, g1 = _cell(x, w)
    c2, g2 = _cell(x + half, w)
    a00 = _bilinear(ii, r0, f0, c0, g0)
    a01 = _bilinear(ii, r0, f0, c1, g1)
    a02 = _bilinear(ii, r0, f0, c2, g2)
    a10 = _bilinear(ii, r1, f1, c0, g0)
    a12 = _bilinear(ii, r1, f1, c2, g2)
    a20 = _bilinear(ii, r2, f2, c0, g0)
    a21 = _bilinear(ii, r2, f2, c1, g1)
    a22 = _bilinear(ii, r2, f2, c2, g2)
    # right minus left half; bottom minus top half
    dx = (a22 - a02 - a21 + a01) - (a21 - a01 - a20 + a00)
    dy = (a22 - a12 - a20 + a10) - (a12 - a02 - a10 + a00)
    return dx, dy


#: Angular bins of the orientation sweep (5 degrees); the 60-degree window spans 12.
_ORI_BINS = 72
_ORI_WIN = 12


@nb.njit(cache=True, parallel=True)
def _orientations(ii: F64, xy: F64, scale: F64, subpixel: bool, out: F64) -> None:
    """Dominant orientation of each keypoint.

    The weighted Haar responses are summed in 5-degree bins, a 60-degree window (12 bins) slides
    over them, and the direction of the longest window sum is the orientation.
    """
    n = xy.shape[0]
    for p in nb.prange(n):
        s = scale[p]
        x0 = xy[p, 0]
        y0 = xy[p, 1]
        half = max(int(np.round(2.0 * s)), 1)
        bx = np.zeros(_ORI_BINS)
        by = np.zeros(_ORI_BINS)
        for i in range(-6, 7):
            for j in range(-6, 7):
                if i * i + j * j >= 36:
                    continue
                g = np.exp(-(i * i + j * j) / 8.0)  # sigma = 2s in units of s
                if subpixel:
                    dx, dy = _haar_f(ii, x0 + i * s, y0 + j * s, 2.0 * s)
                else:
                    dx, dy = _haar(ii, int(np.round(x0 + i * s + 0.5)), int(np.round(y0 + j * s + 0.5)), half)
                if dx == 0.0 and dy == 0.0:
                    continue
                a = np.arctan2(dy, dx) + np.pi
                q = min(int(a * (_ORI_BINS / (2.0 * np.pi))), _ORI_BINS - 1)
                bx[q] += g * dx
                by[q] += g * dy
        sx = 0.0
        sy = 0.0
        for q in range(_ORI_WIN):
            sx += bx[q]
            sy += by[q]
        best = sx * sx + sy * sy
        ox = sx
        oy = sy
        for q in range(1, _ORI_BINS):
            e = (q + _ORI_WIN - 1) % _ORI_BINS
            sx += bx[e] - bx[q - 1]
            sy += by[e] - by[q - 1]
            mag = sx * sx + sy * sy
            if mag > best:
                best = mag
                ox = sx
                oy = sy
        out[p] = np.arctan2(oy, ox)


@nb.njit(cache=True, parallel=True)
def _descriptors_overlap(ii: F64, xy: F64, scale: F64, angle: F64, extended: bool, subpixel: bool, out: F32) -> None:
    """Descriptors with overlapping sub-regions (Agrawal, Konolige & Blas 2008).

    Haar responses on a 24 x 24 grid (step s) around the keypoint; each of the 4 x 4 sub-regions
    (centres 5s apart) sums the 9 x 9 samples around its centre weighted by a Gaussian of sigma
    2.5s, and its four sums are weighted by a Gaussian of sigma 1.5 sub-regions centred on the
    keypoint. Same layout as the standard descriptor.
    """
    n = xy.shape[0]
    dim = out.shape[1]
    g1 = np.empty(9)
    for k in range(9):
        g1[k] = np.exp(-((k - 4.0) ** 2) / (2.0 * 2.5 * 2.5))
    for p in nb.prange(n):
        s = scale[p]
        co = np.cos(angle[p])
        si = np.sin(angle[p])
        x0 = xy[p, 0]
        y0 = xy[p, 1]
        half = max(int(np.round(s)), 1)
        du = np.empty((24, 24))
        dv = np.empty((24, 24))
        for a in range(24):  # across the orientation (v)
            v = -11.5 + a
            for b in range(24):  # along it (u)
                u = -11.5 + b
                px = x0 + s * (co * u - si * v)
                py = y0 + s * (si * u + co * v)
                if subpixel:
                    rx, ry = _haar_f(ii, px, py, s)
                else:
                    rx, ry = _haar(ii, int(np.round(px + 0.5)), int(np.round(py + 0.5)), half)
                du[a, b] = co * rx + si * ry
                dv[a, b] = -si * rx + co * ry
        vec = np.zeros(dim)
        for a in range(4):
            for b in range(4):
                base = (a * 4 + b) * (8 if extended else 4)
                g2 = np.exp(-((a - 1.5) ** 2 + (b - 1.5) ** 2) / (2.0 * 1.5 * 1.5))
                for k in range(9):
                    for m in range(9):
                        g = g2 * g1[k] * g1[m]
                        x = g * du[5 * a + k, 5 * b + m]
                        y = g * dv[5 * a + k, 5 * b + m]
                        if not extended:
                            vec[base] += x
                            vec[base + 1] += y
                            vec[base + 2] += abs(x)
                            vec[base + 3] += abs(y)
                        else:
                            o = 0 if y < 0 else 2
                            vec[base + o] += x
                            vec[base + o + 1] += abs(x)
                            o = 4 if x < 0 else 6
                            vec[base + o] += y
                            vec[base + o + 1] += abs(y)
        nrm = np.sqrt(np.sum(vec * vec))
        if nrm > 0:
            vec /= nrm
        for d in range(dim):
            out[p, d] = vec[d]


@nb.njit(cache=True, parallel=True)
def _descriptors(ii: F64, xy: F64, scale: F64, angle: F64, extended: bool, subpixel: bool, out: F32) -> None:
    """SURF descriptors (64 or 128 per keypoint) -> ``out``."""
    n = xy.shape[0]
    dim = out.shape[1]
    for p in nb.prange(n):
        s = scale[p]
        co = np.cos(angle[p])
        si = np.sin(angle[p])
        x0 = xy[p, 0]
        y0 = xy[p, 1]
        half = max(int(np.round(s)), 1)
        vec = np.zeros(dim)
        for a in range(4):
            for b in range(4):
                base = (a * 4 + b) * (8 if extended else 4)
                for k in range(5):
                    for m in range(5):
                        u = -10.0 + 5 * b + k + 0.5  # along the orientation (units of s)
                        v = -10.0 + 5 * a + m + 0.5  # across it
                        g = np.exp(-(u * u + v * v) / (2.0 * 3.3 * 3.3))
                        px = x0 + s * (co * u - si * v)
                        py = y0 + s * (si * u + co * v)
                        if subpixel:
                            rx, ry = _haar_f(ii, px, py, s)
                        else:
                            rx, ry = _haar(ii, int(np.round(px + 0.5)), int(np.round(py + 0.5)), half)
                        du = g * (co * rx + si * ry)
                        dv = g * (-si * rx + co * ry)
                        if not extended:
                            vec[base] += du
                            vec[base + 1] += dv
                            vec[base + 2] += abs(du)
                            vec[base + 3] += abs(dv)
                        else:
                            o = 0 if dv < 0 else 2
                            vec[base + o] += du
                            vec[base + o + 1] += abs(du)
                            o = 4 if du < 0 else 6
                            vec[base + o] += dv
                            vec[base + o + 1] += abs(dv)
        nrm = np.sqrt(np.sum(vec * vec))
        if nrm > 0:
            vec /= nrm
        for d in range(dim):
            out[p, d] = vec[d]


@dataclass
class Surf:
    """The SURF detector/descriptor.

    ``threshold``: Hessian-determinant threshold (image scaled to [0, 1]);
    ``n_octaves`` and ``n_layers`` (filters per octave, >= 3); ``step0``: sampling step of
    the first octave in pixels, ``dense_octaves`` octaves keep it (then it doubles per
    octave); ``presmooth_sigma_px``: Gaussian smoothing before the integral image;
    ``edge_ratio``: if > 0, reject maxima whose box-filter Hessian has a principal
    curvature ratio above it (SIFT's edge test; off by default); ``max_features``: keep
    the strongest (0: all); ``extended``: 128-element descriptors; ``upright``: U-SURF
    (no orientation); ``overlap``: overlapping, Gaussian-weighted sub-regions (Agrawal et
    al. 2008, the "M-SURF" variant) instead of the paper's disjoint ones;
    ``smooth_per_octave``: the smoothing grows with the octave's filters
    (:meth:`octave_smoothing_px`); ``subpixel_haar``: Haar wavelets of real-valued centre and
    side (exact box sums by bilinear lookup of the integral image) instead of rounding both to
    whole pixels, in the orientation (and with ``subpixel_descriptor`` in the descriptor);
    ``describe_sigma_px``: the smoothing of the image that orientation and
    descriptor are computed on.
    """

    # Defaults measured with tools/bench_surf.py on fountain-P11 and the RTAB-Map corridor
    # images: a low threshold, so that ``max_features`` (the strongest) are kept even in
    # low-contrast images (5e-5 left 185 features in corridor image 50 and loop-detection
    # recall at 0.77; 1.5e-5: 0.84, precision 1.0 both, tools/bench_loopdet.py), and a Gaussian
    # pre-smoothing of 1.5 px, which raised the repeatability under rotation (30-180 deg)
    # and scale (0.5-2x) on both sets (e.g. rotation 90: 0.91 -> 0.96, scale 2: 0.55 -> 0.64).
    # Overlapping sub-regions raised the matching score on both sets (rotation 45:
    # 0.38 -> 0.41, scale 0.5: 0.60 -> 0.63) and the fountain relocalization inliers
    # (view 8: 140 -> 234 of about 330 matches).
    # Measured this session (issue 18) on the same two sets (fountain views 0, 5, corridor 1, 60):
    # with one smoothing for every octave, keypoints of the larger filters move under rotation
    # (median offset of repeated keypoints at rotation 30: 0.23 px below scale 2.3, 0.89 px above;
    # 0.08 / 0.18 under a pure sub-pixel shift), since the box filters' anisotropy grows with
    # their side while the smoothing stays; smoothing in proportion to the octave's filters
    # (smooth_per_octave) raised repeatability at rotation 30/45/135 from 0.55/0.57/0.58 to
    # 0.60/0.62/0.62 and at scale 0.5 from 0.76 to 0.83 (scale 2: 0.68 -> 0.66), and on the
    # fountain relocalization view 9's error from 0.53 deg / 62 mm to 0.10 deg / 18 mm. Haar
    # responses at rounded positions and sides made the orientation depend on the pixel grid
    # (median orientation error at rotation 90: 1.25 deg; with subpixel_haar 0.23 deg); in the
    # descriptor as well (subpixel_descriptor) they kept loop-detection recall at 0.818 (rounded:
    # 0.795) and fountain view 10 at 0.21 deg (rounded: 0.38 deg), for 1.13x SIFT's time on
    # 640x480 (rounded: 0.82x; tools/bench.py surf, load 11-19).
    # Descriptors computed on the detector's 1.5 px smoothing lose detail at small scales:
    # describe_sigma_px 0.8 lifted the fountain view 10 relocalization from 52 inliers of 255
    # matches (ratio 0.20, failed) to 67 of 253 (0.26; 0.5: 62/254, failed).
    # (the defaults are those of loopmodel.config.SurfConfig, the one place they are set)
    threshold: float = _DEFAULTS.threshold
    n_octaves: int = _DEFAULTS.n_octaves
    n_layers: int = _DEFAULTS.n_layers
    step0: int = _DEFAULTS.step0
    dense_octaves: int = _DEFAULTS.dense_octaves
    presmooth_sigma_px: float = _DEFAULTS.presmooth_sigma_px
    edge_ratio: float = _DEFAULTS.edge_ratio
    overlap: bool = _DEFAULTS.overlap
    max_features: int = 2000
    extended: bool = _DEFAULTS.extended
    upright: bool = _DEFAULTS.upright
    smooth_per_octave: bool = _DEFAULTS.smooth_per_octave
    subpixel_haar: bool = _DEFAULTS.subpixel_haar
    describe_sigma_px: float = _DEFAULTS.describe_sigma_px
    subpixel_descriptor: bool = _DEFAULTS.subpixel_descriptor

    @classmethod
    def from_config(cls, config: SurfConfig | None, max_features: int) -> Surf:
        """The detector of a ``loop.surf`` section, keeping at most ``max_features``."""
        return cls(max_features=max_features, **(config if config is not None else _DEFAULTS).model_dump())

    @property
    def dim(self) -> int:
        """Descriptor length (64 or 128)."""
        return 128 if self.extended else 64

    def filter_sizes(self, octave: int) -> NDArray[np.int64]:
        """Box-filter sides of one octave (9, 15, 21, 27; 15, 27, 39, 51; ...)."""
        k = np.arange(1, self.n_layers + 1)
        return np.asarray(3 * (2 ** (octave + 1) * k + 1), dtype=np.int64)

    def octave_smoothing_px(self, octave: int) -> float:
        """Gaussian sigma (px) of the image the Hessian of ``octave`` is computed on.

        ``presmooth_sigma_px`` in the first octave; with ``smooth_per_octave`` it grows in
        proportion to the octave's detection filters (the middle layers' mean side), so that the
        smoothing keeps the same size relative to the box filters at every scale.
        """
        if not self.smooth_per_octave or octave == 0:
            return self.presmooth_sigma_px
        mid = self.filter_sizes(octave)[1:-1].mean()
        return float(self.presmooth_sigma_px * mid / self.filter_sizes(0)[1:-1].mean())

    def integral(self, image: NDArray[np.generic]) -> F64:
        """The integral image the detector (its first octave) and the Laplacian sign work on."""
        return integral_image(image, self.presmooth_sigma_px)

    def describe_integral(self, image: NDArray[np.generic], ii: F64 | None = None) -> F64:
        """The integral image orientation and descriptor work on (``describe_sigma_px``).

        ``ii``: the detector's, reused when both smoothings are equal.
        """
        if ii is not None and self.describe_sigma_px == self.presmooth_sigma_px:
            return ii
        return integral_image(image, self.describe_sigma_px)

    def detect(
        self, image: NDArray[np.generic], ii: F64 | None = None, ii_describe: F64 | None = None
    ) -> SurfKeypoints:
        """Fast-Hessian keypoints with orientation (0 when upright) of a grey image.

        ``ii`` / ``ii_describe``: the integral images of :meth:`integral` and
        :meth:`describe_integral` when the caller has them.
        """
        img = np.asarray(image)
        if ii is None:
            ii = self.integral(img)
        h, w = img.shape[:2]
        cap = 200_000
        found = np.zeros((cap, 5))
        count = 0
        for o in range(self.n_octaves):
            step = self.step0 * 2 ** max(o - self.dense_octaves + 1, 0)
            sizes = self.filter_sizes(o)
            if sizes[-1] >= min(h, w):
                break
            rows = (h - 1) // step + 1
            cols = (w - 1) // step + 1
            stack = np.zeros((sizes.size, rows, cols), np.float32)
            laps = np.zeros((sizes.size, rows, cols), np.float32)
            sigma = self.octave_smoothing_px(o)
            ii_o = ii if sigma == self.presmooth_sigma_px else integral_image(img, sigma)
            _hessian_octave(ii_o, sizes, step, stack, laps)
            count = _extrema(stack, laps, sizes, step, self.threshold, self.edge_ratio, h, w, found, count)
        kp = found[:count]
        if self.max_features and count > self.max_features:
            kp = kp[np.argsort(-kp[:, 3], kind="stable")[: self.max_features]]
        xy = np.ascontiguousarray(kp[:, :2])
        scale = 1.2 * kp[:, 2] / 9.0
        angle = np.zeros(kp.shape[0])
        if not self.upright and kp.shape[0]:
            iid = self.describe_integral(img, ii) if ii_describe is None else ii_describe
            _orientations(iid, xy, np.ascontiguousarray(scale), self.subpixel_haar, angle)
        return SurfKeypoints(xy, scale, angle, kp[:, 3].copy(), kp[:, 4].astype(np.int8))

    def orient(self, image: NDArray[np.generic], xy: F64, scale: F64, ii: F64 | None = None) -> F64:
        """Dominant orientations (radians) at positions (N, 2) and scales (N,); ``ii``: :meth:`describe_integral`."""
        ii = self.describe_integral(image) if ii is None else ii
        out = np.zeros(xy.shape[0])
        if xy.shape[0] and not self.upright:
            _orientations(
                ii,
                np.ascontiguousarray(xy, dtype=float),
                np.ascontiguousarray(scale, dtype=float),
                self.subpixel_haar,
                out,
            )
        return out

    def describe(self, image: NDArray[np.generic], kp: SurfKeypoints, ii: F64 | None = None) -> F32:
        """Descriptors (N, 64 or 128) float32 of given keypoints; ``ii``: :meth:`describe_integral`."""
        ii = self.describe_integral(image) if ii is None else ii
        out = np.zeros((len(kp), self.dim), np.float32)
        if len(kp):
            kernel = _descriptors_overlap if self.overlap else _descriptors
            kernel(
                ii,
                np.ascontiguousarray(kp.xy, dtype=float),
                np.ascontiguousarray(kp.scale, dtype=float),
                np.ascontiguousarray(kp.angle, dtype=float),
                self.extended,
                self.subpixel_descriptor,
                out,
            )
        return out

    def detect_and_describe(self, image: NDArray[np.generic]) -> tuple[SurfKeypoints, F32]:
        """Keypoints and their descriptors of a grey image."""
        ii = self.integral(image)
        iid = self.describe_integral(image, ii)
        kp = self.detect(image, ii, iid)
        return kp, self.describe(image, kp, iid)

    def laplacian_sign(
        self, image: NDArray[np.generic], xy: F64, scale: F64, ii: F64 | None = None
    ) -> NDArray[np.int8]:
        """Sign of the box-filter Laplacian at given positions and scales (N,)."""
        ii = self.integral(image) if ii is None else ii
        out = np.ones(xy.shape[0], np.int8)
        if xy.shape[0]:
            _laplacian_at(ii, np.ascontiguousarray(xy, dtype=float), np.ascontiguousarray(scale, dtype=float), out)
        return out


@nb.njit(cache=True)
def _laplacian_at(ii: F64, xy: F64, scale: F64, out: NDArray[np.int8]) -> None:
    for p in range(xy.shape[0]):
        size = int(np.round(scale[p] * 9.0 / 1.2 / 6.0)) * 6 + 3  # nearest side 3 (mod 6)
        size = max(size, 9)
        lobe = size // 3
        b = (size - 1) // 2
        hl = (lobe - 1) // 2
        r = int(np.round(xy[p, 1]))
        c = int(np.round(xy[p, 0]))
        dyy = _box(ii, r - b, c - lobe + 1, r + b + 1, c + lobe) - 3.0 * _box(
            ii, r - hl, c - lobe + 1, r + hl + 1, c + lobe
        )
        dxx = _box(ii, r - lobe + 1, c - b, r + lobe, c + b + 1) - 3.0 * _box(
            ii, r - lobe + 1, c - hl, r + lobe, c + hl + 1
        )
        out[p] = 1 if dxx + dyy >= 0 else -1
