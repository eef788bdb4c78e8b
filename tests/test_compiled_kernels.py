"""The front end's compiled kernels against independent numpy computations (issue 33/36: cost, same results).

- :func:`loopmodel.frontend.affine_klt.refine_affine` (per feature, numba) against a batched numpy
  Gauss-Newton of the same model sampled with ``cv2.remap``;
- the stereo row scan against ZNCC computed directly in float64;
- the stereo column fit against a known sub-pixel shift.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from loopmodel.frontend._stereo_kernels import row_gradient, row_peaks, zncc_scan
from loopmodel.frontend.affine_klt import refine_affine
from loopmodel.frontend.stereo import MIN_DISPARITY_SIGMA_PX, _zncc_scan


def _texture(rng: np.random.Generator, shape: tuple[int, int] = (240, 320)) -> np.ndarray:
    img = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min())
    return np.clip(20 + 215 * img, 0, 255).astype(np.uint8)


def _remap(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return cv2.remap(img, x.astype(np.float32), y.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).astype(np.float64)


def _numpy_affine(ref: np.ndarray, cur: np.ndarray, uv_ref: np.ndarray, guess: np.ndarray, h: int,
                  iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Batched Gauss-Newton over (position, 2x2 warp, gain, offset), images sampled by OpenCV."""
    n = len(uv_ref)
    c, A = guess.astype(float).copy(), np.tile(np.eye(2), (n, 1, 1))
    gain, offset, active = np.ones(n), np.zeros(n), np.ones(n, bool)
    reff, curf = ref.astype(np.float32), cur.astype(np.float32)
    gx = cv2.Sobel(curf, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    gy = cv2.Sobel(curf, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
    s = np.arange(-h, h + 1, dtype=float)
    sx, sy = (a.ravel()[None] for a in np.meshgrid(s, s))
    T = _remap(reff, uv_ref[:, :1] + sx, uv_ref[:, 1:] + sy)
    for _ in range(iterations):
        i = np.flatnonzero(active)
        if not i.size:
            break
        x = c[i, :1] + A[i, 0, :1] * sx + A[i, 0, 1:] * sy
        y = c[i, 1:] + A[i, 1, :1] * sx + A[i, 1, 1:] * sy
        Gx, Gy = _remap(gx, x, y), _remap(gy, x, y)
        r = _remap(curf, x, y) - (gain[i, None] * T[i] + offset[i, None])
        J = np.stack([Gx, Gy, Gx * sx, Gx * sy, Gy * sx, Gy * sy, -T[i], -np.ones_like(Gx)], axis=1)
        H = J @ J.transpose(0, 2, 1)
        H[:, range(8), range(8)] += 1e-6 * (1.0 + H[:, range(8), range(8)])
        dp = -np.linalg.solve(H, (J @ r[:, :, None]))[:, :, 0]
        c[i] += dp[:, :2]
        A[i] += dp[:, 2:6].reshape(-1, 2, 2)
        gain[i] += dp[:, 6]
        offset[i] += dp[:, 7]
        active[i[np.abs(dp[:, :2]).max(axis=1) < 1e-3]] = False
    x = c[:, :1] + A[:, 0, :1] * sx + A[:, 0, 1:] * sy
    y = c[:, 1:] + A[:, 1, :1] * sx + A[:, 1, 1:] * sy
    Ic = _remap(curf, x, y)
    tc, ic = T - T.mean(1, keepdims=True), Ic - Ic.mean(1, keepdims=True)
    return c, np.sum(tc * ic, 1) / np.sqrt(np.sum(tc * tc, 1) * np.sum(ic * ic, 1) + 1e-9)


def test_compiled_affine_refinement_matches_a_numpy_gauss_newton(rng: np.random.Generator) -> None:
    ref = _texture(rng)
    # the current image: the reference warped by a small affine map (rotation 4 deg, scale 1.05)
    M = np.array([[1.05 * np.cos(0.07), -np.sin(0.07), 6.3], [np.sin(0.07), 1.05 * np.cos(0.07), -4.2]])
    cur = cv2.warpAffine(ref, M, (ref.shape[1], ref.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    uv_ref = rng.uniform([40, 40], [280, 200], (60, 2))
    truth = uv_ref @ M[:, :2].T + M[:, 2]
    guess = truth + rng.uniform(-1.0, 1.0, truth.shape)
    m = refine_affine(ref, cur, uv_ref, guess, None, 7, min_ncc=0.8, max_shift_px=3.0)
    c_np, ncc_np = _numpy_affine(ref, cur, uv_ref, guess, 7)
    assert m.ok.sum() >= 58
    # measured: 1.3e-6 px and 8e-9 between the two (60 of 60 ok); 0.038 px from the truth at most
    assert np.abs(m.uv_px - c_np)[m.ok].max() < 1e-4
    assert np.abs(m.ncc - ncc_np)[m.ok].max() < 1e-5
    assert np.abs(m.uv_px - truth)[m.ok].max() < 0.1



def test_compiled_affine_refinement_at_the_border_matches_numpy(rng: np.random.Generator) -> None:
    """Patches that cross the image border (the clamped samples) beside patches inside (the unclamped path)."""
    ref = _texture(rng)
    M = np.array([[np.cos(0.03), -np.sin(0.03), 1.7], [np.sin(0.03), np.cos(0.03), -1.2]])
    cur = cv2.warpAffine(ref, M, (ref.shape[1], ref.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    h, w = ref.shape
    # within 2-12 px of an edge: the 15 x 15 patch crosses it in one image or both; and some inside
    edge = np.column_stack([rng.uniform(2, 12, 40), rng.uniform(20, h - 20, 40)])
    edge[10:20, 0] = w - 1 - edge[10:20, 0]
    edge[20:30] = edge[20:30, ::-1] * [w / h, 1.0]
    edge[20:30, 1] = rng.uniform(2, 12, 10)
    edge[30:40, 1] = h - 1 - rng.uniform(2, 12, 10)
    uv_ref = np.vstack([edge, rng.uniform([40, 40], [280, 200], (20, 2))])
    guess = uv_ref @ M[:, :2].T + M[:, 2] + rng.uniform(-0.5, 0.5, uv_ref.shape)
    m = refine_affine(ref, cur, uv_ref, guess, None, 7, min_ncc=-1.0, max_shift_px=3.0)
    c_np, ncc_np = _numpy_affine(ref, cur, uv_ref, guess, 7)
    both = m.ok & np.isfinite(c_np).all(axis=1)
    assert both[:40].sum() >= 30 and both[40:].all()
    # measured: 7.3e-6 px and 1.4e-6 NCC apart at most, 34 of the 40 border patches ok in both
    assert np.abs(m.uv_px - c_np)[both].max() < 1e-4
    assert np.abs(m.ncc - ncc_np)[both].max() < 1e-5

@pytest.mark.parametrize(("length", "half"), [(9, 3), (7, 5), (1, 2), (40, 3)])
def test_compiled_zncc_scan_matches_float64_zncc(rng: np.random.Generator, length: int, half: int) -> None:
    """Both paths of the scan: a long row (vectorised over the windows), a short one (eight windows in registers)."""
    src, dst = _texture(rng, (80, 120)), _texture(rng, (80, 120))
    pad = 10 if length < 20 else 40
    u = rng.integers(20, min(90, 120 - length - half + 5), 25)  # every window inside the unpadded image
    v = rng.integers(20, 60, 25)
    start = u - 6
    rows = (-1, 0, 1)
    srcp = cv2.copyMakeBorder(src, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    dstp = cv2.copyMakeBorder(dst, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    got = _zncc_scan(srcp, dstp, pad, u, v, start, length, half, rows)
    want = np.empty_like(got, dtype=float)
    for i in range(len(u)):
        t = src[v[i] - half : v[i] + half + 1, u[i] - half : u[i] + half + 1].astype(float)
        t = t - t.mean()
        for ri, r in enumerate(rows):
            for k in range(length):
                cx, cy = start[i] + k, v[i] + r
                w = dst[cy - half : cy + half + 1, cx - half : cx + half + 1].astype(float)
                w = w - w.mean()
                want[i, ri, k] = np.sum(t * w) / (np.sqrt(np.sum(t * t)) * np.sqrt(np.sum(w * w)))
    assert np.abs(got - want).max() < 5e-5  # float32 sums; measured 4.7e-6
    with pytest.raises(ValueError):  # a window beyond the padding is refused, never read
        _zncc_scan(srcp, dstp, pad, u, v, start - pad - 30, length, half, rows)


def test_compiled_row_peaks_match_numpy_masks_and_maxima(rng: np.random.Generator) -> None:
    """The coarse scan's best window inside the image and its margin (fe8): numpy's argmax, ties included."""
    for trial in range(40):
        n, length = 30, int(rng.integers(1, 90))
        levels = np.linspace(-1, 1, 7).astype(np.float32)  # every other trial: many ties
        sc = rng.choice(levels, (n, length)) if trial % 2 else rng.uniform(-1, 1, (n, length)).astype(np.float32)
        start = rng.integers(-20, 600, n).astype(np.int64)
        lo, hi = 3, int(rng.integers(0, 620))
        masked = sc.copy()
        col = start[:, None] + np.arange(length)
        masked[(col < lo) | (col > hi)] = -2.0
        k = np.argmax(masked, axis=1)
        apart = np.abs(np.arange(length)[None, :] - k[:, None]) > 2
        margin = (masked[np.arange(n), k] - np.max(np.where(apart, masked, -2.0), axis=1)).astype(float)
        got_k, got_margin = row_peaks(sc, start, lo, hi, 2)
        np.testing.assert_array_equal(got_k, k)
        np.testing.assert_array_equal(got_margin, margin)


def test_compiled_column_fit_recovers_a_sub_pixel_shift() -> None:
    y, x = np.mgrid[0:60, 0:200].astype(float)

    def tex(xx: np.ndarray) -> np.ndarray:  # smooth, analytic: the shifted image needs no resampling
        return 128 + 50 * np.sin(xx / 3.1) * np.cos(y / 4.3) + 40 * np.sin(xx / 7.7 + y / 5.9)

    shift = 0.37
    src = np.rint(tex(x)).astype(np.uint8)
    dst = np.rint(tex(x + shift)).astype(np.uint8)  # dst(x - shift) = src(x)
    u = np.arange(40, 160, 10, dtype=np.int64)
    v = np.full(u.size, 30, np.int64)
    col, sigma = row_gradient(src, dst, 0, u, v, u.astype(float), v, 5, 4, MIN_DISPARITY_SIGMA_PX)
    # measured: within 0.027 px of u - shift (grey levels rounded to integers), sigma at its 0.05 px floor
    assert np.abs(col - (u - shift)).max() < 0.04
    assert np.all(sigma >= MIN_DISPARITY_SIGMA_PX) and np.all(sigma < 0.1)
    # the scan on the same unpadded pair: windows inside the image are allowed
    assert zncc_scan(src, dst, 0, u, v, u - 2, 5, 3, np.zeros(1, np.int64)).shape == (u.size, 1, 5)


def test_compiled_vocabulary_descent_gives_the_nearest_child_words(rng: np.random.Generator) -> None:
    from loopmodel.io.vocabulary_file import shipped_vocabulary
    from loopmodel.loop.vocabulary import hamming_to

    voc = shipped_vocabulary("orb")
    assert voc is not None and voc.binary
    desc = rng.integers(0, 256, (300, voc.centers.shape[1]), dtype=np.uint8)
    want = np.empty(len(desc), np.int64)
    for i, d in enumerate(desc):  # one descriptor at a time, numpy's Hamming distances, first on a tie
        node = 0
        while (voc.children[node] >= 0).any():
            ch = voc.children[node][voc.children[node] >= 0]
            node = int(ch[np.argmin(hamming_to(d[None], voc.centers[ch])[0])])
        want[i] = voc.word[node]
    assert np.array_equal(voc.transform(desc), want)
