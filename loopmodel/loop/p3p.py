"""Vectorised P3P (Grunert's formulation) and a bank of many P3P hypotheses scored in bulk.

Grunert's three-point problem: world points ``P1, P2, P3`` (metres) seen along unit rays
``j1, j2, j3`` (camera frame) at unknown distances ``s1, s2, s3``. The law of cosines gives

    s1² + s2² − 2 s1 s2 cos γ = c²,  s1² + s3² − 2 s1 s3 cos β = b²,  s2² + s3² − 2 s2 s3 cos α = a²

(``a = |P2 − P3|``, ``α`` the angle between ``j2`` and ``j3``, and so on). With
``s2 = u s1`` and ``s3 = v s1`` the system reduces to a quartic in ``v``; every real root
gives ``s1``, then ``u`` from the ``c`` equation, a Newton polish of the three distances on
the original equations, and the pose by absolute orientation of the three point pairs.

All functions work on stacks of ``H`` problems at once (no Python loop over hypotheses):
the quartic roots are the eigenvalues of stacked companion matrices, the absolute
orientation is a stacked SVD. Degenerate triples (coincident or collinear world points,
coplanar rays, i.e. the camera centre in the plane of the points) are rejected.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import cross_rows

F64 = NDArray[np.float64]
B = NDArray[np.bool_]

#: Relative tolerance on the imaginary part of a quartic root for it to count as real.
_IMAG_TOL = 1e-6


@dataclass
class P3PSolutions:
    """Up to four poses per problem.

    ``R`` (H, 4, 3, 3), ``t`` (H, 4, 3) with ``p_in_cam = R @ p_in_world + t`` (``cam_from_world``),
    ``valid`` (H, 4).
    """

    R: F64
    t: F64
    valid: B

    @property
    def count(self) -> NDArray[np.int64]:
        """Number of valid solutions per problem (H,)."""
        return np.asarray(self.valid.sum(axis=1), dtype=np.int64)


def _quartic_roots(coeffs: F64) -> tuple[F64, B]:
    """Roots of stacked quartics ``c4 v⁴ + ...

    + c0`` (H, 5) -> (H, 4) real parts and a mask of the real ones. A vanishing ``c4`` sends one
    root to infinity (then masked).
    """
    H = coeffs.shape[0]
    c = coeffs.copy()
    scale = np.max(np.abs(c), axis=1)
    scale = np.where(scale > 0, scale, 1.0)
    c /= scale[:, None]
    lead = c[:, 0]
    tiny = np.abs(lead) < 1e-12
    lead = np.where(tiny, np.where(lead < 0, -1e-12, 1e-12), lead)
    comp = np.zeros((H, 4, 4))
    comp[:, 0, :] = -c[:, 1:] / lead[:, None]
    comp[:, 1, 0] = 1.0
    comp[:, 2, 1] = 1.0
    comp[:, 3, 2] = 1.0
    finite = np.all(np.isfinite(comp), axis=(1, 2))
    comp[~finite] = 0.0
    roots = np.linalg.eigvals(comp)
    real = np.abs(roots.imag) <= _IMAG_TOL * (1.0 + np.abs(roots.real))
    real &= finite[:, None]
    return np.asarray(roots.real), real


def _triangle_frame(T: F64) -> F64:
    """Orthonormal frames (columns) of stacked triangles (..., 3 points, 3)."""
    e1 = T[..., 1, :] - T[..., 0, :]
    n = cross_rows(e1, T[..., 2, :] - T[..., 0, :])
    e1 = e1 / np.maximum(np.linalg.norm(e1, axis=-1, keepdims=True), 1e-300)
    e3 = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    e2 = cross_rows(e3, e1)
    return np.stack([e1, e2, e3], axis=-1)


def p3p_grunert(bearings: F64, p_in_world: F64, degenerate_tol: float = 1e-6) -> P3PSolutions:
    """Solve H P3P problems at once.

    ``bearings``: (H, 3, 3) unit rays in the camera frame (rows ``j1, j2, j3``);
    ``p_in_world``: (H, 3, 3) the matching world points (rows ``P1, P2, P3``, metres).
    Returns every real, physically valid solution (distances > 0), at most 4 per problem.
    ``degenerate_tol`` bounds the normalised triangle area and the normalised triple
    product of the rays below which a problem is rejected (no solution).
    """
    j = np.asarray(bearings, dtype=float).reshape(-1, 3, 3)
    j = j / np.linalg.norm(j, axis=2, keepdims=True)
    P = np.asarray(p_in_world, dtype=float).reshape(-1, 3, 3)

    a2 = np.sum((P[:, 1] - P[:, 2]) ** 2, axis=1)
    b2 = np.sum((P[:, 0] - P[:, 2]) ** 2, axis=1)
    c2 = np.sum((P[:, 0] - P[:, 1]) ** 2, axis=1)
    ca = np.sum(j[:, 1] * j[:, 2], axis=1)
    cb = np.sum(j[:, 0] * j[:, 2], axis=1)
    cg = np.sum(j[:, 0] * j[:, 1], axis=1)

    # Degeneracies: coincident/collinear points, coplanar rays (camera in the points' plane).
    side2 = np.maximum(np.maximum(a2, b2), c2)
    area2 = np.sum(cross_rows(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]) ** 2, axis=1)
    ok = (side2 > 0) & (b2 > 1e-12 * np.maximum(side2, 1e-300))
    ok &= area2 > (degenerate_tol * np.maximum(side2, 1e-300)) ** 2
    triple = np.abs(np.einsum("hi,hi->h", j[:, 0], cross_rows(j[:, 1], j[:, 2])))
    ok &= triple > degenerate_tol
    ok &= np.all(np.isfinite(j), axis=(1, 2)) & np.all(np.isfinite(P), axis=(1, 2))

    b2s = np.where(ok, b2, 1.0)
    amc = (a2 - c2) / b2s
    apc = (a2 + c2) / b2s
    A4 = (amc - 1.0) ** 2 - 4.0 * c2 / b2s * ca**2
    A3 = 4.0 * (amc * (1.0 - amc) * cb - (1.0 - apc) * ca * cg + 2.0 * c2 / b2s * ca**2 * cb)
    A2 = 2.0 * (
        amc**2
        - 1.0
        + 2.0 * amc**2 * cb**2
        + 2.0 * (b2 - c2) / b2s * ca**2
        - 4.0 * apc * ca * cb * cg
        + 2.0 * (b2 - a2) / b2s * cg**2
    )
    A1 = 4.0 * (-amc * (1.0 + amc) * cb + 2.0 * a2 / b2s * cg**2 * cb - (1.0 - apc) * ca * cg)
    A0 = (1.0 + amc) ** 2 - 4.0 * a2 / b2s * cg**2
    coeffs = np.stack([A4, A3, A2, A1, A0], axis=1)
    coeffs[~ok] = np.array([1.0, 0.0, 0.0, 0.0, 1.0])  # placeholder, masked below
    v, real = _quartic_roots(coeffs)
    real &= ok[:, None]

    # s1 from the b equation, u from the c equation (two branches; keep the one fitting a).
    cb_ = cb[:, None]
    cg_ = cg[:, None]
    ca_ = ca[:, None]
    den = 1.0 + v**2 - 2.0 * v * cb_
    valid = real & (v > 0) & (den > 1e-12)
    s1sq = np.where(valid, b2[:, None] / np.where(den > 1e-12, den, 1.0), 1.0)
    s1 = np.sqrt(np.maximum(s1sq, 0.0))
    disc = cg_**2 - 1.0 + c2[:, None] / s1sq
    valid &= disc > -1e-6
    root = np.sqrt(np.maximum(disc, 0.0))
    best_u = np.zeros_like(v)
    best_res = np.full_like(v, np.inf)
    for sign in (1.0, -1.0):
        u = cg_ + sign * root
        res = np.abs(s1sq * (u**2 + v**2 - 2.0 * u * v * ca_) - a2[:, None])
        better = (u > 0) & (res < best_res)
        best_u = np.where(better, u, best_u)
        best_res = np.where(better, res, best_res)
    valid &= np.isfinite(best_res)
    valid &= best_res <= 1e-2 * np.maximum(side2, 1e-300)[:, None] + 1e-9
    s = np.stack([s1, best_u * s1, v * s1], axis=-1)  # (H, 4, 3)
    s = np.where(valid[..., None], s, 1.0)

    # Newton polish of the three distances on the law-of-cosines equations.
    cosines = np.stack([cg, cb, ca], axis=1)[:, None, :]  # (H, 1, 3) for pairs 12, 13, 23
    rhs = np.stack([c2, b2, a2], axis=1)[:, None, :]
    for _ in range(3):
        s1_, s2_, s3_ = s[..., 0], s[..., 1], s[..., 2]
        f = (
            np.stack(
                [
                    s1_**2 + s2_**2 - 2 * s1_ * s2_ * cosines[..., 0],
                    s1_**2 + s3_**2 - 2 * s1_ * s3_ * cosines[..., 1],
                    s2_**2 + s3_**2 - 2 * s2_ * s3_ * cosines[..., 2],
                ],
                axis=-1,
            )
            - rhs
        )
        J = np.zeros(s.shape + (3,))
        J[..., 0, 0] = 2 * s1_ - 2 * s2_ * cosines[..., 0]
        J[..., 0, 1] = 2 * s2_ - 2 * s1_ * cosines[..., 0]
        J[..., 1, 0] = 2 * s1_ - 2 * s3_ * cosines[..., 1]
        J[..., 1, 2] = 2 * s3_ - 2 * s1_ * cosines[..., 1]
        J[..., 2, 1] = 2 * s2_ - 2 * s3_ * cosines[..., 2]
        J[..., 2, 2] = 2 * s3_ - 2 * s2_ * cosines[..., 2]
        r0, r1, r2 = J[..., 0, :], J[..., 1, :], J[..., 2, :]
        c12, c20, c01 = cross_rows(r1, r2), cross_rows(r2, r0), cross_rows(r0, r1)
        det = np.sum(r0 * c12, axis=-1)
        good = valid & (np.abs(det) > 1e-14 * np.maximum(side2, 1e-300)[:, None] ** 1.5)
        det = np.where(good, det, 1.0)
        step = (c12 * f[..., 0:1] + c20 * f[..., 1:2] + c01 * f[..., 2:3]) / det[..., None]
        step = np.where(good[..., None], step, 0.0)
        s = s - step
    valid &= np.all(s > 0, axis=-1) & np.all(np.isfinite(s), axis=-1)

    # Pose from the two triangles' orthonormal frames (exact: the distances fit after Newton).
    X = s[..., :, None] * j[:, None, :, :]  # (H, 4, 3 points, 3) camera-frame points
    Pw = np.broadcast_to(P[:, None], X.shape)
    Fx = _triangle_frame(X)
    Fp = _triangle_frame(Pw)
    R = Fx @ np.swapaxes(Fp, -1, -2)
    t = X[..., 0, :] - np.einsum("hkij,hkj->hki", R, Pw[..., 0, :])
    # Check the three correspondences are reproduced (rejects spurious roots).
    Xr = np.einsum("hkij,hknj->hkni", R, Pw) + t[..., None, :]
    err = np.max(np.linalg.norm(Xr - X, axis=-1), axis=-1)
    valid &= err <= 1e-5 * np.sqrt(np.maximum(side2, 1e-300))[:, None] + 1e-9
    R = np.where(valid[..., None, None], R, np.nan)
    t = np.where(valid[..., None], t, np.nan)
    return P3PSolutions(R=R, t=t, valid=valid)
