"""Exact rendering of a marker image seen through a Gaussian PSF, with its parameter Jacobian.

The marker image (brightness 1 on the marker) is convolved with an isotropic Gaussian of
sigma ``psf_sigma_px`` and sampled at the centres of an h x h px grid. Polygons are exact;
circles are replaced by inscribed regular polygons (the same polygons for the data and for
the model, so the Monte-Carlo model is exactly right). Per sample and edge:

* value: winding number (scan-line parity) minus, for every edge within the cut-off, the
  Owen's-T term of the Gaussian integral over the triangle (sample, edge start, edge end);
* Jacobian: ``d s / d A_i = contour_integral (n.Q_i) G dl``; along a straight image edge
  ``n.Q_i`` is exactly quadratic in arc length (1/depth is affine on the image of a plane),
  so each edge's integral is a closed form in ``erf``.

Only samples within the cut-off (``cutoff_sigmas`` PSF sigmas plus ``margin_px``) of the
contour are kept: elsewhere the image is 0 or 1 to within exp(-cutoff^2/2) for any
parameters that move the contour by less than ``margin_px``, so a maximum-likelihood fit on
the band equals the fit on the whole image.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import erf, erfc, owens_t

from loopmodel.accuracy.marker import Marker
from loopmodel.accuracy.view import Views, flows, project
from loopmodel.errors import InputError

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class BlurredRenderer:
    """Renders one camera's view of a marker on a band of samples around the contour.

    ``view``: a single camera (``Views`` with n = 1) at its nominal pose; ``psf_sigma_px``:
    Gaussian PSF sigma (px); ``sample_px``: sample pitch h (px); ``n_circle``: polygon
    vertices per circle; ``max_edge_px``: piece length for finding the band (px).
    """

    def __init__(
        self,
        marker: Marker,
        view: Views,
        psf_sigma_px: float,
        sample_px: float = 0.25,
        n_circle: int = 96,
        max_edge_px: float = 4.0,
        cutoff_sigmas: float = 6.0,
        margin_px: float = 0.3,
    ) -> None:
        if view.n != 1:
            raise InputError(None, "BlurredRenderer needs exactly one camera")
        if psf_sigma_px <= 0 or sample_px <= 0:
            raise InputError(None, "psf sigma and sample pitch must be > 0")
        self.view = view
        self.sigma = float(psf_sigma_px)
        self.h = float(sample_px)
        self.cutoff_px = cutoff_sigmas * self.sigma
        nominal = view.with_params(np.zeros(4))
        pa, pb = [], []
        for verts, hole in marker.outlines(n_circle):
            img = project(nominal, verts)[0]
            x, y = img[:, 0], img[:, 1]
            area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
            if (area > 0) == hole:  # bright region must lie left of each edge
                verts = verts[::-1]
            pa.append(verts)
            pb.append(np.roll(verts, -1, axis=0))
        self.pa = np.concatenate(pa)
        self.pb = np.concatenate(pb)
        self.pm = 0.5 * (self.pa + self.pb)
        self._build_band(nominal, self.cutoff_px + margin_px, max_edge_px)

    # -- set-up ---------------------------------------------------------------------------
    def _build_band(self, nominal: Views, reach: float, max_edge_px: float) -> None:
        h = self.h
        a0 = project(nominal, self.pa)[0]
        b0 = project(nominal, self.pb)[0]
        # split long edges into pieces only to enumerate nearby grid cells cheaply
        pieces = np.maximum(1, np.ceil(np.linalg.norm(b0 - a0, axis=1) / max_edge_px)).astype(
            np.int64
        )
        parent = np.repeat(np.arange(len(a0)), pieces)
        kth = np.arange(pieces.sum()) - np.repeat(np.cumsum(pieces) - pieces, pieces)
        ta, tb = (kth / pieces[parent])[:, None], ((kth + 1) / pieces[parent])[:, None]
        a = a0[parent] + ta * (b0 - a0)[parent]
        b = a0[parent] + tb * (b0 - a0)[parent]
        lo = np.minimum(a, b) - reach
        hi = np.maximum(a, b) + reach
        i0, j0 = np.floor(lo[:, 0] / h).astype(np.int64), np.floor(lo[:, 1] / h).astype(np.int64)
        i1, j1 = np.ceil(hi[:, 0] / h).astype(np.int64), np.ceil(hi[:, 1] / h).astype(np.int64)
        ni, nj = i1 - i0 + 1, j1 - j0 + 1
        counts = ni * nj
        piece = np.repeat(np.arange(len(a)), counts)
        off = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        ci = i0[piece] + off // nj[piece]
        cj = j0[piece] + off % nj[piece]
        px, py = (ci + 0.5) * h, (cj + 0.5) * h
        d = _segment_distance(np.column_stack([px, py]), a[piece], b[piece])
        keep = d <= reach
        ci, cj, edge = ci[keep], cj[keep], parent[piece[keep]]
        jmin = cj.min()
        key = ci * (1 << 31) + (cj - jmin)
        cells, inverse = np.unique(key, return_inverse=True)
        self.samples = np.column_stack(
            [(cells >> 31) * h + 0.5 * h, ((cells & ((1 << 31) - 1)) + jmin + 0.5) * h]
        )
        pair = np.unique(inverse.astype(np.int64) * len(a0) + edge)
        self.pair_sample: I64 = pair // len(a0)
        self.pair_edge: I64 = pair % len(a0)
        self.row = (cells & ((1 << 31) - 1)).astype(np.int64)
        self.row_y0 = (jmin + 0.5) * h

    @property
    def n_samples(self) -> int:
        """Number of samples in the band."""
        return len(self.samples)

    # -- rendering ------------------------------------------------------------------------
    def _parity(self, a: F64, b: F64) -> F64:
        """Even-odd inside test of every band sample against the image edges a->b."""
        h, y0 = self.h, self.row_y0
        ya, yb = a[:, 1], b[:, 1]
        jlo = np.floor((np.minimum(ya, yb) - y0) / h).astype(np.int64)
        jhi = np.ceil((np.maximum(ya, yb) - y0) / h).astype(np.int64)
        counts = np.maximum(jhi - jlo + 1, 0)
        e = np.repeat(np.arange(len(a)), counts)
        j = jlo[e] + np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        y = y0 + j * h
        hit = (ya[e] <= y) != (yb[e] <= y)
        e, j, y = e[hit], j[hit], y[hit]
        xc = a[e, 0] + (y - ya[e]) * (b[e, 0] - a[e, 0]) / (yb[e] - ya[e])
        span = float(max(np.ptp(self.samples[:, 0]), np.ptp(xc) if len(xc) else 0.0)) * 4 + 10.0
        xmin = float(min(self.samples[:, 0].min(), xc.min() if len(xc) else 0.0))
        ckey = np.sort(j * span + (xc - xmin))
        skey = self.row * span + (self.samples[:, 0] - xmin)
        below = np.searchsorted(ckey, skey) - np.searchsorted(ckey, self.row * span - 0.5)
        return (below % 2).astype(float)

    def render(self, params: ArrayLike) -> tuple[F64, F64]:
        """Sample values (K,) and Jacobian d values / d A (K, 4) at parameters ``params``.

        The parameters are offsets (r, v, u, gamma) from the nominal pose; m, m, m, rad.
        """
        v = self.view.with_params(np.asarray(params, dtype=float).reshape(1, 4))
        E = len(self.pa)
        pts = np.concatenate([self.pa, self.pm, self.pb])
        img = project(v, pts)[0]
        Q = flows(v, pts)[0]
        a, m, b = img[:E], img[E : 2 * E], img[2 * E :]
        d = b - a
        L = np.linalg.norm(d, axis=1)
        u = d / L[:, None]
        n = np.column_stack([u[:, 1], -u[:, 0]])  # outward normal
        qa = np.einsum("eik,ek->ei", Q[:E], n)
        qm = np.einsum("eik,ek->ei", Q[E : 2 * E], n)
        qb = np.einsum("eik,ek->ei", Q[2 * E :], n)
        sm = np.sum((m - a) * u, axis=1)[:, None]
        f01 = (qm - qa) / sm
        f12 = (qb - qm) / (L[:, None] - sm)
        c2 = (f12 - f01) / L[:, None]
        c1 = f01 - c2 * sm
        c0 = qa

        k, e = self.pair_sample, self.pair_edge
        rel = self.samples[k] - a[e]
        s0 = np.sum(rel * u[e], axis=1)
        dn = np.sum(rel * n[e], axis=1)
        sg = self.sigma
        alpha, beta = -s0, L[e] - s0
        # value: parity minus Owen's T terms of the near edges
        dist = np.maximum(np.abs(dn), 1e-12)
        hh = dist / sg
        sgn = np.where(dn <= 0, 1.0, -1.0)
        # feet well inside the edge: T(h, inf) - T(h, -inf) = erfc(h / sqrt 2) / 2
        tt = 0.5 * erfc(hh / math.sqrt(2.0))
        ends = (alpha > -self.cutoff_px) | (beta < self.cutoff_px)
        tt[ends] = owens_t(hh[ends], beta[ends] / dist[ends]) - owens_t(
            hh[ends], alpha[ends] / dist[ends]
        )
        K = self.n_samples
        values: F64 = self._parity(a, b) - np.bincount(k, sgn * tt, minlength=K)
        # Jacobian: Gaussian moments along each edge
        r2 = math.sqrt(2.0) * sg
        ea, eb = np.exp(-((alpha / r2) ** 2)), np.exp(-((beta / r2) ** 2))
        I0 = sg * math.sqrt(math.pi / 2.0) * (erf(beta / r2) - erf(alpha / r2))
        I1 = sg**2 * (ea - eb)
        I2 = sg**2 * I0 + sg**2 * (alpha * ea - beta * eb)
        g = np.exp(-((dn / r2) ** 2)) / (2.0 * math.pi * sg**2)
        C0, C1, C2 = c0[e], c1[e], c2[e]
        s0c = s0[:, None]
        b0 = C0 + C1 * s0c + C2 * s0c**2
        b1 = C1 + 2.0 * C2 * s0c
        contrib = g[:, None] * (b0 * I0[:, None] + b1 * I1[:, None] + C2 * I2[:, None])
        jac = np.column_stack([np.bincount(k, contrib[:, i], minlength=K) for i in range(4)])
        return values, jac.astype(float)


def _segment_distance(p: F64, a: F64, b: F64) -> F64:
    d = b - a
    t = np.clip(np.sum((p - a) * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - a - t[:, None] * d, axis=1)
