"""Beyond the paper: Fisher information for a finite pixel size.

The image (sharp marker convolved with a Gaussian PSF of sigma ``psf_sigma_px``) is integrated
over square pixels of pitch ``pixel_px`` (in the pixels of the noise convention, see
``loopmodel.accuracy``); a pixel of area p^2 then carries white noise of variance
``(N0/2) / p^2``. The derivative of a pixel's mean brightness is a contour integral,

    d mu_k / d A_i = contour_integral (n.Q_i)(l) K(c_k - l) dl,
    K(D) = prod_{x,y} [Phi((D + p/2)/sigma) - Phi((D - p/2)/sigma)] / p^2,

and ``J = (p^2 / (N0/2)) sum_k grad(mu_k) grad(mu_k)^T``, averaged over random sub-pixel
positions of the pixel grid. As p -> 0 it tends to the contour bound (with the default PSF);
``psf_sigma_px = 0`` gives a sharp image on box pixels, whose information grows as 1/p.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

from loopmodel.accuracy import PSF_SIGMA_PX
from loopmodel.accuracy.marker import Marker
from loopmodel.accuracy.view import Views, flows, image_tangents, project

F64 = NDArray[np.float64]


def _contour_terms(marker: Marker, view: Views, step_px: float) -> tuple[F64, F64, F64]:
    """Image points (M, 2), arc-length weights (M,) and n.Q (M, 4) of a fine contour."""
    img_size = float(np.ptp(project(view, marker.outlines(64)[0][0])[0], axis=0).max())
    size_m = max(float(np.ptp(v, axis=0).max()) for v, _ in marker.outlines(64))
    px_per_m = img_size / max(size_m, 1e-12)
    longest = max(
        float(np.max(np.linalg.norm(np.roll(v, -1, 0) - v, axis=1))) for v, _ in marker.outlines(64)
    )
    n_edge = max(8, math.ceil(2.0 * longest * px_per_m / step_px))
    circ = max([s.perimeter for s in marker.shapes if not hasattr(s, "vertices")] + [0.0])
    n_circle = max(64, math.ceil(2.0 * circ * px_per_m / step_px))
    cs = marker.contour(n_edge, n_circle)
    a = project(view, cs.points)[0]
    Q = flows(view, cs.points)[0]
    adot = image_tangents(view, cs.points, cs.tangents)[0]
    speed = np.linalg.norm(adot, axis=1)
    n = np.column_stack([adot[:, 1], -adot[:, 0]]) / speed[:, None]
    return a, cs.weights * speed, np.einsum("mik,mk->mi", Q, n)


def _box_gauss(i: NDArray[np.int64], x: F64, s: float) -> F64:
    """Share of a unit Gaussian blob of sigma s (pixels) centred at x falling into pixel i."""
    d = i + 0.5 - x[:, None]
    return ndtr((d + 0.5) / s) - ndtr((d - 0.5) / s)


def fisher_pixels(
    marker: Marker,
    view: Views,
    noise: float,
    pixel_px: float,
    psf_sigma_px: float = PSF_SIGMA_PX,
    n_phase: int = 4,
    rng: np.random.Generator | None = None,
) -> F64:
    """(4, 4) Fisher information of ``A`` from pixels of pitch ``pixel_px`` for one camera (``view`` with n = 1).

    ``noise`` = N0/2 (contrast^2 px^2).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    p, sg = float(pixel_px), float(psf_sigma_px)
    step = min(p, sg if sg > 0 else p) / (4.0 if sg > 0 else 16.0)
    pts, dl, nq = _contour_terms(marker, view, step)
    wq = dl[:, None] * nq  # (M, 4)
    J = np.zeros((4, 4))
    for _ in range(n_phase):
        off = rng.uniform(0.0, p, size=2)
        rel = (pts - off) / p  # pixel coordinates
        if sg == 0.0:
            ij = np.floor(rel).astype(np.int64)
            ij -= ij.min(axis=0)
            key = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
            _, inv = np.unique(key, return_inverse=True)
            grad = np.column_stack([np.bincount(inv, wq[:, i]) for i in range(4)]) / p**2
        else:
            reach = 0.5 + 6.0 * sg / p
            w = int(math.ceil(2 * reach)) + 1
            base = np.floor(rel - reach).astype(np.int64)  # (M, 2)
            k = np.arange(w)
            ix = base[:, 0:1] + k[None, :]  # (M, w)
            iy = base[:, 1:2] + k[None, :]
            s = sg / p

            kx, ky = _box_gauss(ix, rel[:, 0], s), _box_gauss(iy, rel[:, 1], s)  # (M, w)
            weight = (kx[:, :, None] * ky[:, None, :]).reshape(len(pts), -1) / p**2
            gx = np.repeat(ix, w, axis=1) - ix.min()
            gy = np.tile(iy, (1, w)) - iy.min()
            key = (gx * (gy.max() + 1) + gy).ravel()
            uniq, inv = np.unique(key, return_inverse=True)
            grad = np.column_stack(
                [
                    np.bincount(inv, (weight * wq[:, i : i + 1]).ravel(), minlength=len(uniq))
                    for i in range(4)
                ]
            )
        J += (p**2 / noise) * grad.T @ grad
    return J / n_phase
